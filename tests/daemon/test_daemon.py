"""The daemon in-process on a simulated bench: protocol errors on the wire, bad-input fuzz, the
set_view storm, laser arming rules, allowed paths, and stop/blank beside a long job."""

from __future__ import annotations

import contextlib
import json
import re
import shutil
import socket
import threading
import time
from pathlib import Path

import pytest

from nhfd.benchmarks.safety import bad_requests
from nhfd.daemon.protocol import RpcError

from .conftest import Running, bench_config, free_port, wait_until


def raw_session(path, lines: list[bytes], expect: int, timeout_s: float = 5.0) -> list:
    """Send lines on one connection; read `expect` reply lines."""
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(timeout_s)
        s.connect(str(path))
        s.sendall(b"".join(lines))
        buf = b""
        while buf.count(b"\n") < expect:
            chunk = s.recv(65536)
            assert chunk, "daemon hung up"
            buf += chunk
        return [json.loads(x) for x in buf.splitlines()]


def test_protocol_errors_on_the_wire(running: Running):
    cap = running.daemon.config.daemon.server.max_line_bytes
    replies = raw_session(running.socket, [
        b'{"jsonrpc":"2.0","method":"status"\n',                                  # malformed
        b'{"jsonrpc":"2.0","method":"focus","params":{"z_mm":NaN},"id":2}\n',
        b'{"jsonrpc":"2.0","method":"focus","params":{"z_mm":1e400},"id":3}\n',
        b'{"jsonrpc":"2.0","method":"fly","id":4}\n',
        b'{"jsonrpc":"2.0","method":"focus","params":{"z_mm":"1"},"id":5}\n',
        b'{"jsonrpc":"2.0","method":"focus","params":{"z_mm":99},"id":6}\n',
        b'{"jsonrpc":"2.0","method":"set_view","params":{"orbit":{}}}\n',          # notification
        b'{"jsonrpc":"2.0","method":"status","params":{"x":1},"id":7}\n',
        b'{"x":"' + b"a" * (cap + 10) + b'"}\n',                                  # oversize
        b"[]\n",
        b'[{"jsonrpc":"2.0","method":"status","id":8},{"jsonrpc":"2.0","method":"status"},'
        b'{"jsonrpc":"2.0","method":"nope","id":9}, 5]\n',
        b'{"jsonrpc":"2.0","method":"status","id":"last"}\n',
    ], expect=11)
    codes = [r["error"]["code"] if isinstance(r, dict) and "error" in r else r for r in replies]
    assert codes[:8] == [-32700, -32700, -32700, -32601, -32602, -32602, -32602, -32600]
    assert replies[0]["id"] is None and replies[3]["id"] == 4
    assert "set_view" in replies[3]["error"]["data"]["allowed"]
    assert replies[4]["error"]["data"] == {"field": "z_mm",
                                          "allowed": "a finite number in [-5, 5]"}
    assert replies[6]["error"]["data"]["field"] == "x"
    assert "longer than" in replies[7]["error"]["message"]
    assert codes[8] == -32600  # empty batch
    batch = replies[9]
    assert [r.get("id") for r in batch] == [8, 9, None]  # the notification got no reply
    assert "result" in batch[0] and batch[1]["error"]["code"] == -32601
    assert batch[2]["error"]["code"] == -32600
    assert replies[10]["id"] == "last" and replies[10]["result"]["daemon"]["state"] == "ready"


def test_batches_can_be_refused_with_a_clear_error(short_dir, mecom_twin):
    r = Running(bench_config(short_dir, mecom_twin, server={"max_batch": 0}), short_dir)
    try:
        (reply,) = raw_session(r.socket, [b'[{"jsonrpc":"2.0","method":"status","id":1}]\n'], 1)
        assert reply["error"]["code"] == -32600
        assert "batches are not supported" in reply["error"]["message"]
    finally:
        r.stop()


