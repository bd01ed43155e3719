"""The trigger contract: every trigger line (nhfd.drivers.trigger), in both wirings, and a lab's
real line when NHFD_TEST_TRIGGER names its class and device
(NHFD_TEST_TRIGGER=class:mylab.triggers.GpioExposureInput:/dev/gpiochip0, the class called with
the fields after it as strings; leave the camera idle while it runs: the facts that need its
exposures run on the set-ups that drive them). No real trigger line ships: a lab's fills in
nhfd.drivers.templates.trigger_backend.

The frame-flip line ("slm_flip": the SLM's flip output to the camera's trigger input):

- a flip after a frame's write starts one exposure (one record) the trigger delay after the flip,
  and the record's times are in order: write, flip, exposure start;
- an older frame's flip never starts a newer frame's exposure: with no flip after the write the
  camera's wait fails with TriggerTimeout (a DeviceError) naming the trigger and its timeout, once
  the line's clock has passed the write plus the timeout, and records nothing;
- over seeded random shows (some never flipping) the records are one per exposure and monotone.

The exposure-active line ("camera_exposure": the camera's output to the host, gating the SLM):

- a write goes through at once while the line is low and waits while it is high, landing after
  the line fell;
- a line that stays high fails the write with TriggerTimeout naming the trigger and its timeout,
  once the line's clock has passed the timeout, and nothing is written; written again once low;
- over seeded random writes and exposures each exposure is recorded once (a fall reported twice
  too), windows and writes are monotone and no write falls inside an exposure;
- where the line holds off the camera's next exposure during a write (the model and the
  simulated bench; a host input cannot): no exposure begins while a frame is being written, and
  no write falls inside an exposure while a camera exposes continuously.

Both: close is idempotent; a closed line refuses every wait with LinkDown (the camera_exposure
gate refuses the write instead of making it blind, reads no input, and a write waiting on a high
line when it closes fails so too); no flip from before a reopen, nor one that came while it was
closed, starts an exposure after it; it opens again.

Backends: the bare TriggerLine driven by the test's hand ("model"); the simulated bench
(make_bench: the simulated SLM's flips and the simulated camera's exposures drive the same line);
for camera_exposure also the trigger template (a host input, polled) filled in as a test double
over a fake digital input.
"""

from __future__ import annotations

import importlib
import itertools
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import pytest

from nhfd.config import Config
from nhfd.device_settings import SLMOutputSettings, TriggerSettings
from nhfd.drivers.errors import DeviceError, LinkDown
from nhfd.drivers.factory import BenchDevices, make_bench
from nhfd.drivers.slm import SLM, SimulatedSLM
from nhfd.drivers.templates.trigger_backend import MyExposureInput
from nhfd.drivers.trigger import ExposureWindow, TriggerLine, TriggerTimeout

from . import bench_target

PANEL = 64
DELAY_MS = 2.0
TIMEOUT_MS = 150.0
FLIP_LATENCY_MS = 5.0
EXPOSURE_S = 0.04  # the simulated camera's exposure: well inside the timeout a write waits
READOUT_S = 0.005  # between a continuously exposing camera's exposures

FLIP_MISSED = (rf"trigger slm_flip: no frame-flip edge within {TIMEOUT_MS:g} ms "
               r"\(devices\.trigger\.timeout_ms\)")
STAYED_HIGH = (rf"trigger camera_exposure: the camera's exposure-active line stayed high for "
               rf"{TIMEOUT_MS:g} ms \(devices\.trigger\.timeout_ms\)")


def frame(level: int) -> np.ndarray:
    return np.full((PANEL, PANEL), level, np.uint8)


