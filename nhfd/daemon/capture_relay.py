"""The frame link's capture relay: a citl refinement's capture requests from the frame worker to
the daemon's bench job, and the bench's answers back; and the ends of emission sessions.

The worker asks with a `CaptureAsked`; the control loop hands it to the owner (`capture`, the
daemon's bench-job submitter) while its view is the one shown and the newest asked for, and
refuses it at once otherwise (a `CaptureAnswer` with the reason). The bench job answers from its
own thread (`answer`), and the control loop sends the answer while the worker still waits for
it (`send_answers`): once the worker cancels the refinement that asked (a new view, a load, a
crash: `cancelled`) nobody waits, and a bench job that asks `wanted` stops capturing. An
emission session's end (a laser off, disarm, stop; any thread) is queued here for the control
loop, which ends the citl run of the view on the panel with it.
"""

from __future__ import annotations

import queue
from collections.abc import Callable, Iterator
from typing import Any

from nhfd.frame_message import CaptureReply, CaptureRequest
from nhfd.worker_messages import CaptureAnswer, ToWorker

from .load_queue import drain


class CaptureRelay:
    """citl's capture requests and answers between the frame worker and the daemon's bench.
    `capture(req_id, request)`: the owner's, which answers later, from any thread, with
    `answer` (None: every request is refused, "this daemon has no camera loop")."""

    def __init__(self, capture: Callable[[int, CaptureRequest], None] | None) -> None:
        self.capture = capture
        # The requests the worker still waits for, and the answers bench jobs give (from their
        # threads) for the control loop to send.
        self._wanted: set[int] = set()
        self._answers: queue.SimpleQueue[tuple[int, CaptureReply]] = queue.SimpleQueue()
        # Where the bench's citl capture job is (request id, what it does), written by that
        # job's thread alone and read for `status`.
        self._phase: tuple[int, str] = (0, "")
        # Emission sessions that ended (from any thread): (the newest view then, why).
        self._ends: queue.SimpleQueue[tuple[int, str]] = queue.SimpleQueue()

    # -- the control loop -----------------------------------------------------------------------

    def asked(self, seq: int, req_id: int, request: Any, current: bool,
              send: Callable[[ToWorker], None]) -> bool:
        """A citl step of view `seq` asks for captures (request `req_id`): handed to the owner
        when `current` (`seq` is the view on the panel and the newest asked for), and True;
        refused otherwise, answered at once through `send`, and False."""
        capture = self.capture
        if not isinstance(request, CaptureRequest):
            why = f"not a capture request: {type(request).__name__}"
        elif capture is None:
            why = "this daemon has no camera loop"
        elif not current:
            why = f"view {seq} is no longer the one shown"
        else:
            self._wanted.add(req_id)
            capture(req_id, request)
            return True
        send(CaptureAnswer(req_id, CaptureReply(error=why)))
        return False

    def send_answers(self, send: Callable[[ToWorker], None]) -> None:
        """The answers bench jobs gave since, through `send`, for the requests the worker still
        waits for (the others are dropped)."""
        for req_id, reply in drain(self._answers):
            if req_id in self._wanted:
                self._wanted.discard(req_id)
                send(CaptureAnswer(req_id, reply))

    def cancelled(self) -> None:
        """The worker cancelled (or lost) the refinement that asked: nobody waits for any
        capture now."""
        self._wanted.clear()

    def waiting_phase(self) -> str | None:
        """What the bench does for the capture the worker waits for ("capturing green at plane
        2 of 3", "waiting for the bench"), or None when it waits for none."""
        req_id, what = self._phase
        if req_id in self._wanted:
            return what or "waiting for the bench"
        return None

    def emission_ends(self) -> Iterator[tuple[int, str]]:
        """The emission sessions that ended since, in order: (the newest view then, why)."""
        return drain(self._ends)

    # -- any thread -----------------------------------------------------------------------------

    def wanted(self, req_id: int) -> bool:
        """Whether the worker still waits for capture request `req_id` (a bench job stops
        capturing once it does not)."""
        return req_id in self._wanted

    def answer(self, req_id: int, reply: CaptureReply) -> None:
        """The bench's answer to request `req_id`; sent at the control loop's next step."""
        self._answers.put((req_id, reply))

    def phase(self, req_id: int, what: str) -> None:
        """Where the bench's capture job for request `req_id` is (its thread only)."""
        self._phase = (req_id, what)

    def emission_ended(self, seq: int, reason: str) -> None:
        """An emission session ended while `seq` was the newest view (applied at the control
        loop's next step, `emission_ends`)."""
        self._ends.put((seq, reason))
