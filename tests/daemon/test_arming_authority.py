"""Arming follows authority, not a process name (issue 32, item 2).

Who may arm is the Unix-socket peer's uid as the kernel reports it (SO_PEERCRED) and that uid's
groups, against `daemon.arming.users` / `groups` (default: the daemon's own user). A relay that
runs as an allowed user is that user to the kernel, so an optional confirmation by a person at
the bench (a key switch on a serial line, a navigator button) must come within
`confirm_timeout_s`: the wait is a bench job, and the control loop goes on meanwhile. Every
claim about light is read from the laser twin's emission record.
"""

from __future__ import annotations

import contextlib
import grp
import json
import os
import pwd
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import nhfd.daemon.server as server_module
from nhfd.cli.nhfctl import main
from nhfd.config import ArmingSettings, ConfigError
from nhfd.daemon.arming import ArmingGate, arm_refusal, check_confirm_settings, groups_of
from nhfd.daemon.protocol import RpcError
from nhfd.daemon.server import Connection

from .conftest import Running, bench_config, wait_until

ME = os.geteuid()
MY_NAME = pwd.getpwuid(ME).pw_name
KEY = "the key switch (CTS of simulated)"


def settings(**arming: Any) -> ArmingSettings:
    """`[daemon.arming]` with the keys given."""
    return ArmingSettings(**arming)


def other_uid() -> int:
    """A uid that is not this process's: `nobody` where it exists."""
    try:
        uid = pwd.getpwnam("nobody").pw_uid
    except KeyError:
        uid = ME + 12345
    return uid if uid != ME else ME + 12345


def foreign_group() -> str | None:
    """A group this user is not a member of (None on a system where it is in all)."""
    mine = groups_of(ME)
    return next((g.gr_name for g in grp.getgrall() if g.gr_gid not in mine), None)


def audit(root: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (root / "run" / "audit.jsonl").read_text().splitlines()]


@contextlib.contextmanager
def daemon(short_dir: Path, twin: Any, *, navigator: str | None = None, **arming: Any
           ) -> Iterator[Running]:  # fmt: skip
    """A running daemon with `arming` as its `[daemon.arming]` keys."""
    config = bench_config(short_dir, twin, arming=arming)
    if navigator is not None:
        config = config.model_copy(update={"devices": config.devices.model_copy(
            update={"navigator": navigator})})
    r = Running(config, short_dir)
    try:
        yield r
    finally:
        r.stop()


# -- authority: the kernel's uid and the user database's groups ---------------------------------


def test_by_default_only_the_daemons_own_uid_may_arm_and_a_refusal_names_uid_and_settings():
    s = settings()
    assert arm_refusal({"uid": ME}, s, ME) is None
    uid = other_uid()
    why = arm_refusal({"uid": uid, "process": "nhfctl"}, s, ME)
    name = pwd.getpwuid(uid).pw_name if uid in {p.pw_uid for p in pwd.getpwall()} else None
    assert why is not None and why.startswith(f"uid {uid} (")
    assert (f"({name})" if name else "(no user entry)") in why
    assert "daemon.arming.users and daemon.arming.groups are empty" in why
    assert f"only the daemon's own user may (uid {ME} ({MY_NAME}))" in why
    # A uid the user database does not know is refused too, saying so.
    assert "(no user entry)" in arm_refusal({"uid": 3_999_999}, s, ME)
    # No uid at all (not a Unix-socket peer): refused.
    assert "uid is unknown" in arm_refusal({}, s, ME)


def test_arming_users_replace_the_default_by_name():
    assert arm_refusal({"uid": ME}, settings(users=[MY_NAME]), ME) is None
    # Listed users only: the daemon's own user is no longer implied.
    why = arm_refusal({"uid": ME}, settings(users=["no-such-user-nhfd"]), ME)
    assert why is not None and f"uid {ME} ({MY_NAME}) may not arm" in why
    assert "daemon.arming.users = ['no-such-user-nhfd']" in why
    assert "daemon.arming.groups = []" in why


