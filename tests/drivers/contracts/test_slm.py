"""The SLM contract: every SLM backend, and a real panel when NHFD_TEST_SLM names its output
(NHFD_TEST_SLM=framebuffer:/dev/fb1:1920x1080 or window:HDMI-A-1:1920x1080; the panel shows
test patterns while it runs).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from nhfd.device_settings import SLMOutputSettings
from nhfd.drivers.errors import DeviceError
from nhfd.drivers.framebuffer import FramebufferSLM
from nhfd.drivers.slm import SLM, SimulatedSLM
from nhfd.drivers.window import WindowSLM

from ..conftest import fake_framebuffer
from . import bench_target

H, W = 6, 10


def real_slm(tmp_path: Path) -> SLM:
    backend, (target, *rest) = bench_target(
        "NHFD_TEST_SLM", ("framebuffer", "window"), "framebuffer:/dev/fb1:1920x1080")
    width, height = (int(v) for v in (rest[0] if rest else "1920x1080").split("x"))
    if backend == "framebuffer":
        return FramebufferSLM(width, height, SLMOutputSettings(framebuffer_device=target))
    return WindowSLM(width, height, SLMOutputSettings(drm_connector=target))


def slmsuite_slm() -> SLM:
    """slmsuite's simulated SLM behind nhfd's slmsuite backend."""
    simulated = pytest.importorskip(
        "slmsuite.hardware.slms.simulated", reason="slmsuite is not installed: pip install "
        "'nhfd[slmsuite]'")
    from nhfd.drivers.slmsuite import SlmsuiteSLM

    device = simulated.SimulatedSLM((W, H), pitch_um=(8.0, 8.0))
    return SlmsuiteSLM(W, H, SLMOutputSettings(settle_ms=0.0), pitch_um=8.0, device=device)


@pytest.fixture(params=["simulated", "framebuffer-file", "slmsuite", "bench"])
def slm(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[SLM]:
    if request.param == "simulated":
        driver: SLM = SimulatedSLM(W, H, SLMOutputSettings(settle_ms=0.0))
    elif request.param == "framebuffer-file":
        settings = fake_framebuffer(tmp_path, width=W, height=H, bpp=32, stride=W * 4)
        driver = FramebufferSLM(W, H, settings.model_copy(update={"settle_ms": 0.0}))
    elif request.param == "slmsuite":
        driver = slmsuite_slm()
    else:
        driver = real_slm(tmp_path)
    with driver:
        yield driver
        driver.blank()


def test_shows_a_uint8_frame_of_the_panels_shape(slm):
    h, w = slm.shape
    frame = (np.arange(h * w) % 256).astype(np.uint8).reshape(h, w)
    slm.show(frame, wait_settled=True)
    shown = slm.last_frame
    assert shown.shape == (3, h, w) and shown.dtype == np.uint8
    for channel in shown:
        np.testing.assert_array_equal(channel, frame)
    assert slm.settled and slm.health().ok


def test_refuses_a_wrong_shape_or_dtype_and_keeps_the_panel(slm):
    h, w = slm.shape
    slm.show(np.full((h, w), 7, np.uint8))
    for bad, why in [
        (np.zeros((w, h), np.uint8), "shape"),
        (np.zeros((h + 1, w), np.uint8), "shape"),
        (np.zeros((2, h, w), np.uint8), "shape"),
        (np.zeros((h, w), np.complex64), "dtype"),
        (np.full((h, w), 256, np.int32), r"\[0, 255\]"),
        (np.full((h, w), np.nan), "NaN"),
    ]:
        with pytest.raises(ValueError, match=why):
            slm.show(bad)
    assert (slm.last_frame == 7).all()


def test_a_closed_slm_shows_nothing(slm):
    slm.close()
    with pytest.raises(DeviceError, match="not open"):
        slm.show(np.zeros(slm.shape, np.uint8))
    slm.open()
