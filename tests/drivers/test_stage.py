"""The APT stage driver against the KDC101 twin; motion runs on a clock the test holds."""

from __future__ import annotations

import threading
import time

import pytest

from nhfd.drivers import apt
from nhfd.drivers.errors import LinkDown, ReplyTimeout, WrongDevice
from nhfd.drivers.stage import (
    AptDeviceError,
    AptStage,
    LimitSwitchHit,
    MotionError,
    MotionTimeout,
    MoveStopped,
    NotHomed,
    SoftLimitError,
)
from nhfd.drivers.twins.apt_twin import AptTwin
from nhfd.drivers.twins.clock import ManualClock

M = apt.MsgId
MOVES = {M.MOT_MOVE_HOME, M.MOT_MOVE_ABSOLUTE, M.MOT_MOVE_RELATIVE}
CPM = 34554.96


def homed_stage(twin: AptTwin, clock: ManualClock, settings) -> AptStage:
    stage = AptStage(settings, twin.opener()).open()
    stage.home(wait=False)
    twin.wait_moving()
    clock.advance(10.0)
    stage.wait()
    return stage


def test_identifies_first_and_never_moves_at_start_up(apt_twin, stage_settings):
    with AptStage(stage_settings, apt_twin.opener()) as stage:
        assert stage.info.model == "KDC101" and stage.info.serial_number == "27000001"
        ids = apt_twin.received_ids()
        assert ids[0] == M.HW_REQ_INFO
        assert not set(ids) & MOVES
        assert apt_twin.position_mm == pytest.approx(7.0) and not apt_twin.moving
        # The RTS pulse and latency timer were asked for; a pty records them as no-ops.
        calls = stage._transport.line_control_calls
        assert calls[0].rts_pulse and calls[0].latency_timer_ms == 1
        # Velocity parameters were written and read back in APT units.
        assert apt_twin.vel_params == (0, stage_settings.acceleration_units,
                                       stage_settings.velocity_units)
        assert stage.state().enabled
    assert apt_twin.received_ids()[-1] == M.HW_DISCONNECT


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"model": "BSC201"}, "BSC201"), ({"serial_number": 83000007}, "83000007")],
)
def test_refuses_a_controller_the_settings_do_not_name(stage_settings, kwargs, match):
    settings = stage_settings.model_copy(update={"usb_serial": "27000001"})
    with AptTwin(**kwargs) as twin:
        with pytest.raises(WrongDevice, match=match):
            AptStage(settings, twin.opener()).open()
        assert twin.received_ids() == [M.HW_REQ_INFO]


def test_moves_need_homing_and_homing_reaches_zero(apt_twin, clock, stage_settings):
    with AptStage(stage_settings, apt_twin.opener()) as stage:
        with pytest.raises(NotHomed):
            stage.move_to(5.0)
        assert not set(apt_twin.received_ids()) & {M.MOT_MOVE_ABSOLUTE}
        stage.home(wait=False)
        apt_twin.wait_moving()
        clock.advance(1.0)  # 2 mm/s toward the reverse switch: 2 mm done, not home yet
        assert apt_twin.position_mm == pytest.approx(5.0)
        assert stage.state().homing
        clock.advance(10.0)
        state = stage.wait()
        assert state.homed and state.position_mm == 0.0


def test_move_absolute_and_relative_take_time_on_the_clock(apt_twin, clock, stage_settings):
    with homed_stage(apt_twin, clock, stage_settings) as stage:
        stage.move_to(12.5, wait=False)
        apt_twin.wait_moving()
        clock.advance(2.0)  # 2 mm/s
        assert apt_twin.position_mm == pytest.approx(4.0)
        assert stage.state().moving
        clock.advance(10.0)
        state = stage.wait()
        assert state.position_mm == pytest.approx(12.5, abs=1 / CPM)
        stage.move_by(-2.5, wait=False)
        apt_twin.wait_moving()
        clock.advance(5.0)
        assert stage.wait().position_mm == pytest.approx(10.0, abs=1 / CPM)
    rel = [m for _, m in apt_twin.received if m.msg_id == M.MOT_MOVE_RELATIVE]
    assert apt.MOVE.unpack(rel[0].data) == (1, -round(2.5 * CPM))


def test_stop_mid_move_from_another_thread(apt_twin, clock, stage_settings):
    with homed_stage(apt_twin, clock, stage_settings) as stage:
        outcome: dict[str, BaseException] = {}

        def mover():
            try:
                stage.move_to(20.0, timeout_s=5.0)
            except BaseException as exc:
                outcome["exc"] = exc

        worker = threading.Thread(target=mover)
        worker.start()
        apt_twin.wait_moving()
        clock.advance(3.0)
        stage.stop()  # while the other thread waits for the move
        worker.join(timeout=5)
        assert isinstance(outcome.get("exc"), MoveStopped)
        assert "6.0000 mm" in str(outcome["exc"])
        clock.advance(30.0)
        assert apt_twin.position_mm == pytest.approx(6.0) and not apt_twin.moving
        stage.stop()  # stopping a stage at rest is always allowed