def test_membership_of_any_of_the_uids_groups_allows_arming():
    entry = pwd.getpwuid(ME)
    mine = groups_of(ME)
    # The primary group and every supplementary group the user database lists for this user.
    assert mine == {entry.pw_gid, *os.getgrouplist(entry.pw_name, entry.pw_gid)}
    for gid in sorted(mine):
        name = grp.getgrgid(gid).gr_name
        # Another uid as the daemon's: only the group can be what allows it.
        assert arm_refusal({"uid": ME}, settings(groups=[name]), ME + 1) is None, name
    other = foreign_group()
    if other is not None:
        why = arm_refusal({"uid": ME}, settings(groups=[other]), ME)
        assert why is not None and f"daemon.arming.groups = [{other!r}]" in why
        assert grp.getgrgid(entry.pw_gid).gr_name in why  # the user's groups, named


def gate_of(arming: ArmingSettings, navigator_backend: str = "none") -> ArmingGate:
    """A gate for what is decided before anything arms (authority, the settings' checks): its
    collaborators are never called."""
    unused: Any = None
    return ArmingGate(arming, navigator_backend, laser=unused, audit=unused,
                      bench_jobs=unused, navigation=unused)


def test_tcp_and_the_web_views_connection_are_refused_whatever_their_uid():
    gate = gate_of(settings())
    cases = {"tcp": ({"address": "127.0.0.1:5000", "uid": ME},
                     "arming is accepted only over the Unix socket"),
             "unix": ({"uid": ME, "pid": os.getpid(), "web_client": {"via": "web view"}},
                      "arming is not possible from the web view")}
    for transport, (peer, message) in cases.items():
        with pytest.raises(RpcError) as info:
            gate.authorise(Connection(None, transport, peer))  # type: ignore[arg-type]
        assert info.value.name == "forbidden" and info.value.message.startswith(message)
    gate.authorise(Connection(None, "unix", {"uid": ME}))  # the same uid, at the bench: fine


def test_a_confirmation_without_its_input_is_a_configuration_error_naming_the_keys():
    with pytest.raises(ConfigError, match=r"daemon.arming.confirm = 'serial' needs "
                       r"daemon.arming.confirm_port"):
        check_confirm_settings(settings(confirm="serial"), "none")
    with pytest.raises(ConfigError, match=r"'spacemouse' needs a navigator: devices.navigator"):
        gate_of(settings(confirm="spacemouse"), "none")
    gate_of(settings(confirm="spacemouse"), "simulated")  # a navigator: fine


def test_a_peer_whose_uid_is_not_allowed_is_refused_and_audited(short_dir, mecom_twin,
                                                                   monkeypatch):
    uid = other_uid()
    real = server_module.peer_credentials

    def as_another_user(sock: Any) -> dict[str, Any]:
        return {**real(sock), "uid": uid, "user": None}

    with daemon(short_dir, mecom_twin) as r:
        monkeypatch.setattr(server_module, "peer_credentials", as_another_user)
        with r.client() as c, pytest.raises(RpcError) as info:
            c.call("laser", action="arm", duration_s=30.0)
        monkeypatch.setattr(server_module, "peer_credentials", real)
        assert info.value.name == "forbidden"
        assert info.value.message.startswith(f"uid {uid} (")
        assert "daemon.arming.users" in info.value.message
        assert info.value.data["allowed"] == (f"the daemon's own user, uid {ME} ({MY_NAME}), "
                                              "over the Unix socket")
        with r.client() as c:
            assert c.status()["laser"]["armed"] is False
            with pytest.raises(RpcError, match="arm"):  # the guardian refuses: not armed
                c.call("laser", action="enable", channel="red")
        refused = [e for e in audit(short_dir) if e["who"].get("uid") == uid]
        assert refused and refused[0]["outcome"].startswith("refused")
    assert mecom_twin.max_emitted_pct() == 0.0


