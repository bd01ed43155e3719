"""The arm confirmation's inputs: a key switch on a serial port's CTS or DSR line (the real driver
against its twin, which stands behind pyserial's modem-line interface) and navigator button
presses counted report by report."""

from __future__ import annotations

import pytest

from nhfd.drivers.errors import PortNotFound, PortVanished
from nhfd.drivers.keyswitch import KeySwitch, open_serial_lines
from nhfd.drivers.navigator import SimulatedNavigator, SpaceMouseNavigator
from nhfd.drivers.twins.keyswitch_twin import KeySwitchTwin


def test_the_driver_powers_the_switch_and_reads_the_configured_line():
    twin = KeySwitchTwin("dsr", output="rts")
    with KeySwitch(twin.opener, "dsr", "simulated") as switch:
        assert twin.outputs == [("dtr", True), ("rts", True)]  # asserted explicitly at open
        assert switch.on() is False
        twin.turn(True)
        assert switch.on() is True
    assert twin.opens == twin.closes == 1
    # Wired to DSR, read on CTS: never on, whatever the key does.
    with KeySwitch(twin.opener, "cts", "simulated") as switch:
        assert switch.on() is False
        assert switch.describe == "CTS of simulated"


def test_a_confirmation_is_a_turn_seen_after_the_request():
    twin = KeySwitchTwin("cts")
    twin.turn(True)  # left on before the request
    with KeySwitch(twin.opener, "cts", "simulated") as switch:
        assert switch.expect_turn() is True
        assert not switch.turned() and not switch.seen_off  # on all along: no confirmation
        twin.turn(False)
        assert not switch.turned() and switch.seen_off
        twin.turn(True)
        assert switch.turned()


def test_an_unplugged_port_raises_naming_it():
    twin = KeySwitchTwin("cts")
    switch = KeySwitch(twin.opener, "cts", "/dev/ttyKEY")
    switch.open()
    twin.vanish()
    with pytest.raises(PortVanished, match=r"key switch on /dev/ttyKEY: port vanished"):
        switch.on()
    switch.close()
    with pytest.raises(PortNotFound, match="simulated: no such port"):
        KeySwitch(twin.opener, "cts", "simulated").open()
    with pytest.raises(PortNotFound, match="/dev/nhfd-no-such-port: no such port"):
        open_serial_lines("/dev/nhfd-no-such-port")


def test_a_line_other_than_cts_or_dsr_is_refused_naming_it():
    with pytest.raises(ValueError, match=r"key switch line 'ri': allowed: cts or dsr"):
        KeySwitch(KeySwitchTwin().opener, "ri", "simulated")


class _Reports:
    """A hidapi device whose reports are queued (non-blocking reads: [] when none)."""

    def __init__(self, reports: list[list[int]]) -> None:
        self.reports = reports

    def read(self, size: int) -> list[int]:
        return self.reports.pop(0) if self.reports else []


def test_a_press_and_release_between_two_reads_counts_as_a_press():
    nav = SpaceMouseNavigator()
    nav.settings = nav.settings.model_copy(update={"read_timeout_ms": 0})
    nav._device = _Reports([[3, 2, 0], [3, 0, 0], [1, 0, 0, 0, 0, 0, 0]])
    reading = nav.read()
    assert reading.buttons == 0 and nav.presses == 1  # down and up again, both seen
    nav._device = _Reports([[3, 1, 0], [3, 3, 0]])  # held, then a second button as well
    assert nav.read().buttons == 3 and nav.presses == 3


def test_the_simulated_navigator_is_pressed_from_a_test():
    nav = SimulatedNavigator([])
    nav.press(4)
    assert nav.presses == 0  # seen by the next read, as a report would be
    assert nav.read().buttons == 0 and nav.presses == 1
    with pytest.raises(ValueError, match=r"button: 40; allowed: 0 to 31"):
        nav.press(40)
