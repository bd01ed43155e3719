"""A KDC101 / TDC001 twin: answers APT on a pty, with motion that takes time on a clock.

Motion runs at the commanded maximum velocity (converted back from APT units with the time unit
T, as the controller does) on the twin's clock, so a test that holds a `ManualClock` decides when
a move is halfway or done. Hardware limit switches sit just outside the travel: the reverse one
`home_offset_mm` below 0 (homing drives there and then calls the offset position 0, like a Z8),
the forward one at `travel_mm`. A move that reaches a switch stops there with its limit bit set
and MOT_MOVE_STOPPED. Homing when already homed is skipped (MOT_MOVE_HOMED at once), as on the
real units.

Status updates (HW_START_UPDATEMSGS) go out every `update_period_s` of twin time and stop after
`unacked_updates_max` updates without MOT_ACK_DCSTATUSUPDATE, as the firmware does.

Faults (`inject`) apply to the next matching message from the host:
  "no_reply"      ignored, not executed
  "garbage"       line noise first, then handled normally (the driver must resynchronise)
  "error"         not executed; HW_RICHRESPONSE with `code` and `notes` instead
  "vanish"        the port disappears on receipt
  "short_reply"   executed; only the first `keep_bytes` of the reply are sent
  "motion_error"  the motion it starts stops halfway with the motion-error bit
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from .. import apt
from .clock import Clock, real_clock
from .pty import TICK_S, PtyPeer

FAULT_KINDS = ("no_reply", "garbage", "error", "vanish", "short_reply", "motion_error")


@dataclass
class _Fault:
    kind: str
    msg_id: int | None
    count: int
    code: int
    notes: str
    keep_bytes: int


@dataclass
class _Motion:
    kind: str  # "move" or "home"
    t0: float
    start: float
    target: float
    speed: float  # counts/s
    fail_at: float | None = None  # motion error at this position


class AptTwin(PtyPeer):
    """A simulated KDC101 / TDC001 that answers APT on a pty, moving on its clock between limit
    switches (positions in encoder counts inside, mm at the test API)."""

    def __init__(
        self,
        *,
        serial_number: int = 27000001,
        model: str = "KDC101",
        firmware: tuple[int, int, int] = (3, 0, 10),
        channel: int = 1,
        counts_per_mm: float = 34554.96,
        time_unit_s: float = 2048 / 6e6,
        travel_mm: float = 25.0,
        home_offset_mm: float = 0.1,
        position_mm: float = 7.0,
        homed: bool = False,
        home_velocity_mm_s: float = 2.0,
        update_period_s: float = 0.1,
        unacked_updates_max: int = 50,
        clock: Clock = real_clock,
    ) -> None:
        super().__init__(clock=clock)
        self.info = apt.HwInfo(serial_number, model, 27, firmware, "APT twin", 1, 0, 1)
        self.channel = channel
        self.time_unit_s = time_unit_s
        self.counts_per_mm = counts_per_mm
        self.limits = (-home_offset_mm * counts_per_mm, travel_mm * counts_per_mm)
        self.position = position_mm * counts_per_mm  # counts (float: motion is continuous)
        self.homed = homed
        self.enabled = False
        self.motion_error = False
        self.home_speed = home_velocity_mm_s * counts_per_mm
        self.vel_params = (0, 0, round(counts_per_mm * time_unit_s * 65536 * 2.0))
        self.update_period_s = update_period_s
        self.unacked_updates_max = unacked_updates_max
        self.updates_on = False
        self.unacked = 0
        self._last_update = 0.0
        self._motion: _Motion | None = None
        self._faults: list[_Fault] = []
        self._stream = apt.AptStream(from_unit=False)
        # What the host sent, on the twin's clock, and a few counters tests read.
        self.received: list[tuple[float, apt.Message]] = []
        self.acks = 0
        self.updates_sent = 0

    # -- test API ------------------------------------------------------------------------------

    def inject(self, kind: str, *, msg_id: int | None = None, count: int = 1, code: int = 0x2B,
               notes: str = "simulated fault", keep_bytes: int = 10) -> None:
        """Apply fault `kind` (one of `FAULT_KINDS`) to the next `count` messages from the host
        (those with `msg_id` only, when given); ValueError for an unknown kind."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault {kind!r}: one of {FAULT_KINDS}")
        with self.lock:
            self._faults.append(_Fault(kind, msg_id, count, code, notes, keep_bytes))

    @property
    def position_mm(self) -> float:
        """The position now (mm, on the twin's clock, mid-move included)."""
        with self.lock:
            return self._position_now() / self.counts_per_mm

    @property
    def moving(self) -> bool:
        """Whether a move or homing is under way."""
        with self.lock:
            return self._motion is not None

    def wait_moving(self, timeout_s: float = 2.0) -> None:
        """Until a commanded motion has started on the twin (before advancing a manual clock)."""
        self.wait_for(lambda: self._motion is not None, timeout_s)

    def received_ids(self) -> list[int]:
        """The ids of every message received from the host, in order."""
        with self.lock:
            return [m.msg_id for _, m in self.received]

    # -- state ---------------------------------------------------------------------------------

    def _speed_counts_s(self) -> float:
        return self.vel_params[2] / (self.time_unit_s * 65536)

    def _position_now(self) -> float:
        m = self._motion
        if m is None:
            return self.position
        travelled = m.speed * max(0.0, self.clock() - m.t0)
        if travelled >= abs(m.target - m.start):
            pos = m.target
        else:
            pos = m.start + (travelled if m.target >= m.start else -travelled)
        return min(max(pos, self.limits[0]), self.limits[1])

    def _status(self) -> apt.DcStatus:
        pos = self._position_now()
        bits = apt.Status(0)
        if pos <= self.limits[0]:
            bits |= apt.Status.LIMIT_CCW
        if pos >= self.limits[1]:
            bits |= apt.Status.LIMIT_CW
        m = self._motion
        velocity = 0
        if m is not None:
            bits |= apt.Status.MOVING_CW if m.target >= m.start else apt.Status.MOVING_CCW
            if m.kind == "home":
                bits |= apt.Status.HOMING
            velocity = int(max(-32768, min(32767, (1 if m.target >= m.start else -1) * 1000)))
        if self.homed:
            bits |= apt.Status.HOMED
        if self.motion_error:
            bits |= apt.Status.MOTION_ERROR
        if self.enabled:
            bits |= apt.Status.ENABLED
        return apt.DcStatus(self.channel, round(pos), velocity, bits)

    def _reply(self, msg_id: int, data: bytes | None = None, param1: int = 0,
               param2: int = 0) -> bytes:
        return apt.Message(msg_id, param1, param2, data, dest=apt.HOST,
                           source=apt.USB_UNIT).encode()

    def _start(self, kind: str, target: float, speed: float, fault: _Fault | None) -> None:
        start = self._position_now()
        self.motion_error = False
        fail_at = (start + target) / 2 if fault and fault.kind == "motion_error" else None
        self._motion = _Motion(kind, self.clock(), start, target, speed, fail_at)

    # -- protocol ------------------------------------------------------------------------------

    def on_bytes(self, data: bytes) -> None:
        """Decode the host's bytes and handle each whole message (faults applied), recording it."""
        for message in self._stream.feed(data):
            self.received.append((self.clock(), message))
            self._handle(message)
            if self._master is None:
                return

    def _take_fault(self, message: apt.Message) -> _Fault | None:
        for fault in self._faults:
            if fault.msg_id is None or fault.msg_id == message.msg_id:
                fault.count -= 1
                if fault.count <= 0:
                    self._faults.remove(fault)
                return fault
        return None

    def _handle(self, message: apt.Message) -> None:
        fault = self._take_fault(message)
        kind = fault.kind if fault else None
        if kind == "vanish":
            self.vanish()
            return
        if kind == "no_reply":
            return
        if kind == "garbage":
            self.send(b"\xff\x00\x13" + os.urandom(7))
        if kind == "error":
            assert fault is not None
            rich = apt.RichResponse(message.msg_id, fault.code, fault.notes)
            self.send(self._reply(apt.MsgId.HW_RICHRESPONSE, rich.encode()))
            return
        reply = self._execute(message, fault)
        if reply:
            if kind == "short_reply":
                assert fault is not None
                reply = reply[: fault.keep_bytes]
            self.send(reply)

    def _execute(self, message: apt.Message, fault: _Fault | None) -> bytes:
        M = apt.MsgId
        mid = message.msg_id
        if mid == M.HW_REQ_INFO:
            return self._reply(M.HW_GET_INFO, self.info.encode())
        if mid == M.HW_START_UPDATEMSGS:
            self.updates_on, self.unacked = True, 0
            self._last_update = self.clock()
        elif mid == M.HW_STOP_UPDATEMSGS:
            self.updates_on = False
        elif mid == M.MOT_ACK_DCSTATUSUPDATE:
            self.acks += 1
            self.unacked = 0
        elif mid == M.MOD_SET_CHANENABLESTATE:
            self.enabled = message.param2 == apt.ENABLE_ON
        elif mid == M.MOT_SET_VELPARAMS:
            assert message.data is not None
            vp = apt.VelParams.decode(message.data)
            self.vel_params = (vp.min_velocity, vp.acceleration, vp.max_velocity)
        elif mid == M.MOT_REQ_VELPARAMS:
            return self._reply(M.MOT_GET_VELPARAMS,
                               apt.VELPARAMS.pack(self.channel, *self.vel_params))
        elif mid == M.MOT_REQ_STATUSBITS:
            return self._reply(M.MOT_GET_STATUSBITS,
                               apt.STATUSBITS.pack(self.channel, int(self._status().status)))
        elif mid == M.MOT_REQ_DCSTATUSUPDATE:
            return self._reply(M.MOT_GET_DCSTATUSUPDATE, self._status().encode())
        elif mid == M.MOT_MOVE_HOME:
            if self.homed and self._motion is None:
                return self._reply(M.MOT_MOVE_HOMED, param1=self.channel)
            self.homed = False
            self._start("home", self.limits[0], self.home_speed, fault)
        elif mid in (M.MOT_MOVE_ABSOLUTE, M.MOT_MOVE_RELATIVE):
            assert message.data is not None
            _, counts = apt.MOVE.unpack(message.data)
            target = counts if mid == M.MOT_MOVE_ABSOLUTE else self._position_now() + counts
            self._start("move", float(target), self._speed_counts_s(), fault)
        elif mid == M.MOT_MOVE_STOP:
            # Immediate and profiled alike stop at once here (no deceleration model).
            self.position = self._position_now()
            was_homing = self._motion is not None and self._motion.kind == "home"
            self._motion = None
            if was_homing:
                self.homed = False
            return self._reply(M.MOT_MOVE_STOPPED, self._status().encode())
        return b""

    def tick_period_s(self) -> float | None:
        """Every few ms while moving, or on a clock a test advances (the thread cannot see it
        move); otherwise until the next status update, or only bytes when none are due."""
        if self._motion is not None or self.clock is not real_clock:
            return TICK_S
        if self.updates_on and self.unacked < self.unacked_updates_max:
            return max(TICK_S, self._last_update + self.update_period_s - self.clock())
        return None

    def tick(self) -> None:
        """Advance the motion to the clock (arrival, limit switches, an injected motion error) and
        send status updates when due."""
        now = self.clock()
        m = self._motion
        if m is not None:
            pos = self._position_now()
            if m.fail_at is not None and (pos - m.fail_at) * (m.target - m.start) >= 0:
                self.position, self._motion = m.fail_at, None
                self.motion_error = True
                self.send(self._reply(apt.MsgId.MOT_MOVE_STOPPED, self._status().encode()))
            elif m.kind == "home" and pos <= self.limits[0]:
                # At the reverse switch: this position, plus the offset, becomes 0.
                self.position, self._motion, self.homed = 0.0, None, True
                self.send(self._reply(apt.MsgId.MOT_MOVE_HOMED, param1=self.channel))
            elif pos == m.target:
                self.position, self._motion = pos, None
                self.send(self._reply(apt.MsgId.MOT_MOVE_COMPLETED, self._status().encode()))
            elif (pos >= self.limits[1] and m.target > pos) or (
                    pos <= self.limits[0] and m.target < pos):
                # A switch stops only a motion heading into it: a move away from a pressed
                # switch (after homing onto it, or a move to the end of the travel) goes on.
                self.position, self._motion = pos, None
                self.send(self._reply(apt.MsgId.MOT_MOVE_STOPPED, self._status().encode()))
        if (self.updates_on and self.unacked < self.unacked_updates_max
                and now - self._last_update >= self.update_period_s):
            self._last_update = now
            self.unacked += 1
            self.updates_sent += 1
            self.send(self._reply(apt.MsgId.MOT_GET_DCSTATUSUPDATE, self._status().encode()))
