"""The web view against hostile peers (issue 32): a token holder flooding its WebSocket, oversized
and deeply nested messages, more connections than `max_connections`, connections that never send
a request, running out of descriptors, the server failing inside the daemon, and "All lasers off"
audited as the web client that sent it rather than as the daemon."""

from __future__ import annotations

import asyncio
import http.client
import json
import logging
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from nhfd.config import WebSettings
from nhfd.daemon.audit import AuditLog
from nhfd.daemon.client import Client
from nhfd.daemon.protocol import RpcError
from tests.daemon.conftest import bench_config, running_daemon, wait_until

aiohttp = pytest.importorskip("aiohttp", reason="the web view needs the web extra (aiohttp)")

from nhfd.web.server import MAX_DEPTH, MAX_IN_FLIGHT, WebView  # noqa: E402

TOKEN = "t0k3n"
GUARD_S = 10.0  # how long a test waits for something that should come at once (never a measure)


class Clock:
    """The time the view measures message rates in: still unless a test moves it."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


class FakeDaemon:
    """Records what reaches the daemon; `hold` keeps `stop` waiting until it is set."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, dict]] = []
        self.hold: threading.Event | None = None
        self.fail_status = 0  # this many status calls raise (a bug in the reply's handling)

    def __call__(self, method: str, **params):
        self.calls.append((method, params))
        if method == "status":
            if self.fail_status:
                self.fail_status -= 1
                raise KeyError("frames")
            return {"frames": {"frames_shown": 0}}
        if method == "preview":
            return {"source": params["source"], "available": False}
        if method == "stop" and self.hold is not None:
            self.hold.wait(GUARD_S)
        return {"ok": True}

    def count(self, method: str) -> int:
        return sum(1 for m, _ in self.calls if m == method)


def start_view(tmp: Path, *, audit: AuditLog | None = None, clock: Clock | None = None,
               idle_timeout_s: float = 30.0, **settings) -> tuple[WebView, FakeDaemon]:
    fake = FakeDaemon()
    view = WebView(WebSettings(**{"port": 0, "push_interval_s": 10.0, **settings}),
                   socket_path=tmp / "none.sock", token=TOKEN, snapshot_dir=tmp, base_dir=tmp,
                   call=fake, audit=audit, idle_timeout_s=idle_timeout_s,
                   **({"clock": clock} if clock is not None else {}))
    view.start()
    return view, fake


async def signed_in(view: WebView) -> aiohttp.ClientSession:
    # force_close: the sign-in's connection ends with its reply, so the connections a test
    # counts are the ones it opened afterwards (a kept-alive one closing late made the count
    # move under a loaded machine)
    session = aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True),
                                    connector=aiohttp.TCPConnector(force_close=True))
    async with session.get(f"{view.url}?token={TOKEN}", allow_redirects=False) as r:
        assert r.status == 303
    return session


async def next_of(ws, kind: str) -> dict:
    """The next message of `kind` ("reply", "refused"), skipping state pushes."""
    while True:
        msg = await ws.receive(timeout=GUARD_S)
        assert msg.type == aiohttp.WSMsgType.TEXT, (msg.type, msg.data)
        data = json.loads(msg.data)
        if data["type"] == kind:
            return data


async def messages_until(ws, done) -> dict[str, list[dict]]:
    """Every message by type, in the order each type came, until `done(by_type)` holds: replies
    and notices travel separately, so their order between them is not the test's to fix."""
    by_type: dict[str, list[dict]] = {}
    while not done(by_type):
        msg = await ws.receive(timeout=GUARD_S)
        assert msg.type == aiohttp.WSMsgType.TEXT, (msg.type, msg.data)
        data = json.loads(msg.data)
        by_type.setdefault(data["type"], []).append(data)
    return by_type


def audit_lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def web_log(caplog: pytest.LogCaptureFixture, text: str) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "nhfd.web" and text in r.getMessage()]


