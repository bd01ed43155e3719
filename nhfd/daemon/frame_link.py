"""The daemon's side of the frame worker: the spawned process that renders, runs the network
and codes frames (`nhfd.pipeline.worker`); the messages they exchange are
`nhfd.worker_messages`' (docs/frames.md, "The worker's pipe", has them in one table).

Why a process: rendering, inference and propagation hold the CPU for tens of milliseconds at a
time; in the daemon's own process they would delay the control loop that feeds the laser
guardian's heartbeat. Why spawned, not forked: a fork copies the daemon's threads' locks and
the already-initialised thread pools of torch/OpenMP in whatever state they are in; a fresh
interpreter gets its thread counts in its environment before any pool exists.

The daemon spawns the worker by its module's name (`WORKER_MODULE`) and learns everything of
the model (what status reports of it, why one was refused) as data over the pipe: nothing here
imports the pipeline, the models or torch. Views go out in a `FrameRequest`, frames come back
in a `FrameDone` holding an `nhfd.frame_message.FrameMessage`, a load's answer is a `Loaded`
holding a `ModelLoaded` (the model's `ModelInfo` itself and how it serves) or a `SceneLoaded`:
L0 values both sides import, matched by type and read by name. A message of another type is an
error in `status`, never an exception out of the control loop. `FrameLink` never blocks on the
pipe: it polls it once per control-loop tick.

`FrameLink` knows nothing of the daemon: it gets its configuration, the view slot, a getter of
the panel and its `FrameEvents` (shown, error, crashed, SLM lost, capture) at construction. It
keeps the worker's lifecycle (its state a `LinkState`: spawn, crash, restart) and the view in
the worker (an `InFlight`), and composes three parts, each built with what it uses:

  `LoadQueue` (`load_queue`)        load jobs' loads: queued from their threads, sent by the
                                    control loop, answered; what the worker serves since; the
                                    served model and scene again after a crash
  `FramePacer` (`pacing`)           when the frame back goes to the panel (one per refresh), a
                                    refinement's K subframes in turn, the panels reused
                                    (`PanelBuffer`), the counts
  `CaptureRelay` (`capture_relay`)  citl's capture requests to the bench job and its answers
                                    back; emission sessions' ends

Load jobs' threads only queue a `LoadRequest` and wait on it: the control loop sends it, and on
the worker's answer updates the link and finishes the request, so no field is written from two
threads.

Frames cross in shared memory (docs/frames.md): `FrameWorker` creates `SLOTS` (one) segment
named `nhfd-<pid>-<n>-<slot>` in /dev/shm, sized for the whole panel (a grey region and its
render can never be larger, so a model, scene or refocus that changes the window needs no new
slot), and unlinks it whenever the worker is closed: stop, crash, restart. The slot is named in
each frame request; the worker writes only that one, and the daemon names it again only after
it has copied the frame out, so no slot is overwritten while the daemon reads it. A
refinement's better frames come the same way, in refine slots (`REFINE_SLOTS`) that the
worker and the daemon hand back and forth: the daemon pastes one subframe per refresh straight
from the slot it shows, and gives the other back (`FrameWorker.free_refine`) once it shows a
newer frame, so no turn of the control loop does work proportional to K subframes.

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
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import StrEnum
from multiprocessing import shared_memory
from typing import Any

import numpy as np

from nhfd.calibration import Calibration, CalibrationStore
from nhfd.config import Config, FramesSettings
from nhfd.frame_message import CaptureReply, CaptureRequest, FrameMessage, RefinedFrame
from nhfd.model_info import SUBFRAMES_RANGE
from nhfd.worker_messages import (
    FROM_WORKER,
    BetterFrame,
    CancelFrame,
    CaptureAsked,
    FrameCancelled,
    FrameDone,
    FrameFailed,
    FrameRequest,
    Loaded,
    LoadFailed,
    MessageRefused,
    ModelLoaded,
    RefineFailed,
    RefineSlotFree,
    SceneLoaded,
    Stop,
    ToWorker,
    WorkerReady,
    refusal,
)

from .capture_relay import CaptureRelay
from .load_queue import LoadQueue, LoadRequest
from .pacing import (
    FrameCounts,
    FramePacer,
    PanelBuffer,
    PanelView,
    Refinement,
    ViewSource,
    WaitingFrame,
)

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
# Refine slots per worker: a refinement's K subframes `[K, 3, H, W]`, or a K-subframe model's
# (each slot sized for the panel and the larger K). Three: the worker writes a better frame into
# one while the daemon shows another (double-buffered), and a K-subframe model's next frame
# takes the third while the one shown cycles; the daemon gives a slot back once it shows a newer
# one. (tmpfs pages: only what is written takes memory.)
REFINE_SLOTS = 3
# The /dev/shm names of the slots start with this (then the daemon's pid, a counter, the slot).
SHM_PREFIX = "nhfd-"
# The frame link's names, and those of its parts it re-exports (the daemon's citl, its tests and
# the calibration's twin import `PanelBuffer`, `WaitingFrame` and the panel's protocols here).
__all__ = [
    "LOAD_TIMEOUT_S", "REFINE_SLOTS", "RESTART_BACKOFF_S", "SHM_PREFIX", "SLOTS",
    "WORKER_MODULE", "FrameCounts", "FrameEvents", "FrameLink", "FrameWorker", "InFlight",
    "LinkState", "LoadRequest", "PanelBuffer", "PanelView", "Refinement", "ViewSource",
    "WaitingFrame", "run_by_name", "worker_environment",
]


# -- the worker process, seen from the daemon --------------------------------------------------


def worker_environment(frames: FramesSettings) -> dict[str, str]:
    """The worker's thread counts (`daemon.frames.worker_threads`, `worker_threading_layer`), for
    its environment: read once, when torch, numba and onnxruntime load in the spawned process, so
    they must be there before its first import."""
    threads = str(int(frames.worker_threads))
    env = {var: threads for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}
    env["NUMBA_THREADING_LAYER"] = str(frames.worker_threading_layer)
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


class FrameWorker:
    """The worker process and its pipe, seen from the daemon. Non-blocking except `start`."""

    _workers = itertools.count(1)

    def __init__(self, config: Config, calibration: CalibrationStore,
                 module: str = WORKER_MODULE) -> None:
        """`config`: the whole configuration, which the worker gets (it builds its frame
        settings from `[slm]`, `[optics]`, `[coding]`, `[daemon]` and the calibration file);
        here `daemon.frames.transport` and the panel's size (`[slm]`, the slots).
        `calibration`: the daemon's; the worker gets the version accepted here at its start.
        `module`: the worker's module, spawned by name."""
        self.config = config
        self.calibration = calibration
        self.module = module
        self.process: Any = None
        self.conn: Any = None
        self.pid: int | None = None
        self.ready = False
        self.transport = str(config.daemon.frames.transport)
        self.shms: list[shared_memory.SharedMemory] = []
        self.free_slots: list[int] = []
        self.refine_shms: list[shared_memory.SharedMemory] = []

    def start(self) -> None:
        """Make the slots and spawn the worker (blocks for the spawn, not for its import);
        its `WorkerReady` comes later on the pipe."""
        slots = self._make_slots() if self.transport == "shm" else None
        try:
            ctx = mp.get_context("spawn")
            here, there = ctx.Pipe(duplex=True)
            self.process = ctx.Process(target=run_by_name,
                                       args=(self.module,
                                             worker_environment(self.config.daemon.frames),
                                             there, self.config.model_dump(),
                                             _accepted(self.calibration), slots),
                                       name="nhfd-frame-worker", daemon=True)
            self.process.start()
        except BaseException:
            self._unlink()
            raise
        there.close()
        self.conn, self.ready, self.pid = here, False, self.process.pid

    def _make_slots(self) -> dict[str, Any]:
        """The frame slots, each for a grey region and a render as large as the panel, and the
        refine slots, each for `refine.subframes` grey regions as large as the panel (tmpfs
        pages: only what a frame writes takes memory)."""
        panel = self.config.slm
        plane = 3 * int(panel.height_px) * int(panel.width_px)
        # a refinement's K or a K-subframe model's, whichever is more
        k = max(int(self.config.refine.subframes), SUBFRAMES_RANGE[1])
        nbytes, refine_bytes = 2 * plane, k * plane
        tag = f"{SHM_PREFIX}{os.getpid()}-{next(self._workers)}"
        try:
            for i in range(SLOTS):
                self.shms.append(shared_memory.SharedMemory(name=f"{tag}-{i}", create=True,
                                                            size=nbytes))
            for i in range(REFINE_SLOTS):
                self.refine_shms.append(shared_memory.SharedMemory(name=f"{tag}-r{i}",
                                                                   create=True,
                                                                   size=refine_bytes))
        except BaseException:
            self._unlink()
            raise
        self.free_slots = list(range(SLOTS))
        return {"names": [shm.name for shm in self.shms], "bytes": nbytes,
                "refine_names": [shm.name for shm in self.refine_shms],
                "refine_bytes": refine_bytes}

    def take_slot(self) -> int | None:
        """A slot the worker may write (None: pickled transport). LookupError if none is free:
        the link never asks while it holds one (`FrameLink._ready_to_send`)."""
        if self.transport != "shm":
            return None
        if not self.free_slots:
            raise LookupError("no free frame slot")
        return self.free_slots.pop(0)

    def release(self, slot: int | None) -> None:
        """Give frame slot `slot` back once its frame is shown or dropped (None, pickled transport:
        nothing to give back)."""
        if slot is not None and slot not in self.free_slots and slot < len(self.shms):
            self.free_slots.append(slot)

    def arrays(self, message: FrameMessage) -> tuple[np.ndarray, np.ndarray | None]:
        """A frame's grey region `[3, h, w]` and render `[3, H, W]` (or None), uint8: views into
        its slot (copy before releasing it), or the arrays pickled in the message."""
        if message.slot is None:
            if message.grey is None:
                raise ValueError("a frame message with neither a slot nor its grey region")
            return message.grey, message.rgb
        buf = self.shms[message.slot].buf
        if message.grey_hwc:  # `[h, w, 3]` in the slot: its `[3, h, w]` view
            c, h, w = message.grey_shape
            grey = np.ndarray((h, w, c), np.uint8, buffer=buf).transpose(2, 0, 1)
        else:
            grey = np.ndarray(message.grey_shape, np.uint8, buffer=buf)
        rgb = (np.ndarray(message.rgb_shape, np.uint8, buffer=buf, offset=grey.nbytes)
               if message.rgb_shape else None)
        return grey, rgb

    def refined_arrays(self, refined: RefinedFrame) -> np.ndarray:
        """A better frame's subframes `[K, 3, h, w]` uint8: a view into its refine slot (valid
        until the slot is given back), or the arrays pickled in the message. ValueError when
        they do not fit the slot."""
        if refined.slot is None:
            assert refined.grey is not None  # a report only carries no subframes
            return refined.grey
        shape = refined.grey_shape
        assert shape is not None  # RefinedFrame checks it goes with a slot
        if refined.slot >= len(self.refine_shms) or math.prod(shape) > \
                self.refine_shms[refined.slot].size:
            raise ValueError(f"refined subframes {list(shape)} in refine slot {refined.slot}: "
                             f"{len(self.refine_shms)} slots of the panel's size")
        return np.ndarray(shape, np.uint8, buffer=self.refine_shms[refined.slot].buf)

    def free_refine(self, slot: int | None) -> None:
        """Give refine slot `slot` back to the worker (it may write a better frame there)."""
        if slot is not None and self.alive:
            with contextlib.suppress(OSError, ValueError):
                self.send(RefineSlotFree(slot))

    @property
    def alive(self) -> bool:
        """Whether the worker process is running."""
        return self.process is not None and self.process.is_alive()

    def send(self, msg: ToWorker) -> None:
        """One message to the worker over its pipe (`nhfd.worker_messages.TO_WORKER`). Only the
        control loop sends: load jobs and bench jobs hand theirs to it, so the pipe needs no
        lock."""
        self.conn.send(msg)

    def receive(self) -> list[Any]:
        """Every message waiting on the pipe (never blocks); EOFError when the worker is gone.
        Whatever the worker sent: the frame link matches each by its type."""
        out = []
        while self.conn.poll(0):
            out.append(self.conn.recv())
        return out

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the worker (asked, then killed after `timeout_s`) and unlink its slots."""
        if self.process is None:
            return
        with contextlib.suppress(Exception):
            self.send(Stop())
        self.process.join(timeout_s)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(timeout_s)
        with contextlib.suppress(Exception):
            self.conn.close()
        self._unlink()

    def _unlink(self) -> None:
        """Remove the slots from /dev/shm (the worker is gone: nothing else maps them)."""
        for shm in (*self.shms, *self.refine_shms):
            with contextlib.suppress(FileNotFoundError):
                shm.unlink()
            with contextlib.suppress(BufferError):  # a view still alive: unmapped when freed
                shm.close()
        self.shms, self.free_slots, self.refine_shms = [], [], []


class LinkState(StrEnum):
    """Where the frame link stands with its worker (`status.frames.state` shows the value)."""

    IDLE = "idle"  # no worker yet: it starts with the first load
    STARTING = "starting"  # spawned, its WorkerReady not yet received
    RUNNING = "running"
    CRASHED = "crashed"  # died: restarted RESTART_BACKOFF_S later, with the same model and scene
    STOPPED = "stopped"  # closed for good


@dataclass(frozen=True)
class InFlight:
    """The view the worker is computing: its sequence number, when it went out (monotonic s),
    the shared-memory slot the worker may write (None: the pickled transport), whether it is a
    scene's exact frame with no model (seconds: a newer view cancels it) and whether that
    cancel was sent."""

    seq: int
    sent_s: float
    slot: int | None
    exact: bool = False
    cancelled: bool = False


@dataclass(frozen=True)
class FrameEvents:
    """How a `FrameLink` reports to its owner (the daemon), given at construction: it calls
    these on the control loop's thread and never reaches into the owner otherwise.

    shown     (seq): view `seq`'s frame is on the panel
    error     (source, message): a line for `status`'s errors ("frame worker", "slm")
    crashed   (message): the worker died ("frame worker (pid P) died with exit code C"); the
              owner makes the bench safe (lasers off, panel blanked) and records the error. The
              link restarts the worker after RESTART_BACKOFF_S.
    slm_lost  (detail): the SLM refused a frame because its output is lost (`SLMOutputLost`)
    capture   (req_id, request): a citl step of the view on the panel asks for the bench's
              captures (`CaptureRequest`); the owner answers later, from any thread, with
              `FrameLink.answer_capture` (`CaptureRelay`). None: every request is refused.
    """

    shown: Callable[[int], None]
    error: Callable[[str, str], None]
    crashed: Callable[[str], None]
    slm_lost: Callable[[str], None]
    capture: Callable[[int, CaptureRequest], None] | None = None


class FrameLink:
    """The daemon's use of the worker: send the newest view when the worker is free, show the
    frames it returns, load models and scenes, relay citl's captures, and report a worker crash
    (then restart it with the same model and scene).

    One thread owns it: the control loop's, which calls `step`, `close`, `status` and reads its
    counters. Load jobs run on threads of their own: `load_model` and `load_scene` only queue a
    `LoadRequest` and wait for the control loop to fill in its outcome, so every field here is
    written by the control loop alone. A queued load goes out at the loop's next step (within
    `daemon.arming.heartbeat_s`).

    Its parts: `loads` (a `LoadQueue`), `pacer` (a `FramePacer`), `relay` (a `CaptureRelay`);
    what they hold reads through here too (`model`, `shown_seq`, `refinement`, `wake_s`, ...)."""

    def __init__(self, config: Config, calibration: CalibrationStore, views: ViewSource,
                 panel: Callable[[], PanelView], events: FrameEvents,
                 worker_module: str = WORKER_MODULE) -> None:
        """`config`: the daemon's (`nhfd.config.Config`: slm.refresh_hz, the worker's
        settings). `calibration`: the daemon's, whose accepted version each worker starts
        with. `views`: the newest view requested (read only: `events.shown` marks it
        applied). `panel`: the panel in use now (a getter, asked each time it is used).
        `worker_module`: another worker speaking the same
        protocol (tests use a fake one)."""
        self.config = config
        self.views = views
        self.panel = panel
        self.events = events
        self.worker = FrameWorker(config, calibration, worker_module)
        self.state = LinkState.IDLE
        self.inflight: InFlight | None = None
        self.sent_seq = 0  # the newest view sent to a worker
        # The current view again (a new model or scene, a restarted worker, an SLM output back)
        self._resend = False
        self.crashes = 0
        self._restart_at = 0.0
        self.loads = LoadQueue(events.error)
        self.pacer = FramePacer(1.0 / float(config.slm.refresh_hz), views, panel,
                                lambda: self.worker, shown=events.shown, error=events.error,
                                slm_lost=events.slm_lost)
        self.relay = CaptureRelay(events.capture)

    # -- what the parts hold, read here ----------------------------------------------------------

    @property
    def model_path(self) -> str | None:
        """The model file the worker serves (None: none loaded yet)."""
        return self.loads.model_path

    @property
    def model(self) -> ModelLoaded | None:
        """What the worker reported of the model it serves (`status`'s "model" is its
        `to_json()`), or None."""
        return self.loads.model

    @property
    def scene_path(self) -> str | None:
        """The scene file the worker renders (None: none loaded yet)."""
        return self.loads.scene_path

    @property
    def scene(self) -> SceneLoaded | None:
        """What the worker reported of the scene it renders, or None."""
        return self.loads.scene

    @property
    def waiting(self) -> WaitingFrame | None:
        """The frame back from the worker that waits for its refresh, if any."""
        return self.pacer.waiting

    @property
    def refinement(self) -> Refinement | None:
        """The refinement of the view on the panel, if it asked for one."""
        return self.pacer.refinement

    @property
    def shown_seq(self) -> int:
        """The sequence number of the view whose frame the panel shows last."""
        return self.pacer.shown_seq

    @property
    def subframes_shown(self) -> int:
        """How many subframes take turns on the panel now, one per refresh (1: a still frame)."""
        r = self.pacer.refinement
        return r.subframes if r is not None and self.pacer.cycling else 1

    @property
    def last_frame(self) -> np.ndarray | None:
        """The last view frame as shown (`[3, H, W]` uint8), or None."""
        return self.pacer.last_frame

    @property
    def last_rgb(self) -> np.ndarray | None:
        """The last shown frame's render (`[3, H, W]` uint8), or None."""
        return self.pacer.last_rgb

    @property
    def timings(self) -> dict[str, Any] | None:
        """The last shown frame's per-stage timings (ms), its sequence number, cache and
        clipping (`status`'s "timings")."""
        return self.pacer.timings

    @property
    def warnings(self) -> list[str]:
        """Why the last shown frame's view lies outside the model's pose envelope."""
        return self.pacer.warnings

    @property
    def counts(self) -> FrameCounts:
        """Frames shown, dropped and late (`status.frames`)."""
        return self.pacer.counts

    @property
    def refresh_s(self) -> float:
        """The panel's refresh period (s)."""
        return self.pacer.refresh_s

    @property
    def last_show_s(self) -> float:
        """When the last view frame went to the panel (monotonic s)."""
        return self.pacer.last_show_s

    @property
    def due_s(self) -> float:
        """When the next view frame may go to the panel (monotonic; `FramePacer.due_s`)."""
        return self.pacer.due_s

    @property
    def send_at_s(self) -> float:
        """When the next view may go to the worker (monotonic; `FramePacer.send_at_s`)."""
        return self.pacer.send_at_s

    # -- lifecycle (the control loop's thread) -------------------------------------------------

    def start(self) -> None:
        """Spawn the worker; the model and scene it had (after a crash) load again."""
        self.worker.start()
        self.state = LinkState.STARTING
        self.loads.restarted()
        self._send_loads()

    def ensure_started(self) -> None:
        """Start the worker unless it runs (the first load does this too): a daemon with no
        model or scene (most tests, a bench used only for captures) never pays for a process
        that imports torch. The control loop's thread only."""
        if self.state == LinkState.IDLE:
            self.start()

    def close(self) -> None:
        """Stop the worker for good; every load still waiting fails ("the frame worker
        stopped")."""
        self.state = LinkState.STOPPED
        self.relay.cancelled()
        # A frame waiting for its refresh, or in the worker: its slot goes with the worker, as
        # does the refinement's refine slot.
        self.inflight = None
        self.pacer.forget()
        self.worker.close()
        self.loads.close()

    # -- loads (from load jobs' threads) --------------------------------------------------------

    def load_model(self, path: str) -> ModelLoaded:
        """Blocks the calling job until the worker has the model (what it reports of it), or
        raises with the worker's reason (a ModelMismatch names the field); on failure the old
        model keeps running."""
        result = self._load(LoadRequest("model", path))
        assert isinstance(result, ModelLoaded)  # `LoadQueue.answered` checked the kind
        return result

    def load_scene(self, path: str) -> SceneLoaded:
        """Blocks the calling job until the worker has the scene (its counts, centre, up axis),
        or raises with the worker's reason; on failure the old scene keeps rendering."""
        result = self._load(LoadRequest("scene", path))
        assert isinstance(result, SceneLoaded)
        return result

    def _load(self, request: LoadRequest) -> ModelLoaded | SceneLoaded:
        # Only the queue is touched from this thread (the state is read, never written); the
        # control loop sends the load, and on the worker's answer records the new model or
        # scene and finishes the request.
        if self.state == LinkState.STOPPED:
            raise ValueError("the frame worker stopped")
        return self.loads.load(request, LOAD_TIMEOUT_S, lambda: self.state == LinkState.STOPPED)

    def _send_loads(self) -> None:
        """Queued loads to the worker, starting it for the first; held while it restarts."""
        if self.loads.take() and self.state == LinkState.IDLE:
            self.start()  # sends them
            return
        if self.state not in (LinkState.STARTING, LinkState.RUNNING):
            return
        if self.loads.send(self.worker.send):
            self.relay.cancelled()  # the worker cancels its refinement for any load

    @property
    def pipe(self) -> Any:
        """The worker's end of the pipe while `step` drains it (the worker starting or
        running), else None: the control loop keeps it in its selector, so a frame, a load's
        answer or the worker's death wakes the loop at once."""
        if self.state in (LinkState.STARTING, LinkState.RUNNING):
            return self.worker.conn
        return None

    def resend(self) -> None:
        """Send the current view again at the next step (the panel lost it: an SLM output
        back). The control loop's thread only."""
        self._resend = True

    # -- the control loop's part ---------------------------------------------------------------

    def step(self) -> None:
        """Once per tick: take queued loads, collect what the worker sent, show the newest frame
        when its refresh is due, send the newest view."""
        self._send_loads()
        if self.state in (LinkState.IDLE, LinkState.STOPPED):
            return
        if self.state == LinkState.CRASHED:
            if time.monotonic() >= self._restart_at:
                self.worker = FrameWorker(self.config, self.worker.calibration,
                                          self.worker.module)
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
        for seq, reason in self.relay.emission_ends():
            self.pacer.emission_ended(seq, reason)
        self.relay.send_answers(self.worker.send)
        self.pacer.show_due()
        self._send_next()

    @property
    def wake_s(self) -> float:
        """When the control loop must step again (monotonic; inf: nothing is waiting): for a
        frame waiting for its refresh, the next subframe, or a newer view waiting for its time
        to go out."""
        if self.pacer.waiting is not None or self.pacer.cycling:
            return self.pacer.due_s
        if self._ready_to_send():
            return self.pacer.send_at_s  # the step then sends it (_send_next)
        return math.inf

    def _ready_to_send(self) -> bool:
        """Whether the newest view may go to the worker, its time (`send_at_s`) aside: the worker
        runs with a model and a scene, it computes nothing of ours and no frame waits for its
        refresh (one frame at a time: the next view is taken only once the frame before it is on
        the panel, so what the worker computes is the newest view then, and the slot is free),
        and a view newer than the last sent is waiting (or the current one is to go again)."""
        views = self.views
        # Without a model, a view above "network" still goes: the worker serves its exact
        # frame (the scene's own hologram, seconds) and refines it.
        served = self.loads.model_path is not None or (views.view is not None
                                                       and views.view.quality != "network")
        return (self.state == LinkState.RUNNING and self.worker.ready
                and self.inflight is None and self.pacer.waiting is None
                and served and self.loads.scene_path is not None
                and views.view is not None and (views.seq > self.sent_seq or self._resend))

    def _handle(self, msg: Any) -> None:
        """One message from the worker, by its type; one of another type is an error in
        status (the loop goes on)."""
        match msg:
            case WorkerReady():
                self.worker.ready = True
                self.state = LinkState.RUNNING
            case Loaded() | LoadFailed():
                if self.loads.answered(msg):
                    self._resend = True  # the current view again, with the new model or scene
            case FrameDone(seq=seq, message=message, subframes=subframes):
                self._frame_done(seq, message, subframes)
            case FrameFailed(seq=seq, error=error):
                self._inflight_over()
                self.events.error("frame worker", f"view {seq}: {error}")
            case FrameCancelled():  # a load or a newer view overtook an exact frame
                self._inflight_over()
                self.pacer.counts.dropped += 1
                self.pacer.counts.cancelled += 1
            case BetterFrame(seq=seq, frame=frame):
                self.pacer.refined(seq, frame)
            case CaptureAsked(seq=seq, req_id=req_id, request=request):
                current = self.views.seq == seq and self.pacer.shown_seq == seq
                if self.relay.asked(seq, req_id, request, current, self.worker.send):
                    self.pacer.counted_capture(seq)
            case RefineFailed(seq=seq, error=error):
                self.pacer.refine_failed(seq, error)
            case MessageRefused(error=error):
                self.events.error("frame worker", f"refused {error}")
            case _:
                self.events.error("frame worker", refusal(msg, "the frame link", FROM_WORKER))

    def _frame_done(self, seq: int, message: Any, subframes: RefinedFrame | None = None
                    ) -> None:
        """View `seq`'s frame (and a K-subframe model's K) is back: it waits for its refresh
        (`FramePacer.arrived`)."""
        inflight, self.inflight = self.inflight, None
        if not isinstance(message, FrameMessage):  # a worker speaking another protocol
            if inflight is not None:
                self.worker.release(inflight.slot)
            self.events.error("frame worker", f"view {seq}: not a frame message: "
                                              f"{type(message).__name__}")
            return
        sent_s = inflight.sent_s if inflight is not None and inflight.seq == seq else None
        self.pacer.arrived(seq, message, sent_s, subframes)

    def _inflight_over(self) -> None:
        """The view in the worker came to nothing (failed, cancelled): its slot is free."""
        if self.inflight is not None:
            self.worker.release(self.inflight.slot)
        self.inflight = None

    def _cancel_overtaken_exact(self) -> None:
        """A scene's exact frame with no model takes seconds: when a newer view waits, the
        worker is asked to cancel it (it answers `FrameCancelled` and the newest view goes out
        at once) instead of the newer one waiting its turn."""
        f = self.inflight
        if f is None or not f.exact or f.cancelled or self.views.seq <= f.seq:
            return
        self.worker.send(CancelFrame(f.seq))
        self.inflight = replace(f, cancelled=True)

    def _send_next(self) -> None:
        self._cancel_overtaken_exact()
        if not self._ready_to_send() or time.monotonic() < self.pacer.send_at_s:
            return  # the loop wakes at send_at_s (wake_s)
        seq, view = self.views.seq, self.views.view
        assert view is not None  # `_ready_to_send`
        shm_slot = self.worker.take_slot()  # free: no frame of ours is out or waiting
        self.worker.send(FrameRequest(seq, view, shm_slot))
        self.relay.cancelled()  # the worker cancels the refinement that asked
        # Without a model, a view above "network" is the scene's exact frame: seconds.
        exact = self.loads.model_path is None and view.quality != "network"
        self.inflight = InFlight(seq, time.monotonic(), shm_slot, exact=exact)
        if self.sent_seq and seq > self.sent_seq + 1:
            self.pacer.counts.dropped += seq - self.sent_seq - 1  # overtaken, never computed
        self.sent_seq = max(self.sent_seq, seq)
        self._resend = False

    def _crashed(self) -> None:
        code = self.worker.process.exitcode if self.worker.process is not None else None
        self.crashes += 1
        self.relay.cancelled()  # nobody waits for the captures now
        message = f"frame worker (pid {self.worker.pid}) died with exit code {code}"
        log.error("%s; lasers off, SLM blanked, restarting", message)
        # The panel may hold a half-updated or stale frame the daemon no longer controls: the
        # owner switches the lasers off and blanks the panel (`FrameEvents.crashed`).
        self.events.crashed(message)
        # Its refine slot goes with the worker (the panel is blanked); a frame waiting for its
        # refresh too: never shown.
        self.pacer.forget(crashed=True)
        self.worker.close(timeout_s=0.5)
        self.loads.worker_gone()
        self.state = LinkState.CRASHED
        self._resend = True
        self._restart_at = time.monotonic() + RESTART_BACKOFF_S

    # -- the emission sessions and citl's captures (any thread) ---------------------------------

    def emission_ended(self, reason: str) -> None:
        """An emission session ended (a laser off, disarm, stop, shutdown, the guardian's own
        disarm; any thread): the citl run of the view on the panel ends with it. Its capture
        requests are refused by the owner (`FrameEvents.capture`); here `status` says why at
        once (applied at the control loop's next step)."""
        self.relay.emission_ended(self.views.seq, reason)

    def capture_phase(self, req_id: int, what: str) -> None:
        """Where the bench's capture job for request `req_id` is (its thread only)."""
        self.relay.phase(req_id, what)

    def capture_wanted(self, req_id: int) -> bool:
        """Whether the worker still waits for capture request `req_id` (any thread: a bench job
        stops capturing once it is not)."""
        return self.relay.wanted(req_id)

    def answer_capture(self, req_id: int, reply: CaptureReply) -> None:
        """The bench's answer to capture request `req_id` (any thread); the control loop sends
        it at its next step, while the worker still waits for it."""
        self.relay.answer(req_id, reply)

    # -- status ---------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """`status.frames`: the worker, what it serves, the sequence numbers, the counts and
        the pacing."""
        model = self.loads.model
        return {"state": str(self.state), "pid": self.worker.pid, "alive": self.worker.alive,
                "model": self.loads.model_path, "scene": self.loads.scene_path,
                "model_variant": None if model is None else model.variant,
                "model_variant_reason": None if model is None else model.variant_reason,
                "sent_seq": self.sent_seq, "shown_seq": self.pacer.shown_seq,
                **self.pacer.status(), "transport": self.worker.transport,
                "crashes": self.crashes, "pose_warnings": self.pacer.warnings,
                "refine": self.pacer.refine_status(self.relay.waiting_phase())}


def _accepted(calibration: CalibrationStore) -> Calibration | None:
    """The calibration this process applies, for the worker; None when there is none to keep
    (the worker's own load then says why, with each frame)."""
    try:
        return calibration.active()
    except ValueError:
        return None
