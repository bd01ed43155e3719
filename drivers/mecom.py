"""Meerstetter MeCom ASCII frames, as the FISBA READYBeam speaks them (docs/design.md, "The
hardware": Lasers).

Host frame:   `#` AA SSSS payload CCCC `\\r`   (AA address, SSSS sequence, CCCC CRC, all hex)
Device frames, echoing address and sequence:
  value:      `!` AA SSSS VVVVVVVV CCCC `\\r`  (CCCC: the device's CRC of its own frame)
  ack:        `!` AA SSSS CCCC `\\r`           (CCCC: the *request's* CRC echoed back)
  error:      `!` AA SSSS `+` EE CCCC `\\r`     (EE: error code in hex)
The CRC is CRC-16/XMODEM (poly 0x1021, init 0, no reflection) over everything before it, written
as 4 upper-case hex digits. A host frame with a bad CRC gets no answer.

Both directions live here (the twin composes device frames with the same code), so every
framing constant is in one place.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from .errors import DeviceError, ProtocolError

CRC_POLY = 0x1021
HOST_START = b"#"
DEVICE_START = b"!"
EOL = b"\r"
QUERY = "?VR"
SET = "VS"

# Error codes as the device sends them: two hex digits, parsed as hex. Public code lists the two
# timeouts as decimal 20/21 while parsing hex, so a unit may send "20"/"21" (0x20/0x21) or
# "14"/"15" (decimal 20/21 written in hex): both spellings map to the timeout meanings.
ERROR_MEANINGS: dict[int, str] = {
    0x01: "command not available",
    0x02: "device busy",
    0x03: "general communication error",
    0x04: "format error",
    0x05: "parameter not available",
    0x06: "parameter read-only",
    0x07: "value out of range",
    0x08: "instance not available",
    0x09: "parameter internal failure",
    0x14: "set timeout",
    0x15: "query timeout",
    0x20: "set timeout",
    0x21: "query timeout",
}

_HEX = "0-9A-Fa-f"
_DEVICE_FRAME = re.compile(
    rf"!(?P<addr>[{_HEX}]{{2}})(?P<seq>[{_HEX}]{{4}})(?P<body>(\+[{_HEX}]{{2}}|[{_HEX}]{{8}})?)"
    rf"(?P<crc>[{_HEX}]{{4}})"
)
_HOST_FRAME = re.compile(
    rf"#(?P<addr>[{_HEX}]{{2}})(?P<seq>[{_HEX}]{{4}})(?P<payload>.*)(?P<crc>[{_HEX}]{{4}})", re.S
)


def crc16_xmodem(data: bytes) -> int:
    """The CRC-16/XMODEM of `data` (poly 0x1021, init 0, no reflection)."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ CRC_POLY) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def int_bits(value: int) -> int:
    """A signed or unsigned 32-bit integer as its 32 bits."""
    if not -(2**31) <= value < 2**32:
        raise ValueError(f"{value} does not fit in 32 bits")
    return value & 0xFFFFFFFF


def float_bits(value: float) -> int:
    """A float as the bits of its IEEE-754 single."""
    return struct.unpack(">I", struct.pack(">f", value))[0]


def bits_int32(bits: int) -> int:
    """32 value bits read as a signed 32-bit integer."""
    return struct.unpack(">i", struct.pack(">I", bits))[0]


def bits_float32(bits: int) -> float:
    """32 value bits read as an IEEE-754 single."""
    return struct.unpack(">f", struct.pack(">I", bits))[0]


# ------------------------------------------------------------------------------------ requests


@dataclass(frozen=True)
class Request:
    """One host request: the device address, the sequence number and the payload (`?VR...` or
    `VS...`)."""

    address: int
    sequence: int
    payload: str

    @property
    def body(self) -> bytes:
        """The frame before its CRC: `#`, address, sequence and payload."""
        return f"#{self.address:02X}{self.sequence:04X}{self.payload}".encode("ascii")

    @property
    def crc(self) -> int:
        """The CRC-16/XMODEM of `body`."""
        return crc16_xmodem(self.body)

    @property
    def frame(self) -> bytes:
        """The whole frame: body, CRC as 4 hex digits, `\\r`."""
        return self.body + f"{self.crc:04X}".encode() + EOL

    @property
    def is_query(self) -> bool:
        """Whether this is a `?VR` read (else a `VS` write)."""
        return self.payload.startswith(QUERY)

    @property
    def parameter(self) -> tuple[int, int]:
        """(parameter id, instance) of a ?VR or VS request."""
        start = len(QUERY) if self.is_query else len(SET)
        p = self.payload
        return int(p[start : start + 4], 16), int(p[start + 4 : start + 6], 16)

    @property
    def value_bits(self) -> int:
        """The 32-bit value of a VS request."""
        return int(self.payload[len(SET) + 6 : len(SET) + 14], 16)


def _check(address: int, sequence: int, param_id: int, instance: int) -> None:
    if not (0 <= address <= 0xFF and 0 <= sequence <= 0xFFFF):
        raise ValueError(f"address {address} / sequence {sequence} out of range")
    if not (0 <= param_id <= 0xFFFF and 0 <= instance <= 0xFF):
        raise ValueError(f"parameter {param_id} / instance {instance} out of range")