def test_a_flood_is_refused_at_the_bucket_and_summarised_not_logged_per_message(
        tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="nhfd.web")
    audit = AuditLog(tmp_path / "audit.jsonl", summary_s=1.0, max_bytes=1 << 20, backups=1)
    clock = Clock()
    view, fake = start_view(tmp_path, audit=audit, clock=clock, messages_per_s=5.0)

    async def run() -> list[dict]:
        async with await signed_in(view) as s:
            ws = await s.ws_connect(f"{view.url}ws")
            for i in range(40):  # all at one instant of the view's clock: a burst of 5 passes
                await ws.send_str(json.dumps({"id": i, "op": "stop"}))
            got = await messages_until(ws, lambda t: t.get("refused")
                                       and len(t.get("reply", [])) == 5)
            await asyncio.to_thread(wait_until, lambda: view.messages_refused == 35, GUARD_S,
                                    "the flood read")
            clock.now_s += 1 / 5  # one token more: the next message passes
            await ws.send_str(json.dumps({"id": "last", "op": "stop"}))
            replies = got["reply"]
            while replies[-1]["id"] != "last":
                replies.append(await next_of(ws, "reply"))
            await ws.close()
            return [got["refused"][0], *replies]

    try:
        notice, *replies = asyncio.run(run())
    finally:
        view.stop()
        audit.close()
    # Only the burst and the one message after the refill reached the daemon.
    assert fake.count("stop") == 6
    assert sorted(r["id"] for r in replies if r["id"] != "last") == [0, 1, 2, 3, 4]
    assert all(r["ok"] for r in replies)
    assert notice["count"] == 1 and notice["error"]["name"] == "busy"
    # 35 refusals: one line when the first came, one with the count of the rest (at stop here).
    lines = web_log(caplog, "web message rate")
    assert len(lines) == 2, lines
    assert "over 5 messages per s" in lines[0] and lines[1].startswith("web view: 34 more ")
    records = [r for r in audit_lines(tmp_path / "audit.jsonl")
               if r["what"].startswith("web message rate")]
    assert [r["what"] for r in records] == ["web message rate",
                                            "web message rate (refusals summary)"]
    assert records[1]["count"] == 34 and records[0]["who"]["transport"] == "web"


def test_operations_at_once_are_bounded_and_lasers_off_still_goes(tmp_path):
    view, fake = start_view(tmp_path, clock=Clock(), messages_per_s=100.0)
    fake.hold = threading.Event()
    loop = view._loop

    async def tasks_now() -> int:
        return len(asyncio.all_tasks())

    def tasks_in_view() -> int:
        return asyncio.run_coroutine_threadsafe(tasks_now(), loop).result(GUARD_S)

    async def run() -> tuple[list[int], list[dict], list[dict]]:
        async with await signed_in(view) as s:
            ws = await s.ws_connect(f"{view.url}ws")
            await next_of(ws, "state")
            tasks = [tasks_in_view()]
            for i in range(30):  # within the rate: all read, none dropped
                await ws.send_str(json.dumps({"id": i, "op": "stop"}))
            busy = [await next_of(ws, "reply") for _ in range(30 - MAX_IN_FLIGHT)]
            tasks.append(tasks_in_view())
            await ws.send_str(json.dumps({"id": "off", "op": "lasers_off"}))
            await ws.send_str(json.dumps({"id": "more", "op": "stop"}))
            busy.append(await next_of(ws, "reply"))
            tasks.append(tasks_in_view())
            fake.hold.set()
            done = [await next_of(ws, "reply") for _ in range(MAX_IN_FLIGHT + 1)]
            await ws.close()
            return tasks, busy, done

    try:
        tasks, busy, done = asyncio.run(run())
    finally:
        fake.hold.set()
        view.stop()
    # 30 operations at once: MAX_IN_FLIGHT became tasks, the rest were answered busy at once;
    # "lasers_off" became a task even so, a further stop did not.
    assert [n - tasks[0] for n in tasks[1:]] == [MAX_IN_FLIGHT, MAX_IN_FLIGHT + 1]
    assert [r["id"] for r in busy] == [*range(MAX_IN_FLIGHT, 30), "more"]
    assert {r["error"]["name"] for r in busy} == {"busy"}
    assert f"{MAX_IN_FLIGHT} operations are running already" in busy[0]["error"]["message"]
    assert sorted(str(r["id"]) for r in done) == sorted(
        [*(str(i) for i in range(MAX_IN_FLIGHT)), "off"])
    assert all(r["ok"] for r in done)
    assert fake.count("stop") == MAX_IN_FLIGHT and fake.count("laser") == 1


