"""The daemon's side of the frame worker: the spawned process that renders, runs the network
and codes frames (`nhfd.pipeline.worker`, whose docstring has the pipe's protocol).

Why a process: rendering, inference and propagation hold the CPU for tens of milliseconds at a
time; in the daemon's own process they would delay the control loop that feeds the laser
guardian's heartbeat. Why spawned, not forked: a fork copies the daemon's threads' locks and
the already-initialised thread pools of torch/OpenMP in whatever state they are in; a fresh
interpreter gets its thread counts in its environment before any pool exists.

The daemon spawns the worker by its module's name (`WORKER_MODULE`) and learns everything of
the model (its metadata, why one was refused) as data over the pipe: nothing here imports the
pipeline, the models or torch. `FrameLink` never blocks on the pipe: it polls it once per
control-loop tick, and it shows the frames it gets (the "output" stage: the coded region pasted
into the blank frame, `PanelBuffer`).

Frames cross in shared memory (docs/frames.md): `FrameWorker` creates `SLOTS` (one) segment
named `nhfd-<pid>-<n>-<slot>` in /dev/shm, sized for the whole panel (a grey region and its
render can never be larger, so a model, scene or refocus that changes the window needs no new
slot), and unlinks it whenever the worker is closed: stop, crash, restart. The slot is named in
each frame request; the worker writes only that one, and the daemon names it again only after
it has copied the frame out, so no slot is overwritten while the daemon reads it.

Pacing: at most one view frame per refresh (`slm.refresh_hz`). A frame that arrives sooner
waits (the control loop wakes for it at `wake_s`); the next view goes to the worker only once
the frame before it is on the panel, so the frame shown is never older than one refresh.
`status` counts frames shown, dropped and late (`FrameLink.status`).
"""

from __future__ import annotations

import contextlib
import importlib
import itertools
import logging
import math
import multiprocessing as mp
import os
import threading
import time
from multiprocessing import shared_memory
from types import SimpleNamespace
from typing import Any, Protocol

import numpy as np

from nhfd.calibration import active_calibration
from nhfd.drivers import factory
from nhfd.drivers.slm import SLMOutputLost

log = logging.getLogger("nhfd.daemon.frame_link")

# How long a load may take in the worker before the load job gives up waiting (s).
LOAD_TIMEOUT_S = 120.0
# A crashed worker is restarted at most this often (s), so a worker that dies at start-up does
# not spin.
RESTART_BACKOFF_S = 2.0
# The worker process's module: the spawned interpreter imports it by this name and runs its
# `worker_main(conn, config_data, calibration)`.
WORKER_MODULE = "nhfd.pipeline.worker"
# Shared-memory slots per worker. One is all the pacing can use: the link holds at most one
# frame at a time (in the worker, or waiting for its refresh), and sends the next view only once
# that frame is on the panel and its slot is free. (~12.4 MB at 1920 x 1080, per worker.)
SLOTS = 1
# The /dev/shm names of the slots start with this (then the daemon's pid, a counter, the slot).
SHM_PREFIX = "nhfd-"
# A frame is shown when its refresh is due within this (s): the control loop's select may wake
# a little before the time it was given.
DUE_SLACK_S = 0.0005
# A view goes to a worker faster than the panel this long (plus 1.5 frame times) before the
# refresh its frame is for (s).
SEND_MARGIN_S = 0.002


# -- what the frame link uses of the daemon ----------------------------------------------------


class PanelView(Protocol):
    """The daemon's panel (`nhfd.daemon.panel.Panel`), as far as view frames go."""

    def show_view(self, frame: np.ndarray, seq: int) -> np.ndarray: ...

    def blank_frame(self) -> np.ndarray: ...

    def blank(self) -> None: ...


class SLMFaults(Protocol):
    """Where an SLM whose output is lost is reported (`nhfd.daemon.bench.Bench`)."""

    def note_slm_lost(self, detail: str) -> None: ...


class ViewSource(Protocol):
    """The newest view requested (`nhfd.daemon.views.ViewSlot`)."""

    seq: int
    view: dict[str, Any] | None

    def mark_applied(self, seq: int) -> None: ...


class LaserSwitch(Protocol):
    def off(self) -> None: ...


