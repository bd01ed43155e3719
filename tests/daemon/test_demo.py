"""`nhfd demo` (the daemon demo): its refusal without a model, and its PNG reader."""

from __future__ import annotations

import numpy as np
import pytest

from nhfd.cli.main import main
from nhfd.daemon.client import Client
from nhfd.daemon.png import write_png16
from nhfd.demos.serve import focus_command_mm, read_png16


def test_demo_without_the_model_says_how_to_build_it_and_fails(tmp_path, capsys):
    absent = tmp_path / "nhf-donut-512.onnx"
    code = main(["demo", "--model", str(absent), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code != 0
    assert str(absent) in err and "nhfd dataset build" in err and "nhfd train" in err
    assert not (tmp_path / "out").exists()  # nothing started, nothing written


def test_captures_read_back_exactly(tmp_path):
    image = np.random.default_rng(0).random((37, 53))
    write_png16(tmp_path / "c.png", image)
    back = read_png16(tmp_path / "c.png")
    assert back.shape == (37, 53)
    assert np.abs(back - image).max() <= 0.5 / 65535 + 1e-12


def test_focus_commands_follow_the_simulated_relay():
    from nhfd.drivers.simcamera import TrueBench

    truth = TrueBench()
    # Stage travel for 1 mm of hologram depth is M^2 = 0.5625 mm on the default relay.
    assert focus_command_mm(1e-3, truth) == np.float64(1e-3 * 1e3 / truth.stage_scale)
    assert abs(focus_command_mm(1e-3, truth) - 0.5625) < 1e-12


def test_focus_correlation_picks_the_capture_where_each_region_is_sharp():
    """A textured view; in one capture the bottom band is sharp and the top blurred, in the
    other the reverse: the match with the view inside each band peaks at its own capture."""
    from nhfd.demos.serve import focus_correlation

    rng = np.random.default_rng(1)
    view = np.zeros((120, 160))
    view[20:100, 30:130] = 1 + rng.random((80, 100))
    blur = (view + np.roll(view, 2, 0) + np.roll(view, -2, 0) + np.roll(view, 2, 1)
            + np.roll(view, -2, 1)) / 5  # fmt: skip
    top, bottom = np.zeros(view.shape, bool), np.zeros(view.shape, bool)
    top[20:60, 30:130], bottom[60:100, 30:130] = True, True
    bottom_sharp = np.where(bottom, view, blur) * 3 + 0.2  # gain and offset do not matter
    top_sharp = np.where(top, view, blur)
    near = focus_correlation([bottom_sharp, top_sharp], view, bottom)
    far = focus_correlation([bottom_sharp, top_sharp], view, top)
    assert near[0] > 0.99 > near[1] and far[1] > 0.99 > far[0]


def test_depth_regions_are_the_nearest_and_farthest_quarter_of_the_content():
    from nhfd.demos.serve import depth_regions

    zh = np.full((10, 10), np.nan)
    zh[2:8, 2:8] = np.linspace(-2e-3, 2e-3, 36).reshape(6, 6)
    near, far = depth_regions(zh)
    assert near.sum() == far.sum() == 9  # a quarter of 36
    assert zh[near].min() > zh[far].max()
    assert not (near | far)[np.isnan(zh)].any()
    with pytest.raises(ValueError, match="no content"):
        depth_regions(np.full((4, 4), np.nan))


class _ScriptedClient(Client):
    """The real `Client.wait_job` over a scripted `job` method (no daemon, no socket)."""

    def __init__(self, states: list[str]) -> None:
        self.states = states

    def call(self, method: str, **params):
        assert method == "job" and params == {"id": 7}
        state = self.states.pop(0) if len(self.states) > 1 else self.states[0]
        return {"id": 7, "kind": "focus", "state": state, "error": "stage stalled"}

    def status(self):
        return {"errors": ["e1", "e2", "e3", "e4"]}


def test_the_demo_waits_on_a_job_as_the_client_does():
    from nhfd.demos.serve import _job

    assert _job(_ScriptedClient(["queued", "running", "done"]), 7, 5.0)["state"] == "done"
    with pytest.raises(RuntimeError, match="focus job 7 failed: stage stalled"):
        _job(_ScriptedClient(["running", "failed"]), 7, 5.0)
    with pytest.raises(TimeoutError, match=r"after 0.2 s waiting for job 7 \(still running\); "
                       r"daemon errors: \['e2', 'e3', 'e4'\]"):
        _job(_ScriptedClient(["running"]), 7, 0.2)


def test_the_gif_shows_each_region_enlarged_by_a_whole_factor(tmp_path):
    """The sweep's regions, cropped to their boxes and enlarged, below the overview: a row per
    region (near, far), a column per frame (network, sgd), every inset pixel its crop's pixel
    repeated factor x factor; a region wider than its column shows its central part at 1:1; and
    the GIF's frames hold them at that size."""
    from PIL import Image

    from nhfd.demos.serve import focal_gif, region_insets

    rng = np.random.default_rng(5)
    net, ref = rng.random((90, 140)), rng.random((90, 140))
    near, far = np.zeros((90, 140), bool), np.zeros((90, 140), bool)
    near[10:30, 20:50], far[50:80, 90:130] = True, True
    nbox, fbox = np.s_[6:34, 16:54], np.s_[46:84, 86:134]  # the masks' boxes, padded by 4
    canvas, factor = region_insets([net, ref], [near, far], width_px=500)
    # columns of (500 - 4) // 2 = 248 px; the widest box, 48 px, fits 5 times
    assert factor == 5 and canvas.shape == (28 * 5 + 4 + 38 * 5, 500)
    for (top, box), (left, img) in [((t, b), (c, i)) for t, b in ((0, nbox), (144, fbox))
                                    for c, i in ((0, net), (252, ref))]:
        crop = np.kron(img[box], np.ones((5, 5)))
        h, w = crop.shape
        assert np.array_equal(canvas[top : top + h, left : left + w], crop)
    narrow, one = region_insets([net, ref], [near, far], width_px=60)  # columns of 28 px
    assert one == 1 and np.array_equal(narrow[:28, :28], net[nbox][:, 5:33])  # the centre
    # Through the demo's GIF: the overview pair is binned 2 x 2, the insets sit below it.
    sweep = [(z, np.rot90(img, 2)) for z, img in ((-1e-3, net), (1e-3, ref))]
    regions = {"near": {"mask_camera": np.rot90(near, 2)}, "far": {"mask_camera": np.rot90(far, 2)}}
    focal_gif(sweep, sweep, regions, tmp_path / "s.gif")
    gif = Image.open(tmp_path / "s.gif")
    assert gif.n_frames == 2  # near to far and back: 2 depths make 2 frames
    # the content's box (pad 12: rows 0:90, cols 8:140) binned to 45 x 66, twice and a 4 px gap;
    # below, 4 px on, the insets in 66 px columns at factor 1: rows of 28 and 38, 4 apart
    assert gif.size == (66 + 4 + 66, 45 + 4 + 28 + 4 + 38)
