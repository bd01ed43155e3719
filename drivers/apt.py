"""Thorlabs APT messages for KDC101 / TDC001 motor controllers (docs/design.md, "The hardware":
Stage).

Header, 6 bytes little-endian:
  short message  `<H B B B B`  id, param1, param2, dest, source
  long message   `<H H B B`    id, data length, dest | 0x80, source; then the data
Host -> controller: dest 0x50 (generic USB unit), source 0x01 (host); replies swap them.
Example, move absolute to 2048 counts: `53 04 06 00 D0 01 01 00 00 08 00 00`.

Every id, length, layout and status bit lives here, once; `AptStream` decodes a byte stream in
either direction and resynchronises after garbage by dropping bytes until a header is plausible
(known id, right addresses, right length).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag

HOST = 0x01
USB_UNIT = 0x50
LONG_FLAG = 0x80
HEADER = struct.Struct("<HBBBB")
LONG_HEADER = struct.Struct("<HHBB")


class MsgId(IntEnum):
    """The APT message ids nhfd sends or reads."""

    HW_DISCONNECT = 0x0002
    HW_REQ_INFO = 0x0005
    HW_GET_INFO = 0x0006
    HW_START_UPDATEMSGS = 0x0011
    HW_STOP_UPDATEMSGS = 0x0012
    HW_RESPONSE = 0x0080
    HW_RICHRESPONSE = 0x0081
    MOD_SET_CHANENABLESTATE = 0x0210
    MOT_SET_VELPARAMS = 0x0413
    MOT_REQ_VELPARAMS = 0x0414
    MOT_GET_VELPARAMS = 0x0415
    MOT_REQ_STATUSBITS = 0x0429
    MOT_GET_STATUSBITS = 0x042A
    MOT_MOVE_HOME = 0x0443
    MOT_MOVE_HOMED = 0x0444
    MOT_MOVE_RELATIVE = 0x0448
    MOT_MOVE_ABSOLUTE = 0x0453
    MOT_MOVE_COMPLETED = 0x0464
    MOT_MOVE_STOP = 0x0465
    MOT_MOVE_STOPPED = 0x0466
    MOT_REQ_DCSTATUSUPDATE = 0x0490
    MOT_GET_DCSTATUSUPDATE = 0x0491
    MOT_ACK_DCSTATUSUPDATE = 0x0492


class Status(IntFlag):
    """The status bits of a DC servo controller's status block (limits, motion, homing, enabled)."""

    LIMIT_CW = 0x1
    LIMIT_CCW = 0x2
    MOVING_CW = 0x10
    MOVING_CCW = 0x20
    HOMING = 0x200
    HOMED = 0x400
    MOTION_ERROR = 0x4000
    ENABLED = 0x80000000


MOVING = Status.MOVING_CW | Status.MOVING_CCW
LIMITS = Status.LIMIT_CW | Status.LIMIT_CCW

# MOD_SET_CHANENABLESTATE param2, MOT_MOVE_STOP param2.
ENABLE_ON, ENABLE_OFF = 0x01, 0x02
STOP_IMMEDIATE, STOP_PROFILED = 0x01, 0x02

# Data layouts.
STATUS_BLOCK = struct.Struct("<HlhHL")  # channel, position, velocity (signed), reserved, bits
INFO = struct.Struct("<L8sH4B48s12sHHH")  # serial, model, type, fw x4, notes, -, hw, mod, nchs
MOVE = struct.Struct("<Hl")  # channel, counts (absolute position or relative distance)
VELPARAMS = struct.Struct("<Hlll")  # channel, min velocity, acceleration, max velocity
STATUSBITS = struct.Struct("<HL")  # channel, bits
RICH = struct.Struct("<HH64s")  # message that failed, error code, notes

