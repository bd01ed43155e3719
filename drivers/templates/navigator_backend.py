"""Template: a navigator backend. The base class applies dead zone and scaling, refuses reads
once closed, and reconnects; prove a filled-in copy with the navigator's contract suite
(tests/drivers/contracts/test_navigator.py)."""

from __future__ import annotations

from nhfd.drivers.navigator import Navigator, RawState


class MyNavigator(Navigator):
    """A navigator backend to fill in: return the latest raw axis counts and buttons."""

    def _do_open(self) -> None:
        # Match the device by vendor AND product id; a failure to find or open it raises
        # PortNotFound. Start from self._at_rest() (zero axes, the buttons last seen): a puck
        # reports only what changes.
        pass

    def _do_close(self) -> None:
        pass  # release the device (idempotent)

    def _poll(self) -> RawState:
        # Consume every waiting report (e.g. with navigator.parse_report), calling
        # self._count_presses(state.buttons) after each one so that a press and release between
        # two reads still counts, and return the latest raw axes (x, y, z, rx, ry, rz counts)
        # and button bitmask, without blocking long. A read that fails (unplugged) raises
        # DeviceError (PortVanished), never OSError.
        raise NotImplementedError
