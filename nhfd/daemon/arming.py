"""Who may arm the lasers, and the optional confirmation by a person at the bench.

**Authority** comes from what the kernel vouches for about a Unix-socket peer: its uid
(SO_PEERCRED, read at accept by `server.peer_credentials`). That uid's groups come from the user
database (its primary group and `os.getgrouplist`), not from the peer process. They are checked
against `daemon.arming.users` and `daemon.arming.groups`; with both empty, only the daemon's own
(effective) user may arm. Arming is refused over TCP whatever the token, and the web view never
sends it.

The process-name rule (a peer named `sshd*` is an SSH tunnel: `server.forwarded_by_ssh`) is kept
as defence in depth, and it can only refuse. It costs nothing and stops the commonest remote path
(`ssh -L` by an allowed user) when no confirmation is configured. It is no authority: a relay with
any other name passes it, and a process can choose its own name. So the docs promise nothing from
it. Likewise a connection the web view has marked as its own (`web_client`) is refused: the web
view runs in the daemon's process, as its user, and never sends `arm` anyway.

**The honest limit.** A relay that runs as an allowed user (`ssh -L` by that user, `socat`, 20
lines of Python) *is* that user to the kernel: nothing on this socket can tell it from a person
at the bench. That is what the confirmation is for.

**Confirmation** (`daemon.arming.confirm`): with "serial" a key switch on `confirm_port`'s CTS or
DSR line (`nhfd.drivers.keyswitch`; "simulated" hosts the twin) must be turned on after the request
(seen off, then on). With "spacemouse", a navigator button must go down after the request. Either
way it must happen within `confirm_timeout_s`. The wait runs as a bench job
(`JobRunner`), never in the control loop, so requests and the guardian's heartbeat go on. The
`laser arm` reply comes at once, `{"armed": false, "pending": true, "job": N, ...}`; `job N` (and
`status.jobs`) shows the wait, and the job ends `done` (armed, for `duration_s` from the
confirmation), `failed` (no confirmation in time: not armed) or `cancelled` (`laser off`,
`disarm` or `stop` first). Each outcome is audited with the requester's identity. A deferred RPC
reply was not chosen: the line server answers each request in the same pass, and a reply held
for seconds would need per-connection state in the server, which is the same job with more code.
"""

from __future__ import annotations

import functools
import grp
import logging
import os
import pwd
import threading
import time
from collections.abc import Mapping
from typing import Any, Protocol

from nhfd.config import ArmingSettings, ConfigError
from nhfd.drivers.errors import DeviceError
from nhfd.drivers.keyswitch import KeySwitch, LinesOpener, open_serial_lines
from nhfd.drivers.twins.keyswitch_twin import KeySwitchTwin

from .audit import AuditLog
from .guardian_link import LaserLink
from .jobs import Cancelled, Job, JobRunner, submit_or_busy
from .protocol import BUSY, FORBIDDEN, NOT_AVAILABLE, RpcError
from .server import Connection, forwarded_by_ssh

log = logging.getLogger("nhfd.daemon.arming")

SIMULATED_PORT = "simulated"  # daemon.arming.confirm_port: the daemon hosts a simulated key switch
POLL_S = 0.02  # how often the confirmation input is sampled while an arm waits


class ArmNotConfirmed(RuntimeError):
    """No confirmation from the bench in time: the lasers stay disarmed."""


class NavigatorState(Protocol):
    """What a button-press confirmation reads of the navigator input
    (`nhfd.daemon.navigation.NavigatorInput`): the open navigator (None when there is none)
    and why there is none."""

    navigator: Any
    error: str | None


# -- authority --------------------------------------------------------------------------------


def user_name(uid: int) -> str | None:
    """The user database's name for `uid` (None when it has none)."""
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return None


def group_name(gid: int) -> str:
    """The group database's name for `gid` (the number itself when it has none)."""
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


def groups_of(uid: int) -> set[int]:
    """`uid`'s groups in the user database: its primary group and every group that lists it.
    Empty when the uid has no user entry."""
    try:
        entry = pwd.getpwuid(uid)
    except KeyError:
        return set()
    return {entry.pw_gid, *os.getgrouplist(entry.pw_name, entry.pw_gid)}


def _who(uid: int) -> str:
    name = user_name(uid)
    return f"uid {uid} ({name})" if name else f"uid {uid} (no user entry)"


