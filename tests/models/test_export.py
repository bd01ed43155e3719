"""ONNX export: agrees with torch, carries its optics, refuses mismatches and bad files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nhfd.config import Config
from nhfd.models.export import OnnxModel, export_onnx, load_model
from nhfd.models.metadata import ModelMismatch, NotAModel, expected_from_config
from nhfd.models.net import predict
from nhfd.models.train import load_run


@pytest.fixture(scope="module")
def exported(tiny_run, tmp_path_factory):
    path = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    return export_onnx(tiny_run, path)


def test_onnx_agrees_with_torch_at_other_sizes(exported, tiny_run):
    assert exported.max_abs_diff < 1e-4
    assert len(exported.checked_sizes) >= 2
    net, _ = load_run(tiny_run)
    model = OnnxModel(exported.path)
    rgb = torch.rand(3, 37, 53)  # not a multiple of the stride: padded outside the graph
    amp, phase = model(rgb.numpy())
    with torch.no_grad():
        ta, tp = predict(net, rgb)
    assert amp.shape == phase.shape == (3, 37, 53)
    assert np.abs(amp - ta.numpy()).max() < 1e-4 and np.abs(phase - tp.numpy()).max() < 1e-4


def test_metadata_records_the_optics_and_the_dataset(exported, tiny_data):
    meta = OnnxModel(exported.path).metadata
    manifest = json.loads((tiny_data / "manifest.json").read_text())
    s = manifest["settings"]
    assert meta["wavelengths_m"] == pytest.approx(s["wavelengths_m"])
    assert meta["pitch_m"] == s["pitch_m"] and meta["z0_m"] == s["z0_m"]
    assert meta["volume_m"] == pytest.approx(s["volume_m"])
    assert meta["mapping"]["a_m"] == manifest["mapping"]["a_m"]
    assert meta["amplitude_scale"] == manifest["amplitude_scale"]["value"]
    assert meta["fx"] > 0 and meta["fy"] > 0 and meta["train_size_hw"] == [64, 64]
    assert meta["scene_sha256"] == manifest["scene"]["sha256"]
    assert meta["dataset_manifest_key"] == manifest["key"]
    assert len(meta["dataset_manifest_sha256"]) == 64
    assert meta["input_multiple"] == 4 and meta["opset"] >= 18
    assert meta["colour_space"].startswith("sRGB") and meta["nhfd_version"]
    assert meta["pose_envelope"] and meta["profile"]


def test_a_model_for_other_optics_is_refused_naming_what_differs(exported):
    config = Config()  # default optics: the synthetic dataset uses the same
    load_model(exported.path, config)
    other = Config.model_validate({"optics": {"z0_mm": 7.0}, "slm": {"pitch_um": 6.4}})
    with pytest.raises(ModelMismatch, match=r"z0_m: model 0\.006, configured 0\.007") as err:
        load_model(exported.path, other)
    assert "pitch_m" in str(err.value) and "wavelengths_m" not in str(err.value)
    expected = expected_from_config(config.optics, config.slm) | {"aperture_shape": "circle"}
    with pytest.raises(ModelMismatch, match="aperture_shape"):
        OnnxModel(exported.path, expected=expected)


def test_corrupt_and_foreign_files_get_clear_errors(exported, tmp_path):
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(exported.path.read_bytes()[:500])
    with pytest.raises(NotAModel, match=r"corrupt\.onnx: not a readable ONNX model"):
        OnnxModel(corrupt)
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"\x00\x01 not onnx at all" * 10)
    with pytest.raises(NotAModel, match="not a readable ONNX model"):
        OnnxModel(garbage)
    import onnx
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Relu", ["x"], ["y"])], "foreign",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])],
    )  # fmt: skip
    foreign = tmp_path / "foreign.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]), foreign)
    with pytest.raises(NotAModel, match="without nhfd metadata"):
        OnnxModel(foreign)
    with pytest.raises(FileNotFoundError, match="no such model file"):
        OnnxModel(tmp_path / "missing.onnx")


def test_onnx_extremes_give_finite_outputs(exported):
    model = OnnxModel(exported.path)
    for rgb in (np.zeros((3, 16, 20)), np.ones((3, 16, 20)), np.full((3, 16, 20), 5.0),
                np.random.default_rng(0).random((3, 16, 20)).astype(np.float16)):  # fmt: skip
        amp, phase = model(rgb)
        assert np.isfinite(amp).all() and np.isfinite(phase).all()
