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

Only its controller commands it. At start the guardian writes a random token into
`<socket>.token` (mode 0600, in its own directory, never on a command line) and its pid into
`<socket>.pid`; a client that sends `auth {token}` may then use every request. Without it only
`hello`, `status` and `off` are open: switching off is always allowed. It refuses a directory
that another user owns or may write to (`nhfd.drivers.rundir`), and `hello` says which port and
which unit (serial number) it drives, so a client can refuse a guardian of another laser.

Requests (replies are {"ok": true, ...} or {"ok": false, "error": "...", "type": "..."}):
  open:  hello | status | off | auth {token}
  token: heartbeat | arm {duration_s} | disarm | power {channel, power_pct} |
         enable {channel, on} | clear_fault | shutdown (all off, then the guardian exits)

`nhfd laser-off` sends `off` here, or opens the port itself when no guardian answers.
Run: `python -m nhfd.drivers.guardian --settings-json '{...}' [--port PATH] [--socket PATH]`.
"""

from __future__ import annotations

import argparse
import contextlib
import hmac
import json
import logging
import os
import secrets
import selectors
import signal
import socket
import stat
import struct
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nhfd.device_settings import LaserSettings

from .errors import DeviceError, TransportError
from .laser import Laser, MecomLaser, install_signal_handlers
from .rundir import GUARDIAN_SOCKET_NAME, UnsafeDirectory, make_private_dir, runtime_dir

log = logging.getLogger(__name__)

READY = "ready"
_MAX_LINE = 65536
# Requests anyone who can reach the socket may send: switching off is always allowed.
OPEN_OPS = frozenset({"hello", "status", "off", "auth"})
# A process whose command line holds one of these is an nhfd laser guardian.
GUARDIAN_COMMANDS = (("nhfd.drivers.guardian",), ("nhfd", "laser-guardian"))


def default_socket_path(runtime: str | os.PathLike[str] | None = None) -> Path:
    """laser.sock in `runtime`, else in the default runtime directory (`rundir.runtime_dir`)."""
    return Path(runtime or runtime_dir()) / GUARDIAN_SOCKET_NAME


def socket_path_for(settings: LaserSettings,
                    runtime: str | os.PathLike[str] | None = None) -> Path:
    """The configured socket, else laser.sock in the daemon's runtime directory: two daemons
    with two runtime directories get two guardians."""
    return Path(settings.guardian.socket_path) if settings.guardian.socket_path else (
        default_socket_path(runtime)
    )


def pid_path_for(socket_path: str | os.PathLike[str]) -> Path:
    """The guardian's pid file beside its socket: `<socket>.pid`."""
    p = Path(socket_path)
    return p.with_name(p.name + ".pid")


def token_path_for(socket_path: str | os.PathLike[str]) -> Path:
    """The guardian's token file beside its socket: `<socket>.token` (mode 0600)."""
    p = Path(socket_path)
    return p.with_name(p.name + ".token")


class GuardianError(DeviceError):
    """The guardian refused a request or the laser failed; the message says why."""


class GuardianUnavailable(GuardianError):
    """No guardian answers on the socket."""


class GuardianUnresponsive(GuardianUnavailable):
    """A guardian accepted the connection but did not answer in time (hung or stopped)."""


class GuardianRefused(GuardianError):
    """The process on the socket is not a guardian this client may trust: another user, another
    process than the one started, another port, or an unsafe directory."""


# ---------------------------------------------------------------------------------------- server


@dataclass
class _Client:
    sock: socket.socket
    buffer: bytearray = field(default_factory=bytearray)
    controller: bool = False
    authed: bool = False