def allowed_description(settings: ArmingSettings, daemon_uid: int) -> str:
    """Who may arm under these settings, in words."""
    if not settings.users and not settings.groups:
        return f"the daemon's own user, {_who(daemon_uid)}, over the Unix socket"
    return (f"users {list(settings.users)} and members of groups {list(settings.groups)}"
            " (daemon.arming.users, daemon.arming.groups), over the Unix socket")


def arm_refusal(peer: Mapping[str, Any], settings: ArmingSettings,
                daemon_uid: int) -> str | None:
    """None when the Unix-socket peer (`peer_credentials`) may arm; otherwise why not, naming the
    uid and user and the settings that would allow it."""
    uid = peer.get("uid")
    if not isinstance(uid, int):
        return "the peer's uid is unknown (no SO_PEERCRED): arming needs the Unix socket"
    users, groups = list(settings.users), list(settings.groups)
    if not users and not groups:
        if uid == daemon_uid:
            return None
        name = user_name(uid)
        return (f"{_who(uid)} may not arm the lasers: daemon.arming.users and daemon.arming.groups "
                f"are empty, so only the daemon's own user may ({_who(daemon_uid)}); to allow "
                f"it, add {name or uid!r} to daemon.arming.users or one of its groups to "
                "daemon.arming.groups")
    name = user_name(uid)
    if name is not None and name in users:
        return None
    gids = groups_of(uid)
    for group in groups:
        try:
            if grp.getgrnam(group).gr_gid in gids:
                return None
        except KeyError:  # no such group (warned at start): it admits no one
            continue
    mine = ", ".join(sorted(group_name(g) for g in gids)) or "none"
    return (f"{_who(uid)} may not arm the lasers: not in daemon.arming.users = {users}, and none "
            f"of its groups ({mine}) is in daemon.arming.groups = {groups}; to allow it, add "
            "the user or one of its groups there")


def check_confirm_settings(settings: ArmingSettings, navigator_backend: str) -> None:
    """ConfigError naming the keys when a confirmation is configured without its input."""
    if settings.confirm == "serial" and not settings.confirm_port.strip():
        raise ConfigError("daemon.arming.confirm = 'serial' needs daemon.arming.confirm_port: the "
                          "serial device whose CTS or DSR line the key switch drives (e.g. "
                          f"/dev/serial/by-id/...), or {SIMULATED_PORT!r} for the simulated one")
    if settings.confirm == "spacemouse" and navigator_backend == "none":
        raise ConfigError("daemon.arming.confirm = 'spacemouse' needs a navigator: "
                          "devices.navigator = 'spacemouse' (or 'simulated' on the simulated "
                          "bench), not 'none'")


# -- confirmation inputs ------------------------------------------------------------------------


class _KeyTurn:
    """A key switch turned on after the request."""

    def __init__(self, switch: KeySwitch) -> None:
        self.switch = switch
        self.what = f"the key switch ({switch.describe})"
        self.prompt = f"turn {self.what} on (off first if it is on)"

    def start(self) -> None:
        self.switch.open()
        try:
            self.switch.expect_turn()
        except BaseException:
            self.switch.close()
            raise

    def confirmed(self) -> bool:
        return self.switch.turned()

    def hint(self) -> str:
        return ("" if self.switch.seen_off else "; the key was on throughout: a confirmation is "
                "a turn from off to on after the request")

    def stop(self) -> None:
        self.switch.close()


class _ButtonPress:
    """A navigator button gone down after the request (the control loop reads the navigator;
    this only watches its press count)."""

    def __init__(self, navigation: NavigatorState) -> None:
        self.navigation = navigation
        nav = navigation.navigator
        product = getattr(nav, "product", "") or type(nav).__name__
        self.what = f"a button of the navigator ({product})"
        self.prompt = f"press {self.what}"
        self._base = 0

    def _navigator(self) -> Any:
        nav = self.navigation.navigator
        if nav is None:
            raise DeviceError(f"the navigator closed while an arm waited for it "
                              f"({self.navigation.error or 'no error recorded'})")
        return nav

    def start(self) -> None:
        self._base = self._navigator().presses

    def confirmed(self) -> bool:
        return self._navigator().presses > self._base

    def hint(self) -> str:
        return ""

    def stop(self) -> None:
        pass


# -- the gate -----------------------------------------------------------------------------------


