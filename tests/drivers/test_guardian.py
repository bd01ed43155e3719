"""The laser guardian process: lasers off within a second when the daemon dies or hangs.

Each test runs a real guardian process on the twin's pty and, where needed, a daemon-like child
that talks to it; the twin's emission record (same monotonic clock as this process) measures
how long light kept coming after the daemon stopped.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nhfd.cli.main import main
from nhfd.device_settings import GuardianSettings, LaserSettings
from nhfd.drivers.guardian import (
    GuardianClient,
    GuardianError,
    GuardianRefused,
    GuardianUnavailable,
    pid_path_for,
    read_token,
    spawn_guardian,
    token_path_for,
)
from nhfd.drivers.twins.mecom_twin import MecomTwin

from .conftest import read_line, reaped

HEAVY = ("torch", "numba", "onnxruntime")

DAEMON = """
import sys, time
from nhfd.drivers.guardian import GuardianClient, read_token
c = GuardianClient({sock!r}, token=read_token({sock!r}))
c.heartbeat()
c.arm(60)
c.set_power("red", 80.0)
c.set_power("blue", 4.0)
c.enable("red")
c.enable("blue")
print("on", flush=True)
while True:
    c.heartbeat()
    time.sleep(0.05)
"""


def light(client: GuardianClient, channel: str, power_pct: float) -> None:
    """As the daemon does: heartbeat, arm for 30 s, set the power, enable."""
    client.heartbeat()
    client.arm(30)
    client.set_power(channel, power_pct)
    client.enable(channel)


def guardian_settings(sock, heartbeat_timeout_s: float = 0.5) -> LaserSettings:
    return LaserSettings(
        reply_timeout_s=0.2,
        guardian=GuardianSettings(socket_path=str(sock), heartbeat_timeout_s=heartbeat_timeout_s,
                                  start_timeout_s=15.0),
    )


def controller(sock) -> GuardianClient:
    """The guardian's controller: a client with the token from its 0600 file."""
    return GuardianClient(sock, token=read_token(sock))


def wait_dark(twin, timeout_s: float = 3.0) -> float:
    deadline = time.monotonic() + timeout_s
    while (dark := twin.dark_since()) is None:
        assert time.monotonic() < deadline, f"still emitting {twin.emitting()}"
        time.sleep(0.005)
    return dark


@pytest.mark.parametrize("how", ["SIGKILL", "hang"])
def test_lasers_go_off_within_a_second_when_the_daemon_dies_or_hangs(mecom_twin, short_dir,
                                                                     how):
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock), port=mecom_twin.port_path,
                              stderr=subprocess.DEVNULL)
    daemon = subprocess.Popen([sys.executable, "-c", DAEMON.format(sock=str(sock))],
                              stdout=subprocess.PIPE, text=True)
    with reaped(daemon, guardian):
        assert read_line(daemon, 10).strip() == "on"
        assert mecom_twin.emitting() == {"red": 10.0, "green": 0.0, "blue": 4.0}  # capped
        n_before = len(mecom_twin.requests)
        stopped = time.monotonic()
        # SIGKILL: nothing in the daemon runs. SIGSTOP: a hung daemon, socket still open.
        os.kill(daemon.pid, signal.SIGKILL if how == "SIGKILL" else signal.SIGSTOP)
        dark = wait_dark(mecom_twin)
        assert dark - stopped < 1.0
        # ...and the guardian read the enables back after switching them off.
        time.sleep(0.1)
        after = [r.payload for r in mecom_twin.requests[n_before:]]
        for instance in ("01", "02", "03"):
            assert f"?VR1B5E{instance}" in after
        assert guardian.poll() is None  # still on duty
    assert mecom_twin.max_emitted_pct() == 10.0


def test_emission_needs_a_live_heartbeat(mecom_twin, short_dir):
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock), port=mecom_twin.port_path,
                              stderr=subprocess.DEVNULL)
    with reaped(guardian), controller(sock) as client:
        with pytest.raises(GuardianError, match="heartbeat"):
            client.arm(10)
        client.heartbeat()
        client.arm(10)
        client.set_power("green", 1.0)
        time.sleep(0.7)  # the heartbeat lapses: the session trips
        with pytest.raises(GuardianError, match="heartbeat"):
            client.enable("green")
        client.heartbeat()
        with pytest.raises(GuardianError, match="NotArmed"):  # the trip disarmed it
            client.enable("green")
        assert client.hello()["max_power_pct"] == [10.0, 10.0, 10.0]
        with pytest.raises(GuardianError, match="unknown op"):
            client.call("fire")
    assert mecom_twin.max_emitted_pct() == 0.0


