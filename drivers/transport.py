"""Byte transports: a serial port (pyserial) or a pseudo-terminal whose other end is a twin.

A driver talks to a `Transport` only: write bytes, read with a bounded timeout, flush, close, and
one line-control hook. The hook carries what a real FTDI port needs and a pseudo-terminal cannot
do (the RTS pulse APT controllers expect, the FTDI latency timer): the serial backend does it, the
pty backend records the request as a no-op, so the same driver code runs against real devices and
twins.

Drivers take an *opener* (a callable returning a fresh transport) rather than a transport, so
reconnecting after a port vanishes finds the port again (by USB serial number, or the twin's new
pty path) instead of reopening a path that may now name something else.

A port that disappears while open raises `PortVanished`; every read has a deadline.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import select
import time
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import PortBusy, PortNotFound, PortVanished, ReplyTimeout, TransportError

log = logging.getLogger(__name__)

# Upper bound on one blocking wait inside a read, so a closed transport is noticed promptly.
_POLL_S = 0.05


def same_port(a: str, b: str) -> bool:
    """True when two port paths name the same device (a /dev/serial/by-id link and its tty)."""
    return bool(a and b) and (a == b or os.path.realpath(a) == os.path.realpath(b))


@dataclass(frozen=True)
class LineControl:
    """What a device needs from the line beyond bytes, applied once after open."""

    # APT: set RTS, 50 ms, purge both buffers, 50 ms, clear RTS (the official initialisation).
    rts_pulse: bool = False
    # FTDI latency timer in ms (1 for snappy replies); None leaves it as it is.
    latency_timer_ms: int | None = None


class Transport(ABC):
    """One open byte link. Backends implement `_write`, `_read_some`, `_close`, `line_control`."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._rx = bytearray()
        self._closed = False

    # -- backend hooks -------------------------------------------------------------------------

    @abstractmethod
    def _write(self, data: bytes) -> None: ...

    @abstractmethod
    def _read_some(self, timeout_s: float) -> bytes:
        """Whatever arrives within timeout_s (b"" if nothing); PortVanished if the port is gone."""

    @abstractmethod
    def _close(self) -> None: ...

    @abstractmethod
    def line_control(self, control: LineControl) -> None:
        """Apply line control (RTS pulse, latency timer)."""

    def _flush(self) -> None:  # noqa: B027 - optional hook: most links send on write
        pass

    # -- shared logic --------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """Whether `close` has been called."""
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"{self.name}: transport is closed")

    def write(self, data: bytes) -> None:
        """Send `data`; TransportError when closed, PortVanished where the port is gone."""
        self._check_open()
        self._write(bytes(data))

    def flush(self) -> None:
        """Block until written bytes have left the host."""
        self._check_open()
        self._flush()

    def _fill(self, deadline: float) -> bool:
        """Append what arrives before the deadline to the buffer; False when time ran out."""
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        chunk = self._read_some(min(remaining, _POLL_S))
        self._rx += chunk
        return True

    def read(self, size: int, timeout_s: float) -> bytes:
        """Exactly `size` bytes, or ReplyTimeout after timeout_s."""
        self._check_open()
        deadline = time.monotonic() + timeout_s
        while len(self._rx) < size:
            if not self._fill(deadline):
                raise ReplyTimeout(
                    f"{self.name}: {len(self._rx)} of {size} bytes after {timeout_s:g} s"
                )
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def read_until(self, terminator: bytes, timeout_s: float) -> bytes:
        """Bytes up to and including `terminator`, or ReplyTimeout after timeout_s."""
        self._check_open()
        deadline = time.monotonic() + timeout_s
        while (end := self._rx.find(terminator)) < 0:
            if not self._fill(deadline):
                raise ReplyTimeout(f"{self.name}: no {terminator!r} within {timeout_s:g} s")
        end += len(terminator)
        out = bytes(self._rx[:end])
        del self._rx[:end]
        return out

    def read_available(self, timeout_s: float) -> bytes:
        """What is buffered, else whatever arrives within timeout_s (possibly b"")."""
        self._check_open()
        if not self._rx:
            self._rx += self._read_some(timeout_s)
        out = bytes(self._rx)
        self._rx.clear()
        return out

    def discard_input(self) -> None:
        """Drop buffered and pending input (stale replies from an interrupted exchange)."""
        self._check_open()
        self._rx.clear()
        while self._read_some(0.0):
            pass

    def close(self) -> None:
        """Close the link; a no-op when closed."""
        if not self._closed:
            self._closed = True
            self._close()

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}{', closed' if self._closed else ''})"


