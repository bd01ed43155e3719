"""The laser guardian: a small process that owns the laser port and turns every channel off when
the daemon's heartbeat stops.

Software in the daemon cannot act when the daemon is SIGKILLed, runs out of memory, crashes in
native code or hangs. The guardian can: it imports nothing heavy (no torch, numba, onnxruntime),
holds the laser port exclusively, and listens on a local Unix socket (mode 0660) for one JSON
object per line. A client that sends `heartbeat` becomes a *controller*; when a controller's
connection closes (the daemon died: the kernel closes its socket at once) or no heartbeat arrives
for `heartbeat_timeout_s` (the daemon hangs), the guardian disarms, switches every channel off and
reads back that they are off. Emission needs a live heartbeat and a person's arming.

The daemon should send heartbeats from its main loop, not from a helper thread: a thread would
keep beating while the loop that drives the bench is stuck.

Requests (replies are {"ok": true, ...} or {"ok": false, "error": "...", "type": "..."}):
  hello | heartbeat | arm {duration_s} | disarm | power {channel, power_pct} |
  enable {channel, on} | off | status | clear_fault

`nhfd laser-off` sends `off` here, or opens the port itself when no guardian answers.
Run: `python -m nhfd.drivers.guardian --settings-json '{...}' [--port PATH] [--socket PATH]`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import selectors
import socket
import stat
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import DeviceError, TransportError
from .laser import Laser, MecomLaser, install_signal_handlers
from .settings import LaserSettings

log = logging.getLogger(__name__)

READY = "ready"
_MAX_LINE = 65536


def default_socket_path() -> Path:
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    base = Path(runtime) / "nhfd" if runtime else Path(f"/tmp/nhfd-{os.getuid()}")
    return base / "laser.sock"


def socket_path_for(settings: LaserSettings) -> Path:
    return Path(settings.guardian.socket_path) if settings.guardian.socket_path else (
        default_socket_path()
    )


class GuardianError(DeviceError):
    """The guardian refused a request or the laser failed; the message says why."""


class GuardianUnavailable(GuardianError):
    """No guardian answers on the socket."""


# ---------------------------------------------------------------------------------------- server


@dataclass
class _Client:
    sock: socket.socket
    buffer: bytearray = field(default_factory=bytearray)
    controller: bool = False


class Guardian:
    """Serves one laser on a Unix socket; call `serve()` with the laser open."""

    def __init__(
        self,
        laser: Laser,
        socket_path: str | os.PathLike[str],
        *,
        heartbeat_timeout_s: float,
        tick_s: float,
    ) -> None:
        self.laser = laser
        self.socket_path = Path(socket_path)
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.tick_s = tick_s
        self._last_heartbeat: float | None = None
        self._sel = selectors.DefaultSelector()
        self._server: socket.socket | None = None
        self._clients: dict[int, _Client] = {}
        self._next_link_try = 0.0
        self._link_retry_s = 0.0

    # -- socket --------------------------------------------------------------------------------

    def listen(self) -> None:
        path = self.socket_path
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        if path.exists() or path.is_symlink():
            if not stat.S_ISSOCK(path.lstat().st_mode):
                raise GuardianError(f"{path} exists and is not a socket")
            with contextlib.suppress(GuardianUnavailable):
                GuardianClient(path, timeout_s=0.5).close()
                raise GuardianError(f"another guardian is listening on {path}")
            path.unlink()
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old_umask = os.umask(0o117)  # socket file mode 0660: owner and the lab group
        try:
            server.bind(str(path))
        finally:
            os.umask(old_umask)
        server.listen(8)
        server.setblocking(False)
        self._server = server
        self._sel.register(server, selectors.EVENT_READ)

    def close(self) -> None:
        for client in list(self._clients.values()):
            self._drop(client, trip=False)
        if self._server is not None:
            self._sel.unregister(self._server)
            self._server.close()
            self._server = None
            with contextlib.suppress(OSError):
                self.socket_path.unlink()
        self._sel.close()

    # -- loop ----------------------------------------------------------------------------------

    def serve(self, stop_after_s: float | None = None) -> None:
        """Run until interrupted (SIGTERM/SIGINT raise) or stop_after_s has passed."""
        end = None if stop_after_s is None else time.monotonic() + stop_after_s
        while end is None or time.monotonic() < end:
            self.step()

    def step(self) -> None:
        for key, _ in self._sel.select(timeout=self.tick_s):
            if key.fileobj is self._server:
                self._accept()
            else:
                self._receive(self._clients[key.fd])
        self._watchdog()

    def _accept(self) -> None:
        assert self._server is not None
        with contextlib.suppress(BlockingIOError):
            sock, _ = self._server.accept()
            sock.settimeout(0.5)  # replies are small; a client that does not read is dropped
            client = _Client(sock)
            self._clients[sock.fileno()] = client
            self._sel.register(sock, selectors.EVENT_READ)

    def _receive(self, client: _Client) -> None:
        try:
            data = client.sock.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._drop(client, trip=client.controller)
            return
        client.buffer += data
        while (end := client.buffer.find(b"\n")) >= 0:
            line = bytes(client.buffer[:end])
            del client.buffer[: end + 1]
            reply = self._handle(client, line)
            try:
                client.sock.sendall(json.dumps(reply).encode() + b"\n")
            except OSError:
                self._drop(client, trip=client.controller)
                return
        if len(client.buffer) > _MAX_LINE:
            self._drop(client, trip=client.controller)

    def _drop(self, client: _Client, *, trip: bool) -> None:
        fd = client.sock.fileno()
        if fd in self._clients:
            self._sel.unregister(client.sock)
            del self._clients[fd]
        client.sock.close()
        if trip:
            self._trip("a controller disconnected")

    def _watchdog(self) -> None:
        laser = self.laser
        if not laser.connected:
            self._retry_link()
            return
        try:
            laser.service()
        except DeviceError as exc:
            log.error("guardian: arming expiry: %s", exc)
        last = self._last_heartbeat
        if last is not None and time.monotonic() - last > self.heartbeat_timeout_s:
            self._trip(f"no heartbeat for {self.heartbeat_timeout_s:g} s")

    def _trip(self, reason: str) -> None:
        """Session over: disarm, all off with read-back."""
        self._last_heartbeat = None
        log.warning("guardian: %s: disarming, all channels off", reason)
        try:
            self.laser.disarm()
            log.warning("guardian: all channels off (read back)")
        except DeviceError as exc:
            log.error("guardian: ALL-OFF NOT CONFIRMED: %s", exc)

    def _retry_link(self) -> None:
        """The port vanished: keep trying to reopen (which re-identifies and switches all off)."""
        now = time.monotonic()
        if now < self._next_link_try:
            return
        s = self.laser.settings
        try:
            self.laser.open()
            log.warning("guardian: laser link back, all channels off")
            self._link_retry_s = 0.0
        except (TransportError, DeviceError) as exc:
            self._link_retry_s = min(max(self._link_retry_s * 2, s.reconnect_backoff_s),
                                     s.reconnect_backoff_max_s)
            self._next_link_try = now + self._link_retry_s
            log.error("guardian: laser link down (%s); next try in %.1f s", exc,
                      self._link_retry_s)

    # -- requests ------------------------------------------------------------------------------

    def _session_alive(self) -> bool:
        last = self._last_heartbeat
        return last is not None and time.monotonic() - last <= self.heartbeat_timeout_s

    def _handle(self, client: _Client, line: bytes) -> dict[str, Any]:
        try:
            msg = json.loads(line)
            if not isinstance(msg, dict) or not isinstance(msg.get("op"), str):
                raise ValueError('a request is a JSON object with an "op"')
            return {"ok": True, **self._dispatch(client, msg)}
        except (DeviceError, ValueError, TypeError, KeyError) as exc:
            return {"ok": False, "error": str(exc), "type": type(exc).__name__}

    def _dispatch(self, client: _Client, msg: dict[str, Any]) -> dict[str, Any]:
        laser, op = self.laser, msg["op"]
        if op == "hello":
            s = laser.settings
            return {"channels": list(laser.channels), "max_power_pct": s.max_power_pct,
                    "heartbeat_timeout_s": self.heartbeat_timeout_s, "pid": os.getpid()}
        if op == "heartbeat":
            client.controller = True
            self._last_heartbeat = time.monotonic()
            return {"armed": laser.armed, "armed_remaining_s": laser.armed_remaining_s,
                    "fault": laser.fault, "connected": laser.connected}
        if op == "off":
            # Raises (and the client hears why) unless every channel read back off.
            if laser.connected:
                laser.disarm()
            else:
                laser.all_off()
            return {"off": True}
        if op == "disarm":
            laser.disarm()
            return {}
        if op == "status":
            st = laser.status()
            return {"device_status": st.device_status_name, "armed": st.armed,
                    "armed_remaining_s": st.armed_remaining_s, "fault": st.fault,
                    "channels": {ch: {"enabled": c.enabled, "power_pct": c.power_pct}
                                 for ch, c in st.channels.items()}}
        if op == "clear_fault":
            laser.clear_fault()
            return {}
        if op in ("arm", "power", "enable"):
            if not self._session_alive():
                raise GuardianError("no live heartbeat: send heartbeat first (and keep sending)")
            if op == "arm":
                laser.arm(float(msg["duration_s"]))
                return {"armed_remaining_s": laser.armed_remaining_s}
            if op == "power":
                return {"power_pct": laser.set_power(str(msg["channel"]),
                                                     float(msg["power_pct"]))}
            on = msg.get("on", True)
            if not isinstance(on, bool):
                raise ValueError('"on" must be true or false')
            laser.enable(str(msg["channel"]), on)
            return {}
        raise ValueError(f"unknown op {op!r}")


# ---------------------------------------------------------------------------------------- client


class GuardianClient:
    """The daemon's (and `nhfd laser-off`'s) side of the socket. Every call is bounded."""

    def __init__(self, socket_path: str | os.PathLike[str] | None = None, *,
                 timeout_s: float = 2.0) -> None:
        self.socket_path = Path(socket_path) if socket_path else default_socket_path()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout_s)
        self._buffer = bytearray()
        try:
            self._sock.connect(str(self.socket_path))
        except OSError as exc:
            self._sock.close()
            raise GuardianUnavailable(
                f"no laser guardian at {self.socket_path} ({exc.strerror or exc})"
            ) from None

    def call(self, op: str, **params: Any) -> dict[str, Any]:
        try:
            self._sock.sendall(json.dumps({"op": op, **params}).encode() + b"\n")
            while (end := self._buffer.find(b"\n")) < 0:
                chunk = self._sock.recv(4096)
                if not chunk:
                    raise GuardianUnavailable(f"guardian at {self.socket_path} hung up")
                self._buffer += chunk
        except TimeoutError:
            raise GuardianUnavailable(f"guardian at {self.socket_path} did not answer") from None
        except OSError as exc:
            raise GuardianUnavailable(f"guardian at {self.socket_path}: {exc}") from None
        reply = json.loads(bytes(self._buffer[:end]))
        del self._buffer[: end + 1]
        if not reply.pop("ok", False):
            raise GuardianError(f"guardian: {reply.get('type', 'error')}: {reply.get('error')}")
        return reply

    def hello(self) -> dict[str, Any]:
        return self.call("hello")

    def heartbeat(self) -> dict[str, Any]:
        return self.call("heartbeat")

    def arm(self, duration_s: float) -> None:
        self.call("arm", duration_s=duration_s)

    def disarm(self) -> None:
        self.call("disarm")

    def set_power(self, channel: str, power_pct: float) -> float:
        return float(self.call("power", channel=channel, power_pct=power_pct)["power_pct"])

    def enable(self, channel: str, on: bool = True) -> None:
        self.call("enable", channel=channel, on=on)

    def all_off(self) -> None:
        self.call("off")

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> GuardianClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ------------------------------------------------------------------------------------- processes


def spawn_guardian(
    settings: LaserSettings,
    *,
    port: str | None = None,
    socket_path: str | os.PathLike[str] | None = None,
    stderr: Any = None,
    python: str = sys.executable,
) -> subprocess.Popen[str]:
    """Start a guardian process and wait (bounded by guardian.start_timeout_s) until it has
    identified the laser, switched it off and listens. The caller owns the process."""
    args = [python, "-m", "nhfd.drivers.guardian", "--settings-json",
            settings.model_dump_json()]
    if port:
        args += ["--port", port]
    if socket_path:
        args += ["--socket", str(socket_path)]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=stderr, text=True)
    assert proc.stdout is not None
    timeout_s = settings.guardian.start_timeout_s
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if sel.select(timeout=timeout_s):
            line = proc.stdout.readline()
            if line.startswith(READY):
                return proc
    proc.kill()
    proc.wait(timeout=5)
    raise GuardianError(f"laser guardian did not become ready within {timeout_s:g} s "
                        f"(exit code {proc.returncode})")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="nhfd-laser-guardian", description=__doc__.split("\n")[0])
    parser.add_argument("--settings-json", default="{}", help="LaserSettings as JSON")
    parser.add_argument("--port", help="laser port path (overrides the settings)")
    parser.add_argument("--socket", help="socket path (overrides the settings)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s laser-guardian %(levelname)s %(message)s")
    settings = LaserSettings.model_validate_json(args.settings_json)
    if args.port:
        settings = settings.model_copy(update={"port": args.port})
    return run(settings, args.socket)


def run(settings: LaserSettings, socket_path: str | None = None) -> int:
    install_signal_handlers()
    path = Path(socket_path) if socket_path else socket_path_for(settings)
    laser = MecomLaser(settings)
    try:
        with laser:
            g = settings.guardian
            guardian = Guardian(laser, path, heartbeat_timeout_s=g.heartbeat_timeout_s,
                                tick_s=g.tick_s)
            guardian.listen()
            try:
                print(f"{READY} {path}", flush=True)
                guardian.serve()
            finally:
                guardian.close()
    except (SystemExit, KeyboardInterrupt):
        log.info("stopped; all channels off")
        return 0
    except DeviceError as exc:
        log.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