def test_an_oversized_message_closes_the_socket_before_it_reaches_the_daemon(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="nhfd.web")
    view, fake = start_view(tmp_path, max_message_bytes=1024)

    async def run() -> tuple[int | None, dict]:
        async with await signed_in(view) as s:
            ws = await s.ws_connect(f"{view.url}ws")
            await ws.send_str(json.dumps({"id": 1, "op": "stop", "pad": "x" * 1100}))
            while (await ws.receive(timeout=GUARD_S)).type == aiohttp.WSMsgType.TEXT:
                pass
            code = ws.close_code
            ws = await s.ws_connect(f"{view.url}ws")  # a message within the limit still goes
            await ws.send_str(json.dumps({"id": 2, "op": "stop", "pad": "x" * 900}))
            reply = await next_of(ws, "reply")
            await ws.close()
            return code, reply

    try:
        code, reply = asyncio.run(run())
    finally:
        view.stop()
    assert code == 1009  # MESSAGE_TOO_BIG
    assert reply["id"] == 2 and fake.count("stop") == 1
    assert any("over 1024 bytes (daemon.web.max_message_bytes)" in line
               for line in web_log(caplog, "web message size"))


def test_deeply_nested_json_is_answered_with_an_error_and_the_socket_goes_on(tmp_path):
    view, fake = start_view(tmp_path)
    nested = "[" * 30000 + "]" * 30000  # 60,000 bytes: within max_message_bytes

    async def run() -> list[dict]:
        async with await signed_in(view) as s:
            ws = await s.ws_connect(f"{view.url}ws")
            await ws.send_str(nested)
            deep_param = {"id": 2, "op": "focus", "z_mm": json.loads("[" * 50 + "]" * 50)}
            await ws.send_str(json.dumps(deep_param))
            await ws.send_str(json.dumps({"id": [[1]], "op": "stop"}))
            await ws.send_str(json.dumps({"id": 4, "op": "stop"}))
            replies = [await next_of(ws, "reply") for _ in range(4)]
            await ws.close()
            return replies

    try:
        nested_reply, deep_reply, bad_id, fine = asyncio.run(run())
    finally:
        view.stop()
    assert nested_reply["id"] is None and nested_reply["error"]["name"] == "invalid_request"
    assert "nested too deeply" in nested_reply["error"]["message"]
    assert deep_reply["id"] is None and (f"allowed: at most {MAX_DEPTH} levels"
                                         in deep_reply["error"]["message"])
    assert "id: allowed: a string" in bad_id["error"]["message"]
    assert fine == {"type": "reply", "id": 4, "op": "stop", "ok": True, "result": {"ok": True}}
    assert [m for m, _ in fake.calls if m not in ("status", "preview")] == ["stop"]


def raw_connection(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=GUARD_S)
    return sock


def read_all(sock: socket.socket) -> bytes:
    """Everything until the server closes (a recv timing out raises: the server kept it)."""
    out = b""
    while chunk := sock.recv(4096):
        out += chunk
    return out


def test_connections_past_max_connections_get_503_and_a_freed_slot_is_taken_again(tmp_path):
    """Idle connections fill the cap (a WebSocket counts alike: both are aiohttp's connections;
    raw ones keep the count free of a client library's own connections coming and going)."""
    view, _ = start_view(tmp_path, max_connections=3)
    held: list[socket.socket] = []
    try:
        for n in range(1, 4):  # one at a time: each counted before the next comes
            held.append(raw_connection(view.port))
            wait_until(lambda n=n: view.connections() == n, GUARD_S, f"{n} connections held")
        extra = raw_connection(view.port)
        answer = read_all(extra)
        assert answer.startswith(b"HTTP/1.1 503 Service Unavailable\r\n")
        assert answer.endswith(b"daemon.web.max_connections connections already\n")
        assert view.connections() == 3
        held.pop().close()
        wait_until(lambda: view.connections() == 2, GUARD_S, "the closed one to go")
        conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=GUARD_S)
        conn.request("GET", "/")
        assert conn.getresponse().status == 401  # served: the login form
        conn.close()
    finally:
        for sock in held:
            sock.close()
        view.stop()


