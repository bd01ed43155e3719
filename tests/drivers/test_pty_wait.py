"""The pty twins wait for bytes instead of polling: what each one says it must tick for, and that
a wait with no timed event still ends on bytes, `vanish()`/`replug()` and `close()`."""

from __future__ import annotations

import os
import select

from nhfd.drivers.twins.apt_twin import AptTwin
from nhfd.drivers.twins.clock import ManualClock
from nhfd.drivers.twins.mecom_twin import MecomTwin
from nhfd.drivers.twins.pty import TICK_S, PtyPeer


class Echo(PtyPeer):
    """No timed state: bytes in, the same bytes out."""

    def on_bytes(self, data: bytes) -> None:
        self.send(data)


def test_what_each_twin_ticks_for():
    assert MecomTwin().tick_period_s() is None  # nothing timed: bytes only
    assert Echo().tick_period_s() is None
    apt = AptTwin()
    assert apt.tick_period_s() is None  # no motion, no status updates asked for
    apt.updates_on = True
    assert TICK_S <= apt.tick_period_s() <= apt.update_period_s  # the next update
    apt.unacked = apt.unacked_updates_max  # the firmware's limit: no more updates
    assert apt.tick_period_s() is None
    assert AptTwin(clock=ManualClock()).tick_period_s() == TICK_S  # a test's clock: poll


def test_a_waiting_twin_answers_bytes_and_wakes_for_vanish_replug_and_close():
    twin = Echo().start()
    thread = twin._thread
    try:
        for _ in range(2):  # the second time on the pair replug() made: the wait saw it
            fd = os.open(twin.port_path, os.O_RDWR | os.O_NOCTTY)
            try:
                os.write(fd, b"ping")
                got = b""
                while len(got) < 4 and select.select([fd], [], [], 5.0)[0]:
                    got += os.read(fd, 16)
                assert got == b"ping"
            finally:
                os.close(fd)
            twin.vanish()
            twin.replug()
    finally:
        twin.close()
    assert not thread.is_alive()  # close() woke a wait that has no timeout
