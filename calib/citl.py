"""The camera in the loop (`citl`, `nhfd.pipeline.refine`): the bench's devices show each step's
frame, capture it at the content's planes, and the images are mapped onto the SLM's pixel grid
through the calibration's geometry.

Laser safety: `CameraLoop` never arms and never sets a power. It captures only while a person's
arming holds, switching each colour on in turn at the power already set and off again after;
disarmed, expired or faulted, it stops with `CaptureStopped` before switching anything on, and
every colour is off on every way out of a capture (`finally`; should switching one off fail, the
laser's `all_off`, which zeroes the powers too).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from nhfd.calibration import Calibration
from nhfd.device_settings import COLOURS, citl_laser_refusal
from nhfd.drivers.camera import colour_planes
from nhfd.drivers.errors import DeviceError
from nhfd.optics.camera_grid import calibrated_geometry
from nhfd.pipeline.citl import captured_window
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.refine import CaptureStopped


class CameraLoop:
    """A `nhfd.pipeline.refine.Capture` over the bench's devices (`BenchDevices`: SLM, laser,
    stage, camera), the calibration that maps focus to the stage and the camera onto the SLM,
    and the encoder whose region the frames fill (the rest of the panel shows its zero
    pattern). Each call: per plane, the stage at the plane's focus; per colour (the camera is
    mono; a colour camera's own channel is read), that diode alone on at its set power; the K
    subframes shown in turn, their images averaged (one exposure spanning K flips); the dark
    frame subtracted. `frames`: images averaged per capture."""

    def __init__(self, devices: Any, calibration: Calibration, encoder: Encoder, *,
                 frames: int = 1) -> None:
        missing = [n for n in ("slm", "laser", "stage", "camera")
                   if getattr(devices, n, None) is None]
        if missing:
            raise ValueError(f"quality = 'citl' needs the bench's {', '.join(missing)} "
                             f"(devices.{missing[0]} = 'none')")
        self.devices = devices
        self.calibration = calibration
        self.encoder = encoder
        self.frames = int(frames)
        self.geometry = calibrated_geometry(calibration,
                                            devices.camera.settings.pixel_pitch_um * 1e-6)
        self.dark: np.ndarray | None = None
        self.captures = 0
        stage = devices.stage
        if stage.settings.require_homed and not stage.state().homed:
            stage.home()

    def _check_laser(self) -> dict[str, float]:
        status = self.devices.laser.status()
        powers = {name: float(status.channels[name].power_pct) for name in COLOURS}
        refusal = citl_laser_refusal(status.fault, status.armed, status.armed_remaining_s,
                                     powers)
        if refusal:
            raise CaptureStopped(refusal)
        return powers

    def _lights_out(self) -> None:
        """Every colour switched off, each read back, keeping the powers a person set; if that
        fails, `all_off` (powers to 0 as well), and the error goes on."""
        laser = self.devices.laser
        try:
            for name in COLOURS:
                laser.enable(name, False)
        except BaseException:
            laser.all_off()
            raise

    def _panel(self, grey: np.ndarray) -> np.ndarray:
        r = self.encoder.region
        panel = self.encoder.zero.copy()
        panel[:, r.top : r.top + r.height, r.left : r.left + r.width] = grey
        return panel

    def __call__(self, grey: np.ndarray, planes_m: Sequence[float]
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Show the K subframes `grey` `[K, C, Hr, Wr]` uint8 (the encoder's region) and capture
        them at each plane of `planes_m` (m, SLM space, from the reference plane): (intensities `[D,
        C, h, w]` float32 on the window's SLM pixel grid, dark subtracted, any units; the pixels the
        camera saw `[h, w]` bool). CaptureStopped when the lasers are not armed, the arming expired,
        a fault latched or a device failed."""
        d = self.devices
        grey = np.asarray(grey, np.uint8)
        self._check_laser()  # before anything moves or emits
        panels = [self._panel(g) for g in grey]
        s = self.encoder.settings

        def at_plane(i: int) -> None:
            d.stage.move_to(self.calibration.stage_mm_for(s.z0_m + s.refocus_m
                                                          + float(planes_m[i])))

        def show(k: int, _name: str) -> None:
            d.slm.show(panels[k])
            d.slm.wait_settled()

        def light(name: str, on: bool) -> None:
            try:
                d.laser.enable(name, on)
            except DeviceError as exc:  # NotArmed, a fault: nothing was switched on
                if on:
                    raise CaptureStopped(f"{name} could not be switched on: {exc}") from exc
                raise

        def capture() -> Any:
            self.captures += 1
            return d.camera.capture(self.frames)

        try:
            if self.dark is None:
                self._lights_out()
                self.dark = d.camera.capture_dark(self.frames)
            images, saturated = colour_planes(
                len(planes_m), len(panels), at_plane=at_plane,
                before_colour=lambda _name: self._check_laser(), show=show, light=light,
                capture=capture)
        finally:
            self._lights_out()
        return captured_window(images, saturated, self.geometry, self.encoder)
