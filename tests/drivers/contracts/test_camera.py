"""The camera contract: every camera backend, and a real camera when NHFD_TEST_CAMERA names it
(NHFD_TEST_CAMERA=opencv:0 or genicam:/path/to/producer.cti[:serial]). A real bench has no light
the test can switch, so the linearity fact runs where the set-up supplies one.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from nhfd.config import Config
from nhfd.device_settings import CameraSettings
from nhfd.drivers.camera import Camera, GenICamCamera, OpenCVCamera
from nhfd.drivers.errors import DeviceError
from nhfd.drivers.factory import make_bench
from nhfd.drivers.simcamera import TrueBench

from . import bench_target


class RampCamera(Camera):
    """A backend whose sensor sees a fixed irradiance ramp (0 to 5 x full scale at the reference
    exposure: at the default 4 ms the top half saturates), encoded through its gamma response."""

    REFERENCE_EXPOSURE_S = 0.01

    def __init__(self, settings: CameraSettings) -> None:
        super().__init__(settings)
        self.lit = True
        self.ramp = np.linspace(0.0, 5.0, 64).reshape(8, 8)

    def _do_open(self) -> None:
        pass

    def _do_close(self) -> None:
        pass

    def _apply_exposure(self, exposure_s: float) -> float:
        return exposure_s

    def _apply_gain(self, gain_db: float) -> float:
        return gain_db

    def _grab(self) -> np.ndarray:
        signal = self.ramp * self.exposure_s / self.REFERENCE_EXPOSURE_S * self.lit
        return np.rint(self.response.to_raw(np.clip(signal, 0.0, 1.0))).astype(np.uint16)


@dataclass
class Setup:
    camera: Camera
    light: Callable[[bool], None] | None  # switches the scene's light; None: the test cannot
    saturates: bool = False  # the lit scene drives part (not all) of the sensor to full scale


def slmsuite_setup() -> Iterator[Setup]:
    """slmsuite's simulated camera imaging slmsuite's simulated SLM (its far field) through
    nhfd's slmsuite backends; the light is the SLM's simulated illumination."""
    simulated = pytest.importorskip(
        "slmsuite.hardware.slms.simulated", reason="slmsuite is not installed: pip install "
        "'nhfd[slmsuite]'")
    from slmsuite.hardware.cameras.simulated import SimulatedCamera

    from nhfd.device_settings import SlmsuiteSettings
    from nhfd.drivers.slmsuite import SlmsuiteCamera

    n = 32
    device = simulated.SimulatedSLM((n, n), pitch_um=(8.0, 8.0))
    # A seeded random (diffuser) frame spreads the beam into speckle over the whole sensor;
    # with this gain the mean pixel is ~60 of 255 levels at 4 ms.
    device.set_phase(np.random.default_rng(5).integers(0, 256, (n, n), dtype=np.uint8))
    beam = device.source["amplitude_sim"].copy()
    camera = SlmsuiteCamera(CameraSettings(exposure_s=0.004), SlmsuiteSettings(),
                            device=SimulatedCamera(device, gain=15000.0))

    def light(on: bool) -> None:
        device.source["amplitude_sim"] = beam if on else 0 * beam

    with camera:
        yield Setup(camera, light)


@pytest.fixture(params=["ramp", "simulated", "slmsuite", "bench"])
def setup(request: pytest.FixtureRequest) -> Iterator[Setup]:
    if request.param == "ramp":
        camera = RampCamera(CameraSettings(exposure_s=0.004, response_gamma=2.2, bit_depth=10))

        def light(on: bool) -> None:
            camera.lit = on

        with camera:
            yield Setup(camera, light, saturates=True)
    elif request.param == "simulated":
        bench = TrueBench(zero_order_fraction=0.0)
        d = Config().devices
        with make_bench(d, 64, 64, bench=bench, roi=bench.roi_for_panel((64, 64))) as devices:
            frame = np.zeros((64, 64), np.uint8)
            frame[:, 32:] = 128  # a grey step diffracts light onto the sensor
            devices.slm.show(frame)
            laser = devices.laser

            def light(on: bool) -> None:
                if on:
                    laser.arm(60)
                    laser.set_power("green", 10.0)
                    laser.enable("green")
                else:
                    laser.disarm()

            yield Setup(devices.camera, light)
    elif request.param == "slmsuite":
        yield from slmsuite_setup()
    else:
        backend, (target, *rest) = bench_target(
            "NHFD_TEST_CAMERA", ("opencv", "genicam"), "opencv:0")
        if backend == "opencv":
            real: Camera = OpenCVCamera(CameraSettings(device=target))
        else:
            real = GenICamCamera(CameraSettings(cti_path=target,
                                                serial_number=rest[0] if rest else ""))
        with real:
            yield Setup(real, None)


def test_exposure_and_gain_are_set_and_read_back(setup):
    camera = setup.camera
    got = camera.set_exposure(0.002)
    assert got == pytest.approx(0.002, rel=0.05) and camera.exposure_s == got
    got = camera.set_gain(6.0)
    assert got == pytest.approx(6.0, abs=0.5) and camera.gain_db == got
    with pytest.raises(ValueError, match=r"exposure_s = -1\.0: must be in"):
        camera.set_exposure(-1.0)
    with pytest.raises(ValueError, match=r"gain_db = 49\.0: must be in \[0, 48\]"):
        camera.set_gain(49.0)
    assert camera.gain_db == got  # a refused value changes nothing


def test_a_capture_is_linear_float32_with_saturation_flagged(setup):
    camera = setup.camera
    if setup.light is not None:
        setup.light(True)
    cap = camera.capture(1, subtract_dark=False)
    assert cap.image.dtype == np.float32 and cap.saturated.dtype == np.bool_
    assert cap.saturated.shape == cap.image.shape and cap.frames == 1
    # Fractions of full scale: the top raw level, and only it, is 1.0 (saturated).
    assert float(cap.image.min()) >= 0.0 and float(cap.image.max()) <= 1.0
    assert (cap.image[cap.saturated] == 1.0).all() and (cap.image[~cap.saturated] < 1.0).all()
    if setup.saturates:
        assert cap.any_saturated and not cap.saturated.all()


def test_signal_above_dark_is_proportional_to_exposure(setup):
    if setup.light is None:
        pytest.skip("no switchable light on a real bench: linearity is checked on the set-ups "
                    "that have one")
    camera = setup.camera
    signals = []
    for exposure_s in (0.002, 0.004):
        camera.set_exposure(exposure_s)
        setup.light(False)
        camera.capture_dark(4)
        setup.light(True)
        signals.append(camera.capture(4))
    lit = ~(signals[0].saturated | signals[1].saturated)
    lit &= signals[0].image > 0.02  # well above the noise
    assert lit.sum() >= 8
    ratio = float(signals[1].image[lit].mean() / signals[0].image[lit].mean())
    assert ratio == pytest.approx(2.0, rel=0.05)


def test_a_closed_camera_captures_nothing(setup):
    camera = setup.camera
    camera.close()
    with pytest.raises(DeviceError, match="not open"):
        camera.capture()
    camera.open()
