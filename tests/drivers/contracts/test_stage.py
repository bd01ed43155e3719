"""The stage contract: every stage backend, and a real Thorlabs controller when NHFD_TEST_STAGE
names its port (NHFD_TEST_STAGE=kinesis:/dev/ttyUSB1). On a real bench the stage homes and moves
within its configured soft limits: clear the travel first.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from nhfd.device_settings import StageSettings
from nhfd.drivers.factory import SimulatedStage
from nhfd.drivers.stage import AptStage, NotHomed, SoftLimitError, Stage
from nhfd.drivers.twins.apt_twin import AptTwin

from . import bench_target

# Quick twins: 20 mm/s moves and homing, short timeouts.
FAST = {"enable_settle_s": 0.0, "reply_timeout_s": 0.2, "reconnect_backoff_s": 0.05,
        "reconnect_attempts": 4, "home_timeout_s": 5.0, "move_timeout_s": 5.0,
        "velocity_mm_s": 20.0}
HOME_MM_S = 20.0


@pytest.fixture(params=["apt-twin", "simulated", "bench"])
def stage(request: pytest.FixtureRequest) -> Iterator[Stage]:
    twin: AptTwin | None = None
    if request.param == "apt-twin":
        twin = AptTwin(position_mm=1.0, home_velocity_mm_s=HOME_MM_S).start()
        driver: Stage = AptStage(StageSettings(**FAST), twin.opener())
    elif request.param == "simulated":
        driver = SimulatedStage(StageSettings(**FAST))
        driver.twin.home_speed = HOME_MM_S * driver.settings.counts_per_mm
    else:
        _, (port, *_) = bench_target("NHFD_TEST_STAGE", ("kinesis", "apt"),
                                     "kinesis:/dev/ttyUSB1")
        driver = AptStage(StageSettings(port=port))
    try:
        with driver:
            yield driver
    finally:
        if twin is not None:
            twin.close()


def test_open_identifies_and_does_not_move(stage):
    assert stage.info is not None and stage.info.serial_number
    before = stage.position_mm()
    assert not stage.state().moving and not stage.moving
    assert stage.position_mm() == before


def test_moves_need_homing_first(stage):
    if not stage.settings.require_homed or stage.state().homed:
        pytest.skip("this stage is homed already or its settings allow moves before homing")
    with pytest.raises(NotHomed, match="not homed"):
        stage.move_to(sum(stage.settings.soft_limits_mm) / 2)


def test_a_move_within_the_limits_reaches_the_position(stage):
    stage.home()
    low, high = stage.settings.soft_limits_mm
    tolerance = stage.settings.arrival_tolerance_mm
    target_mm = low + 0.2 * (high - low)
    assert stage.move_to(target_mm).position_mm == pytest.approx(target_mm, abs=tolerance)
    assert stage.move_by(0.5).position_mm == pytest.approx(target_mm + 0.5, abs=tolerance)
    assert stage.position_mm() == pytest.approx(target_mm + 0.5, abs=tolerance)


def test_a_target_outside_the_soft_limits_is_refused_and_nothing_moves(stage):
    stage.home()
    low, high = stage.settings.soft_limits_mm
    before = stage.position_mm()
    for target_mm in (high + 1.0, low - 1.0, float("nan")):
        with pytest.raises(SoftLimitError, match=r"outside the soft limits"):
            stage.move_to(target_mm)
    with pytest.raises(SoftLimitError):
        stage.move_by(high - low + 1.0)
    assert isinstance(SoftLimitError("x"), ValueError)  # bad input, not a bench failure
    assert not stage.state().moving and stage.position_mm() == before


def test_reconnect_finds_the_same_unit(stage):
    serial = stage.info.serial_number
    stage.reconnect()
    assert stage.info.serial_number == serial and not stage.moving
