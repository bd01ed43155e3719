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

With `source = "camera_exposure"` the other wire is used: the camera's exposure-active output
(high from the exposure's start to its end) is wired to the host. Without it the host cannot
tell when an exposure is over, only when its image has arrived (after readout and transfer), and
must not write the next frame before then; with it, the SLM's write waits only for the line to be
low (`wait_exposure_over`), so the next frame's write and settle may overlap the last image's
readout, and no frame changes while the sensor integrates. The SLM still waits its settle time
(nothing tells the camera when the panel flipped). The simulated camera raises the line for each
exposure (`exposure_begins` / `exposure_ends`, its exposure then lasting `exposure_s` in time);
it models no readout, and a capture call returns with its image, so the overlap itself is not
simulated (that needs an asynchronous capture). `exposures` and `writes` are the twin's record:
a write inside an exposure window is the fault the line prevents (`writes_during_exposures`).
A line stuck high (`stick_high()`, test-only: a pulled cable reading high, a camera that never
ends its exposure) fails the write after `timeout_ms` with a `TriggerTimeout` naming the
trigger and the timeout; a cut one (`cut()`) reads low, and frames are then written inside
exposures, as without the wire.

A real camera's trigger mode (GenICam TriggerMode/TriggerSource/TriggerDelay, or a vendor SDK's
equivalent) is set by its backend; this module holds the timing every backend shares.

