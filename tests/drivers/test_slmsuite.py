"""The slmsuite backends (nhfd.drivers.slmsuite) on slmsuite's simulated SLM and camera: the bytes
the slmsuite SLM receives are nhfd's grey frame, geometry is cross-checked, and, end to end through
a daemon and calibration's DaemonBenchIO, gratings land where Fourier optics puts them, the
simulated panel's phase response is recovered from the captures, and frames coded with the
recovered curve diffract as designed.

slmsuite's simulated camera images the SLM's far field (a Fourier plane: one camera pixel per
FFT bin on a panel-sized grid, the zero order at the centre), not nhfd's Fresnel bench: a
binary grating of period P px puts its +-1 orders W/P px either side of the zero order, and the
orders' powers give the grey level's phase step (I1 / I0 = (2 / pi)^2 tan^2(dphi / 2)).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("slmsuite", reason="slmsuite is not installed: pip install 'nhfd[slmsuite]'")

from daemon.conftest import Running, bench_config, running_daemon
from slmsuite.hardware.cameras.simulated import SimulatedCamera
from slmsuite.hardware.slms.simulated import SimulatedSLM

from nhfd.calib.capture import DaemonBenchIO
from nhfd.config import Config
from nhfd.device_settings import (
    CameraSettings,
    SLMOutputSettings,
    SlmsuiteSettings,
)
from nhfd.drivers.factory import make_bench
from nhfd.drivers.slmsuite import SlmsuiteCamera, SlmsuiteSLM, SlmsuiteUnavailable
from nhfd.spec import PhaseCurve, nearest_level

logging.getLogger("slmsuite").setLevel(logging.ERROR)  # "resolution is unusual" for test panels

N = 64  # panel and camera: N x N, so camera pixel = far-field bin
PERIOD_PX = 8  # the gratings' period: +-1 orders at N / 8 = 8 px from the zero order
# slmsuite's simulated far field holds N^2 counts per second of exposure at gain 1: with this
# gain the whole beam in one pixel is ~3000 of the 12-bit camera's 4095 levels at 5 ms.
GAIN = 150.0
EXPOSURE_S = 0.005
# The simulated panel's true grey -> phase response, in units of 2 pi (slmsuite's gamma_sim):
# not linear and not nhfd's default curve, so a recovered curve is the panel's, not an assumption.
# Its stroke stays under one wave: a step of 2 pi + x diffracts as x does, no grating tells them
# apart.
TRUE_WAVES = 0.98 * (np.arange(256) / 256) ** 1.25


def grating(grey: int) -> np.ndarray:
    """Binary grating: columns alternate PERIOD_PX / 2 at 0 and PERIOD_PX / 2 at `grey`."""
    frame = np.zeros((N, N), np.uint8)
    frame[:, (np.arange(N) // (PERIOD_PX // 2)) % 2 == 1] = grey
    return frame


class RecordingSLM(SimulatedSLM):
    """slmsuite's simulated SLM, keeping what reached its hardware hook."""

    def __init__(self, *a: Any, **kw: Any) -> None:
        self.received: list[np.ndarray] = []
        super().__init__(*a, **kw)

    def _set_phase_hw(self, display: Any) -> None:
        self.received.append(np.array(display, copy=True))


def test_the_slmsuite_slm_receives_nhfds_grey_levels_unchanged():
    device = RecordingSLM((10, 6), pitch_um=(8.0, 8.0))
    frame = np.random.default_rng(2).integers(0, 256, (3, 6, 10), dtype=np.uint8)
    with SlmsuiteSLM(10, 6, SLMOutputSettings(settle_ms=0.0), SlmsuiteSettings(channel="blue"),
                     pitch_um=8.0, device=device) as slm:
        slm.show(frame)
        got = device.received[-1]
    # Byte for byte the blue plane: slmsuite's phase -> grey conversion (which would map these
    # levels through its phase_scaling and flip their sign) never ran.
    assert got.dtype == np.uint8 and got.shape == (6, 10)
    np.testing.assert_array_equal(got, frame[2])
    np.testing.assert_array_equal(device.display, frame[2])


