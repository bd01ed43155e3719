"""Transports: bounded reads, exclusive opens, vanishing ports, ports found by serial number."""

from __future__ import annotations

import os
import time
import tty
from types import SimpleNamespace

import pytest

from nhfd.drivers import transport as tr
from nhfd.drivers.errors import PortBusy, PortNotFound, PortVanished, ReplyTimeout, TransportError


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    try:
        yield master, path
    finally:
        for fd in (master, slave):
            try:
                os.close(fd)
            except OSError:
                pass


def test_pty_transport_reads_and_writes_with_deadlines(pty_pair):
    master, path = pty_pair
    with tr.PtyTransport(path) as t:
        os.write(master, b"!abc\rxyz")
        assert t.read_until(b"\r", 1.0) == b"!abc\r"
        assert t.read(3, 1.0) == b"xyz"
        t.write(b"#hello\r")
        assert os.read(master, 100) == b"#hello\r"
        start = time.monotonic()
        with pytest.raises(ReplyTimeout, match=r"0\.2 s"):
            t.read_until(b"\r", 0.2)
        assert 0.15 < time.monotonic() - start < 1.0
        os.write(master, b"stale")
        time.sleep(0.02)
        t.discard_input()
        assert t.read_available(0.05) == b""
        t.line_control(tr.LineControl(rts_pulse=True, latency_timer_ms=1))
        assert t.line_control_calls == [tr.LineControl(rts_pulse=True, latency_timer_ms=1)]
    with pytest.raises(TransportError, match="closed"):
        t.write(b"x")


def test_ports_are_exclusive(pty_pair):
    _, path = pty_pair
    with tr.PtyTransport(path):
        with pytest.raises(PortBusy):
            tr.PtyTransport(path)
        with pytest.raises(PortBusy):
            tr.SerialTransport(path, 57600)


def test_a_vanished_port_raises_on_read_and_write(pty_pair):
    master, path = pty_pair
    t = tr.PtyTransport(path)
    os.close(master)
    with pytest.raises(PortVanished, match="vanished"):
        t.read_until(b"\r", 1.0)
    with pytest.raises(PortVanished):
        t.write(b"#")
    t.close()
    with pytest.raises(PortNotFound):
        tr.PtyTransport("/dev/pts/does-not-exist")


def test_serial_transport_over_a_pty_and_why_line_control_is_a_hook(pty_pair):
    master, path = pty_pair
    with tr.SerialTransport(path, 57600) as t:
        os.write(master, b"!0001\r")
        assert t.read_until(b"\r", 1.0) == b"!0001\r"
        t.write(b"#x\r")
        t.flush()
        assert os.read(master, 10) == b"#x\r"
        # A pty has no RTS line, like an adapter without modem-control lines: the real backend's
        # line control fails, naming the port and the step (not a bare "Inappropriate ioctl").
        # Twins use PtyTransport, whose hook records the request instead.
        with pytest.raises(tr.LineControlError) as info:
            t.line_control(tr.LineControl(rts_pulse=True))
        assert str(info.value) == (f"{path}: the line reset (RTS pulse and buffer purge after "
                                   "open) failed: Inappropriate ioctl for device; the adapter "
                                   "has no RTS line?")
        t.line_control(tr.LineControl(rts_pulse=False))  # nothing asked of the lines: no error
        os.close(master)
        with pytest.raises(PortVanished):
            t.read_until(b"\r", 1.0)


def ports(*rows):
    return [SimpleNamespace(device=d, serial_number=s, vid=v, pid=p) for d, s, v, p in rows]


def test_ports_are_found_by_usb_serial_number(monkeypatch):
    from serial.tools import list_ports

    monkeypatch.setattr(list_ports, "comports", lambda: ports(
        ("/dev/ttyUSB0", "27000001", 0x0403, 0xFAF0),
        ("/dev/ttyUSB1", "FT4ABCDE", 0x0403, 0x6001),
        ("/dev/ttyUSB2", "DUP", 0x0403, 0x6001),
        ("/dev/ttyUSB3", "DUP", 0x0403, 0x6001),
    ))
    assert tr.find_serial_port("FT4ABCDE") == "/dev/ttyUSB1"
    assert tr.find_serial_port("27000001", 0x0403, 0xFAF0) == "/dev/ttyUSB0"
    with pytest.raises(PortNotFound, match="ttyUSB1 \\(serial FT4ABCDE\\)"):
        tr.find_serial_port("27000001", 0x0403, 0x6001)
    with pytest.raises(PortNotFound, match="several"):
        tr.find_serial_port("DUP")
    with pytest.raises(ValueError, match="port path or a USB serial"):
        tr.serial_opener(baud=57600)
    with pytest.raises(PortNotFound):
        tr.serial_opener(usb_serial="nope", baud=57600)()


def test_the_ftdi_latency_timer_is_set_through_sysfs(tmp_path):
    dev = tmp_path / "bus" / "usb-serial" / "devices" / "ttyUSB0"
    dev.mkdir(parents=True)
    (dev / "latency_timer").write_text("16\n")
    assert tr.set_ftdi_latency_timer("/dev/ttyUSB0", 1, tmp_path)
    assert (dev / "latency_timer").read_text().strip() == "1"
    assert not tr.set_ftdi_latency_timer("/dev/pts/7", 1, tmp_path)  # not a USB adapter
