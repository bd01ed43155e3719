"""The camera in the loop (`citl`, `nhfd.pipeline.refine`): the bench's devices show each step's
frame, capture it at the content's planes, and the images are mapped onto the SLM's pixel grid
through the calibration's geometry.

Laser safety: `CameraLoop` never arms and never sets a power. It captures only while a person's
arming holds, switching each colour on in turn at the power already set and off again after;
disarmed, expired or faulted, it stops with `CaptureStopped` before switching anything on, and
every colour is off on every way out of a capture (`finally`; should switching one off fail, the
laser's `all_off`, which zeroes the powers too).

`DaemonCameraLoop` is the same loop through a running daemon: its `capture_stack` job is the
daemon's citl capture sequence, under the same rules.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.calibration import Calibration
from nhfd.daemon.protocol import RpcError
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


class DaemonCameraLoop:
    """A `nhfd.pipeline.refine.Capture` through a running daemon (`nhfd serve` owns the devices),
    for `nhfd calib learn`: each call writes the K subframes into `work_dir` (which must lie
    inside the daemon's `daemon.paths.pattern_dirs`) and waits for a `capture_stack` job, the
    daemon's citl capture sequence (a held panel, the stage at each plane's focus through the
    daemon's calibration, each diode alone on at the power a person set, never arming, every
    diode off on every way out); the raw images it writes are mapped onto the window's SLM grid
    through `calibration`'s geometry, as `CameraLoop`'s are. `calibration` must be the one the
    daemon applies (its focus mapping moves the stage). A refusal or a failed job is
    `CaptureStopped` with the daemon's reason."""

    def __init__(self, client: Any, calibration: Calibration, encoder: Encoder,
                 work_dir: Path | str, *, camera_pitch_m: float, frames: int = 0,
                 job_timeout_s: float = 300.0, poll_s: float = 0.02) -> None:
        self.client, self.calibration, self.encoder = client, calibration, encoder
        self.work_dir = Path(work_dir).resolve()
        self.geometry = calibrated_geometry(calibration, camera_pitch_m)
        self.frames, self.job_timeout_s, self.poll_s = int(frames), job_timeout_s, poll_s
        self.captures = 0

    def _call(self, method: str, **params: Any) -> Any:
        try:
            return self.client.call(method, **params)
        except RpcError as exc:
            raise CaptureStopped(f"the daemon refused {method}: {exc.message}") from None

    def __call__(self, grey: np.ndarray, planes_m: Sequence[float]
                 ) -> tuple[np.ndarray, np.ndarray]:
        """As `CameraLoop.__call__`: the K subframes `grey` `[K, C, Hr, Wr]` uint8 captured at
        `planes_m` (m from the reference plane) -> (`[D, C, h, w]` on the window, the pixels
        the camera saw `[h, w]`)."""
        s, r = self.encoder.settings, self.encoder.region
        self.work_dir.mkdir(parents=True, exist_ok=True)
        shown, out = self.work_dir / "stack.npy", self.work_dir / "stack.npz"
        tmp = self.work_dir / ".stack.tmp.npy"
        np.save(tmp, np.ascontiguousarray(grey, np.uint8))
        tmp.replace(shown)
        out.unlink(missing_ok=True)  # never an older pattern's images
        params: dict[str, Any] = {
            "path": str(shown), "top": r.top, "left": r.left, "out": str(out),
            "z_m": [s.z0_m + s.refocus_m + float(dz) for dz in planes_m]}
        if self.frames:
            params["frames"] = self.frames
        job_id = self._call("capture_stack", **params)["job"]
        try:
            job = self.client.wait_job(job_id, self.job_timeout_s, self.poll_s)
        except RpcError as exc:
            raise CaptureStopped(f"the daemon refused job: {exc.message}") from None
        if job["state"] != "done":
            raise CaptureStopped(f"the daemon's capture_stack job {job_id} {job['state']}"
                                 + (f": {job['error']}" if job.get("error") else
                                    f" after {self.job_timeout_s:g} s"))
        images, saturated = read_stack(out, len(planes_m))
        self.captures += images.shape[0] * images.shape[1]
        return captured_window(images, saturated, self.geometry, self.encoder)


def read_stack(path: Path, planes: int) -> tuple[np.ndarray, np.ndarray]:
    """The images `[P, 3, Hc, Wc]` float32 and saturation (bool, the same shape) a
    `capture_stack` job wrote to `path`, checked: `planes` planes, finite, no pickles;
    CaptureStopped naming the file otherwise."""
    try:
        with np.load(path, allow_pickle=False) as z:
            images, saturated = z["images"], z["saturated"]
    except (OSError, ValueError, KeyError) as exc:
        raise CaptureStopped(f"{path}: not a capture_stack result ({exc})") from None
    if (images.dtype != np.float32 or images.ndim != 4 or images.shape[:2] != (planes, 3)
            or saturated.dtype != bool or saturated.shape != images.shape):
        raise CaptureStopped(f"{path}: images {images.dtype} {list(images.shape)}, saturation "
                             f"{saturated.dtype} {list(saturated.shape)}: expected float32 "
                             f"[{planes}, 3, H, W] and bool of that shape")
    if not np.isfinite(images).all():
        raise CaptureStopped(f"{path}: the images hold NaN or Inf")
    return images, saturated
