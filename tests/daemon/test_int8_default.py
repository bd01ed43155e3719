"""The int8 sibling of a model is served on the CPU by the held-out loss recorded in its own
metadata (`daemon.frames.int8`): within 0.5 dB of its float model, int8; more, none or for another
float file, the float model; status says which and why."""

from __future__ import annotations

import contextlib
import json
import shutil
import time
from pathlib import Path

import onnx
import pytest

from nhfd.benchmarks.pipeline import _Host, _load
from nhfd.config import Config, _overlay
from nhfd.models.data import HoloData
from nhfd.models.export import OnnxModel
from nhfd.models.metadata import METADATA_KEY
from nhfd.models.quantise import HELDOUT_KEY, int8_sibling, quantise_int8, record_heldout_loss
from nhfd.pipeline.worker import choose_variant

from .test_frames import FRONT_VIEW, small_config


def with_int8(config: Config, mode: str, **frames) -> Config:
    """`config` with daemon.frames.int8 = `mode` and the other `[daemon.frames]` keys given."""
    return Config.model_validate(_overlay(config.model_dump(),
                                          {"daemon": {"frames": {"int8": mode, **frames}}}))


def show_a_frame(host, link, timeout_s: float = 30.0) -> None:
    """Submit the front view and step the link until the panel shows it, with no error."""
    seq = host.views.submit(FRONT_VIEW)
    deadline = time.monotonic() + timeout_s
    while link.shown_seq < seq:
        link.step()
        assert not host.errors and time.monotonic() < deadline, host.errors
        time.sleep(0.002)


def record(loss_db: float, float_path: Path) -> dict:
    from nhfd.dataset.build import sha256_file

    return {HELDOUT_KEY: {"loss_vs_float_db": loss_db, "float_sha256": sha256_file(float_path),
                          "views": 4}}


def test_the_choice_follows_the_recorded_loss_and_the_setting(tmp_path):
    f = tmp_path / "model.onnx"
    f.write_bytes(b"float model bytes")
    auto = small_config()
    assert int8_sibling(f) == tmp_path / "model-int8.onnx"
    variant, why = choose_variant(str(f), auto.daemon, record(0.3, f))
    assert variant == "int8" and "loses 0.30 dB" in why and "within 0.5 dB" in why
    variant, why = choose_variant(str(f), auto.daemon, record(0.7, f))
    assert variant == "float" and "loses 0.70 dB of held-out PSNR, more than 0.5 dB" in why
    variant, why = choose_variant(str(f), auto.daemon, {})
    assert variant == "float" and "records no held-out loss" in why
    variant, why = choose_variant(str(f), auto.daemon, None)
    assert variant == "float" and "no int8 model beside it (model-int8.onnx)" in why
    other = tmp_path / "other.onnx"
    other.write_bytes(b"another float model")
    variant, why = choose_variant(str(f), auto.daemon, record(0.1, other))
    assert variant == "float" and "measured against another float model" in why
    # The setting decides over the record.
    assert choose_variant(str(f), with_int8(auto, "never").daemon, record(0.1, f))[0] == "float"
    assert choose_variant(str(f), with_int8(auto, "always").daemon, record(0.7, f)) == (
        "int8", 'daemon.frames.int8 = "always" (model-int8.onnx)')
    cuda = with_int8(auto, "auto", onnx_providers=["CUDAExecutionProvider",
                                                   "CPUExecutionProvider"])
    variant, why = choose_variant(str(f), cuda.daemon, record(0.1, f))
    assert variant == "float" and "only on the CPU path" in why


@pytest.fixture(scope="module")
def pair(tiny, tmp_path_factory) -> dict[str, Path]:
    """The tiny model and a real static int8 quantisation of it, side by side."""
    root = tmp_path_factory.mktemp("int8")
    f = root / "model.onnx"
    shutil.copyfile(tiny["model"], f)
    meta = OnnxModel(f).metadata
    quantise_int8(f, int8_sibling(f), HoloData(tiny["model"].parent / "data"),
                  int(meta["input_multiple"]), "rgb", n_calib=1)
    return {"float": f, "int8": int8_sibling(f), "scene": tiny["scene"]}


def test_the_record_travels_in_the_int8_files_metadata(pair):
    rec = record_heldout_loss(pair["int8"], pair["float"], float_psnr_db=30.0,
                              int8_psnr_db=29.7, views=4)
    meta = OnnxModel(pair["int8"]).metadata
    assert meta[HELDOUT_KEY] == rec
    assert rec["loss_vs_float_db"] == pytest.approx(0.3) and rec["max_loss_db"] == 0.5
    # The rest of the nhfd metadata is the float model's, untouched.
    props = {p.key: p.value for p in onnx.load(str(pair["float"])).metadata_props}
    assert {k: v for k, v in meta.items() if k != HELDOUT_KEY} == json.loads(props[METADATA_KEY])


@contextlib.contextmanager
def served(pair, int8_psnr_db: float, **frames):
    """A frame link serving the pair's float model (the int8 one beside it records a held-out
    PSNR of `int8_psnr_db` against 30 dB), with `frames` as `[daemon.frames]` keys; closed
    after."""
    host = _Host(small_config(daemon={"frames": {"cache_frames": 0, **frames}}))
    link = host.frame_link()
    try:
        record_heldout_loss(pair["int8"], pair["float"], float_psnr_db=30.0,
                            int8_psnr_db=int8_psnr_db, views=4)
        _load(link, pair["scene"], pair["float"])
        yield host, link
    finally:
        link.close()


def test_the_worker_serves_int8_within_half_a_db_and_float_beyond(pair):
    with served(pair, 29.7) as (host, link):
        info = link.model
        assert info.variant == "int8" and info.served == str(pair["int8"].resolve())
        assert info.inference == "onnxruntime"  # "auto" on the CPU
        assert "model-int8.onnx loses 0.30 dB" in info.variant_reason
        status = link.status()
        assert status["model_variant"] == "int8"
        show_a_frame(host, link)

        record_heldout_loss(pair["int8"], pair["float"], float_psnr_db=30.0, int8_psnr_db=29.3,
                            views=4)
        _load(link, pair["scene"], pair["float"])
        status = link.status()
        assert status["model_variant"] == "float"
        assert "loses 0.70 dB of held-out PSNR, more than 0.5 dB" in status["model_variant_reason"]
        assert link.model.served == str(pair["float"].resolve())


def test_torch_inference_serves_the_float_model_and_says_so(pair):
    """daemon.frames.inference = "torch": int8 arithmetic is onnxruntime's, so the float model
    serves (frames and all), and the model's status names what runs the network and why."""
    with served(pair, 29.9, inference="torch") as (host, link):
        info = link.model
        assert (info.inference, info.providers) == ("torch", ("torch",))
        assert info.inference_reason == ('daemon.frames.inference = "torch": the network in '
                                         "torch on cpu")
        assert info.variant == "float" and info.served == str(pair["float"].resolve())
        assert "daemon.frames.inference = 'torch'" in info.variant_reason
        show_a_frame(host, link)