@contextmanager
def simulated_bench(source: str) -> Iterator[BenchDevices]:
    """The simulated SLM and camera wired by `source` (no laser light needed: only timing)."""
    from nhfd.drivers.simcamera import TrueBench

    d = Config().devices
    devices = d.model_copy(update={
        "slm_output": d.slm_output.model_copy(update={"settle_ms": 0.0,
                                                      "flip_latency_ms": FLIP_LATENCY_MS}),
        "trigger": TriggerSettings(source=source, delay_ms=DELAY_MS, timeout_ms=TIMEOUT_MS)})
    true = TrueBench(zero_order_fraction=0.0)
    with make_bench(devices, PANEL, PANEL, bench=true,
                    roi=true.roi_for_panel((PANEL, PANEL))) as out:
        out.camera.set_exposure(EXPOSURE_S)
        yield out


def lab_line(source: str) -> TriggerLine:
    """A lab's own line from NHFD_TEST_TRIGGER=class:module.Class[:field...]."""
    _, (name, *fields) = bench_target(
        "NHFD_TEST_TRIGGER", ("class",), "class:mylab.triggers.GpioExposureInput:/dev/gpiochip0")
    module, _, cls = name.rpartition(".")
    line = getattr(importlib.import_module(module), cls)(*fields)
    assert isinstance(line, TriggerLine), f"{name} is not a nhfd.drivers.trigger.TriggerLine"
    if line.source != source:
        line.close()
        pytest.skip(f"NHFD_TEST_TRIGGER's line is a {line.source} line: these are {source} facts")
    return line


def spy_edges(line: TriggerLine) -> list[float]:
    """Every flip edge the line is given, in order."""
    edges: list[float] = []
    edge = line.edge

    def spy(at_s: float) -> None:
        edges.append(at_s)
        edge(at_s)

    line.edge = spy  # type: ignore[method-assign]
    return edges


def needs(hand: Any) -> Any:
    if hand is None:
        pytest.skip("needs the SLM's or the camera's side driven: this fact runs on the set-ups "
                    "that drive it")
    return hand


# -- the frame-flip line ---------------------------------------------------------------------


@dataclass
class FlipSetup:
    line: TriggerLine
    # The host writes a frame; with True its flip comes, with False it never does. None: not
    # driven (a real line).
    show: Callable[[bool], None] | None
    expose: Callable[[], float]  # the camera's side: waits for its exposure's start, returns it
    edges: list[float] = field(default_factory=list)  # every flip edge given to the line


@pytest.fixture(params=["model", "simulated-bench", "bench"])
def flip(request: pytest.FixtureRequest) -> Iterator[FlipSetup]:
    if request.param == "model":
        line = TriggerLine("slm_flip", delay_ms=DELAY_MS, timeout_ms=TIMEOUT_MS)
        edges = spy_edges(line)

        def show(flips: bool) -> None:
            line.written(line.clock())
            if flips:
                line.edge(line.clock())

        with line:
            yield FlipSetup(line, show, line.wait_exposure_start, edges)
    elif request.param == "simulated-bench":
        with simulated_bench("slm_flip") as b:
            line = b.slm.trigger
            edges = spy_edges(line)
            levels = iter(range(1, 1 << 30))

            def show(flips: bool) -> None:
                b.slm.never_flip(not flips)
                b.slm.show(frame(next(levels) % 256))

            def expose() -> float:
                b.camera.capture(1, subtract_dark=False)
                return line.record[-1].exposure_start_s

            yield FlipSetup(line, show, expose, edges)
    else:
        line = lab_line("slm_flip")
        with line:
            yield FlipSetup(line, None, line.wait_exposure_start)


def test_a_flip_starts_one_exposure_its_delay_after_the_flip(flip):
    show, line = needs(flip.show), flip.line
    before = len(line.record)
    show(True)
    start = flip.expose()
    (rec,) = line.record[before:]
    assert rec.flip_s == flip.edges[-1]  # this frame's flip
    assert rec.written_s <= rec.flip_s <= rec.exposure_start_s == start
    assert line.delay_s == DELAY_MS / 1000 and start == rec.flip_s + line.delay_s


