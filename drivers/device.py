"""The lifecycle every device kind shares: open, close, identify, link check, reconnect.

`Device` is the base of `SLM`, `Camera`, `Laser`, `Stage` and `Navigator` (python-microscope
style: the public methods live here once, a backend fills in hooks):

  _do_open()        open the link / output / device; no writes that change what it does
  _do_close()       release it (idempotent)
  _do_identify()    who is there (a laser's device type, a stage's serial and model), read
                    without writing; None for kinds with nothing to ask
  _do_check_link()  False once the link is known to be gone (a vanished port)

A device kind overrides `open()` / `close()` to add its own rules around those hooks (a laser
switches every channel off, a stage stops a pending motion) and `_reopen()` / `_retry_on` to
take part in `reconnect()`: the one back-off loop for every device with `reconnect_attempts`,
`reconnect_backoff_s` and `reconnect_backoff_max_s` in its settings.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Self

from .errors import LinkDown, TransportError

log = logging.getLogger(__name__)


class Device:
    """Open/close as a context manager, the backend hooks, and reconnect with back-off."""

    settings: Any

    # What a failed reconnect attempt may raise and still be retried; anything else (WrongDevice
    # above all) ends the reconnect at once.
    _retry_on: tuple[type[BaseException], ...] = (TransportError,)

    @property
    def name(self) -> str:
        """The device's name in messages: its class name unless a backend says more."""
        return type(self).__name__

    def open(self) -> Self:
        """Open the device (`_do_open`); returns it, for `with`."""
        self._do_open()
        return self

    def close(self) -> None:
        """Close the device (`_do_close`)."""
        self._do_close()

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- reconnect -----------------------------------------------------------------------------

    def reconnect(self) -> None:
        """Reopen after a link loss: up to settings.reconnect_attempts tries, sleeping
        reconnect_backoff_s, then twice that, ... (at most reconnect_backoff_max_s) between
        them. Raises LinkDown naming the last failure when every attempt failed."""
        s = self.settings
        self._before_reconnect()
        self._close_quietly()
        delay = s.reconnect_backoff_s
        last: BaseException | None = None
        for attempt in range(1, s.reconnect_attempts + 1):
            try:
                self._reopen()
                log.info("%s: reconnected on attempt %d", self.name, attempt)
                return
            except self._retry_on as exc:
                last = exc
                self._close_quietly()
                log.warning("%s: reconnect attempt %d failed: %s", self.name, attempt, exc)
            if attempt < s.reconnect_attempts:
                time.sleep(min(delay, s.reconnect_backoff_max_s))
                delay *= 2
        raise LinkDown(f"{self.name}: no link after {s.reconnect_attempts} attempts: {last}")

    def _before_reconnect(self) -> None:
        """Forget state a reconnect must not carry over (arming, a pending motion)."""

    def _reopen(self) -> None:
        """One reconnect attempt."""
        self.open()

    def _close_quietly(self) -> None:
        try:
            self._do_close()
        except Exception as exc:
            log.warning("%s: disconnect: %s", self.name, exc)

    # -- backend hooks -------------------------------------------------------------------------

    def _do_open(self) -> None:
        pass

    def _do_close(self) -> None:
        pass

    def _do_identify(self) -> Any:
        return None

    def _do_check_link(self) -> bool:
        return True
