"""The daemon's side of the frame worker: the spawned process that renders, runs the network
and codes frames (`nhfd.pipeline.worker`, whose docstring has the pipe's protocol).

Why a process: rendering, inference and propagation hold the CPU for tens of milliseconds at a
time; in the daemon's own process they would delay the control loop that feeds the laser
guardian's heartbeat. Why spawned, not forked: a fork copies the daemon's threads' locks and
the already-initialised thread pools of torch/OpenMP in whatever state they are in; a fresh
interpreter gets its thread counts in its environment before any pool exists.

The daemon spawns the worker by its module's name (`WORKER_MODULE`) and learns everything of
the model (what status reports of it, why one was refused) as data over the pipe: nothing here
imports the pipeline, the models or torch. Views go out as `nhfd.views.View` and frames come
back as `nhfd.frame_message.FrameMessage` (L0 values both sides import, read by name).
`FrameLink` never blocks on the pipe: it polls it once per control-loop tick, and it shows the
frames it gets (the "output" stage: the coded region pasted into the blank frame,
`PanelBuffer`).

`FrameLink` knows nothing of the daemon: it gets its configuration, the view slot, a getter of
the panel and its `FrameEvents` (shown, error, crashed, SLM lost) at construction. Its state is
a `LinkState`; the view in the worker an `InFlight`, a frame waiting for its refresh a
`WaitingFrame`. Load jobs' threads only queue a `LoadRequest` and wait on it: the control loop
sends it, and on the worker's answer updates the link and finishes the request, so no field
is written from two threads.

Frames cross in shared memory (docs/frames.md): `FrameWorker` creates `SLOTS` (one) segment
named `nhfd-<pid>-<n>-<slot>` in /dev/shm, sized for the whole panel (a grey region and its
render can never be larger, so a model, scene or refocus that changes the window needs no new
slot), and unlinks it whenever the worker is closed: stop, crash, restart. The slot is named in
each frame request; the worker writes only that one, and the daemon names it again only after
it has copied the frame out, so no slot is overwritten while the daemon reads it. A
refinement's better frames come the same way, in two refine slots (`REFINE_SLOTS`) that the
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
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from enum import StrEnum
from multiprocessing import shared_memory
from typing import Any, Protocol

import numpy as np

from nhfd.calibration import Calibration, active_calibration
from nhfd.config import Config, DaemonSettings
from nhfd.drivers.slm import SLMOutputLost
from nhfd.frame_message import (
    CaptureReply,
    CaptureRequest,
    FrameMessage,
    RefinedFrame,
    Region,
    is_interleaved,
)
from nhfd.views import View

log = logging.getLogger("nhfd.daemon.frame_link")

# How long a load may take in the worker before the load job gives up waiting (s).
LOAD_TIMEOUT_S = 120.0
# How often a waiting load job looks whether the link has stopped (s): a load queued just as the
# daemon closes is answered by no control loop.
WAIT_POLL_S = 0.1
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
# Refine slots per worker: a refinement's K subframes `[K, 3, H, W]` (each slot sized for the
# panel and `refine.subframes`). Two, double-buffered: the worker writes a better frame into one
# while the daemon shows the other, and the daemon gives a slot back once it shows a newer one.
REFINE_SLOTS = 2
# Panels the frame link builds in turn (`PanelBuffer`'s `reuse`): the one shown last stays
# whole (the panel's `resume` after a capture shows it again) while the next is built.
PANELS_REUSED = 2
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

    @property
    def vsync_detail(self) -> str:
        """How the SLM paces frames to its refresh, when it says; "" otherwise."""
        ...

    def show_view(self, frame: np.ndarray, seq: int) -> np.ndarray:
        """Show view `seq`'s full-panel frame (`[3, H, W]` uint8) in the colour mode; returns the
        frame as shown."""
        ...

    def blank_frame(self) -> np.ndarray:
        """The blank of the coding in use, `[3, H, W]` uint8: the panel around every view frame."""
        ...

    def blank(self) -> None:
        """Show the blank."""
        ...


class ViewSource(Protocol):
    """The newest view requested and its sequence number (`nhfd.daemon.views.ViewSlot`)."""

    seq: int
    view: View | None


# -- the worker process, seen from the daemon --------------------------------------------------


def worker_environment(settings: DaemonSettings) -> dict[str, str]:
    """The worker's thread counts (`daemon.frames.worker_threads`, `worker_threading_layer`), for
    its environment: read once, when torch, numba and onnxruntime load in the spawned process, so
    they must be there before its first import."""
    threads = str(int(settings.frames.worker_threads))
    env = {var: threads for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}
    env["NUMBA_THREADING_LAYER"] = str(settings.frames.worker_threading_layer)
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


@dataclass
class LoadRequest:
    """A model or scene load: queued by a load job (or by a restart, `reload`), sent by the
    control loop, which fills in its outcome (`finish`) and sets `done`; the job's thread only
    waits for that."""

    kind: str  # "model" | "scene"
    path: str
    reload: bool = False  # a restarted worker's: nobody waits, a failure is an error in status
    done: threading.Event = field(default_factory=threading.Event)
    ok: bool = False
    result: Any = None

    def finish(self, ok: bool, result: Any) -> None:
        """The control loop's outcome: `ok` and `result` (the worker's report, or its reason for
        refusing), then `done` set."""
        self.ok, self.result = ok, result
        self.done.set()  # publishes ok and result to the waiting thread

    def wait(self, timeout_s: float, stopped: Callable[[], bool] = lambda: False) -> Any:
        """The worker's report of the load, or ValueError with its reason (TimeoutError when
        it did not answer within `timeout_s`; ValueError at once when `stopped()` turns true:
        no control loop will answer then)."""
        deadline = time.monotonic() + timeout_s
        while not self.done.wait(min(WAIT_POLL_S, max(0.0, deadline - time.monotonic()))):
            if stopped():
                raise ValueError("the frame worker stopped")
            if time.monotonic() >= deadline:
                raise TimeoutError(f"the frame worker did not answer within {timeout_s:g} s")
        if not self.ok:
            raise ValueError(str(self.result))
        return self.result


class FrameWorker:
    """The worker process and its pipe, seen from the daemon. Non-blocking except `start`."""

    _ids = itertools.count(1)
    _workers = itertools.count(1)

    def __init__(self, config: Config, module: str = WORKER_MODULE) -> None:
        """`config`: the whole configuration, which the worker gets (it builds its frame
        settings from `[slm]`, `[optics]`, `[coding]`, `[daemon]` and the calibration); here
        `daemon.frames.transport` and the panel's size (`[slm]`, the slots). `module`: the
        worker's module, spawned by name."""
        self.config = config
        self.module = module
        self.process: Any = None
        self.conn: Any = None
        self.pid: int | None = None
        self.ready = False
        # Loads sent, by request id, until the worker answers. Only the control loop sends:
        # load jobs hand their loads to it (`FrameLink._load`), so the pipe needs no lock.
        self.pending: dict[int, LoadRequest] = {}
        self.transport = str(config.daemon.frames.transport)
        self.shms: list[shared_memory.SharedMemory] = []
        self.free_slots: list[int] = []
        self.refine_shms: list[shared_memory.SharedMemory] = []

    def start(self) -> None:
        """Make the slots and spawn the worker (blocks for the spawn, not for its import);
        its "ready" comes later on the pipe."""
        slots = self._make_slots() if self.transport == "shm" else None
        try:
            ctx = mp.get_context("spawn")
            here, there = ctx.Pipe(duplex=True)
            self.process = ctx.Process(target=run_by_name,
                                       args=(self.module, worker_environment(self.config.daemon),
                                             there, self.config.model_dump(),
                                             _accepted_calibration(self.config), slots),
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
        nbytes, refine_bytes = 2 * plane, int(self.config.refine.subframes) * plane
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
                self.send(("refine_free", slot))

    @property
    def alive(self) -> bool:
        """Whether the worker process is running."""
        return self.process is not None and self.process.is_alive()

    def send(self, msg: tuple) -> None:
        """One message to the worker over its pipe (a tuple: the kind first)."""
        self.conn.send(msg)

    def request(self, request: LoadRequest) -> None:
        """Send a load; its answer finishes it (`FrameLink._handle`), or the worker's end."""
        req_id = next(self._ids)
        self.pending[req_id] = request
        self.send((request.kind, req_id, request.path))

    def receive(self) -> list[tuple]:
        """Every message waiting on the pipe (never blocks); EOFError when the worker is gone."""
        out = []
        while self.conn.poll(0):
            out.append(self.conn.recv())
        return out

    def close(self, timeout_s: float = 2.0) -> list[LoadRequest]:
        """Stop the worker (asked, then killed after `timeout_s`) and unlink its slots; the
        loads it had not answered fail ("the frame worker stopped") and are returned."""
        if self.process is None:
            return []
        with contextlib.suppress(Exception):
            self.send(("stop",))
        self.process.join(timeout_s)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(timeout_s)
        with contextlib.suppress(Exception):
            self.conn.close()
        self._unlink()
        failed = list(self.pending.values())
        for request in failed:
            request.finish(False, "the frame worker stopped")
        self.pending.clear()
        return failed

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
    STARTING = "starting"  # spawned, its "ready" not yet received
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
class WaitingFrame:
    """A frame back from the worker, waiting for its refresh: its view's sequence number, the
    worker's message, and when the view went out (monotonic s; None when it was not the one in
    flight)."""

    seq: int
    message: FrameMessage
    sent_s: float | None


@dataclass
class Refinement:
    """The refinement of the view on the panel (the progressive mode): its sequence number,
    the tier the view asked for, the worker's latest report (`nhfd.frame_message.REFINE_KEYS`;
    its "tier" is the stage running: a citl view's sgd steps say "sgd"), the better frame's
    subframes `[K, 3, h, w]` and where they go (shown in turn, one per refresh: each turn pastes
    one into a panel, never all K), the refine slot they are in, the one shown last, the citl
    capture requests so far, and why its emission session ended ("" while it holds)."""

    seq: int
    tier: str
    report: dict[str, Any]
    region: Region | None = None
    greys: np.ndarray | None = None
    slot: int | None = None
    index: int = 0
    swaps: int = 0
    captures: int = 0
    ended: str = ""

    @property
    def subframes(self) -> int:
        """How many subframes take turns on the panel (0: none refined yet)."""
        return 0 if self.greys is None else int(self.greys.shape[0])


@dataclass
class FrameCounts:
    """What `status.frames` counts (docs/frames.md): frames shown; views never computed because
    a newer one overtook them (latest wins), plus a frame waiting for its refresh when the
    worker crashed; frames shown more than one refresh after the worker finished them; and the
    ages (s, from the frame whole in its slot to the end of the panel write)."""

    shown: int = 0
    dropped: int = 0
    late: int = 0
    last_age_s: float | None = None
    max_age_s: float = 0.0

    def showed(self, age_s: float | None, refresh_s: float) -> None:
        """One more frame on the panel, `age_s` old (None: its age is unknown)."""
        self.shown += 1
        if age_s is not None:
            self.last_age_s, self.max_age_s = age_s, max(self.max_age_s, age_s)
            self.late += age_s > refresh_s


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
              `FrameLink.answer_capture`. None: every request is refused.
    """

    shown: Callable[[int], None]
    error: Callable[[str, str], None]
    crashed: Callable[[str], None]
    slm_lost: Callable[[str], None]
    capture: Callable[[int, CaptureRequest], None] | None = None


class FrameLink:
    """The daemon's use of the worker: send the newest view when the worker is free, show the
    frames it returns, load models and scenes, and report a worker crash (then restart it with
    the same model and scene).

    One thread owns it: the control loop's, which calls `step`, `close`, `status` and reads its
    counters. Load jobs run on threads of their own: `load_model` and `load_scene` only queue a
    `LoadRequest` and wait for the control loop to fill in its outcome, so every field here is
    written by the control loop alone. A queued load goes out at the loop's next step (within
    `daemon.arming.heartbeat_s`)."""

    def __init__(self, config: Config, views: ViewSource, panel: Callable[[], PanelView],
                 events: FrameEvents, worker_module: str = WORKER_MODULE) -> None:
        """`config`: the daemon's (`nhfd.config.Config`: slm.refresh_hz, the worker's
        settings). `views`: the newest view requested (read only: `events.shown` marks it
        applied). `panel`: the panel in use now (a getter, asked each time it is used).
        `worker_module`: another worker speaking the same
        protocol (tests use a fake one)."""
        self.config = config
        self.views = views
        self.panel = panel
        self.events = events
        self.worker = FrameWorker(config, worker_module)
        self.model_path: str | None = None
        self.model_info: dict[str, Any] | None = None  # what the worker reported at the load
        self.scene_path: str | None = None
        self.state = LinkState.IDLE
        self.inflight: InFlight | None = None
        self.waiting: WaitingFrame | None = None
        self.sent_seq = 0  # the newest view sent to a worker
        self.shown_seq = 0
        # The current view again (a new model or scene, a restarted worker, an SLM output back)
        self._resend = False
        self.timings: dict[str, Any] | None = None
        self.warnings: list[str] = []
        self.last_rgb: np.ndarray | None = None
        self.last_frame: np.ndarray | None = None
        self.counts = FrameCounts()
        self.refinement: Refinement | None = None  # of the view on the panel, if it asked
        self.refresh_s = 1.0 / float(config.slm.refresh_hz)
        self.last_show_s = -math.inf  # monotonic, when the last view frame went to the panel
        self.compute_s: float | None = None  # the worker's recent frame time, request to ready
        self.crashes = 0
        # Loads queued by load jobs' threads (the one thing they touch), and those taken from
        # it that wait for a worker to send them to.
        self._requests: queue.SimpleQueue[LoadRequest] = queue.SimpleQueue()
        self._unsent: list[LoadRequest] = []
        self._zero: PanelBuffer | None = None  # of the blank frame `_zero_of`, built on use
        self._zero_of: np.ndarray | None = None
        self._restart_at = 0.0
        # citl's capture requests the worker still waits for, and the answers bench jobs give
        # (from their threads) for the control loop to send.
        self._captures_wanted: set[int] = set()
        self._capture_answers: queue.SimpleQueue[tuple[int, CaptureReply]] = queue.SimpleQueue()
        # Where the bench's citl capture job is (request id, what it does), written by that
        # job's thread alone and read for `status`.
        self._capture_phase: tuple[int, str] = (0, "")
        # Emission sessions that ended (from any thread): (the newest view then, why), applied
        # to the refinement by the control loop.
        self._emission_ends: queue.SimpleQueue[tuple[int, str]] = queue.SimpleQueue()

    # -- lifecycle (the control loop's thread) -------------------------------------------------

    def start(self) -> None:
        """Spawn the worker; the model and scene it had (after a crash) load again."""
        self.worker.start()
        self.state = LinkState.STARTING
        if self.scene_path:
            self._unsent.insert(0, LoadRequest("scene", self.scene_path, reload=True))
        if self.model_path:
            self._unsent.insert(int(bool(self.scene_path)),
                                LoadRequest("model", self.model_path, reload=True))
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
        self._captures_wanted.clear()
        # A frame waiting for its refresh, or in the worker: its slot goes with the worker, as
        # does the refinement's refine slot.
        self.waiting = self.inflight = self.refinement = None
        self._report_failed_reloads(self.worker.close())
        self._take_requests()  # nothing queued may wait for a worker that will not come
        for request in self._unsent:
            request.finish(False, "the frame worker stopped")
        self._unsent.clear()

    # -- loads (from load jobs' threads) --------------------------------------------------------

    def load_model(self, path: str) -> dict[str, Any]:
        """Blocks the calling job until the worker has the model, or raises with the worker's
        reason (a ModelMismatch names the field); on failure the old model keeps running."""
        return self._load(LoadRequest("model", path))

    def load_scene(self, path: str) -> dict[str, Any]:
        """Blocks the calling job until the worker has the scene (its counts, centre, up axis),
        or raises with the worker's reason; on failure the old scene keeps rendering."""
        return self._load(LoadRequest("scene", path))

    def _load(self, request: LoadRequest) -> dict[str, Any]:
        # Only the queue is touched from this thread (the state is read, never written); the
        # control loop sends the load, and on the worker's answer records the new model or
        # scene and finishes the request.
        if self.state == LinkState.STOPPED:
            raise ValueError("the frame worker stopped")
        self._requests.put(request)
        return request.wait(LOAD_TIMEOUT_S, lambda: self.state == LinkState.STOPPED)

    def _take_requests(self) -> None:
        self._unsent.extend(_drain(self._requests))

    def _send_loads(self) -> None:
        """Queued loads to the worker, starting it for the first; held while it restarts."""
        self._take_requests()
        if self._unsent and self.state == LinkState.IDLE:
            self.start()  # sends them
            return
        if self.state not in (LinkState.STARTING, LinkState.RUNNING):
            return
        for request in self._unsent:
            self.worker.request(request)
            self._captures_wanted.clear()  # the worker cancels its refinement for any load
        self._unsent.clear()

    def _loaded(self, request: LoadRequest, ok: bool, result: Any) -> None:
        """The worker's answer to a load: on success the link serves the new model or scene
        (and the current view again with it); a restart's reload that failed is an error in
        status (no job waits for it)."""
        if ok:
            if request.kind == "model":
                self.model_path, self.model_info = request.path, result
            else:
                self.scene_path = request.path
            self._resend = True
        request.finish(ok, result)
        self._report_failed_reloads([request] if not ok else [])

    def _report_failed_reloads(self, requests: list[LoadRequest]) -> None:
        for r in requests:
            if r.reload:
                self.events.error("frame worker", f"reloading {r.kind} {r.path}: {r.result}")

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
                self.worker = FrameWorker(self.config, self.worker.module)
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
        self._apply_emission_ends()
        self._send_capture_answers()
        if self.waiting is not None and time.monotonic() >= self.due_s - DUE_SLACK_S:
            waiting, self.waiting = self.waiting, None
            self._show(waiting)
        elif self._cycling and time.monotonic() >= self.due_s - DUE_SLACK_S:
            self._show_subframe()
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
    def _cycling(self) -> bool:
        """Whether the panel shows time-multiplexed subframes, one per refresh."""
        r = self.refinement
        return r is not None and r.subframes > 1 and self.views.seq == r.seq

    @property
    def wake_s(self) -> float:
        """When the control loop must step again (monotonic; inf: nothing is waiting): for a
        frame waiting for its refresh, the next subframe, or a newer view waiting for its time
        to go out."""
        if self.waiting is not None or self._cycling:
            return self.due_s
        if self._ready_to_send():
            return self.send_at_s  # the step then sends it (_send_next)
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
        served = self.model_path is not None or (views.view is not None
                                                 and views.view.quality != "network")
        return (self.state == LinkState.RUNNING and self.worker.ready
                and self.inflight is None and self.waiting is None
                and served and self.scene_path is not None
                and views.view is not None and (views.seq > self.sent_seq or self._resend))

    def _handle(self, msg: tuple) -> None:
        kind = msg[0]
        if kind == "ready":
            self.worker.ready = True
            self.state = LinkState.RUNNING
        elif kind in ("model", "scene"):
            _, req_id, ok, result = msg
            request = self.worker.pending.pop(req_id, None)
            if request is not None:
                self._loaded(request, ok, result)
        elif kind == "frame":
            seq, message = msg[1], msg[2]
            inflight, self.inflight = self.inflight, None
            if not isinstance(message, FrameMessage):  # a worker speaking another protocol
                if inflight is not None:
                    self.worker.release(inflight.slot)
                self.events.error("frame worker", f"view {seq}: not a frame message: "
                                                  f"{type(message).__name__}")
                return
            sent_s = inflight.sent_s if inflight is not None and inflight.seq == seq else None
            if sent_s is not None and message.ready_s is not None:
                took = max(0.0, message.ready_s - sent_s)
                self.compute_s = took if self.compute_s is None else (
                    0.7 * self.compute_s + 0.3 * took)
            self.waiting = WaitingFrame(seq, message, sent_s)  # one frame at a time
        elif kind == "frame_error":
            seq, message = msg[1], msg[2]
            if self.inflight is not None:
                self.worker.release(self.inflight.slot)
            self.inflight = None
            self.events.error("frame worker", f"view {seq}: {message}")
        elif kind == "frame_cancelled":  # a load or a newer view overtook an exact frame
            if self.inflight is not None:
                self.worker.release(self.inflight.slot)
            self.inflight = None
            self.counts.dropped += 1
        elif kind == "refined":
            self._refined(msg[1], msg[2])
        elif kind == "capture":
            self._capture_requested(msg[1], msg[2], msg[3])
        elif kind == "refine_error":
            seq, message = msg[1], msg[2]
            self.events.error("frame worker", f"view {seq}: refinement failed: {message}")
            if self.refinement is not None and self.refinement.seq == seq:
                self.refinement.report = {**self.refinement.report, "stop": f"error: {message}"}

    def _capture_requested(self, seq: int, req_id: int, request: Any) -> None:
        """A citl step of view `seq` asks for captures: handed to the owner while `seq` is the
        view on the panel and the newest asked for; refused (answered at once) otherwise."""
        why = None
        if not isinstance(request, CaptureRequest):
            why = f"not a capture request: {type(request).__name__}"
        elif self.events.capture is None:
            why = "this daemon has no camera loop"
        elif self.views.seq != seq or self.shown_seq != seq:
            why = f"view {seq} is no longer the one shown"
        if why is not None:
            self.worker.send(("captured", req_id, CaptureReply(error=why)))
            return
        if self.refinement is not None and self.refinement.seq == seq:
            self.refinement.captures += 1
        self._captures_wanted.add(req_id)
        self.events.capture(req_id, request)

    def capture_wanted(self, req_id: int) -> bool:
        """Whether the worker still waits for capture request `req_id` (any thread: a bench job
        stops capturing once it is not)."""
        return req_id in self._captures_wanted

    def answer_capture(self, req_id: int, reply: CaptureReply) -> None:
        """The bench's answer to capture request `req_id` (any thread); the control loop sends
        it at its next step, while the worker still waits for it."""
        self._capture_answers.put((req_id, reply))

    def _send_capture_answers(self) -> None:
        for req_id, reply in _drain(self._capture_answers):
            if req_id in self._captures_wanted:
                self._captures_wanted.discard(req_id)
                self.worker.send(("captured", req_id, reply))

    def _refined(self, seq: int, refined: Any) -> None:
        """A better frame for view `seq`: shown only while `seq` is the view on the panel and no
        newer one was asked for (a refinement the worker had not yet seen cancelled is
        stale); its subframes then take turns, one per refresh. A stale frame's refine slot,
        and the one the frame before it was in, go back to the worker."""
        current = self.refinement
        if not isinstance(refined, RefinedFrame):
            self.events.error("frame worker", f"view {seq}: not a refined frame: "
                                              f"{type(refined).__name__}")
            return
        if (current is None or current.seq != seq or self.shown_seq != seq
                or self.views.seq != seq or self.waiting is not None):
            self.worker.free_refine(refined.slot)
            return
        current.report = dict(refined.report)
        if not refined.subframes:
            return
        try:
            greys = self.worker.refined_arrays(refined)
        except ValueError as exc:
            self.events.error("frame worker", f"view {seq}'s refined frame: {exc}")
            self.worker.free_refine(refined.slot)
            return
        previous = current.slot
        current.region, current.greys, current.slot = refined.region, greys, refined.slot
        if previous is not None and previous != refined.slot:
            self.worker.free_refine(previous)
        current.index, current.swaps = -1, current.swaps + 1
        self._show_subframe()

    def _show_subframe(self) -> None:
        """The refinement's next subframe on the panel (the control loop paces them, one per
        refresh): one subframe pasted into a fresh panel, straight from its refine slot, so a
        turn of the loop costs one frame whatever K. A panel that refuses it is an error in
        status; the frame before stays."""
        r = self.refinement
        assert r is not None and r.greys is not None and r.region is not None
        r.index = (r.index + 1) % r.subframes
        self.last_show_s = time.monotonic()
        try:
            panel = self._zero_buffer().frame(r.region.top, r.region.left, r.greys[r.index])
            self.last_frame = self.panel().show_view(panel, r.seq)
        except Exception as exc:
            self.events.error("slm", f"showing view {r.seq}'s refined frame: "
                                     f"{type(exc).__name__}: {exc}")
            self._drop_subframes(r)
            if isinstance(exc, SLMOutputLost):
                self.events.slm_lost(str(exc))

    def _zero_buffer(self) -> PanelBuffer:
        """The panel buffer of the blank frame in use now (rebuilt when the blank changes)."""
        blank = self.panel().blank_frame()
        if self._zero is None or self._zero_of is not blank:
            self._zero, self._zero_of = PanelBuffer(blank, reuse=PANELS_REUSED), blank
        return self._zero

    def _drop_subframes(self, r: Refinement) -> None:
        """Stop showing `r`'s subframes, and give their refine slot back."""
        self.worker.free_refine(r.slot)
        r.greys, r.slot = None, None

    def _drop_refinement(self) -> None:
        """The refinement of the view on the panel is over (a newer view's frame is shown)."""
        if self.refinement is not None:
            self._drop_subframes(self.refinement)
            self.refinement = None

    def _cancel_overtaken_exact(self) -> None:
        """A scene's exact frame with no model takes seconds: when a newer view waits, the
        worker is asked to cancel it (it answers "frame_cancelled" and the newest view goes
        out at once) instead of the newer one waiting its turn."""
        f = self.inflight
        if f is None or not f.exact or f.cancelled or self.views.seq <= f.seq:
            return
        self.worker.send(("cancel", f.seq))
        self.inflight = replace(f, cancelled=True)

    # -- the emission sessions (any thread) and citl's status -----------------------------------

    def emission_ended(self, reason: str) -> None:
        """An emission session ended (a laser off, disarm, stop, shutdown, the guardian's own
        disarm; any thread): the citl run of the view on the panel ends with it. Its capture
        requests are refused by the owner (`FrameEvents.capture`); here `status` says why at
        once (applied at the control loop's next step)."""
        self._emission_ends.put((self.views.seq, reason))

    def _apply_emission_ends(self) -> None:
        for seq, reason in _drain(self._emission_ends):
            r = self.refinement
            if r is not None and r.tier == "citl" and r.seq <= seq and not r.ended:
                r.ended = reason

    def capture_phase(self, req_id: int, what: str) -> None:
        """Where the bench's capture job for request `req_id` is (its thread only)."""
        self._capture_phase = (req_id, what)

    def _send_next(self) -> None:
        self._cancel_overtaken_exact()
        if not self._ready_to_send() or time.monotonic() < self.send_at_s:
            return  # the loop wakes at send_at_s (wake_s)
        seq, view = self.views.seq, self.views.view
        shm_slot = self.worker.take_slot()  # free: no frame of ours is out or waiting
        self.worker.send(("frame", seq, view, shm_slot))
        self._captures_wanted.clear()  # the worker cancels the refinement that asked
        # Without a model, a view above "network" is the scene's exact frame: seconds.
        exact = self.model_path is None and view is not None and view.quality != "network"
        self.inflight = InFlight(seq, time.monotonic(), shm_slot, exact=exact)
        if self.sent_seq and seq > self.sent_seq + 1:
            self.counts.dropped += seq - self.sent_seq - 1  # overtaken, never computed
        self.sent_seq = max(self.sent_seq, seq)
        self._resend = False

    def _show(self, waiting: WaitingFrame) -> None:
        seq, message = waiting.seq, waiting.message
        # One clock (monotonic) for all: the worker's ready_s is CLOCK_MONOTONIC, as is sent_s.
        t0 = self.last_show_s = time.monotonic()
        # A frame that cannot be shown (a region off the panel, arrays that do not fit the
        # slot, the SLM refusing it) is an error in status, not an exception out of the control
        # loop: the panel keeps the frame before it and the daemon keeps running.
        try:
            try:
                panel, rgb = self._panel(message)
            finally:  # copied out (or refused): the worker may write the slot again
                self.worker.release(message.slot)
            # The panel applies the colour mode, and holds the frame back during a capture.
            frame = self.panel().show_view(panel, seq)
        except Exception as exc:
            self.events.error("slm", f"showing view {seq}: {type(exc).__name__}: {exc}")
            if isinstance(exc, SLMOutputLost):  # the control loop switches lasers off
                self.events.slm_lost(str(exc))
            return
        done = time.monotonic()
        self.counts.showed(None if message.ready_s is None else done - message.ready_s,
                           self.refresh_s)
        stages = {**message.timings.seconds(), "output": done - t0}
        timings: dict[str, Any] = {f"{k}_ms": round(v * 1e3, 3) for k, v in stages.items()}
        if waiting.sent_s is not None:
            timings["view_to_slm_ms"] = round((done - waiting.sent_s) * 1e3, 3)
        timings.update(seq=seq, cached=message.cached,
                       clipped_fraction=list(message.clipped_fraction))
        self.timings = timings
        self.warnings = list(message.warnings)
        self.last_rgb, self.last_frame = rgb, frame
        self.shown_seq = seq
        view = self.views.view if self.views.seq == seq else None
        quality = view.quality if view is not None else "network"
        self._drop_refinement()
        if quality != "network":
            # A scene's exact frame with no model is the exact tier already: nothing follows.
            done = "exact" if message.tier == quality else ""
            self.refinement = Refinement(seq, quality, {
                "tier": message.tier if done else quality, "iterations": 0, "seconds": 0.0,
                "loss": None, "psnr_db": None, "start_psnr_db": None, "stop": done})
        self.events.shown(seq)

    def _panel(self, message: FrameMessage) -> tuple[np.ndarray, np.ndarray | None]:
        """The full panel: the blank frame (the zero pattern of the coding in use) outside the
        coded region; and a copy of the render. Both copied out of the frame's slot."""
        grey, rgb = self.worker.arrays(message)
        panel = self._zero_buffer().frame(message.region.top, message.region.left, grey)
        rgb = None if rgb is None else rgb.copy()
        del grey  # no view into the slot outlives this call
        return panel, rgb

    def _crashed(self) -> None:
        code = self.worker.process.exitcode if self.worker.process is not None else None
        self.crashes += 1
        self._captures_wanted.clear()  # nobody waits for them now
        message = f"frame worker (pid {self.worker.pid}) died with exit code {code}"
        log.error("%s; lasers off, SLM blanked, restarting", message)
        # The panel may hold a half-updated or stale frame the daemon no longer controls: the
        # owner switches the lasers off and blanks the panel (`FrameEvents.crashed`).
        self.events.crashed(message)
        self.refinement = None  # its refine slot goes with the worker; the panel is blanked
        if self.waiting is not None:  # its slot goes with the worker: never shown
            self.counts.dropped += 1
            self.waiting = None
        self._report_failed_reloads(self.worker.close(timeout_s=0.5))
        self.state = LinkState.CRASHED
        self._resend = True
        self._restart_at = time.monotonic() + RESTART_BACKOFF_S

    def status(self) -> dict[str, Any]:
        """`status.frames`: the worker, what it serves, the sequence numbers, the counts and
        the pacing."""
        info, c = self.model_info or {}, self.counts
        pacing = f"timer: one frame per refresh at {1 / self.refresh_s:g} Hz (slm.refresh_hz)"
        vsync = self.panel().vsync_detail  # the framebuffer's FBIO_WAITFORVSYNC, or why not
        if vsync:
            pacing += f"; {vsync}"
        return {"state": str(self.state), "pid": self.worker.pid, "alive": self.worker.alive,
                "model": self.model_path, "scene": self.scene_path,
                "model_variant": info.get("variant"),
                "model_variant_reason": info.get("variant_reason"),
                "sent_seq": self.sent_seq, "shown_seq": self.shown_seq,
                "frames_shown": c.shown, "frames_dropped": c.dropped, "frames_late": c.late,
                "last_frame_age_ms": (None if c.last_age_s is None
                                      else round(c.last_age_s * 1e3, 3)),
                "max_frame_age_ms": round(c.max_age_s * 1e3, 3),
                "refresh_hz": round(1 / self.refresh_s, 6), "pacing": pacing,
                "transport": self.worker.transport, "crashes": self.crashes,
                "pose_warnings": self.warnings, "refine": self._refine_status()}

    def _refine_status(self) -> dict[str, Any] | None:
        """`status.frames.refine`: the refinement of the view on the panel (None: it asked for
        the network's frame): the worker's report, the tier asked for and the stage running
        (`stage`: a citl view's first steps are sgd's), what it is doing now (`phase`: "sgd
        through the bench model", "citl step 3: capturing green at plane 2 of 3"), the view's
        sequence number, the better frames swapped in and the subframes shown in turn. A citl
        run whose emission session ended says so in `stop` at once ("stopped: lasers off ...")."""
        r = self.refinement
        if r is None:
            return None
        out = {**r.report, "tier": r.tier, "stage": r.report.get("tier", r.tier),
               "seq": r.seq, "swaps": r.swaps, "subframes": r.subframes,
               "capture_steps": r.captures}
        if r.ended:
            out["stop"] = f"stopped: {r.ended}"
        out["phase"] = self._phase(r, out)
        return out

    def _phase(self, r: Refinement, shown: dict[str, Any]) -> str:
        """What the refinement `r` does now, in a few words ("" once it stopped)."""
        if shown.get("stop"):
            return ""
        req_id, what = self._capture_phase
        if r.tier == "citl" and req_id in self._captures_wanted:
            return f"citl step {r.captures}: {what or 'waiting for the bench'}"
        stage = shown["stage"]
        if stage == "citl":
            return f"citl step {r.captures}: fitting the captures"
        if shown.get("iterations"):
            return f"{stage} through the bench model"
        return "the view's light-field inversion (its exact target)"