def test_an_older_frames_flip_never_starts_a_newer_frames_exposure(flip):
    show, line = needs(flip.show), flip.line
    show(True)
    flip.expose()
    before = len(line.record)
    t0 = line.clock()
    show(False)  # written; the only flip since is the older frame's
    with pytest.raises(TriggerTimeout, match=FLIP_MISSED) as missed:
        flip.expose()
    assert isinstance(missed.value, DeviceError)
    assert line.clock() >= t0 + line.timeout_s  # on the line's clock: after the whole timeout
    assert len(line.record) == before
    show(True)  # the next frame's flip triggers again
    flip.expose()
    assert len(line.record) == before + 1


def test_records_are_one_per_exposure_and_monotone(flip):
    show, line = needs(flip.show), flip.line
    rng = np.random.default_rng(3)
    before = len(line.record)
    flipped = 0
    for _ in range(16):
        flips = bool(rng.random() >= 0.2)
        show(flips)
        if flips:
            flip.expose()
            flipped += 1
        else:
            with pytest.raises(TriggerTimeout):
                flip.expose()
    records = line.record[before:]
    assert len(records) == flipped
    for rec in records:
        assert rec.written_s <= rec.flip_s <= rec.exposure_start_s == rec.flip_s + line.delay_s
    for a, b in itertools.pairwise(records):
        assert a.written_s <= b.written_s and a.flip_s <= b.flip_s
        assert a.exposure_start_s <= b.exposure_start_s


def test_a_closed_flip_line_starts_no_exposure_and_opens_again(flip):
    line = flip.line
    if flip.show is not None:
        flip.show(True)  # flipped before the close
    line.close()
    line.close()
    assert not line.is_open
    with pytest.raises(LinkDown, match="trigger slm_flip: not open"):
        flip.expose()
    line.open()
    line.open()  # a no-op when open
    assert line.is_open
    if flip.show is None:
        return
    with pytest.raises(TriggerTimeout):  # nothing from before the reopen starts an exposure
        flip.expose()
    line.close()
    flip.show(True)  # its flip comes while the line is closed: lost
    line.open()
    with pytest.raises(TriggerTimeout):
        flip.expose()
    flip.show(True)
    flip.expose()


# -- the exposure-active line ----------------------------------------------------------------


class ExposureHand(Protocol):
    """The camera's side of the exposure-active line."""

    def begin(self) -> None:
        """An exposure starts: the line reads high once this returns."""

    def end(self) -> float:
        """The exposure ends (or has ended): returns when the line fell, on the line's clock."""

    def hold_high(self) -> None:
        """The line stays high (a camera that never ends its exposure)."""

    def release(self) -> None:
        """It falls again."""

    def expose(self) -> None:
        """One whole exposure of EXPOSURE_S."""

    def still_high(self) -> bool:
        """Whether the exposure begun is still running (it may end by itself)."""


class HandDriven:
    """A hand whose exposures last exactly from `begin` to `end`: held high is begun and not
    ended, one exposure is begun, EXPOSURE_S, ended."""

    def begin(self) -> None:
        raise NotImplementedError

    def end(self) -> float:
        raise NotImplementedError

    def hold_high(self) -> None:
        self.begin()

    def release(self) -> None:
        self.end()

    def expose(self) -> None:
        self.begin()
        time.sleep(EXPOSURE_S)
        self.end()

    def still_high(self) -> bool:
        return True  # until end()


class LineHand(HandDriven):
    """The model's line driven by hand, as the simulated camera drives it."""

    def __init__(self, line: TriggerLine) -> None:
        self.line = line

    def begin(self) -> None:
        self.line.exposure_begins()

    def end(self) -> float:
        at_s = self.line.clock()
        self.line.exposure_ends(at_s)
        return at_s