Opener = Callable[[], Transport]


class LineControlError(TransportError):
    """The port is open but its modem-control lines cannot be driven (no RTS on the adapter)."""


# ----------------------------------------------------------------------------- pseudo-terminal


class PtyTransport(Transport):
    """The slave end of a pseudo-terminal, opened by path, raw, exclusive (flock) like a port."""

    def __init__(self, path: str, *, exclusive: bool = True) -> None:
        super().__init__(path)
        self.path = path
        # Line-control requests, kept so tests can check that a driver asked for them.
        self.line_control_calls: list[LineControl] = []
        try:
            self._fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except FileNotFoundError:
            raise PortNotFound(f"{path}: no such pseudo-terminal") from None
        except OSError as exc:
            raise TransportError(f"{path}: cannot open: {exc.strerror}") from None
        try:
            if exclusive:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            tty.setraw(self._fd)
        except BlockingIOError:
            os.close(self._fd)
            raise PortBusy(f"{path}: another process holds this port") from None
        except OSError as exc:
            os.close(self._fd)
            raise TransportError(f"{path}: cannot configure: {exc.strerror}") from None

    def line_control(self, control: LineControl) -> None:
        """Record the request in `line_control_calls` (a pty has no RTS line or latency timer)."""
        # A pty has no RTS line or latency timer (the ioctls raise ENOTTY): record the request so
        # tests can check the driver asked for it.
        self._check_open()
        self.line_control_calls.append(control)

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        deadline = time.monotonic() + 1.0
        while view:
            try:
                n = os.write(self._fd, view)
            except BlockingIOError:
                n = 0
            except OSError as exc:
                raise self._vanished(exc) from None
            view = view[n:]
            if view:
                if time.monotonic() > deadline:
                    raise TransportError(f"{self.path}: write stalled (peer not reading)")
                select.select([], [self._fd], [], _POLL_S)

    def _read_some(self, timeout_s: float) -> bytes:
        try:
            ready, _, _ = select.select([self._fd], [], [], max(timeout_s, 0.0))
            if not ready:
                return b""
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return b""
        except OSError as exc:
            raise self._vanished(exc) from None
        if not data:  # readable but empty: the master side hung up
            raise self._vanished(None)
        return data

    def _vanished(self, exc: OSError | None) -> PortVanished:
        why = f" ({exc.strerror})" if exc else ""
        return PortVanished(f"{self.path}: port vanished{why}")

    def _close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self._fd)



def pty_opener(path: str | Callable[[], str]) -> Opener:
    """An opener for a pty path, or for a callable giving the current path (a replugged twin)."""
    return lambda: PtyTransport(path() if callable(path) else path)


# ---------------------------------------------------------------------------------- serial port


def set_ftdi_latency_timer(port: str, ms: int, sysfs_root: str | Path = "/sys") -> bool:
    """Write the FTDI latency timer through sysfs; False (and a warning) where not possible.

    Usually needs root or a udev rule; the udev rule is the lasting fix, this is best effort.
    """
    node = Path(os.path.realpath(port)).name
    device = Path(sysfs_root) / "bus" / "usb-serial" / "devices" / node
    path = device / "latency_timer"
    if not device.is_dir():
        log.debug("%s: not a USB serial adapter, no latency timer to set", port)
        return False
    try:
        current = int(path.read_text().strip())
        if current != ms:
            path.write_text(f"{ms}\n")
        return True
    except (OSError, ValueError) as exc:
        log.warning("%s: cannot set the FTDI latency timer to %d ms via %s (%s); "
                    "replies will be slower (install the udev rule)", port, ms, path, exc)
        return False


def find_serial_port(usb_serial: str, vid: int | None = None, pid: int | None = None) -> str:
    """The device path of the port whose USB serial number is `usb_serial`."""
    from serial.tools import list_ports

    ports = list(list_ports.comports())
    matches = [
        p.device
        for p in ports
        if p.serial_number == usb_serial
        and (vid is None or p.vid == vid)
        and (pid is None or p.pid == pid)
    ]
    if len(matches) == 1:
        return matches[0]
    if not matches:
        seen = ", ".join(f"{p.device} (serial {p.serial_number})" for p in ports) or "none"
        raise PortNotFound(f"no serial port with USB serial number {usb_serial!r}; ports: {seen}")
    raise PortNotFound(f"USB serial number {usb_serial!r} matches several ports: {matches}")