class ArmingGate:
    """Decides every `laser arm` request: authority first, then the configured confirmation.

    One per daemon (`Daemon.arming`). At most one arm waits for confirmation at a time; `cancel`
    (from `laser off` / `disarm`) guarantees it does not arm afterwards."""

    def __init__(self, settings: ArmingSettings, navigator_backend: str, *, laser: LaserLink,
                 audit: AuditLog, bench_jobs: JobRunner, navigation: NavigatorState,
                 daemon_uid: int | None = None, key_opener: LinesOpener | None = None) -> None:
        """`settings`: `[daemon.arming]` (who may arm, the confirmation and its input).
        `navigator_backend`: `devices.navigator` (a SpaceMouse confirmation needs one).
        `laser`: what arms. `audit`: where each outcome is written. `bench_jobs`: the runner
        a confirmation waits on (BUSY when its queue is full). `navigation`: the navigator a
        button press is read from. `daemon_uid`: the daemon's user (default: this process's
        effective uid). `key_opener`: the key switch's lines (default: from the settings)."""
        check_confirm_settings(settings, navigator_backend)
        self.settings = settings
        self.laser = laser
        self.audit = audit
        self.bench_jobs = bench_jobs
        self.navigation = navigation
        self.daemon_uid = os.geteuid() if daemon_uid is None else daemon_uid
        self.twin: KeySwitchTwin | None = None
        port = settings.confirm_port.strip()
        if settings.confirm == "serial" and key_opener is None:
            if port == SIMULATED_PORT:
                self.twin = KeySwitchTwin(settings.confirm_line, port=SIMULATED_PORT)
                key_opener = self.twin.opener
            else:
                key_opener = functools.partial(open_serial_lines, port)
        self._key_opener = key_opener
        self._lock = threading.Lock()
        self._pending: Job | None = None
        self.listening: int | None = None  # the job whose confirmation window is open now
        for user in settings.users:
            try:
                pwd.getpwnam(user)
            except KeyError:
                log.warning("daemon.arming.users names %r, which is no user here: it admits no one",
                            user)
        for group in settings.groups:
            try:
                grp.getgrnam(group)
            except KeyError:
                log.warning("daemon.arming.groups names %r, which is no group here: it admits no "
                            "one", group)

    # -- requests ------------------------------------------------------------------------------

    def authorise(self, conn: Connection) -> None:
        """RpcError(FORBIDDEN) unless `conn` may arm: the Unix socket, an allowed uid, and (defence
        in depth only) not an sshd peer."""
        allowed = allowed_description(self.settings, self.daemon_uid)
        if conn.transport != "unix":
            # A person arms from the bench's machine, identified by uid; never over the network.
            raise RpcError(FORBIDDEN, "arming is accepted only over the Unix socket",
                           {"field": "action", "allowed": allowed})
        if conn.peer.get("web_client"):
            # The web view runs in this process, as this user: the kernel's uid cannot tell its
            # connection from a person's, its own marking (`web_client`) can.
            raise RpcError(FORBIDDEN, "arming is not possible from the web view: a person arms "
                           "at the bench (nhfctl laser arm)", {"field": "action",
                                                               "allowed": allowed})
        why = arm_refusal(conn.peer, self.settings, self.daemon_uid)
        if why is not None:
            raise RpcError(FORBIDDEN, why, {"field": "action", "allowed": allowed})
        if forwarded_by_ssh(conn.peer):
            raise RpcError(FORBIDDEN, "arming is refused through an SSH tunnel: a person arms "
                           "on the bench's machine", {"field": "action", "allowed": allowed})

    def authorise_emission(self, conn: Connection, what: str) -> None:
        """RpcError(FORBIDDEN) when `conn` is a remote peer (TCP, the web view's clients) asking
        for `what`, something that makes a laser emit, and `daemon.arming.remote_emission` is
        false: a person at the bench starts emission, as they arm. `laser off` and `disarm` are
        never asked about."""
        if conn.remote and not self.settings.remote_emission:
            raise RpcError(FORBIDDEN, f"{what} makes a laser emit, and {conn.describe()} may not "
                           "start that (daemon.arming.remote_emission = false): ask from the "
                           "bench's machine (nhfctl over the Unix socket), or set "
                           "daemon.arming.remote_emission = true",
                           {"field": "daemon.arming.remote_emission",
                            "allowed": "the Unix socket"})

    def arm(self, conn: Connection, duration_s: float) -> dict[str, Any]:
        """The `laser arm` request: armed now (no confirmation configured), or a pending job
        that waits for the person at the bench."""
        self.authorise(conn)
        uid = conn.peer.get("uid")
        if self.settings.confirm == "none":
            reply = self.laser.arm(duration_s)
            return {"armed": True, "armed_remaining_s": reply.get("armed_remaining_s"),
                    "by_uid": uid}
        source = self._source()
        timeout_s = self.settings.confirm_timeout_s
        who = conn.who
        with self._lock:
            pending = self._pending
            if pending is not None and not pending.done.is_set():
                raise RpcError(BUSY, f"an arm request (job {pending.id}) is already waiting for "
                               "its confirmation; wait for it, or send laser off",
                               {"field": "action", "job": pending.id})
            job = Job("laser arm", {"duration_s": duration_s, "confirm": source.what,
                                    "timeout_s": timeout_s, "by_uid": uid,
                                    "by_user": conn.peer.get("user")},
                      lambda job: self._wait_and_arm(who, duration_s, source, job))
            submit_or_busy(self.bench_jobs, job)  # BUSY when the bench queue is full
            self._pending = job
        return {"armed": False, "pending": True, "job": job.id, "confirm": source.what,
                "prompt": f"{source.prompt} within {timeout_s:g} s", "timeout_s": timeout_s,
                "by_uid": uid}

    def cancel(self) -> int | None:
        """Cancel the arm waiting for confirmation (the id of its job, None if there was none).
        Once this returns, that job cannot arm: its last check and the arm itself hold the same
        lock."""
        with self._lock:
            job = self._pending
            if job is None or job.done.is_set():
                return None
            job.cancel.set()
            return job.id

    def close(self) -> None:
        """At shutdown, before the lasers go off: nothing pending may arm after them."""
        self.cancel()

    def status(self) -> dict[str, Any]:
        """The confirmation configured, the arm waiting for it (its job) and whether its
        window is open now."""
        job = self._pending
        return {"confirm": self.settings.confirm,
                "pending_job": job.id if job is not None and not job.done.is_set() else None,
                "listening": self.listening is not None}

    # -- the wait (a bench job's thread) ---------------------------------------------------------

    def _source(self) -> _KeyTurn | _ButtonPress:
        """The configured input, or NOT_AVAILABLE (at once, not after the wait) when it cannot
        be read."""
        if self.settings.confirm == "serial":
            assert self._key_opener is not None  # set in __init__ for "serial"
            return _KeyTurn(KeySwitch(self._key_opener, self.settings.confirm_line,
                                      self.settings.confirm_port.strip()))
        if self.navigation.navigator is None:
            raise RpcError(NOT_AVAILABLE, "daemon.arming.confirm = 'spacemouse', but no navigator "
                           f"is open ({self.navigation.error or 'devices.navigator'}): nothing "
                           "at the bench can confirm an arm", {"device": "navigator"})
        return _ButtonPress(self.navigation)

    def _wait_and_arm(self, who: dict[str, Any], duration_s: float,
                      source: _KeyTurn | _ButtonPress, job: Job) -> dict[str, Any]:
        timeout_s = self.settings.confirm_timeout_s
        try:
            waited_s = self._wait(source, job, timeout_s)
            with self._lock:
                job.check()  # a laser off, disarm or stop since the request wins
                reply = self.laser.arm(duration_s)
        except Cancelled:
            self.audit.write(who, "laser arm cancelled", job=job.id,
                             outcome="cancelled: laser off, disarm or stop before the "
                                     "confirmation; not armed")
            raise
        except Exception as exc:
            self.audit.write(who, "laser arm refused", job=job.id, confirm=source.what,
                             outcome=f"refused: {exc}")
            raise
        self.audit.write(who, "laser arm confirmed", job=job.id, confirm=source.what,
                         waited_s=round(waited_s, 3), duration_s=duration_s, outcome="armed")
        return {"armed": True, "armed_remaining_s": reply.get("armed_remaining_s"),
                "by_uid": who.get("uid"), "confirmed_by": source.what,
                "waited_s": round(waited_s, 3)}

    def _wait(self, source: _KeyTurn | _ButtonPress, job: Job, timeout_s: float) -> float:
        """Seconds until the confirmation came; ArmNotConfirmed after `timeout_s`."""
        job.check()
        source.start()
        try:
            start = time.monotonic()
            self.listening = job.id
            while not source.confirmed():
                job.check()
                if time.monotonic() - start >= timeout_s:
                    raise ArmNotConfirmed(
                        f"no confirmation from {source.what} within {timeout_s:g} s "
                        f"(daemon.arming.confirm_timeout_s): the lasers stay disarmed"
                        f"{source.hint()}")
                time.sleep(POLL_S)
            return time.monotonic() - start
        finally:
            self.listening = None
            source.stop()
