"""SLM frames: validation and quantisation, the simulated SLM, and the framebuffer's exact bytes."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from nhfd.device_settings import SLMOutputSettings
from nhfd.drivers import framebuffer
from nhfd.drivers.framebuffer import FramebufferError, FramebufferSLM
from nhfd.drivers.slm import SimulatedSLM, SLMOutputLost, to_rgb
from nhfd.drivers.trigger import TriggerLine
from nhfd.drivers.twins.clock import ManualClock

from .conftest import fake_framebuffer

H, W = 3, 5


def test_one_grey_pattern_goes_to_all_three_channels_and_three_to_one_each():
    grey = np.arange(H * W, dtype=np.uint8).reshape(H, W)
    rgb = to_rgb(grey, H, W)
    assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8 and rgb.flags.c_contiguous
    for c in range(3):
        assert (rgb[..., c] == grey).all()
    per = np.stack([grey, grey + 100, grey + 200]).astype(np.uint8)
    rgb = to_rgb(per, H, W)
    assert (rgb[..., 0] == grey).all() and (rgb[..., 2] == grey + 200).all()
    assert (to_rgb(grey[None], H, W) == to_rgb(grey, H, W)).all()


def test_quantisation_rounds_floats_and_refuses_what_cannot_be_shown():
    f = np.full((H, W), 254.6)
    f[0, 0], f[0, 1] = -0.4, 7.5
    rgb = to_rgb(f, H, W)
    assert rgb[0, 0, 0] == 0 and rgb[0, 1, 0] == 8 and rgb[1, 1, 1] == 255
    assert to_rgb(np.full((H, W), 255, np.int64), H, W).max() == 255
    for bad, why in [
        (np.full((H, W), 255.6), "round into"),
        (np.full((H, W), np.nan), "NaN"),
        (np.full((H, W), 256, np.int32), r"\[0, 255\]"),
        (np.full((H, W), -1, np.int16), r"\[0, 255\]"),
        (np.zeros((W, H), np.uint8), "shape"),
        (np.zeros((2, H, W), np.uint8), "shape"),
        (np.zeros((H, W), np.complex64), "dtype"),
    ]:
        with pytest.raises(ValueError, match=why):
            to_rgb(bad, H, W)


def test_simulated_slm_keeps_frames_settles_and_refuses_when_unplugged(tmp_path):
    clock = ManualClock(100.0)
    settings = SLMOutputSettings(settle_ms=40.0, history_frames=2, png_dir=str(tmp_path))
    with SimulatedSLM(W, H, settings, clock=clock) as slm:
        assert slm.last_frame is None and slm.shape == (H, W)
        for level in (10, 20, 30):
            ready = slm.show(np.full((H, W), level, np.uint8))
        assert ready == pytest.approx(100.04) and not slm.settled
        clock.advance(0.05)
        assert slm.settled
        assert [int(f[0, 0, 0]) for f in slm.frames] == [20, 30] and slm.count == 3
        assert slm.last_frame.shape == (3, H, W) and int(slm.last_frame[1, 2, 4]) == 30
        slm.unplug()
        assert not slm.health().ok
        with pytest.raises(SLMOutputLost, match="unplugged"):
            slm.show(np.zeros((H, W), np.uint8))
        assert int(slm.last_frame[0, 0, 0]) == 30  # a refused frame changes nothing
        with pytest.raises(ValueError):
            slm.show(np.zeros((H, W + 1), np.uint8))
    pngs = sorted(tmp_path.glob("slm_*.png"))
    assert len(pngs) == 3
    from matplotlib import image

    saved = image.imread(pngs[-1])
    assert saved.shape[:2] == (H, W) and round(float(saved[0, 0, 0]) * 255) == 30


def test_framebuffer_writes_bgrx_rows_with_stride_padding(tmp_path):
    settings = fake_framebuffer(tmp_path, width=W, height=H, bpp=32, stride=W * 4 + 4)
    frame = np.zeros((3, H, W), np.uint8)
    for y in range(H):
        for x in range(W):
            frame[:, y, x] = (10 * y + x, 100 + 10 * y + x, 200 + 10 * y + x)  # R, G, B
    with FramebufferSLM(W, H, settings) as slm:
        slm.show(frame)
    expected = bytearray()
    for y in range(H):
        for x in range(W):
            r, g, b = 10 * y + x, 100 + 10 * y + x, 200 + 10 * y + x
            expected += bytes([b, g, r, 0xFF])
        expected += b"\xab" * 4  # padding after each row is left alone
    assert (tmp_path / "dev" / "fb1").read_bytes() == bytes(expected)


def test_framebuffer_24_bpp_and_rgb_order(tmp_path):
    base = fake_framebuffer(tmp_path, width=W, height=H + 1, bpp=24, stride=W * 3 + 1)
    settings = base.model_copy(update={"pixel_order": "RGB"})
    frame = np.stack([np.full((H, W), v, np.uint8) for v in (1, 2, 3)])
    with FramebufferSLM(W, H, settings) as slm:
        slm.show(frame)
    data = (tmp_path / "dev" / "fb1").read_bytes()
    row = bytes([1, 2, 3] * W) + b"\xab"
    # Only the panel's rows are written; a taller virtual screen keeps its extra row.
    assert data == row * H + b"\xab" * (W * 3 + 1)


@pytest.mark.parametrize("source", ["slm_flip", "camera_exposure"])
def test_framebuffer_waits_for_the_vertical_blank_before_the_frame_is_stamped_written(
        tmp_path, monkeypatch, source):
    # The blank waited for ends the old frame's scan: a flip during the wait is the old frame's.
    # slm_flip: the written stamp must follow the wait, or a flip-triggered exposure would start
    # on the old frame. camera_exposure: the wait must come before the write gate (which holds
    # the line's lock), or the camera's exposure callbacks would block for up to a refresh.
    fb = tmp_path / "dev" / "fb1"
    events: list[tuple[str, int]] = []  # (what, the first pixel's byte then)
    monkeypatch.setattr(framebuffer.fcntl, "ioctl",
                        lambda fd, request, arg: events.append(("vsync", fb.read_bytes()[0])))
    settings = fake_framebuffer(tmp_path, width=W, height=H, bpp=32, stride=W * 4)
    line = TriggerLine(source)
    written, gate = line.written, line.frame_write

    def spy_written(at_s: float) -> None:
        events.append(("written", fb.read_bytes()[0]))
        written(at_s)

    @contextmanager
    def spy_gate() -> Iterator[float]:
        events.append(("gate", fb.read_bytes()[0]))
        with gate() as low_s:
            yield low_s

    line.written, line.frame_write = spy_written, spy_gate
    with FramebufferSLM(W, H, settings) as slm:
        slm.attach_trigger(line)
        del events[:]  # the probe at open
        slm.show(np.full((H, W), 7, np.uint8))
        slm.show(np.full((H, W), 9, np.uint8))
    gated = source == "camera_exposure"
    expected = [[("vsync", old)] + [("gate", old)] * gated + [("written", old)]
                for old in (0xAB, 7)]  # each before its frame's pixels are written
    assert events == expected[0] + expected[1]
    assert fb.read_bytes()[:4] == bytes([9, 9, 9, 0xFF])


def test_framebuffer_refuses_16_bpp_and_a_wrong_geometry(tmp_path):
    settings = fake_framebuffer(tmp_path / "a", width=W, height=H, bpp=16, stride=W * 2)
    with pytest.raises(FramebufferError, match="16 bpp"):
        FramebufferSLM(W, H, settings).open()
    settings = fake_framebuffer(tmp_path / "b", width=W + 1, height=H, bpp=32, stride=24)
    with pytest.raises(FramebufferError, match="is 6 x 3, the SLM is 5 x 3"):
        FramebufferSLM(W, H, settings).open()


def test_framebuffer_notices_an_unplugged_output(tmp_path):
    settings = fake_framebuffer(tmp_path, width=W, height=H, bpp=32, stride=W * 4,
                                connectors={"card0-HDMI-A-1": "connected",
                                            "card0-HDMI-A-2": "connected",
                                            "card0-DP-1": "disconnected"})
    drm = tmp_path / "sys" / "class" / "drm"
    with FramebufferSLM(W, H, settings) as slm:
        slm.show(np.full((H, W), 7, np.uint8))
        (drm / "card0-HDMI-A-2" / "status").write_text("disconnected\n")
        assert "card0-HDMI-A-2 disconnected" in slm.health().detail
        before = (tmp_path / "dev" / "fb1").read_bytes()
        with pytest.raises(SLMOutputLost, match="HDMI-A-2"):
            slm.show(np.full((H, W), 9, np.uint8))
        assert (tmp_path / "dev" / "fb1").read_bytes() == before
    named = settings.model_copy(update={"drm_connector": "card0-HDMI-A-1"})
    with FramebufferSLM(W, H, named) as slm:
        assert slm.health().ok  # only the named connector matters
    missing = settings.model_copy(update={"drm_connector": "card9-VGA-1"})
    with pytest.raises(FramebufferError, match="card9-VGA-1"):
        FramebufferSLM(W, H, missing).open()


def test_the_driver_and_the_coder_agree_on_the_panel_depth():
    """drivers.slm keeps its own copy (no torch in SLM backends); it must equal the coder's."""
    from nhfd.drivers.slm import GREY_LEVELS as driver_levels
    from nhfd.optics.dpac import GREY_LEVELS as coder_levels

    assert driver_levels == coder_levels == 256
