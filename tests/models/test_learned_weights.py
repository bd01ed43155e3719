"""The learned bench's weights file: safetensors only, every hostile or foreign file refused with
a ValueError naming the file and the problem, and a good one read back exactly."""

from __future__ import annotations

import json
import pickle
import struct
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from nhfd.models.learned_bench import (
    MAX_HEADER_BYTES,
    MAX_TENSOR_BYTES,
    LearnedBench,
    LearnedOptics,
    LearnedWeightsError,
    load_learned,
    save_learned,
)

OPTICS = LearnedOptics((638e-9, 520e-9, 450e-9), 8e-6, (128, 128))


def _trained() -> LearnedBench:
    """A model whose weights are not the identity's (seeded), so a read-back means something."""
    torch.manual_seed(0)
    m = LearnedBench(OPTICS)
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.01 * torch.randn_like(p))
    return m


@pytest.fixture
def good(tmp_path: Path) -> tuple[Path, str, LearnedBench]:
    m = _trained()
    path = tmp_path / "learned.safetensors"
    return path, save_learned(m, path, {"held_out_psnr_db": [1.0, 2.0, 3.0]}), m


def _raw(header: dict, body: bytes) -> bytes:
    h = json.dumps(header).encode()
    return struct.pack("<Q", len(h)) + h + body


def _header_of(path: Path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8 : 8 + n]), data[8 + n :]


def test_a_saved_model_loads_back_exactly(good) -> None:
    path, sha, m = good
    back = load_learned(path, OPTICS, sha256=sha)
    for k, v in m.state_dict().items():
        assert torch.equal(back.state_dict()[k], v), k
    assert not any(p.requires_grad for p in back.parameters())


def test_a_fresh_model_is_the_identity() -> None:
    m = LearnedBench(OPTICS)
    phase = torch.rand(2, 20, 24) * 6
    u = m.slm_field(phase, 1, (10, 20, 20, 24))
    assert torch.allclose(u, torch.polar(torch.ones_like(phase), phase), atol=1e-6)
    img = torch.rand(2, 3, 16, 16)
    assert torch.equal(m.intensity(img, 0), img)


@pytest.mark.parametrize("cut", [4, 40, -3])
def test_a_truncated_file_is_refused(good, cut: int) -> None:
    path = good[0]
    data = path.read_bytes()
    path.write_bytes(data[:cut])
    with pytest.raises(LearnedWeightsError, match=rf"{path}: .*truncated"):
        load_learned(path, OPTICS)


def test_a_pickle_named_safetensors_is_refused_unopened(good, tmp_path: Path) -> None:
    path = tmp_path / "evil.safetensors"
    path.write_bytes(pickle.dumps(good[2].state_dict(), protocol=4))
    with pytest.raises(LearnedWeightsError, match=rf"{path}: a pickle, not safetensors"):
        load_learned(path, OPTICS)
    zipped = tmp_path / "zipped.safetensors"
    torch.save(good[2].state_dict(), zipped)
    with pytest.raises(LearnedWeightsError, match=rf"{zipped}: a zip archive"):
        load_learned(zipped, OPTICS)


def test_a_huge_declared_tensor_or_header_is_refused(good) -> None:
    path = good[0]
    header, body = _header_of(path)
    name = "unmodulated"
    header[name]["shape"] = [1 << 20, 3]
    header[name]["data_offsets"] = [0, 4 * 3 << 20]
    path.write_bytes(_raw(header, body))
    with pytest.raises(LearnedWeightsError, match=rf"{path}: tensor {name}: declares "
                                                  rf"{4 * 3 << 20} bytes .*more than the cap"):
        load_learned(path, OPTICS)
    assert 4 * 3 << 20 > MAX_TENSOR_BYTES
    # Within the cap but beyond the file's end.
    header, _ = _header_of(path)
    header[name]["shape"] = [3, 2000]
    header[name]["data_offsets"] = [0, 4 * 6000]
    path.write_bytes(_raw(header, body))
    with pytest.raises(LearnedWeightsError, match=rf"{path}: tensor {name}: .*larger than"):
        load_learned(path, OPTICS)
    path.write_bytes(struct.pack("<Q", MAX_HEADER_BYTES + 1) + b"{" + b" " * 100)
    with pytest.raises(LearnedWeightsError, match=rf"{path}: the header declares "
                                                  rf"{MAX_HEADER_BYTES + 1} bytes"):
        load_learned(path, OPTICS)


