"""The RPC methods. Each reads and checks all its parameters first (`Params.done()`), then acts,
so a bad request changes nothing.

  status       {}                                     -> devices, laser, scene, model, view, jobs
  set_view     {orbit|pose|relative: {...}, refocus_mm?, quality?} -> {seq, view}
  focus        {z_mm, home?}                          -> {job, stage_mm}
  laser        {action: arm|disarm|off|power|enable|disable, duration_s?, channel?, power_pct?}
  stop         {}                                     -> jobs cancelled, stage stop sent
  blank        {}                                     -> the zero-amplitude pattern is shown
  snapshot     {path?, frames?}                       -> {job, path} (colour_mode "capture":
                                                         one capture per colour, see colour.py)
  show_pattern {path}                                 -> {showing, shape} a calibration frame
                                                         (.npy uint8 [3, H, W], [H, W, 3] or
                                                         [H, W], the panel's size, inside
                                                         daemon.paths.pattern_dirs) instead of the
                                                         view until the next set_view / blank
  stage_move   {position_mm, home?}                   -> {job, stage_mm} raw stage move (no
                                                         calibration mapping), soft limits
  capture      {path, frames?, exposure_s?, dark?}    -> {job, path}: a linear float32 image
                                                         (.npy, dark subtracted; dark: true
                                                         captures and stores the dark frame,
                                                         lasers off) and its saturation mask
                                                         (<stem>.saturated.npy), inside
                                                         daemon.paths.pattern_dirs or snapshot_dir
  capture_stack {path, top, left, z_m, out, frames?}  -> {job, path}: K subframes (.npy uint8
                                                         [K, 3, h, w] inside pattern_dirs) shown
                                                         at (top, left) and captured at each
                                                         depth z_m (m from the SLM; the
                                                         calibration's focus) with each diode on
                                                         alone, as citl's steps (colour_mode
                                                         "capture"; never arms); out: a .npz of
                                                         images [P, 3, Hc, Wc], saturated, z_m
  load_scene   {path}                                 -> {job}
  load_model   {path}                                 -> {job} (old model kept on failure)
  job          {id}                                   -> one job's state
  preview      {source: slm|camera, max_px?}          -> read-only: the SLM's last frame or the
                                                         last capture, every k-th pixel so the
                                                         longest side is at most max_px, as
                                                         uint8 pixels (base64, [H, W, C]), for
                                                         the web view's thumbnails
  auth         {token}                                -> TCP connections only
  web_client   {address, tls?, token_file?}           -> the web view (this process only) names
                                                         the web client its next requests on
                                                         this connection come from (audit)
  shutdown     {}                                     -> lasers off, devices closed, exit

`stop`, `blank` and laser `off`/`disarm` act on the control loop directly: they never wait
behind a job.
"""

from __future__ import annotations

import base64
import hmac
import itertools
import math
import os
import time
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from nhfd.calibration import CalibrationFileError, CalibrationStore
from nhfd.config import MAX_PLANES, MAX_SUBFRAMES, Config
from nhfd.device_settings import COLOURS
from nhfd.frame_message import CaptureRequest, Region
from nhfd.scene.io import SCENE_NAMES, SCENE_SUFFIXES, is_sog_folder
from nhfd.worker_messages import ModelLoaded, SceneLoaded

from .arming import ArmingGate
from .audit import AuditLog
from .bench import Bench, stage_mm_for_focus
from .citl import citl_capture, citl_problem
from .colour import ShownViews, capture_colours, check_laser_command
from .guardian_link import LaserLink
from .jobs import Job, JobRunner, submit_or_busy
from .panel import Panel
from .paths import inside
from .png import write_png16, write_preview8
from .protocol import (
    DEVICE_ERROR,
    FORBIDDEN,
    INVALID_FILE,
    LASER_REFUSED,
    NO_SUCH_JOB,
    NOT_AVAILABLE,
    UNAUTHORIZED,
    Params,
    RpcError,
    bad_param,
)
from .scene_check import read_scene_counts
from .server import Connection
from .views import ViewSlot, parse_view


class Frames(ShownViews, Protocol):
    """The frame worker as the methods see it: the last frame shown, the model it serves, and
    loads (which block the calling load job until the worker answers)."""

    model_path: str | None
    subframes_shown: int  # K subframes taking turns on the panel, one per refresh (1: still)
    refresh_s: float  # the panel's refresh period

    def load_scene(self, path: str) -> SceneLoaded:
        """Load the scene file at `path` into the worker, blocking until it answers: the scene's
        counts, centre and up axis; raises with the worker's reason."""
        ...

    def load_model(self, path: str) -> ModelLoaded:
        """Load the model file at `path` into the worker, blocking until it answers: the model's
        information; raises with the worker's reason."""
        ...


