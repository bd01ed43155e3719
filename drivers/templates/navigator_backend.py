"""Template: a navigator backend. The base class applies dead zone and scaling."""

from __future__ import annotations

from nhfd.drivers.navigator import Navigator, RawState


class MyNavigator(Navigator):
    """A navigator backend to fill in: return the latest raw axis counts and buttons."""

    def _do_open(self) -> None:
        pass  # match the device by vendor AND product id

    def _do_close(self) -> None:
        pass

    def _poll(self) -> RawState:
        # Consume every waiting report (e.g. with navigator.parse_report) and return the latest
        # raw axes (x, y, z, rx, ry, rz counts) and button bitmask, without blocking long.
        raise NotImplementedError
