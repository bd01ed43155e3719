"""Template: a stage backend. The base class does soft limits, homing rules and timeouts."""

from __future__ import annotations

from nhfd.device_settings import StageSettings
from nhfd.drivers.stage import Outcome, Stage, StageInfo, StageState


class MyStage(Stage):
    """A stage backend to fill in: identify, start homing and moves (mm), stop, read the state, wait
    for the end."""

    def __init__(self, settings: StageSettings) -> None:
        super().__init__(settings)

    def _do_open(self) -> None:
        raise NotImplementedError  # open the transport; never move here

    def _do_close(self) -> None:
        raise NotImplementedError

    def _do_identify(self) -> StageInfo:
        # Ask the controller who it is; raise WrongDevice for a model the settings do not allow.
        raise NotImplementedError

    def _begin_home(self) -> None:
        raise NotImplementedError  # start homing and return at once

    def _begin_move_absolute(self, position_mm: float) -> None:
        raise NotImplementedError  # start the move and return at once

    def _begin_move_relative(self, distance_mm: float) -> None:
        raise NotImplementedError

    def _send_stop(self, immediate: bool) -> None:
        # Must work from any thread while another thread sits in _wait_motion.
        raise NotImplementedError

    def _read_state(self) -> StageState:
        raise NotImplementedError

    def _wait_motion(self, timeout_s: float) -> tuple[Outcome, StageState]:
        # Block until the motion ends ("completed", "stopped" or "homed"); raise ReplyTimeout
        # after timeout_s (the base then stops the stage).
        raise NotImplementedError
