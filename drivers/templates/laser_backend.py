"""Template: a laser backend. The base class does arming, caps, read-back and all-off."""

from __future__ import annotations

from nhfd.device_settings import LaserSettings
from nhfd.drivers.laser import Laser
from nhfd.drivers.transport import Opener, Transport, serial_opener


class MyLaser(Laser):
    """A laser backend to fill in: identify, read and write one channel's enable and power (%)."""

    def __init__(self, settings: LaserSettings, opener: Opener | None = None) -> None:
        super().__init__(settings)
        # Real port by path or USB serial number; a test passes its twin's opener instead.
        self._opener = opener or serial_opener(settings.port, settings.usb_serial,
                                               baud=settings.baud)
        self._transport: Transport | None = None

    def _do_open(self) -> None:
        self._transport = self._opener()  # no writes to the device here

    def _do_close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    def _do_identify(self) -> int:
        # Read the device type WITHOUT writing anything; the base compares it with the
        # settings' device_type and refuses anything else.
        raise NotImplementedError

    def _write_enable(self, channel: str, on: bool) -> None:
        raise NotImplementedError

    def _read_enable(self, channel: str) -> bool:
        raise NotImplementedError

    def _write_power(self, channel: str, power_pct: float) -> None:
        # power_pct is already clamped to the channel's cap by the base class.
        raise NotImplementedError

    def _read_power(self, channel: str) -> float:
        raise NotImplementedError