def test_geometry_and_bit_depth_mismatches_are_refused_naming_both():
    with pytest.raises(ValueError, match=r"is 10 x 6 px but \[slm\] width_px x height_px is "
                                         r"12 x 6"):
        SlmsuiteSLM(12, 6, device=SimulatedSLM((10, 6), pitch_um=(8.0, 8.0))).open()
    with pytest.raises(ValueError, match=r"pitch_um is \[8\.0, 8\.0\] but \[slm\] pitch_um is "
                                         r"3\.74"):
        SlmsuiteSLM(10, 6, pitch_um=3.74,
                    device=SimulatedSLM((10, 6), pitch_um=(8.0, 8.0))).open()
    with pytest.raises(ValueError, match=r"bitdepth 10: nhfd codes 256 grey levels"):
        SlmsuiteSLM(10, 6, device=SimulatedSLM((10, 6), bitdepth=10)).open()
    with pytest.raises(SlmsuiteUnavailable, match=r"devices.slmsuite.slm_class = "
                                                  r"'nope.nothing:X': cannot import nope.nothing"):
        SlmsuiteSLM(10, 6, suite=SlmsuiteSettings(slm_class="nope.nothing:X")).open()
    # From the configuration: [devices.slmsuite]'s class and kwargs, [slm]'s pitch.
    devices = Config().devices.model_copy(update={
        "slm": "slmsuite", "camera": "none", "laser": "none", "stage": "none",
        "slmsuite": SlmsuiteSettings(slm_kwargs={"resolution": [10, 6], "pitch_um": [8.0, 8.0]})})
    with make_bench(devices, 10, 6, pitch_um=8.0) as b:
        assert b.slm.device.shape == (6, 10)
    with pytest.raises(ValueError, match=r"pitch_um is \[8\.0, 8\.0\] but \[slm\] pitch_um is 12"):
        make_bench(devices, 10, 6, pitch_um=12.0)


