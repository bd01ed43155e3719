"""The bench's non-laser devices for the daemon: SLM (what it shows: `panel`), stage, camera;
the focus mapping without calibration.

A device that fails to open is recorded (its error shows in `status`) and left out; the daemon
still starts, because the lasers are held off by the guardian regardless. A monitor thread
refreshes the stage state and the SLM's health for `status`, so a slow or vanished device never
stalls the control loop that sends the laser heartbeat.

Faults and the light path: an SLM whose output is lost (cable unplugged, output disabled) no
longer shows what the daemon computed, so the lasers must go off. The monitor only *notices*
(it must not talk to the laser guardian: the control loop owns that link); it queues the change
in `faults`, and the control loop switches the lasers off (the daemon's device faults). The stage
and the camera sit on the detection side: their faults fail jobs and show in `status`, the
lasers stay as they are. Every fault clears when the device answers again.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from types import SimpleNamespace
from typing import Any

from nhfd.calibration import CalibrationStore
from nhfd.config import Config
from nhfd.drivers import factory

from .panel import Panel

log = logging.getLogger("nhfd.daemon.bench")


def focus_stage_mm(z_mm: float, stage_at_reference_mm: float) -> float:
    """The documented default mapping without calibration: the camera sees the reference plane
    at `stage_at_reference_mm`, and one mm of hologram depth is one mm of stage travel."""
    return stage_at_reference_mm + z_mm


def stage_mm_for_focus(config: Config, calibration: CalibrationStore, z_mm: float) -> float:
    """The stage position (mm) that focuses the camera `z_mm` of hologram depth from the
    reference plane: the active calibration's fitted mapping (green's focus) when there is
    one, else `focus_stage_mm` from `daemon.bench.stage_at_reference_mm`. A configured
    calibration that cannot be applied raises its `CalibrationFileError`. `config`:
    `optics.z0_m` and the uncalibrated mapping."""
    cal = calibration.active()
    if cal is not None:
        return cal.stage_mm_for(config.optics.z0_m + z_mm * 1e-3, 1)
    return focus_stage_mm(z_mm, config.daemon.bench.stage_at_reference_mm)


class Bench:
    """The SLM (through its `panel`), the stage and the camera, opened by `open`; a device
    that fails to open is left None with its error in `errors`."""

    def __init__(self, config: Config, calibration: CalibrationStore) -> None:
        """`config`: the devices (`[devices]`) at the panel's size and pitch (`[slm]`); the
        camera region (`daemon.bench.camera_roi_px`); the panel's colour mode and coding (its
        `Panel` reads `[daemon.frames]`, `[slm]` and `calibration`'s curves)."""
        self.config = config
        self.laser_twin: Any = None  # the guardian's simulated laser, for the simulated camera
        self.slm: Any = None
        self.stage: Any = None
        self.camera: Any = None
        self.errors: dict[str, str | None] = {"slm": None, "stage": None, "camera": None}
        self._stage_state: dict[str, Any] = {}
        self._slm_health: dict[str, Any] = {}
        # SLM output lost / back, for the control loop: (device, lost, detail).
        self.faults: queue.SimpleQueue[tuple[str, bool, str]] = queue.SimpleQueue()
        self.slm_lost: str | None = None  # why the SLM's output is lost, while it is
        # what the SLM shows: every change goes through it
        self.panel = Panel(config, self, calibration)
        self._stop = threading.Event()
        self._monitor: threading.Thread | None = None
        self._reconnect: threading.Thread | None = None

    # -- open / close --------------------------------------------------------------------------

    def open(self, laser_twin: Any = None) -> None:
        """Open the devices (the SLM first, showing the blank), then start the monitor.
        `laser_twin`: the guardian's simulated laser (`LaserLink.twin`), which the simulated
        camera images; None otherwise."""
        # The guardian owns the laser port: the bench builds no laser driver, and the simulated
        # camera reads the guardian's twin. A device that fails is reported and left None.
        self.laser_twin = laser_twin
        devices = factory.make_bench(
            self.config.devices, self.config.slm.width_px, self.config.slm.height_px,
            laser=False, laser_twin=self.laser_twin, on_open=self._opened, on_error=self._failed,
            pitch_um=self.config.slm.pitch_um)
        self.slm, self.stage, self.camera = devices.slm, devices.stage, devices.camera
        self._apply_camera_roi()
        self._refresh()  # status has the stage's state from the first request on
        self._monitor = threading.Thread(target=self._watch, name="nhfd-bench-monitor",
                                         daemon=True)
        self._monitor.start()

    def _apply_camera_roi(self) -> None:
        """Give the simulated camera the configured sensor region (daemon.bench.camera_roi_px): the
        camera is rebuilt, because its fixed-pattern noise is drawn for its region at
        creation."""
        roi = list(self.config.daemon.bench.camera_roi_px)
        if not roi or self.camera is None or self.config.devices.camera != "simulated":
            return
        with contextlib.suppress(Exception):
            self.camera.close()
        camera = factory.make_camera(self.config.devices, slm=self.slm,
                                     laser=SimpleNamespace(twin=self.laser_twin),
                                     stage=self.stage, roi=tuple(roi))
        if camera is not None:
            camera.open()
        self.camera = camera

    def _opened(self, device: str, driver: Any) -> None:
        if device == "slm":
            self.slm = driver
            self.panel.blank()  # before the stage and camera open

    def _failed(self, device: str, exc: Exception) -> None:
        self.errors[device] = f"{type(exc).__name__}: {exc}"
        log.error("%s: %s", device, self.errors[device])

    def close(self) -> None:
        """Stop the monitor, then close the camera, the stage and the SLM (blank first)."""
        self._stop.set()
        if self._monitor is not None:
            self._monitor.join(2.0)
        if self._reconnect is not None:  # a stage reconnect in its backoff: not for long
            self._reconnect.join(1.0)
        for name in ("camera", "stage", "slm"):
            device = getattr(self, name)
            if device is None:
                continue
            try:
                if name == "slm":
                    self.panel.blank()  # leave the panel showing nothing
                device.close()
            except Exception as exc:
                log.warning("%s close: %s", name, exc)

    # -- actions -------------------------------------------------------------------------------

    def capture(self, frames: int | None = None) -> Any:
        """One camera capture; a failure (a timeout) is the camera's error in `status` until a
        capture succeeds again."""
        if self.camera is None:
            raise RuntimeError(self.errors["camera"] or "no camera configured")
        try:
            cap = self.camera.capture(frames)
        except Exception as exc:
            self.errors["camera"] = f"{type(exc).__name__}: {exc}"
            raise
        self.errors["camera"] = None
        return cap

    def note_slm_lost(self, detail: str) -> None:
        """The SLM's output is gone (from the monitor, or a failed show): queue it once."""
        if self.slm_lost is None:
            self.slm_lost = detail
            self.errors["slm"] = f"output lost: {detail}"
            log.error("SLM output lost: %s", detail)
            self.faults.put(("slm", True, detail))

    def stop_stage(self) -> str:
        """Stop the stage at once (from any thread): "stop sent", or "no stage"."""
        if self.stage is None:
            return "no stage"
        self.stage.stop(immediate=True)  # the driver: safe from any thread at any time
        return "stop sent"

    # -- monitor -------------------------------------------------------------------------------

    def _watch(self) -> None:
        while not self._stop.wait(0.2):
            self._refresh()

    def _refresh(self) -> None:
        # The SLM first: it is the light path's check, and a stage reconnect never delays it.
        if self.slm is not None:
            try:
                h = self.slm.health()
                ok, detail = h.ok, h.detail
            except Exception as exc:
                ok, detail = False, f"health check failed: {type(exc).__name__}: {exc}"
            self._slm_health = {"ok": ok, "detail": detail, "checked_s": time.time()}
            if not ok:
                self.note_slm_lost(detail)
            elif self.slm_lost is not None:
                log.warning("SLM output back (was: %s)", self.slm_lost)
                self.slm_lost = None
                self.errors["slm"] = None
                self.faults.put(("slm", False, detail))
        if self.stage is not None and not (self._reconnect and self._reconnect.is_alive()):
            try:
                st = self.stage.state()
                self._stage_state = {"position_mm": st.position_mm, "homed": st.homed,
                                     "moving": st.moving or self.stage.moving,
                                     "at_limit": st.at_limit,
                                     "motion_error": st.motion_error}
                self.errors["stage"] = None
            except Exception as exc:
                # A vanished port: say so at once, then try to come back (same serial only) on
                # a thread of its own: the reconnect backs off for seconds.
                self.errors["stage"] = f"{type(exc).__name__}: {exc}; reconnecting"
                self._stage_state = {}
                self._reconnect = threading.Thread(target=self._reconnect_stage, args=(exc,),
                                                   name="nhfd-stage-reconnect", daemon=True)
                self._reconnect.start()

    def _reconnect_stage(self, why: Exception) -> None:
        try:
            self.stage.reconnect()
            log.warning("stage: link back after: %s", why)
        except Exception as again:
            self.errors["stage"] = f"{type(again).__name__}: {again}"

    def status(self) -> dict[str, Any]:
        """`status.devices`: each device's backend, whether it is open, its state and error."""
        d = self.config.devices
        return {
            "slm": {"backend": d.slm, "open": self.slm is not None, "showing": self.panel.showing,
                    "health": self._slm_health, "error": self.errors["slm"]},
            "stage": {"backend": d.stage, "open": self.stage is not None, **self._stage_state,
                      "error": self.errors["stage"]},
            "camera": {"backend": d.camera, "open": self.camera is not None,
                       "error": self.errors["camera"]},
        }