def test_connections_that_send_no_request_or_half_of_one_are_dropped(tmp_path):
    view, _ = start_view(tmp_path, idle_timeout_s=0.3)
    try:
        silent = raw_connection(view.port)
        half = raw_connection(view.port)
        half.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # the blank line never comes
        assert read_all(silent) == b""
        assert read_all(half) == b""
        wait_until(lambda: view.connections() == 0, GUARD_S, "no connection held")
    finally:
        view.stop()


EMFILE_CHILD = """
import logging, os, resource, sys, time
from pathlib import Path
from nhfd.config import WebSettings
from nhfd.web.server import WebView
logging.basicConfig(level=logging.INFO, stream=sys.stderr)
view = WebView(WebSettings(port=0, max_connections=4096), socket_path=Path("/nonexistent"),
               token="t", call=lambda method, **p: {}, idle_timeout_s=60)
view.start()
soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
resource.setrlimit(resource.RLIMIT_NOFILE, (len(os.listdir("/proc/self/fd")) + 12, hard))
print(view.port, flush=True)
sys.stdin.read()  # until the test closes it
view.stop()
"""


def test_running_out_of_descriptors_is_logged_once_and_the_view_serves_again(tmp_path):
    err = tmp_path / "stderr.txt"
    with err.open("w") as stderr:
        child = subprocess.Popen([sys.executable, "-c", EMFILE_CHILD], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, stderr=stderr, text=True,
                                 cwd=Path(__file__).resolve().parents[2])
    peers: list[socket.socket] = []
    try:
        port = int(child.stdout.readline())
        # The child has 12 descriptors to spare: 40 connections run it out while accepting.
        peers = [raw_connection(port) for _ in range(40)]
        wait_until(lambda: "cannot accept a connection" in err.read_text(), GUARD_S,
                   "the child to run out of descriptors")
        for sock in peers:
            sock.close()
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=GUARD_S)
        conn.request("GET", "/")
        assert conn.getresponse().status == 401
        conn.close()
        assert child.poll() is None
    finally:
        for sock in peers:
            sock.close()
        child.stdin.close()
        child.wait(GUARD_S)
    text = err.read_text()
    assert text.count("cannot accept a connection: [Errno 24] Too many open files") == 1, text
    assert "Traceback" not in text


def test_a_failing_push_is_logged_and_the_pushes_go_on(tmp_path, caplog):
    view, fake = start_view(tmp_path, push_interval_s=0.05)
    fake.fail_status = 1

    async def run() -> list[dict]:
        async with await signed_in(view) as s:
            ws = await s.ws_connect(f"{view.url}ws")
            states = [await next_of(ws, "state") for _ in range(2)]
            await ws.close()
            return states

    try:
        first, second = asyncio.run(run())
    finally:
        view.stop()
    assert "KeyError" in first["daemon_error"]
    assert second["status"] == {"frames": {"frames_shown": 0}}
    assert web_log(caplog, "push failed: KeyError")


def armed_daemon_config(root: Path):
    return bench_config(root, None, web={"enabled": True, "port": 0})