def test_the_camera_flags_the_top_level_of_the_devices_bit_depth_and_scales_gain():
    slm = SimulatedSLM((N, N), pitch_um=(8.0, 8.0))
    device = SimulatedCamera(slm, gain=GAIN, bitdepth=12)
    with SlmsuiteCamera(CameraSettings(exposure_s=EXPOSURE_S), device=device) as camera:
        slm.set_phase(grating(0), settle=False)  # a flat panel: the whole beam in one pixel
        cap = camera.capture(1, subtract_dark=False)
        peak = float(cap.image[N // 2, N // 2])
        # 4096 counts/s x 5 ms x 150 = 3072 raw levels of 4095 (12 bits, not the settings' 8).
        assert peak == pytest.approx(3072 / 4095, abs=1.5 / 4095) and not cap.any_saturated
        assert camera.set_gain(6.0) == pytest.approx(6.0)
        assert device.gain == pytest.approx(GAIN * 10 ** (6 / 20))
        cap = camera.capture(1, subtract_dark=False)
        # x 2 in counts: past full scale, so the pixel is flagged and reads exactly 1.0.
        assert cap.saturated[N // 2, N // 2] and cap.image[N // 2, N // 2] == 1.0
        assert cap.saturated.sum() == 1


# ------------------------------------------------------------------------------ through a daemon


def slmsuite_daemon_config(root: Path) -> Any:
    config = bench_config(root, None, frames={"colour_mode": "single", "single_colour": "green"},
                          paths={"pattern_dirs": [str(root / "calib")]})
    suite = SlmsuiteSettings(
        slm_kwargs={"resolution": [N, N], "pitch_um": [8.0, 8.0],
                    "gamma_sim": [float(v) for v in TRUE_WAVES]},
        camera_kwargs={"gain": GAIN, "bitdepth": 12})
    d = config.devices
    devices = d.model_copy(update={
        "slm": "slmsuite", "camera": "slmsuite", "slmsuite": suite,
        "slm_output": d.slm_output.model_copy(update={"settle_ms": 1.0}),
        "camera_settings": d.camera_settings.model_copy(update={"bit_depth": 12})})
    slm = config.slm.model_copy(update={"width_px": N, "height_px": N, "pitch_um": 8.0})
    return config.model_copy(update={"devices": devices, "slm": slm})


@pytest.fixture(scope="module")
def daemon() -> Iterator[tuple[Running, Path]]:
    with running_daemon(slmsuite_daemon_config, "nhfd-s-") as (r, root):
        yield r, root


def orders(image: np.ndarray) -> tuple[float, float]:
    """(zero order, mean of the +-1 orders) of a grating's far field."""
    c, d = N // 2, N // PERIOD_PX
    return float(image[c, c]), float(image[c, c - d] + image[c, c + d]) / 2


def unfold(folded: list[float]) -> np.ndarray:
    """The orders fold the phase step into [0, pi]; a monotone panel passes pi once: unfold
    (p -> 2 pi - p) after the level where the smoothest curve results."""
    best: np.ndarray | None = None
    for turn in range(len(folded)):
        curve = np.array([p if k <= turn else 2 * math.pi - p for k, p in enumerate(folded)])
        if best is None or np.square(np.diff(curve, 2)).sum() < np.square(np.diff(best, 2)).sum():
            best = curve
    assert best is not None
    return best


def test_gratings_through_the_daemon_land_where_fourier_optics_puts_them(daemon):
    r, root = daemon
    c = r.client(timeout_s=30.0)
    status = c.status()["devices"]
    assert status["slm"]["backend"] == "slmsuite" and status["slm"]["open"]
    assert status["camera"]["backend"] == "slmsuite" and status["camera"]["open"], status
    io = DaemonBenchIO(c, root / "calib" / "io", exposure_s=EXPOSURE_S)
    io.show(grating(0))
    flat, _ = io.capture(1)
    io.show(grating(128))
    image, saturated = io.capture(1)
    assert not saturated.any()
    # Flat: everything in the zero order. The grating at grey 128 (about 0.46 waves on this
    # panel): orders at +-N/P = +-8 px from the centre, and nowhere between.
    assert np.unravel_index(int(flat.argmax()), flat.shape) == (N // 2, N // 2)
    bright = {tuple(int(v) for v in p) for p in np.argwhere(image > 0.01 * image.max())}
    assert {(32, 24), (32, 40)} <= bright <= {(32, x) for x in (8, 24, 32, 40, 56)}
    # The slmsuite SLM was handed the daemon's single-colour frame, grey for grey.
    np.testing.assert_array_equal(r.daemon.bench.slm.device.display, grating(128))


@pytest.fixture(scope="module")
def measured(daemon) -> tuple[list[int], np.ndarray]:
    """Phase step per grey level from binary gratings (the zero order's and +-1 orders' powers),
    captured through the daemon: (levels, phase steps in rad)."""
    r, root = daemon
    io = DaemonBenchIO(r.client(timeout_s=30.0), root / "calib" / "response",
                       exposure_s=EXPOSURE_S)
    levels = list(range(16, 256, 16))
    folded = []
    for g in levels:
        io.show(grating(g))
        image, saturated = io.capture(2)
        assert not saturated.any()
        i0, i1 = orders(image)
        folded.append(2 * math.atan2(math.pi / 2 * math.sqrt(i1), math.sqrt(i0)))
    return levels, unfold(folded)


def test_the_panels_phase_response_is_recovered_through_the_daemon(measured):
    """Against slmsuite's true gamma_sim."""
    levels, dphi = measured
    truth = 2 * math.pi * (TRUE_WAVES[levels] - TRUE_WAVES[0])
    err = np.abs(dphi - truth)
    # 12-bit quantisation of the orders' counts: 0.026 rad at most, 0.018 rad median here.
    assert err.max() < 0.05, (dphi.round(3), truth.round(3))
    assert float(np.median(err)) < 0.03


def test_frames_coded_with_the_measured_curve_diffract_as_designed(daemon, measured):
    """The measured curve as nhfd's phase curve (nhfd.spec.nearest_level, the coding rule of
    nhfd.optics.phase_to_grey): an 8-step blazed grating puts all of its light in one first
    order on this sampled far field; coded with the nominal linear curve, some stays behind."""
    levels, dphi = measured
    # Through (0, 0) and the measured levels, extended to 255 with the last slope.
    xs = [0, *levels, 255]
    ys = [0.0, *dphi, dphi[-1] + (dphi[-1] - dphi[-2]) * (255 - levels[-1]) / 16]
    curve = PhaseCurve(tuple(np.interp(np.arange(256), xs, ys)))
    r, root = daemon
    io = DaemonBenchIO(r.client(timeout_s=30.0), root / "calib" / "blaze", exposure_s=EXPOSURE_S)
    c, d = N // 2, N // PERIOD_PX
    share = {}
    for name, coding in (("nominal", PhaseCurve.linear()), ("measured", curve)):
        greys = [nearest_level(2 * math.pi * k / PERIOD_PX, coding) for k in range(PERIOD_PX)]
        io.show(np.tile(np.array(greys, np.uint8), (N, N // PERIOD_PX)))
        image, saturated = io.capture(1)
        assert not saturated.any()
        total = float(image.sum())
        share[name] = (max(image[c, c - d], image[c, c + d]) / total, image[c, c] / total)
    # Measured here: 100.0 % against 97.2 % in the first order, 0.0 % against 1.1 % at zero.
    assert share["measured"][0] > 0.995 and share["measured"][1] < 0.002
    assert share["nominal"][0] < 0.98 and share["nominal"][1] > 0.005


def test_a_daemon_refuses_an_slmsuite_panel_whose_pitch_is_not_the_configured_one():
    """The daemon hands [slm] pitch_um to the backend: a bench configured for 12 um driving an
    8 um slmsuite panel reports the mismatch and shows nothing on it."""
    def twelve_um(root: Path) -> Any:
        config = slmsuite_daemon_config(root)
        return config.model_copy(update={"slm": config.slm.model_copy(update={"pitch_um": 12.0})})

    with running_daemon(twelve_um, "nhfd-s-") as (r, _):
        status = r.client(timeout_s=30.0).call("status")
        errors = " ".join(str(e) for e in status["errors"])
        assert "pitch_um is [8.0, 8.0] but [slm] pitch_um is 12" in errors
        assert r.daemon.bench.slm is None
