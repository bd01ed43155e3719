"""The daemon against a faulty or foreign laser guardian (issue 21, laser safety 1-5): a hung
guardian, an impostor, two daemons, an orphan. Every claim about light is read from the laser
twin's emission record, never from the daemon's own word."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from nhfd.daemon.service import Daemon
from nhfd.device_settings import GuardianSettings, LaserSettings
from nhfd.drivers.guardian import GuardianRefused, alive, port_holders, spawn_guardian
from nhfd.drivers.twins.mecom_twin import MecomTwin

from .conftest import Running, bench_config, free_port, wait_until

OFF = {"red": 0.0, "green": 0.0, "blue": 0.0}


def light_red(client, twin, pct: float = 5.0) -> None:
    client.call("laser", action="arm", duration_s=60.0)
    client.call("laser", action="power", channel="red", power_pct=pct)
    client.call("laser", action="enable", channel="red")
    assert twin.emitting()["red"] == pct


@contextlib.contextmanager
def stopped(pid: int) -> Iterator[None]:
    """SIGSTOP `pid`; whatever happens, it is continued (if still there) afterwards."""
    os.kill(pid, signal.SIGSTOP)
    try:
        yield
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)


# ---------------------------------------------------------------------------- 1. hung guardian


@pytest.mark.parametrize("how", ["heartbeat", "nhfctl laser off"])
def test_a_hung_guardian_the_daemon_started_is_killed_and_replaced_lasers_off(short_dir,
                                                                              mecom_twin, how):
    r = Running(bench_config(short_dir, mecom_twin), short_dir)
    try:
        with r.client() as c:
            light_red(c, mecom_twin)
            st = c.status()["laser"]
            old = st["guardian"]["pid"]
            assert st["guardian"]["spawned"] and old == st["guardian"]["spawned_pid"]
            with stopped(old):
                frozen = time.monotonic()
                if how != "heartbeat":  # answered only once a new guardian read it back off
                    assert c.call("laser", action="off") == {"armed": False, "all_off": True}
                    assert mecom_twin.emitting() == OFF
                wait_until(lambda: mecom_twin.dark_since() is not None, 5, "lasers off")
                dark = mecom_twin.dark_since()
            # Off well inside the issue's second on an idle machine (`nhfd bench safety`
            # measures it); the margin here is for a loaded test machine.
            assert dark - frozen < 2.0
            assert not alive(old)  # SIGKILLed by pid, not merely abandoned
            wait_until(lambda: c.status()["laser"]["guardian"]["pid"] not in (None, old), 5,
                       "the new guardian")
            st = c.status()["laser"]
            assert st["guardian"]["spawned"] and st["guardian"]["replaced"] == 1
            assert st["error"] is None and st["armed"] is False  # arming is never restored
            # The twin's own end (this process) and the new guardian hold the port, nobody else.
            assert set(port_holders(mecom_twin.port_path)) == {os.getpid(),
                                                               st["guardian"]["pid"]}
    finally:
        r.stop()
    assert mecom_twin.emitting() == OFF


def test_connect_mode_reports_an_unresponsive_guardian_as_unknown_never_off(short_dir,
                                                                            mecom_twin, caplog):
    sock = short_dir / "laser.sock"
    settings = LaserSettings(port=mecom_twin.port_path, reply_timeout_s=0.2,
                             guardian=GuardianSettings(socket_path=str(sock),
                                                       heartbeat_timeout_s=0.5))
    guardian = spawn_guardian(settings, socket_path=sock, stderr=subprocess.DEVNULL)
    r = None
    try:
        r = Running(bench_config(short_dir, mecom_twin, arming={"guardian": "connect"}), short_dir)
        with r.client() as c:
            light_red(c, mecom_twin)
            assert c.status()["laser"]["guardian"]["spawned"] is False
            with stopped(guardian.pid):
                wait_until(lambda: "guardian unresponsive" in (c.status()["laser"]["error"]
                                                               or ""), 5, "unknown state")
                st = c.status()["laser"]
                assert st["error"].startswith("laser state unknown: guardian unresponsive")
                assert st["state"] == "laser state unknown: guardian unresponsive"
                assert st["channels"] == {}  # no stale read-back shown as current
                # The daemon may not end a guardian it does not own: light is still on, and
                # nothing said otherwise.
                assert mecom_twin.emitting()["red"] == 5.0 and alive(guardian.pid)
            assert "lasers are off" not in caplog.text
            assert "laser state unknown: guardian unresponsive" in caplog.text
            # Continued, it sees its controller gone and switches off; the daemon reconnects.
            wait_until(lambda: mecom_twin.dark_since() is not None, 5, "lasers off")
            wait_until(lambda: c.status()["laser"]["error"] is None, 5, "reconnected")
    finally:
        if r is not None:
            r.stop()
        guardian.kill()
        guardian.wait(5)
    assert mecom_twin.emitting() == OFF


# ------------------------------------------------------------------------- 2. impostor guardian


class FakeGuardian:
    """Answers every request on `sock` with "ok, all off" (and a hello claiming `port`)."""

    def __init__(self, sock: Path, port: str = "") -> None:
        self.server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.server.bind(str(sock))
        self.server.listen(4)
        self.server.settimeout(0.1)
        self.port = port
        self.asked: list[str] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _reply(self, op: str) -> dict:
        self.asked.append(op)
        return {"ok": True, "off": True, "pid": os.getpid(), "port": self.port, "armed": False,
                "fault": None, "channels": {ch: {"enabled": False, "power_pct": 0.0}
                                            for ch in OFF}}

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.server.accept()
            except TimeoutError:
                continue
            with conn, conn.makefile("rwb") as f:
                for line in f:
                    f.write(json.dumps(self._reply(json.loads(line)["op"])).encode() + b"\n")
                    f.flush()

    def close(self) -> None:
        self._stop.set()
        self.thread.join(2)
        self.server.close()


def fake_config(root: Path, twin: MecomTwin, sock: Path):
    cfg = bench_config(root, twin)
    laser = cfg.devices.readybeam
    laser = laser.model_copy(update={"guardian": laser.guardian.model_copy(
        update={"socket_path": str(sock)})})
    return cfg.model_copy(update={"devices": cfg.devices.model_copy(
        update={"readybeam": laser})})


@pytest.mark.parametrize("mode", [0o777, 0o757])
def test_a_fake_guardian_in_a_directory_others_may_write_is_refused(short_dir, mecom_twin, mode):
    mecom_twin.set_state("red", enabled=1, power_pct=7.0)  # emitting, and nobody says otherwise
    unsafe = short_dir / "shared"
    unsafe.mkdir()
    unsafe.chmod(mode)
    fake = FakeGuardian(unsafe / "laser.sock", port=mecom_twin.port_path)
    try:
        daemon = Daemon(fake_config(short_dir, mecom_twin, unsafe / "laser.sock"),
                        base_dir=short_dir, env={}, handle_signals=False)
        with pytest.raises(GuardianRefused) as info:
            daemon.start()
        assert f"{unsafe} is writable by other users (owner uid {os.getuid()}, mode " \
               f"{mode:04o})" in str(info.value)
        assert fake.asked == []  # not even asked
    finally:
        fake.close()
    assert mecom_twin.emitting()["red"] == 7.0


def test_a_fake_guardian_that_answers_all_off_is_refused_by_the_daemon(short_dir, mecom_twin):
    mecom_twin.set_state("red", enabled=1, power_pct=7.0)
    sock = short_dir / "laser.sock"  # a safe directory: the fake runs as this user
    fake = FakeGuardian(sock, port=mecom_twin.port_path)  # ...and lies about the port
    try:
        daemon = Daemon(fake_config(short_dir, mecom_twin, sock), base_dir=short_dir, env={},
                        handle_signals=False)
        with pytest.raises(GuardianRefused, match="is not an nhfd laser guardian of this user"):
            daemon.start()
        assert "off" not in fake.asked  # never trusted for the all-off
    finally:
        fake.close()
    assert mecom_twin.emitting()["red"] == 7.0


def test_a_runtime_directory_of_another_owner_or_mode_is_refused(short_dir, mecom_twin):
    run = short_dir / "run"
    run.mkdir()
    run.chmod(0o770)  # group-writable, and no daemon.server.socket_group configured
    daemon = Daemon(bench_config(short_dir, mecom_twin), base_dir=short_dir, env={},
                    handle_signals=False)
    with pytest.raises(Exception, match=f"{run} is group-writable .*mode 0770.*socket_group"):
        daemon.start()
    assert mecom_twin.requests == []  # no guardian started, nothing sent to the laser


# ----------------------------------------------------------------------- 3. two daemons, one laser


def test_two_daemons_with_two_runtime_dirs_get_two_guardians(short_dir):
    twins = [MecomTwin(), MecomTwin()]
    running: list[Running] = []
    try:
        for i, twin in enumerate(twins):
            twin.start()
            root = short_dir / f"d{i}"
            root.mkdir()
            cfg = bench_config(root, twin)
            laser = cfg.devices.readybeam
            laser = laser.model_copy(update={"guardian": laser.guardian.model_copy(
                update={"socket_path": ""})})  # the default: follows the runtime directory
            cfg = cfg.model_copy(update={"devices": cfg.devices.model_copy(
                update={"readybeam": laser})})
            running.append(Running(cfg, root))
        a, b = (r.client() for r in running)
        sa, sb = a.status()["laser"]["guardian"], b.status()["laser"]["guardian"]
        assert sa["socket"] == str(short_dir / "d0" / "run" / "laser.sock")
        assert sb["socket"] == str(short_dir / "d1" / "run" / "laser.sock")
        assert sa["pid"] != sb["pid"] and sa["port"] == twins[0].port_path
        light_red(b, twins[1])
        assert twins[0].max_emitted_pct() == 0.0  # daemon A's laser never lit
        a.close()
        b.close()
    finally:
        for r in running:
            r.stop()
        for twin in twins:
            twin.close()


def test_a_found_guardian_driving_another_port_is_refused_by_name(short_dir, mecom_twin):
    sock = short_dir / "laser.sock"
    with MecomTwin() as other:
        settings = LaserSettings(port=other.port_path, reply_timeout_s=0.2,
                                 guardian=GuardianSettings(socket_path=str(sock)))
        guardian = spawn_guardian(settings, socket_path=sock, stderr=subprocess.DEVNULL)
        try:
            daemon = Daemon(bench_config(short_dir, mecom_twin), base_dir=short_dir, env={},
                            handle_signals=False)
            with pytest.raises(GuardianRefused) as info:
                daemon.start()
            assert (f"(pid {guardian.pid}) drives port {other.port_path!r}, not "
                    f"{mecom_twin.port_path!r}; refusing it") in str(info.value)
            assert guardian.poll() is None  # another daemon's guardian is left alone
        finally:
            guardian.kill()
            guardian.wait(5)


# ---------------------------------------------------------------------------------- 5. orphans


def test_the_tcp_token_is_removed_at_shutdown(short_dir, mecom_twin):
    r = Running(bench_config(short_dir, mecom_twin, server={"tcp_port": free_port()}), short_dir)
    token = short_dir / "run" / "tcp.token"
    try:
        assert token.stat().st_mode & 0o777 == 0o600
    finally:
        r.stop()
    assert not token.exists()


def test_nhfd_demo_removes_its_temporary_runtime_directory(tmp_path, monkeypatch):
    from nhfd.demos import serve as demo

    seen: list[Path] = []

    def stop_here(base, *, runtime, **kw):
        seen.append(runtime)
        (runtime / "laser.sock.token").write_text("secret\n")  # what a guardian leaves there
        raise RuntimeError("stopped by the test")

    monkeypatch.setattr(demo, "demo_config", stop_here)
    # The model and scene checks run before the runtime directory exists; not this test's subject.
    monkeypatch.setattr(demo, "check_model_and_scene", lambda *a: {})
    with pytest.raises(RuntimeError, match="stopped by the test"):
        demo.run(tmp_path / "out", config=None, model=tmp_path / "m.onnx",
                 scene=tmp_path / "s.ply", log=lambda *a: None)
    assert len(seen) == 1 and seen[0].name.startswith("nhfd-demo-")
    assert not seen[0].exists()
