"""`nhfd demo` (the daemon demo): its refusal without a model, and its PNG reader."""

from __future__ import annotations

import numpy as np

from nhfd.cli.main import main
from nhfd.daemon.bench import write_png16
from nhfd.daemon.demo import focus_command_mm, read_png16


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


def test_region_sharpness_follows_which_third_is_in_focus():
    """Two textured bands on a grey frame with a thin bright border (like a window's edge):
    the capture with the bottom band sharp scores the near third higher, and vice versa."""
    from nhfd.daemon.demo import region_sharpness

    rng = np.random.default_rng(1)
    texture = rng.random((30, 80))
    blurred = (texture + np.roll(texture, 1, 0) + np.roll(texture, 1, 1)
               + np.roll(texture, -1, 0) + np.roll(texture, -1, 1)) / 5  # fmt: skip

    def frame(top: np.ndarray, bottom: np.ndarray) -> np.ndarray:
        img = np.full((160, 200), 0.1)
        img[2, :] = img[-3, :] = img[:, 2] = img[:, -3] = 2.0  # thin lines: not content
        img[40:70, 60:140] = 1 + top
        img[70:100, 60:140] = 1 + bottom
        return img

    near_focus, far_focus = frame(blurred, texture), frame(texture, blurred)
    near_s, far_s, (near, far) = region_sharpness([near_focus, far_focus])
    assert near[0].start >= 70 and far[0].stop <= 70  # the content box, not the border
    assert near_s[0] > 1.5 * near_s[1]
    assert far_s[1] > 1.5 * far_s[0]