def open_serial(port: str, **settings: Any) -> Any:
    """`port` opened exclusively through pyserial, non-blocking (`timeout=0`) with `settings`
    (baud rate, flow control, ...); its errors as the drivers' own, naming the port: PortBusy,
    PortNotFound or TransportError."""
    import serial

    try:
        return serial.Serial(port=port, timeout=0, exclusive=True, **settings)
    except serial.SerialException as exc:
        text = str(exc)
        if "exclusively lock" in text:
            raise PortBusy(f"{port}: another process holds this port") from None
        if isinstance(exc.__context__, FileNotFoundError) or "No such file" in text:
            raise PortNotFound(f"{port}: no such port") from None
        raise TransportError(f"{port}: cannot open: {text}") from None


class SerialTransport(Transport):
    """A pyserial port, opened exclusively, 8N1."""

    def __init__(
        self,
        port: str,
        baud: int,
        *,
        rtscts: bool = False,
        write_timeout_s: float = 1.0,
        sysfs_root: str | Path = "/sys",
    ) -> None:
        import serial

        super().__init__(port)
        self._sysfs_root = sysfs_root
        self._ser = open_serial(port, baudrate=baud, bytesize=serial.EIGHTBITS,
                                parity=serial.PARITY_NONE, stopbits=serial.STOPBITS_ONE,
                                rtscts=rtscts, write_timeout=write_timeout_s)

    def line_control(self, control: LineControl) -> None:
        """Set the FTDI latency timer (ms, through sysfs) and pulse RTS with a buffer purge, as
        `control` asks; LineControlError where the adapter has no RTS line."""
        self._check_open()
        if control.latency_timer_ms is not None:
            set_ftdi_latency_timer(self.name, control.latency_timer_ms, self._sysfs_root)
        if control.rts_pulse:
            # An adapter without modem-control lines (or a pty) answers the RTS ioctl with
            # ENOTTY: say which port and which step, not a bare "Inappropriate ioctl".
            try:
                self._ser.rts = True
                time.sleep(0.05)
                self._ser.reset_input_buffer()
                self._ser.reset_output_buffer()
                time.sleep(0.05)
                self._ser.rts = False
            except OSError as exc:
                raise LineControlError(
                    f"{self.name}: the line reset (RTS pulse and buffer purge after open) "
                    f"failed: {exc.strerror or exc}; the adapter has no RTS line?") from None

    def _write(self, data: bytes) -> None:
        import serial

        try:
            self._ser.write(data)
        except serial.SerialTimeoutException:
            raise TransportError(f"{self.name}: write timed out (flow control held?)") from None
        except (serial.SerialException, OSError) as exc:
            raise PortVanished(f"{self.name}: port vanished during write ({exc})") from None

    def _flush(self) -> None:
        import serial

        try:
            self._ser.flush()
        except (serial.SerialException, OSError) as exc:
            raise PortVanished(f"{self.name}: port vanished ({exc})") from None

    def _read_some(self, timeout_s: float) -> bytes:
        import serial

        try:
            # select, then a non-blocking read: changing pyserial's timeout per call would
            # reconfigure the port (tcsetattr) on every read.
            ready, _, _ = select.select([self._ser.fileno()], [], [], max(timeout_s, 0.0))
            if not ready:
                return b""
            return self._ser.read(max(1, self._ser.in_waiting))
        except serial.SerialException as exc:
            # pyserial's word for a port that reports data but has none: it is gone.
            raise PortVanished(f"{self.name}: port vanished ({exc})") from None
        except OSError as exc:
            if exc.errno in (errno.EIO, errno.ENXIO, errno.ENODEV, errno.EBADF):
                raise PortVanished(f"{self.name}: port vanished ({exc})") from None
            raise TransportError(f"{self.name}: read failed ({exc})") from None

    def _close(self) -> None:
        with contextlib.suppress(Exception):
            self._ser.close()


def serial_opener(
    port: str = "",
    usb_serial: str = "",
    *,
    baud: int,
    rtscts: bool = False,
    vid: int | None = None,
    pid: int | None = None,
) -> Opener:
    """An opener that resolves the port at each open: by path, or by USB serial number."""
    if not port and not usb_serial:
        raise ValueError("a serial device needs a port path or a USB serial number")

    def open_() -> Transport:
        path = port or find_serial_port(usb_serial, vid, pid)
        return SerialTransport(path, baud, rtscts=rtscts)

    return open_
