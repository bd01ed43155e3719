"""The learned bench in the calibration and in `BenchForward`: old calibration files load and
fingerprint as before, the reference round-trips, the learned model starts as the parametric
one and changes it only through its parts, and a refused weights file leaves the parametric
model in use with the file and the problem named."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path

import pytest
import torch

from nhfd.calibration import Calibration, fingerprint, parametric_fingerprint
from nhfd.config import RefineSettings
from nhfd.drivers.simcamera import TrueBench
from nhfd.models.learned_bench import LearnedBench, LearnedOptics, learned_of, save_learned
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.refine import BenchForward
from nhfd.pipeline.settings import FrameSettings, with_calibration
from tests.calib.twin_stack import truth_calibration

PANEL_HW = (128, 128)
PLANES_M = (-0.4e-3, 0.0, 0.4e-3)


@pytest.fixture(scope="module")
def cal(tmp_path_factory: pytest.TempPathFactory) -> Calibration:
    """A calibration as read from its file (its creation time set, as `nhfd calib learn`
    finds one)."""
    path = tmp_path_factory.mktemp("cal") / "calibration.toml"
    return Calibration.load(truth_calibration(TrueBench()).save(path))


def _encoder(cal: Calibration) -> Encoder:
    base = FrameSettings(panel_hw=PANEL_HW, window_hw=(48, 48), pitch_m=cal.pitch_m,
                         wavelengths_m=cal.wavelengths_m, z0_m=2e-3, aperture_shape="square",
                         cutoff_per_px=(0.25,) * 3, amplitude_scale=1.0, zero_below=1e-3,
                         phase_stroke_rad=(2 * math.pi,) * 3)
    return Encoder(with_calibration(base, cal))


def _optics(cal: Calibration) -> LearnedOptics:
    return LearnedOptics(cal.wavelengths_m, cal.pitch_m, PANEL_HW)


def test_a_calibration_without_a_learned_bench_is_as_before(cal, tmp_path: Path) -> None:
    assert "[learned]" not in cal.to_toml()
    back = Calibration.load(cal.save(tmp_path / "calibration.toml"))
    assert back.learned_path() is None
    for c in (cal, back):
        # The fingerprint's definition before calibrations could reference a learned bench.
        values = dataclasses.asdict(c)
        for k in ("source", "learned_file", "learned_sha256"):
            values.pop(k)
        old = hashlib.sha256(json.dumps(values, sort_keys=True, default=str).encode())
        assert fingerprint(c) == old.hexdigest() == parametric_fingerprint(c)


def test_the_learned_reference_round_trips_and_counts_by_its_hash(cal, tmp_path: Path) -> None:
    with_learned = dataclasses.replace(cal, learned_file="learned.safetensors",
                                       learned_sha256="ab" * 32)
    back = Calibration.load(with_learned.save(tmp_path / "calibration.toml"))
    assert (back.learned_file, back.learned_sha256) == ("learned.safetensors", "ab" * 32)
    assert back.learned_path() == tmp_path / "learned.safetensors"
    assert fingerprint(back) != fingerprint(cal)
    assert parametric_fingerprint(back) == fingerprint(cal)
    renamed = dataclasses.replace(with_learned, learned_file="other.safetensors")
    assert fingerprint(renamed) == fingerprint(with_learned)  # its bytes count, not its name


@pytest.mark.parametrize("name,sha", [("../up.safetensors", "ab" * 32), ("w.pt", "ab" * 32),
                                      ("learned.safetensors", "xyz"), ("", "ab" * 32)])
def test_a_bad_learned_reference_is_refused(cal, name: str, sha: str) -> None:
    with pytest.raises(ValueError, match=r"learned\.(file|sha256) = "):
        dataclasses.replace(cal, learned_file=name, learned_sha256=sha)


def test_the_setting_takes_only_the_two_models() -> None:
    assert RefineSettings().bench_model == "learned"
    with pytest.raises(ValueError, match="bench_model"):
        RefineSettings(bench_model="neural")


def test_a_fresh_learned_bench_is_the_parametric_model_and_its_parts_act(cal) -> None:
    enc = _encoder(cal)
    r = enc.region
    torch.manual_seed(1)
    phase = 2 * math.pi * torch.rand(2, 3, r.height, r.width)
    parametric = BenchForward(enc, PLANES_M)(phase)
    learned = LearnedBench(_optics(cal))
    same = BenchForward(enc, PLANES_M, learned)(phase)
    assert same.shape == parametric.shape == (2, len(PLANES_M), 3, 48, 48)
    assert torch.allclose(same, parametric, rtol=1e-5, atol=1e-6 * float(parametric.max()))
    with torch.no_grad():
        learned.unmodulated[1, 0] = 0.2  # unmodulated light in green only
    lit = BenchForward(enc, PLANES_M, learned)(phase)
    for c in (0, 2):
        assert torch.allclose(lit[:, :, c], parametric[:, :, c], rtol=1e-5,
                              atol=1e-6 * float(parametric.max()))
    assert (lit[:, :, 1] - parametric[:, :, 1]).abs().mean() > 0.05 * parametric[:, :, 1].mean()


def test_a_refused_weights_file_leaves_the_parametric_model(cal, tmp_path: Path) -> None:
    path = tmp_path / "learned.safetensors"
    sha = save_learned(LearnedBench(_optics(cal)), path,
                       {"parametric_sha256": parametric_fingerprint(cal)})
    ref = dataclasses.replace(cal, learned_file=path.name, learned_sha256=sha)
    ref = Calibration.load(ref.save(tmp_path / "calibration.toml"))
    model, why = learned_of(ref, _optics(cal))
    assert model is not None and why is None
    assert learned_of(cal, _optics(cal)) == (None, None)  # none referenced
    path.write_bytes(path.read_bytes()[:-8])  # the file changed after the calibration
    model, why = learned_of(ref, _optics(cal))
    assert model is None
    assert why is not None and str(path) in why and "SHA-256" in why
    assert why.endswith("the parametric bench model stays in use")
    # Learned on top of another parametric fit.
    other = dataclasses.replace(cal, stage_scale=cal.stage_scale * 1.01)
    sha = save_learned(LearnedBench(_optics(cal)), path,
                       {"parametric_sha256": parametric_fingerprint(other)})
    ref = dataclasses.replace(ref, learned_sha256=sha)
    model, why = learned_of(ref, _optics(cal))
    assert model is None and "learned on top of another calibration" in str(why)