class CameraHand:
    """The simulated camera's captures drive the line (each capture one exposure of EXPOSURE_S);
    it cannot be stuck, so a line that stays high is the line's own fault (`stick_high`)."""

    def __init__(self, b: BenchDevices) -> None:
        self.b = b
        self.line = b.slm.trigger
        self.rose = threading.Event()
        begins = self.line.exposure_begins

        def spy() -> float:
            at_s = begins()
            self.rose.set()
            return at_s

        self.line.exposure_begins = spy  # type: ignore[method-assign]
        self.thread: threading.Thread | None = None
        self.errors: list[BaseException] = []
        self.ended = 0  # exposures ended before the one begun

    def expose(self) -> None:
        self.b.camera.capture(1, subtract_dark=False)

    def _capture(self) -> None:
        try:
            self.expose()
        except BaseException as exc:  # surfaced by end()
            self.errors.append(exc)

    def begin(self) -> None:
        self.rose.clear()
        self.ended = len(self.line.exposures)
        self.thread = threading.Thread(target=self._capture)
        self.thread.start()
        assert self.rose.wait(10.0), "the simulated camera's exposure never began"

    def end(self) -> float:
        if self.thread is not None:
            self.thread.join(10.0)
            self.thread = None
        assert not self.errors, self.errors
        return self.line.exposures[-1].end_s

    def still_high(self) -> bool:
        return len(self.line.exposures) == self.ended

    def hold_high(self) -> None:
        self.line.stick_high()

    def release(self) -> None:
        self.line.mend()


class Pin:
    """A fake digital input (a GPIO line): `level` is the camera's exposure-active output;
    `reads_closed` counts reads while it is released."""

    def __init__(self) -> None:
        self.level = False
        self.opened = False
        self.reads_closed = 0


class TemplateExposureInput(MyExposureInput):
    """The trigger template filled in as its comments say, over a fake digital input."""

    def __init__(self, pin: Pin) -> None:
        self.pin = pin
        super().__init__("fake-gpio", timeout_ms=TIMEOUT_MS)

    def _do_open(self) -> None:
        self.pin.opened = True

    def _do_close(self) -> None:
        self.pin.opened = False

    def _input_high(self) -> bool:
        if not self.pin.opened:
            self.pin.reads_closed += 1
        return self.pin.level


class PinHand(HandDriven):
    """Sets the fake input's level; keeps the windows it made (a host input has no record)."""

    def __init__(self, pin: Pin, clock: Callable[[], float]) -> None:
        self.pin = pin
        self.clock = clock
        self.windows: list[ExposureWindow] = []
        self._since: float | None = None

    def begin(self) -> None:
        self._since = self.clock()
        self.pin.level = True

    def end(self) -> float:
        at_s = self.clock()
        self.pin.level = False
        if self._since is not None:
            self.windows.append(ExposureWindow(self._since, at_s))
            self._since = None
        return self.windows[-1].end_s



@dataclass
class ExposureSetup:
    line: TriggerLine
    slm: SLM  # writes its frames through the line's gate
    hand: ExposureHand | None  # None: not driven (a real line: leave the camera idle)
    windows: Callable[[], list[ExposureWindow]] | None = None  # the exposures' record
    holds_off_exposures: bool = False  # the line holds off the camera's next exposure in a write
    reads_after_close: Callable[[], int] | None = None


def gated_slm(line: TriggerLine) -> SLM:
    slm = SimulatedSLM(PANEL, PANEL, SLMOutputSettings(settle_ms=0.0))
    slm.attach_trigger(line)
    return slm.open()


