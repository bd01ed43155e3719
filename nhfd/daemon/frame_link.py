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
"""

from __future__ import annotations

import contextlib
import importlib
import itertools
import logging
import multiprocessing as mp
import os
import threading
import time
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

    def __init__(self, config: Any) -> None:
        self.config = config
        self.process: Any = None
        self.conn: Any = None
        self.pid: int | None = None
        self.ready = False
        self._send_lock = threading.Lock()  # load jobs send from their own thread
        self.pending: dict[int, Pending] = {}

    def start(self) -> None:
        ctx = mp.get_context("spawn")
        here, there = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=run_by_name,
                                   args=(WORKER_MODULE, worker_environment(self.config), there,
                                         self.config.model_dump(),
                                         _accepted_calibration(self.config)),
                                   name="nhfd-frame-worker", daemon=True)
        self.process.start()
        there.close()
        self.conn, self.ready, self.pid = here, False, self.process.pid

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
        for p in self.pending.values():
            p.ok, p.result = False, "the frame worker stopped"
            p.done.set()
        self.pending.clear()


class FrameLink:
    """The daemon's use of the worker: send the newest view when the worker is free, show the
    frames it returns, load models and scenes, and turn a worker crash into lasers off plus an
    error in `status` (then restart it with the same model and scene)."""

    def __init__(self, daemon: FrameHost) -> None:
        self.d = daemon
        self.worker = FrameWorker(daemon.config)
        self.model_path: str | None = None
        self.model_info: dict[str, Any] | None = None
        self.scene_path: str | None = None
        self.inflight: tuple[int, float] | None = None  # (seq, sent at perf_counter)
        self.sent_seq = 0
        self.shown_seq = 0
        self.timings: dict[str, Any] | None = None
        self.warnings: list[str] = []
        self.last_rgb: np.ndarray | None = None
        self.last_frame: np.ndarray | None = None
        self.frames_shown = 0
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
        """Once per tick: collect what the worker sent, show frames, send the newest view."""
        if self.state in ("idle", "stopped"):
            return
        if self.state == "crashed":
            if time.monotonic() >= self._restart_at:
                self.worker = FrameWorker(self.d.config)
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
        self._send_next()

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
            self._show(msg[1], msg[2])
        elif kind == "frame_error":
            seq, message = msg[1], msg[2]
            self.inflight = None
            self.d._error("frame worker", f"view {seq}: {message}")

    def _send_next(self) -> None:
        if self.inflight is not None or not self.worker.ready:
            return
        if self.model_path is None or self.scene_path is None:
            return
        slot = self.d.views
        if slot.view is None or slot.seq <= self.sent_seq:
            return
        seq, view = slot.seq, slot.view
        self.worker.send(("frame", seq, view))
        self.inflight = (seq, time.perf_counter())
        self.sent_seq = seq

    def _show(self, seq: int, payload: dict[str, Any]) -> None:
        sent_at = self.inflight[1] if self.inflight and self.inflight[0] == seq else None
        self.inflight = None
        t0 = time.perf_counter()
        try:  # the panel applies the colour mode, and holds the frame back during a capture
            frame = self.d.panel.show_view(self._panel(payload), seq)
        except Exception as exc:
            self.d._error("slm", f"showing view {seq}: {type(exc).__name__}: {exc}")
            if isinstance(exc, SLMOutputLost):  # the control loop switches lasers off
                self.d.bench.note_slm_lost(str(exc))
            return
        done = time.perf_counter()
        stages = dict(payload["timings_s"])
        stages["output"] = done - t0
        timings = {f"{k}_ms": round(v * 1e3, 3) for k, v in stages.items()}
        if sent_at is not None:
            timings["view_to_slm_ms"] = round((done - sent_at) * 1e3, 3)
        timings.update(seq=seq, cached=payload["cached"],
                       clipped_fraction=list(payload["clipped_fraction"]))
        self.timings = timings
        self.warnings = list(payload["warnings"])
        self.last_rgb, self.last_frame = payload.get("rgb"), frame
        self.shown_seq = seq
        self.frames_shown += 1
        self.d.views.mark_applied(seq)

    def _panel(self, payload: dict[str, Any]) -> np.ndarray:
        """The full panel: the blank frame (the zero pattern of the coding in use) outside the
        coded region."""
        blank = self.d.panel.blank_frame()
        if self._zero is None or self._zero_of is not blank:
            self._zero, self._zero_of = PanelBuffer(blank), blank
        top, left = payload["region"][:2]
        return self._zero.frame(top, left, payload["grey"])

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
        self.worker.close(timeout_s=0.5)
        self.state = "crashed"
        self.sent_seq = 0
        self._restart_at = time.monotonic() + RESTART_BACKOFF_S

    def status(self) -> dict[str, Any]:
        return {"state": self.state, "pid": self.worker.pid, "alive": self.worker.alive,
                "model": self.model_path, "scene": self.scene_path,
                "sent_seq": self.sent_seq, "shown_seq": self.shown_seq,
                "frames_shown": self.frames_shown, "crashes": self.crashes,
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

