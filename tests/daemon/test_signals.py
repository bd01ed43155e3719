"""`nhfd serve` as a real process on the simulated bench (laser twin in this process):
SIGTERM/SIGINT shut down with lasers read back off and the socket removed; SIGKILL leaves the
guardian to switch the lasers off. The twin's emission record is the proof."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from nhfd.daemon.client import Client, DaemonUnavailable
from nhfd.drivers.guardian import port_holders

from .conftest import wait_until


def write_config(root, twin) -> str:
    for sub in ("scenes", "models", "snaps"):
        (root / sub).mkdir(exist_ok=True)
    text = f"""
[devices]
laser = "readybeam"
slm = "none"
camera = "none"
stage = "none"
[devices.readybeam]
port = "{twin.port_path}"
reply_timeout_s = 0.2
[devices.readybeam.guardian]
socket_path = "{root / 'laser.sock'}"
heartbeat_timeout_s = 0.5
[daemon.server]
runtime_dir = "{root / 'run'}"
[daemon.paths]
scene_dirs = ["{root / 'scenes'}"]
model_dirs = ["{root / 'models'}"]
snapshot_dir = "{root / 'snaps'}"
"""
    path = root / "nhfd.toml"
    path.write_text(text)
    return str(path)


def start_daemon(root, twin) -> tuple[subprocess.Popen, Client]:
    cfg = write_config(root, twin)
    proc = subprocess.Popen([sys.executable, "-m", "nhfd.cli.main", "serve", "--config", cfg],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    sock = root / "run" / "control.sock"
    clients: list[Client] = []

    def answers() -> bool:
        if proc.poll() is not None:
            return True
        try:  # a killed daemon's stale socket file may still be there: wait for an answer
            clients.append(Client(sock, timeout_s=2))
            return True
        except DaemonUnavailable:
            return False

    wait_until(answers, 20, "the daemon's socket")
    assert proc.poll() is None, proc.stderr.read()
    return proc, clients[0]


def light_red(client: Client, twin) -> None:
    client.call("laser", action="arm", duration_s=60.0)
    client.call("laser", action="power", channel="red", power_pct=5.0)
    client.call("laser", action="enable", channel="red")
    assert twin.emitting()["red"] == 5.0


def _close(proc: subprocess.Popen, client: Client) -> None:
    """Close the client, and kill the daemon if a failed test left it running."""
    client.close()
    if proc.poll() is None:
        proc.kill()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_and_sigint_shut_down_with_lasers_off(short_dir, mecom_twin, sig):
    proc, client = start_daemon(short_dir, mecom_twin)
    try:
        light_red(client, mecom_twin)
        guardian_pid = client.status()["laser"]["guardian"]["spawned_pid"]
        sent = time.monotonic()
        proc.send_signal(sig)
        assert proc.wait(timeout=10) == 0
        dark = mecom_twin.dark_since()
        assert dark is not None and dark - sent < 2.0
        assert mecom_twin.emitting() == {"red": 0.0, "green": 0.0, "blue": 0.0}
        assert not (short_dir / "run" / "control.sock").exists()
        with pytest.raises(ProcessLookupError):  # the guardian it started has exited too
            wait_until(lambda: _gone(guardian_pid), 5, "the guardian to exit")
            os.kill(guardian_pid, 0)
        assert "lasers: read back off through the guardian" in proc.stderr.read()
    finally:
        _close(proc, client)


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_sigkill_of_the_daemon_leaves_the_guardian_to_switch_lasers_off(short_dir, mecom_twin):
    proc, client = start_daemon(short_dir, mecom_twin)
    guardian_pid = None
    try:
        light_red(client, mecom_twin)
        guardian_pid = client.status()["laser"]["guardian"]["spawned_pid"]
        killed = time.monotonic()
        proc.kill()
        proc.wait(timeout=5)
        wait_until(lambda: mecom_twin.dark_since() is not None, 3, "lasers off")
        assert mecom_twin.dark_since() - killed < 1.0
        assert not _gone(guardian_pid)  # still on duty, holding the port with lasers off
        # A second daemon takes the lock (the kernel released it) and reuses the guardian.
        proc2, client2 = start_daemon(short_dir, mecom_twin)
        try:
            st = client2.status()["laser"]
            assert st["guardian"]["connected"] and st["guardian"]["spawned_pid"] is None
            assert st["guardian"]["pid"] == guardian_pid and st["guardian"]["spawned"] is False
            assert st["armed"] is False  # arming is never restored
            client2.call("shutdown")
            assert proc2.wait(timeout=10) == 0
            # The adopted orphan ended with the clean shutdown, and the port is free again.
            wait_until(lambda: _gone(guardian_pid), 5, "the adopted guardian to exit")
            assert port_holders(mecom_twin.port_path) == [os.getpid()]  # the twin's own end
            assert not (short_dir / "laser.sock").exists()
        finally:
            _close(proc2, client2)
    finally:
        _close(proc, client)
        if guardian_pid and not _gone(guardian_pid):
            os.kill(guardian_pid, signal.SIGTERM)
    assert mecom_twin.max_emitted_pct() == 5.0


def test_a_second_daemon_is_refused_by_the_lock(short_dir, mecom_twin):
    proc, client = start_daemon(short_dir, mecom_twin)
    try:
        cfg = str(short_dir / "nhfd.toml")
        second = subprocess.run([sys.executable, "-m", "nhfd.cli.main", "serve", "--config", cfg],
                                capture_output=True, text=True, timeout=20)
        assert second.returncode == 3
        assert f"pid {proc.pid}" in second.stderr and "holds" in second.stderr
        assert client.status()["daemon"]["pid"] == proc.pid  # the first one is untouched
        client.call("shutdown")
        assert proc.wait(timeout=10) == 0
    finally:
        _close(proc, client)