@dataclass
class RpcContext:
    """What the RPC methods act on, given explicitly: the daemon builds one at construction
    from its parts (`Daemon.rpc`), and a method touches nothing else. Not the daemon: no
    method can reach its lifecycle, its loop or another part's insides."""

    config: Config  # [daemon.*] limits and colour mode, [slm] size
    calibration: CalibrationStore  # the focus mapping, whether citl can run
    base_dir: Path  # relative paths in requests and settings are taken from here
    scene_dirs: list[Path]  # where load_scene may read (resolved, `paths.resolve_dirs`)
    model_dirs: list[Path]  # where load_model may read
    snapshot_dirs: list[Path]  # where snapshot (and capture) may write
    pattern_dirs: list[Path]  # where show_pattern may read and capture may write
    audit: AuditLog
    laser: LaserLink
    arming: ArmingGate
    bench: Bench
    panel: Panel  # the bench's: what the SLM shows
    views: ViewSlot
    frames: Frames
    bench_jobs: JobRunner
    load_jobs: JobRunner
    status: Callable[[], dict[str, Any]]  # the daemon's whole `status`
    request_shutdown: Callable[[str], None]  # the daemon's, with the reason
    tcp_token: str | None = None  # set at start when daemon.server.tcp_port is
    scene: dict[str, Any] | None = None  # the loaded scene (status "scene"), set by load_scene
    snapshot_numbers: Iterator[int] = field(default_factory=lambda: itertools.count(1))


MODEL_SUFFIXES = (".onnx",)
PATTERN_SUFFIXES = (".npy",)


# The last capture of each bench (snapshot or capture, time_s and linear image), for `preview`.
_LAST_CAPTURE: weakref.WeakKeyDictionary[Any, tuple[float, np.ndarray]] = (
    weakref.WeakKeyDictionary())


@dataclass(frozen=True)
class Method:
    """An RPC method: its function and what the dispatcher does around it."""

    func: Callable[[RpcContext, Connection, Params], Any]
    audited: bool  # changes the bench: written to the audit log with who and what
    while_stopping: bool = False  # still served during shutdown