Lifecycle: a line is open once made (as pyserial's `Serial` is), `close()` (idempotent) releases
it and `open()` opens it again. On a closed line every wait raises LinkDown at once (a waiter
blocked when it closes wakes and raises too), so a frame write that the camera_exposure line
should gate is refused rather than made blind; a flip edge that comes while it is closed is
lost, and none from before a reopen starts an exposure after it.

Backend hooks, for a line the host reads from hardware (the model needs none): `_do_open` and
`_do_close` (its input: a GPIO line, a serial port's modem-status line), and `_input_high()`,
the camera's exposure-active output as read now, which waits poll every `poll_s`
(nhfd.drivers.templates.trigger_backend). The contract every line keeps is
tests/drivers/contracts/test_trigger.py.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from nhfd.device_settings import TRIGGER_DELAY_MS, TRIGGER_SOURCES, TRIGGER_TIMEOUT_MS

from .errors import DeviceError, LinkDown


class TriggerTimeout(DeviceError):
    """No trigger edge arrived within the trigger's timeout after a frame was written, or the
    camera's exposure-active line stayed high past it."""


@dataclass(frozen=True)
class TriggeredExposure:
    """One triggered exposure on the line's clock: the frame's write, the flip edge it waited
    for, and the exposure's start (edge + delay)."""

    written_s: float
    flip_s: float
    exposure_start_s: float


@dataclass(frozen=True)
class ExposureWindow:
    """One exposure on the line's clock, as the exposure-active line showed it."""

    start_s: float
    end_s: float


class TriggerLine:
    """The wire from the SLM's frame-flip output to the camera's trigger input ("slm_flip"), or
    from the camera's exposure-active output to the host ("camera_exposure"). Open once made."""

    # How often a wait re-reads the line (s): the model is woken by the camera's and the SLM's
    # calls and only rechecks its deadline; a backend polling an input (`_input_high`) sets less.
    poll_s = 0.05

    def __init__(self, source: str = "slm_flip", *, delay_ms: float = 10.0,
                 timeout_ms: float = 500.0, clock: Callable[[], float] = time.monotonic) -> None:
        wired = TRIGGER_SOURCES[1:]
        if source not in wired:
            raise ValueError(f"trigger source {source!r}: expected one of {wired}")
        lo, hi = TRIGGER_DELAY_MS
        if not (lo <= delay_ms <= hi):
            raise ValueError(f"trigger delay_ms = {delay_ms!r}: must be in [{lo:g}, {hi:g}]")
        lo, hi = TRIGGER_TIMEOUT_MS
        if not (lo < timeout_ms <= hi):
            raise ValueError(f"trigger timeout_ms = {timeout_ms!r}: must be in ({lo:g}, {hi:g}]")
        self.source = source
        self.delay_s = delay_ms / 1000
        self.timeout_s = timeout_ms / 1000
        self._clock = clock
        self._cond = threading.Condition()
        self._written_s = -float("inf")  # the last frame written by the host
        self._edges: list[float] = []  # flip edges not older than the last write
        self._cut = False
        self.record: list[TriggeredExposure] = []
        # camera_exposure: the line's level, and the twin's record of exposures and writes.
        self._exposing_since: float | None = None
        self._stuck_high = False
        self.exposures: list[ExposureWindow] = []
        self.writes: list[float] = []
        self._is_open = False
        self.open()

    @property
    def flip_triggers_exposure(self) -> bool:
        """slm_flip: the camera exposes on the flip (plus delay); the host sleeps no settle."""
        return self.source == "slm_flip"

    @property
    def exposure_gates_write(self) -> bool:
        """camera_exposure: a frame is written only while no exposure is running."""
        return self.source == "camera_exposure"

    @property
    def clock(self) -> Callable[[], float]:
        """The clock the line's times are on (s)."""
        return self._clock

    @classmethod
    def from_settings(cls, settings: Any, *,
                      clock: Callable[[], float] = time.monotonic) -> TriggerLine | None:
        """The line `[devices.trigger]` describes, or None for source = "none"."""
        if settings.source == "none":
            return None
        return cls(settings.source, delay_ms=settings.delay_ms, timeout_ms=settings.timeout_ms,
                   clock=clock)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.source!r}, delay {self.delay_s * 1e3:g} ms, "
                f"timeout {self.timeout_s * 1e3:g} ms)")

    # -- lifecycle -----------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """Whether the line is open (waits allowed)."""
        return self._is_open

    def open(self) -> TriggerLine:
        """Open the line (`_do_open`); a no-op when open. Flip edges from before are forgotten:
        none of them starts an exposure after the reopen."""
        with self._cond:
            if self._is_open:
                return self
            self._do_open()
            self._edges = []
            self._is_open = True
        return self

    def close(self) -> None:
        """Close the line (`_do_close`); a no-op when closed. Waiters wake and raise LinkDown."""
        with self._cond:
            if not self._is_open:
                return
            self._is_open = False
            self._edges = []
            self._cond.notify_all()
            self._do_close()

    def __enter__(self) -> TriggerLine:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if not self._is_open:
            raise LinkDown(f"trigger {self.source}: not open")

    # -- backend hooks -------------------------------------------------------------------------

    def _do_open(self) -> None:
        """Open the host's input (nothing for the model)."""

    def _do_close(self) -> None:
        """Release the host's input (idempotent; nothing for the model)."""

    def _input_high(self) -> bool | None:
        """camera_exposure: the exposure-active output as the host's input reads it now (True:
        high, an exposure running), or None where the camera reports its exposures itself
        (`exposure_begins` / `exposure_ends`: the model). A failed read raises DeviceError."""
        return None

    def _line_high(self) -> bool:
        """Whether the exposure-active line reads high now (the caller holds the condition)."""
        if self._stuck_high:
            return True
        level = self._input_high()
        return self._exposing_since is not None if level is None else bool(level)

    # -- the SLM's side ------------------------------------------------------------------------

    def written(self, at_s: float) -> None:
        """The host wrote a frame at `at_s`: from now on only a later flip triggers."""
        with self._cond:
            self._written_s = at_s
            if self.exposure_gates_write:
                self.writes.append(at_s)
            self._edges = [t for t in self._edges if t >= at_s]

    def edge(self, at_s: float) -> None:
        """The SLM's flip output gave an edge at `at_s` (lost on a cut wire or a closed line)."""
        with self._cond:
            if self._cut or not self._is_open:
                return
            self._edges.append(at_s)
            self._cond.notify_all()

    # -- test-only fault -----------------------------------------------------------------------

    def cut(self) -> None:
        """Test-only: the wire is cut. slm_flip: no edge reaches the camera (as when the SLM never
        flips). camera_exposure: the host's input reads low, so frames are written whatever the
        camera does; the twin's record still holds the true exposures."""
        with self._cond:
            self._cut = True

    def mend(self) -> None:
        """Test-only: undo `cut` and `stick_high`."""
        with self._cond:
            self._cut = False
            self._stuck_high = False
            self._cond.notify_all()

    def stick_high(self) -> None:
        """Test-only: the exposure-active line reads high whatever the camera does (a camera
        that never ends its exposure, a broken input pulled high)."""
        with self._cond:
            self._stuck_high = True

    # -- camera_exposure: the camera's exposure-active output ----------------------------------

    def exposure_begins(self) -> float:
        """The camera's exposure starts now (the line rises); returns the start. Not while a
        frame is being written (`frame_write`): the wiring orders the two."""
        with self._cond:
            self._exposing_since = self._clock()
            return self._exposing_since

    def exposure_ends(self, at_s: float) -> None:
        """The camera's exposure ended at `at_s` (the line falls): record the exposure window and
        wake writers waiting for it."""
        with self._cond:
            if self._exposing_since is not None:
                self.exposures.append(ExposureWindow(self._exposing_since, at_s))
            self._exposing_since = None
            self._cond.notify_all()

    @contextmanager
    def frame_write(self) -> Iterator[float]:
        """Around the SLM's write of a frame: waits for the line to be low (`wait_exposure_over`)
        and holds off the next exposure until the write is done (the line wired to the SLM's
        trigger input, or the host's write between exposures), so no write falls inside one."""
        with self._cond:
            yield self.wait_exposure_over()

    def wait_exposure_over(self) -> float:
        """Block while the exposure-active line is high (at once when low); returns when it was
        seen low, on the line's clock. Raises TriggerTimeout when it stays high past the
        timeout: the host cannot know the exposure is over, so it must not write a frame;
        LinkDown on a closed line (one that closes while it waits too)."""
        with self._cond:
            self._check_open()
            if self._cut:
                return self._clock()
            self._wait(lambda: not self._line_high(), self._clock() + self.timeout_s,
                       f"the camera's exposure-active line stayed high for "
                       f"{self.timeout_s * 1e3:g} ms (devices.trigger.timeout_ms): is the "
                       "camera's exposure output wired to the host, and is the camera stuck?")
            return self._clock()

    def _wait(self, ready: Callable[[], bool], deadline_s: float, missed: str) -> None:
        """Wait on the line's condition (held by the caller) until `ready()`; TriggerTimeout
        naming the trigger and `missed` past `deadline_s` on the line's clock, LinkDown once the
        line closes."""
        while not ready():
            left = deadline_s - self._clock()
            if left <= 0:
                raise TriggerTimeout(f"trigger {self.source}: {missed}")
            self._cond.wait(min(left, self.poll_s))
            self._check_open()

    def writes_during_exposures(self) -> list[tuple[float, ExposureWindow]]:
        """The twin's check: each frame write that fell inside an exposure (none on a working
        line)."""
        with self._cond:
            return [(w, e) for e in self.exposures for w in self.writes
                    if e.start_s < w < e.end_s]

    # -- the camera's side ---------------------------------------------------------------------

    def wait_exposure_start(self) -> float:
        """Block until the exposure may start: `delay` after the flip of the last frame written
        (at once when that moment has passed). Returns the start on the line's clock; raises
        TriggerTimeout when no flip came within the timeout after the write, LinkDown on a
        closed line."""
        with self._cond:
            self._check_open()
            written = self._written_s
            # Nothing written yet: the timeout counts from now.
            deadline = (self._clock() if written == -float("inf") else written) + self.timeout_s
            self._wait(lambda: any(t >= written for t in self._edges), deadline,
                       f"no frame-flip edge within {self.timeout_s * 1e3:g} ms "
                       "(devices.trigger.timeout_ms) of the frame written: is the SLM's flip "
                       "output wired to the camera's trigger input?")
            flip = [t for t in self._edges if t >= written][-1]
        start = flip + self.delay_s
        wait = start - self._clock()
        if wait > 0:
            time.sleep(wait)
        self.record.append(TriggeredExposure(written, flip, start))
        return start