def test_wrong_shapes_names_and_dtypes_are_refused(good, tmp_path: Path) -> None:
    m = good[2]
    bad = tmp_path / "shape.safetensors"
    state = {k: v.clone() for k, v in m.state_dict().items()}
    state["unmodulated"] = torch.zeros(3, 3)
    save_file(state, bad, metadata=m.metadata())
    with pytest.raises(LearnedWeightsError, match=rf"{bad}: tensor unmodulated: shape \[3, 3\], "
                                                  r"expected \[3, 2\]"):
        load_learned(bad, OPTICS)
    state = {k: v.clone() for k, v in m.state_dict().items() if k != "unmodulated"}
    state["extra"] = torch.zeros(1)
    save_file(state, bad, metadata=m.metadata())
    with pytest.raises(LearnedWeightsError, match=r"missing \['unmodulated'\], unexpected "
                                                  r"\['extra'\]"):
        load_learned(bad, OPTICS)
    state = {k: v.to(torch.float64) for k, v in m.state_dict().items()}
    save_file(state, bad, metadata=m.metadata())
    with pytest.raises(LearnedWeightsError, match=r"dtype 'F64', expected 'F32'"):
        load_learned(bad, OPTICS)


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused(good, tmp_path: Path, value: float) -> None:
    m = good[2]
    state = {k: v.clone() for k, v in m.state_dict().items()}
    state["target.1.0.weight"][0, 0, 1, 1] = value
    bad = tmp_path / "nan.safetensors"
    save_file(state, bad, metadata=m.metadata())
    with pytest.raises(LearnedWeightsError, match=rf"{bad}: tensor target.1.0.weight: 1 NaN "
                                                  r"or infinite"):
        load_learned(bad, OPTICS)
    with pytest.raises(ValueError, match="not finite, not written"):
        m2 = LearnedBench(OPTICS)
        with torch.no_grad():
            m2.unmodulated[0, 0] = value
        save_learned(m2, tmp_path / "never.safetensors")
    assert not (tmp_path / "never.safetensors").exists()


def test_weights_for_other_optics_are_refused(good) -> None:
    path = good[0]
    other = [LearnedOptics((1064e-9, 520e-9, 450e-9), 8e-6, (128, 128)),
             LearnedOptics(OPTICS.wavelengths_m, 3.74e-6, (128, 128)),
             LearnedOptics(OPTICS.wavelengths_m, 8e-6, (1080, 1920))]
    for optics, what in zip(other, ("wavelengths_m\\[0\\]", "pitch_m", "panel_hw"), strict=True):
        with pytest.raises(LearnedWeightsError, match=rf"{path}: learned for other optics: "
                                                      rf"{what}"):
            load_learned(path, optics)


def test_another_file_than_the_calibration_records_is_refused(good) -> None:
    path, sha, _ = good
    with pytest.raises(LearnedWeightsError, match=rf"{path}: SHA-256 {sha[:12]}.*another file"):
        load_learned(path, OPTICS, sha256="0" * 64)


def test_a_missing_file_and_a_foreign_format_are_refused(good, tmp_path: Path) -> None:
    with pytest.raises(LearnedWeightsError, match=r"nope\.safetensors: not found"):
        load_learned(tmp_path / "nope.safetensors", OPTICS)
    path = good[0]
    header, body = _header_of(path)
    header["__metadata__"]["format"] = "something-else"
    path.write_bytes(_raw(header, body))
    with pytest.raises(LearnedWeightsError, match=r"format 'something-else'"):
        load_learned(path, OPTICS)
