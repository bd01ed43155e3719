"""The daemon's side of the laser guardian: start or connect, heartbeat, commands, read-back.

The guardian process owns the laser port; the daemon never opens it. Heartbeats go out from the
control loop (never a helper thread: a stuck loop must stop them, so the guardian switches the
lasers off). With `devices.laser = "simulated"` the daemon hosts the READYBeam twin on a pty and
the guardian drives it through the same MeCom code as the real unit.

Trust: the guardian's directory must be this user's and writable by no one else; the process on
the socket must run as this user (SO_PEERCRED) and, when the daemon started it, be that child;
its `hello` must name the configured port; the daemon commands it with the token from the
guardian's 0600 token file. Anything else is refused by name, and start fails.

A heartbeat that gets no answer within `guardian.heartbeat_reply_timeout_s` means a hung
guardian: one the daemon started (or adopted from a killed daemon, verified as ours in /proc) is
SIGKILLed and replaced by a new one, which opens the port and switches everything off (read
back). With `daemon.arming.guardian = "connect"` the guardian belongs to someone else: the daemon
says "laser state unknown: guardian unresponsive" and never claims the lasers are off.

Laser state changes the guardian makes by itself (arming expiry, a tripped heartbeat) are seen in
the heartbeat replies and written to the audit log.

Emission sessions: every run that could switch a diode on (a citl refinement's captures, a
capture-mode snapshot) belongs to the session current when it was asked for (`session`). Each
arm starts a new session, and each end ends it: `laser off`, `disarm`, `stop`, shutdown, the
guardian's own disarm (expiry, a fault, a tripped heartbeat), a lost SLM output, a crashed frame
worker. A run checks its session before anything moves or emits and after each capture, and
`enable(channel, True, session=s)` checks it under the same lock as `off`, so no switch-on of an
ended run can follow the end; a later arm starts another session and never resumes it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import threading
import time
from collections.abc import Callable
from typing import Any

from nhfd.device_settings import LaserSettings
from nhfd.drivers.guardian import (
    GuardianClient,
    GuardianError,
    GuardianRefused,
    GuardianUnavailable,
    GuardianUnresponsive,
    guardian_pid,
    is_our_guardian,
    kill_guardian,
    read_token,
    socket_path_for,
    spawn_guardian,
    verify_guardian,
    wait_gone,
)
from nhfd.drivers.rundir import UnsafeDirectory, make_private_dir
from nhfd.drivers.transport import same_port
from nhfd.drivers.twins.mecom_twin import MecomTwin

from .audit import AuditLog
from .protocol import LASER_REFUSED, NOT_AVAILABLE, RpcError

log = logging.getLogger("nhfd.daemon.laser")

SYSTEM = {"who": "daemon"}
UNKNOWN = "laser state unknown: guardian unresponsive"


class LasersNotOff(RuntimeError):
    """Every channel could not be read back off: the daemon must not report ready."""


class EmissionEnded(RuntimeError):
    """A run that could emit belongs to an emission session that has ended (the module's
    docstring); the message says what ended it."""


# Emission sessions whose end reasons are kept (a run older than that reads the oldest's).
SESSIONS_KEPT = 64


class LaserLink:
    """The lasers through the guardian process (the module's docstring): started or connected
    (`mode`: "auto", "spawn" or "connect"), the heartbeats the control loop sends, commands one at a
    time under one lock, the channels read back, and the emission sessions. `backend`: "simulated"
    (the daemon hosts the twin), "readybeam" or "none"."""
    def __init__(self, settings: LaserSettings, backend: str, mode: str, audit: AuditLog, *,
                 runtime_dir: str | os.PathLike[str] | None = None, socket_group: str = "",
                 call_timeout_s: float = 1.0, refresh_s: float = 1.0,
                 on_session_end: Callable[[str], None] | None = None) -> None:
        """`on_session_end(reason)`: called (on the ending thread, under the link's lock) each
        time an emission session ends, with what ended it."""
        self.settings = settings
        self.backend = backend  # "simulated", "readybeam" or "none"
        self.mode = mode  # "auto", "spawn" or "connect"
        self.audit = audit
        self.call_timeout_s = call_timeout_s
        self.heartbeat_timeout_s = settings.guardian.heartbeat_reply_timeout_s
        self.refresh_s = refresh_s
        self.socket_path = socket_path_for(settings, runtime_dir)
        self.group_writable_ok = bool(socket_group)
        self.twin: Any = None  # the simulated laser's MecomTwin (the simulated camera reads it)
        self.proc: subprocess.Popen[str] | None = None
        self.client: GuardianClient | None = None
        self.pid: int | None = None  # the guardian's pid (started or adopted)
        self.identity: dict[str, Any] = {}  # the guardian's hello: port, serial number, pid
        self.replaced = 0  # hung guardians killed and replaced
        self.error: str | None = None
        self._beat: dict[str, Any] = {}
        # The control loop's heartbeats as the daemon sent them: a gap past half the guardian's
        # timeout is logged (the loop stalled), and counted for `status`.
        self._beat_sent_at: float | None = None
        self.late_heartbeats = 0
        self.max_heartbeat_gap_s = 0.0
        self._channels: dict[str, Any] = {}
        self._read_at = 0.0
        self._next_reconnect = 0.0
        # One socket, one request at a time: the control loop (heartbeats, commands) and the
        # capture-mode snapshot job (per-colour enables) both use it.
        self._lock = threading.RLock()
        # The emission session (the module's docstring) and why each recent one ended.
        self._session = 1
        self._ended: dict[int, str] = {}
        self._on_session_end = on_session_end
        # Why every switch-on is refused from now on, whatever its session (`refuse_from_now`:
        # a shutdown was asked), or None.
        self._refusing: str | None = None

    @property
    def present(self) -> bool:
        """Whether a laser is configured (`backend` is not "none")."""
        return self.backend != "none"

    @property
    def spawned(self) -> bool:
        """Whether this daemon started the guardian it talks to."""
        return self.proc is not None

    # -- emission sessions ---------------------------------------------------------------------

    @property
    def session(self) -> int:
        """The emission session now: a run asked for now belongs to it (any thread)."""
        return self._session

    def end_session(self, reason: str) -> None:
        """End the emission session (`reason`: what ended it, in the words a run's refusal and
        `status` show); every run of it is refused from now on. Any thread."""
        with self._lock:
            self._next_session(reason)

    def _next_session(self, reason: str) -> None:
        self._ended[self._session] = reason
        if len(self._ended) > SESSIONS_KEPT:
            self._ended.pop(min(self._ended))
        self._session += 1
        if self._on_session_end is not None:
            try:
                self._on_session_end(reason)
            except Exception:  # a report, never a reason for the off itself to fail
                log.exception("emission session end hook")

    def refuse_from_now(self, reason: str) -> None:
        """Refuse every switch-on from now on, whatever its session (`reason`: why, as a run's
        refusal says it). A shutdown's first act, asked perhaps from a signal handler in the
        middle of this link's own work: so no lock, only an assignment. The session ends too
        when the loop next steps (`end_session`); a run switching its diodes in turn must not
        light the next one meanwhile."""
        self._refusing = reason

    def check_session(self, session: int) -> None:
        """EmissionEnded, saying what ended it, unless `session` is the session now (and no
        shutdown refuses every switch-on)."""
        if self._refusing is not None:
            raise EmissionEnded(self._refusing)
        if session != self._session:
            raise EmissionEnded(self._ended.get(
                session, "the lasers were switched off or re-armed since it was asked for"))

    # -- start / stop --------------------------------------------------------------------------

    def start(self) -> None:
        """Connect to (or start) the guardian, switch every channel off and read it back."""
        if not self.present:
            return
        try:
            make_private_dir(self.socket_path.parent, group_writable_ok=self.group_writable_ok)
        except UnsafeDirectory as exc:
            raise GuardianRefused(f"laser guardian directory: {exc}") from None
        if self.mode in ("auto", "connect"):
            self._adopt()
        if self.client is None:
            if self.mode == "connect":
                raise GuardianUnavailable(f"no laser guardian at {self.socket_path} and "
                                          "daemon.arming.guardian = 'connect'")
            self._spawn()
        self.all_off_confirmed("start")

    def _adopt(self) -> None:
        """Use a guardian already listening (a killed daemon's, or a service's) if it is ours and
        drives the configured port. In auto mode a hung one of ours, or one left driving a killed
        simulated daemon's twin, is ended (verified in /proc) and a new one started."""
        if not self.socket_path.exists():
            if self.mode == "connect":
                raise GuardianUnavailable(f"no laser guardian at {self.socket_path} and "
                                          "daemon.arming.guardian = 'connect'")
            return
        try:
            self._open_client()
            log.info("laser guardian found at %s (pid %s, port %s)", self.socket_path, self.pid,
                     self.identity.get("port"))
            return
        except GuardianUnresponsive as exc:
            if self.mode == "connect":
                raise GuardianUnavailable(f"{UNKNOWN}: {exc}") from None
            reason: GuardianError = exc
        except GuardianRefused as exc:
            if self.mode == "connect" or self.backend != "simulated":
                raise
            reason = exc
        except GuardianUnavailable:  # a stale socket file: nobody listens
            if self.mode == "connect":
                raise
            return
        pid = guardian_pid(self.socket_path)
        if pid is None:
            raise GuardianRefused(f"{reason}; and it is not an nhfd laser guardian of this "
                                  "user, so it is left alone") from None
        log.warning("%s: ending laser guardian pid %d", reason, pid)
        kill_guardian(pid)

    def _expected_port(self) -> str:
        if self.backend == "simulated":
            return self.twin.port_path if self.twin is not None else ""
        return self.settings.port

    def _open_client(self, expected_pid: int | None = None) -> None:
        """Connect, check the peer, its hello (port) and authenticate with its token."""
        client = GuardianClient(self.socket_path, timeout_s=self.call_timeout_s,
                                expected_pid=expected_pid)
        try:
            # A live guardian answers hello at once: a short bound keeps a hung one from
            # stalling the control loop for long.
            hello = client.call("hello", timeout_s=self.heartbeat_timeout_s)
            self._check_identity(hello)
            if expected_pid is None:  # found, not started: it must be a guardian on that port
                verify_guardian(client.peer_pid, str(hello.get("port") or ""),
                                f"the laser guardian at {self.socket_path}")
            client.call("auth", token=read_token(self.socket_path))
        except BaseException:
            client.close()
            raise
        self.client, self.identity, self.pid = client, hello, client.peer_pid

    def _check_identity(self, hello: dict[str, Any]) -> None:
        port, s = hello.get("port"), self.settings
        expected = self._expected_port()
        where = f"the laser guardian at {self.socket_path} (pid {hello.get('pid')})"
        if expected:
            if not same_port(str(port or ""), expected):
                raise GuardianRefused(f"{where} drives port {port!r}, not {expected!r}; "
                                      "refusing it")
        elif s.usb_serial and hello.get("usb_serial") != s.usb_serial:
            raise GuardianRefused(f"{where} drives the laser with USB serial "
                                  f"{hello.get('usb_serial')!r}, not {s.usb_serial!r}; refusing it")
        elif self.backend == "simulated":
            raise GuardianRefused(f"{where} drives {port!r}, not this daemon's simulated laser; "
                                  "refusing it")

    def _spawn(self) -> None:
        port = None
        if self.backend == "simulated":
            if self.twin is None:
                s = self.settings
                self.twin = MecomTwin(device_type=s.device_type, address=s.address,
                                      channel_instances=s.channel_instances,
                                      parameter_ids=s.parameter_ids)
                self.twin.start()
            port = self.twin.port_path
        self.proc = spawn_guardian(self.settings, port=port, socket_path=self.socket_path,
                                   group_writable_ok=self.group_writable_ok)
        try:
            self._open_client(expected_pid=self.proc.pid)
        except BaseException:
            self.proc.kill()
            self.proc.wait()
            self.proc = None
            raise
        log.info("laser guardian started, pid %d, socket %s, port %s, serial number %s",
                 self.proc.pid, self.socket_path, self.identity.get("port"),
                 self.identity.get("serial_number"))

    def all_off_confirmed(self, why: str) -> None:
        """Disarm, all channels off, then read every channel back; LasersNotOff otherwise. Ends
        the emission session."""
        self.end_session(f"lasers off ({why})")
        client = self._require()
        # Under the socket's lock: a bench job still switching a diode (a citl step at
        # shutdown) must not interleave its request with these, or each reads the other's reply.
        with self._lock:
            # No heartbeat here: `off` needs none, and a first heartbeat would start the
            # guardian's watchdog before the control loop runs (start-up opens slow devices in
            # between).
            client.all_off()  # the guardian reads back too, and raises if it could not confirm
            status = client.status()
        on = {ch: c for ch, c in status["channels"].items()
              if c["enabled"] or abs(c["power_pct"]) > self.settings.readback_tolerance_pct}
        if on or status["armed"]:
            raise LasersNotOff(f"lasers not read back off ({why}): {on or 'still armed'}")
        self._channels, self._read_at = status["channels"], time.monotonic()
        self._beat = {"armed": False, "armed_remaining_s": 0.0, "fault": status["fault"]}
        self.audit.write(SYSTEM, "laser all off (read back)", reason=why, guardian_pid=self.pid)

    def close(self) -> str:
        """All off with read-back, then leave; returns how the lasers were confirmed off. A
        guardian adopted from a killed daemon is ended too (it would hold the port for ever);
        one that belongs to a service (`connect`) is left running."""
        if not self.present:
            return "no laser"
        how = "not confirmed"
        try:
            if self.client is not None:
                self.all_off_confirmed("shutdown")
                how = "read back off through the guardian"
                if self.proc is None and self.mode != "connect" and self.pid is not None:
                    self._end_adopted()
        except (GuardianError, LasersNotOff, OSError) as exc:
            log.error("laser all-off at shutdown: %s", exc)
        finally:
            if self.client is not None:
                self.client.close()  # the guardian trips as well when a controller leaves
                self.client = None
            if self.proc is not None:
                if self.proc.poll() is None:
                    self.proc.terminate()  # it switches everything off and exits 0
                with contextlib.suppress(subprocess.TimeoutExpired):
                    code = self.proc.wait(timeout=5)
                    if code == 0 and how == "not confirmed":
                        how = "guardian exited cleanly (its exit switches everything off)"
                if self.proc.poll() is None:
                    self.proc.kill()
                    self.proc.wait()
            if self.twin is not None:
                self.twin.close()
        return how

    def _end_adopted(self) -> None:
        assert self.client is not None and self.pid is not None
        pid = self.client.shutdown()
        if not wait_gone(pid, 5.0):
            kill_guardian(pid)
        log.info("adopted laser guardian pid %d ended (all off, read back); port free", pid)

    # -- loop ----------------------------------------------------------------------------------

    def heartbeat(self, now: float) -> None:
        """From the control loop, every tick."""
        if not self.present:
            return
        with self._lock:
            self._heartbeat(now)

    def _heartbeat(self, now: float) -> None:
        if self.client is None:
            self._reconnect(now)
            return
        gap_s = self._heartbeat_gap(time.monotonic())  # `now` predates waiting for the lock
        try:
            beat = self.client.heartbeat(timeout_s=self.heartbeat_timeout_s)
        except GuardianError as exc:
            self._lost(f"guardian heartbeat failed: {exc}")
            self._reconnect(now)  # at once: a hung guardian may be holding the lasers on
            return
        if self._beat.get("armed") and not beat["armed"]:
            # The guardian says why (an older one does not: then it was an expiry or a fault).
            # The daemon's own disarms (`off`, `disarm`) mark the beat unarmed when they are
            # sent, so only the guardian's own reach this line, once.
            new_trip = beat.get("trips", 0) > self._beat.get("trips", 0)
            reason = (beat.get("last_trip") or {}).get("reason") if new_trip else None
            what = reason or "arming expiry or a fault"
            self._next_session(f"the guardian disarmed the lasers ({what})")
            self.audit.write(SYSTEM, f"laser disarmed by the guardian: {what}",
                             fault=beat.get("fault"), heartbeat_gap_ms=round(gap_s * 1e3, 1))
        self._beat = beat
        self.error = None
        if now - self._read_at >= self.refresh_s:
            self.refresh(now)

    def _heartbeat_gap(self, now: float) -> float:
        """Seconds since the previous heartbeat was sent (`now`: monotonic, when this one is
        sent; 0 for the first); a gap past half
        the guardian's timeout is logged: the control loop stalled, and the guardian disarms
        once a gap reaches its timeout."""
        last, self._beat_sent_at = self._beat_sent_at, now
        if last is None:
            return 0.0
        gap_s = now - last
        self.max_heartbeat_gap_s = max(self.max_heartbeat_gap_s, gap_s)
        timeout_s = float(self.identity.get("heartbeat_timeout_s") or 0.0)
        if timeout_s and gap_s > timeout_s / 2:
            self.late_heartbeats += 1
            log.warning("heartbeat %.0f ms after the previous one (the guardian disarms at "
                        "%.0f ms): the control loop stalled", gap_s * 1e3, timeout_s * 1e3)
        return gap_s

    def refresh(self, now: float | None = None) -> None:
        """Read the channels back from the guardian (what `status` shows) at clock time `now` (s,
        monotonic; default now); a guardian that does not answer is lost."""
        with self._lock:
            self._refresh(now)

    def _refresh(self, now: float | None) -> None:
        client = self._require()
        try:
            self._channels = client.status()["channels"]
        except GuardianError as exc:
            self._lost(f"guardian status failed: {exc}")
        self._read_at = time.monotonic() if now is None else now

    def _lost(self, why: str) -> None:
        """The guardian stopped answering: nothing is known about the lasers until a guardian
        reads them back off again."""
        log.error("%s (%s)", UNKNOWN, why)
        self.error = f"{UNKNOWN} ({why})"
        if self.client is not None:
            self.client.close()
            self.client = None
        self._beat = {}
        self._channels = {}

    def _reconnect(self, now: float) -> None:
        if now < self._next_reconnect:
            return
        self._next_reconnect = now + 1.0
        old = self.pid
        try:
            if self.mode == "connect":
                self._open_client()
            else:
                self._replace()
            self.all_off_confirmed("guardian reconnected")  # arming is never restored
            self.error = None
            log.warning("laser guardian pid %s (was %s): all channels off (read back), not "
                        "armed", self.pid, old)
        except (GuardianError, LasersNotOff, OSError) as exc:
            self.error = f"{UNKNOWN} ({exc})"
            log.error("%s", self.error)
            if self.client is not None:
                self.client.close()
                self.client = None

    def _replace(self) -> None:
        """End the guardian we started or adopted (SIGKILL: it may be stopped and deaf to
        anything else; the kernel frees the port), then start a new one, which opens the port
        and switches everything off."""
        pid = self.proc.pid if self.proc is not None else self.pid
        if pid is not None and (self.proc is not None or is_our_guardian(pid)):
            if self.proc is not None:
                self.proc.kill()
                self.proc.wait()
            else:
                kill_guardian(pid)
            self.replaced += 1
            log.error("laser guardian pid %d did not answer: killed (SIGKILL); starting a new "
                      "one to switch every channel off", pid)
            self.audit.write(SYSTEM, "laser guardian unresponsive: killed", guardian_pid=pid)
        self.proc, self.pid = None, None
        self._spawn()

    # -- commands ------------------------------------------------------------------------------

    def _require(self) -> GuardianClient:
        if not self.present:
            raise RpcError(NOT_AVAILABLE, "no laser configured (devices.laser = 'none')",
                           {"device": "laser"})
        if self.client is None:
            raise RpcError(LASER_REFUSED, self.error or "laser guardian not connected",
                           {"device": "laser"})
        return self.client

    def _call(self, op: str, **params: Any) -> dict[str, Any]:
        with self._lock:
            return self._call_locked(op, **params)

    def _call_locked(self, op: str, **params: Any) -> dict[str, Any]:
        client = self._require()
        try:
            reply = client.call(op, **params)
        except GuardianUnavailable as exc:
            self._lost(str(exc))
            raise RpcError(LASER_REFUSED, str(exc), {"device": "laser"}) from None
        except GuardianError as exc:
            raise RpcError(LASER_REFUSED, str(exc), {"device": "laser"}) from None
        finally:
            with contextlib.suppress(RpcError, GuardianError):
                if self.client is not None:
                    self.refresh()
        return reply

    def arm(self, duration_s: float) -> dict[str, Any]:
        """Arm for `duration_s`. Lasers that were not armed start a new emission session: a
        run asked for before never emits in it."""
        with self._lock:
            # A heartbeat first: the guardian's own disarms (an expiry) are seen, and audited,
            # before this arm, and the guardian knows its controller.
            self._heartbeat(time.monotonic())
            was_armed = bool(self._beat.get("armed"))
            reply = self._call("arm", duration_s=duration_s)
            if not was_armed:  # extending an arming keeps the runs asked for under it
                self._next_session("the lasers were armed after it was asked for")
            self._beat = {**self._beat, "armed": True}
            return reply

    def disarm(self, reason: str = "lasers disarmed") -> None:
        """Disarm (the diodes keep their powers; nothing can be enabled): ends the emission
        session with `reason`."""
        with self._lock:
            self._next_session(reason)
            self._call("disarm")
            self._disarmed_here()

    def off(self, reason: str = "lasers off") -> None:
        """All off: ends the emission session with `reason`. A guardian that fails to answer is
        replaced at once (one we started or adopted), and the new one's read-back counts;
        otherwise the refusal stands."""
        with self._lock:
            self._next_session(reason)
            try:
                self._call("off")
            except RpcError:
                if self.client is not None or self.mode == "connect" or not self.present:
                    raise
                self._next_reconnect = 0.0
                self._reconnect(time.monotonic())
                if self.client is None:
                    raise
            self._disarmed_here()

    def _disarmed_here(self) -> None:
        """The daemon's own disarm: the next heartbeat must not read it as the guardian's."""
        if self._beat:
            self._beat = {**self._beat, "armed": False, "armed_remaining_s": 0.0}

    def power(self, channel: str, power_pct: float) -> float:
        """Set `channel`'s power (% of its maximum); returns the power the guardian applied (%,
        within `max_power_pct`)."""
        return float(self._call("power", channel=channel, power_pct=power_pct)["power_pct"])

    def enable(self, channel: str, on: bool, *, session: int | None = None) -> None:
        """Switch a diode on or off. With `session`, a switch-on happens only while that
        emission session holds (EmissionEnded otherwise), checked under the lock `off` takes."""
        with self._lock:
            if on and session is not None:
                self.check_session(session)
            self._call("enable", channel=channel, on=on)

    def status(self) -> dict[str, Any]:
        """The laser part of `status`: the guardian (socket, pid, replacements, heartbeat gaps, its
        trips), armed and the arming's time left (s), the emission session, the fault, the channels
        as last read back and how long ago (s), and the power caps (%)."""
        if not self.present:
            return {"backend": "none"}
        return {
            "backend": self.backend,
            "guardian": {"socket": str(self.socket_path), "connected": self.client is not None,
                         "pid": self.pid, "spawned": self.spawned,
                         "spawned_pid": self.proc.pid if self.proc else None,
                         "port": self.identity.get("port"),
                         "serial_number": self.identity.get("serial_number"),
                         "replaced": self.replaced,
                         "late_heartbeats": self.late_heartbeats,
                         "max_heartbeat_gap_ms": round(self.max_heartbeat_gap_s * 1e3, 1),
                         # the guardian's own record: its disarms, and the longest gap it saw
                         "trips": self._beat.get("trips"),
                         "seen_max_heartbeat_gap_ms": self._beat.get("max_heartbeat_gap_ms")},
            "state": "read back through the guardian" if self.client is not None else UNKNOWN,
            "armed": bool(self._beat.get("armed", False)),
            "armed_remaining_s": self._beat.get("armed_remaining_s", 0.0),
            "emission_session": self._session,
            "fault": self._beat.get("fault"),
            "channels": self._channels,
            "channels_read_s_ago": round(time.monotonic() - self._read_at, 3),
            "max_power_pct": list(self.settings.max_power_pct),
            "error": self.error,
        }