def test_ten_thousand_bad_requests_leave_the_daemon_serving_and_unchanged(running, mecom_twin):
    c = running.client()
    before = c.status()
    cap = running.daemon.config.daemon.server.max_line_bytes
    lines, expected = bad_requests(10_000, seed=7, cap=cap)
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(20)
        s.connect(str(running.socket))
        # A last, good request marks the end: every reply before it answers a bad request, so
        # the count is exact however the replies arrive in chunks.
        end = b'{"jsonrpc":"2.0","method":"status","id":"end"}\n'
        writer = threading.Thread(target=s.sendall, args=(b"".join(lines) + end,))
        writer.start()
        buf, got = bytearray(), []
        while not got or got[-1].get("id") != "end":
            chunk = s.recv(1 << 20)
            assert chunk, f"hung up after {len(got)} replies"
            buf += chunk
            *done, rest = bytes(buf).split(b"\n")
            got += [json.loads(x) for x in done]
            buf = bytearray(rest)
        writer.join()
    got.pop()
    assert len(got) == expected
    assert all("error" in r and "result" not in r for r in got), \
        [r for r in got if "error" not in r][:3]
    after = c.status()
    for key in ("view", "scene", "model", "display", "jobs"):
        assert after[key] == before[key], key
    assert after["laser"]["armed"] is False and after["daemon"]["state"] == "ready"
    assert after["devices"]["stage"].get("homed") == before["devices"]["stage"].get("homed")
    assert mecom_twin.max_emitted_pct() == 0.0
    assert not list((running.daemon.rpc.snapshot_dirs[0]).iterdir())


def test_eight_clients_storming_set_view_end_on_the_last_sequence_number(running):
    seqs: list[int] = []
    last_view: dict = {}
    lock = threading.Lock()
    status_latency: list[float] = []
    storming = threading.Event()

    def storm(k: int) -> None:
        with running.client() as c:
            for i in range(150):
                view = {"azimuth_deg": float(k), "elevation_deg": float(i % 80), "radius": 2.0}
                r = c.call("set_view", orbit=view)
                with lock:
                    seqs.append(r["seq"])
                    if r["seq"] == max(seqs):
                        last_view.update(r["view"])

    def poll_status() -> None:
        with running.client() as c:
            while storming.is_set():
                t = time.monotonic()
                assert c.status()["daemon"]["state"] == "ready"
                status_latency.append(time.monotonic() - t)

    threads = [threading.Thread(target=storm, args=(k,)) for k in range(8)]
    storming.set()
    poller = threading.Thread(target=poll_status)
    poller.start()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    storming.clear()
    poller.join()
    assert sorted(seqs) == list(range(1, 8 * 150 + 1))  # every request got its own number
    view = running.client().status()["view"]
    assert view["seq"] == max(seqs) == 1200
    assert view["requested"] == last_view
    assert status_latency and max(status_latency) < 2.0