def test_soft_limits_refuse_before_anything_is_sent(apt_twin, clock, stage_settings):
    with homed_stage(apt_twin, clock, stage_settings) as stage:
        sent = len(apt_twin.received)
        for target in (25.01, -0.5, float("nan")):
            with pytest.raises(SoftLimitError, match="soft limits"):
                stage.move_to(target)
        stage.move_to(20.0, wait=False)
        apt_twin.wait_moving()
        clock.advance(20.0)
        stage.wait()
        n = len(apt_twin.received)
        with pytest.raises(SoftLimitError):
            stage.move_by(6.0)
        ids = [m.msg_id for _, m in apt_twin.received[sent:]]
        assert ids.count(M.MOT_MOVE_ABSOLUTE) == 1
        assert M.MOT_MOVE_RELATIVE not in [m.msg_id for _, m in apt_twin.received[n:]]


def test_a_hardware_limit_switch_ends_a_move_with_an_error(apt_twin, clock, stage_settings):
    wide = stage_settings.model_copy(update={"soft_limits_mm": [-5.0, 40.0]})
    with homed_stage(apt_twin, clock, wide) as stage:
        stage.move_to(30.0, wait=False)
        apt_twin.wait_moving()
        clock.advance(60.0)
        with pytest.raises(LimitSwitchHit, match=r"25\.0000 mm"):
            stage.wait()
        assert stage.state().limit_cw


@pytest.mark.parametrize("target_mm", [25.0, 0.0])
def test_a_move_to_either_end_of_the_travel_arrives(clock, stage_settings, target_mm):
    # home_offset_mm = 0: homing leaves the reverse switch pressed at 0 mm, as a unit whose home
    # offset is zero does; the forward switch sits at the default soft limit, 25 mm.
    with AptTwin(clock=clock, home_offset_mm=0.0) as twin:
        with homed_stage(twin, clock, stage_settings) as stage:
            assert stage.settings.soft_limits_mm == [0.0, 25.0]
            stage.move_to(12.0, wait=False)
            twin.wait_moving()
            clock.advance(10.0)
            stage.wait()
            stage.move_to(target_mm, wait=False)
            twin.wait_moving()
            clock.advance(10.0)
            state = stage.wait()  # no LimitSwitchHit: the switch is pressed at the target
            assert state.position_mm == target_mm and state.at_limit
            assert (state.limit_cw, state.limit_ccw) == (target_mm == 25.0, target_mm == 0.0)
            assert twin.position_mm == pytest.approx(target_mm)
            stage.move_by(1.0 if target_mm == 0.0 else -1.0, wait=False)  # and moves on
            twin.wait_moving()
            clock.advance(10.0)
            assert not stage.wait().at_limit


def test_a_switch_short_of_a_relative_target_is_still_a_limit_hit(clock, stage_settings):
    with AptTwin(clock=clock, travel_mm=24.0) as twin:
        with homed_stage(twin, clock, stage_settings) as stage:
            stage.move_by(25.0, wait=False)  # inside the soft limits, past the switch
            twin.wait_moving()
            clock.advance(30.0)
            with pytest.raises(LimitSwitchHit, match=r"24\.0000 mm"):
                stage.wait()


def test_wait_is_bounded_and_stops_the_stage(apt_twin, clock, stage_settings):
    with homed_stage(apt_twin, clock, stage_settings) as stage:
        start = time.monotonic()
        with pytest.raises(MotionTimeout, match="stop sent"):
            stage.move_to(20.0, timeout_s=0.3)  # the clock stands still: never arrives
        assert time.monotonic() - start < 1.5
        apt_twin.wait_for(lambda: not apt_twin._motion)
        assert M.MOT_MOVE_STOP in apt_twin.received_ids()


def test_status_updates_are_kept_alive(stage_settings):
    settings = stage_settings.model_copy(update={"keepalive_period_s": 0.05})
    lazy = stage_settings.model_copy(update={"keepalive_period_s": 5.0})
    counts = []
    for s in (settings, lazy):
        with AptTwin(update_period_s=0.01, unacked_updates_max=5) as twin, \
                AptStage(s, twin.opener()):
            time.sleep(0.5)
            counts.append((twin.updates_sent, twin.acks))
    (kept, acks), (starved, _) = counts
    assert acks >= 4 and kept > 10
    assert starved <= 6  # without acknowledgements the controller stops after 5


