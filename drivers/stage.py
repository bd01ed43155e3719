"""Motorised stage: a base class with the motion rules, and the Thorlabs APT backend.

The base class holds what any stage must do on this bench:

- identify before any move, and never move at start-up (open only identifies, configures and
  reads the state; homing and moves happen on request);
- refuse targets outside the soft limits before sending anything, and refuse moves before homing
  (unless the settings allow it);
- `wait(timeout_s)` always has a deadline; on timeout the stage is stopped and MotionTimeout
  raised; a move that ends at a limit switch, with a motion error, or because somebody called
  `stop()` raises, so a caller never mistakes an unreached target for a reached one;
- `stop()` works at any time from any thread, also while another thread waits on a move.

`AptStage` (KDC101 / TDC001) speaks APT through a transport. A reader thread decodes every
message (resynchronising after garbage), keeps the latest status block, and acknowledges status
updates about once a second so the controller keeps sending them. With an `AptTwin`'s opener it is
the simulated stage.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Literal

from nhfd.device_settings import StageSettings

from . import apt
from .device import Device
from .errors import DeviceError, LinkDown, PortVanished, ReplyTimeout, TransportError, WrongDevice
from .transport import LineControl, LineControlError, Opener, Transport, serial_opener

log = logging.getLogger(__name__)

# FTDI ids of Thorlabs motion controllers (docs/design.md, "The hardware"): used when searching
# by serial number.
THORLABS_VID, THORLABS_PID = 0x0403, 0xFAF0

Outcome = Literal["completed", "stopped", "homed"]


class StageError(DeviceError):
    """The stage did not do what was asked."""


class SoftLimitError(ValueError):
    """A target outside the configured soft limits (nothing was sent)."""


class NotHomed(StageError):
    """Moves need a homed stage (its position means nothing before)."""


class LimitSwitchHit(StageError):
    """A move ended on a hardware limit switch."""


class MoveStopped(StageError):
    """A move or homing ended because it was stopped, before reaching its target."""


class MotionTimeout(StageError):
    """A move did not finish within its timeout; the stage was told to stop."""


class MotionError(StageError):
    """The controller reports a motion error."""


class AptDeviceError(StageError):
    """The controller sent HW_RESPONSE / HW_RICHRESPONSE."""

    def __init__(self, device: str, code: int, notes: str, msg_ident: int | None) -> None:
        self.code, self.notes, self.msg_ident = code, notes, msg_ident
        about = f" about {apt.Message(msg_ident).name}" if msg_ident is not None else ""
        super().__init__(f"{device}: controller error {code}{about}: {notes or 'no notes'}")


@dataclass(frozen=True)
class StageInfo:
    """Who the controller is: serial number, model ("KDC101") and firmware version."""

    serial_number: str
    model: str
    firmware: str


@dataclass(frozen=True)
class StageState:
    """The axis as read: position (mm), motion, homing and homed flags, the two limit switches,
    motion error, drive enabled and the raw status bits."""

    position_mm: float
    moving: bool
    homing: bool
    homed: bool
    limit_cw: bool
    limit_ccw: bool
    motion_error: bool
    enabled: bool
    status_bits: int

    @property
    def at_limit(self) -> bool:
        """Whether either limit switch is pressed."""
        return self.limit_cw or self.limit_ccw


class Stage(Device, ABC):
    """One motorised axis in mm."""

    def __init__(self, settings: StageSettings) -> None:
        self.settings = settings
        self.info: StageInfo | None = None
        self._pending: str | None = None  # "home" / "move" while a motion is outstanding
        self._pending_timeout_s = 0.0
        self._pending_target_mm: float | None = None  # a move's target
        self._state_lock = threading.Lock()
        self._info_before_reconnect: StageInfo | None = None

    # -- lifecycle -----------------------------------------------------------------------------

    def open(self) -> Stage:
        """Connect and identify; configure; read the state. Never moves."""
        self._do_open()
        try:
            self.info = self._do_identify()
            self._configure()
        except BaseException:
            self._close_quietly()
            raise
        log.info("%s: %s serial %s, firmware %s; not moved", self.name, self.info.model,
                 self.info.serial_number, self.info.firmware)
        return self

    def close(self) -> None:
        """Stop any motion, then disconnect."""
        try:
            if self._do_check_link() and self._pending is not None:
                with contextlib.suppress(DeviceError):
                    self.stop()
        finally:
            self._pending = None
            self._close_quietly()

    # ReplyTimeout is a TransportError; a unit that identifies as another raises WrongDevice.
    _retry_on = (TransportError, LinkDown)

    def _before_reconnect(self) -> None:
        # `Device.reconnect` with back-off; the device must identify as the same unit.
        self._info_before_reconnect = self.info
        self._pending = None

    def _reopen(self) -> None:
        before = self._info_before_reconnect
        self._do_open()
        info = self._do_identify()
        if before is not None and info.serial_number != before.serial_number:
            self._close_quietly()
            raise WrongDevice(f"{self.name}: reconnected to serial {info.serial_number}, "
                              f"was {before.serial_number}")
        self.info = info
        self._configure()

    # -- motion --------------------------------------------------------------------------------

    def home(self, *, wait: bool = True, timeout_s: float | None = None) -> StageState | None:
        """Home the axis; with `wait`, until it is homed (bounded by `timeout_s`, default
        `home_timeout_s`) and return the state. StageError while another motion is outstanding."""
        self._begin("home", timeout_s or self.settings.home_timeout_s)
        try:
            self._begin_home()
        except BaseException:
            self._pending = None
            raise
        return self.wait() if wait else None

    def move_to(self, position_mm: float, *, wait: bool = True,
                timeout_s: float | None = None) -> StageState | None:
        """Move to `position_mm` (mm); with `wait`, until it arrives (bounded by `timeout_s`,
        default `move_timeout_s`) and return the state. SoftLimitError outside the soft limits,
        NotHomed before homing."""
        self._check_target(position_mm)
        self._require_homed()
        self._begin("move", timeout_s or self.settings.move_timeout_s, position_mm)
        try:
            self._begin_move_absolute(position_mm)
        except BaseException:
            self._pending = None
            raise
        return self.wait() if wait else None

    def move_by(self, distance_mm: float, *, wait: bool = True,
                timeout_s: float | None = None) -> StageState | None:
        """Move by `distance_mm` (mm, signed) from the position read now; otherwise as `move_to`."""
        if not math.isfinite(distance_mm):
            raise ValueError(f"distance_mm = {distance_mm}: must be finite")
        self._require_homed()
        target_mm = self.state().position_mm + distance_mm
        self._check_target(target_mm)
        self._begin("move", timeout_s or self.settings.move_timeout_s, target_mm)
        try:
            self._begin_move_relative(distance_mm)
        except BaseException:
            self._pending = None
            raise
        return self.wait() if wait else None

    def stop(self, immediate: bool = True) -> None:
        """Stop now (or with a deceleration profile). Safe from any thread at any time."""
        self._send_stop(immediate)

    def wait(self, timeout_s: float | None = None) -> StageState:
        """Until the outstanding home or move ends; raises unless it reached its target."""
        kind = self._pending
        if kind is None:
            return self.state()
        timeout = timeout_s or self._pending_timeout_s
        try:
            outcome, state = self._wait_motion(timeout)
        except ReplyTimeout:
            with contextlib.suppress(DeviceError):
                self.stop(immediate=False)
            self._pending = None
            raise MotionTimeout(f"{self.name}: {kind} not done within {timeout:g} s; "
                                "stop sent") from None
        except BaseException:
            self._pending = None
            raise
        self._pending = None
        if state.motion_error:
            raise MotionError(f"{self.name}: motion error during {kind} at "
                              f"{state.position_mm:.4f} mm")
        if kind == "move" and state.at_limit:
            if not self._arrived(state):
                raise LimitSwitchHit(f"{self.name}: move ended on a limit switch at "
                                     f"{state.position_mm:.4f} mm")
            # The target was the end of the travel: the switch says where the stage is, not
            # that the move was cut short.
            log.info("%s: at the target %.4f mm with a limit switch pressed", self.name,
                     state.position_mm)
            return state
        if outcome == "stopped":
            raise MoveStopped(f"{self.name}: {kind} stopped at {state.position_mm:.4f} mm")
        if kind == "home" and not state.homed:
            raise StageError(f"{self.name}: homing ended but the controller is not homed")
        return state

    def position_mm(self) -> float:
        """The position read from the controller now (mm)."""
        return self.state().position_mm

    def state(self) -> StageState:
        """The axis's state read from the controller now."""
        return self._read_state()

    @property
    def moving(self) -> bool:
        """Whether a home or move is outstanding (requested and not yet waited for)."""
        return self._pending is not None

    # -- shared helpers ------------------------------------------------------------------------

    def _begin(self, kind: str, timeout_s: float, target_mm: float | None = None) -> None:
        if self.info is None:
            raise LinkDown(f"{self.name}: not open (a stage moves only after identification)")
        with self._state_lock:
            if self._pending is not None:
                raise StageError(f"{self.name}: a {self._pending} is in progress; wait or stop")
            self._pending = kind
            self._pending_timeout_s = timeout_s
            self._pending_target_mm = target_mm

    def _arrived(self, state: StageState) -> bool:
        target = self._pending_target_mm
        return target is not None and (
            abs(state.position_mm - target) <= self.settings.arrival_tolerance_mm)

    def _check_target(self, position_mm: float) -> None:
        low, high = self.settings.soft_limits_mm
        if not (math.isfinite(position_mm) and low <= position_mm <= high):
            raise SoftLimitError(
                f"{self.name}: target {position_mm} mm is outside the soft limits "
                f"[{low:g}, {high:g}] mm; not moving"
            )

    def _require_homed(self) -> None:
        if self.settings.require_homed and not self.state().homed:
            raise NotHomed(f"{self.name}: not homed; call home() first")

    # -- backend hooks -------------------------------------------------------------------------

    @abstractmethod
    def _do_open(self) -> None: ...

    @abstractmethod
    def _do_close(self) -> None: ...

    @abstractmethod
    def _do_identify(self) -> StageInfo:
        """Who is there; raise WrongDevice for anything the settings do not allow."""

    def _configure(self) -> None:
        """After identification: enable the axis, set velocities, start status updates."""

    @abstractmethod
    def _begin_home(self) -> None: ...

    @abstractmethod
    def _begin_move_absolute(self, position_mm: float) -> None: ...

    @abstractmethod
    def _begin_move_relative(self, distance_mm: float) -> None: ...

    @abstractmethod
    def _send_stop(self, immediate: bool) -> None: ...

    @abstractmethod
    def _read_state(self) -> StageState: ...

    @abstractmethod
    def _wait_motion(self, timeout_s: float) -> tuple[Outcome, StageState]:
        """Block until the outstanding motion ends; ReplyTimeout after timeout_s."""


