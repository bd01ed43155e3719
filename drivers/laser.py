"""Lasers: a base class with the safety logic, and the FISBA READYBeam backend over MeCom.

The base class owns everything that must hold for any laser a lab plugs in:

- identify before any write, and refuse a device of another type;
- all channels off on open, close, exceptions (`with` blocks), SIGTERM/SIGINT (after
  `install_signal_handlers()`), interpreter exit, link loss and reconnect;
- an armed state a person sets (`arm(duration_s)`), which expires and is never restored
  automatically (not after a reconnect, not after a restart);
- power clamped to the configured cap per channel whatever the caller asks;
- every write read back; a mismatch is a fault: all channels off, fault latched until a person
  calls `clear_fault()`.

A backend implements the small hooks at the bottom of `Laser` (connect, identify, read/write one
channel's enable and power). `MecomLaser` is the READYBeam; with a `MecomTwin`'s opener it is
also the simulated laser, so tests run the real protocol code.

Software safety never replaces the lab's hardware interlock.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import math
import signal
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from types import FrameType

from nhfd.device_settings import COLOURS, LaserSettings

from . import mecom
from .device import Device
from .errors import (
    DeviceError,
    LinkDown,
    PortVanished,
    ProtocolError,
    ReplyTimeout,
    TransportError,
    WrongDevice,
)
from .transport import LineControl, Opener, Transport, serial_opener

log = logging.getLogger(__name__)

Clock = Callable[[], float]

# READYBeam status parameter (104) values, as in Meerstetter's public drivers.
DEVICE_STATUS = {0: "init", 1: "ready", 2: "run", 3: "error", 4: "bootloader", 5: "pending reset"}
DEVICE_STATUS_ERROR = 3


class LaserFault(DeviceError):
    """The laser is not in the state the driver commanded. Latched until `clear_fault()`."""


class ReadbackMismatch(LaserFault):
    """A value read back after a write differs from what was written."""


class NotArmed(DeviceError):
    """Emission needs an armed laser (armed by a person, not expired)."""


@dataclass(frozen=True)
class ChannelState:
    """One channel as read back: enabled, and its power in % of the diode's full power."""

    enabled: bool
    power_pct: float


@dataclass(frozen=True)
class LaserStatus:
    """The laser as read back: the device's status code and name, each channel's `ChannelState`,
    arming (the time left in s) and the latched fault, if any."""

    device_status: int | None
    device_status_name: str
    channels: dict[str, ChannelState]
    armed: bool
    armed_remaining_s: float
    fault: str | None

    @property
    def any_on(self) -> bool:
        """Whether any channel is enabled at a power above 0."""
        return any(c.enabled and c.power_pct > 0 for c in self.channels.values())


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT/SIGTERM while lasers are being switched off, so a second Ctrl-C cannot cut an
    all-off in half; they are delivered right after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _raise_system_exit(signum: int, frame: FrameType | None) -> None:
    raise SystemExit(128 + signum)


def install_signal_handlers() -> None:
    """Make SIGTERM unwind like SIGINT does (SystemExit instead of an instant death), so `with`
    blocks, `finally` and atexit turn lasers off. Call from the main thread of a process that
    drives lasers; SIGINT raises Python's KeyboardInterrupt. That holds even where SIGINT was
    inherited as ignored (a shell without job control starts `cmd &` so, and Python then leaves
    it ignored): a laser process must not shrug off an interrupt. A handler the program
    installed itself is kept."""
    signal.signal(signal.SIGTERM, _raise_system_exit)
    if signal.getsignal(signal.SIGINT) in (signal.SIG_DFL, signal.SIG_IGN):
        signal.signal(signal.SIGINT, signal.default_int_handler)