@pytest.mark.parametrize("member", [True, False])
def test_arming_groups_decide_over_the_socket(short_dir, mecom_twin, member):
    group = grp.getgrgid(pwd.getpwuid(ME).pw_gid).gr_name if member else foreign_group()
    if group is None:
        pytest.skip("this user is a member of every group here")
    # The daemon runs as this user: with daemon.arming.groups set, the group alone decides.
    with daemon(short_dir, mecom_twin, groups=[group]) as r, r.client() as c:
        if member:
            assert c.call("laser", action="arm", duration_s=30.0)["armed"] is True
            return
        with pytest.raises(RpcError,
                           match=re.escape(f"daemon.arming.groups = [{group!r}]")) as info:
            c.call("laser", action="arm", duration_s=30.0)
        assert info.value.name == "forbidden"
        assert c.status()["laser"]["armed"] is False


# -- the confirmation at the bench ----------------------------------------------------------------

RELAY = """if True:
    import os, socket, sys, threading
    listen, target = sys.argv[1], sys.argv[2]
    srv = socket.socket(socket.AF_UNIX)
    srv.bind(listen)
    srv.listen(4)
    def pump(a, b):
        try:
            while data := a.recv(65536):
                b.sendall(data)
        except OSError:
            pass
        for s in (a, b):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
    print("ready", flush=True)
    while True:
        c, _ = srv.accept()
        u = socket.socket(socket.AF_UNIX)
        u.connect(target)
        for a, b in ((c, u), (u, c)):
            threading.Thread(target=pump, args=(a, b), daemon=True).start()
"""


