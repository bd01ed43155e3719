"""systemd's notify protocol without a systemd dependency: datagrams to $NOTIFY_SOCKET.

READY=1 once the lasers are read back off, STATUS=... for `systemctl status`, WATCHDOG=1 from the
control loop (so a hung loop stops feeding it and systemd restarts the unit, after which the stop
hook runs `nhfd laser-off`), STOPPING=1 at shutdown. Without $NOTIFY_SOCKET every call is a no-op.
"""

from __future__ import annotations

import contextlib
import os
import socket
import time
from collections.abc import Mapping


class Notifier:
    """systemd's notify protocol (the module's docstring) to $NOTIFY_SOCKET of `env` (default the
    process's environment); the watchdog interval from WATCHDOG_USEC when WATCHDOG_PID is this
    process. Without $NOTIFY_SOCKET every call is a no-op."""
    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        address = env.get("NOTIFY_SOCKET", "")
        # '@' names a Linux abstract socket: its first byte is NUL on the wire.
        self._address = "\0" + address[1:] if address.startswith("@") else address
        self._sock: socket.socket | None = None
        if self._address:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.watchdog_s = self._watchdog_interval(env)
        self._last_watchdog = 0.0

    @staticmethod
    def _watchdog_interval(env: Mapping[str, str]) -> float | None:
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        if not usec.isdigit() or (pid and pid != str(os.getpid())):
            return None
        return int(usec) / 1e6

    @property
    def enabled(self) -> bool:
        """Whether there is a $NOTIFY_SOCKET to send to."""
        return self._sock is not None

    def send(self, **fields: str) -> None:
        """One datagram of `KEY=value` lines; a socket error is ignored (the service manager's
        socket never takes the daemon down)."""
        if self._sock is None:
            return
        text = "\n".join(f"{k}={v}" for k, v in fields.items())
        # Never let the service manager's socket take the daemon down.
        with contextlib.suppress(OSError):
            self._sock.sendto(text.encode(), self._address)

    def ready(self, status: str) -> None:
        """READY=1 with `status`: once the lasers are read back off."""
        self.send(READY="1", STATUS=status)

    def status(self, status: str) -> None:
        """STATUS=`status`, what `systemctl status` shows."""
        self.send(STATUS=status)

    def stopping(self, status: str = "stopping: lasers off") -> None:
        """STOPPING=1 with `status`, at shutdown."""
        self.send(STOPPING="1", STATUS=status)

    def watchdog(self, now: float | None = None) -> None:
        """Feed at half the interval systemd asked for."""
        if self.watchdog_s is None:
            return
        now = time.monotonic() if now is None else now
        if now - self._last_watchdog >= self.watchdog_s / 2:
            self._last_watchdog = now
            self.send(WATCHDOG="1")

    def close(self) -> None:
        """Close the socket; later calls are no-ops."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
