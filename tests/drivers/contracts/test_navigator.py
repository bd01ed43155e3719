"""The navigator contract: every navigator backend, and a real SpaceMouse when NHFD_TEST_NAVIGATOR
names its hidraw node (NHFD_TEST_NAVIGATOR=spacemouse:/dev/hidraw3; leave the puck alone while it
runs: the facts that need a hand on it run on the set-ups that have one).

What every backend keeps (docs/hardware.md, "Navigator"; nhfd.drivers.navigator):

- raw counts (on a SpaceMouse: HID report id 1 translation, id 2 rotation, 3 x int16 little-endian
  each, or one 13-byte report id 1 on some models) become velocities in the documented units: 0
  inside the dead zone, linear from its edge to `full_scale_counts`, clipped there, times
  `axis_signs` and `max_translation_m_s` (m/s) or `max_rotation_deg_s` (deg/s); a read consumes
  every report waiting, so it shows the latest state; its time is the navigator's clock;
- buttons are edge-detected: `presses` grows once per report in which a button goes down (a
  press and release between two reads counts, a button held or reported again does not);
- an unplugged puck raises DeviceError on every read (never OSError, never a stale reading), a
  reconnect fails with LinkDown until it is back and then starts from rest (the deflection seen
  before the unplug is not replayed, a button held through it is no new press);
- close is idempotent, a closed navigator reads nothing (LinkDown, and no read reaches the
  device), and it opens again.

Backends: SpaceMouseNavigator on a HID twin (hidapi's interface, so the driver's code runs
unchanged) sending separate id 1 / id 2 reports, the same on a model that sends the 13-byte
combined report, SimulatedNavigator, and the navigator template (nhfd.drivers.templates.
navigator_backend) filled in as its comments say, on the same HID twin.
"""

from __future__ import annotations

import math
import struct
import threading
import time
import types
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np
import pytest

from nhfd.device_settings import NavigatorSettings
from nhfd.drivers import navigator as navigator_module
from nhfd.drivers.errors import DeviceError, LinkDown, PortNotFound, PortVanished
from nhfd.drivers.navigator import (
    Navigator,
    RawState,
    SimulatedNavigator,
    SpaceMouseNavigator,
    Waypoint,
    matches,
    parse_report,
)
from nhfd.drivers.templates.navigator_backend import MyNavigator
from nhfd.drivers.twins.clock import ManualClock

from . import bench_target

Axes = tuple[int, int, int, int, int, int]

DEAD, FULL = 15, 350
MAX_M_S, MAX_DEG_S = 0.2, 90.0
SIGNS = (1, -1, 1, 1, -1, -1)
SETTINGS = NavigatorSettings(dead_zone_counts=DEAD, full_scale_counts=FULL,
                             max_translation_m_s=MAX_M_S, max_rotation_deg_s=MAX_DEG_S,
                             axis_signs=list(SIGNS), read_timeout_ms=0)
REST: Axes = (0, 0, 0, 0, 0, 0)
DEFLECTED: Axes = (200, 0, -120, 0, 90, 0)