@pytest.fixture(params=["model", "simulated-bench", "template", "bench"])
def exposure(request: pytest.FixtureRequest) -> Iterator[ExposureSetup]:
    if request.param == "model":
        line = TriggerLine("camera_exposure", timeout_ms=TIMEOUT_MS)
        with line, gated_slm(line) as slm:
            yield ExposureSetup(line, slm, LineHand(line), lambda: line.exposures, True)
    elif request.param == "simulated-bench":
        with simulated_bench("camera_exposure") as b:
            line = b.slm.trigger
            yield ExposureSetup(line, b.slm, CameraHand(b), lambda: line.exposures, True)
    elif request.param == "template":
        pin = Pin()
        with TemplateExposureInput(pin) as line, gated_slm(line) as slm:
            hand = PinHand(pin, line.clock)
            yield ExposureSetup(line, slm, hand, lambda: hand.windows,
                                reads_after_close=lambda: pin.reads_closed)
    else:
        with lab_line("camera_exposure") as line, gated_slm(line) as slm:
            yield ExposureSetup(line, slm, None)


def shown(slm: SLM) -> int:
    return int(slm.last_frame[0, 0, 0])


def test_a_write_goes_through_a_low_line_and_waits_while_it_is_high(exposure):
    slm, line = exposure.slm, exposure.line
    n = len(line.writes)
    slm.show(frame(1))  # low: written at once
    assert len(line.writes) == n + 1 and shown(slm) == 1
    hand = needs(exposure.hand)
    hand.begin()
    errors: list[BaseException] = []

    def write() -> None:
        try:
            slm.show(frame(2))
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    writer = threading.Thread(target=write)
    writer.start()
    time.sleep(0.01)  # the writer reaches the gate (no assertion rests on how long it takes)
    nothing_yet = len(line.writes) == n + 1 and shown(slm) == 1
    still_high = hand.still_high()  # after: then it was high when nothing_yet was read
    fell_s = hand.end()
    writer.join(10.0)
    assert not errors, errors
    if still_high:
        assert nothing_yet  # held while the line was high
    assert line.writes[-1] >= fell_s and shown(slm) == 2  # written once it fell


def test_a_line_that_stays_high_fails_the_write_naming_the_trigger_and_timeout(exposure):
    slm, line = exposure.slm, exposure.line
    hand = needs(exposure.hand)
    slm.show(frame(10))
    hand.hold_high()
    writes = len(line.writes)
    t0 = line.clock()
    with pytest.raises(TriggerTimeout, match=STAYED_HIGH) as stayed:
        slm.show(frame(100))
    assert isinstance(stayed.value, DeviceError)
    assert line.clock() >= t0 + line.timeout_s  # on the line's clock: after the whole timeout
    assert len(line.writes) == writes and shown(slm) == 10  # nothing written
    hand.release()
    slm.show(frame(100))
    assert shown(slm) == 100


def test_exposures_and_writes_are_recorded_once_in_order_and_never_overlap(exposure):
    slm, line = exposure.slm, exposure.line
    hand = needs(exposure.hand)
    windows = exposure.windows
    assert windows is not None
    rng = np.random.default_rng(5)
    writes_before, windows_before = len(line.writes), len(windows())
    exposed = 0
    for _ in range(14):
        if rng.random() < 0.5:
            slm.show(frame(int(rng.integers(0, 256))))
        else:
            hand.begin()
            hand.end()
            if rng.random() < 0.3:
                hand.end()  # the fall reported again: still one exposure
            exposed += 1
    writes, got = line.writes[writes_before:], windows()[windows_before:]
    assert len(got) == exposed
    assert writes == sorted(writes)
    for w in got:
        assert w.start_s <= w.end_s
    for a, b in itertools.pairwise(got):
        assert a.end_s <= b.start_s
    assert not [(t, w) for w in got for t in writes if w.start_s < t < w.end_s]
    assert line.writes_during_exposures() == []