def test_each_self_disarm_is_counted_and_its_reason_told_in_the_heartbeat(mecom_twin,
                                                                          short_dir):
    """The daemon audits what the guardian says here (issue 32): a lapsed heartbeat and an
    arming that ran out are told apart; a heartbeat lapse while disarmed is no disarm."""
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock), port=mecom_twin.port_path,
                              stderr=subprocess.DEVNULL)
    with reaped(guardian), controller(sock) as client:
        beat = client.heartbeat()
        assert (beat["trips"], beat["last_trip"]) == (0, None)
        time.sleep(0.7)  # lapses while disarmed: nothing to disarm, nothing counted
        assert client.heartbeat()["trips"] == 0
        client.arm(30)
        time.sleep(0.7)
        beat = client.heartbeat()
        assert not beat["armed"] and beat["trips"] == 1
        assert beat["last_trip"]["reason"] == "no heartbeat for 0.5 s"
        client.arm(0.2)
        deadline = time.monotonic() + 3.0
        while (beat := client.heartbeat())["armed"]:
            assert time.monotonic() < deadline, "arming never ran out"
            time.sleep(0.05)
        assert beat["trips"] == 2 and beat["last_trip"]["reason"] == "arming expired"


def test_nhfd_laser_off_through_the_guardian(mecom_twin, short_dir, capsys):
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock, heartbeat_timeout_s=5.0),
                              port=mecom_twin.port_path, stderr=subprocess.DEVNULL)
    with reaped(guardian), controller(sock) as client:
        light(client, "green", 2.0)
        assert mecom_twin.emitting()["green"] == 2.0
        assert main(["laser-off", "--socket", str(sock)]) == 0
        assert mecom_twin.emitting()["green"] == 0.0
        assert "read back by the guardian" in capsys.readouterr().out
        assert client.status()["armed"] is False


def test_the_guardian_switches_off_and_exits_on_sigterm(mecom_twin, short_dir):
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock, heartbeat_timeout_s=5.0),
                              port=mecom_twin.port_path, stderr=subprocess.DEVNULL)
    with reaped(guardian):
        with controller(sock) as client:
            light(client, "red", 1.0)
            sent = time.monotonic()
            guardian.send_signal(signal.SIGTERM)
            assert guardian.wait(timeout=5) == 0
        assert wait_dark(mecom_twin) - sent < 1.0
        assert not sock.exists()


def test_nhfd_laser_off_without_a_guardian_opens_the_port_itself(mecom_twin, short_dir, capsys):
    mecom_twin.set_state("blue", enabled=1, power_pct=30.0)
    code = main(["laser-off", "--socket", str(short_dir / "none.sock"),
                 "--port", mecom_twin.port_path])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "read back on" in out.out and "no guardian" in out.out
    assert mecom_twin.emitting()["blue"] == 0.0
    assert mecom_twin.requests[0].payload == "?VR006401"  # identified first


def test_nhfd_laser_off_fails_loudly_when_nothing_can_be_reached(short_dir, capsys):
    code = main(["laser-off", "--socket", str(short_dir / "none.sock"), "--timeout-s", "0.2"])
    assert code == 1
    assert "no laser port is configured" in capsys.readouterr().err


def test_a_second_guardian_can_take_neither_the_port_nor_the_socket(mecom_twin, short_dir):
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock), port=mecom_twin.port_path,
                              stderr=subprocess.DEVNULL)
    with reaped(guardian), MecomTwin() as other_twin:
        settings = guardian_settings(sock).model_copy(update={"guardian": GuardianSettings(
            socket_path=str(sock), start_timeout_s=5.0)})
        # The port is held exclusively by the first guardian.
        with pytest.raises(GuardianError, match="did not become ready"):
            spawn_guardian(settings, port=mecom_twin.port_path, stderr=subprocess.DEVNULL)
        # Another laser, same socket: refused, and the socket is left to the first one.
        with pytest.raises(GuardianError, match="did not become ready"):
            spawn_guardian(settings, port=other_twin.port_path, stderr=subprocess.DEVNULL)
        with controller(sock) as client:
            assert client.hello()["pid"] == guardian.pid


def test_guardian_client_reports_a_missing_guardian(short_dir):
    with pytest.raises(GuardianUnavailable, match="no laser guardian"):
        GuardianClient(short_dir / "absent.sock", timeout_s=0.2)


