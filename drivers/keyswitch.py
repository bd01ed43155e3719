"""A key switch on a serial port's modem-status line: a person at the bench confirms an arm
(`daemon.arming.confirm = "serial"`).

Wiring: the switch connects one of the port's outputs (DTR or RTS; the driver asserts both while
the port is open) to the configured input, CTS or DSR. The input therefore reads asserted only
while the port is open, the driver drives its outputs and the key is on. An unplugged adapter, a
cut wire or a port nobody opened reads "off", the safe side; a vanished port raises.

The driver writes no bytes and reads no data: it asserts DTR and RTS once and then reads the
modem-status lines through pyserial (TIOCMGET). A pseudo-terminal has no modem lines, so the
simulated key switch (`nhfd.drivers.twins.keyswitch_twin`) stands behind the interface pyserial
gives (`ModemLines`), and this driver's code runs unchanged in every test.

A confirmation is a turn seen after the request (`expect_turn`, then `turned`): the key seen off,
then on. A key left on does not confirm the next request by itself.
"""

from __future__ import annotations

import errno
from collections.abc import Callable
from typing import Protocol

import serial

from .device import Device
from .errors import DeviceError, PortVanished, TransportError
from .transport import open_serial

LINES = ("cts", "dsr")


class ModemLines(Protocol):
    """What the driver uses of a port: pyserial's `Serial` has exactly this."""

    dtr: bool
    rts: bool

    @property
    def cts(self) -> bool:
        """Whether the CTS input is asserted."""
        ...

    @property
    def dsr(self) -> bool:
        """Whether the DSR input is asserted."""
        ...

    def close(self) -> None:
        """Release the port."""
        ...


LinesOpener = Callable[[], ModemLines]


def open_serial_lines(port: str) -> ModemLines:
    """`port` opened exclusively through pyserial, without hardware flow control (which would
    take the lines read here), its DTR and RTS asserted by the open."""
    return open_serial(port, rtscts=False, dsrdtr=False)


class KeySwitch(Device):
    """The key switch on `line` ("cts" or "dsr") of the port that `opener` opens (`port` names
    it in messages)."""

    def __init__(self, opener: LinesOpener, line: str, port: str) -> None:
        if line not in LINES:
            raise ValueError(f"key switch line {line!r}: allowed: {' or '.join(LINES)}")
        self.opener = opener
        self.line = line
        self.port = port
        self._lines: ModemLines | None = None
        self._seen_off = False

    @property
    def describe(self) -> str:
        """Where the switch is read, for messages: "CTS of /dev/ttyUSB0"."""
        return f"{self.line.upper()} of {self.port}"

    def _do_open(self) -> None:
        lines = self.opener()
        try:
            # The switch is powered from these outputs: asserted explicitly, whatever the open did.
            lines.dtr = True
            lines.rts = True
        except (OSError, serial.SerialException) as exc:
            lines.close()
            raise DeviceError(f"key switch on {self.port}: cannot assert DTR and RTS ({exc}); "
                              "an adapter without modem-control lines cannot power it") from None
        self._lines = lines

    def _do_close(self) -> None:
        if self._lines is not None:
            lines, self._lines = self._lines, None
            try:
                lines.close()
            except (OSError, serial.SerialException):
                pass  # gone already: nothing left to release

    def on(self) -> bool:
        """True while the key closes the circuit (the input line asserted)."""
        if self._lines is None:
            raise DeviceError(f"key switch on {self.port}: not open")
        try:
            return bool(self._lines.cts if self.line == "cts" else self._lines.dsr)
        except (OSError, serial.SerialException) as exc:
            gone = isinstance(exc, serial.SerialException) or getattr(exc, "errno", None) in (
                errno.EIO, errno.ENXIO, errno.ENODEV, errno.EBADF)
            if gone:
                raise PortVanished(f"key switch on {self.port}: port vanished ({exc})") from None
            raise TransportError(f"key switch on {self.port}: reading {self.line.upper()} "
                                 f"failed ({exc})") from None

    @property
    def seen_off(self) -> bool:
        """The key has been seen off since `expect_turn` (False: on all along)."""
        return self._seen_off

    def expect_turn(self) -> bool:
        """Start watching for a turn; returns whether the key is on now (then it must be seen
        off before an on counts)."""
        now_on = self.on()
        self._seen_off = not now_on
        return now_on

    def turned(self) -> bool:
        """True once the key has been seen off and then on since `expect_turn`."""
        now_on = self.on()
        if not now_on:
            self._seen_off = True
        return now_on and self._seen_off