def query(address: int, sequence: int, param_id: int, instance: int) -> Request:
    """`?VR` read of one parameter instance."""
    _check(address, sequence, param_id, instance)
    return Request(address, sequence, f"{QUERY}{param_id:04X}{instance:02X}")


def set_value(address: int, sequence: int, param_id: int, instance: int, bits: int) -> Request:
    """`VS` write of 32 value bits (see int_bits / float_bits)."""
    _check(address, sequence, param_id, instance)
    if not 0 <= bits <= 0xFFFFFFFF:
        raise ValueError(f"value bits {bits:#x} do not fit in 32 bits")
    return Request(address, sequence, f"{SET}{param_id:04X}{instance:02X}{bits:08X}")


def parse_request(frame: bytes) -> Request:
    """A host frame (as a device reads it) -> Request; ProtocolError if malformed or bad CRC."""
    text = frame.rstrip(EOL).decode("ascii", errors="replace")
    m = _HOST_FRAME.fullmatch(text)
    if not m:
        raise ProtocolError(f"not a MeCom host frame: {frame!r}")
    req = Request(int(m["addr"], 16), int(m["seq"], 16), m["payload"])
    if req.crc != int(m["crc"], 16):
        raise ProtocolError(f"bad CRC in {frame!r}: computed {req.crc:04X}")
    return req


# ------------------------------------------------------------------------------------- replies


@dataclass(frozen=True)
class ValueReply:
    """A value reply: the parameter's 32 value bits."""

    bits: int

    @property
    def as_int(self) -> int:
        """The value as a signed 32-bit integer."""
        return bits_int32(self.bits)

    @property
    def as_float(self) -> float:
        """The value as an IEEE-754 single."""
        return bits_float32(self.bits)


@dataclass(frozen=True)
class Ack:
    """An acknowledgement of a `VS` write (no value)."""

    pass


@dataclass(frozen=True)
class ErrorReply:
    """An error reply: the error code, and its two hex digits as sent."""

    code: int
    code_text: str

    @property
    def meaning(self) -> str:
        """The error code in words (`ERROR_MEANINGS`), or "unknown error code"."""
        return ERROR_MEANINGS.get(self.code, "unknown error code")


Reply = ValueReply | Ack | ErrorReply


class StaleReply(ProtocolError):
    """A well-formed reply to another request (an earlier sequence number): skip it."""


class MecomDeviceError(DeviceError):
    """The device answered a request with an error code."""

    def __init__(self, reply: ErrorReply, request: Request, device: str) -> None:
        self.code = reply.code
        self.code_text = reply.code_text
        self.meaning = reply.meaning
        super().__init__(
            f"{device}: MeCom error +{reply.code_text} ({reply.meaning}) in reply to "
            f"{request.payload}"
        )


def value_frame(address: int, sequence: int, bits: int) -> bytes:
    """A device's value reply frame (`!` address, sequence, 8 hex digits, its own CRC, `\\r`): the
    twin sends these."""
    body = f"!{address:02X}{sequence:04X}{bits:08X}".encode()
    return body + f"{crc16_xmodem(body):04X}".encode() + EOL


def ack_frame(request: Request) -> bytes:
    """A device's acknowledgement of `request` (echoing the request's CRC): the twin sends these."""
    return f"!{request.address:02X}{request.sequence:04X}{request.crc:04X}".encode() + EOL


def error_frame(address: int, sequence: int, code_text: str) -> bytes:
    """A device's error reply frame with `code_text` (two hex digits; ValueError otherwise): the
    twin sends these."""
    if not re.fullmatch(rf"[{_HEX}]{{2}}", code_text):
        raise ValueError(f"error code must be two hex digits, got {code_text!r}")
    body = f"!{address:02X}{sequence:04X}+{code_text}".encode()
    return body + f"{crc16_xmodem(body):04X}".encode() + EOL


def decode_reply(frame: bytes, request: Request) -> Reply:
    """One device frame (with or without its `\\r`) in answer to `request`.

    Raises StaleReply for another sequence number and ProtocolError for anything malformed, with
    a wrong CRC, a wrong address, or an acknowledgement that does not echo the request's CRC.
    """
    text = frame.rstrip(EOL).decode("ascii", errors="replace")
    m = _DEVICE_FRAME.fullmatch(text)
    if not m:
        raise ProtocolError(f"not a MeCom reply: {frame!r}")
    address, sequence, body, crc = int(m["addr"], 16), int(m["seq"], 16), m["body"], m["crc"]
    crc_value = int(crc, 16)
    if sequence != request.sequence:
        raise StaleReply(f"reply to sequence {sequence:04X}, expected {request.sequence:04X}")
    if address != request.address:
        raise ProtocolError(f"reply from address {address:02X}, expected {request.address:02X}")
    if not body:
        if crc_value != request.crc:
            raise ProtocolError(
                f"acknowledgement echoes CRC {crc}, request had {request.crc:04X}: {frame!r}"
            )
        return Ack()
    own = crc16_xmodem(text[:-4].encode())
    if own != crc_value:
        raise ProtocolError(f"bad CRC in reply {frame!r}: computed {own:04X}")
    if body.startswith("+"):
        return ErrorReply(int(body[1:], 16), body[1:].upper())
    return ValueReply(int(body, 16))