def _modules_after(imports: str) -> set[str]:
    probe = f"import sys, json\n{imports}\nprint(json.dumps(sorted(sys.modules)))\n"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True, timeout=60)
    return set(json.loads(out.stdout))


def test_the_guardian_and_drivers_import_no_heavy_libraries():
    # The laser's safety processes (the guardian, `nhfd laser-off`) load only what switching the
    # lasers needs: no USB or HID stack, no window toolkit.
    safety = _modules_after("import nhfd.drivers.guardian, nhfd.drivers.laser\n"
                            "import nhfd.drivers.twins.mecom_twin, nhfd.cli.cmd_laser")
    assert not safety & (set(HEAVY) | {"hid", "usb", "pyglet", "cv2"})
    # The rest of the drivers may use hidapi and pyusb (dependencies: the SpaceMouse, `nhfd
    # devices`), but never torch and friends, and pyglet only in the window backend's open.
    loaded = _modules_after(
        "import nhfd.drivers.stage, nhfd.drivers.slm, nhfd.drivers.framebuffer\n"
        "import nhfd.drivers.navigator, nhfd.drivers.twins.apt_twin, nhfd.drivers.factory\n"
        "import nhfd.drivers.discovery, nhfd.drivers.window, nhfd.cli.cmd_devices")
    assert not loaded & (set(HEAVY) | {"pyglet"})
    assert not any(m.startswith(("nhfd.models", "nhfd.optics")) for m in loaded)


# ------------------------------------------------------------- issue 21: token, hung, impostor


def test_only_the_token_holder_commands_the_guardian_but_anyone_may_switch_off(mecom_twin,
                                                                               short_dir):
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock, heartbeat_timeout_s=5.0),
                              port=mecom_twin.port_path, stderr=subprocess.DEVNULL)
    token_file = token_path_for(sock)
    with reaped(guardian), GuardianClient(sock) as stranger:
        assert token_file.stat().st_mode & 0o777 == 0o600
        token = read_token(sock)
        cmdline = Path(f"/proc/{guardian.pid}/cmdline").read_bytes()
        assert token.encode() not in cmdline  # never on a command line
        for op, params in [("heartbeat", {}), ("arm", {"duration_s": 10}),
                           ("power", {"channel": "red", "power_pct": 5.0}),
                           ("enable", {"channel": "red"}), ("disarm", {}), ("clear_fault", {}),
                           ("shutdown", {})]:
            with pytest.raises(GuardianError, match=f"'{op}' needs the controller's token"):
                stranger.call(op, **params)
        with pytest.raises(GuardianError, match="wrong token"):
            stranger.call("auth", token="x" * len(token))
        with pytest.raises(GuardianError, match="needs the controller's token"):
            stranger.heartbeat()  # a failed auth grants nothing
        assert mecom_twin.max_emitted_pct() == 0.0
        with controller(sock) as owner:
            owner.heartbeat()
            owner.arm(30)
            owner.set_power("green", 2.0)
            owner.enable("green")
            assert mecom_twin.emitting()["green"] == 2.0
            stranger.all_off()  # switching off is always allowed
            assert mecom_twin.emitting() == {"red": 0.0, "green": 0.0, "blue": 0.0}
            assert stranger.status()["armed"] is False
            assert owner.shutdown() == guardian.pid  # the controller may end it
        assert guardian.wait(timeout=5) == 0
    assert not sock.exists() and not token_file.exists() and not pid_path_for(sock).exists()


def test_hello_names_the_port_and_the_units_serial_number(mecom_twin, short_dir):
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock), port=mecom_twin.port_path,
                              stderr=subprocess.DEVNULL)
    with reaped(guardian), GuardianClient(sock, expected_pid=guardian.pid) as client:
        hello = client.hello()
        assert hello["port"] == mecom_twin.port_path
        assert hello["serial_number"] == mecom_twin.serial_number == 23051
        assert hello["pid"] == client.peer_pid == guardian.pid
        assert int(pid_path_for(sock).read_text()) == guardian.pid
        assert "?VR006601" in [r.payload for r in mecom_twin.requests]  # parameter 102 read
    with pytest.raises(GuardianRefused, match=r"is pid \d+, not the guardian started"):
        other = spawn_guardian(guardian_settings(sock), port=mecom_twin.port_path,
                               stderr=subprocess.DEVNULL)
        with reaped(other):
            GuardianClient(sock, expected_pid=other.pid + 1)