class FrameHost(Protocol):
    """What `FrameLink` uses of the daemon (`nhfd.daemon.service.Daemon`): its configuration,
    the views, the panel (view frames and the blank), the lasers (off when the worker crashes)
    and the error list of `status`."""

    config: Any  # nhfd.config.Config
    panel: PanelView
    bench: SLMFaults
    views: ViewSource
    laser: LaserSwitch

    def _error(self, source: str, message: str) -> None: ...


# -- the worker process, seen from the daemon --------------------------------------------------


def worker_environment(config: Any) -> dict[str, str]:
    """The worker's thread counts, for its environment: read once, when torch, numba and
    onnxruntime load in the spawned process, so they must be there before its first import."""
    threads = str(int(config.daemon.worker_threads))
    env = {var: threads for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}
    env["NUMBA_THREADING_LAYER"] = str(config.daemon.worker_threading_layer)
    return env


def run_by_name(module: str, env: dict[str, str], *args: Any) -> None:
    """The spawned process's target: set its environment, then import `module` by name and run
    its `worker_main(*args)`. By name, so the daemon has no import edge to the frame pipeline
    (and never loads torch itself)."""
    os.environ.update(env)
    # OpenMP threads sleep when idle instead of spinning: each stage hands the cores to another
    # library (render and coding in numba, propagation in torch, inference in onnxruntime), and a
    # spinning pool takes them from the next stage. Set before torch or numba load libgomp.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    importlib.import_module(module).worker_main(*args)


class Pending:
    """A load sent to the worker; the control loop fills in its outcome."""

    def __init__(self) -> None:
        self.done = threading.Event()
        self.ok = False
        self.result: Any = None

    def wait(self, timeout_s: float) -> Any:
        if not self.done.wait(timeout_s):
            raise TimeoutError(f"the frame worker did not answer within {timeout_s:g} s")
        if not self.ok:
            raise ValueError(str(self.result))
        return self.result


class FrameWorker:
    """The worker process and its pipe, seen from the daemon. Non-blocking except `start`."""

    _ids = itertools.count(1)
    _workers = itertools.count(1)

    def __init__(self, config: Any, module: str = WORKER_MODULE) -> None:
        self.config = config
        self.module = module
        self.process: Any = None
        self.conn: Any = None
        self.pid: int | None = None
        self.ready = False
        self._send_lock = threading.Lock()  # load jobs send from their own thread
        self.pending: dict[int, Pending] = {}
        self.transport = str(config.daemon.frame_transport)
        self.shms: list[shared_memory.SharedMemory] = []
        self.free_slots: list[int] = []

    def start(self) -> None:
        slots = self._make_slots() if self.transport == "shm" else None
        try:
            ctx = mp.get_context("spawn")
            here, there = ctx.Pipe(duplex=True)
            self.process = ctx.Process(target=run_by_name,
                                       args=(self.module, worker_environment(self.config), there,
                                             self.config.model_dump(),
                                             _accepted_calibration(self.config), slots),
                                       name="nhfd-frame-worker", daemon=True)
            self.process.start()
        except BaseException:
            self._unlink()
            raise
        there.close()
        self.conn, self.ready, self.pid = here, False, self.process.pid

    def _make_slots(self) -> dict[str, Any]:
        """The slots, each for a grey region and a render as large as the panel."""
        panel = self.config.slm
        nbytes = 2 * 3 * int(panel.height_px) * int(panel.width_px)
        tag = f"{SHM_PREFIX}{os.getpid()}-{next(self._workers)}"
        try:
            for i in range(SLOTS):
                self.shms.append(shared_memory.SharedMemory(name=f"{tag}-{i}", create=True,
                                                            size=nbytes))
        except BaseException:
            self._unlink()
            raise
        self.free_slots = list(range(SLOTS))
        return {"names": [shm.name for shm in self.shms], "bytes": nbytes}

    def take_slot(self) -> int | None:
        """A slot the worker may write (None: pickled transport). LookupError if none is free:
        the link never asks while it holds one (`FrameLink._ready_to_send`)."""
        if self.transport != "shm":
            return None
        if not self.free_slots:
            raise LookupError("no free frame slot")
        return self.free_slots.pop(0)

    def release(self, slot: int | None) -> None:
        if slot is not None and slot not in self.free_slots and slot < len(self.shms):
            self.free_slots.append(slot)

    def arrays(self, payload: dict[str, Any]) -> tuple[np.ndarray, np.ndarray | None]:
        """A frame's grey region and render: views into its slot (copy before releasing it),
        or the arrays pickled in the payload."""
        slot = payload.get("slot")
        if slot is None:
            return payload["grey"], payload.get("rgb")
        buf = self.shms[slot].buf
        grey = np.ndarray(tuple(payload["grey_shape"]), np.uint8, buffer=buf)
        rgb_shape = payload.get("rgb_shape")
        rgb = (np.ndarray(tuple(rgb_shape), np.uint8, buffer=buf, offset=grey.nbytes)
               if rgb_shape else None)
        return grey, rgb

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.is_alive()

    def send(self, msg: tuple) -> None:
        with self._send_lock:
            self.conn.send(msg)

    def request(self, kind: str, path: str) -> Pending:
        req_id = next(self._ids)
        pending = self.pending[req_id] = Pending()
        self.send((kind, req_id, path))
        return pending

    def receive(self) -> list[tuple]:
        """Every message waiting on the pipe (never blocks); EOFError when the worker is gone."""
        out = []
        while self.conn.poll(0):
            out.append(self.conn.recv())
        return out

    def close(self, timeout_s: float = 2.0) -> None:
        if self.process is None:
            return
        with contextlib.suppress(Exception):
            self.send(("stop",))
        self.process.join(timeout_s)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(timeout_s)
        with contextlib.suppress(Exception):
            self.conn.close()
        self._unlink()
        for p in self.pending.values():
            p.ok, p.result = False, "the frame worker stopped"
            p.done.set()
        self.pending.clear()

    def _unlink(self) -> None:
        """Remove the slots from /dev/shm (the worker is gone: nothing else maps them)."""
        for shm in self.shms:
            with contextlib.suppress(FileNotFoundError):
                shm.unlink()
            with contextlib.suppress(BufferError):  # a view still alive: unmapped when freed
                shm.close()
        self.shms, self.free_slots = [], []


