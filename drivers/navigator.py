"""6-DoF navigator: SpaceMouse HID report parsing, a hidapi backend, and a simulated navigator.

HID reports (docs/design.md, "The hardware": Navigator): id 1 translation (3 x int16
little-endian), id 2 rotation (3 x int16), id 3 buttons (bitmask); some models send translation
and rotation together in one 13-byte report id 1. Other ids (battery, LEDs) are ignored. Devices
are matched by vendor AND product id: vendor 0x046d is Logitech's, shared with mice and keyboards.

`Navigator.read()` returns velocities: each raw axis through a dead zone, scaled linearly from the
dead-zone edge to full deflection, times the configured maximum.

`presses` counts button presses (a button going down) report by report, so a press and release
that arrive between two reads still count: the daemon's arm confirmation
(`daemon.arming.confirm = "spacemouse"`) waits for it to grow. The simulated navigator is pressed by
`press()`.

Lifecycle (the base class, for every backend): `read()` on a navigator that was closed raises
LinkDown and touches no device until it opens again; `close()` is idempotent. A read that fails
(an unplugged puck) raises DeviceError; `reconnect()` reopens it (one attempt: the caller reads
again on its own period) and starts from rest: the last deflection seen before the unplug is not
replayed (a puck sends reports only when it changes), and a button held through it is no new
press. The contract every backend keeps is tests/drivers/contracts/test_navigator.py.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import hid

from nhfd.device_settings import NavigatorSettings

from .device import Device
from .errors import (
    DeviceError,
    LinkDown,
    PortNotFound,
    PortVanished,
    ProtocolError,
    TransportError,
)

REPORT_TRANSLATION = 1
REPORT_ROTATION = 2
REPORT_BUTTONS = 3
COMBINED_REPORT_BYTES = 13  # id + 6 x int16
AXES = struct.Struct("<3h")
AXES6 = struct.Struct("<6h")


@dataclass(frozen=True)
class RawState:
    """Raw axis counts x, y, z, rx, ry, rz and the button bitmask."""

    axes: tuple[int, int, int, int, int, int] = (0, 0, 0, 0, 0, 0)
    buttons: int = 0


def parse_report(report: bytes | Sequence[int], state: RawState = RawState()) -> RawState:
    """The state after one HID report (report id first)."""
    data = bytes(report)
    if not data:
        raise ProtocolError("empty HID report")
    rid, body = data[0], data[1:]
    if rid == REPORT_TRANSLATION:
        if len(data) >= COMBINED_REPORT_BYTES:
            return RawState(AXES6.unpack_from(body), state.buttons)
        if len(body) < AXES.size:
            raise ProtocolError(f"translation report of {len(data)} bytes: {data.hex(' ')}")
        return RawState(AXES.unpack_from(body) + state.axes[3:], state.buttons)
    if rid == REPORT_ROTATION:
        if len(body) < AXES.size:
            raise ProtocolError(f"rotation report of {len(data)} bytes: {data.hex(' ')}")
        return RawState(state.axes[:3] + AXES.unpack_from(body), state.buttons)
    if rid == REPORT_BUTTONS:
        return RawState(state.axes, int.from_bytes(body, "little"))
    return state


def matches(vendor_id: int, product_id: int, usb_ids: Sequence[Sequence[int]]) -> bool:
    """Whether (vendor_id, product_id) is one of `usb_ids` (both must match)."""
    return any(vendor_id == v and product_id == p for v, p in usb_ids)


@dataclass(frozen=True)
class NavigatorReading:
    """One reading: view translation velocity (scene m/s) and rotation velocity (deg/s) about x, y,
    z, the button bitmask, and when it was read (s, the navigator's clock)."""

    translation_m_s: tuple[float, float, float]
    rotation_deg_s: tuple[float, float, float]
    buttons: int
    time_s: float

    def pressed(self, button: int) -> bool:
        """Whether button `button` (bit index) is down."""
        return bool(self.buttons >> button & 1)


def scale_axis(raw: int, dead_zone: int, full_scale: int) -> float:
    """Raw counts -> [-1, 1]: 0 inside the dead zone, linear from its edge, clipped at 1."""
    magnitude = abs(raw)
    if magnitude <= dead_zone:
        return 0.0
    span = max(full_scale - dead_zone, 1)
    return (1.0 if raw > 0 else -1.0) * min(1.0, (magnitude - dead_zone) / span)


def to_reading(state: RawState, settings: NavigatorSettings, time_s: float) -> NavigatorReading:
    """Raw counts -> velocities: each axis through the dead zone and `axis_signs`, times
    `max_translation_m_s` or `max_rotation_deg_s`."""
    s = settings
    unit = [sign * scale_axis(v, s.dead_zone_counts, s.full_scale_counts)
            for v, sign in zip(state.axes, s.axis_signs, strict=True)]
    return NavigatorReading(
        translation_m_s=(unit[0] * s.max_translation_m_s, unit[1] * s.max_translation_m_s,
                         unit[2] * s.max_translation_m_s),
        rotation_deg_s=(unit[3] * s.max_rotation_deg_s, unit[4] * s.max_rotation_deg_s,
                        unit[5] * s.max_rotation_deg_s),
        buttons=state.buttons,
        time_s=time_s,
    )


class Navigator(Device, ABC):
    """A 6-DoF navigator read as velocities; `presses` counts button presses. A backend implements
    `_poll` (and `_do_open` / `_do_close`); the base keeps the lifecycle: no read once closed,
    an idempotent close, a reconnect that starts from rest."""

    def __init__(self, settings: NavigatorSettings | None = None, *,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.settings = settings or NavigatorSettings()
        self._clock = clock
        self.presses = 0  # buttons gone down, counted per report (read by other threads)
        self._buttons_seen = 0
        self._is_open = False
        # Closed after an open: reads refused until it opens again. (One never opened is left
        # to its backend: the simulated one reads its script, the SpaceMouse has no device.)
        self._closed = False

    @property
    def is_open(self) -> bool:
        """Whether the navigator is open (reads allowed)."""
        return self._is_open

    def open(self) -> Navigator:
        """Open the backend (`_do_open`); a no-op when open. The buttons last seen down are
        kept: one still down after a reopen is no new press (a reconnect never confirms an arm
        by itself)."""
        if not self._is_open:
            self._do_open()
            self._is_open, self._closed = True, False
        return self

    def close(self) -> None:
        """Close the backend (`_do_close`); a no-op when closed."""
        if self._is_open:
            self._is_open, self._closed = False, True
            self._do_close()

    def reconnect(self) -> None:
        """Reopen after a link loss (an unplugged puck): one attempt, since NavigatorSettings has
        no back-off (the caller reads again on its own period). Raises LinkDown naming the
        failure when the navigator is not back."""
        self._is_open, self._closed = False, True
        self._close_quietly()
        try:
            self.open()
        except TransportError as exc:
            raise LinkDown(f"{self.name}: no link: {exc}") from None

    def _at_rest(self) -> RawState:
        """The state a backend starts from when it opens: every axis at zero (a puck reports only
        what changes: the deflection last seen is not replayed), the buttons last seen down kept
        (one still down is no new press)."""
        return RawState(buttons=self._buttons_seen)

    def _count_presses(self, buttons: int) -> None:
        """Count a press for each report in which a button goes down."""
        if buttons & ~self._buttons_seen:
            self.presses += 1
        self._buttons_seen = buttons

    def read(self) -> NavigatorReading:
        """The current velocities and buttons (consumes every report waiting). LinkDown once
        closed; DeviceError when the device cannot be read (unplugged: `reconnect`)."""
        if self._closed:
            raise LinkDown(f"{self.name}: navigator not open")
        return to_reading(self._poll(), self.settings, self._clock())

    # -- backend hooks -------------------------------------------------------------------------

    @abstractmethod
    def _poll(self) -> RawState:
        """Consume every report waiting, counting presses per report (`_count_presses`), and
        return the latest raw state; DeviceError when the device cannot be read."""


class SpaceMouseNavigator(Navigator):
    """A 3Dconnexion SpaceMouse through hidapi: the first device matching the USB ids, or the one
    at `path` (a hidapi path such as /dev/hidraw3, which must match them too)."""

    def __init__(self, settings: NavigatorSettings | None = None, *,
                 clock: Callable[[], float] = time.monotonic,
                 path: str | bytes | None = None) -> None:
        super().__init__(settings, clock=clock)
        self.path = path
        self._device: Any = None
        self._state = RawState()
        self.product: str = ""

    def _do_open(self) -> None:
        found = [d for d in hid.enumerate()
                 if matches(d["vendor_id"], d["product_id"], self.settings.usb_ids)]
        where = ""
        if self.path is not None:
            wanted = os.fsencode(self.path)
            found = [d for d in found if os.fsencode(d["path"]) == wanted]
            where = f" at {os.fsdecode(wanted)}"
        # A device may expose several interfaces; the multi-axis controller is usage page 1,
        # usage 8 where hidapi reports usages.
        found.sort(key=lambda d: (d.get("usage_page"), d.get("usage")) != (1, 8))
        if not found:
            raise PortNotFound(f"no SpaceMouse found{where} (vendor and product id; is the udev "
                               "rule installed?)")
        info = found[0]
        device = hid.device()
        try:
            device.open_path(info["path"])
            device.set_nonblocking(True)
        except OSError as exc:  # gone since the enumeration, or no permission
            raise PortNotFound(f"SpaceMouse {os.fsdecode(info['path'])}: cannot open ({exc}; is "
                               "the udev rule installed?)") from None
        self._device = device
        self._state = self._at_rest()
        self.product = info.get("product_string") or f"{info['vendor_id']:04x}:" \
            f"{info['product_id']:04x}"

    def _do_close(self) -> None:
        if self._device is not None:
            self._device.close()
            self._device = None

    def _poll(self) -> RawState:
        if self._device is None:
            raise DeviceError("navigator not open")
        deadline = time.monotonic() + self.settings.read_timeout_ms / 1000
        for _ in range(256):  # drain, bounded
            try:
                report = self._device.read(64)
            except (OSError, ValueError) as exc:  # hidapi: OSError unplugged, ValueError closed
                raise PortVanished(f"SpaceMouse read failed (unplugged?): {exc}") from None
            if not report:
                if time.monotonic() >= deadline:
                    break
                time.sleep(0.001)
                continue
            self._state = parse_report(report, self._state)
            self._count_presses(self._state.buttons)
        return self._state


@dataclass(frozen=True)
class Waypoint:
    """From t_s on (seconds after open), the puck reads axes_counts and these buttons."""

    t_s: float
    axes_counts: tuple[int, int, int, int, int, int]
    buttons: int = 0


class SimulatedNavigator(Navigator):
    """Replays a scripted trajectory on the clock, holding each waypoint until the next (and the
    last one for ever: end a script with a zero waypoint)."""

    def __init__(self, trajectory: Sequence[Waypoint], settings: NavigatorSettings | None = None,
                 *, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(settings, clock=clock)
        self.trajectory = list(trajectory)
        times = [w.t_s for w in self.trajectory]
        if times != sorted(times):
            raise ValueError("waypoints must be in time order")
        self._t0 = clock()
        self._pressed: list[int] = []  # press() not yet seen by a read
        self._press_lock = threading.Lock()
        self._plugged = True

    def _do_open(self) -> None:
        if not self._plugged:
            raise PortNotFound(f"{self.name}: unplugged")
        self._t0 = self._clock()

    def unplug(self) -> None:
        """Test-only: the puck's cable is pulled: reads fail (DeviceError) and opens find nothing
        until `replug`; presses meanwhile are lost."""
        self._plugged = False

    def replug(self) -> None:
        """Test-only: the cable is back; `reconnect` opens it again."""
        self._plugged = True

    def press(self, button: int = 0) -> None:
        """A person presses and releases `button` (test-only: the bench's hand); the next read
        sees it go down and up, as two HID reports between reads would show it."""
        if not 0 <= button < 32:
            raise ValueError(f"button: {button!r}; allowed: 0 to 31")
        with self._press_lock:
            self._pressed.append(button)

    def _poll(self) -> RawState:
        with self._press_lock:
            pressed, self._pressed = self._pressed, []
        if not self._plugged:
            raise PortVanished(f"{self.name}: read failed (unplugged)")
        for button in pressed:
            self._count_presses(self._buttons_seen | 1 << button)
            self._count_presses(self._buttons_seen & ~(1 << button))
        t = self._clock() - self._t0
        state = RawState()
        for w in self.trajectory:
            if w.t_s > t:
                break
            state = RawState(w.axes_counts, w.buttons)
        self._count_presses(state.buttons)
        return state