def test_nhfd_laser_off_ends_a_hung_guardian_and_switches_off_itself(mecom_twin, short_dir,
                                                                     capsys):
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock, heartbeat_timeout_s=5.0),
                              port=mecom_twin.port_path, stderr=subprocess.DEVNULL)
    with reaped(guardian), controller(sock) as client:
        light(client, "red", 3.0)
        guardian.send_signal(signal.SIGSTOP)  # hung: the socket accepts, nothing answers
        try:
            # No --port: the port comes from the verified guardian's own command line.
            code = main(["laser-off", "--socket", str(sock), "--timeout-s", "0.3"])
        finally:
            with contextlib.suppress(ProcessLookupError):
                guardian.send_signal(signal.SIGCONT)
        out = capsys.readouterr()
        assert code == 0, out.err
        assert f"killed the hung guardian, pid {guardian.pid}" in out.err
        assert f"read back on {mecom_twin.port_path}" in out.out
        assert guardian.wait(timeout=5) == -signal.SIGKILL
    assert mecom_twin.emitting() == {"red": 0.0, "green": 0.0, "blue": 0.0}


def test_nhfd_laser_off_frees_a_port_held_by_a_hung_guardian_on_another_socket(mecom_twin,
                                                                              short_dir, capsys):
    sock = short_dir / "laser.sock"
    guardian = spawn_guardian(guardian_settings(sock, heartbeat_timeout_s=5.0),
                              port=mecom_twin.port_path, stderr=subprocess.DEVNULL)
    with reaped(guardian), controller(sock) as client:
        light(client, "blue", 4.0)
        guardian.send_signal(signal.SIGSTOP)
        try:
            code = main(["laser-off", "--socket", str(short_dir / "other.sock"),
                         "--port", mecom_twin.port_path])
        finally:
            with contextlib.suppress(ProcessLookupError):
                guardian.send_signal(signal.SIGCONT)
        out = capsys.readouterr()
        assert code == 0, out.err
        assert f"killed nhfd guardian pid {guardian.pid}, which held" in out.err
        assert guardian.wait(timeout=5) == -signal.SIGKILL
    assert mecom_twin.emitting() == {"red": 0.0, "green": 0.0, "blue": 0.0}


FAKE = """
import json, os, socket, sys
s = socket.socket(socket.AF_UNIX); s.bind(sys.argv[1]); s.listen(4)
print("ready", flush=True)
while True:
    c, _ = s.accept()
    f = c.makefile("rwb")
    for line in f:
        f.write(json.dumps({"ok": True, "off": True, "port": sys.argv[2], "pid": os.getpid(),
            "armed": False, "fault": None, "channels": {k: {"enabled": False, "power_pct": 0.0}
            for k in ("red", "green", "blue")}}).encode() + b"\\n"); f.flush()
"""


@pytest.mark.parametrize("unsafe_mode", [None, 0o777, 0o757])
def test_nhfd_laser_off_does_not_trust_a_fake_that_answers_all_off(mecom_twin, short_dir, capsys,
                                                                   unsafe_mode):
    where = short_dir
    if unsafe_mode is not None:
        where = short_dir / "shared"
        where.mkdir()
        where.chmod(unsafe_mode)
    sock = where / "laser.sock"
    fake = subprocess.Popen([sys.executable, "-c", FAKE, str(sock), mecom_twin.port_path],
                            stdout=subprocess.PIPE, text=True)
    mecom_twin.set_state("green", enabled=1, power_pct=6.0)
    with reaped(fake):
        assert read_line(fake, 10).strip() == "ready"
        code = main(["laser-off", "--socket", str(sock), "--timeout-s", "1"])
        err = capsys.readouterr().err
        assert code == 1
        if unsafe_mode is None:
            assert f"pid {fake.pid} is not an nhfd laser guardian of this user" in err
        else:
            assert (f"{where} is writable by other users (owner uid {os.getuid()}, mode "
                    f"{unsafe_mode:04o})") in err
        assert "no laser port is configured" in err
        assert mecom_twin.emitting()["green"] == 6.0  # nobody claimed otherwise
        # With the port named, laser-off trusts only its own read-back on it.
        assert main(["laser-off", "--socket", str(sock), "--port", mecom_twin.port_path]) == 0
        assert "read back on" in capsys.readouterr().out
        assert mecom_twin.emitting()["green"] == 0.0