class PanelBuffer:
    """Full panel frames from the zero pattern and a coded region, built in the SLM's `[H, W, 3]`
    layout: a frame is a fresh copy of the interleaved zero pattern with the region interleaved
    in, returned as its `[3, H, W]` view. `nhfd.drivers.slm.to_rgb` takes that view as it is,
    where a channel-first frame costs a transposing copy of the whole panel (~10 ms at
    1920 x 1080)."""

    def __init__(self, zero: np.ndarray, reuse: int = 0) -> None:
        """`reuse`: 0, every frame is a fresh array; N > 0, frames are built in N arrays reused
        in turn, so a frame stays as it was until N - 1 newer ones (the control loop's: a
        fresh 6 MB panel costs ~500 page faults, 13 ms of CPU on this project's VM, where a
        copy into memory already touched costs 0.5 ms)."""
        self.zero_hwc = np.ascontiguousarray(np.asarray(zero, np.uint8).transpose(1, 2, 0))
        self.reuse = int(reuse)
        self._outs: list[np.ndarray] = []
        self._next = 0

    def _out(self) -> np.ndarray:
        if len(self._outs) < self.reuse:
            self._outs.append(self.zero_hwc.copy())
            return self._outs[-1]
        if not self.reuse:
            return self.zero_hwc.copy()
        out = self._outs[self._next]
        self._next = (self._next + 1) % self.reuse
        np.copyto(out, self.zero_hwc)
        return out

    def frame(self, top: int, left: int, grey: np.ndarray) -> np.ndarray:
        """The panel `[3, H, W]` (a view of its `[H, W, 3]` array) with `grey` `[3, h, w]` at
        (top, left). A grey region in the SLM's layout (`is_interleaved`: a device frame's) is
        pasted row by row; a channel-first one is interleaved plane by plane (at 1920 x 1080 on
        this project's CPU: 0.2 against 1.7 ms)."""
        out = self._out()
        _, h, w = grey.shape
        dst = out[top : top + h, left : left + w]
        if is_interleaved(grey):
            dst[...] = grey.transpose(1, 2, 0)
        else:
            for c in range(grey.shape[0]):
                dst[..., c] = grey[c]
        return out.transpose(2, 0, 1)


def _drain(q: queue.SimpleQueue[Any]) -> Iterator[Any]:
    """What other threads have put on `q` so far, in order (never blocks)."""
    while True:
        try:
            yield q.get_nowait()
        except queue.Empty:
            return


def _accepted_calibration(config: Config) -> Calibration | None:
    """The calibration this process applies, for the worker; None when there is none to keep
    (the worker's own load then says why, with each frame)."""
    try:
        return active_calibration(config)
    except ValueError:
        return None