def test_garbage_and_short_replies_are_resynchronised(apt_twin, clock, stage_settings):
    apt_twin.inject("garbage", msg_id=M.HW_REQ_INFO)
    apt_twin.inject("short_reply", msg_id=M.MOT_REQ_VELPARAMS, keep_bytes=9)
    with AptStage(stage_settings, apt_twin.opener()) as stage:
        assert stage.stream.discarded >= 10
        assert apt_twin.received_ids().count(M.MOT_REQ_VELPARAMS) == 2
        apt_twin.inject("garbage", msg_id=M.MOT_REQ_DCSTATUSUPDATE)
        assert stage.position_mm() == pytest.approx(7.0, abs=1 / CPM)


def test_a_missing_reply_is_resent_once_then_times_out(apt_twin, stage_settings):
    with AptStage(stage_settings, apt_twin.opener()) as stage:
        apt_twin.inject("no_reply", msg_id=M.MOT_REQ_DCSTATUSUPDATE)
        assert stage.position_mm() == pytest.approx(7.0, abs=1 / CPM)
        apt_twin.inject("no_reply", msg_id=M.MOT_REQ_DCSTATUSUPDATE, count=2)
        with pytest.raises(ReplyTimeout, match="status block"):
            stage.position_mm()


def test_controller_errors_name_the_code_and_the_message(apt_twin, clock, stage_settings):
    with homed_stage(apt_twin, clock, stage_settings) as stage:
        apt_twin.inject("error", msg_id=M.MOT_MOVE_ABSOLUTE, code=43, notes="encoder fault")
        with pytest.raises(AptDeviceError,
                           match="controller error 43 about MOT_MOVE_ABSOLUTE: encoder fault"):
            stage.move_to(3.0)
        apt_twin.inject("motion_error", msg_id=M.MOT_MOVE_ABSOLUTE)
        stage.move_to(4.0, wait=False)
        apt_twin.wait_moving()
        clock.advance(5.0)
        with pytest.raises(MotionError):
            stage.wait()


def test_a_port_vanishing_mid_move_raises_and_reconnect_reidentifies(apt_twin, clock,
                                                                     stage_settings):
    stage = homed_stage(apt_twin, clock, stage_settings)
    try:
        stage.move_to(10.0, wait=False)
        apt_twin.wait_moving()
        clock.advance(2.0)
        apt_twin.vanish()
        with pytest.raises(LinkDown, match="vanished"):
            stage.wait()
        with pytest.raises(LinkDown):
            stage.stop()
        clock.advance(10.0)
        threading.Timer(0.15, apt_twin.replug).start()
        n = len(apt_twin.received)
        stage.reconnect()
        after = [m.msg_id for _, m in apt_twin.received[n:]]
        assert after[0] == M.HW_REQ_INFO and not set(after) & MOVES
        state = stage.state()
        assert state.homed and state.position_mm == pytest.approx(10.0, abs=1 / CPM)
    finally:
        stage.close()


def test_a_port_vanishing_during_a_command_raises_clearly(apt_twin, stage_settings):
    stage = AptStage(stage_settings, apt_twin.opener()).open()
    apt_twin.inject("vanish", msg_id=M.MOT_REQ_DCSTATUSUPDATE)
    with pytest.raises(LinkDown, match="vanished"):
        stage.state()
    stage.close()
    with pytest.raises(LinkDown, match="4 attempts"):
        stage.reconnect()


def test_closing_during_a_move_stops_it(apt_twin, clock, stage_settings):
    stage = homed_stage(apt_twin, clock, stage_settings)
    stage.move_to(15.0, wait=False)
    apt_twin.wait_moving()
    clock.advance(1.0)
    stage.close()
    apt_twin.wait_for(lambda: not apt_twin._motion)
    clock.advance(20.0)
    assert apt_twin.position_mm == pytest.approx(2.0)


def test_an_adapter_without_modem_lines_is_named_and_the_reset_can_be_skipped(apt_twin,
                                                                           stage_settings):
    from nhfd.drivers.transport import LineControlError, SerialTransport

    # pyserial on the twin's pty: the real serial backend, on a line without RTS.
    def opener():
        return SerialTransport(apt_twin.port_path, stage_settings.baud)

    with pytest.raises(LineControlError) as info:
        AptStage(stage_settings, opener).open()
    assert str(info.value) == (
        f"stage {apt_twin.port_path}: the line reset (RTS pulse and buffer purge after open) "
        "failed: Inappropriate ioctl for device; the adapter has no RTS line?; for an adapter "
        "without modem-control lines set rts_reset = false in [devices.apt]")
    assert apt_twin.received_ids() == []  # nothing was sent
    skip = stage_settings.model_copy(update={"rts_reset": False})
    with AptStage(skip, opener) as stage:
        assert stage.info.serial_number == "27000001" and stage.state().enabled