class Guardian:
    """Serves one laser on a Unix socket; call `serve()` with the laser open."""

    def __init__(
        self,
        laser: Laser,
        socket_path: str | os.PathLike[str],
        *,
        heartbeat_timeout_s: float,
        tick_s: float,
        group_writable_ok: bool = False,
    ) -> None:
        self.laser = laser
        self.socket_path = Path(socket_path)
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.tick_s = tick_s
        self.group_writable_ok = group_writable_ok
        self.token = secrets.token_urlsafe(32)
        self.stopped = False
        self._last_heartbeat: float | None = None
        # Why the guardian last disarmed by itself, and how often it has: the daemon reads both
        # in each heartbeat reply, so its audit says "no heartbeat for 0.5 s" rather than
        # guessing between an expiry and a fault.
        self.trips = 0
        self.last_trip: dict[str, Any] | None = None
        # The longest time between two heartbeats of one controller session (s): the guardian's
        # own record of how late the daemon's control loop has been.
        self.max_heartbeat_gap_s = 0.0
        self._expiries_seen = laser.expiries
        self._sel = selectors.DefaultSelector()
        self._server: socket.socket | None = None
        self._clients: dict[int, _Client] = {}
        self._next_link_try = 0.0
        self._link_retry_s = 0.0

    # -- socket --------------------------------------------------------------------------------

    def listen(self) -> None:
        """Bind the socket (mode 0660, in a private directory) and write the token and pid files;
        GuardianError when the directory is unsafe, the path is not a socket, or another guardian
        listens there."""
        path = self.socket_path
        try:
            make_private_dir(path.parent, group_writable_ok=self.group_writable_ok)
        except UnsafeDirectory as exc:
            raise GuardianError(str(exc)) from None
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
        _write_private(token_path_for(path), self.token + "\n", 0o600)
        _write_private(pid_path_for(path), f"{os.getpid()}\n", 0o644)

    def close(self) -> None:
        """Drop every client (without tripping), close the socket and remove it and its token and
        pid files."""
        for client in list(self._clients.values()):
            self._drop(client, trip=False)
        if self._server is not None:
            self._sel.unregister(self._server)
            self._server.close()
            self._server = None
            for p in (self.socket_path, token_path_for(self.socket_path),
                      pid_path_for(self.socket_path)):
                with contextlib.suppress(OSError):
                    p.unlink()
        self._sel.close()

    # -- loop ----------------------------------------------------------------------------------

    def serve(self, stop_after_s: float | None = None) -> None:
        """Run until interrupted (SIGTERM/SIGINT raise) or stop_after_s has passed."""
        end = None if stop_after_s is None else time.monotonic() + stop_after_s
        while not self.stopped and (end is None or time.monotonic() < end):
            self.step()

    def step(self) -> None:
        """One turn of the loop: serve the clients that are ready (waiting at most `tick_s`), then
        enforce arming expiry and the heartbeat timeout."""
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
        self._service_laser()
        last = self._last_heartbeat
        if last is not None and time.monotonic() - last > self.heartbeat_timeout_s:
            self._trip(f"no heartbeat for {self.heartbeat_timeout_s:g} s")

    def _service_laser(self) -> None:
        """Enforce arming expiry now, recording an arming that ran out (here or in a command's
        own `service()`) as a trip."""
        try:
            self.laser.service()
        except DeviceError as exc:
            log.error("guardian: arming expiry: %s", exc)
        if self.laser.expiries != self._expiries_seen:
            self._expiries_seen = self.laser.expiries
            self._record_trip("arming expired")

    def _record_trip(self, reason: str) -> None:
        self.trips += 1
        self.last_trip = {"reason": reason, "at_s": time.time()}

    def _trip(self, reason: str) -> None:
        """Session over: disarm, all off with read-back."""
        self._last_heartbeat = None
        if self.laser.armed:
            self._record_trip(reason)
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
                    "heartbeat_timeout_s": self.heartbeat_timeout_s, "pid": os.getpid(),
                    "uid": os.getuid(), "port": _port_name(laser),
                    "usb_serial": s.usb_serial, "device_type": laser.device_type,
                    "serial_number": laser.serial_number}
        if op == "auth":
            client.authed = hmac.compare_digest(str(msg.get("token", "")), self.token)
            if not client.authed:
                raise GuardianError("wrong token")
            return {}
        if op not in OPEN_OPS and not client.authed:
            raise GuardianError(f"{op!r} needs the controller's token (auth first); only "
                                f"{', '.join(sorted(OPEN_OPS - {'auth'}))} are open")
        if op == "shutdown":
            laser.disarm()  # all off with read-back, or this raises and the guardian stays
            self.stopped = True
            return {"off": True, "pid": os.getpid()}
        if op == "heartbeat":
            client.controller = True
            now = time.monotonic()
            if self._last_heartbeat is not None:
                self.max_heartbeat_gap_s = max(self.max_heartbeat_gap_s,
                                               now - self._last_heartbeat)
            self._last_heartbeat = now
            if laser.connected:  # the reply tells an arming that just ran out as a trip
                self._service_laser()
            return {"armed": laser.armed, "armed_remaining_s": laser.armed_remaining_s,
                    "fault": laser.fault, "connected": laser.connected, "trips": self.trips,
                    "last_trip": self.last_trip,
                    "max_heartbeat_gap_ms": round(self.max_heartbeat_gap_s * 1e3, 1)}
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
    """The daemon's (and `nhfd laser-off`'s) side of the socket. Every call is bounded.

    The peer's credentials (SO_PEERCRED) are checked on connect: it must run as this user and,
    where `expected_pid` is given (a guardian this process started), be that process. With a
    `token` the client authenticates as the controller at once."""

    def __init__(self, socket_path: str | os.PathLike[str] | None = None, *,
                 timeout_s: float = 2.0, expected_pid: int | None = None,
                 token: str | None = None) -> None:
        self.socket_path = Path(socket_path) if socket_path else default_socket_path()
        self.timeout_s = timeout_s
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout_s)
        self._buffer = bytearray()
        try:
            self._sock.connect(str(self.socket_path))
        except TimeoutError:  # a full backlog: the guardian accepts nothing
            self._sock.close()
            raise GuardianUnresponsive(f"guardian at {self.socket_path} accepts no connection "
                                       f"within {timeout_s:g} s") from None
        except OSError as exc:
            self._sock.close()
            raise GuardianUnavailable(
                f"no laser guardian at {self.socket_path} ({exc.strerror or exc})"
            ) from None
        try:
            self.peer_pid, self.peer_uid = peer_credentials(self._sock)
            if self.peer_uid != os.getuid():
                raise GuardianRefused(
                    f"the process on {self.socket_path} (pid {self.peer_pid}) runs as uid "
                    f"{self.peer_uid}, not {os.getuid()}; refusing it")
            if expected_pid is not None and self.peer_pid != expected_pid:
                raise GuardianRefused(
                    f"the process on {self.socket_path} is pid {self.peer_pid}, not the "
                    f"guardian started (pid {expected_pid}); refusing it")
            if token is not None:
                self.call("auth", token=token)
        except BaseException:
            self._sock.close()
            raise

    def call(self, op: str, *, timeout_s: float | None = None, **params: Any) -> dict[str, Any]:
        """Send request `op` with `params` and return the reply without its "ok" (bounded by
        `timeout_s`, default the client's); GuardianError with the guardian's reason when it
        refuses, GuardianUnresponsive when it does not answer in time."""
        self._sock.settimeout(self.timeout_s if timeout_s is None else timeout_s)
        try:
            self._sock.sendall(json.dumps({"op": op, **params}).encode() + b"\n")
            while (end := self._buffer.find(b"\n")) < 0:
                chunk = self._sock.recv(4096)
                if not chunk:
                    raise GuardianUnavailable(f"guardian at {self.socket_path} hung up")
                self._buffer += chunk
        except TimeoutError:
            raise GuardianUnresponsive(
                f"guardian at {self.socket_path} did not answer {op!r} within "
                f"{self._sock.gettimeout():g} s") from None
        except OSError as exc:
            raise GuardianUnavailable(f"guardian at {self.socket_path}: {exc}") from None
        try:
            reply = json.loads(bytes(self._buffer[:end]))
        except ValueError:
            raise GuardianRefused(f"guardian at {self.socket_path}: not a JSON reply") from None
        del self._buffer[: end + 1]
        if not isinstance(reply, dict):
            raise GuardianRefused(f"guardian at {self.socket_path}: not a JSON object")
        if not reply.pop("ok", False):
            raise GuardianError(f"guardian: {reply.get('type', 'error')}: {reply.get('error')}")
        return reply

    def hello(self) -> dict[str, Any]:
        """Who the guardian is: its channels and caps, heartbeat timeout (s), pid, uid, port and the
        laser's identity (open to anyone)."""
        return self.call("hello")

    def heartbeat(self, timeout_s: float | None = None) -> dict[str, Any]:
        """Keep the session alive and become the controller; the reply holds armed, the arming left
        (s), fault, connected, trips and the last trip."""
        return self.call("heartbeat", timeout_s=timeout_s)

    def arm(self, duration_s: float) -> None:
        """Arm the laser for `duration_s` (s, at most `arm_max_s`); needs a live heartbeat.
        GuardianError when the guardian refuses."""
        self.call("arm", duration_s=duration_s)

    def disarm(self) -> None:
        """Disarm: every channel off, read back."""
        self.call("disarm")

    def set_power(self, channel: str, power_pct: float) -> float:
        """Set `channel`'s power (% of full power, clamped to [0, cap]); returns the power applied,
        read back. Needs a live heartbeat."""
        return float(self.call("power", channel=channel, power_pct=power_pct)["power_pct"])

    def enable(self, channel: str, on: bool = True) -> None:
        """Switch `channel`'s emission on or off (on needs an arming); needs a live heartbeat."""
        self.call("enable", channel=channel, on=on)

    def all_off(self) -> None:
        """Every channel off, read back (open to anyone: switching off is always allowed)."""
        self.call("off")

    def status(self) -> dict[str, Any]:
        """The laser's status: device status, arming, fault and each channel's enable and power
        (%)."""
        return self.call("status")

    def shutdown(self) -> int:
        """All off with read-back, then the guardian exits; returns its pid (token needed)."""
        return int(self.call("shutdown")["pid"])

    def close(self) -> None:
        """Close the connection (a controller's close makes the guardian switch every channel
        off)."""
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
    group_writable_ok: bool = False,
) -> subprocess.Popen[str]:
    """Start a guardian process and wait (bounded by guardian.start_timeout_s) until it has
    identified the laser, switched it off and listens. The caller owns the process."""
    args = [python, "-m", "nhfd.drivers.guardian", "--settings-json",
            settings.model_dump_json()]
    if port:
        args += ["--port", port]
    if socket_path:
        args += ["--socket", str(socket_path)]
    if group_writable_ok:
        args += ["--group-writable-dir"]
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
    """`python -m nhfd.drivers.guardian`: parse the settings, port and socket, and run the guardian;
    returns the exit code."""
    parser = argparse.ArgumentParser(prog="nhfd-laser-guardian", description=__doc__.split("\n")[0])
    parser.add_argument("--settings-json", default="{}", help="LaserSettings as JSON")
    parser.add_argument("--port", help="laser port path (overrides the settings)")
    parser.add_argument("--socket", help="socket path (overrides the settings)")
    parser.add_argument("--group-writable-dir", action="store_true",
                        help="accept a group-writable socket directory "
                             "(daemon.server.socket_group)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s laser-guardian %(levelname)s %(message)s")
    settings = LaserSettings.model_validate_json(args.settings_json)
    if args.port:
        settings = settings.model_copy(update={"port": args.port})
    return run(settings, args.socket, group_writable_ok=args.group_writable_dir)


