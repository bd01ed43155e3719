"""The lifecycle base every device kind shares: one reconnect with back-off."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from nhfd.drivers import device as device_module
from nhfd.drivers.camera import Camera
from nhfd.drivers.device import Device
from nhfd.drivers.errors import LinkDown, PortNotFound, WrongDevice
from nhfd.drivers.laser import Laser
from nhfd.drivers.navigator import Navigator
from nhfd.drivers.slm import SLM
from nhfd.drivers.stage import Stage


class Flaky(Device):
    """Fails to open `failures` times (a port not back yet), then opens."""

    def __init__(self, failures: int, error: Exception | None = None) -> None:
        self.settings = SimpleNamespace(reconnect_attempts=5, reconnect_backoff_s=0.5,
                                        reconnect_backoff_max_s=1.5)
        self.failures, self.error = failures, error
        self.calls: list[str] = []

    def _do_open(self) -> None:
        self.calls.append("open")
        if self.failures:
            self.failures -= 1
            raise self.error or PortNotFound("not back yet")

    def _do_close(self) -> None:
        self.calls.append("close")


@pytest.fixture
def sleeps(monkeypatch) -> list[float]:
    slept: list[float] = []
    monkeypatch.setattr(device_module.time, "sleep", slept.append)
    return slept


def test_every_device_kind_shares_the_lifecycle_base():
    for kind in (SLM, Camera, Laser, Stage, Navigator):
        assert issubclass(kind, Device)


def test_reconnect_backs_off_doubling_up_to_the_cap(sleeps):
    flaky = Flaky(failures=3)
    flaky.reconnect()
    assert sleeps == [0.5, 1.0, 1.5]
    assert flaky.calls == ["close", "open", "close", "open", "close", "open", "close", "open"]


def test_reconnect_gives_up_naming_the_last_failure(sleeps):
    with pytest.raises(LinkDown, match="no link after 5 attempts: not back yet"):
        Flaky(failures=99).reconnect()
    assert sleeps == [0.5, 1.0, 1.5, 1.5]  # no sleep after the last attempt


def test_another_device_is_not_retried(sleeps):
    flaky = Flaky(failures=1, error=WrongDevice("serial 2, was 1"))
    with pytest.raises(WrongDevice):
        flaky.reconnect()
    assert sleeps == [] and flaky.calls == ["close", "open"]
