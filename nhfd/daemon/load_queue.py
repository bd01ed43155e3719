"""The frame link's load queue: model and scene loads from load jobs' threads to the frame
worker, and what the worker serves since.

A load job's thread only queues a `LoadRequest` and waits on it (`LoadQueue.load`); the control
loop takes the queued ones (`take`), sends each to the worker as a `LoadModel` or `LoadScene`
with a request id of its own (`send`), and on the worker's answer (`Loaded` or `LoadFailed`,
`answered`) records the model or scene served and finishes the request, so no field here is
written from two threads. After a worker crash the loads it had not answered fail ("the frame
worker stopped", `worker_gone`) and the model and scene it served load again in the new one
first (`restarted`: those reloads have nobody waiting, so a refused one is an error in
`status`). The queue knows nothing of the worker process: it is handed the worker's `send`.
"""

from __future__ import annotations

import itertools
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from nhfd.worker_messages import (
    Loaded,
    LoadFailed,
    LoadModel,
    LoadScene,
    ModelLoaded,
    SceneLoaded,
    ToWorker,
)

# How often a waiting load job looks whether the link has stopped (s): a load queued just as the
# daemon closes is answered by no control loop.
WAIT_POLL_S = 0.1
# What a load the worker can no longer answer fails with.
STOPPED = "the frame worker stopped"
# What each kind of load is answered with.
RESULTS: dict[str, type] = {"model": ModelLoaded, "scene": SceneLoaded}


def drain(q: queue.SimpleQueue[Any]) -> Iterator[Any]:
    """What other threads have put on `q` so far, in order (never blocks)."""
    while True:
        try:
            yield q.get_nowait()
        except queue.Empty:
            return


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
    result: ModelLoaded | SceneLoaded | str | None = None  # the worker's report, or why not

    def message(self, req_id: int) -> LoadModel | LoadScene:
        """The message asking the worker for this load, as request `req_id`."""
        return LoadModel(req_id, self.path) if self.kind == "model" else LoadScene(req_id,
                                                                                   self.path)

    def finish(self, ok: bool, result: ModelLoaded | SceneLoaded | str) -> None:
        """The control loop's outcome: `ok` and `result` (the worker's report, or its reason for
        refusing), then `done` set."""
        self.ok, self.result = ok, result
        self.done.set()  # publishes ok and result to the waiting thread

    def wait(self, timeout_s: float, stopped: Callable[[], bool] = lambda: False
             ) -> ModelLoaded | SceneLoaded:
        """The worker's report of the load, or ValueError with its reason (TimeoutError when
        it did not answer within `timeout_s`; ValueError at once when `stopped()` turns true:
        no control loop will answer then)."""
        deadline = time.monotonic() + timeout_s
        while not self.done.wait(min(WAIT_POLL_S, max(0.0, deadline - time.monotonic()))):
            if stopped():
                raise ValueError(STOPPED)
            if time.monotonic() >= deadline:
                raise TimeoutError(f"the frame worker did not answer within {timeout_s:g} s")
        if not self.ok:
            raise ValueError(str(self.result))
        assert isinstance(self.result, ModelLoaded | SceneLoaded)  # `answered` checked it
        return self.result


class LoadQueue:
    """Loads on their way to the frame worker and back, and what it serves since (`model_path`
    and `model`, `scene_path` and `scene`: None until a load succeeds; a refused load changes
    nothing). `error(source, message)`: the owner's line for `status` (a restart's reload that
    failed).

    Any thread may call `load`; everything else is the control loop's."""

    def __init__(self, error: Callable[[str, str], None]) -> None:
        self.error = error
        self.model_path: str | None = None
        self.model: ModelLoaded | None = None  # what the worker reported at the load
        self.scene_path: str | None = None
        self.scene: SceneLoaded | None = None
        # Loads sent, by request id, until the worker answers.
        self.pending: dict[int, LoadRequest] = {}
        # Loads queued by load jobs' threads (the one thing they touch), and those taken from
        # it that wait for a worker to send them to.
        self._requests: queue.SimpleQueue[LoadRequest] = queue.SimpleQueue()
        self._unsent: list[LoadRequest] = []
        self._ids = itertools.count(1)

    # -- a load job's thread --------------------------------------------------------------------

    def load(self, request: LoadRequest, timeout_s: float,
             stopped: Callable[[], bool] = lambda: False) -> ModelLoaded | SceneLoaded:
        """Queue `request` and block until the control loop has the worker's answer (its
        report; ValueError with its reason; `LoadRequest.wait`)."""
        self._requests.put(request)
        return request.wait(timeout_s, stopped)

    # -- the control loop -----------------------------------------------------------------------

    @property
    def unsent(self) -> int:
        """How many loads wait for a worker to send them to."""
        return len(self._unsent)

    def take(self) -> int:
        """Take what load jobs queued since; how many loads now wait to be sent."""
        self._unsent.extend(drain(self._requests))
        return len(self._unsent)

    def restarted(self) -> None:
        """A new worker: the scene and the model the last one served load in it first (in that
        order, before any load queued), as reloads nobody waits for."""
        reloads = [LoadRequest(kind, path, reload=True)
                   for kind, path in (("scene", self.scene_path), ("model", self.model_path))
                   if path]
        self._unsent[:0] = reloads

    def send(self, send: Callable[[ToWorker], None]) -> int:
        """Every load waiting, to the worker through `send`, each under a new request id; how
        many went (the worker cancels its refinement for any of them)."""
        sent = 0
        for request in self._unsent:
            req_id = next(self._ids)
            self.pending[req_id] = request
            send(request.message(req_id))
            sent += 1
        self._unsent.clear()
        return sent

    def answered(self, reply: Loaded | LoadFailed) -> bool:
        """The worker's answer to a load: on success the queue serves the new model or scene,
        and True says so (the current view is to go again with it); a restart's reload that
        failed is an error in status (no job waits for it). An answer to no load sent, or one
        of the wrong kind (a model's report for a scene), changes nothing served."""
        request = self.pending.pop(reply.req_id, None)
        if request is None:
            return False
        if isinstance(reply, LoadFailed):
            request.finish(False, reply.error)
            self._report_failed_reloads([request])
            return False
        result, expected = reply.result, RESULTS[request.kind]
        if not isinstance(result, expected):
            request.finish(False, f"the frame worker answered a {request.kind} load with "
                                  f"{type(result).__name__}, not {expected.__name__}")
            self._report_failed_reloads([request])
            return False
        if isinstance(result, ModelLoaded):
            self.model_path, self.model = request.path, result
        else:
            self.scene_path, self.scene = request.path, result
        request.finish(True, result)
        return True

    def worker_gone(self) -> None:
        """The worker stopped or died: the loads it had not answered fail (a reload among them
        is an error in status); those not yet sent wait for the next worker."""
        failed = list(self.pending.values())
        self.pending.clear()
        for request in failed:
            request.finish(False, STOPPED)
        self._report_failed_reloads(failed)

    def close(self) -> None:
        """No worker will come: every load sent, queued or waiting fails ("the frame worker
        stopped")."""
        self.worker_gone()
        self.take()  # nothing queued may wait for a worker that will not come
        for request in self._unsent:
            request.finish(False, STOPPED)
        self._unsent.clear()

    def _report_failed_reloads(self, requests: list[LoadRequest]) -> None:
        for r in requests:
            if r.reload:
                self.error("frame worker", f"reloading {r.kind} {r.path}: {r.result}")
