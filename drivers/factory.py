"""Build each device's driver from the configuration's `[devices]` section.

`[devices]` names a backend per device; "simulated" is the default everywhere. A simulated laser
or stage is the *real* driver talking to its twin on a pseudo-terminal (`MecomLaser` +
`MecomTwin`, `AptStage` + `AptTwin`), built from the same settings as the real device, caps and
soft limits included; closing the driver also stops its twin. The simulated camera images what
the simulated SLM shows, lit by the laser twin's emission, at the stage twin's position.

Nothing is opened here: the caller opens (which identifies, and for lasers switches everything
off) and closes. `devices` is `nhfd.config.DeviceSettings` (duck-typed, so this module imports
nothing outside `nhfd.drivers`); SLM geometry comes from `[slm]`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

from nhfd.device_settings import COLOURS, LaserSettings, StageSettings

from .camera import Camera, GenICamCamera, OpenCVCamera
from .framebuffer import FramebufferSLM
from .laser import Laser, MecomLaser
from .navigator import Navigator, SimulatedNavigator, SpaceMouseNavigator, Waypoint
from .slm import SLM, SimulatedSLM
from .slmsuite import SlmsuiteCamera, SlmsuiteSLM
from .stage import AptStage, Stage
from .trigger import TriggerLine
from .twins.apt_twin import AptTwin
from .twins.clock import Clock
from .twins.mecom_twin import MecomTwin
from .window import WindowSLM


class SimulatedLaser(MecomLaser):
    """The READYBeam driver on a `MecomTwin` it owns: `twin` holds the emission record."""

    def __init__(self, settings: LaserSettings, *, clock: Clock = time.monotonic) -> None:
        self.twin = MecomTwin(device_type=settings.device_type, address=settings.address,
                              channel_instances=settings.channel_instances,
                              parameter_ids=settings.parameter_ids, clock=clock)
        self.twin.start()
        super().__init__(settings, self.twin.opener(), clock=clock)

    def close(self) -> None:
        """Close the driver (all channels off, read back), then stop the twin, even when off could
        not be confirmed."""
        try:
            super().close()
        finally:
            self.twin.close()


class SimulatedStage(AptStage):
    """The APT driver on an `AptTwin` it owns (a KDC101 with the settings' serial number),
    homing at the settings' `velocity_mm_s` (a real controller's homing velocity is its own
    parameter, which the driver leaves as it is)."""

    def __init__(self, settings: StageSettings, *, clock: Clock = time.monotonic) -> None:
        serial = int(settings.usb_serial) if settings.usb_serial.isdigit() else 27000001
        self.twin = AptTwin(serial_number=serial, model=settings.allowed_models[0][:8],
                            channel=settings.channel, counts_per_mm=settings.counts_per_mm,
                            time_unit_s=settings.time_unit_s,
                            home_velocity_mm_s=settings.velocity_mm_s, clock=clock)
        self.twin.start()
        super().__init__(settings, self.twin.opener())

    def close(self) -> None:
        """Close the driver, then stop the twin."""
        try:
            super().close()
        finally:
            self.twin.close()


def _require_port(entry: str, settings: LaserSettings | StageSettings) -> None:
    if not (settings.port or settings.usb_serial):
        raise ValueError(f"devices.{entry}: set usb_serial (better: `nhfd devices` lists it) or "
                         "port to use the real device")


def make_laser(devices: Any, *, clock: Clock = time.monotonic) -> Laser | None:
    """The laser driver `[devices].laser` names (None for "none"), not opened; ValueError when
    "readybeam" has neither port nor usb_serial, or the backend is unknown."""
    backend, settings = devices.laser, devices.readybeam
    if backend == "none":
        return None
    if backend == "readybeam":
        _require_port("readybeam", settings)
        return MecomLaser(settings, clock=clock)
    if backend == "simulated":
        return SimulatedLaser(settings, clock=clock)
    raise ValueError(f"devices.laser = {backend!r}: no such backend")


def make_stage(devices: Any, *, clock: Clock = time.monotonic) -> Stage | None:
    """The stage driver `[devices].stage` names (None for "none"), not opened; ValueError when "apt"
    has neither port nor usb_serial, or the backend is unknown."""
    backend, settings = devices.stage, devices.apt
    if backend == "none":
        return None
    if backend == "apt":
        _require_port("apt", settings)
        return AptStage(settings)
    if backend == "simulated":
        return SimulatedStage(settings, clock=clock)
    raise ValueError(f"devices.stage = {backend!r}: no such backend")


def make_slm(devices: Any, width_px: int, height_px: int, *,
             clock: Callable[[], float] = time.monotonic,
             pitch_um: float | None = None) -> SLM | None:
    """`pitch_um` ([slm]'s) is checked against a backend that knows its own (slmsuite)."""
    backend, settings = devices.slm, devices.slm_output
    if backend == "none":
        return None
    if backend == "simulated":
        return SimulatedSLM(width_px, height_px, settings, clock=clock)
    if backend == "framebuffer":
        return FramebufferSLM(width_px, height_px, settings, clock=clock)
    if backend == "window":
        return WindowSLM(width_px, height_px, settings, clock=clock)
    if backend == "slmsuite":
        return SlmsuiteSLM(width_px, height_px, settings, devices.slmsuite, pitch_um=pitch_um,
                           clock=clock)
    raise ValueError(f"devices.slm = {backend!r}: no such backend")


def make_navigator(devices: Any, trajectory: Sequence[Waypoint] = (), *,
                   clock: Callable[[], float] = time.monotonic) -> Navigator | None:
    """`trajectory` scripts the simulated navigator (empty: the puck rests)."""
    backend, settings = devices.navigator, devices.spacemouse
    if backend == "none":
        return None
    if backend == "spacemouse":
        return SpaceMouseNavigator(settings, clock=clock)
    if backend == "simulated":
        return SimulatedNavigator(trajectory, settings, clock=clock)
    raise ValueError(f"devices.navigator = {backend!r}: no such backend")


def make_camera(
    devices: Any,
    *,
    slm: SLM | None = None,
    laser: Laser | None = None,
    stage: Stage | None = None,
    bench: Any = None,
    roi: tuple[int, int, int, int] | None = None,
) -> Camera | None:
    """The configured camera. The simulated one needs the simulated SLM, laser and stage it
    watches (their twins are the bench's truth); `bench` is a `TrueBench` (default: its own).
    When `slm`'s flip output is wired (`slm.trigger`), the camera's trigger input is on it."""
    camera = _make_camera(devices, slm=slm, laser=laser, stage=stage, bench=bench, roi=roi)
    line = getattr(slm, "trigger", None)
    if camera is not None and line is not None:
        camera.trigger = line
    return camera


def _make_camera(devices: Any, *, slm: SLM | None, laser: Laser | None, stage: Stage | None,
                 bench: Any, roi: tuple[int, int, int, int] | None) -> Camera | None:
    backend, settings = devices.camera, devices.camera_settings
    if backend == "none":
        return None
    if backend == "opencv":
        return OpenCVCamera(settings)
    if backend == "genicam":
        return GenICamCamera(settings)
    if backend == "slmsuite":
        return SlmsuiteCamera(settings, devices.slmsuite,
                              slm=slm if isinstance(slm, SlmsuiteSLM) else None)
    if backend == "simulated":
        twin_laser = getattr(laser, "twin", None)
        twin_stage = getattr(stage, "twin", None)
        if slm is None or twin_laser is None or twin_stage is None:
            raise ValueError(
                "devices.camera = 'simulated' images the simulated bench: it needs the simulated "
                "SLM, laser and stage (devices.slm, .laser and .stage = 'simulated')"
            )
        # The one lazy import here: the simulated camera images through the optics core
        # (torch), and the daemon imports this module while it must stay torch-free.
        from .simcamera import SimulatedCamera, slm_frame_source

        def powers() -> list[float]:
            emitting = twin_laser.emitting()
            return [emitting[colour] / 100.0 for colour in COLOURS]

        return SimulatedCamera(
            slm_frame_source(slm), powers, lambda: twin_stage.position_mm, bench, settings,
            roi=roi,
        )
    raise ValueError(f"devices.camera = {backend!r}: no such backend")


@dataclass
class BenchDevices:
    """The devices of one bench, each None where `[devices]` says "none" (or it failed)."""

    slm: SLM | None = None
    laser: Laser | None = None
    stage: Stage | None = None
    camera: Camera | None = None

    def close(self) -> None:
        """Close every device, the camera first and the laser last (its close switches every
        channel off with read-back); every close is tried even if one raises, and the first
        error is raised after."""
        first: BaseException | None = None
        for name in ("camera", "stage", "slm", "laser"):
            device = getattr(self, name)
            if device is None:
                continue
            try:
                device.close()
            except BaseException as exc:
                first = first or exc
        if first is not None:
            raise first

    def __enter__(self) -> BenchDevices:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def make_bench(
    devices: Any,
    width_px: int,
    height_px: int,
    *,
    laser: bool = True,
    laser_twin: MecomTwin | None = None,
    bench: Any = None,
    roi: tuple[int, int, int, int] | None = None,
    clock: Clock = time.monotonic,
    on_open: Callable[[str, Any], None] | None = None,
    on_error: Callable[[str, Exception], None] | None = None,
    pitch_um: float | None = None,
) -> BenchDevices:
    """Build and open the configured bench in the order that wires it: SLM, laser, stage, then
    the camera that (when simulated) watches them. The one place a bench is assembled: the
    daemon, the benchmarks and the tests call it.

    `laser=False` leaves the laser to somebody else (the daemon's guardian owns the port);
    `laser_twin` is then the twin the simulated camera reads the emission from. `bench` and
    `roi` are the simulated camera's `TrueBench` and sensor region. `on_open(name, device)` runs
    right after each device opens (the daemon blanks the SLM before anything else opens).
    Without `on_error` a failure closes what was opened and raises; with it, the failing device
    is reported as `on_error(name, exc)`, left None, and the rest of the bench is still built.
    `pitch_um` is [slm]'s, checked against an slmsuite SLM's own.

    `[devices.trigger]` wires the SLM's flip output to the camera's trigger input
    (drivers/trigger.py): the SLM holds the `TriggerLine`, and a camera made to watch it
    (`make_camera`, here or when the daemon rebuilds it) takes it. It is modelled on the
    simulated SLM, the only one whose flip this process sees. `source = "camera_exposure"` is
    the same `TriggerLine` carrying the simulated camera's exposure-active output to the SLM's
    writes, which wait for it to fall.
    """
    trigger = getattr(devices, "trigger", None)
    if trigger is not None and trigger.source != "none" and devices.slm != "simulated":
        raise ValueError(
            f"devices.trigger.source = {trigger.source!r} needs devices.slm = 'simulated' (its "
            f"flip output is modelled); with devices.slm = {devices.slm!r} set source = 'none'")
    if trigger is not None and trigger.source == "camera_exposure" and \
            devices.camera != "simulated":
        raise ValueError(
            f"devices.trigger.source = 'camera_exposure' needs devices.camera = 'simulated' (its "
            f"exposure-active output is modelled); with devices.camera = {devices.camera!r} set "
            "source = 'none'")
    out = BenchDevices()

    def build(name: str, make: Callable[[], Any]) -> None:
        try:
            device = make()
            if device is None:
                return
            setattr(out, name, device)
            device.open()
            if on_open is not None:
                on_open(name, device)
        except Exception as exc:
            if on_error is None:
                # Everything built so far, the failed device too (a simulated one owns a twin).
                with contextlib.suppress(Exception):
                    out.close()
                raise
            setattr(out, name, None)
            on_error(name, exc)

    line = TriggerLine.from_settings(trigger, clock=clock) if trigger is not None else None

    def slm_with_trigger() -> SLM | None:
        slm = make_slm(devices, width_px, height_px, clock=clock, pitch_um=pitch_um)
        if slm is not None and line is not None:
            slm.attach_trigger(line)  # before it opens: the first frame's flip is on the line
        return slm

    build("slm", slm_with_trigger)
    if laser:
        build("laser", lambda: make_laser(devices, clock=clock))
        laser_twin = laser_twin or getattr(out.laser, "twin", None)
    build("stage", lambda: make_stage(devices, clock=clock))
    build("camera", lambda: make_camera(devices, slm=out.slm,
                                        laser=SimpleNamespace(twin=laser_twin),
                                        stage=out.stage, bench=bench, roi=roi))
    return out