class FrameLink:
    """The daemon's use of the worker: send the newest view when the worker is free, show the
    frames it returns, load models and scenes, and turn a worker crash into lasers off plus an
    error in `status` (then restart it with the same model and scene)."""

    def __init__(self, daemon: FrameHost, worker_module: str = WORKER_MODULE) -> None:
        self.d = daemon
        # `worker_module`: another worker speaking the same protocol (tests use a fake one).
        self.worker = FrameWorker(daemon.config, worker_module)
        self.model_path: str | None = None
        self.model_info: dict[str, Any] | None = None
        self.scene_path: str | None = None
        # (seq, sent at (monotonic), its slot): the view the worker is computing
        self.inflight: tuple[int, float, int | None] | None = None
        self.sent_seq = 0
        self.shown_seq = 0
        self.timings: dict[str, Any] | None = None
        self.warnings: list[str] = []
        self.last_rgb: np.ndarray | None = None
        self.last_frame: np.ndarray | None = None
        self.frames_shown = 0
        # Views never computed because a newer one overtook them (latest wins), plus a frame
        # waiting for its refresh when the worker crashed; frames shown more than one refresh
        # after the worker finished them (docs/frames.md).
        self.frames_dropped = 0
        self.frames_late = 0
        self.refresh_s = 1.0 / float(daemon.config.slm.refresh_hz)
        self.pending: tuple[int, dict[str, Any], float | None] | None = None  # waits its refresh
        self.last_show_s = -math.inf  # monotonic, when the last view frame went to the panel
        self.last_age_s: float | None = None
        self.max_age_s = 0.0
        self._view_seq = 0  # the newest view sent to a worker (never reset: skipped views)
        self.compute_s: float | None = None  # the worker's recent frame time, request to ready
        self.crashes = 0
        self.state = "idle"
        self._start_lock = threading.Lock()
        self._zero: PanelBuffer | None = None  # of the blank frame `_zero_of`, built on use
        self._zero_of: np.ndarray | None = None
        self._restart_at = 0.0

    # -- lifecycle -----------------------------------------------------------------------------

    def start(self) -> None:
        self.worker.start()
        self.state = "starting"
        if self.scene_path:
            self._track(self.worker.request("scene", self.scene_path), "scene", self.scene_path)
        if self.model_path:
            self._track(self.worker.request("model", self.model_path), "model", self.model_path)

    def ensure_started(self) -> None:
        """The worker starts with the first load: a daemon with no model or scene (most tests,
        a bench used only for captures) never pays for a process that imports torch."""
        with self._start_lock:
            if self.state == "idle":
                self.start()

    def close(self) -> None:
        self.state = "stopped"
        # A frame waiting for its refresh, or in the worker: its slot goes with the worker.
        self.pending = self.inflight = None
        self.worker.close()

    def _track(self, pending: Pending, kind: str, path: str) -> Pending:
        """Restarts reload in the background: their outcome only matters if it failed."""
        def watch() -> None:
            pending.done.wait(LOAD_TIMEOUT_S)
            if pending.done.is_set() and not pending.ok:
                self.d._error("frame worker", f"reloading {kind} {path}: {pending.result}")
        threading.Thread(target=watch, daemon=True, name="nhfd-reload-watch").start()
        return pending

    # -- loads (from load jobs' threads) --------------------------------------------------------

    def load_model(self, path: str) -> dict[str, Any]:
        """Blocks the calling job until the worker has the model, or raises with the worker's
        reason (a ModelMismatch names the field); on failure the old model keeps running."""
        self.ensure_started()
        info = self.worker.request("model", path).wait(LOAD_TIMEOUT_S)
        self.model_path, self.model_info = path, info
        self.sent_seq = 0  # the current view again, with the new model
        return info

    def load_scene(self, path: str) -> dict[str, Any]:
        self.ensure_started()
        info = self.worker.request("scene", path).wait(LOAD_TIMEOUT_S)
        self.scene_path = path
        self.sent_seq = 0
        return info

    # -- the control loop's part ---------------------------------------------------------------

    def step(self) -> None:
        """Once per tick: collect what the worker sent, show the newest frame when its refresh
        is due, send the newest view."""
        if self.state in ("idle", "stopped"):
            return
        if self.state == "crashed":
            if time.monotonic() >= self._restart_at:
                self.worker = FrameWorker(self.d.config, self.worker.module)
                self.inflight = None
                self.start()
            return
        try:
            msgs = self.worker.receive()
        except (EOFError, OSError):
            msgs = None
        if msgs is None or not self.worker.alive:
            self._crashed()
            return
        for msg in msgs:
            self._handle(msg)
        if self.pending is not None and time.monotonic() >= self.due_s - DUE_SLACK_S:
            seq, payload, sent_at = self.pending
            self.pending = None
            self._show(seq, payload, sent_at)
        self._send_next()

    @property
    def due_s(self) -> float:
        """When the next view frame may go to the panel (monotonic): one refresh after the
        last."""
        return self.last_show_s + self.refresh_s

    @property
    def send_at_s(self) -> float:
        """When the next view may go to the worker (monotonic): early enough that its frame is
        ready for the next refresh (1.5 x the worker's recent frame time plus a margin before
        it), no earlier, so a worker faster than the panel computes the view that is newest
        just before the refresh instead of one a refresh old."""
        if self.compute_s is None:
            return -math.inf
        return self.due_s - 1.5 * self.compute_s - SEND_MARGIN_S

    @property
    def wake_s(self) -> float:
        """When the control loop must step again (monotonic; inf: nothing is waiting): for a
        frame waiting for its refresh, or a newer view waiting for its time to go out."""
        if self.pending is not None:
            return self.due_s
        if self._ready_to_send():
            return self.send_at_s  # the step then sends it (_send_next)
        return math.inf

    def _ready_to_send(self) -> bool:
        """Whether the newest view may go to the worker, its time (`send_at_s`) aside: the worker
        runs with a model and a scene, it computes nothing of ours and no frame waits for its
        refresh (one frame at a time: the next view is taken only once the frame before it is on
        the panel, so what the worker computes is the newest view then, and the slot is free),
        and a view newer than the last sent is waiting."""
        views = self.d.views
        return (self.state == "running" and self.worker.ready
                and self.inflight is None and self.pending is None
                and self.model_path is not None and self.scene_path is not None
                and views.view is not None and views.seq > self.sent_seq)

    def _handle(self, msg: tuple) -> None:
        kind = msg[0]
        if kind == "ready":
            self.worker.ready = True
            self.state = "running"
        elif kind in ("model", "scene"):
            _, req_id, ok, result = msg
            pending = self.worker.pending.pop(req_id, None)
            if pending is not None:
                pending.ok, pending.result = ok, result
                pending.done.set()
        elif kind == "frame":
            seq, payload = msg[1], msg[2]
            sent_at = self.inflight[1] if self.inflight and self.inflight[0] == seq else None
            if sent_at is not None and payload.get("ready_s") is not None:
                took = max(0.0, float(payload["ready_s"]) - sent_at)
                self.compute_s = took if self.compute_s is None else (
                    0.7 * self.compute_s + 0.3 * took)
            self.inflight = None
            self.pending = (seq, payload, sent_at)  # none before it: one frame at a time
        elif kind == "frame_error":
            seq, message = msg[1], msg[2]
            if self.inflight is not None:
                self.worker.release(self.inflight[2])
            self.inflight = None
            self.d._error("frame worker", f"view {seq}: {message}")

    def _send_next(self) -> None:
        if not self._ready_to_send() or time.monotonic() < self.send_at_s:
            return  # the loop wakes at send_at_s (wake_s)
        seq, view = self.d.views.seq, self.d.views.view
        shm_slot = self.worker.take_slot()  # free: no frame of ours is out or waiting
        self.worker.send(("frame", seq, view, shm_slot))
        self.inflight = (seq, time.monotonic(), shm_slot)
        self.sent_seq = seq
        if self._view_seq and seq > self._view_seq + 1:
            self.frames_dropped += seq - self._view_seq - 1  # overtaken, never computed
        self._view_seq = max(self._view_seq, seq)

    def _show(self, seq: int, payload: dict[str, Any], sent_at: float | None) -> None:
        # One clock (monotonic) for all: the worker's ready_s is CLOCK_MONOTONIC, as is sent_at.
        t0 = self.last_show_s = time.monotonic()
        # A frame that cannot be shown (a region off the panel, a malformed payload, the SLM
        # refusing it) is an error in status, not an exception out of the control loop: the
        # panel keeps the frame before it and the daemon keeps running.
        try:
            try:
                panel, rgb = self._panel(payload)
            finally:  # copied out (or refused): the worker may write the slot again
                self.worker.release(payload.get("slot"))
            # The panel applies the colour mode, and holds the frame back during a capture.
            frame = self.d.panel.show_view(panel, seq)
        except Exception as exc:
            self.d._error("slm", f"showing view {seq}: {type(exc).__name__}: {exc}")
            if isinstance(exc, SLMOutputLost):  # the control loop switches lasers off
                self.d.bench.note_slm_lost(str(exc))
            return
        done = time.monotonic()
        if payload.get("ready_s") is not None:
            age = done - float(payload["ready_s"])
            self.last_age_s, self.max_age_s = age, max(self.max_age_s, age)
            self.frames_late += age > self.refresh_s
        stages = dict(payload["timings_s"])
        stages["output"] = done - t0
        timings = {f"{k}_ms": round(v * 1e3, 3) for k, v in stages.items()}
        if sent_at is not None:
            timings["view_to_slm_ms"] = round((done - sent_at) * 1e3, 3)
        timings.update(seq=seq, cached=payload["cached"],
                       clipped_fraction=list(payload["clipped_fraction"]))
        self.timings = timings
        self.warnings = list(payload["warnings"])
        self.last_rgb, self.last_frame = rgb, frame
        self.shown_seq = seq
        self.frames_shown += 1
        self.d.views.mark_applied(seq)

    def _panel(self, payload: dict[str, Any]) -> tuple[np.ndarray, np.ndarray | None]:
        """The full panel: the blank frame (the zero pattern of the coding in use) outside the
        coded region; and a copy of the render. Both copied out of the frame's slot."""
        blank = self.d.panel.blank_frame()
        if self._zero is None or self._zero_of is not blank:
            self._zero, self._zero_of = PanelBuffer(blank), blank
        top, left = payload["region"][:2]
        grey, rgb = self.worker.arrays(payload)
        panel = self._zero.frame(top, left, grey)
        rgb = None if rgb is None else rgb.copy()
        del grey  # no view into the slot outlives this call
        return panel, rgb

    def _crashed(self) -> None:
        code = self.worker.process.exitcode if self.worker.process is not None else None
        self.crashes += 1
        message = f"frame worker (pid {self.worker.pid}) died with exit code {code}"
        log.error("%s; lasers off, SLM blanked, restarting", message)
        # The panel may hold a half-updated or stale frame the daemon no longer controls: the
        # light path is affected, so the lasers go off first.
        try:
            self.d.laser.off()
            message += "; lasers switched off"
        except Exception as exc:
            message += f"; lasers off FAILED: {exc}"
        with contextlib.suppress(Exception):
            self.d.panel.blank()
        self.d._error("frame worker", message)
        if self.pending is not None:  # its slot goes with the worker: never shown
            self.frames_dropped += 1
            self.pending = None
        self.worker.close(timeout_s=0.5)
        self.state = "crashed"
        self.sent_seq = 0
        self._restart_at = time.monotonic() + RESTART_BACKOFF_S

    def status(self) -> dict[str, Any]:
        info = self.model_info or {}
        slm = getattr(getattr(self.d.panel, "devices", None), "slm", None)
        pacing = f"timer: one frame per refresh at {1 / self.refresh_s:g} Hz (slm.refresh_hz)"
        if getattr(slm, "vsync_detail", ""):  # the framebuffer's FBIO_WAITFORVSYNC, or why not
            pacing += f"; {slm.vsync_detail}"
        return {"state": self.state, "pid": self.worker.pid, "alive": self.worker.alive,
                "model": self.model_path, "scene": self.scene_path,
                "model_variant": info.get("variant"),
                "model_variant_reason": info.get("variant_reason"),
                "sent_seq": self.sent_seq, "shown_seq": self.shown_seq,
                "frames_shown": self.frames_shown, "frames_dropped": self.frames_dropped,
                "frames_late": self.frames_late,
                "last_frame_age_ms": (None if self.last_age_s is None
                                      else round(self.last_age_s * 1e3, 3)),
                "max_frame_age_ms": round(self.max_age_s * 1e3, 3),
                "refresh_hz": round(1 / self.refresh_s, 6), "pacing": pacing,
                "transport": self.worker.transport, "crashes": self.crashes,
                "pose_warnings": self.warnings}


