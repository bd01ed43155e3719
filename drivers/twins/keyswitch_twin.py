"""The simulated key switch: a switch wired from a port's DTR (or RTS) output to its CTS (or DSR)
input, behind the interface pyserial gives a port's modem lines (`nhfd.drivers.keyswitch.
ModemLines`).

A pseudo-terminal has no modem-control lines, so this twin replaces the port object itself: the
driver opens it through `opener()` as it would open `serial.Serial`, asserts DTR and RTS, and reads
CTS or DSR. The input reads asserted only while the key is on (`turn`) and the output it is wired
to is asserted, as a real switch would. `vanish()` makes every later read fail with EIO, as an
unplugged USB adapter does. `opens`, `closes`, `reads` and `outputs` are the record a test reads.
"""

from __future__ import annotations

import errno
import threading

from ..errors import PortNotFound

OUTPUTS = ("dtr", "rts")


class KeySwitchTwin:
    """A simulated key switch wired from a port's DTR or RTS output to its CTS or DSR input, with
    the record of opens, closes, reads and output changes."""

    def __init__(self, line: str = "cts", *, output: str = "dtr", port: str = "simulated") -> None:
        if line not in ("cts", "dsr"):
            raise ValueError(f"key switch line {line!r}: allowed: cts or dsr")
        if output not in OUTPUTS:
            raise ValueError(f"key switch output {output!r}: allowed: dtr or rts")
        self.line = line
        self.output = output
        self.port = port
        self.lock = threading.Lock()
        self.key_on = False
        self.gone = False
        self.opens = 0
        self.closes = 0
        self.reads = 0  # reads of CTS or DSR: a test waits for a sample after it turned the key
        self.outputs: list[tuple[str, bool]] = []  # every DTR / RTS change the host made

    def turn(self, on: bool) -> None:
        """A person turns the key (test-only: the bench's hand)."""
        with self.lock:
            self.key_on = on

    def vanish(self) -> None:
        """The adapter is unplugged: opens fail, reads of an open port fail with EIO."""
        with self.lock:
            self.gone = True

    def replug(self) -> None:
        """The adapter is back: opens and reads work again."""
        with self.lock:
            self.gone = False

    def opener(self) -> TwinLines:
        """Open the port (what `serial.Serial(port)` is to a real one)."""
        with self.lock:
            if self.gone:
                raise PortNotFound(f"{self.port}: no such port")
            self.opens += 1
        return TwinLines(self)


class TwinLines:
    """One open of the twin's port: DTR and RTS asserted by the open, as pyserial does."""

    def __init__(self, twin: KeySwitchTwin) -> None:
        self._twin = twin
        self._out = {"dtr": True, "rts": True}
        self._closed = False

    def _set(self, name: str, value: bool) -> None:
        self._check()
        with self._twin.lock:
            self._out[name] = bool(value)
            self._twin.outputs.append((name, bool(value)))

    def _check(self) -> None:
        if self._closed:
            raise OSError(errno.EBADF, "port is closed")
        if self._twin.gone:
            raise OSError(errno.EIO, "Input/output error")

    def _input(self, name: str) -> bool:
        self._check()
        t = self._twin
        with t.lock:
            t.reads += 1
            return t.line == name and t.key_on and self._out[t.output]

    @property
    def dtr(self) -> bool:
        """Whether DTR is asserted (set it to change it)."""
        return self._out["dtr"]

    @dtr.setter
    def dtr(self, value: bool) -> None:
        self._set("dtr", value)

    @property
    def rts(self) -> bool:
        """Whether RTS is asserted (set it to change it)."""
        return self._out["rts"]

    @rts.setter
    def rts(self, value: bool) -> None:
        self._set("rts", value)

    @property
    def cts(self) -> bool:
        """Whether CTS reads asserted: the key is on, the switch is on CTS and its output is
        asserted. OSError (EIO) once vanished."""
        return self._input("cts")

    @property
    def dsr(self) -> bool:
        """Whether DSR reads asserted: the key is on, the switch is on DSR and its output is
        asserted. OSError (EIO) once vanished."""
        return self._input("dsr")

    def close(self) -> None:
        """Close this open of the port (counted in the twin's `closes`)."""
        if not self._closed:
            self._closed = True
            with self._twin.lock:
                self._twin.closes += 1