# Messages each side sends, with their data length (None: a short, header-only message).
TO_UNIT: dict[int, int | None] = {
    MsgId.HW_DISCONNECT: None,
    MsgId.HW_REQ_INFO: None,
    MsgId.HW_START_UPDATEMSGS: None,
    MsgId.HW_STOP_UPDATEMSGS: None,
    MsgId.MOD_SET_CHANENABLESTATE: None,
    MsgId.MOT_SET_VELPARAMS: VELPARAMS.size,
    MsgId.MOT_REQ_VELPARAMS: None,
    MsgId.MOT_REQ_STATUSBITS: None,
    MsgId.MOT_MOVE_HOME: None,
    MsgId.MOT_MOVE_RELATIVE: MOVE.size,
    MsgId.MOT_MOVE_ABSOLUTE: MOVE.size,
    MsgId.MOT_MOVE_STOP: None,
    MsgId.MOT_REQ_DCSTATUSUPDATE: None,
    MsgId.MOT_ACK_DCSTATUSUPDATE: None,
}
FROM_UNIT: dict[int, int | None] = {
    MsgId.HW_GET_INFO: INFO.size,
    MsgId.HW_RESPONSE: None,
    MsgId.HW_RICHRESPONSE: RICH.size,
    MsgId.MOT_GET_VELPARAMS: VELPARAMS.size,
    MsgId.MOT_GET_STATUSBITS: STATUSBITS.size,
    MsgId.MOT_MOVE_HOMED: None,
    MsgId.MOT_MOVE_COMPLETED: STATUS_BLOCK.size,
    MsgId.MOT_MOVE_STOPPED: STATUS_BLOCK.size,
    MsgId.MOT_GET_DCSTATUSUPDATE: STATUS_BLOCK.size,
}


@dataclass(frozen=True)
class Message:
    """One APT message: id, the two header parameters (short form) or the data (long form),
    destination and source."""

    msg_id: int
    param1: int = 0
    param2: int = 0
    data: bytes | None = None  # None: short message
    dest: int = USB_UNIT
    source: int = HOST

    def encode(self) -> bytes:
        """The message's bytes: the 6-byte header, then the data of a long message."""
        if self.data is None:
            return HEADER.pack(self.msg_id, self.param1, self.param2, self.dest, self.source)
        return (
            LONG_HEADER.pack(self.msg_id, len(self.data), self.dest | LONG_FLAG, self.source)
            + self.data
        )

    @property
    def name(self) -> str:
        """The id's name in `MsgId`, else its hex value."""
        try:
            return MsgId(self.msg_id).name
        except ValueError:
            return f"0x{self.msg_id:04X}"


def short(msg_id: int, param1: int = 0, param2: int = 0, *, dest: int = USB_UNIT,
          source: int = HOST) -> bytes:
    """A header-only message's bytes (host to controller unless `dest` and `source` say)."""
    return Message(msg_id, param1, param2, None, dest, source).encode()


def long(msg_id: int, data: bytes, *, dest: int = USB_UNIT, source: int = HOST) -> bytes:
    """A long message's bytes: the header with the data's length, then `data`."""
    return Message(msg_id, data=data, dest=dest, source=source).encode()


# ---------------------------------------------------------------------- host -> controller


def req_info() -> bytes:
    """HW_REQ_INFO: ask for the controller's `HwInfo`."""
    return short(MsgId.HW_REQ_INFO)


def start_update_msgs() -> bytes:
    """HW_START_UPDATEMSGS: ask for periodic status updates (`DcStatus`)."""
    return short(MsgId.HW_START_UPDATEMSGS)


def stop_update_msgs() -> bytes:
    """HW_STOP_UPDATEMSGS: stop the status updates."""
    return short(MsgId.HW_STOP_UPDATEMSGS)


def disconnect() -> bytes:
    """HW_DISCONNECT: tell the controller the host is leaving."""
    return short(MsgId.HW_DISCONNECT)


def set_channel_enable(channel: int, on: bool) -> bytes:
    """MOD_SET_CHANENABLESTATE: enable or disable `channel`'s motor drive."""
    return short(MsgId.MOD_SET_CHANENABLESTATE, channel, ENABLE_ON if on else ENABLE_OFF)


def move_home(channel: int) -> bytes:
    """MOT_MOVE_HOME: home `channel` (answered by MOT_MOVE_HOMED)."""
    return short(MsgId.MOT_MOVE_HOME, channel)