class HidTwin:
    """A SpaceMouse (and a Logitech mouse beside it) behind hidapi's interface: the `hid` module's
    enumerate() and device() with open_path, set_nonblocking, read and close. The hand sends
    reports; `unplug()` drops the puck from the enumeration, fails opens, makes every handle
    opened before it fail its reads with OSError for good (as a vanished hidraw node does) and
    loses what the puck sends meanwhile. `reads_closed` counts reads of a closed handle."""

    PATH = b"/dev/hidraw7"
    PUCK: ClassVar[dict[str, Any]] = {
        "vendor_id": 0x256F, "product_id": 0xC635, "path": PATH, "usage_page": 1, "usage": 8,
        "product_string": "SpaceMouse Compact"}
    MOUSE: ClassVar[dict[str, Any]] = {
        "vendor_id": 0x046D, "product_id": 0xC077, "path": b"/dev/hidraw2"}

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.reports: deque[bytes] = deque()
        self.plugged = True
        self.generation = 0  # bumped by each unplug: older handles are dead
        self.reads_closed = 0
        self.module = self._module()

    def send(self, report: bytes) -> None:
        with self.lock:
            if self.plugged:
                self.reports.append(report)

    def unplug(self) -> None:
        with self.lock:
            self.plugged = False
            self.generation += 1
            self.reports.clear()

    def replug(self) -> None:
        with self.lock:
            self.plugged = True

    def _module(self) -> types.ModuleType:
        twin = self
        module = types.ModuleType("hid")

        class Handle:
            def __init__(self) -> None:
                self.generation: int | None = None

            def open_path(self, path: bytes) -> None:
                with twin.lock:
                    if not twin.plugged or path != twin.PATH:
                        raise OSError("open failed")
                    self.generation = twin.generation

            def set_nonblocking(self, flag: bool) -> None:
                pass

            def read(self, size: int) -> list[int]:
                with twin.lock:
                    if self.generation is None:
                        twin.reads_closed += 1
                        raise ValueError("not open")
                    if self.generation != twin.generation:
                        raise OSError("read error")
                    return list(twin.reports.popleft()[:size]) if twin.reports else []

            def close(self) -> None:
                self.generation = None

        def enumerate(vendor_id: int = 0, product_id: int = 0) -> list[dict[str, Any]]:
            with twin.lock:
                return [dict(twin.MOUSE)] + ([dict(twin.PUCK)] if twin.plugged else [])

        module.enumerate = enumerate
        module.device = Handle
        return module


class TemplateNavigator(MyNavigator):
    """The navigator template filled in as its comments say, over hidapi's interface."""

    def __init__(self, hid: types.ModuleType, settings: NavigatorSettings,
                 clock: Callable[[], float]) -> None:
        super().__init__(settings, clock=clock)
        self.hid = hid
        self.handle: Any = None
        self.state = RawState()

    def _do_open(self) -> None:
        found = [d for d in self.hid.enumerate()
                 if matches(d["vendor_id"], d["product_id"], self.settings.usb_ids)]
        if not found:
            raise PortNotFound("no navigator found")
        handle = self.hid.device()
        try:
            handle.open_path(found[0]["path"])
        except OSError as exc:
            raise PortNotFound(f"navigator: {exc}") from None
        self.handle, self.state = handle, self._at_rest()

    def _do_close(self) -> None:
        if self.handle is not None:
            self.handle.close()
            self.handle = None

    def _poll(self) -> RawState:
        try:
            while report := self.handle.read(64):
                self.state = parse_report(report, self.state)
                self._count_presses(self.state.buttons)
        except OSError as exc:
            raise PortVanished(f"navigator read failed: {exc}") from None
        return self.state


class Hand(Protocol):
    """The bench's hand on the puck."""

    def hold(self, axes: Axes, buttons: int = 0) -> None:
        """Deflect the puck to these raw counts with these buttons down (until the next hold)."""

    def tap(self, button: int) -> None:
        """Press and release `button` before the next read."""

    def unplug(self) -> None: ...

    def replug(self) -> None: ...


class HidHand:
    """Moves the twin's puck: each hold sends its axis reports (id 1 and id 2, or the 13-byte
    combined id 1) and a button report (id 3, 2 bytes), as a SpaceMouse does."""

    def __init__(self, twin: HidTwin, *, combined: bool) -> None:
        self.twin = twin
        self.combined = combined
        self.buttons = 0

    def hold(self, axes: Axes, buttons: int = 0) -> None:
        if self.combined:
            self.twin.send(bytes([1]) + struct.pack("<6h", *axes))
        else:
            self.twin.send(bytes([1]) + struct.pack("<3h", *axes[:3]))
            self.twin.send(bytes([2]) + struct.pack("<3h", *axes[3:]))
        self.twin.send(bytes([3]) + buttons.to_bytes(2, "little"))
        self.buttons = buttons

    def tap(self, button: int) -> None:
        self.twin.send(bytes([3]) + (self.buttons | 1 << button).to_bytes(2, "little"))
        self.twin.send(bytes([3]) + self.buttons.to_bytes(2, "little"))

    def unplug(self) -> None:
        self.twin.unplug()

    def replug(self) -> None:
        self.twin.replug()


