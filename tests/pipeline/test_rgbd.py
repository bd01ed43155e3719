"""The frame pipeline feeds an rgbd model the render's mapped depth, built as training built it."""

from __future__ import annotations

import numpy as np

from nhfd.calibration import CalibrationStore
from nhfd.models.export import load_model
from nhfd.models.inputs import depth_channel, mapped_depth
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.frame import compute_frame
from nhfd.pipeline.settings import frame_settings
from nhfd.pipeline.view import Scene, SceneFrame, render_camera
from nhfd.scene.io import load_scene
from nhfd.scene.raster import render
from tests.daemon.test_frames import FRONT_VIEW, make_tiny_model, make_tiny_scene, small_config


class Spy:
    """The model, recording what the pipeline feeds it."""

    def __init__(self, model) -> None:
        self.model, self.info, self.inputs = model, model.info, model.inputs
        self.seen: list[np.ndarray] = []

    def __call__(self, x: np.ndarray):
        self.seen.append(np.array(x))
        return self.model(x)


def test_an_rgbd_model_gets_the_renders_mapped_depth(tmp_path):
    config = small_config()
    model = Spy(load_model(make_tiny_model(tmp_path, inputs="rgbd"), config))
    assert model.inputs == "rgbd"
    scene = Scene(load_scene(make_tiny_scene(tmp_path / "cloud.ply")),
                  SceneFrame((0.0, 0.0, 0.0), "-y"))
    encoder = Encoder(frame_settings(config, model.info, CalibrationStore.of(config).active()))
    frame = compute_frame(FRONT_VIEW, scene, model, encoder)
    (x,) = model.seen
    assert x.shape == (4, 64, 96)
    np.testing.assert_array_equal(x[:3], frame.rgb)

    again = render(scene.gaussians, render_camera(FRONT_VIEW, scene.frame, model.info, (64, 96)))
    m = model.model.metadata  # the file's own record, not the info parsed from it
    want = depth_channel(mapped_depth(again.depth, again.alpha, m["mapping"]["a_m"],
                                      m["mapping"]["b_m"]), m["volume_m"])  # fmt: skip
    np.testing.assert_allclose(x[3], want, atol=1e-6)
    content = again.alpha >= 0.5
    assert content.sum() > 50 and np.all(x[3][~content] == 0)  # background: the reference plane
    assert np.ptp(x[3][content]) > 0.01  # the cloud has depth, and the channel shows it
    assert frame.grey.dtype == np.uint8