class PanelBuffer:
    """Full panel frames from the zero pattern and a coded region, built in the SLM's `[H, W, 3]`
    layout: a frame is a fresh copy of the interleaved zero pattern with the region interleaved
    in, returned as its `[3, H, W]` view. `nhfd.drivers.slm.to_rgb` takes that view as it is,
    where a channel-first frame costs a transposing copy of the whole panel (~10 ms at
    1920 x 1080)."""

    def __init__(self, zero: np.ndarray) -> None:
        self.zero_hwc = np.ascontiguousarray(np.asarray(zero, np.uint8).transpose(1, 2, 0))

    def frame(self, top: int, left: int, grey: np.ndarray) -> np.ndarray:
        out = self.zero_hwc.copy()
        _, h, w = grey.shape
        dst = out[top : top + h, left : left + w]
        for c in range(grey.shape[0]):
            dst[..., c] = grey[c]
        return out.transpose(2, 0, 1)


def _accepted_calibration(config: Any) -> Any:
    """The calibration this process applies, for the worker; None when there is none to keep
    (the worker's own load then says why, with each frame)."""
    try:
        return active_calibration(config)
    except ValueError:
        return None


def apply_camera_roi(bench: Any, config: Any) -> None:
    """Give the simulated camera the configured sensor region (daemon.camera_roi_px): the
    camera is rebuilt, because its fixed-pattern noise is drawn for its region at creation."""
    roi = list(config.daemon.camera_roi_px)
    if not roi or bench.camera is None or config.devices.camera != "simulated":
        return
    with contextlib.suppress(Exception):
        bench.camera.close()
    camera = factory.make_camera(config.devices, slm=bench.slm,
                                 laser=SimpleNamespace(twin=bench.laser_twin),
                                 stage=bench.stage, roi=tuple(roi))
    if camera is not None:
        camera.open()
    bench.camera = camera