def move_absolute(channel: int, position_counts: int) -> bytes:
    """MOT_MOVE_ABSOLUTE: move `channel` to `position_counts` (encoder counts)."""
    return long(MsgId.MOT_MOVE_ABSOLUTE, MOVE.pack(channel, position_counts))


def move_relative(channel: int, distance_counts: int) -> bytes:
    """MOT_MOVE_RELATIVE: move `channel` by `distance_counts` (encoder counts, signed)."""
    return long(MsgId.MOT_MOVE_RELATIVE, MOVE.pack(channel, distance_counts))


def move_stop(channel: int, immediate: bool = True) -> bytes:
    """MOT_MOVE_STOP: stop `channel`, at once or with the deceleration profile."""
    return short(MsgId.MOT_MOVE_STOP, channel, STOP_IMMEDIATE if immediate else STOP_PROFILED)


def req_status_bits(channel: int) -> bytes:
    """MOT_REQ_STATUSBITS: ask for `channel`'s status bits."""
    return short(MsgId.MOT_REQ_STATUSBITS, channel)


def req_dc_status(channel: int) -> bytes:
    """MOT_REQ_DCSTATUSUPDATE: ask for `channel`'s status block (`DcStatus`)."""
    return short(MsgId.MOT_REQ_DCSTATUSUPDATE, channel)


def ack_dc_status() -> bytes:
    """MOT_ACK_DCSTATUSUPDATE: the keep-alive without which the controller stops its status
    updates."""
    return short(MsgId.MOT_ACK_DCSTATUSUPDATE)


def set_vel_params(channel: int, min_velocity: int, acceleration: int, max_velocity: int) -> bytes:
    """MOT_SET_VELPARAMS: `channel`'s velocity profile in APT units (as
    `StageSettings.velocity_units` and `acceleration_units` scale mm/s and mm/s^2)."""
    return long(MsgId.MOT_SET_VELPARAMS,
                VELPARAMS.pack(channel, min_velocity, acceleration, max_velocity))


def req_vel_params(channel: int) -> bytes:
    """MOT_REQ_VELPARAMS: ask for `channel`'s velocity profile (`VelParams`)."""
    return short(MsgId.MOT_REQ_VELPARAMS, channel)


# -------------------------------------------------------------------- controller payloads


@dataclass(frozen=True)
class DcStatus:
    """A DC servo status block: channel, position (encoder counts), velocity (raw APT units) and
    status bits."""

    channel: int
    position_counts: int
    velocity_raw: int
    status: Status

    @classmethod
    def decode(cls, data: bytes) -> DcStatus:
        """The status block in `data` (14 bytes)."""
        channel, position, velocity, _reserved, bits = STATUS_BLOCK.unpack(data)
        return cls(channel, position, velocity, Status(bits))

    def encode(self) -> bytes:
        """The 14-byte status block (what a controller sends; the twin uses it)."""
        return STATUS_BLOCK.pack(self.channel, self.position_counts, self.velocity_raw, 0,
                                 int(self.status))

    @property
    def moving(self) -> bool:
        """Whether the motor moves, either way."""
        return bool(self.status & MOVING)

    @property
    def homing(self) -> bool:
        """Whether a homing move runs."""
        return Status.HOMING in self.status

    @property
    def homed(self) -> bool:
        """Whether the stage has been homed since power-up."""
        return Status.HOMED in self.status

    @property
    def at_limit(self) -> bool:
        """Whether either limit switch is pressed."""
        return bool(self.status & LIMITS)

    @property
    def motion_error(self) -> bool:
        """Whether the controller reports a motion error."""
        return Status.MOTION_ERROR in self.status

    @property
    def enabled(self) -> bool:
        """Whether the channel's drive is enabled."""
        return Status.ENABLED in self.status