def run(settings: LaserSettings, socket_path: str | None = None, *,
        group_writable_ok: bool = False) -> int:
    """Open the laser (every channel off), listen on the socket, print "ready" and serve until a
    signal; the channels are off when it returns. Returns 0, or 1 on a device error."""
    install_signal_handlers()
    path = Path(socket_path) if socket_path else socket_path_for(settings)
    laser = MecomLaser(settings)
    try:
        with laser:
            g = settings.guardian
            guardian = Guardian(laser, path, heartbeat_timeout_s=g.heartbeat_timeout_s,
                                tick_s=g.tick_s, group_writable_ok=group_writable_ok)
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


# --------------------------------------------------------------------------------- verification


def _port_name(laser: Laser) -> str:
    return str(getattr(laser, "port_name", "") or laser.settings.port)


def _write_private(path: Path, text: str, mode: int) -> None:
    """Replace `path` with a new file of `mode` (never through a symlink someone left there)."""
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, mode)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def peer_credentials(sock: socket.socket) -> tuple[int, int]:
    """(pid, uid) of the process at the other end of a Unix socket (SO_PEERCRED)."""
    raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    pid, uid, _gid = struct.unpack("3i", raw)
    return pid, uid


def read_private(path: Path) -> str:
    """The text of a file this user owns that nobody else may read or write (a token)."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    with os.fdopen(fd) as f:
        st = os.fstat(f.fileno())
        if st.st_uid != os.getuid() or stat.S_IMODE(st.st_mode) & 0o077:
            raise GuardianRefused(f"{path}: owner uid {st.st_uid}, mode "
                                  f"{stat.S_IMODE(st.st_mode):04o}; a token file must be this "
                                  "user's and mode 0600")
        return f.read().strip()


def read_token(socket_path: str | os.PathLike[str]) -> str:
    """The controller's token of the guardian on `socket_path` (`read_private`); GuardianRefused
    when the token file is missing or unsafe."""
    try:
        return read_private(token_path_for(socket_path))
    except FileNotFoundError:
        raise GuardianRefused(f"no token file {token_path_for(socket_path)}: the guardian there "
                              "did not start as this nhfd's guardian") from None


def is_our_guardian(pid: int) -> bool:
    """True when `pid` is a live nhfd laser guardian of this user (read from /proc)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return False
    uids = next((ln.split()[1:] for ln in status.splitlines() if ln.startswith("Uid:")), [])
    state = next((ln.split()[1] for ln in status.splitlines() if ln.startswith("State:")), "")
    if not uids or int(uids[0]) != os.getuid() or state == "Z":
        return False
    return any(all(any(word in arg for arg in argv) for word in words)
               for words in GUARDIAN_COMMANDS)


