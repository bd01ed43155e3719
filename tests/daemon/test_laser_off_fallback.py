"""`nhfctl laser off` / `disarm` switch the lasers off whatever the daemon does (issue 32, item 1):
through the daemon when it answers, else through the laser guardian as `nhfd laser-off` does. The
output names the path; the exit code is 0 only when every channel was read back off. Light is read
from the laser twin's emission record."""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from nhfd.cli.nhfctl import main
from nhfd.device_settings import GuardianSettings, LaserSettings
from nhfd.drivers.guardian import GuardianClient, read_token, spawn_guardian
from nhfd.drivers.twins.mecom_twin import MecomTwin

from .conftest import Running

OFF = {"red": 0.0, "green": 0.0, "blue": 0.0}


@contextlib.contextmanager
def lit_guardian(sock: Path, twin: MecomTwin) -> Iterator[GuardianClient]:
    """A guardian of its own (no daemon) on the twin, with green lit by its controller."""
    settings = LaserSettings(reply_timeout_s=0.2, guardian=GuardianSettings(
        socket_path=str(sock), heartbeat_timeout_s=10.0, start_timeout_s=15.0))
    proc = spawn_guardian(settings, port=twin.port_path, stderr=subprocess.DEVNULL)
    try:
        with GuardianClient(sock, token=read_token(sock)) as controller:
            controller.heartbeat()
            controller.arm(60)
            controller.set_power("green", 3.0)
            controller.enable("green")
            assert twin.emitting()["green"] == 3.0
            yield controller
    finally:
        proc.kill()
        proc.wait(10)


@contextlib.contextmanager
def fake_daemon(path: Path, how: str) -> Iterator[list[bytes]]:
    """A control socket that never switches anything off: "busy" answers every request with
    the daemon's busy error, "full" refuses at connect as a daemon at max_clients does (a busy
    line with no id, then it hangs up), "silent" reads and never answers."""
    srv = socket.socket(socket.AF_UNIX)
    srv.bind(str(path))
    srv.listen(8)
    seen: list[bytes] = []
    stop = threading.Event()
    conns: list[socket.socket] = []

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            conns.append(conn)
            busy = {"jsonrpc": "2.0", "error": {"code": 1001, "message": "too many clients "
                                                "(daemon.server.max_clients = 1)"}}
            if how == "full":
                conn.sendall(json.dumps({**busy, "id": None}).encode() + b"\n")
                conn.close()
                continue
            line = conn.makefile("rb").readline()
            seen.append(line)
            if how == "busy":
                conn.sendall(json.dumps({**busy, "id": json.loads(line)["id"]}).encode() + b"\n")

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        yield seen
    finally:
        stop.set()
        srv.close()
        for conn in conns:
            conn.close()
        t.join(5)


@pytest.mark.parametrize("action", ["off", "disarm"])
def test_with_no_daemon_the_guardian_switches_off(short_dir, mecom_twin, capsys, action):
    # Where the daemon would live, from the configuration: its socket is absent, its guardian
    # (laser.sock in the same runtime directory) is there.
    config = short_dir / "nhfd.toml"
    config.write_text(f'[daemon.server]\nruntime_dir = "{short_dir}"\n')
    with lit_guardian(short_dir / "laser.sock", mecom_twin) as controller:
        code = main(["--config", str(config), "laser", action])
        out = capsys.readouterr()
        assert code == 0, out.err
        assert out.out.startswith(f"all laser channels off (without the daemon, read back by "
                                  f"the guardian at {short_dir / 'laser.sock'}, pid ")
        assert out.err.startswith(f"nhfctl laser {action}: the daemon did not switch the lasers "
                                  f"off (no nhfd serve at {short_dir / 'control.sock'}")
        assert mecom_twin.emitting() == OFF
        assert controller.status()["armed"] is False


@pytest.mark.parametrize("how", ["busy", "full", "silent"])
def test_a_daemon_that_is_busy_or_silent_is_bypassed(short_dir, mecom_twin, capsys, how):
    sock = short_dir / "g" / "laser.sock"
    sock.parent.mkdir(mode=0o700)
    with lit_guardian(sock, mecom_twin), fake_daemon(short_dir / "c.sock", how) as seen:
        code = main(["--socket", str(short_dir / "c.sock"), "--json", "laser", "off",
                     "--guardian-socket", str(sock)])
        out = capsys.readouterr()
        assert code == 0, out.err
        result = json.loads(out.out)
        assert result["all_off"] is True and result["switched_off_by"] == "guardian"
        # "full": the busy line, or a broken pipe when the hang-up came before the request.
        why = {"busy": "the daemon refused: busy: too many clients (daemon.server.max_clients = 1)",
               "full": f"nhfd serve at {short_dir / 'c.sock'}: ",
               "silent": f"nhfd serve at {short_dir / 'c.sock'} did not answer"}[how]
        assert why in result["daemon"] and why in out.err
        assert mecom_twin.emitting() == OFF
        if how != "full":  # the daemon was asked first
            assert json.loads(seen[0])["params"] == {"action": "off"}


def test_a_daemon_that_answers_switches_off_itself_and_says_so(running: Running, mecom_twin,
                                                                capsys):
    mecom_twin.set_state("blue", enabled=1, power_pct=3.0)
    assert main(["--socket", str(running.socket), "laser", "off"]) == 0
    out = capsys.readouterr()
    assert out.out == (f"all laser channels off (through the daemon at {running.socket}, read "
                       "back by its laser guardian)\n")
    assert out.err == ""
    assert mecom_twin.emitting() == OFF


def test_lasers_not_confirmed_off_is_a_failure(short_dir, capsys):
    config = short_dir / "nhfd.toml"
    config.write_text(f'[daemon.server]\nruntime_dir = "{short_dir}"\n')
    assert main(["--config", str(config), "laser", "off"]) == 3
    err = capsys.readouterr().err
    assert "nhfctl laser off: error: lasers NOT confirmed off: no laser guardian at " in err
    assert "no laser port is configured (devices.readybeam.port, or nhfd laser-off --port)" in err