def test_the_web_views_thread_ending_leaves_the_daemon_serving_and_the_lasers_as_they_were(
        caplog):
    caplog.set_level(logging.INFO, logger="nhfd.web")
    with running_daemon(armed_daemon_config, "nhfd-w-") as (r, _):
        view = r.web_view()
        try:
            with r.client() as c:
                c.call("laser", action="arm", duration_s=60)
                before = c.call("status")["laser"]
                assert before["armed"]

                def end_the_thread() -> None:
                    raise SystemExit("injected: the web view's thread ends")

                view._loop.call_soon_threadsafe(end_the_thread)
                wait_until(lambda: not view.alive, GUARD_S, "the web view's thread to end")
                after = c.call("status")
            assert r.thread.is_alive() and not r.daemon.stopping
            assert after["laser"]["armed"] and after["daemon"]["state"] == "ready"
            assert web_log(caplog, "web view failed (SystemExit: injected")
            assert "the daemon goes on, lasers as they were" in web_log(caplog, "failed")[0]
            with pytest.raises(OSError):
                socket.create_connection(("127.0.0.1", view.port), timeout=1).close()
        finally:
            view.stop()


def test_all_lasers_off_from_the_page_is_audited_as_the_web_client(tmp_path):
    with running_daemon(armed_daemon_config, "nhfd-w-") as (r, root):
        view = r.web_view()

        async def run() -> tuple[str, dict]:
            async with await signed_in_with(view, (root / "run" / "web.token")) as s:
                ws = await s.ws_connect(f"{view.url}ws")
                host, port = ws.get_extra_info("sockname")[:2]
                await ws.send_str(json.dumps({"id": 1, "op": "lasers_off"}))
                reply = await next_of(ws, "reply")
                await ws.close()
                return f"{host}:{port}", reply

        try:
            with r.client() as c:
                c.call("laser", action="arm", duration_s=60)
            address, reply = asyncio.run(run())
        finally:
            view.stop()
        assert reply["ok"] and reply["result"]["all_off"]
        offs = [line for line in audit_lines(root / "run" / "audit.jsonl")
                if line["what"] == "laser" and line.get("params") == {"action": "off"}]
        assert len(offs) == 1
        who = offs[0]["who"]
        assert who["web_client"] == {"via": "web view", "address": address, "tls": False,
                                     "token_file": str(root / "run" / "web.token")}
        assert who["transport"] == "unix" and who["pid"] == os.getpid()  # relayed by itself

        # Any other process claiming to be the web view is refused: its pid is not the daemon's.
        code = ("import sys; from nhfd.daemon.client import Client\n"
                "from nhfd.daemon.protocol import RpcError\n"
                "try:\n    Client(sys.argv[1]).call('web_client', address='10.0.0.1:1')\n"
                "except RpcError as exc:\n    print(exc.name, exc.data)")
        done = subprocess.run([sys.executable, "-c", code, str(r.socket)], capture_output=True,
                              text=True, timeout=GUARD_S * 3)
        assert done.stdout.startswith("forbidden {'field': 'method'"), done.stdout + done.stderr
        with Client(r.socket) as c, pytest.raises(RpcError) as info:
            c.call("web_client", address="x", tls="yes")  # checked like any parameter
        assert info.value.data == {"field": "tls", "allowed": "true or false"}


async def signed_in_with(view: WebView, token_file: Path) -> aiohttp.ClientSession:
    session = aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True))
    token = token_file.read_text().strip()
    async with session.get(f"{view.url}?token={token}", allow_redirects=False) as r:
        assert r.status == 303
    return session


def test_reconnecting_does_not_refill_the_burst(tmp_path):
    clock = Clock()
    view, fake = start_view(tmp_path, clock=clock, messages_per_s=5.0)

    async def run() -> None:
        async with await signed_in(view) as s:
            ws = await s.ws_connect(f"{view.url}ws")
            for i in range(5):  # the whole burst
                await ws.send_str(json.dumps({"id": i, "op": "stop"}))
            for _ in range(5):
                await next_of(ws, "reply")
            await ws.close()
            ws = await s.ws_connect(f"{view.url}ws")  # same host, same instant: no new tokens
            for i in range(5):
                await ws.send_str(json.dumps({"id": 10 + i, "op": "stop"}))
            await next_of(ws, "refused")
            await asyncio.to_thread(wait_until, lambda: view.messages_refused == 5, GUARD_S,
                                    "the second socket's messages read")
            await ws.close()

    try:
        asyncio.run(run())
    finally:
        view.stop()
    assert fake.count("stop") == 5
