"""Jobs: slow work (stage moves, captures, scene loads) off the control loop.

Each runner is one worker thread with a bounded queue: bench jobs run one at a time, because
they share the stage and camera, and loads get their own runner so a scene load never waits
behind a move. The control loop never blocks on a job: `stop` cancels queued jobs, sets the
running job's cancel flag and (in the caller) stops the stage directly, which is what ends a
blocking move at once.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from .protocol import BUSY, RpcError

log = logging.getLogger(__name__)

_ids = itertools.count(1)


class Cancelled(Exception):
    """Raised inside a job that saw its cancel flag."""


@dataclass
class Job:
    """One piece of slow work: `run(job)` on a runner's thread, which calls `job.check()`
    between steps so that a cancel ends it; its state, result or error for `job` and
    `status`."""

    kind: str
    describe: dict[str, Any]
    run: Callable[[Job], Any]
    id: int = field(default_factory=lambda: next(_ids))
    state: str = "queued"  # queued, running, done, failed, cancelled
    result: Any = None
    error: str | None = None
    created_s: float = field(default_factory=time.time)
    started_s: float | None = None
    ended_s: float | None = None
    cancel: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)

    def check(self) -> None:
        """Raise `Cancelled` when the job was cancelled (a step boundary of `run`)."""
        if self.cancel.is_set():
            raise Cancelled(f"{self.kind} job {self.id} cancelled")

    def to_json(self) -> dict[str, Any]:
        """The job as `job` and `status.jobs` show it."""
        return {"id": self.id, "kind": self.kind, "state": self.state, "params": self.describe,
                "result": self.result, "error": self.error, "created_s": self.created_s,
                "started_s": self.started_s, "ended_s": self.ended_s}


class JobRunner:
    """One worker thread running jobs in order from a bounded queue, keeping the last `kept`
    finished ones for `job` and `status`. The thread starts with the first job, so a runner
    made with its daemon costs nothing until that daemon has work."""

    def __init__(self, name: str, *, max_queued: int = 16, kept: int = 32,
                 on_finish: Callable[[Job, str, str | None], None] | None = None) -> None:
        """`on_finish(job, state, error)`: called on the runner's thread before the job's end
        state is published (the daemon notes a failure and audits the end)."""
        self.name = name
        self._queue: queue.Queue[Job | None] = queue.Queue(maxsize=max_queued)
        self._lock = threading.Lock()
        self._active: dict[int, Job] = {}
        self._finished: deque[Job] = deque(maxlen=kept)
        self._on_finish = on_finish
        self.current: Job | None = None
        self._thread: threading.Thread | None = None
        self._closed = False

    def submit(self, job: Job) -> Job:
        """Queue a job; queue.Full when the queue is full (the caller answers BUSY, see
        `submit_or_busy`)."""
        with self._lock:
            self._queue.put_nowait(job)
            self._active[job.id] = job
            if self._thread is None and not self._closed:  # closed: nothing runs any more
                self._thread = threading.Thread(target=self._work, name=f"nhfd-{self.name}",
                                                daemon=True)
                self._thread.start()
        return job

    def get(self, job_id: int) -> Job | None:
        """The job with this id, queued, running or among the finished kept; else None."""
        with self._lock:
            if job_id in self._active:
                return self._active[job_id]
            return next((j for j in self._finished if j.id == job_id), None)

    def jobs(self) -> list[Job]:
        """The finished jobs kept, then the queued and running ones by id."""
        with self._lock:
            return [*self._finished, *sorted(self._active.values(), key=lambda j: j.id)]

    def cancel_all(self) -> list[int]:
        """Cancel queued jobs and flag the running one; returns the ids touched. Never waits."""
        with self._lock:
            touched = []
            for job in self._active.values():
                job.cancel.set()
                touched.append(job.id)
            return touched

    def close(self, timeout_s: float = 2.0) -> None:
        """Cancel every job and end the thread (waiting at most about `timeout_s` for each
        step)."""
        self.cancel_all()
        with self._lock:
            self._closed = True
            thread = self._thread
        if thread is None:  # never ran a job: no thread to end
            return
        try:
            self._queue.put(None, timeout=timeout_s)
        except queue.Full:
            pass
        thread.join(timeout_s)

    def _work(self) -> None:
        while (job := self._queue.get()) is not None:
            self._execute(job)

    def _execute(self, job: Job) -> None:
        self.current = job
        job.started_s = time.time()
        # The end state is published last: a client that sees "failed" must also find what the
        # finish hook records (the daemon's error list, the audit log).
        state, error = "failed", None
        try:
            job.check()
            job.state = "running"
            job.result = job.run(job)
            job.check()
            state = "done"
        except Cancelled as exc:
            state, error = "cancelled", str(exc)
        except Exception as exc:
            # A cancel that surfaces as a device error (a stopped move) is still a cancel.
            state = "cancelled" if job.cancel.is_set() else "failed"
            error = f"{type(exc).__name__}: {exc}"
            if state == "failed":
                log.error("job %s %d failed: %s", job.kind, job.id, error)
                log.debug("%s", traceback.format_exc())
        finally:
            job.ended_s = time.time()
            if self._on_finish is not None:
                try:
                    self._on_finish(job, state, error)
                except Exception:
                    log.exception("job finish hook")
            job.state, job.error = state, error
            self.current = None
            with self._lock:
                self._active.pop(job.id, None)
                self._finished.append(job)
            job.done.set()


# What a client hears when the bench queue is full (`submit_or_busy`'s default).
BENCH_QUEUE_FULL = "the bench job queue is full; wait or stop"


def submit_or_busy(runner: JobRunner, job: Job, message: str = BENCH_QUEUE_FULL,
                   data: dict[str, Any] | None = None) -> Job:
    """`runner.submit(job)`, a full queue refused as BUSY with `message` (and `data`): a
    request never waits for room in a queue."""
    try:
        return runner.submit(job)
    except queue.Full:
        raise RpcError(BUSY, message, data) from None
