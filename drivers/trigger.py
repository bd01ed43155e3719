"""Hardware triggers: a capture that starts on the SLM's frame flip instead of after a settle sleep.

Without a trigger the host shows a frame and sleeps the SLM's `settle_ms` before the camera
exposes: a conservative figure that must cover the display pipeline's unknown latency (an HDMI
panel shows a frame one or more refreshes after it was sent) and the liquid crystal's response.

With `[devices.trigger] source = "slm_flip"` the SLM's frame-flip output is wired to the camera's
trigger input. The camera is armed; the host writes the frame; the panel flips and its output
gives an edge; the camera starts exposing `delay_ms` after the edge (its hardware trigger delay,
set to the liquid crystal's response). The host sleeps no settle time: the SLM's `settle_s` is 0
while a line is attached, and the camera's capture waits on the edge instead.

`TriggerLine` is that wire. On the simulated bench it is the whole model: the simulated SLM
emits the edge when its frame flips (`SLMOutputSettings.flip_latency_ms` after the write) and the
simulated camera's exposure starts on it. A cut wire (`cut()`, test-only: a pulled cable, an SLM
that never flips) gives no edge, and the capture fails after `timeout_ms` with a
`TriggerTimeout` naming the trigger and the timeout. `record` keeps, per triggered exposure, the
frame's write, its flip and the exposure's start (the twin's record a test reads).

A real camera's trigger mode (GenICam TriggerMode/TriggerSource/TriggerDelay, or a vendor SDK's
equivalent) is set by its backend; this module holds the timing every backend shares.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .errors import DeviceError


class TriggerTimeout(DeviceError):
    """No trigger edge arrived within the trigger's timeout after a frame was written."""


@dataclass(frozen=True)
class TriggeredExposure:
    """One triggered exposure on the line's clock: the frame's write, the flip edge it waited
    for, and the exposure's start (edge + delay)."""

    written_s: float
    flip_s: float
    exposure_start_s: float


class TriggerLine:
    """The wire from the SLM's frame-flip output to the camera's trigger input."""

    def __init__(self, source: str = "slm_flip", *, delay_ms: float = 10.0,
                 timeout_ms: float = 500.0, clock: Callable[[], float] = time.monotonic) -> None:
        if source != "slm_flip":
            raise ValueError(f"trigger source {source!r}: expected 'slm_flip'")
        if not (0 <= delay_ms <= 1000):
            raise ValueError(f"trigger delay_ms = {delay_ms!r}: must be in [0, 1000]")
        if not (0 < timeout_ms <= 60000):
            raise ValueError(f"trigger timeout_ms = {timeout_ms!r}: must be in (0, 60000]")
        self.source = source
        self.delay_s = delay_ms / 1000
        self.timeout_s = timeout_ms / 1000
        self._clock = clock
        self._cond = threading.Condition()
        self._written_s = -float("inf")  # the last frame written by the host
        self._edges: list[float] = []  # flip edges not older than the last write
        self._cut = False
        self.record: list[TriggeredExposure] = []

    @classmethod
    def from_settings(cls, settings: Any, *,
                      clock: Callable[[], float] = time.monotonic) -> TriggerLine | None:
        """The line `[devices.trigger]` describes, or None for source = "none"."""
        if settings.source == "none":
            return None
        return cls(settings.source, delay_ms=settings.delay_ms, timeout_ms=settings.timeout_ms,
                   clock=clock)

    def __repr__(self) -> str:
        return (f"TriggerLine({self.source!r}, delay {self.delay_s * 1e3:g} ms, "
                f"timeout {self.timeout_s * 1e3:g} ms)")

    # -- the SLM's side ------------------------------------------------------------------------

    def written(self, at_s: float) -> None:
        """The host wrote a frame at `at_s`: from now on only a later flip triggers."""
        with self._cond:
            self._written_s = at_s
            self._edges = [t for t in self._edges if t >= at_s]

    def edge(self, at_s: float) -> None:
        """The SLM's flip output gave an edge at `at_s` (lost on a cut wire)."""
        with self._cond:
            if self._cut:
                return
            self._edges.append(at_s)
            self._cond.notify_all()

    # -- test-only fault -----------------------------------------------------------------------

    def cut(self) -> None:
        """Test-only: the wire is cut (or the SLM never flips): no edge reaches the camera."""
        with self._cond:
            self._cut = True

    def mend(self) -> None:
        with self._cond:
            self._cut = False

    # -- the camera's side ---------------------------------------------------------------------

    def wait_exposure_start(self) -> float:
        """Block until the exposure may start: `delay` after the flip of the last frame written
        (at once when that moment has passed). Returns the start on the line's clock; raises
        TriggerTimeout when no flip came within the timeout after the write."""
        with self._cond:
            written = self._written_s
            # Nothing written yet: the timeout counts from now.
            deadline = (self._clock() if written == -float("inf") else written) + self.timeout_s
            while True:
                flips = [t for t in self._edges if t >= written]
                if flips:
                    flip = flips[-1]
                    break
                left = deadline - self._clock()
                if left <= 0:
                    raise TriggerTimeout(
                        f"trigger {self.source}: no frame-flip edge within "
                        f"{self.timeout_s * 1e3:g} ms (devices.trigger.timeout_ms) of the frame "
                        "written: is the SLM's flip output wired to the camera's trigger input?")
                self._cond.wait(min(left, 0.05))
        start = flip + self.delay_s
        wait = start - self._clock()
        if wait > 0:
            time.sleep(wait)
        self.record.append(TriggeredExposure(written, flip, start))
        return start
