"""The daemon's half of the camera in the loop (`citl`): one refinement step's captures on the
bench, for the frame worker that optimises (`nhfd.pipeline.citl`); the same sequence serves a
client's focal-stack captures (`capture_stack`, for `nhfd calib learn`).

`citl_capture` runs as a bench job. It holds the panel, and captures plane by plane (the stage
at the calibration's focus for each). For each colour that has power, it switches that diode
alone on, shows each of the step's K subframes as the colour's pattern (`Panel.show_colour`, as
the capture-mode snapshot does), captures, and switches the diode off. It answers the raw camera
images; the worker maps them onto the SLM's grid (the daemon imports no optics).

Laser safety: it never arms and never sets a power. Before anything moves or emits, and before
each colour, it reads the arming (the guardian's last heartbeat) and stops with a `CitlStopped`
naming why when the lasers are disarmed, expired or faulted. The run belongs to the emission
session of its view's request (`nhfd.daemon.guardian_link`): once a laser off, disarm, stop or
shutdown has ended that session it switches nothing on (checked under the lock the off takes),
a capture it had under way does not count, and a later arm never resumes it. Every colour is
off on every way out (`finally`, each read back by the guardian), and every switch-on is in the
audit log.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from nhfd.calibration import CalibrationStore
from nhfd.config import Config
from nhfd.device_settings import COLOURS, citl_laser_refusal
from nhfd.drivers.camera import colour_planes
from nhfd.frame_message import CaptureReply, CaptureRequest

from .audit import AuditLog
from .colour import CaptureBench, CapturePanel, ShownViews, diodes_in_turn
from .frame_link import PanelBuffer
from .guardian_link import LaserLink
from .jobs import Job


class CitlStopped(RuntimeError):
    """The bench cannot capture this step; the message says why (the worker's refinement stops
    with it and keeps its best frame)."""


def citl_ended(reason: str) -> str:
    """What a citl run ended with its emission session says (`reason`: what ended it, e.g.
    "lasers off by uid 1000 (ana) on the Unix socket")."""
    return (f"{reason}: this citl run has ended and does not resume; ask for quality citl "
            "again once the lasers are armed")


def citl_problem(config: Config, calibration: CalibrationStore, bench: Any,
                 what: str = "citl") -> str | None:
    """Why this daemon cannot serve `citl` views, or `what` else captures focal stacks with
    `citl_capture` (None: it can): the colour mode, the devices and the calibration it needs
    (in `calibration`), each named by its setting."""
    if config.daemon.frames.colour_mode != "capture":
        return (f"daemon.frames.colour_mode is {config.daemon.frames.colour_mode!r}: {what} "
                "needs 'capture' (the daemon switches each diode on alone for its captures)")
    for name in ("slm", "stage", "camera"):
        if getattr(bench, name, None) is None:
            why = bench.errors.get(name) if hasattr(bench, "errors") else None
            return f"{what} needs the bench's {name} (devices.{name}: {why or 'none configured'})"
    if calibration.active() is None:
        return (f"{what} needs a calibration (calibration.file): it maps the camera onto the "
                "SLM and the focus onto the stage")
    return None


def _check_laser(laser: LaserLink, what: str) -> dict[str, float]:
    """The powers a person set, per colour, while the arming holds; CitlStopped otherwise."""
    status = laser.status()
    channels = status.get("channels") or {}
    powers = {ch: float(channels.get(ch, {}).get("power_pct", 0.0)) for ch in COLOURS}
    refusal = citl_laser_refusal(status.get("fault"), bool(status.get("armed")),
                                 float(status.get("armed_remaining_s") or 0.0), powers, what)
    if refusal:
        raise CitlStopped(refusal)
    return powers


def citl_capture(job: Job, request: CaptureRequest, *, config: Config,
                 calibration: CalibrationStore, bench: CaptureBench,
                 panel: CapturePanel, laser: LaserLink, audit: AuditLog, shown: ShownViews,
                 wanted: Callable[[], bool], session: int,
                 phase: Callable[[str], None] = lambda _what: None,
                 what: str = "citl") -> CaptureReply:
    """One citl step's captures (see the module's docstring): images `[P, C, Hc, Wc]` float32
    (the subframes' mean per plane and colour, the stored dark frame subtracted) and their
    saturation. `wanted()` turns false when the worker moved on (a new view): the sequence stops
    between captures. `session`: the emission session of the view's request (EmissionEnded once
    it has ended). `phase(what)`: where the sequence is ("capturing green at plane 2 of 3"), for
    `status`. `what`: the run's name in the audit log and the refusals ("citl", "focal-stack
    capture"). Raises CitlStopped (or the device's error) without an answer to give."""
    laser.check_session(session)
    problem = citl_problem(config, calibration, bench, what)
    if problem:
        raise CitlStopped(problem)
    cal = calibration.active()
    assert cal is not None  # citl_problem checked it
    camera, stage = bench.camera, getattr(bench, "stage", None)
    # Homing moves the stage to a limit switch: the daemon does it only when asked.
    if stage.settings.require_homed and not stage.state().homed:
        raise CitlStopped("the stage is not homed: home it first (nhfctl focus Z_MM --home)")
    laser.refresh()
    powers = _check_laser(laser, what)  # before anything moves or emits
    r = request.region
    frames = request.frames or None
    buffer = PanelBuffer(panel.blank_frame())
    panels = [buffer.frame(r.top, r.left, g) for g in request.grey]
    planes = len(request.z_m)
    where = {"plane": 0}

    def go_on() -> None:
        job.check()
        laser.check_session(session)
        if not wanted():
            raise CitlStopped("the view changed: its refinement was cancelled")

    def before_colour(name: str) -> None:
        go_on()
        _check_laser(laser, what)
        phase(f"capturing {name} at plane {where['plane'] + 1} of {planes}")

    def at_plane(i: int) -> None:
        go_on()
        where["plane"] = i
        phase(f"moving the stage to plane {i + 1} of {planes}")
        stage.move_to(cal.stage_mm_for(request.z_m[i]))

    def capture() -> Any:
        cap = bench.capture(frames)
        laser.check_session(session)  # cut short by a laser off: not a capture to fit
        return cap

    with diodes_in_turn(job, what, powers, panel=panel, laser=laser, audit=audit,
                        shown=shown, session=session) as light:
        for ch in COLOURS:
            laser.enable(ch, False)
        phase("dark frame")
        camera.capture_dark(frames)
        images, saturated = colour_planes(
            planes, len(panels), at_plane=at_plane, before_colour=before_colour,
            show=lambda k, ch: panel.show_colour(panels[k], ch), light=light, capture=capture)
    laser.check_session(session)
    return CaptureReply(images, saturated)