class Laser(Device, ABC):
    """A multi-channel laser with the safety rules above. Channels are named "red", "green",
    "blue"; powers are percent of the diode's full power, clamped to the settings' cap."""

    channels: tuple[str, ...] = COLOURS

    def __init__(self, settings: LaserSettings, *, clock: Clock = time.monotonic) -> None:
        self.settings = settings
        self._clock = clock
        self._lock = threading.RLock()
        self._connected = False
        self._armed_until: float | None = None
        self.expiries = 0  # armings that ran out (`service`), for the guardian's trip record
        self._fault: str | None = None
        self.device_type: int | None = None
        # The unit's serial number where the device reports one (the guardian's identity).
        self.serial_number: int | None = None

    # -- lifecycle -----------------------------------------------------------------------------

    def open(self) -> Laser:
        """Connect, identify (refusing another device type before writing anything), take
        control, and switch every channel off with read-back."""
        with self._lock:
            if self._connected:
                return self
            self._armed_until = None
            self._do_open()
            try:
                found = self._do_identify()
                if found != self.settings.device_type:
                    raise WrongDevice(
                        f"{self.name}: device type {found}, expected {self.settings.device_type}; "
                        "refusing to drive it (nothing was written)"
                    )
                self.device_type = found
                self._prepare()
                self._connected = True
                self.all_off()
            except BaseException:
                self._connected = False
                self._close_quietly()
                raise
            atexit.register(self._off_at_exit)
            log.info("%s: open, device type %s, all channels off", self.name, found)
            return self

    def close(self) -> None:
        """All channels off (read back), then disconnect. Raises if off could not be confirmed."""
        with self._lock:
            atexit.unregister(self._off_at_exit)
            try:
                if self._connected:
                    self.all_off()
            finally:
                self._connected = False
                self._armed_until = None
                self._close_quietly()

    # A reconnect attempt that finds another device type raises WrongDevice: not retried.
    _retry_on = (TransportError, ProtocolError)

    def reconnect(self) -> None:
        """Reopen after a link loss, with exponential backoff (`Device.reconnect`). Re-identifies
        first, then all off; the armed state is not restored."""
        with self._lock:
            super().reconnect()

    def _before_reconnect(self) -> None:
        self._armed_until = None
        self._connected = False

    # -- arming --------------------------------------------------------------------------------

    def arm(self, duration_s: float) -> None:
        """A person allows emission for duration_s (at most the settings' arm_max_s)."""
        with self._lock:
            self._require_link()
            if not (math.isfinite(duration_s) and 0 < duration_s <= self.settings.arm_max_s):
                raise ValueError(
                    f"arm duration_s = {duration_s}: must be in (0, {self.settings.arm_max_s:g}]"
                )
            if self._fault:
                raise LaserFault(f"{self.name}: cannot arm with a latched fault: {self._fault}")
            self._armed_until = self._clock() + duration_s
            log.warning("%s: ARMED for %.1f s", self.name, duration_s)

    def disarm(self) -> None:
        """End emission permission and switch everything off."""
        with self._lock:
            self._armed_until = None
            if self._connected:
                self.all_off()

    @property
    def armed(self) -> bool:
        """Whether a person's arming is in force (not expired)."""
        return self._armed_until is not None and self._clock() < self._armed_until

    @property
    def armed_remaining_s(self) -> float:
        """Seconds left of the arming (0 when not armed)."""
        if self._armed_until is None:
            return 0.0
        return max(0.0, self._armed_until - self._clock())

    @property
    def connected(self) -> bool:
        """Whether the link is open (identified, every channel switched off at open)."""
        return self._connected

    @property
    def fault(self) -> str | None:
        """The latched fault's description, or None."""
        return self._fault

    def clear_fault(self) -> None:
        """A person has looked at the fault; arming is possible again."""
        with self._lock:
            self._fault = None

    def service(self) -> None:
        """Enforce arming expiry now (call periodically: the guardian does, every tick)."""
        with self._lock:
            if self._armed_until is not None and self._clock() >= self._armed_until:
                self._armed_until = None
                self.expiries += 1
                log.warning("%s: arming expired, all channels off", self.name)
                if self._connected:
                    self.all_off()

    # -- channels ------------------------------------------------------------------------------

    def set_power(self, channel: str, power_pct: float) -> float:
        """Set a channel's power, clamped to [0, cap]; returns the power applied (read back)."""
        with self._lock:
            self._check_channel(channel)
            if not math.isfinite(power_pct):
                raise ValueError(f"power_pct = {power_pct}: must be finite")
            self.service()
            self._require_link()
            cap = self.settings.cap_pct(channel)
            applied = min(max(power_pct, 0.0), cap)
            if applied != power_pct:
                log.warning("%s: %s asked %.3g %%, applying %.3g %% (cap %.3g %%)",
                            self.name, channel, power_pct, applied, cap)
            with self._off_on_error():
                self._write_power(channel, applied)
                self._verify(channel, "power", applied, self._read_power(channel))
            return applied

    def enable(self, channel: str, on: bool = True) -> None:
        """Switch a channel's emission on (armed, no fault, power within cap) or off (always)."""
        with self._lock:
            self._check_channel(channel)
            self.service()
            if not on:
                self._require_link()
                with self._off_on_error():
                    self._write_enable(channel, False)
                    self._verify(channel, "enable", False, self._read_enable(channel))
                return
            self._require_link()
            if self._fault:
                raise LaserFault(f"{self.name}: fault latched: {self._fault}")
            if not self.armed:
                raise NotArmed(f"{self.name}: not armed; a person must arm before {channel} emits")
            with self._off_on_error():
                # The power on the device is what will be emitted: it must be within the cap even
                # if something other than this driver set it.
                power = self._read_power(channel)
                cap = self.settings.cap_pct(channel)
                if power > cap + self.settings.readback_tolerance_pct:
                    raise self._latch(ReadbackMismatch(
                        f"{self.name}: {channel} power reads {power:.4g} %, above the cap "
                        f"{cap:.4g} %; not enabling"))
                self._write_enable(channel, True)
                self._verify(channel, "enable", True, self._read_enable(channel))

    def all_off(self) -> None:
        """Every channel's enable off and power 0, each read back. Tries every channel even if one
        fails; raises LaserFault naming what could not be confirmed."""
        with self._lock, _signals_deferred():
            self._require_link()
            problems: list[str] = []
            for step in ("enable", "power"):
                for channel in self.channels:
                    try:
                        if step == "enable":
                            self._write_enable(channel, False)
                            if self._read_enable(channel):
                                problems.append(f"{channel} still enabled")
                        else:
                            self._write_power(channel, 0.0)
                            power = self._read_power(channel)
                            if abs(power) > self.settings.readback_tolerance_pct:
                                problems.append(f"{channel} power reads {power:.4g} %")
                    except TransportError as exc:
                        if not self._do_check_link():
                            self._connected = False
                            raise self._latch(LaserFault(
                                f"{self.name}: all-off NOT confirmed, link lost: {exc}")) from exc
                        problems.append(f"{channel} {step}: {exc}")
                    except DeviceError as exc:
                        problems.append(f"{channel} {step}: {exc}")
            if not problems:
                try:
                    if self._read_any_on():
                        problems.append("device still reports a laser on")
                except DeviceError as exc:
                    problems.append(f"any-laser-on check: {exc}")
            if problems:
                raise self._latch(
                    LaserFault(f"{self.name}: all-off NOT confirmed: {'; '.join(problems)}")
                )

    def status(self) -> LaserStatus:
        """Everything read back from the device (arming expiry enforced first); LinkDown when not
        connected."""
        with self._lock:
            self.service()
            self._require_link()
            code = self._read_device_status()
            channels = {
                ch: ChannelState(self._read_enable(ch), self._read_power(ch))
                for ch in self.channels
            }
            return LaserStatus(
                device_status=code,
                device_status_name=DEVICE_STATUS.get(code, "unknown") if code is not None
                else "unknown",
                channels=channels,
                armed=self.armed,
                armed_remaining_s=self.armed_remaining_s,
                fault=self._fault,
            )

    # -- shared helpers ------------------------------------------------------------------------

    def _check_channel(self, channel: str) -> None:
        if channel not in self.channels:
            raise ValueError(f"channel {channel!r}: must be one of {', '.join(self.channels)}")

    def _require_link(self) -> None:
        if not self._connected:
            raise LinkDown(f"{self.name}: not connected (open or reconnect first)")

    def _latch(self, exc: LaserFault) -> LaserFault:
        self._fault = str(exc)
        self._armed_until = None
        log.error("%s", exc)
        return exc

    def _verify(self, channel: str, what: str, wrote: float | bool, read: float | bool) -> None:
        tolerance = self.settings.readback_tolerance_pct if what == "power" else 0
        if abs(float(read) - float(wrote)) > tolerance:
            raise self._latch(ReadbackMismatch(
                f"{self.name}: {channel} {what} wrote {wrote!r}, read back {read!r}"))

    @contextlib.contextmanager
    def _off_on_error(self) -> Iterator[None]:
        """Any failure while changing emission: everything off (best effort), then re-raise."""
        try:
            yield
        except BaseException as exc:
            if isinstance(exc, TransportError) and not self._do_check_link():
                self._connected = False
                self._armed_until = None
                self._fault = self._fault or f"link lost while changing emission: {exc}"
                raise LinkDown(f"{self.name}: link lost, emission state unknown: {exc}") from exc
            with contextlib.suppress(Exception):
                self.all_off()
            raise

    def _off_at_exit(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    # -- backend hooks -------------------------------------------------------------------------

    @abstractmethod
    def _do_open(self) -> None:
        """Open the link (no writes to the device)."""

    @abstractmethod
    def _do_close(self) -> None: ...

    @abstractmethod
    def _do_identify(self) -> int:
        """The device type, read without writing anything."""

    def _prepare(self) -> None:
        """After a successful identification: take control of the device if it needs it."""

    @abstractmethod
    def _write_enable(self, channel: str, on: bool) -> None: ...

    @abstractmethod
    def _read_enable(self, channel: str) -> bool: ...

    @abstractmethod
    def _write_power(self, channel: str, power_pct: float) -> None: ...

    @abstractmethod
    def _read_power(self, channel: str) -> float: ...

    def _read_device_status(self) -> int | None:
        return None

    def _read_any_on(self) -> bool:
        return False


class MecomLaser(Laser):
    """FISBA READYBeam over MeCom (57600 8N1, FTDI), or a `MecomTwin` through its opener."""

    def __init__(
        self,
        settings: LaserSettings,
        opener: Opener | None = None,
        *,
        clock: Clock = time.monotonic,
    ) -> None:
        super().__init__(settings, clock=clock)
        self._opener = opener or serial_opener(
            settings.port, settings.usb_serial, baud=settings.baud
        )
        self._transport: Transport | None = None
        self._sequence = 0
        self._vanished = False

    @property
    def name(self) -> str:
        """"laser <port>", for messages."""
        return f"laser {self.port_name or 'laser'}"

    @property
    def port_name(self) -> str:
        """The port actually open (found by USB serial where no path is configured)."""
        return self._transport.name if self._transport else self.settings.port

    # -- link ----------------------------------------------------------------------------------

    def _do_open(self) -> None:
        self._do_close()
        self._vanished = False
        self._transport = self._opener()
        if self.settings.latency_timer_ms:
            self._transport.line_control(
                LineControl(latency_timer_ms=self.settings.latency_timer_ms)
            )

    def _do_close(self) -> None:
        if self._transport is not None:
            transport, self._transport = self._transport, None
            transport.close()

    def _do_check_link(self) -> bool:
        return not self._vanished and self._transport is not None

    def _next_sequence(self) -> int:
        self._sequence = (self._sequence + 1) & 0xFFFF
        return self._sequence

    def transact(self, make: Callable[[int], mecom.Request]) -> mecom.ValueReply | mecom.Ack:
        """Send the request `make(sequence)` and return its reply. Retries (with a new sequence
        number) after a timeout or a corrupt reply; a device error raises MecomDeviceError; a
        vanished port raises PortVanished at once."""
        transport = self._transport
        if transport is None:
            raise LinkDown(f"{self.name}: not connected")
        s = self.settings
        last = ""
        for _ in range(1 + s.retries):
            request = make(self._next_sequence())
            try:
                transport.discard_input()
                transport.write(request.frame)
                reply = self._await_reply(transport, request)
            except PortVanished:
                self._vanished = True
                raise
            except (ReplyTimeout, ProtocolError) as exc:
                last = str(exc)
                log.info("%s: %s for %s, retrying", self.name, exc, request.payload)
                continue
            if isinstance(reply, mecom.ErrorReply):
                raise mecom.MecomDeviceError(reply, request, self.name)
            return reply
        raise ReplyTimeout(f"{self.name}: no valid reply after {1 + s.retries} tries ({last})")

    def _await_reply(self, transport: Transport, request: mecom.Request) -> mecom.Reply:
        deadline = time.monotonic() + self.settings.reply_timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ReplyTimeout(f"no reply to {request.payload}")
            raw = transport.read_until(mecom.EOL, remaining)
            start = raw.rfind(mecom.DEVICE_START)
            if start < 0:
                continue  # line noise without a frame start
            try:
                return mecom.decode_reply(raw[start:], request)
            except mecom.StaleReply:
                continue  # a late answer to an earlier try

    def read_parameter(self, param_id: int, instance: int) -> mecom.ValueReply:
        """`?VR` read of parameter `param_id`, instance `instance`; ProtocolError when the reply
        carries no value."""
        a = self.settings.address
        reply = self.transact(lambda seq: mecom.query(a, seq, param_id, instance))
        if not isinstance(reply, mecom.ValueReply):
            raise ProtocolError(f"{self.name}: ?VR {param_id}/{instance} answered without a value")
        return reply

    def write_parameter(self, param_id: int, instance: int, bits: int) -> None:
        """`VS` write of 32 value bits to parameter `param_id`, instance `instance`; ProtocolError
        when the reply is not an acknowledgement."""
        a = self.settings.address
        reply = self.transact(lambda seq: mecom.set_value(a, seq, param_id, instance, bits))
        if not isinstance(reply, mecom.Ack):
            raise ProtocolError(f"{self.name}: VS {param_id}/{instance} answered with a value")

    # -- hooks ---------------------------------------------------------------------------------

    def _do_identify(self) -> int:
        ids = self.settings.parameter_ids
        return self.read_parameter(ids.device_type, self.settings.channel_instances[0]).as_int

    def _prepare(self) -> None:
        self.serial_number = self._read_serial_number()
        if not self.settings.take_control:
            return
        param = self.settings.parameter_ids.digital_control
        for instance in self.settings.channel_instances:
            self.write_parameter(param, instance, mecom.int_bits(1))
            got = self.read_parameter(param, instance).as_int
            if got != 1:
                raise ReadbackMismatch(
                    f"{self.name}: digital control on instance {instance} reads {got}, wrote 1"
                )

    def _read_serial_number(self) -> int | None:
        """Common parameter 102; None on a unit that answers "parameter not available"."""
        param = self.settings.parameter_ids.serial_number
        try:
            return self.read_parameter(param, self.settings.channel_instances[0]).as_int
        except mecom.MecomDeviceError as exc:
            log.warning("%s: no serial number (parameter %d): %s", self.name, param, exc)
            return None

    def _write_enable(self, channel: str, on: bool) -> None:
        ids = self.settings.parameter_ids
        self.write_parameter(ids.channel_enable, self.settings.instance(channel), int(on))

    def _read_enable(self, channel: str) -> bool:
        ids = self.settings.parameter_ids
        value = self.read_parameter(ids.channel_enable, self.settings.instance(channel)).as_int
        if value not in (0, 1):
            raise ProtocolError(f"{self.name}: {channel} enable reads {value}, not 0 or 1")
        return bool(value)

    def _write_power(self, channel: str, power_pct: float) -> None:
        ids = self.settings.parameter_ids
        self.write_parameter(
            ids.channel_power, self.settings.instance(channel), mecom.float_bits(power_pct)
        )

    def _read_power(self, channel: str) -> float:
        ids = self.settings.parameter_ids
        return self.read_parameter(ids.channel_power, self.settings.instance(channel)).as_float

    def _read_device_status(self) -> int | None:
        ids = self.settings.parameter_ids
        return self.read_parameter(ids.status, self.settings.channel_instances[0]).as_int

    def _read_any_on(self) -> bool:
        if not self.settings.check_any_laser_on:
            return False
        param = self.settings.parameter_ids.any_laser_on
        return self.read_parameter(param, self.settings.channel_instances[0]).as_int != 0