def test_arming_only_over_the_unix_socket_and_everything_audited(short_dir, mecom_twin):
    from nhfd.daemon.client import Client

    r = Running(bench_config(short_dir, mecom_twin, server={"tcp_port": free_port()}), short_dir)
    try:
        addr = r.daemon.server.tcp_address
        assert addr[0] == "127.0.0.1"
        token = (short_dir / "run" / "tcp.token").read_text().strip()
        assert (short_dir / "run" / "tcp.token").stat().st_mode & 0o777 == 0o600
        with Client(tcp=addr) as anon, pytest.raises(RpcError) as info:
            anon.status()
        assert info.value.code == 1005
        with pytest.raises(RpcError, match="wrong token"):
            Client(tcp=addr, token="guess")
        with Client(tcp=addr, token=token) as tcp:
            assert tcp.status()["daemon"]["state"] == "ready"
            with pytest.raises(RpcError) as info:
                tcp.call("laser", action="arm", duration_s=30.0)
            assert info.value.code == 1003 and info.value.data["field"] == "action"
        with r.client() as unix:
            with pytest.raises(RpcError) as info:  # not armed: the guardian refuses
                unix.call("laser", action="enable", channel="red")
            assert info.value.code == 1002
            assert unix.call("laser", action="arm", duration_s=30.0)["by_uid"] is not None
            assert unix.call("laser", action="power", channel="red", power_pct=80.0) == {
                "channel": "red", "power_pct": 10.0, "capped": True}
            unix.call("laser", action="enable", channel="red")
            assert mecom_twin.emitting()["red"] == 10.0
            assert unix.status()["laser"]["armed"] is True
            unix.call("laser", action="off")
            assert mecom_twin.emitting() == {"red": 0.0, "green": 0.0, "blue": 0.0}
            assert unix.status()["laser"]["armed"] is False
    finally:
        r.stop()
    audit = [json.loads(x) for x in (short_dir / "run" / "audit.jsonl").read_text().splitlines()]
    laser = [a for a in audit if a["what"] == "laser"]
    assert [a["params"]["action"] for a in laser] == ["arm", "enable", "arm", "power", "enable",
                                                      "off"]
    assert laser[0]["who"]["transport"] == "tcp" and laser[0]["outcome"].startswith("refused")
    assert laser[2]["who"]["transport"] == "unix" and "uid" in laser[2]["who"]
    assert audit[-1]["what"] == "stop" and "read back off" in audit[-1]["lasers"]
    assert mecom_twin.max_emitted_pct() == 10.0


def test_paths_outside_the_allowed_directories_are_refused(running, short_dir):
    outside = short_dir / "secret.ply"
    outside.write_text("ply\n")
    (short_dir / "scenes" / "link.ply").symlink_to(outside)
    (short_dir / "scenes" / "garbage.ply").write_bytes(b"not a ply")
    (short_dir / "models" / "m.onnx").write_bytes(b"x")
    c = running.client()
    for path in (str(outside), "../secret.ply", "link.ply", "/etc/passwd"):
        with pytest.raises(RpcError) as info:
            c.call("load_scene", path=path)
        assert info.value.code == 1004, path
        assert info.value.data == {"field": "path", "allowed": [str(short_dir / "scenes")]}
    with pytest.raises(RpcError) as info:
        c.call("snapshot", path="/tmp/x.png")
    assert info.value.code == 1004
    job = c.call("load_model", path="m.onnx")["job"]  # a file of garbage: refused by the worker
    wait_until(lambda: c.call("job", id=job)["state"] == "failed", what="model load to fail")
    assert "not a readable ONNX model" in c.call("job", id=job)["error"]
    job = c.call("load_scene", path="garbage.ply")["job"]
    wait_until(lambda: c.call("job", id=job)["state"] == "failed", what="load to fail")
    status = c.status()
    assert status["scene"] is None  # the old scene (none) stays
    assert any("garbage.ply" in e["message"] or "load_scene" in e["source"]
               for e in status["errors"])


def test_stop_and_blank_answer_while_a_long_job_runs(running):
    c = running.client()
    stage = running.daemon.bench.stage
    start_mm = stage.position_mm()
    job = c.call("focus", z_mm=-4.0, home=True)["job"]  # homing from ~7 mm takes seconds
    wait_until(lambda: c.call("job", id=job)["state"] == "running", what="job start")
    time.sleep(0.3)
    t = time.monotonic()
    assert c.call("blank") == {"showing": "blank"}
    reply = c.call("stop")
    elapsed = time.monotonic() - t
    # The job was still running when stop was handled (it is in the cancelled list): stop did
    # not wait behind it. The time bound is loose so a loaded CI machine cannot fail it.
    assert job in reply["cancelled_jobs"] and reply["stage"] == "stop sent"
    assert elapsed < 2.0, elapsed
    wait_until(lambda: c.call("job", id=job)["state"] == "cancelled", what="job cancelled")
    time.sleep(0.2)
    moved_to = stage.position_mm()
    assert 0 < moved_to < start_mm  # it was homing, and stopped on the way
    time.sleep(0.3)
    assert stage.position_mm() == pytest.approx(moved_to, abs=1e-3)


