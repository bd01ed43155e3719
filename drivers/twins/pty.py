"""A protocol peer served from a thread on the master side of a pseudo-terminal pair.

The driver opens the slave path like a serial port (`PtyTransport`). The peer keeps its own slave
descriptor open so the pair survives the driver closing and reopening. `vanish()` closes both
ends, which is what an unplugged USB adapter looks like to the driver (reads hit end-of-file,
writes fail with EIO, the path disappears); `replug()` makes a new pair under a new path, and
`opener()` always opens the current one.

The serving thread sleeps in `select` until the driver writes, a lifecycle call wakes it (a pipe
of its own), or the peer's next timed event (`tick_period_s`): a twin with nothing timed costs no
CPU while it waits, where a fixed 2 ms poll cost about 1 % of a core per twin in an idle daemon.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable

from ..errors import PortNotFound
from ..transport import Opener, pty_opener
from .clock import Clock, real_clock

# How often a peer with timed state (motion, a test's manual clock) ticks.
TICK_S = 0.002


class PtyPeer(ABC):
    """A simulated device on the master side of a pseudo-terminal, served from a thread: a subclass
    answers `on_bytes` and, for timed state, `tick`."""

    def __init__(self, *, clock: Clock = real_clock) -> None:
        self.clock = clock
        self.lock = threading.RLock()
        self._master: int | None = None
        self._slave: int | None = None
        self._path: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._wake_r: int | None = None
        self._wake_w: int | None = None

    # -- lifecycle -----------------------------------------------------------------------------

    def start(self) -> PtyPeer:
        """Open the pty pair and start the serving thread; returns the peer."""
        self._open_pair()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._thread = threading.Thread(target=self._serve, name=type(self).__name__, daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the serving thread and close the pty pair."""
        self._stop.set()
        self.wake()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with self.lock:
            self._close_pair()
        for fd in (self._wake_r, self._wake_w):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._wake_r = self._wake_w = None

    def wake(self) -> None:
        """Wake the serving thread now (a change it must see before its next timed event)."""
        if self._wake_w is not None:
            with contextlib.suppress(OSError):  # full: it is awake already
                os.write(self._wake_w, b"\0")

    def __enter__(self) -> PtyPeer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def port_path(self) -> str:
        """The slave's path the driver opens; RuntimeError before `start` or while vanished."""
        if self._path is None:
            raise RuntimeError(f"{type(self).__name__}: not started, or the port has vanished")
        return self._path

    def opener(self) -> Opener:
        """Opens the current pty; PortNotFound while the port has vanished (like a USB port
        that is not plugged in)."""

        def current_path() -> str:
            if self._path is None:
                raise PortNotFound(f"{type(self).__name__}: port not present")
            return self._path

        return pty_opener(current_path)

    def vanish(self) -> None:
        """The port disappears (USB cable pulled)."""
        with self.lock:
            self._close_pair()
        self.wake()  # a descriptor closed under select() does not wake it

    def replug(self) -> str:
        """The port comes back (under a new path, as a re-enumerated USB device may)."""
        with self.lock:
            if self._master is None:
                self._open_pair()
            path = self.port_path
        self.wake()
        return path

    def wait_for(self, condition: Callable[[], bool], timeout_s: float = 2.0) -> None:
        """Until condition() holds (checked under the lock); TimeoutError after timeout_s.
        Tests use it to let the peer catch up with bytes already written to it."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self.lock:
                if condition():
                    return
            if time.monotonic() > deadline:
                raise TimeoutError(f"{type(self).__name__}: condition not met in {timeout_s} s")
            time.sleep(TICK_S)

    @property
    def present(self) -> bool:
        """Whether the port exists (started and not vanished)."""
        return self._master is not None

    # -- pair ----------------------------------------------------------------------------------

    def _open_pair(self) -> None:
        master, slave = os.openpty()
        # Raw: MeCom ends frames with \r, which a cooked line discipline would turn into \n.
        tty.setraw(slave)
        self._master, self._slave, self._path = master, slave, os.ttyname(slave)

    def _close_pair(self) -> None:
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = self._path = None

    def send(self, data: bytes) -> None:
        """Bytes to the driver (dropped while the port is absent)."""
        with self.lock:
            if self._master is None:
                return
            with contextlib.suppress(OSError):
                os.write(self._master, data)

    # -- serving -------------------------------------------------------------------------------

    def _serve(self) -> None:
        while not self._stop.is_set():
            with self.lock:
                period = self.tick_period_s()
            self._wait_readable(self._master, period, wake=True)
            data = b""
            with self.lock:
                # Read only under the lock, which vanish() closes the pair under: this never
                # reads a descriptor number that has since been reused for another file.
                master = self._master
                if master is not None and self._wait_readable(master, 0.0):
                    try:
                        data = os.read(master, 4096)
                    except OSError:
                        data = b""  # no slave open right now
                if data:
                    self.on_bytes(data)
                self.tick()

    def _wait_readable(self, fd: int | None, timeout_s: float | None = TICK_S,
                       wake: bool = False) -> bool:
        """Whether fd is readable within timeout_s (None: no limit); with `wake`, `wake()`
        ends the wait early."""
        fds = [f for f in (fd, self._wake_r if wake else None) if f is not None]
        try:
            ready = select.select(fds, [], [], timeout_s)[0] if fds else []
        except (OSError, ValueError):  # closed under us (vanish)
            ready = None
        if ready is None or not fds:
            self._stop.wait(TICK_S if timeout_s is None else timeout_s)
            return False
        if self._wake_r is not None and self._wake_r in ready:
            with contextlib.suppress(OSError):
                os.read(self._wake_r, 4096)
        return fd is not None and fd in ready

    def tick_period_s(self) -> float | None:
        """How long the peer may wait for bytes before its next `tick` (None: nothing timed;
        bytes or `wake()` only). Called with `self.lock` held. A peer that overrides `tick`
        ticks every few ms unless it says otherwise."""
        return None if type(self).tick is PtyPeer.tick else TICK_S

    @abstractmethod
    def on_bytes(self, data: bytes) -> None:
        """Bytes from the driver (called with `self.lock` held)."""

    def tick(self) -> None:  # noqa: B027 - optional hook
        """Called every few ms with `self.lock` held: advance simulated state to clock()."""