@dataclass(frozen=True)
class HwInfo:
    """HW_GET_INFO's payload: serial number, model ("KDC101"), hardware type, firmware (major,
    interim, minor), notes, versions and channel count."""

    serial_number: int
    model: str
    hw_type: int
    firmware: tuple[int, int, int]  # major, interim, minor
    notes: str
    hw_version: int
    mod_state: int
    n_channels: int

    @classmethod
    def decode(cls, data: bytes) -> HwInfo:
        """The controller information in `data` (84 bytes)."""
        (serial, model, hw_type, minor, interim, major, _unused, notes, _empty, hw_version,
         mod_state, nchs) = INFO.unpack(data)
        return cls(serial, _text(model), hw_type, (major, interim, minor), _text(notes),
                   hw_version, mod_state, nchs)

    def encode(self) -> bytes:
        """The 84-byte payload (what a controller sends; the twin uses it)."""
        major, interim, minor = self.firmware
        return INFO.pack(self.serial_number, self.model.encode()[:8], self.hw_type, minor,
                         interim, major, 0, self.notes.encode()[:48], b"", self.hw_version,
                         self.mod_state, self.n_channels)


@dataclass(frozen=True)
class VelParams:
    """MOT_GET_VELPARAMS's payload: channel, minimum velocity, acceleration and maximum velocity in
    APT units."""

    channel: int
    min_velocity: int
    acceleration: int
    max_velocity: int

    @classmethod
    def decode(cls, data: bytes) -> VelParams:
        """The velocity profile in `data` (14 bytes)."""
        return cls(*VELPARAMS.unpack(data))


@dataclass(frozen=True)
class RichResponse:
    """HW_RICHRESPONSE's payload: the message that failed, the error code and the controller's
    note."""

    msg_ident: int
    code: int
    notes: str

    @classmethod
    def decode(cls, data: bytes) -> RichResponse:
        """The error report in `data` (68 bytes)."""
        ident, code, notes = RICH.unpack(data)
        return cls(ident, code, _text(notes))

    def encode(self) -> bytes:
        """The 68-byte payload (what a controller sends; the twin uses it)."""
        return RICH.pack(self.msg_ident, self.code, self.notes.encode()[:64])


def _text(raw: bytes) -> str:
    return raw.split(b"\x00", 1)[0].decode("ascii", errors="replace").strip()


# ------------------------------------------------------------------------------- stream


class AptStream:
    """Bytes in, whole messages out, for one direction of the link.

    from_unit=True decodes what a controller sends (dest 0x01 / 0x81, source 0x50); False what a
    host sends. Bytes that cannot start a plausible header are dropped one at a time (counted in
    `discarded`), so the stream recovers from line noise and from truncated replies.
    """

    def __init__(self, *, from_unit: bool) -> None:
        self.lengths = FROM_UNIT if from_unit else TO_UNIT
        self.dest, self.source = (HOST, USB_UNIT) if from_unit else (USB_UNIT, HOST)
        self._buf = bytearray()
        self.discarded = 0

    def feed(self, data: bytes) -> list[Message]:
        """Append `data` and return every whole message it completes, dropping bytes that cannot
        start a plausible header."""
        self._buf += data
        out: list[Message] = []
        while len(self._buf) >= HEADER.size:
            msg_id, p1, p2, dest, source = HEADER.unpack_from(self._buf)
            expected = self.lengths.get(msg_id, -1)
            if expected == -1 or source != self.source:
                self._drop()
                continue
            if expected is None:
                if dest != self.dest:
                    self._drop()
                    continue
                out.append(Message(msg_id, p1, p2, None, dest, source))
                del self._buf[: HEADER.size]
                continue
            length = p1 | (p2 << 8)
            if dest != self.dest | LONG_FLAG or length != expected:
                self._drop()
                continue
            if len(self._buf) < HEADER.size + length:
                break  # wait for the rest
            data_bytes = bytes(self._buf[HEADER.size : HEADER.size + length])
            out.append(Message(msg_id, data=data_bytes, dest=self.dest, source=source))
            del self._buf[: HEADER.size + length]
        return out

    def _drop(self) -> None:
        del self._buf[0]
        self.discarded += 1

    def clear(self) -> None:
        """Drop the buffered bytes (a partial message included)."""
        self._buf.clear()
