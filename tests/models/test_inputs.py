"""The network's inputs: the depth channel's scaling, and that training and the daemon build the
same input from a render (the daemon's path is `network_input`, training's is `HoloData`)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nhfd.dataset.build import shard_name
from nhfd.dataset.shard import read_shard
from nhfd.models.data import HoloData
from nhfd.models.export import OnnxModel, export_onnx
from nhfd.models.inputs import depth_channel, input_channels, mapped_depth, network_input
from nhfd.models.net import NetSpec, build_net, predict
from nhfd.models.train import load_run, train

from .conftest import tiny_options

VOLUME_M = (-3e-3, 3e-3)


def test_the_depth_channel_spans_the_volume_from_minus_one_to_one():
    zh = np.array([-3e-3, 0.0, 1.5e-3, 3e-3, np.nan, 9e-3, -1.0], np.float32)
    d = depth_channel(zh, VOLUME_M)
    assert d.dtype == np.float32
    np.testing.assert_allclose(d, [-1, 0, 0.5, 1, 0, 2, -2], atol=1e-6)  # NaN: background -> 0


def test_mapped_depth_is_the_scene_mapping_on_content_only():
    depth = np.array([[1.0, 2.0], [0.0, 4.0]])
    alpha = np.array([[1.0, 0.6], [1.0, 0.3]])
    zh = mapped_depth(depth, alpha, a_m=-1e-3, b_m=2e-3)
    assert zh[0, 0] == pytest.approx(1e-3) and zh[0, 1] == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(zh[1, 0]) and np.isnan(zh[1, 1])  # no depth; too little coverage


def test_network_input_checks_what_it_needs():
    rgb = np.random.default_rng(0).random((3, 4, 5), np.float32)
    assert network_input(rgb, "rgb") is not None and network_input(rgb, "rgb").shape == (3, 4, 5)
    with pytest.raises(ValueError, match="rgbd model needs the render's depth"):
        network_input(rgb, "rgbd")
    with pytest.raises(ValueError, match=r"inputs = 'rgba': must be one of rgb, rgbd"):
        input_channels("rgba")
    with pytest.raises(ValueError, match=r"volume_m = \[0.003, -0.003\]"):
        depth_channel(np.zeros(2), (3e-3, -3e-3))


def test_the_daemons_float32_depth_channel_matches_trainings_and_handles_bad_depths():
    """network_input builds the channel in float32 in place; training uses the float64
    path. Non-finite or non-positive depths are background (0); depths beyond the volume clip
    at +-2."""
    rng = np.random.default_rng(3)
    depth = (0.5 + 0.3 * rng.random((6, 7))).astype(np.float32)
    depth[0, :6] = [np.nan, np.inf, -np.inf, 0.0, -1.0, 1e-30]  # 1e-30: far in front, clips
    alpha = np.ones((6, 7), np.float32)
    alpha[1, 0] = 0.2  # too faint: background
    mapping = {"a_m": -0.016656, "b_m": 0.010565}
    x = network_input(np.zeros((3, 6, 7), np.float32), "rgbd", depth=depth, alpha=alpha,
                      mapping=mapping, volume_m=VOLUME_M)  # fmt: skip
    want = depth_channel(mapped_depth(depth, alpha, mapping["a_m"], mapping["b_m"]), VOLUME_M)
    assert x.dtype == np.float32 and np.isfinite(x).all()
    np.testing.assert_allclose(x[3], want, atol=1e-6)
    assert (x[3, 0, :5] == 0).all() and x[3, 1, 0] == 0 and x[3, 0, 5] == 2.0


def test_training_and_the_daemon_build_the_same_rgbd_input(tiny_data):
    data = HoloData(tiny_data)
    manifest = json.loads((tiny_data / "manifest.json").read_text())
    split = data.splits["train"]
    shard = read_shard(tiny_data / shard_name(split.indices[1]))
    daemon = network_input(shard["rgb"], "rgbd", depth=shard["depth"], alpha=shard["alpha"],
                           mapping=manifest["mapping"],
                           volume_m=manifest["settings"]["volume_m"])  # fmt: skip
    training = split.inputs("rgbd", 1).numpy()
    assert daemon.shape == training.shape == (4, 64, 64)
    assert split.inputs("rgbd", slice(1, 3)).shape == (2, 4, 64, 64)
    np.testing.assert_allclose(daemon, training, atol=1e-6)
    # The synthetic views hold layers at +1.5 and -1.5 mm of a +-3 mm volume: +-0.5.
    levels = np.round(training[3], 4)
    assert set(np.unique(levels)) <= {-0.5, 0.0, 0.5}
    assert (levels == 0.5).any() and (levels == -0.5).any()


def test_an_rgbd_network_trains_exports_and_refuses_three_channels(tiny_data, tmp_path):
    run = tmp_path / "run"
    train(tiny_data, run, tiny_options(inputs="rgbd"), log=lambda _m: None)
    net, info = load_run(run)
    assert net.spec.inputs == "rgbd" and info["net"]["inputs"] == "rgbd"
    exported = export_onnx(run, tmp_path / "rgbd.onnx")
    assert exported.max_abs_diff < 1e-4
    model = OnnxModel(exported.path)
    assert model.inputs == "rgbd" and "rgbd" in model.metadata["inputs"]
    x = torch.rand(4, 37, 53)
    amp, phase = model(x.numpy())
    with torch.no_grad():
        ta, tp = predict(net, x)
    assert np.abs(amp - ta.numpy()).max() < 1e-4 and np.abs(phase - tp.numpy()).max() < 1e-4
    with pytest.raises(ValueError, match=r"rgbd input \(3, 37, 53\): expected \[4, H, W\]"):
        model(x[:3].numpy())
    with pytest.raises(ValueError, match=r"expected \[4, H, W\] or \[B, 4, H, W\] \(rgbd\)"):
        predict(build_net(NetSpec(8, 2, 1, "rgbd")), x[:3])
