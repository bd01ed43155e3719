"""The laser contract: every laser backend, and the real READYBeam when NHFD_TEST_LASER names its
port (NHFD_TEST_LASER=readybeam:/dev/ttyUSB0; stop the daemon and its guardian first: the
contract opens the port itself).

No fact here makes light: nothing is ever enabled (that needs a person's arming on a real bench,
and the twin-backed tests in test_laser.py check emission against the twin's record). Powers are
set with every channel disabled and switched off again.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import pytest

from nhfd.device_settings import LaserSettings
from nhfd.drivers.errors import LinkDown
from nhfd.drivers.factory import SimulatedLaser
from nhfd.drivers.laser import Laser, MecomLaser, NotArmed
from nhfd.drivers.twins.mecom_twin import MecomTwin

from . import bench_target

FAST = {"reply_timeout_s": 0.1, "retries": 2, "reconnect_backoff_s": 0.05,
        "reconnect_attempts": 4}


@pytest.fixture(params=["mecom-twin", "simulated", "bench"])
def new_laser(request: pytest.FixtureRequest) -> Iterator[Callable[[], Laser]]:
    """Builds an unopened driver of one backend, each call a new driver on the same device."""
    made: list[Laser] = []
    cleanup: list[Callable[[], None]] = []
    if request.param == "mecom-twin":
        twin = MecomTwin().start()
        cleanup.append(twin.close)

        def make() -> Laser:
            return MecomLaser(LaserSettings(**FAST), twin.opener())
    elif request.param == "simulated":
        def make() -> Laser:
            return SimulatedLaser(LaserSettings(**FAST))  # a twin of its own per driver
    else:
        _, (port, *_) = bench_target("NHFD_TEST_LASER", ("readybeam",), "readybeam:/dev/ttyUSB0")

        def make() -> Laser:
            return MecomLaser(LaserSettings(port=port))

    def tracked() -> Laser:
        made.append(make())
        return made[-1]

    try:
        yield tracked
    finally:
        for laser in made:
            laser.close()
        for step in cleanup:
            step()


@pytest.fixture
def laser(new_laser: Callable[[], Laser]) -> Iterator[Laser]:
    with new_laser() as laser:
        yield laser


def assert_all_off(laser: Laser) -> None:
    status = laser.status()
    assert not status.any_on
    for channel, state in status.channels.items():
        assert not state.enabled, channel
        assert abs(state.power_pct) <= laser.settings.readback_tolerance_pct, channel


def test_starts_off_and_not_armed(laser):
    assert laser.connected and not laser.armed
    assert_all_off(laser)


def test_a_power_above_the_cap_is_clamped_to_the_cap_and_read_back(laser):
    channel = laser.channels[0]
    cap = laser.settings.cap_pct(channel)
    applied = laser.set_power(channel, cap + 50.0)
    assert applied == cap
    assert laser.status().channels[channel].power_pct == pytest.approx(
        cap, abs=laser.settings.readback_tolerance_pct)
    assert laser.set_power(channel, -5.0) == 0.0


def test_bad_power_or_channel_is_refused_naming_the_value(laser):
    with pytest.raises(ValueError, match=r"power_pct = nan: must be finite"):
        laser.set_power(laser.channels[0], math.nan)
    with pytest.raises(ValueError, match=r"channel 'violet': must be one of red, green, blue"):
        laser.set_power("violet", 1.0)
    with pytest.raises(ValueError, match=r"arm duration_s = 0: must be in \(0, "):
        laser.arm(0)
    assert_all_off(laser)


def test_emission_needs_a_person_to_arm(laser):
    with pytest.raises(NotArmed, match="not armed"):
        laser.enable(laser.channels[0])
    assert_all_off(laser)


def test_all_off_reads_back_off(laser):
    for channel in laser.channels:
        laser.set_power(channel, laser.settings.cap_pct(channel) / 2)
    laser.all_off()
    assert_all_off(laser)


def test_close_leaves_it_off_and_refuses_commands(new_laser):
    laser = new_laser().open()
    laser.set_power(laser.channels[0], 1.0)
    laser.close()
    assert not laser.connected
    with pytest.raises(LinkDown, match="not connected"):
        laser.set_power(laser.channels[0], 1.0)
    twin = getattr(laser, "twin", None)
    if twin is not None:  # the simulated laser's twin closes with it: its record is the judge
        assert not any(twin.emitting().values())
    else:
        with new_laser() as again:  # another driver on the same device reads what close left
            assert_all_off(again)


def test_reconnect_reidentifies_switches_off_and_does_not_rearm(laser):
    laser.arm(60)
    laser.reconnect()
    assert laser.connected and not laser.armed
    assert_all_off(laser)