def test_no_frame_is_written_inside_an_exposure_while_the_camera_keeps_exposing(exposure):
    slm, line = exposure.slm, exposure.line
    hand = needs(exposure.hand)
    if not exposure.holds_off_exposures:
        pytest.skip("a host input cannot hold off the camera's next exposure during a write: "
                    "only the wait while high is this line's")
    windows = exposure.windows
    assert windows is not None
    rng = np.random.default_rng(1)
    stop = threading.Event()
    errors: list[BaseException] = []

    def camera() -> None:
        try:
            hand.expose()  # at least one exposure, however soon the writes end
            while not stop.is_set():
                time.sleep(READOUT_S)  # the line is low between exposures: writes go then
                hand.expose()
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    writes_before, windows_before = len(line.writes), len(windows())
    worker = threading.Thread(target=camera)
    worker.start()
    try:
        for _ in range(8):
            time.sleep(float(rng.uniform(0.002, 0.012)))
            slm.show(rng.integers(0, 256, (PANEL, PANEL), dtype=np.uint8))
    finally:
        stop.set()
        worker.join(10.0)
    assert not errors, errors
    writes, got = line.writes[writes_before:], windows()[windows_before:]
    assert len(writes) == 8 and got
    assert not [(t, w) for w in got for t in writes if w.start_s < t < w.end_s]


def test_no_exposure_begins_while_a_frame_is_being_written(exposure):
    slm, line = exposure.slm, exposure.line
    hand = needs(exposure.hand)
    if not exposure.holds_off_exposures:
        pytest.skip("a host input cannot hold off the camera's next exposure during a write: "
                    "only the wait while high is this line's")
    windows = exposure.windows
    assert windows is not None
    writing, release, begun = threading.Event(), threading.Event(), threading.Event()
    spans: list[tuple[float, float]] = []
    errors: list[BaseException] = []
    write = slm._write

    def held_write(rgb: np.ndarray) -> None:  # the panel mid-write until released
        start = line.clock()
        writing.set()
        release.wait(10.0)
        write(rgb)
        spans.append((start, line.clock()))

    def run(step: Callable[[], Any]) -> Callable[[], None]:
        def body() -> None:
            try:
                step()
            except BaseException as exc:  # surfaced below
                errors.append(exc)
        return body

    slm._write = held_write  # type: ignore[method-assign]
    writer = threading.Thread(target=run(lambda: slm.show(frame(7))))
    writer.start()
    assert writing.wait(10.0)
    camera = threading.Thread(target=run(lambda: (hand.begin(), begun.set())))
    camera.start()
    begun.wait(0.05)  # a chance to begin during the write (none on a working line)
    release.set()
    writer.join(10.0)
    camera.join(10.0)
    assert not errors, errors
    hand.end()
    assert windows()[-1].start_s >= spans[-1][1]  # the exposure began after the write ended


def test_a_closed_exposure_line_refuses_the_write_it_cannot_gate_and_opens_again(exposure):
    slm, line = exposure.slm, exposure.line
    slm.show(frame(3))
    line.close()
    line.close()
    assert not line.is_open
    writes = len(line.writes)
    with pytest.raises(LinkDown, match="trigger camera_exposure: not open"):
        slm.show(frame(4))
    assert len(line.writes) == writes and shown(slm) == 3
    if exposure.reads_after_close is not None:
        assert exposure.reads_after_close() == 0  # the released input was not read
    line.open()
    line.open()  # a no-op when open
    assert line.is_open
    slm.show(frame(4))
    assert shown(slm) == 4
    if exposure.hand is None:
        return
    # A write waiting on a high line when the line closes fails with LinkDown, not later with
    # the timeout, and writes nothing.
    exposure.hand.hold_high()
    failed: list[BaseException] = []

    def write() -> None:
        try:
            slm.show(frame(5))
        except BaseException as exc:  # judged below
            failed.append(exc)

    writer = threading.Thread(target=write)
    writer.start()
    time.sleep(0.01)  # the writer reaches the gate (it fails the same way if it has not)
    line.close()
    writer.join(10.0)
    assert len(failed) == 1 and isinstance(failed[0], LinkDown), failed
    assert shown(slm) == 4
    exposure.hand.release()
    line.open()
    slm.show(frame(5))
    assert shown(slm) == 5
