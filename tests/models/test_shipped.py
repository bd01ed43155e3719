"""The shipped default model: made for the default optics, and better than the 2D hologram on
views it was not trained on (a two-view 256 x 256 dataset rendered here with its mapping)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nhfd.config import Config

MODEL_NAME = "nhf-donut-512.onnx"


@pytest.fixture(scope="module")
def shipped():
    from nhfd.demos.serve import DEFAULT_MODEL, DEFAULT_SCENE

    if not DEFAULT_MODEL.exists():
        pytest.skip(f"no shipped model at {DEFAULT_MODEL}")
    return DEFAULT_MODEL, DEFAULT_SCENE


def test_shipped_model_matches_the_default_configuration(shipped):
    from nhfd.models.export import load_model
    from nhfd.models.net import NetSpec

    model = load_model(shipped[0], Config())  # raises ModelMismatch naming any difference
    md = model.metadata
    default = Config().model
    assert md["profile"] == default.profile and md["train_size_hw"] == [288, 512]
    # the profile as shipped (a key added to NetSpec after the export reads as its default)
    assert NetSpec(**md["net"]).to_json() == default.profiles[default.profile].model_dump()
    assert model.inputs == default.profiles[default.profile].inputs
    assert shipped[0].stat().st_size < 5 * 2**20  # "a few MB at most"


def test_shipped_model_beats_the_2d_hologram_on_new_views(shipped, tmp_path):
    from nhfd.dataset.build import build, shard_name
    from nhfd.dataset.poses import PoseSampler
    from nhfd.dataset.shard import ExampleSettings, read_shard
    from nhfd.models.export import OnnxModel
    from nhfd.models.inputs import network_input
    from nhfd.optics import Aperture, focal_stack_quality, hologram_2d, quality_planes
    from nhfd.scene.io import load_scene

    model_path, scene_path = shipped
    model = OnnxModel(model_path)
    md = model.metadata
    g = load_scene(scene_path)
    # 256 x 256 at the trained fx (a resolution change keeps fx; only the window changes), the
    # model's scene mapping, and two poses inside its envelope.
    fov = math.degrees(2 * math.atan(128 / md["fx"]))
    settings = ExampleSettings(width_px=256, height_px=256, fov_x_deg=fov, amplitude_samples=64)
    env = md["pose_envelope"]
    radius = float(np.mean(env["distance"]))
    poses = PoseSampler(center=tuple(float(v) for v in np.median(g.means, axis=0)), up="+z",
                        radius=(radius, radius), azimuth_deg=(-8.0, 8.0),
                        elevation_deg=(18.0, 18.0), n_train=2, n_interp=0, n_extrap=0,
                        seed=11).sample()  # fmt: skip
    build(scene_path, tmp_path / "ds", poses, settings, seed=3,
          d_near=md["mapping"]["d_near"], d_far=md["mapping"]["d_far"])  # fmt: skip
    aperture = Aperture(md["aperture_shape"], tuple(md["cutoff_per_px"]))
    kw = dict(planes_m=quality_planes(tuple(md["volume_m"])), pitch_m=md["pitch_m"],
              wavelengths_m=md["wavelengths_m"], aperture=aperture)  # fmt: skip
    for i in range(2):
        shard = read_shard(tmp_path / "ds" / shard_name(i))
        rgb = torch.from_numpy(shard["rgb"])
        target = torch.from_numpy(shard["field"])
        x = network_input(shard["rgb"], model.inputs, depth=shard["depth"], alpha=shard["alpha"],
                          mapping=md["mapping"], volume_m=md["volume_m"])  # fmt: skip
        amp, phase = model(x[None])
        pred = torch.polar(torch.from_numpy(amp[0]) * md["amplitude_scale"],
                           torch.from_numpy(phase[0]))  # fmt: skip
        mask = torch.from_numpy(shard["alpha"] > 0.5)
        ours = focal_stack_quality(pred, target, mask=mask, **kw)
        flat = focal_stack_quality(hologram_2d(rgb, like=target, mask=mask), target, mask=mask,
                                   **kw)  # fmt: skip
        black = focal_stack_quality(torch.zeros_like(target), target, mask=mask, **kw)
        assert np.isfinite(amp).all() and np.isfinite(phase).all()
        # Content crosses this window's left edge, which the 512 x 288 training views never
        # showed. Measured: the shipped model (fast) 32.9 / 33.1 dB (the balanced one shipped
        # before it: 32.9 / 33.0 dB), the energy-matched 2D hologram 22.0 / 22.2 dB, black
        # 5.9 dB; models trained on whole views only fell to 22.1 or even 10.8 dB here while
        # scoring 30 dB on 512 x 288 windows.
        assert ours.psnr_db > flat.psnr_db + 3.0, (ours, flat)
        assert ours.psnr_db > black.psnr_db + 3.0