class AptStage(Stage):
    """Thorlabs KDC101 / TDC001 over APT (115200 8N1, RTS/CTS, FTDI 0403:faf0)."""

    def __init__(self, settings: StageSettings, opener: Opener | None = None) -> None:
        super().__init__(settings)
        self._opener = opener or serial_opener(
            settings.port, settings.usb_serial, baud=settings.baud, rtscts=settings.rtscts,
            vid=THORLABS_VID, pid=THORLABS_PID,
        )
        self._transport: Transport | None = None
        self._write_lock = threading.Lock()
        self._cond = threading.Condition()
        self._reader: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self._resync = threading.Event()
        self.stream = apt.AptStream(from_unit=True)
        self._reset_link_state()

    def _reset_link_state(self) -> None:
        self._link_error: Exception | None = None
        self._configured = False
        self._updates = False
        self._last_ack = 0.0
        self._enabled_at = 0.0
        # Everything the reader learns, with a counter so a waiter only takes what came after
        # its own request.
        self._count = 0
        self._events: list[tuple[int, apt.Message]] = []
        self._status: apt.DcStatus | None = None
        self._status_count = 0
        self._motion_from = 0

    @property
    def name(self) -> str:
        """"stage <port>", for messages."""
        return f"stage {self._transport.name if self._transport else self.settings.port}"

    # -- link ----------------------------------------------------------------------------------

    def _do_open(self) -> None:
        self._do_close()
        self._reset_link_state()
        self.stream = apt.AptStream(from_unit=True)
        transport = self._opener()
        try:
            transport.line_control(LineControl(
                rts_pulse=self.settings.rts_reset,
                latency_timer_ms=self.settings.latency_timer_ms or None))
        except LineControlError as exc:
            transport.close()
            raise LineControlError(f"stage {exc}; for an adapter without modem-control lines "
                                   "set rts_reset = false in [devices.apt]") from None
        except BaseException:
            transport.close()
            raise
        self._transport = transport
        self._stop_reader.clear()
        self._reader = threading.Thread(target=self._read_loop, name="apt-reader", daemon=True)
        self._reader.start()

    def _do_close(self) -> None:
        transport = self._transport
        if transport is None:
            return
        if self._link_error is None and self._configured:
            # Only a unit we identified and configured hears from us beyond HW_REQ_INFO.
            with contextlib.suppress(TransportError, LinkDown):
                if self._updates:
                    self._write(apt.stop_update_msgs())
                self._write(apt.disconnect())
                transport.flush()
        self._stop_reader.set()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0)
        self._transport = None
        transport.close()

    def _do_check_link(self) -> bool:
        return self._transport is not None and self._link_error is None

    def _write(self, frame: bytes) -> None:
        transport = self._transport
        if transport is None or self._link_error is not None:
            raise LinkDown(f"{self.name}: not connected ({self._link_error or 'closed'})")
        with self._write_lock:
            try:
                transport.write(frame)
            except PortVanished as exc:
                self._fail_link(exc)
                raise

    def _fail_link(self, exc: Exception) -> None:
        with self._cond:
            self._link_error = exc
            self._cond.notify_all()

    def _read_loop(self) -> None:
        transport = self._transport
        assert transport is not None
        while not self._stop_reader.is_set():
            try:
                # Messages end the wait at once; the timeout only bounds noticing a stop
                # (50 wake-ups a second at 0.02 s were a third of an idle daemon's CPU).
                data = transport.read_available(0.1)
            except (PortVanished, TransportError) as exc:
                if not self._stop_reader.is_set():
                    log.error("%s: %s", self.name, exc)
                    self._fail_link(exc)
                return
            if self._resync.is_set():
                # A reply timed out: whatever partial message is buffered would swallow the
                # start of the next reply (a unit that answered short), so start afresh.
                self._resync.clear()
                self.stream.clear()
            for message in self.stream.feed(data):
                self._on_message(message)
            now = time.monotonic()
            if self._updates and now - self._last_ack >= self.settings.keepalive_period_s:
                self._last_ack = now
                with contextlib.suppress(DeviceError):
                    self._write(apt.ack_dc_status())

    def _on_message(self, message: apt.Message) -> None:
        with self._cond:
            self._count += 1
            self._events.append((self._count, message))
            del self._events[:-1024]  # a waiter needs only what came after its request
            if message.msg_id in (apt.MsgId.MOT_GET_DCSTATUSUPDATE, apt.MsgId.MOT_MOVE_COMPLETED,
                                  apt.MsgId.MOT_MOVE_STOPPED):
                assert message.data is not None
                self._status = apt.DcStatus.decode(message.data)
                self._status_count = self._count
            self._cond.notify_all()

    def _await(self, ids: set[int], since: int, timeout_s: float, what: str) -> apt.Message:
        """The first message with an id in `ids` that arrived after event `since`."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                if self._link_error is not None:
                    raise LinkDown(f"{self.name}: port vanished while waiting for {what}: "
                                   f"{self._link_error}")
                for n, message in self._events:
                    if n <= since:
                        continue
                    if message.msg_id in (apt.MsgId.HW_RESPONSE, apt.MsgId.HW_RICHRESPONSE):
                        raise self._device_error(message)
                    if message.msg_id in ids:
                        return message
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise ReplyTimeout(f"{self.name}: no {what} within {timeout_s:g} s")
                self._cond.wait(min(remaining, 0.1))

    def _device_error(self, message: apt.Message) -> AptDeviceError:
        if message.data is not None:
            rich = apt.RichResponse.decode(message.data)
            return AptDeviceError(self.name, rich.code, rich.notes, rich.msg_ident)
        return AptDeviceError(self.name, message.param1 | (message.param2 << 8), "", None)

    def _request(self, frame: bytes, ids: set[int], what: str) -> apt.Message:
        """Send and wait for the reply, resending once after a timeout."""
        last: ReplyTimeout | None = None
        for _ in range(2):
            with self._cond:
                since = self._count
            self._write(frame)
            try:
                return self._await(ids, since, self.settings.reply_timeout_s, what)
            except ReplyTimeout as exc:
                last = exc
                self._resync.set()
        assert last is not None
        raise last

    # -- hooks ---------------------------------------------------------------------------------

    def _do_identify(self) -> StageInfo:
        reply = self._request(apt.req_info(), {apt.MsgId.HW_GET_INFO}, "HW_GET_INFO")
        assert reply.data is not None
        hw = apt.HwInfo.decode(reply.data)
        s = self.settings
        info = StageInfo(str(hw.serial_number), hw.model, ".".join(map(str, hw.firmware)))
        if not any(hw.model.startswith(m) for m in s.allowed_models):
            raise WrongDevice(f"{self.name}: model {hw.model!r} (serial {hw.serial_number}) is "
                              f"not one of {s.allowed_models}; not driving it")
        if s.usb_serial and info.serial_number != s.usb_serial:
            raise WrongDevice(f"{self.name}: serial {info.serial_number}, settings say "
                              f"{s.usb_serial}")
        return info

    def _configure(self) -> None:
        s = self.settings
        self._write(apt.set_channel_enable(s.channel, True))
        self._enabled_at = time.monotonic()
        want = (0, s.acceleration_units, s.velocity_units)
        self._write(apt.set_vel_params(s.channel, *want))
        reply = self._request(apt.req_vel_params(s.channel), {apt.MsgId.MOT_GET_VELPARAMS},
                              "MOT_GET_VELPARAMS")
        assert reply.data is not None
        got = apt.VelParams.decode(reply.data)
        if (got.min_velocity, got.acceleration, got.max_velocity) != want:
            raise StageError(f"{self.name}: velocity parameters read back {got}, wrote {want}")
        self._configured = True
        self._write(apt.start_update_msgs())
        self._updates = True
        self._last_ack = time.monotonic()
        self._read_state()

    def _to_state(self, status: apt.DcStatus) -> StageState:
        st = status.status
        return StageState(
            position_mm=status.position_counts / self.settings.counts_per_mm,
            moving=status.moving,
            homing=status.homing,
            homed=status.homed,
            limit_cw=apt.Status.LIMIT_CW in st,
            limit_ccw=apt.Status.LIMIT_CCW in st,
            motion_error=status.motion_error,
            enabled=status.enabled,
            status_bits=int(st),
        )

    def _read_state(self) -> StageState:
        reply = self._request(apt.req_dc_status(self.settings.channel),
                              {apt.MsgId.MOT_GET_DCSTATUSUPDATE, apt.MsgId.MOT_MOVE_COMPLETED,
                               apt.MsgId.MOT_MOVE_STOPPED}, "a status block")
        assert reply.data is not None
        return self._to_state(apt.DcStatus.decode(reply.data))

    def _mark_motion(self) -> None:
        with self._cond:
            self._motion_from = self._count

    def _begin_home(self) -> None:
        # TDC001 quirk: homing right after enabling the channel can lock it up.
        settle = self._enabled_at + self.settings.enable_settle_s - time.monotonic()
        if settle > 0:
            time.sleep(settle)
        self._mark_motion()
        self._write(apt.move_home(self.settings.channel))

    def _counts(self, mm: float) -> int:
        return round(mm * self.settings.counts_per_mm)

    def _begin_move_absolute(self, position_mm: float) -> None:
        self._mark_motion()
        self._write(apt.move_absolute(self.settings.channel, self._counts(position_mm)))

    def _begin_move_relative(self, distance_mm: float) -> None:
        self._mark_motion()
        self._write(apt.move_relative(self.settings.channel, self._counts(distance_mm)))

    def _send_stop(self, immediate: bool) -> None:
        self._write(apt.move_stop(self.settings.channel, immediate))

    def _wait_motion(self, timeout_s: float) -> tuple[Outcome, StageState]:
        ends = {apt.MsgId.MOT_MOVE_COMPLETED, apt.MsgId.MOT_MOVE_STOPPED,
                apt.MsgId.MOT_MOVE_HOMED}
        message = self._await(ends, self._motion_from, timeout_s, "the end of the motion")
        if message.msg_id == apt.MsgId.MOT_MOVE_HOMED:
            return "homed", self._read_state()
        assert message.data is not None
        state = self._to_state(apt.DcStatus.decode(message.data))
        outcome: Outcome = ("completed" if message.msg_id == apt.MsgId.MOT_MOVE_COMPLETED
                            else "stopped")
        return outcome, state