def test_focus_maps_depth_to_stage_and_validates_range(running):
    c = running.client()
    with pytest.raises(RpcError) as info:
        c.call("focus", z_mm=6.0)
    assert info.value.data == {"field": "z_mm", "allowed": "a finite number in [-5, 5]"}
    job = c.call("focus", z_mm=1.5)
    assert job["stage_mm"] == 14.0  # 12.5 + 1.5: the documented default mapping
    wait_until(lambda: c.call("job", id=job["job"])["state"] == "failed", what="job end")
    assert "not homed" in c.call("job", id=job["job"])["error"]  # never homed implicitly


def test_systemd_notify_socket_mode_and_lock(short_dir, mecom_twin):
    import os
    import stat

    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(short_dir / "notify.sock"))
    notify.settimeout(5)
    env = {"NOTIFY_SOCKET": str(short_dir / "notify.sock"), "WATCHDOG_USEC": "200000",
           "WATCHDOG_PID": str(os.getpid())}
    r = Running(bench_config(short_dir, mecom_twin), short_dir, env=env)
    try:
        messages = [notify.recv(4096).decode() for _ in range(3)]
        ready = next(m for m in messages if "READY=1" in m)
        assert "STATUS=ready: lasers off" in ready
        assert messages.index(ready) == 2  # after the two start-up STATUS lines
        assert notify.recv(4096) == b"WATCHDOG=1"  # fed from the control loop
        mode = r.socket.stat().st_mode
        assert stat.S_ISSOCK(mode) and stat.S_IMODE(mode) == 0o660
        assert (short_dir / "run" / "nhfd.lock").read_text().strip() == str(os.getpid())
    finally:
        r.stop()
    seen = []
    with contextlib.suppress(TimeoutError):
        notify.settimeout(0.5)
        while "STOPPING=1" not in "".join(seen):
            seen.append(notify.recv(4096).decode())
    assert any("STOPPING=1" in m for m in seen)
    notify.close()


def test_the_daemon_loads_every_scene_format_nhfd_reads(running, short_dir):
    """.spz, .glb, a .sog bundle and a SOG folder load as scenes (each the donut crop or the tiny
    SH scene, counted as its file declares); a folder without meta.json is refused."""
    formats = Path(__file__).parents[1] / "data" / "formats"
    scenes = short_dir / "scenes"
    for name in ("donut-crop.v4.spz", "donut-crop.glb", "donut-crop.sog"):
        shutil.copy(formats / name, scenes / name)
    shutil.copytree(formats / "tiny-sh.sog.d", scenes / "tiny-sh.sog.d")
    (scenes / "empty.d").mkdir()
    c = running.client(timeout_s=30.0)
    for path, gaussians in (("donut-crop.v4.spz", 2108), ("donut-crop.glb", 2108),
                            ("donut-crop.sog", 2108), ("tiny-sh.sog.d", 64)):
        job = c.wait_job(c.call("load_scene", path=path)["job"], timeout_s=60.0)
        assert job["state"] == "done", (path, job["error"])
        assert c.status()["scene"]["gaussians"] == gaussians, path
    with pytest.raises(RpcError, match="wrong suffix"):
        c.call("load_scene", path="empty.d")
    # a SOG scene named by its meta.json loads too: the one whole name a scene file may have
    job = c.wait_job(c.call("load_scene", path="tiny-sh.sog.d/meta.json")["job"], timeout_s=60.0)
    assert job["state"] == "done", job["error"]
    assert c.status()["scene"]["gaussians"] == 64
    # models (and patterns) are checked by their suffix alone: neither meta.json nor a file
    # whose whole name is the suffix (a dot file, no suffix) is a model
    for name in ("meta.json", ".onnx"):
        (short_dir / "models" / name).write_bytes(b"not a model")
        with pytest.raises(RpcError, match=rf"path: '{re.escape(name)}' has the wrong suffix; "
                                           r"allowed: \.onnx"):
            c.call("load_model", path=name)
