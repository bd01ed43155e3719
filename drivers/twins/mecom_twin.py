"""A READYBeam twin: answers MeCom frames on a pty and records every channel's emission.

It behaves as docs/design.md ("The hardware": Lasers) describes the device: value replies with
their own CRC, acknowledgements echoing the request's CRC, `+EE` error replies in hex, silence on a
bad request CRC, and read-only / out-of-range / unknown-parameter errors. Emission of a channel is
its power while its enable is 1 (the twin does not model digital control gating it).

The record is what tests trust: `emission(channel)` lists (time_s, emitted_pct) at every change,
on the twin's clock, so "the lasers were off by then" is a fact read from the device side.

Faults (`inject`) apply to the next matching request(s):
  "no_reply"    the request is ignored (not executed, no answer)
  "drop_reply"  executed, answer lost
  "garbage"     not executed; line noise (including a `\\r`) instead of an answer
  "bad_crc"     executed; the answer's CRC is corrupted
  "error"       not executed; answered `+code_text`
  "vanish"      the port disappears on receipt (not executed)
  "stuck"       a VS is acknowledged but stores `value` instead (read-back mismatch)
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from nhfd.device_settings import COLOURS, MecomParameterIds

from .. import mecom
from ..errors import ProtocolError
from .clock import Clock, real_clock
from .pty import PtyPeer

FAULT_KINDS = ("no_reply", "drop_reply", "garbage", "bad_crc", "error", "vanish", "stuck")
_MAX_POWER_PCT = 100.5  # the READYBeam accepts up to 100.5 %


@dataclass
class _Fault:
    kind: str
    count: int
    op: str | None
    param: int | None
    instance: int | None
    code_text: str
    value: float | int | None

    def matches(self, req: mecom.Request) -> bool:
        if self.op is not None and not req.payload.startswith(self.op):
            return False
        try:
            param, instance = req.parameter
        except ValueError:
            return self.param is None and self.instance is None
        return (self.param is None or param == self.param) and (
            self.instance is None or instance == self.instance
        )


@dataclass
class RequestRecord:
    """One request the twin received: when (s, the twin's clock), its payload, and whether it was
    answered."""

    time_s: float
    payload: str
    answered: bool = True


@dataclass
class _Channel:
    enabled: int = 0
    power_pct: float = 0.0
    control: int = 0
    log: list[tuple[float, float]] = field(default_factory=list)

    @property
    def emitted_pct(self) -> float:
        return self.power_pct if self.enabled else 0.0


class MecomTwin(PtyPeer):
    """A simulated FISBA READYBeam that answers MeCom on a pty and records each channel's emission
    (% of full power) on its clock."""

    def __init__(
        self,
        *,
        device_type: int = 1171,
        address: int = 0,
        channel_instances: Iterable[int] = (1, 2, 3),
        parameter_ids: MecomParameterIds | None = None,
        device_status: int = 1,
        serial_number: int = 23051,
        initial_pct: Mapping[str, float] | None = None,
        clock: Clock = real_clock,
    ) -> None:
        super().__init__(clock=clock)
        self.device_type = device_type
        self.address = address
        self.ids = parameter_ids or MecomParameterIds()
        self.device_status = device_status
        self.serial_number = serial_number  # common parameter 102, read-only
        self.names = dict(zip(channel_instances, COLOURS, strict=True))
        self._channels = {inst: _Channel() for inst in self.names}
        self.requests: list[RequestRecord] = []
        self.rejected: list[bytes] = []
        self._faults: list[_Fault] = []
        self._rx = bytearray()
        now = self.clock()
        for inst, ch in self._channels.items():
            pct = (initial_pct or {}).get(self.names[inst], 0.0)
            ch.enabled, ch.power_pct = int(pct > 0), pct
            ch.log.append((now, ch.emitted_pct))

    # -- test API ------------------------------------------------------------------------------

    def inject(
        self,
        kind: str,
        *,
        count: int = 1,
        op: str | None = None,
        param: int | None = None,
        instance: int | None = None,
        code_text: str = "05",
        value: float | int | None = None,
    ) -> None:
        """Apply a fault to the next `count` requests matching op ("?VR"/"VS"), param, instance."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault {kind!r}: one of {FAULT_KINDS}")
        with self.lock:
            self._faults.append(_Fault(kind, count, op, param, instance, code_text, value))

    def _instance(self, channel: str | int) -> int:
        if isinstance(channel, int):
            return channel
        return next(i for i, n in self.names.items() if n == channel)

    def emission(self, channel: str | int) -> list[tuple[float, float]]:
        """(time_s, emitted_pct) at start and at every change, on the twin's clock."""
        with self.lock:
            return list(self._channels[self._instance(channel)].log)

    def emitting(self) -> dict[str, float]:
        """Each channel's emission now (%), by colour."""
        with self.lock:
            return {self.names[i]: c.emitted_pct for i, c in self._channels.items()}

    def max_emitted_pct(self, channel: str | int | None = None) -> float:
        """The highest emission (%) ever recorded, on `channel` or on any."""
        insts = self.names if channel is None else [self._instance(channel)]
        with self.lock:
            return max(p for i in insts for _, p in self._channels[i].log)

    def dark_since(self) -> float | None:
        """When every channel last became dark (None while any emits)."""
        with self.lock:
            events = sorted(
                (t, inst, p) for inst, c in self._channels.items() for t, p in c.log
            )
        current: dict[int, float] = {}
        since: float | None = None
        for t, inst, p in events:
            current[inst] = p
            if any(v > 0 for v in current.values()):
                since = None
            elif since is None:
                since = t
        return since

    def set_state(self, channel: str, *, enabled: int | None = None,
                  power_pct: float | None = None) -> None:
        """Change a channel from outside (front panel, another host): drivers must notice."""
        with self.lock:
            ch = self._channels[self._instance(channel)]
            if enabled is not None:
                ch.enabled = enabled
            if power_pct is not None:
                ch.power_pct = power_pct
            self._record(ch)

    def writes(self) -> list[str]:
        """The payloads of every `VS` write received, in order."""
        with self.lock:
            return [r.payload for r in self.requests if r.payload.startswith(mecom.SET)]

    # -- protocol ------------------------------------------------------------------------------

    def on_bytes(self, data: bytes) -> None:
        """Parse the host's frames and handle each (faults applied); frames with a bad CRC get no
        answer and are kept in `rejected`."""
        self._rx += data
        while (end := self._rx.find(mecom.EOL)) >= 0:
            raw = bytes(self._rx[: end + 1])
            del self._rx[: end + 1]
            start = raw.rfind(mecom.HOST_START)
            if start < 0:
                self.rejected.append(raw)
                continue
            try:
                request = mecom.parse_request(raw[start:])
            except ProtocolError:
                self.rejected.append(raw)  # bad CRC: the device stays silent
                continue
            self._handle(request)
            if self._master is None:  # vanished while handling
                self._rx.clear()
                return

    def _take_fault(self, request: mecom.Request) -> _Fault | None:
        for fault in self._faults:
            if fault.matches(request):
                fault.count -= 1
                if fault.count <= 0:
                    self._faults.remove(fault)
                return fault
        return None

    def _handle(self, request: mecom.Request) -> None:
        record = RequestRecord(self.clock(), request.payload)
        self.requests.append(record)
        fault = self._take_fault(request)
        kind = fault.kind if fault else None
        if kind == "vanish":
            record.answered = False
            self.vanish()
            return
        if kind == "no_reply":
            record.answered = False
            return
        if kind == "garbage":
            self.send(b"\x00\xff!zz" + os.urandom(5).hex().encode() + b"\r")
            return
        a, s = request.address, request.sequence
        if kind == "error":
            reply = mecom.error_frame(a, s, fault.code_text)
        else:
            reply = self._execute(request, fault.value if kind == "stuck" else None)
        if kind == "drop_reply" or request.address == 255:
            record.answered = False
            return
        if request.address not in (0, self.address):
            record.answered = False
            return
        if kind == "bad_crc":
            reply = reply[:-5] + (b"0000" if reply[-5:-1] != b"0000" else b"FFFF") + mecom.EOL
        self.send(reply)

    def _execute(self, request: mecom.Request, stuck: float | int | None) -> bytes:
        a, s = request.address, request.sequence
        if not (request.is_query or request.payload.startswith(mecom.SET)):
            return mecom.error_frame(a, s, "01")
        try:
            param, inst = request.parameter
        except ValueError:
            return mecom.error_frame(a, s, "04")
        ids = self.ids
        known = {ids.device_type, ids.status, ids.serial_number, ids.digital_control,
                 ids.channel_enable, ids.channel_power, ids.any_laser_on}
        if param not in known:
            return mecom.error_frame(a, s, "05")
        per_channel = param in (ids.digital_control, ids.channel_enable, ids.channel_power)
        if per_channel and inst not in self._channels:
            return mecom.error_frame(a, s, "08")
        if request.is_query:
            return mecom.value_frame(a, s, self._read(param, inst))
        if not per_channel:
            return mecom.error_frame(a, s, "06")
        bits = request.value_bits
        ch = self._channels[inst]
        if param == ids.channel_power:
            pct = mecom.bits_float32(bits)
            if not 0.0 <= pct <= _MAX_POWER_PCT:
                return mecom.error_frame(a, s, "07")
            ch.power_pct = float(stuck) if stuck is not None else pct
        else:
            value = mecom.bits_int32(bits)
            if value not in (0, 1):
                return mecom.error_frame(a, s, "07")
            value = int(stuck) if stuck is not None else value
            if param == ids.channel_enable:
                ch.enabled = value
            else:
                ch.control = value
        self._record(ch)
        return mecom.ack_frame(request)

    def _read(self, param: int, inst: int) -> int:
        ids = self.ids
        if param == ids.device_type:
            return mecom.int_bits(self.device_type)
        if param == ids.status:
            return mecom.int_bits(self.device_status)
        if param == ids.serial_number:
            return mecom.int_bits(self.serial_number)
        if param == ids.any_laser_on:
            return int(any(c.emitted_pct > 0 for c in self._channels.values()))
        ch = self._channels[inst]
        if param == ids.channel_power:
            return mecom.float_bits(ch.power_pct)
        return mecom.int_bits(ch.enabled if param == ids.channel_enable else ch.control)

    def _record(self, ch: _Channel) -> None:
        if ch.log[-1][1] != ch.emitted_pct:
            ch.log.append((self.clock(), ch.emitted_pct))