class SimulatedHand:
    """Moves the simulated puck: a hold is a one-waypoint script (the puck held from then on)."""

    def __init__(self, navigator: SimulatedNavigator) -> None:
        self.navigator = navigator

    def hold(self, axes: Axes, buttons: int = 0) -> None:
        self.navigator.trajectory = [Waypoint(0.0, axes, buttons)]

    def tap(self, button: int) -> None:
        self.navigator.press(button)

    def unplug(self) -> None:
        self.navigator.unplug()

    def replug(self) -> None:
        self.navigator.replug()


@dataclass
class Setup:
    navigator: Navigator
    hand: Hand | None  # None: a real puck, which no test can move
    clock: Callable[[], float]  # the navigator's clock
    reads_after_close: Callable[[], int] | None = None  # the twin's record, where there is one


def real_navigator() -> Setup:
    _, (path, *_) = bench_target("NHFD_TEST_NAVIGATOR", ("spacemouse",),
                                 "spacemouse:/dev/hidraw3")
    return Setup(SpaceMouseNavigator(NavigatorSettings(), path=path), None, time.monotonic)


@pytest.fixture(params=["spacemouse-hid", "spacemouse-hid-13", "simulated", "template",
                        "bench"])
def setup(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[Setup]:
    clock = ManualClock(100.0)
    if request.param in ("spacemouse-hid", "spacemouse-hid-13", "template"):
        twin = HidTwin()
        hand = HidHand(twin, combined=request.param == "spacemouse-hid-13")
        if request.param == "template":
            driver: Navigator = TemplateNavigator(twin.module, SETTINGS, clock)
        else:
            monkeypatch.setattr(navigator_module, "hid", twin.module)
            driver = SpaceMouseNavigator(SETTINGS, clock=clock)
        built = Setup(driver, hand, clock, lambda: twin.reads_closed)
    elif request.param == "simulated":
        driver = SimulatedNavigator([], SETTINGS, clock=clock)
        built = Setup(driver, SimulatedHand(driver), clock)
    else:
        built = real_navigator()
    with built.navigator:
        yield built


def needs_hand(setup: Setup) -> Hand:
    if setup.hand is None:
        pytest.skip("needs a hand on the puck: this fact runs on the set-ups that have one")
    return setup.hand


def velocity(raw: int, sign: int, maximum: float) -> float:
    """The documented scaling, written out: 0 inside the dead zone, linear from its edge to full
    scale, clipped there."""
    if abs(raw) <= DEAD:
        return 0.0
    return sign * math.copysign(min(1.0, (abs(raw) - DEAD) / (FULL - DEAD)), raw) * maximum


def assert_velocities(reading: Any, axes: Axes) -> None:
    expected = [velocity(v, s, MAX_M_S if i < 3 else MAX_DEG_S)
                for i, (v, s) in enumerate(zip(axes, SIGNS, strict=True))]
    got = list(reading.translation_m_s) + list(reading.rotation_deg_s)
    assert got == pytest.approx(expected, rel=1e-12, abs=1e-12), axes


def still(reading: Any) -> bool:
    return reading.translation_m_s == (0.0, 0.0, 0.0) and reading.rotation_deg_s == (0.0,) * 3


def test_counts_become_velocities_in_the_documented_units_and_signs(setup):
    hand = needs_hand(setup)
    nav = setup.navigator
    # Anchors: full deflection, the axis signs, a fifth of the way past the dead zone's edge,
    # clipping beyond full scale, the int16 extremes.
    hand.hold((FULL, -FULL, DEAD + 67, -(DEAD + 67), 32767, -32768))
    r = nav.read()
    assert r.translation_m_s == pytest.approx((0.2, 0.2, 0.04))  # y's sign is -1
    assert r.rotation_deg_s == pytest.approx((-18.0, -90.0, 90.0))  # ry and rz's are -1
    # Seeded random states, one to three of them between two reads: a read consumes every
    # report waiting and shows the latest.
    rng = np.random.default_rng(7)
    for _ in range(60):
        held: list[tuple[Axes, int]] = []
        for _ in range(int(rng.integers(1, 4))):
            span = 32768 if rng.random() < 0.25 else FULL + 50
            axes = tuple(int(v) for v in rng.integers(-span, span, 6))
            held.append((axes, int(rng.integers(0, 4))))  # type: ignore[arg-type]
            hand.hold(*held[-1])
        if isinstance(setup.clock, ManualClock):
            setup.clock.advance(float(rng.uniform(0.001, 0.1)))
        r = nav.read()
        assert_velocities(r, held[-1][0])
        assert r.buttons == held[-1][1]
        if isinstance(setup.clock, ManualClock):
            assert r.time_s == setup.clock()  # the navigator's clock at the read


def test_inside_the_dead_zone_every_axis_reads_exactly_zero(setup):
    nav = setup.navigator
    times = []
    if setup.hand is None:  # a real puck at rest rests inside the dead zone
        for _ in range(5):
            r = nav.read()
            assert still(r), r
            times.append(r.time_s)
    else:
        rng = np.random.default_rng(11)
        cases = [(DEAD, -DEAD, DEAD, -DEAD, 0, DEAD)]
        cases += [tuple(int(v) for v in rng.integers(-DEAD, DEAD + 1, 6)) for _ in range(40)]
        for axes in cases:
            setup.hand.hold(axes)  # type: ignore[arg-type]
            r = nav.read()
            assert still(r), axes
            times.append(r.time_s)
        setup.hand.hold((DEAD + 1, 0, 0, 0, 0, 0))  # one count past the edge moves
        assert nav.read().translation_m_s[0] == pytest.approx(MAX_M_S / (FULL - DEAD))
    assert times == sorted(times)


def test_buttons_are_edge_detected(setup):
    hand = needs_hand(setup)
    nav = setup.navigator
    base = nav.presses

    def held(buttons: int) -> Any:
        hand.hold(REST, buttons)
        return nav.read()

    r = held(0b1)
    assert r.buttons == 0b1 and r.pressed(0) and not r.pressed(1)
    assert nav.presses == base + 1
    for _ in range(3):  # held, and reported again: no new press
        held(0b1)
    assert nav.presses == base + 1
    assert held(0b101).pressed(2) and nav.presses == base + 2  # another goes down
    held(0b100)
    held(0)  # releases are no presses
    assert nav.presses == base + 2
    hand.tap(1)  # down and up between two reads: still a press
    r = nav.read()
    assert nav.presses == base + 3 and r.buttons == 0
    held(0b11)  # two going down in one report: one press
    assert nav.presses == base + 4


def test_an_unplugged_puck_raises_the_kinds_error_and_a_reconnect_starts_from_rest(setup):
    hand = needs_hand(setup)
    nav = setup.navigator
    hand.hold(DEFLECTED, 0b10)
    assert not still(nav.read())
    presses = nav.presses
    hand.unplug()
    for _ in range(2):  # every read, not a stale reading
        with pytest.raises(DeviceError):
            nav.read()
    with pytest.raises(LinkDown, match="no link"):  # nothing there to open
        nav.reconnect()
    with pytest.raises(DeviceError):
        nav.read()
    hand.hold(REST, 0b10)  # let go while unplugged (a real puck sends nothing meanwhile)
    hand.replug()
    nav.reconnect()
    assert still(nav.read())  # from rest: the deflection before the unplug is not replayed
    hand.hold(REST, 0b10)  # the button held all along, reported again
    r = nav.read()
    assert r.buttons == 0b10 and nav.presses == presses  # no new press
    hand.hold(DEFLECTED)
    assert_velocities(nav.read(), DEFLECTED)


def test_close_is_idempotent_and_nothing_reads_after_it(setup):
    nav = setup.navigator
    nav.read()
    nav.close()
    nav.close()
    assert not nav.is_open
    for _ in range(2):
        with pytest.raises(LinkDown, match="not open"):
            nav.read()
    if setup.reads_after_close is not None:
        assert setup.reads_after_close() == 0  # the device was not touched
    nav.open()
    nav.open()  # a no-op when open
    assert nav.is_open
    nav.read()


def test_a_reconnect_of_a_plugged_navigator_reads_again(setup):
    nav = setup.navigator
    nav.read()
    nav.reconnect()
    assert nav.is_open
    r = nav.read()
    if setup.hand is not None:
        assert still(r)
        setup.hand.hold(DEFLECTED)
        assert_velocities(nav.read(), DEFLECTED)
