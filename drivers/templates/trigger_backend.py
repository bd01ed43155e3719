"""Template: a trigger backend: the camera's exposure-active output read on a host input
(`[devices.trigger] source = "camera_exposure"`). The base class keeps the timing every line
shares: the SLM's frame write waits while the input reads high, TriggerTimeout naming the trigger
and its timeout when it stays high, LinkDown on a closed line. Prove a filled-in copy with the
trigger's contract suite (tests/drivers/contracts/test_trigger.py: add its set-up as a param, or
name it in NHFD_TEST_TRIGGER=class:your.module.YourLine:device).

A host input cannot hold off the camera's next exposure the way the model's lock does: wire the
camera to be triggered after the write (or by the SLM), or accept that an exposure may start
right after the line was seen low. The frame-flip wiring ("slm_flip") needs no host input: it is
the camera backend's hardware trigger mode (TriggerMode/TriggerSource/TriggerDelay).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from nhfd.drivers.trigger import TriggerLine


class MyExposureInput(TriggerLine):
    """The camera's exposure-active output on an input of the host: fill in open, close, and
    read the level."""

    poll_s = 0.001  # how often a waiting write re-reads the input (s)

    def __init__(self, device: str, *, timeout_ms: float = 500.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        # What _do_open needs, before super().__init__(), which opens the line.
        self.device = device
        super().__init__("camera_exposure", timeout_ms=timeout_ms, clock=clock)

    def _do_open(self) -> None:
        # Open the input (a GPIO line through libgpiod, a serial port's CTS or DSR through
        # pyserial as nhfd.drivers.keyswitch does); a failure raises PortNotFound or DeviceError.
        raise NotImplementedError

    def _do_close(self) -> None:
        raise NotImplementedError  # release the input (idempotent)

    def _input_high(self) -> bool:
        # The level now: True while the camera exposes (mind an inverting opto-coupler). A read
        # that fails (a vanished port) raises DeviceError (PortVanished), never OSError: the
        # write it gates then fails instead of going ahead blind.
        raise NotImplementedError
