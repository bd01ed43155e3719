"""`nhfd.model_info.ModelInfo` (issue 33): the model's metadata parsed once at load, read by name
on the frame path; a file whose metadata is incomplete is refused naming the missing field."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import pytest

from nhfd.model_info import DepthMapping, ModelInfo, PoseEnvelope
from nhfd.models.export import OnnxModel, read_model_metadata
from nhfd.models.metadata import InvalidMetadata, parse_model_info
from tests.models.test_hostile_models import hostile_copy

SHIPPED = Path(__file__).resolve().parents[1] / "models" / "nhf-donut-512.onnx"
INFO = ModelInfo(inputs="rgb", wavelengths_m=(6.6e-7, 5.2e-7, 4.5e-7), pitch_m=8e-6,
                 aperture_shape="square", cutoff_per_px=(0.25,) * 3, z0_m=6e-3,
                 volume_m=(-3e-3, 3e-3), amplitude_scale=2.0, train_size_hw=(288, 512),
                 input_multiple=16, fx_px=700.0)


@pytest.fixture(scope="module")
def shipped() -> OnnxModel:
    if not SHIPPED.exists():
        pytest.skip(f"no shipped model at {SHIPPED}")
    return OnnxModel(SHIPPED)


def test_the_shipped_models_info_holds_its_metadatas_values(shipped):
    meta, info = shipped.metadata, shipped.info
    assert info.inputs == "rgbd" and info.channels == shipped.channels == 4
    assert list(info.wavelengths_m) == meta["wavelengths_m"] and info.colours == 3
    assert (info.pitch_m, info.z0_m, info.amplitude_scale) == (
        meta["pitch_m"], meta["z0_m"], meta["amplitude_scale"])
    assert (info.aperture_shape, list(info.cutoff_per_px)) == (
        meta["aperture_shape"], meta["cutoff_per_px"])
    assert list(info.volume_m) == meta["volume_m"]
    assert list(info.train_size_hw) == meta["train_size_hw"]
    assert info.input_multiple == meta["input_multiple"] == shipped.multiple
    assert info.focal_px() == (meta["fx"], meta["fy"])
    assert (info.mapping.a_m, info.mapping.b_m) == (meta["mapping"]["a_m"],
                                                    meta["mapping"]["b_m"])
    env = meta["pose_envelope"]
    assert info.pose_envelope.to_json() == env  # every range, as the file records it
    assert info.checked_sizes_hw() == ([tuple(e["hw"]) for e in meta["checked_sizes"]], True)
    status = info.status_json()
    assert status["fx"] == meta["fx"] and status["pose_envelope"] == env
    assert status["mapping"] == {k: meta["mapping"][k] for k in ("a_m", "b_m", "d_near",
                                                                  "d_far")}


# The fields the frame path cannot do without: each deleted, the file is refused by name.
REQUIRED = ["wavelengths_m", "pitch_m", "aperture_shape", "cutoff_per_px", "z0_m", "volume_m",
            "amplitude_scale", "train_size_hw", "input_multiple", "mapping", "mapping.a_m",
            "format_version"]


@pytest.mark.parametrize("field", REQUIRED)
def test_a_file_missing_a_field_is_refused_naming_it(shipped, tmp_path, field):
    def drop(meta: dict) -> None:
        *parents, last = field.split(".")
        for key in parents:
            meta = meta[key]
        del meta[last]

    path = hostile_copy(SHIPPED, tmp_path / "m.onnx", meta=drop)
    with pytest.raises(InvalidMetadata, match=rf"^{re.escape(str(path))}: metadata "
                                              rf"{re.escape(field)} is missing: expected "):
        OnnxModel(path)
    with pytest.raises(InvalidMetadata, match=rf"metadata {re.escape(field)} is missing"):
        read_model_metadata(path)  # the worker's reader, before any session


def test_a_file_with_no_focal_length_is_refused_and_fov_alone_serves(shipped, tmp_path):
    def no_fx(meta: dict) -> None:
        del meta["fx"], meta["fy"]

    def no_camera(meta: dict) -> None:
        no_fx(meta)
        del meta["fov_x_deg"]

    # Before: a file with neither was drawn at a 40 degree field of view it never said.
    path = hostile_copy(SHIPPED, tmp_path / "none.onnx", meta=no_camera)
    with pytest.raises(InvalidMetadata, match=r"metadata fx is missing: expected the render's "
                                              r"focal length"):
        OnnxModel(path)
    older = OnnxModel(hostile_copy(SHIPPED, tmp_path / "fov.onnx", meta=no_fx)).info
    fov, width = older.fov_x_deg, older.train_size_hw[1]
    fx = 0.5 * width / math.tan(math.radians(fov) / 2)  # the render camera's formula, as before
    assert older.focal_px() == (fx, fx) and fov == 40.0


@pytest.mark.parametrize(("change", "message"), [
    ({"pitch_m": 0.0}, r"model info pitch_m = 0\.0: expected a finite number in \(0, 0\.001\) "
                       r"\(m\)"),
    ({"wavelengths_m": (6.6e-7, 5.2e-7)}, r"model info wavelengths_m = .*: expected 3 numbers"),
    ({"wavelengths_m": (6.6e-7, 5.2e-7, 4.5e-3)}, r"model info wavelengths_m\[2\] = 0\.0045"),
    ({"aperture_shape": "hexagon"}, r"aperture_shape = 'hexagon': expected one of square"),
    ({"volume_m": (-7e-3, 3e-3)}, r"volume_m = .*z0_m \+ near > 0"),
    ({"amplitude_scale": math.inf}, r"amplitude_scale = inf"),
    ({"train_size_hw": (0, 512)}, r"train_size_hw = \[0, 512\]: expected \[height, width\]"),
    ({"input_multiple": 12}, r"input_multiple = 12: expected a power of two"),
    ({"fx_px": None}, r"fx_px = None and fov_x_deg = None"),
    ({"inputs": "rgbd"}, r"mapping = None: an rgbd model needs the scene's depth mapping"),
    ({"inputs": "rgba"}, r"inputs = 'rgba': expected one of rgb, rgbd"),
])
def test_the_constructor_refuses_what_the_frame_path_cannot_use(change, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(INFO, **change)


def test_the_parts_check_their_own_ranges():
    with pytest.raises(ValueError, match=r"mapping\.b_m = nan"):
        DepthMapping(0.0, math.nan)
    with pytest.raises(ValueError, match=r"pose_envelope\.distance = \[0\.8, 0\.6\]: expected "
                                         r"\[low, high\] with low <= high"):
        PoseEnvelope(distance=(0.8, 0.6))
    with pytest.raises(ValueError, match=r"position_min and position_max go together"):
        PoseEnvelope(position_min=(0.0, 0.0, 0.0))
    assert PoseEnvelope(azimuth_deg=[-20, 20]).azimuth_deg == (-20, 20)  # a tuple: frozen


def test_an_older_export_counts_its_padded_training_window_as_checked():
    assert INFO.checked_sizes_hw() == ([(288, 512)], False)
    odd = dataclasses.replace(INFO, train_size_hw=(100, 200))
    assert odd.checked_sizes_hw() == ([(112, 208)], False)  # padded to the multiple, 16


def test_parse_refuses_a_value_only_the_constructor_checks(shipped):
    # validate_metadata passes a partial mapping of an rgb model; its info then has none, and a
    # value the constructor refuses is the file's InvalidMetadata, naming the file.
    meta = dict(shipped.metadata, mapping={"a_m": 0.1}, inputs={"rgb": "..."})
    assert parse_model_info(meta, "m.onnx", "rgb").mapping is None
    with pytest.raises(InvalidMetadata, match=r"^m\.onnx: model info mapping = None"):
        parse_model_info(meta, "m.onnx", "rgbd")