def _status(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    p.done()
    return ctx.status()


def _set_view(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    # Parsed once, here: a View from now on (digital refocus included, kept when not given).
    view = parse_view(p, ctx.views.view, ctx.config.refine.quality)
    if view.quality == "citl":
        problem = citl_problem(ctx.config, ctx.calibration, ctx.bench)
        if problem:
            raise bad_param("quality", f"'citl' cannot be served here: {problem}",
                            "network, exact or sgd on this bench (refine.quality sets the "
                            "default)")
        # Its captures switch the diodes on: a person at the bench starts it.
        kept = "" if p.has("quality") else " (kept from the current view)"
        ctx.arming.authorise_emission(conn, f"quality 'citl'{kept}")
    if ctx.panel.pattern is not None:  # a calibration pattern gives the panel back to the view
        _end_pattern(ctx)
    seq = ctx.views.submit(view)
    shown = view.to_json()  # the reply, the audit log and the recording show the plain form
    ctx.audit.view(conn.who, seq, shown)
    # Accepted all the same (the navigator, or a client that loads its model next, moves the
    # view first; the latest view is shown once a model is there), but said.
    hint = no_model_hint(view.quality, ctx.frames, ctx.load_jobs)
    return {"seq": seq, "view": shown, **({"warning": hint} if hint else {})}


# What a client hears of an open-loop view with no model loaded or loading.
NO_MODEL = ("no model: showing nothing for quality 'network'; ask for quality exact (the "
            "scene's own hologram, seconds) or load a model (nhfctl load-model)")


def no_model_hint(quality: str, frames: Frames, load_jobs: JobRunner) -> str | None:
    """NO_MODEL when a view at `quality` would show nothing: open loop, with no model serving
    and none loading; else None."""
    if quality != "network" or frames.model_path is not None:
        return None
    loading = any(j.kind == "load_model" and j.state in ("queued", "running")
                  for j in load_jobs.jobs())
    return None if loading else NO_MODEL


def _focus(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    cfg = ctx.config.daemon.bench
    low, high = cfg.focus_range_mm
    z_mm = p.number("z_mm", low, high)
    home = p.boolean("home", False)
    p.done()
    stage = ctx.bench.stage
    if stage is None:
        raise RpcError(NOT_AVAILABLE, f"no stage: {ctx.bench.errors['stage'] or 'none configured'}",
                       {"device": "stage"})
    target = _focus_target(ctx, z_mm)
    s_low, s_high = stage.settings.soft_limits_mm
    if not s_low <= target <= s_high:
        z_lo = max(low, s_low - cfg.stage_at_reference_mm)
        z_hi = min(high, s_high - cfg.stage_at_reference_mm)
        raise bad_param("z_mm", f"{z_mm:g} mm needs the stage at {target:g} mm, outside its soft "
                        f"limits [{s_low:g}, {s_high:g}] mm", f"[{z_lo:g}, {z_hi:g}] mm")

    def run(job: Job) -> dict[str, Any]:
        if home:
            stage.home()
            job.check()
        state = stage.move_to(target)
        return {"z_mm": z_mm, "stage_mm": state.position_mm if state else target}

    job = submit_or_busy(ctx.bench_jobs, Job("focus", {"z_mm": z_mm, "home": home}, run))
    return {"job": job.id, "stage_mm": target}


def _focus_target(ctx: RpcContext, z_mm: float) -> float:
    """The stage position for `z_mm`; a configured calibration that cannot be applied (no
    accepted version to keep) is the file's error, not the daemon's."""
    try:
        return stage_mm_for_focus(ctx.config, ctx.calibration, z_mm)
    except CalibrationFileError as exc:
        raise RpcError(INVALID_FILE, str(exc), {"field": "calibration.file"}) from None


def _laser(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    action = p.choice("action", ("arm", "disarm", "off", "power", "enable", "disable"))
    link = ctx.laser
    if action == "arm":
        cap_s = link.settings.arm_max_s
        duration_s = p.number("duration_s", 0.0, cap_s, low_open=True)
        p.done()
        # Who may arm (the kernel's uid, daemon.arming.users / groups; never over TCP) and the
        # optional confirmation at the bench (a pending job): nhfd/daemon/arming.py.
        return ctx.arming.arm(conn, duration_s)
    if action in ("disarm", "off"):
        p.done()
        # First, so that an arm still waiting for its confirmation can never land after this.
        cancelled = ctx.arming.cancel()
        # Ends the emission session: every run that could emit (a citl refinement's captures,
        # a capture-mode snapshot) stops, and no later arm resumes it.
        by = f"by {conn.describe()}"
        link.disarm(f"lasers disarmed {by}") if action == "disarm" else link.off(
            f"lasers off {by}")
        return {"armed": False, "all_off": True,
                **({"cancelled_arm_job": cancelled} if cancelled is not None else {})}
    channel = p.choice("channel", COLOURS)
    if action == "power":
        power_pct = p.number("power_pct", 0.0, 100.0)
        p.done()
        check_laser_command(ctx.config.daemon.frames, action, channel, power_pct)
        if power_pct > 0 and link.status().get("armed"):
            ctx.arming.authorise_emission(conn, f"a {channel} power of {power_pct:g} % while "
                                                "armed")
        applied = link.power(channel, power_pct)
        return {"channel": channel, "power_pct": applied, "capped": applied < power_pct}
    p.done()
    check_laser_command(ctx.config.daemon.frames, action, channel, None)
    if action == "enable":
        ctx.arming.authorise_emission(conn, f"enabling the {channel} diode")
    if action == "enable" and ctx.bench.slm_lost is not None:
        # The light would fall on a panel the daemon does not control.
        raise RpcError(LASER_REFUSED, f"SLM output lost ({ctx.bench.slm_lost}): no diode may be "
                       "enabled until it is back", {"device": "slm"})
    link.enable(channel, action == "enable")
    return {"channel": channel, "enabled": action == "enable"}


def _stop(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    p.done()
    # Every run that could emit ends with its session (a later arm never resumes it), and an
    # arm waiting for its confirmation with it.
    ctx.laser.end_session(f"stop by {conn.describe()}")
    ctx.arming.cancel()
    cancelled = ctx.bench_jobs.cancel_all() + ctx.load_jobs.cancel_all()
    try:
        stage = ctx.bench.stop_stage()
    except Exception as exc:
        raise RpcError(DEVICE_ERROR, f"stage stop failed: {exc}", {"device": "stage"}) from None
    return {"cancelled_jobs": cancelled, "stage": stage}


def _blank(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    p.done()
    try:
        ctx.panel.blank()
    except Exception as exc:
        raise RpcError(DEVICE_ERROR, f"blank failed: {exc}", {"device": "slm"}) from None
    return {"showing": "blank"}


def _camera(ctx: RpcContext) -> Any:
    """The open camera, or NOT_AVAILABLE with why there is none."""
    if ctx.bench.camera is None:
        raise RpcError(NOT_AVAILABLE,
                       f"no camera: {ctx.bench.errors['camera'] or 'none configured'}",
                       {"device": "camera"})
    return ctx.bench.camera


def _snapshot(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    raw = p.string("path", None)
    frames = p.integer("frames", 1, 1000, None)
    p.done()
    name = raw or time.strftime("snapshot-%Y%m%d-%H%M%S") + f"-{next(ctx.snapshot_numbers)}.png"
    path = inside("path", name, ctx.snapshot_dirs, ctx.base_dir)
    if path.suffix.lower() != ".png":
        raise bad_param("path", f"{raw!r} does not end in .png", "a .png file name")
    _camera(ctx)  # refuse now, not in the job
    lit_by_daemon = ctx.config.daemon.frames.colour_mode == "capture"
    if lit_by_daemon:  # it switches each diode on in turn
        ctx.arming.authorise_emission(conn, "a capture-mode snapshot")
    session = ctx.laser.session  # a laser off or stop before it runs ends it

    def run(job: Job) -> dict[str, Any]:
        if lit_by_daemon:
            return capture_colours(job, path, frames, bench=ctx.bench, panel=ctx.panel,
                                   laser=ctx.laser, audit=ctx.audit, shown=ctx.frames,
                                   session=session)
        before = _emitting(ctx.laser)
        cap = ctx.bench.capture(frames)  # a failure is the camera's error in status until it works
        # A channel that emitted for the whole exposure was on before it and still is after.
        emitting = [ch for ch in _emitting(ctx.laser) if ch in before]
        _LAST_CAPTURE[ctx.bench] = (time.time(), cap.image)
        job.check()
        write_png16(path, cap.image)
        preview = write_preview8(path, cap.image)
        return {"path": str(path), "preview": str(preview), "frames": cap.frames,
                "exposure_s": cap.exposure_s, "saturated_fraction": cap.saturated_fraction,
                "max_linear": float(cap.image.max()) if cap.image.size else 0.0,
                "emitting": emitting, **({"warning": NO_LIGHT} if not emitting else {})}

    job = submit_or_busy(ctx.bench_jobs,
                         Job("snapshot", {"path": str(path), "frames": frames}, run))
    return {"job": job.id, "path": str(path)}


# What a snapshot taken with no laser emitting says (its image is the camera's dark noise).
NO_LIGHT = ("no laser was emitting during the exposure: the image is the camera's noise; arm, "
            "set a power and enable a channel (nhfctl laser enable green)")


def _emitting(laser: LaserLink) -> list[str]:
    """The channels emitting now (enabled, with power), read back from the guardian."""
    if not laser.present:
        return []
    laser.refresh()
    channels = laser.status().get("channels") or {}
    return [ch for ch in COLOURS if (channels.get(ch) or {}).get("enabled")
            and float((channels.get(ch) or {}).get("power_pct", 0.0)) > 0]


def _end_pattern(ctx: RpcContext) -> None:
    """The last view frame (or the blank pattern) in place of a calibration pattern."""
    try:
        ctx.panel.resume(ctx.frames.last_frame, ctx.frames.shown_seq)
    except Exception as exc:
        raise RpcError(DEVICE_ERROR, f"ending the calibration pattern failed: {exc}",
                       {"device": "slm"}) from None


def _npy_header(path: Any, allowed: str) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype of the .npy at `path`, from its header alone (nothing else is read
    before they are checked), or RpcError naming the file."""
    fmt = np.lib.format
    try:
        with path.open("rb") as f:
            version = fmt.read_magic(f)
            shape, _, dtype = (fmt.read_array_header_1_0(f) if version == (1, 0)
                               else fmt.read_array_header_2_0(f))
    except Exception as exc:
        raise RpcError(INVALID_FILE, f"path: {path} is not a readable .npy array: {exc}",
                       {"field": "path", "allowed": allowed}) from None
    if dtype != np.uint8:
        raise RpcError(INVALID_FILE, f"path: {path} holds {dtype}, not uint8 grey levels",
                       {"field": "path", "allowed": allowed})
    return tuple(shape), dtype


def _npy_data(path: Any, allowed: str) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:
        raise RpcError(INVALID_FILE, f"path: {path} is not a readable .npy array: {exc}",
                       {"field": "path", "allowed": allowed}) from None


def _pattern_frame(path: Any, hw: tuple[int, int]) -> np.ndarray:
    """The .npy at `path` as a panel frame uint8 [3, H, W], or RpcError naming what is wrong."""
    h, w = hw
    allowed = f"uint8 [3, {h}, {w}], [{h}, {w}, 3] or [{h}, {w}] (.npy, no pickles)"
    shape, _ = _npy_header(path, allowed)
    if shape not in ((3, h, w), (h, w, 3), (h, w)):
        raise RpcError(INVALID_FILE, f"path: {path} has shape {list(shape)}, not the panel's "
                       f"{h} x {w}", {"field": "path", "allowed": allowed})
    a = _npy_data(path, allowed)
    if a.shape == (3, h, w):
        return np.ascontiguousarray(a)
    if a.shape == (h, w, 3):
        return np.ascontiguousarray(a.transpose(2, 0, 1))
    return np.ascontiguousarray(np.broadcast_to(a, (3, h, w)))


def _region_patterns(path: Any, hw: tuple[int, int], top: int, left: int) -> np.ndarray:
    """The .npy at `path` as K subframes of a region at (`top`, `left`) of the `hw` panel,
    uint8 [K, 3, h, w] (1 <= K <= MAX_SUBFRAMES, inside the panel), or RpcError."""
    h, w = hw
    allowed = (f"uint8 [K, 3, h, w] (.npy, no pickles), 1 <= K <= {MAX_SUBFRAMES}, "
               f"top + h <= {h} and left + w <= {w}")
    shape, _ = _npy_header(path, allowed)
    if (len(shape) != 4 or not 1 <= shape[0] <= MAX_SUBFRAMES or shape[1] != 3
            or not 1 <= shape[2] <= h - top or not 1 <= shape[3] <= w - left):
        raise RpcError(INVALID_FILE, f"path: {path} has shape {list(shape)}: not subframes of "
                       f"a region at row {top}, column {left} of the {w} x {h} panel",
                       {"field": "path", "allowed": allowed})
    return np.ascontiguousarray(_npy_data(path, allowed))


def _show_pattern(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    raw = p.string("path")
    p.done()
    path = _checked_file("path", raw, ctx.pattern_dirs, ctx.base_dir, PATTERN_SUFFIXES)
    s = ctx.config.slm
    frame = _pattern_frame(path, (s.height_px, s.width_px))
    if ctx.bench.slm is None:
        raise RpcError(NOT_AVAILABLE, f"no SLM: {ctx.bench.errors['slm'] or 'none configured'}",
                       {"device": "slm"})
    if ctx.bench.slm_lost is not None:
        raise RpcError(DEVICE_ERROR, f"SLM output lost ({ctx.bench.slm_lost})", {"device": "slm"})
    try:
        ctx.panel.show_pattern(frame, str(path))
    except Exception as exc:
        raise RpcError(DEVICE_ERROR, f"show_pattern failed: {exc}", {"device": "slm"}) from None
    return {"showing": str(path), "shape": list(frame.shape)}


def _stage_move(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    stage = ctx.bench.stage
    low, high = (stage.settings.soft_limits_mm if stage is not None else (-1e6, 1e6))
    position = p.number("position_mm", low, high)
    home = p.boolean("home", False)
    p.done()
    if stage is None:
        raise RpcError(NOT_AVAILABLE, f"no stage: {ctx.bench.errors['stage'] or 'none configured'}",
                       {"device": "stage"})

    def run(job: Job) -> dict[str, Any]:
        if home:
            stage.home()
            job.check()
        state = stage.move_to(position)
        return {"stage_mm": state.position_mm if state else position}

    job = submit_or_busy(ctx.bench_jobs,
                         Job("stage_move", {"position_mm": position, "home": home}, run))
    return {"job": job.id, "stage_mm": position}


def _capture(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    raw = p.string("path")
    frames = p.integer("frames", 1, 1000, None)
    exposure_s = p.number("exposure_s", 1e-6, 60.0, None, low_open=False)
    dark = p.boolean("dark", False)
    p.done()
    path = inside("path", raw, [*ctx.pattern_dirs, *ctx.snapshot_dirs], ctx.base_dir)
    if path.suffix.lower() != ".npy":
        raise bad_param("path", f"{raw!r} does not end in .npy", "a .npy file name")
    camera = _camera(ctx)
    mask_path = path.with_name(f"{path.stem}.saturated.npy")

    def run(job: Job) -> dict[str, Any]:
        if exposure_s is not None:
            camera.set_exposure(exposure_s)  # the same value keeps the stored dark frame
        if dark:
            ctx.laser.refresh()
            lit = [ch for ch, c in (ctx.laser.status().get("channels") or {}).items()
                   if c.get("enabled") and c.get("power_pct", 0) > 0]
            if lit:
                raise RuntimeError(f"a dark frame needs every laser off; on: {', '.join(lit)}")
        if ctx.bench.slm is not None:
            ctx.bench.slm.wait_settled()
        job.check()
        if dark:
            image = ctx.bench.camera.capture_dark(frames)
            saturated = np.zeros(image.shape, bool)
            n, exposure = frames or camera.settings.burst_frames, camera.exposure_s
        else:
            cap = ctx.bench.capture(frames)
            _LAST_CAPTURE[ctx.bench] = (time.time(), cap.image)
            image, saturated, n, exposure = cap.image, cap.saturated, cap.frames, cap.exposure_s
        job.check()
        path.parent.mkdir(parents=True, exist_ok=True)
        for target, array in ((path, image.astype(np.float32)), (mask_path, saturated)):
            tmp = target.with_name(f".{target.name}.tmp.npy")
            np.save(tmp, array)
            tmp.replace(target)
        stage = ctx.bench.status()["stage"].get("position_mm")
        return {"path": str(path), "saturated_path": str(mask_path), "dark": dark,
                "frames": n, "exposure_s": exposure, "gain_db": camera.gain_db,
                "shape": list(image.shape),
                "saturated_fraction": float(saturated.mean()) if saturated.size else 0.0,
                "max_linear": float(image.max()) if image.size else 0.0,
                "stage_mm": stage, "showing": ctx.panel.showing,
                **exposure_over_cycle(exposure, ctx.frames.subframes_shown,
                                      ctx.frames.refresh_s)}

    job = submit_or_busy(ctx.bench_jobs, Job("capture", {
        "path": str(path), "frames": frames, "exposure_s": exposure_s, "dark": dark}, run))
    return {"job": job.id, "path": str(path)}


# An exposure within this fraction of a whole number of subframe cycles holds every subframe
# equally (to this fraction of one subframe's light).
CYCLE_TOLERANCE = 0.05


def exposure_over_cycle(exposure_s: float, subframes: int, refresh_s: float) -> dict[str, Any]:
    """What a capture's exposure spans of the K subframes taking turns on the panel: K, the
    cycle's seconds and how many cycles the exposure holds; with a `warning` unless it holds a
    whole number of them (within `CYCLE_TOLERANCE`), when the image weighs some subframes more
    than others. Empty for a still frame."""
    if subframes <= 1:
        return {}
    cycle_s = subframes * refresh_s
    cycles = exposure_s / cycle_s
    out: dict[str, Any] = {"subframes": subframes, "cycle_s": round(cycle_s, 6),
                           "exposure_cycles": round(cycles, 3)}
    whole = max(1, round(cycles))
    if abs(cycles - whole) > CYCLE_TOLERANCE or cycles < 1 - CYCLE_TOLERANCE:
        out["warning"] = (f"exposure {exposure_s * 1e3:g} ms spans {cycles:.2f} cycles of the "
                          f"{subframes} subframes shown in turn ({cycle_s * 1e3:g} ms at "
                          f"{1 / refresh_s:g} Hz): the image weighs them unequally; set "
                          f"exposure_s to a whole number of cycles ({whole * cycle_s:g} s)")
    return out


# What a focal-stack capture is called in refusals and the audit log.
STACK_CAPTURE = "a focal-stack capture"


def _capture_stack(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    raw = p.string("path")
    s = ctx.config.slm
    top = p.integer("top", 0, s.height_px - 1)
    left = p.integer("left", 0, s.width_px - 1)
    z_m = p.numbers("z_m", -1.0, 1.0, MAX_PLANES)
    out_raw = p.string("out")
    frames = p.integer("frames", 1, 1000, None)
    p.done()
    path = _checked_file("path", raw, ctx.pattern_dirs, ctx.base_dir, PATTERN_SUFFIXES)
    out = inside("out", out_raw, [*ctx.pattern_dirs, *ctx.snapshot_dirs], ctx.base_dir)
    if out.suffix.lower() != ".npz":
        raise bad_param("out", f"{out_raw!r} does not end in .npz", "a .npz file name")
    grey = _region_patterns(path, (s.height_px, s.width_px), top, left)
    problem = citl_problem(ctx.config, ctx.calibration, ctx.bench, STACK_CAPTURE)
    if problem:
        raise RpcError(NOT_AVAILABLE, problem)
    ctx.arming.authorise_emission(conn, STACK_CAPTURE)
    session = ctx.laser.session  # a laser off, disarm or stop before it ends ends it
    k, _, h, w = grey.shape
    request = CaptureRequest(Region(top, left, h, w, 0, 0), grey, tuple(z_m), frames or 0)

    def run(job: Job) -> dict[str, Any]:
        reply = citl_capture(job, request, config=ctx.config, calibration=ctx.calibration,
                             bench=ctx.bench, panel=ctx.panel, laser=ctx.laser, audit=ctx.audit,
                             shown=ctx.frames, wanted=lambda: True, session=session,
                             what="focal-stack capture")
        assert reply.images is not None and reply.saturated is not None
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.stem}.tmp.npz")
        np.savez(tmp, images=reply.images.astype(np.float32), saturated=reply.saturated,
                 z_m=np.asarray(request.z_m, np.float64))
        tmp.replace(out)
        return {"path": str(out), "planes": len(z_m), "subframes": k,
                "max_linear": float(reply.images.max()),
                "saturated_fraction": float(reply.saturated.mean())}

    job = submit_or_busy(ctx.bench_jobs, Job("capture_stack", {
        "path": str(path), "top": top, "left": left, "z_m": z_m, "out": str(out),
        "frames": frames}, run))
    return {"job": job.id, "path": str(out)}


def _checked_file(field: str, raw: str, dirs: list[Any], base: Any,
                  suffixes: tuple[str, ...]) -> Any:
    """`raw` resolved inside `dirs`: a readable file whose suffix is one of `suffixes`."""
    return _with_suffix(field, raw, inside(field, raw, dirs, base), suffixes)


def _with_suffix(field: str, raw: str, path: Any, suffixes: tuple[str, ...],
                 allowed: str | None = None) -> Any:
    if path.suffix.lower() not in suffixes:
        raise bad_param(field, f"{raw!r} has the wrong suffix", allowed or " or ".join(suffixes))
    return _readable_file(field, path)


def _readable_file(field: str, path: Any) -> Any:
    if not path.is_file():
        raise RpcError(INVALID_FILE, f"{field}: {path} is not a readable file",
                       {"field": field})
    return path


def _load_scene(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    raw = p.string("path")
    p.done()
    path = inside("path", raw, ctx.scene_dirs, ctx.base_dir)
    # A SOG scene may be a folder, or named by its meta.json; anything else is one file with a
    # scene suffix. Only scenes have such names: _checked_file (models, patterns) is suffix-only.
    if path.name.lower() in SCENE_NAMES:
        _readable_file("path", path)
    elif not is_sog_folder(path):
        _with_suffix("path", raw, path, SCENE_SUFFIXES,
                     " or ".join((*SCENE_SUFFIXES, *SCENE_NAMES, "a SOG folder")))

    def run(job: Job) -> dict[str, Any]:
        # Refuses a file that is not a plausible scene (SceneFileError names the rule), holds
        # more than daemon.paths.max_gaussians or needs more than daemon.paths.scene_memory_mb
        # before the worker is asked: the old scene keeps rendering. Read in a child process
        # (scene_check says why), so neither the daemon's memory nor its control loop pays for the
        # file.
        counts = read_scene_counts(path, ctx.config.daemon.paths.max_gaussians,
                                   ctx.config.daemon.paths.scene_memory_mb, job.check)
        job.check()
        info = {"path": str(path), **counts, "loaded_s": time.time()}
        # The frame worker loads its own copy (it renders in another process).
        info.update(ctx.frames.load_scene(str(path)).to_json(), loaded_s=time.time())
        ctx.scene = info  # replaced only now: on failure the old scene keeps running
        return info

    return _submit_load(ctx, "load_scene", path, run)


def _submit_load(ctx: RpcContext, kind: str, path: Any, run: Any) -> dict[str, Any]:
    """Queue a scene or model load; a full queue is BUSY, not a wait."""
    job = submit_or_busy(ctx.load_jobs, Job(kind, {"path": str(path)}, run),
                         "too many loads queued", {"field": "path"})
    return {"job": job.id, "path": str(path)}


def _load_model(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    raw = p.string("path")
    p.done()
    path = _checked_file("path", raw, ctx.model_dirs, ctx.base_dir, MODEL_SUFFIXES)

    def run(job: Job) -> dict[str, Any]:
        # The worker checks the metadata against [optics] (ModelMismatch names each differing
        # field) and swaps models only on success: on failure the old one keeps running.
        return ctx.frames.load_model(str(path)).to_json()

    return _submit_load(ctx, "load_model", path, run)


def _job(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    job_id = p.integer("id", 1, 2**53)
    p.done()
    job = ctx.bench_jobs.get(job_id) or ctx.load_jobs.get(job_id)
    if job is None:
        raise RpcError(NO_SUCH_JOB, f"no job {job_id} (finished jobs are kept: "
                       f"daemon.paths.jobs_kept = {ctx.config.daemon.paths.jobs_kept})",
                       {"field": "id"})
    return job.to_json()


def _preview(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    source = p.choice("source", ("slm", "camera"))
    max_px = p.integer("max_px", 16, 4096, 320)
    p.done()
    if source == "slm":
        slm = ctx.bench.slm
        frame = slm.last_frame if slm is not None else None  # [3, H, W] uint8, what it shows
        if frame is None:
            return {"source": source, "available": False, "showing": ctx.panel.showing}
        pixels, extra = frame.transpose(1, 2, 0), {"showing": ctx.panel.showing}
    else:
        last = _LAST_CAPTURE.get(ctx.bench)
        if last is None:
            return {"source": source, "available": False}
        time_s, image = last
        grey = image.mean(axis=0) if image.ndim == 3 else image
        peak = float(np.max(grey)) if grey.size else 0.0
        # Shown linear, scaled to its own peak (a display, not a measurement).
        scaled = np.clip(np.nan_to_num(grey / peak if peak > 0 else grey * 0.0), 0.0, 1.0)
        pixels = np.round(scaled * 255).astype(np.uint8)[..., None]
        extra = {"time_s": time_s, "peak_linear": peak}
    h, w = pixels.shape[:2]
    step = max(1, math.ceil(max(h, w) / max_px))  # every step-th pixel: phase is not averaged
    thumb = np.ascontiguousarray(pixels[::step, ::step])
    return {"source": source, "available": True, "size_hw": [h, w], "step": step,
            "shape_hwc": list(thumb.shape), "pixels_b64": base64.b64encode(thumb).decode(),
            **extra}


def _auth(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    token = p.string("token", max_len=1024)
    p.done()
    if conn.transport == "unix":
        return {"authenticated": True}  # the socket's mode and group already decide
    if ctx.tcp_token is None or not hmac.compare_digest(token.encode(), ctx.tcp_token.encode()):
        raise RpcError(UNAUTHORIZED, "wrong token", {"field": "token"})
    conn.authed = True
    return {"authenticated": True}


def _web_client(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    """The web view runs on a thread of this daemon and reaches it over the Unix socket, so
    without this its requests read in the audit log as the daemon's own. It names the web
    client (address, TLS, the token file it signed in with) that the next requests on this
    connection come from. Only this process may say so: the kernel vouches for the peer's pid
    (SO_PEERCRED); from anyone else it would be a claim nobody can check."""
    address = p.string("address", max_len=100)
    tls = p.boolean("tls", False)
    token_file = p.string("token_file", None, max_len=1024)
    p.done()
    if conn.transport != "unix" or conn.peer.get("pid") != os.getpid():
        raise RpcError(FORBIDDEN, "web_client is accepted only from the daemon's own web view",
                       {"field": "method", "allowed": "the daemon's own process, over the Unix "
                                                      "socket"})
    client = {"via": "web view", "address": address, "tls": tls,
              **({"token_file": token_file} if token_file else {})}
    conn.peer["web_client"] = client  # in `conn.who` from now on
    return {"web_client": client}


def _shutdown(ctx: RpcContext, conn: Connection, p: Params) -> Any:
    p.done()
    ctx.request_shutdown(f"shutdown requested by {conn.who}")
    return {"shutting_down": True}


METHODS: dict[str, Method] = {
    "status": Method(_status, audited=False, while_stopping=True),
    "set_view": Method(_set_view, audited=False),  # audited, summarised, in _set_view
    "focus": Method(_focus, audited=True),
    "laser": Method(_laser, audited=True, while_stopping=True),
    "stop": Method(_stop, audited=True, while_stopping=True),
    "blank": Method(_blank, audited=True, while_stopping=True),
    "snapshot": Method(_snapshot, audited=True),
    "show_pattern": Method(_show_pattern, audited=True),
    "stage_move": Method(_stage_move, audited=True),
    "capture": Method(_capture, audited=True),
    "capture_stack": Method(_capture_stack, audited=True),
    "load_scene": Method(_load_scene, audited=True),
    "load_model": Method(_load_model, audited=True),
    "job": Method(_job, audited=False, while_stopping=True),
    "preview": Method(_preview, audited=False),
    "auth": Method(_auth, audited=False, while_stopping=True),
    "web_client": Method(_web_client, audited=False, while_stopping=True),
    "shutdown": Method(_shutdown, audited=True, while_stopping=True),
}