def alive(pid: int) -> bool:
    """Whether process `pid` exists and is not a zombie (from /proc)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    return "\nState:\tZ" not in status


def guardian_pid(socket_path: str | os.PathLike[str], port: str = "") -> int | None:
    """The pid of the nhfd guardian of this user serving `socket_path` (its pid file) or holding
    `port` (from /proc), verified by `is_our_guardian`; None when there is none."""
    candidates: list[int] = []
    with contextlib.suppress(OSError, ValueError):
        pid_file = pid_path_for(socket_path)
        if pid_file.stat().st_uid == os.getuid():
            candidates.append(int(pid_file.read_text().strip()))
    if port:
        candidates += port_holders(port)
    return next((pid for pid in candidates if is_our_guardian(pid)), None)


def holds_port(pid: int, port: str) -> bool:
    """True when process `pid` (of this user: others' fds are not readable) has `port` open."""
    target = os.path.realpath(port)
    with contextlib.suppress(OSError):
        return any(os.path.realpath(fd) == target for fd in Path(f"/proc/{pid}/fd").iterdir())
    return False


def port_holders(port: str) -> list[int]:
    """Processes of this user with `port` open (from /proc/<pid>/fd)."""
    return [int(e.name) for e in Path("/proc").iterdir()
            if e.name.isdigit() and holds_port(int(e.name), port)]


def verify_guardian(pid: int, port: str, where: str) -> None:
    """GuardianRefused unless `pid` is an nhfd guardian of this user that holds `port` open: a
    process can claim any port in its hello, but not hold one another process holds."""
    if not is_our_guardian(pid):
        raise GuardianRefused(f"{where}: pid {pid} is not an nhfd laser guardian of this user "
                              "(/proc); refusing it")
    if not holds_port(pid, port):
        raise GuardianRefused(f"{where}: pid {pid} says it drives {port!r} but does not hold it "
                              "open; refusing it")


def guardian_port(pid: int) -> str:
    """The port a guardian process was started on (its --port or --settings-json), or ""."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return ""
    if "--port" in argv[:-1]:
        return argv[argv.index("--port") + 1]
    if "--settings-json" in argv[:-1]:
        with contextlib.suppress(ValueError, TypeError, AttributeError):
            return str(json.loads(argv[argv.index("--settings-json") + 1]).get("port", ""))
    return ""


def wait_gone(pid: int, timeout_s: float) -> bool:
    """Wait until `pid` has exited (reaping it if it is our child); False if it still runs after
    `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while alive(pid):
        with contextlib.suppress(ChildProcessError):
            if os.waitpid(pid, os.WNOHANG)[0] == pid:
                return True
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def kill_guardian(pid: int, timeout_s: float = 3.0) -> bool:
    """SIGKILL a verified guardian of ours and wait until it is gone (its port is free then);
    False when `pid` is not one (nothing is sent)."""
    if not is_our_guardian(pid):
        return False
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)
    if not wait_gone(pid, timeout_s):
        raise GuardianError(f"guardian pid {pid} still alive {timeout_s:g} s after SIGKILL")
    return True


if __name__ == "__main__":
    sys.exit(main())