@contextlib.contextmanager
def relay(listen: Path, target: Path) -> Iterator[subprocess.Popen[str]]:
    """A Unix-to-Unix forwarder in its own process, as this user (what `ssh -L` or socat is)."""
    proc = subprocess.Popen([sys.executable, "-c", RELAY, str(listen), str(target)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        yield proc
    finally:
        proc.kill()
        proc.wait(10)


def test_a_relay_as_the_same_user_cannot_arm_when_the_confirmation_is_not_given(short_dir,
                                                                                mecom_twin):
    from nhfd.daemon.client import Client

    with daemon(short_dir, mecom_twin, confirm="serial", confirm_port="simulated",
                confirm_timeout_s=1.0) as r, relay(short_dir / "relay.sock",
                                                      r.socket) as proc:
        with Client(short_dir / "relay.sock") as c:
            reply = c.call("laser", action="arm", duration_s=30.0)
            assert reply["armed"] is False and reply["pending"] is True
            assert reply["confirm"] == KEY and reply["timeout_s"] == 1.0
            job = c.wait_job(reply["job"], timeout_s=10)
        assert job["state"] == "failed"
        assert job["error"] == (f"ArmNotConfirmed: no confirmation from {KEY} within 1 s "
                                "(daemon.arming.confirm_timeout_s): the lasers stay disarmed")
        with r.client() as c:
            assert c.status()["laser"]["armed"] is False
            with pytest.raises(RpcError, match="arm"):
                c.call("laser", action="enable", channel="red")
        # Audited with the relay's identity, as the kernel gave it.
        refused = [e for e in audit(short_dir) if e["what"] == "laser arm refused"]
        assert len(refused) == 1 and refused[0]["who"]["pid"] == proc.pid
        assert refused[0]["outcome"].startswith("refused: no confirmation from")
    assert mecom_twin.max_emitted_pct() == 0.0


def test_the_key_switch_confirms_while_the_loop_runs_on_and_a_key_left_on_must_turn(
        short_dir, mecom_twin):
    with daemon(short_dir, mecom_twin, confirm="serial", confirm_port="simulated",
                confirm_timeout_s=20.0) as r, r.client() as c:
        twin = r.daemon.arming.twin
        twin.turn(True)  # left on from before: it does not confirm by itself
        reply = c.call("laser", action="arm", duration_s=30.0)
        wait_until(lambda: r.daemon.arming.listening == reply["job"], 5, "the arm's wait")
        # The control loop serves requests while the arm waits: the job shows as running.
        for _ in range(3):
            jobs = {j["id"]: j for j in c.status()["jobs"]}
            assert jobs[reply["job"]]["state"] == "running"
            assert jobs[reply["job"]]["kind"] == "laser arm"
            assert c.status()["laser"]["armed"] is False
        twin.turn(False)
        seen = twin.reads
        wait_until(lambda: twin.reads > seen + 1, 5, "the key read while off")
        assert c.wait_job(reply["job"], timeout_s=0)["state"] == "running"  # off: no arm yet
        twin.turn(True)  # off, then on: a person turned it
        job = c.wait_job(reply["job"], timeout_s=10)
        assert job["state"] == "done", job
        assert job["result"]["armed"] is True and job["result"]["confirmed_by"] == KEY
        c.call("laser", action="power", channel="red", power_pct=5.0)
        c.call("laser", action="enable", channel="red")
        assert mecom_twin.emitting()["red"] == 5.0  # armed for real
        c.call("laser", action="off")
        confirmed = [e for e in audit(short_dir) if e["what"] == "laser arm confirmed"]
        assert len(confirmed) == 1 and confirmed[0]["who"]["uid"] == ME
        # The driver asserted the outputs that power the switch.
        assert ("dtr", True) in twin.outputs and ("rts", True) in twin.outputs
        assert twin.opens == twin.closes == 1  # the port is held only while an arm waits


def test_laser_off_cancels_an_arm_waiting_for_its_confirmation(short_dir, mecom_twin):
    with daemon(short_dir, mecom_twin, confirm="serial", confirm_port="simulated",
                confirm_timeout_s=20.0) as r, r.client() as c:
        reply = c.call("laser", action="arm", duration_s=30.0)
        with pytest.raises(RpcError, match=r"already waiting for its confirmation") as info:
            c.call("laser", action="arm", duration_s=30.0)
        assert info.value.name == "busy"
        wait_until(lambda: r.daemon.arming.listening == reply["job"], 5, "the arm's wait")
        off = c.call("laser", action="off")
        assert off == {"armed": False, "all_off": True, "cancelled_arm_job": reply["job"]}
        job = c.wait_job(reply["job"], timeout_s=10)
        assert job["state"] == "cancelled"
        r.daemon.arming.twin.turn(True)  # too late: nothing waits for it
        assert c.status()["laser"]["armed"] is False
        assert [e["what"] for e in audit(short_dir)].count("laser arm cancelled") == 1


def test_a_navigator_button_confirms_an_arm(short_dir, mecom_twin):
    with daemon(short_dir, mecom_twin, navigator="simulated", confirm="spacemouse",
                confirm_timeout_s=20.0) as r, r.client() as c:
        reply = c.call("laser", action="arm", duration_s=30.0)
        assert reply["confirm"] == "a button of the navigator (SimulatedNavigator)"
        wait_until(lambda: r.daemon.arming.listening == reply["job"], 5, "the arm's wait")
        r.daemon.navigation.navigator.press(1)
        job = c.wait_job(reply["job"], timeout_s=10)
        assert job["state"] == "done" and job["result"]["armed"] is True, job
        assert c.status()["laser"]["armed"] is True


def test_nhfctl_laser_arm_says_what_the_bench_must_do_and_waits(short_dir, mecom_twin, capsys):
    with daemon(short_dir, mecom_twin, confirm="serial", confirm_port="simulated",
                confirm_timeout_s=20.0) as r:
        codes: list[int] = []
        t = threading.Thread(target=lambda: codes.append(main(
            ["--socket", str(r.socket), "laser", "arm", "--duration-s", "30"])))
        t.start()
        wait_until(lambda: r.daemon.arming.listening is not None, 5, "the arm's wait")
        r.daemon.arming.twin.turn(True)
        t.join(10)
        assert codes == [0]
        out = capsys.readouterr()
        assert out.err.startswith(f"nhfctl laser arm: waiting for the person at the bench to "
                                  f"turn {KEY} on (off first if it is on) within 20 s (job ")
        assert "armed yes" in out.out and f"confirmed by {KEY}" in out.out
