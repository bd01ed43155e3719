"""Hostile peers on the control sockets (issue 32, items 1, 3 and the daemon's side of 4): silent
TCP and TLS connections cannot lock the Unix socket out and are dropped at their deadline; a
refused TLS client reads an RPC error, not a TLS failure; a newline flood and an endless line
stay within the per-connection buffer bound while the heartbeat keeps the guardian armed; one
poll serves for at most the tick budget; accept running out of descriptors pauses that listener
and nothing else; the daemon raises its open-files limit at start; deep nesting is a parse error.
Light is read from the laser twin's emission record, never from the daemon's word."""

from __future__ import annotations

import errno
import itertools
import json
import logging
import resource
import select
import signal
import socket
import ssl
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from nhfd.config import Config, ServerSettings, _overlay, default_text
from nhfd.daemon import protocol
from nhfd.daemon.client import Client
from nhfd.daemon.protocol import RpcError
from nhfd.daemon.server import ACCEPT_BACKOFF_S, LineServer

from .conftest import Running, bench_config, free_port, wait_until
from .test_signals import light_red, write_config

REPO = Path(__file__).resolve().parents[2]
STATUS = b'{"jsonrpc":"2.0","method":"status","id":1}\n'
OFF = {"red": 0.0, "green": 0.0, "blue": 0.0}


class ShiftedClock:
    """time.monotonic plus an offset the test moves: deadlines pass without sleeping."""

    def __init__(self) -> None:
        self.offset_s = 0.0

    def __call__(self) -> float:
        return time.monotonic() + self.offset_s


def read_lines(socks: list[socket.socket], count: int, timeout_s: float = 10.0
               ) -> dict[socket.socket, bytes]:  # fmt: skip
    """The first line (or b"" for a close) from each socket that sends one, until `count` of
    them have, without waiting on the silent ones one by one."""
    got: dict[socket.socket, bytes] = {}
    buffers: dict[socket.socket, bytes] = {s: b"" for s in socks}
    end = time.monotonic() + timeout_s
    while len(got) < count and time.monotonic() < end:
        ready, _, _ = select.select([s for s in socks if s not in got], [], [], 0.1)
        for s in ready:
            try:
                chunk = s.recv(4096)
            except ConnectionResetError:
                chunk = b""
            buffers[s] += chunk
            if not chunk or b"\n" in buffers[s]:
                got[s] = buffers[s].split(b"\n")[0]
    return got


def closed_by_peer(s: socket.socket) -> bool:
    """The daemon closed this silent connection (end of file or a reset)."""
    ready, _, _ = select.select([s], [], [], 0)
    if not ready:
        return False
    try:
        return s.recv(4096) == b""
    except ConnectionResetError:
        return True


# ------------------------------------------------------------------------------ 1. lock-out


@pytest.mark.parametrize("tls", [False, True], ids=["plain", "tls"])
def test_silent_tcp_peers_cannot_lock_out_the_unix_socket_and_go_at_their_deadline(
        short_dir, mecom_twin, tls):
    extra = {}
    cert = None
    if tls:
        pytest.importorskip("cryptography.x509", reason="the dev extra's cryptography makes "
                            "the test certificates")
        from .test_tls import self_signed

        cert, key = self_signed(short_dir, "bench")
        extra = {"tls_cert": str(cert), "tls_key": str(key)}
    # Four Unix slots and twelve silent TCP peers: under a shared cap the silent peers would
    # take every slot (the old daemon answered the Unix client `busy`).
    config = bench_config(short_dir, mecom_twin,
                          server={"tcp_port": free_port(), "max_clients": 4, "max_tcp_clients": 6,
                                  "max_unauthenticated": 3, "auth_timeout_s": 5.0, **extra})
    r = Running(config, short_dir)
    silent: list[socket.socket] = []
    remotes: list[Client] = []
    try:
        server = r.daemon.server
        clock = ShiftedClock()
        server.clock = clock
        addr = server.tcp_address
        token = (short_dir / "run" / "tcp.token").read_text().strip()
        with r.client() as c:
            light_red(c, mecom_twin)
        for _ in range(3):
            silent.append(socket.create_connection(addr, timeout=5))
        wait_until(lambda: server.client_counts()["unauthenticated"] == 3, 10,
                   "three connections waiting to authenticate")
        if tls:
            # A TLS client over the cap completes its handshake and reads the refusal inside
            # TLS (the old daemon wrote it in plaintext: WRONG_VERSION_NUMBER), then a clean end.
            reply = refusal_over(addr, cert)
            assert reply["id"] is None and reply["error"]["code"] == protocol.BUSY.code
            assert ("too many TCP connections waiting to authenticate "
                    "(daemon.server.max_unauthenticated = 3") in reply["error"]["message"]
            assert reply["error"]["data"] == {"field": "daemon.server.max_unauthenticated",
                                              "allowed": "at most 3 at once"}
        late = [socket.create_connection(addr, timeout=5) for _ in range(9)]
        silent += late
        answers = read_lines(late, 9 if not tls else 6)
        if tls:
            # Three more are kept for a busy reply inside TLS (they never say hello); past that
            # cap the daemon closes at once, never writing plaintext to a TLS port.
            assert sorted(answers.values()) == [b""] * 6
            assert server.client_counts()["refusing"] == 3
        else:
            assert len(answers) == 9
            for line in answers.values():
                err = json.loads(line)["error"]
                assert err["code"] == protocol.BUSY.code
                assert "daemon.server.max_unauthenticated = 3" in err["message"]
        assert server.client_counts()["unauthenticated"] == 3
        # The Unix socket is untouched: status, and the lasers off with the twin dark.
        with r.client() as c:
            assert c.status()["daemon"]["state"] == "ready"
            assert c.call("laser", action="off") == {"armed": False, "all_off": True}
        assert mecom_twin.emitting() == OFF
        # The deadline: every silent connection is closed by the daemon, and the slots are
        # free again for a client with the token.
        clock.offset_s = config.daemon.server.auth_timeout_s
        wait_until(lambda: all(closed_by_peer(s) for s in silent), 10,
                   "the silent connections to be dropped")
        wait_until(lambda: server.client_counts() == {"unix": 0, "tcp": 0,
                                                      "unauthenticated": 0, "refusing": 0},
                   10, "every slot free")
        remotes += [Client(tcp=addr, token=token, tls_ca=cert) for _ in range(6)]
        assert remotes[-1].status()["daemon"]["state"] == "ready"
        # Authenticated clients fill max_tcp_clients; the next one hears so in its protocol.
        reply = refusal_over(addr, cert)
        assert reply["error"]["code"] == protocol.BUSY.code
        assert reply["error"]["message"] == ("too many TCP clients "
                                             "(daemon.server.max_tcp_clients = 6); retry later")
        with r.client() as c:
            assert c.status()["daemon"]["state"] == "ready"
    finally:
        for s in silent:
            s.close()
        for remote in remotes:
            remote.close()
        r.stop()


def refusal_over(addr: tuple[str, int], cert: Path | None) -> dict:
    """Connect (TLS when `cert` is given, trusting it), read the one line the daemon sends
    unasked, parsed, and check that the daemon then ends the connection cleanly."""
    sock = socket.create_connection(addr, timeout=5)
    if cert is not None:
        sock = ssl.create_default_context(cafile=str(cert)).wrap_socket(
            sock, server_hostname=addr[0])
    with sock:
        got = b""
        while b"\n" not in got:
            chunk = sock.recv(4096)
            assert chunk, got
            got += chunk
        line, rest = got.split(b"\n", 1)
        assert rest == b"" and sock.recv(4096) == b""  # (TLS: close_notify, no reset)
        return json.loads(line)


def test_unix_clients_past_max_clients_get_the_busy_line(short_dir, mecom_twin):
    r = Running(bench_config(short_dir, mecom_twin, server={"max_clients": 2}), short_dir)
    try:
        with r.client() as a, r.client() as b:
            a.status()
            b.status()
            with socket.socket(socket.AF_UNIX) as third:
                third.settimeout(5)
                third.connect(str(r.socket))
                reply = json.loads(third.recv(4096).split(b"\n")[0])
            assert reply["error"]["code"] == protocol.BUSY.code
            assert reply["error"]["message"] == ("too many clients on the Unix socket "
                                                 "(daemon.server.max_clients = 2); retry later")
    finally:
        r.stop()


# ------------------------------------------------------------------------- 3. newline flood


def _flood(make_sock, payload: bytes, stop: threading.Event, drops: list[int]) -> None:
    """Send `payload` again and again; when the daemon drops us, count it and reconnect, as a
    hostile peer would."""
    while not stop.is_set():
        try:
            s = make_sock()
        except OSError:
            time.sleep(0.01)
            continue
        try:
            while not stop.is_set():
                s.sendall(payload)
        except OSError:
            drops.append(1)
        finally:
            s.close()


@pytest.mark.solo  # the heartbeat's gaps, measured: no other test's load beside it
def test_a_newline_flood_and_an_endless_line_stay_bounded_and_the_heartbeat_keeps_its_period(
        short_dir, mecom_twin, caplog):
    config = bench_config(short_dir, mecom_twin, server={"tcp_port": free_port()})
    c = config.daemon.server
    r = Running(config, short_dir)
    stop = threading.Event()
    threads: list[threading.Thread] = []
    try:
        server = r.daemon.server
        beats: list[float] = []
        peak = [0]
        real_beat, real_poll = r.daemon.laser.heartbeat, server.poll

        def beat(now: float) -> None:
            beats.append(time.monotonic())
            real_beat(now)

        def poll(timeout_s: float):
            try:
                return real_poll(timeout_s)
            finally:  # in the loop's thread: the connections are not changing under us
                held = [len(conn.inbuf) for conn in server.connections.values()]
                peak[0] = max(peak[0], *held, 0)

        with r.client() as cl:
            light_red(cl, mecom_twin)
        r.daemon.laser.heartbeat, server.poll = beat, poll
        addr = server.tcp_address
        newline_drops: list[int] = []
        line_drops: list[int] = []

        def unix_sock() -> socket.socket:
            s = socket.socket(socket.AF_UNIX)
            s.connect(str(r.socket))
            return s

        floods = [
            # Empty lines, unauthenticated, over TCP (the issue's attack, without TLS).
            (lambda: socket.create_connection(addr, timeout=5), b"\n" * (1 << 20), newline_drops),
            # The same from a local peer, which has no auth deadline to save the daemon.
            (unix_sock, b"\n" * (1 << 20), newline_drops),
            # One line that never ends.
            (unix_sock, b"x" * (1 << 20), line_drops),
        ]
        for make, payload, drops in floods:
            t = threading.Thread(target=_flood, args=(make, payload, stop, drops), daemon=True)
            t.start()
            threads.append(t)
        answered = 0
        end = time.monotonic() + 2.0
        with r.client(timeout_s=10) as cl:
            while time.monotonic() < end:
                assert cl.status()["laser"]["armed"] is True
                answered += 1
        stop.set()
        for t in threads:
            t.join(10)
        during = [b for b in beats if b <= end]
        gaps = [b - a for a, b in itertools.pairwise(during)]
        timeout_s = config.devices.readybeam.guardian.heartbeat_timeout_s
        # The guardian disarms after heartbeat_timeout_s (0.5 s) without a heartbeat; the loop
        # sends one every heartbeat_s (0.1 s), late by at most a tick budget and one request.
        assert len(during) >= 10 and max(gaps) < timeout_s, (len(during), max(gaps))
        assert answered >= 5
        # The bound: nothing held more than max_buffered_bytes unhandled (the old daemon grew
        # without limit), and the newline flooders were dropped for it.
        assert peak[0] <= c.max_buffered_bytes, peak[0]
        assert server.peak_buffered_bytes <= c.max_buffered_bytes
        assert newline_drops, ("the newline flooders were never dropped", server.refused, peak)
        reason = (f"dropped: more than daemon.server.max_buffered_bytes = "
                  f"{c.max_buffered_bytes} bytes received and not yet handled")
        assert server.refused[reason] >= 2  # the TCP and the Unix flooder, each at least once
        # Logged once, with the peer, however many times flooders were dropped.
        logged = [r.getMessage() for r in caplog.records if r.getMessage().startswith(reason)]
        assert len(logged) == 1 and "'transport': " in logged[0], logged
        # The endless line is skipped, not buffered: its peer keeps its connection.
        assert not line_drops
        # The twin never went dark, and the guardian never disarmed for a missed heartbeat.
        assert mecom_twin.emitting()["red"] == 5.0 and mecom_twin.dark_since() is None
        with r.client() as cl:
            assert cl.status()["laser"]["armed"] is True
            cl.call("laser", action="off")
    finally:
        stop.set()
        for t in threads:
            t.join(10)
        r.stop()


# --------------------------------------------------------------------------- tick budget


class _Stepped:
    """A LineServer the test polls by hand, on a clock that only the handler advances."""

    def __init__(self, root: Path, per_line_s: float, **kw) -> None:
        self.now = 1000.0
        self.handled: list[bytes] = []

        def handler(conn, line: bytes) -> bytes:
            self.handled.append(line)
            self.now += per_line_s
            return line + b"\n"

        self.server = LineServer(handler, unix_path=root / "s.sock",
                                 settings=ServerSettings(**kw))
        self.server.clock = lambda: self.now
        self.server.listen()

    def connect(self, n: int) -> list[socket.socket]:
        socks = []
        for _ in range(n):
            s = socket.socket(socket.AF_UNIX)
            s.settimeout(5)
            s.connect(str(self.server.unix_path))
            socks.append(s)
        wait = time.monotonic() + 10
        while len(self.server.connections) < n and time.monotonic() < wait:
            self.server.poll(0.05)
        assert len(self.server.connections) == n
        return socks


def test_one_poll_serves_for_at_most_the_tick_budget_and_the_rest_in_turn(short_dir):
    stepped = _Stepped(short_dir, per_line_s=0.01, lines_per_poll=64)
    server = stepped.server
    server.tick_budget_s = 0.05  # five lines' worth of the handler's 10 ms
    socks = stepped.connect(3)
    try:
        for i, s in enumerate(socks):
            s.sendall(b"".join(b"c%d-%02d\n" % (i, k) for k in range(20)))
        time.sleep(0.2)  # every byte in the server's socket buffers (not a timing assertion)
        server.poll(0)
        first = len(stepped.handled)
        assert 1 <= first <= 6, stepped.handled  # the old server handled all 60 in one poll
        polls = 1
        while len(stepped.handled) < 60 and polls < 100:
            server.poll(0)
            polls += 1
        assert len(stepped.handled) == 60 and polls >= 10
        # In turn: no client got its 10th line handled before every client had its 3rd.
        order = [int(line[1:2]) for line in stepped.handled]
        tenth = min(max(k for k, c in enumerate(order) if c == i and
                        order[: k + 1].count(i) == 10) for i in range(3))
        assert all(order[: tenth + 1].count(i) >= 3 for i in range(3)), order
        for i, s in enumerate(socks):
            got = b""
            while got.count(b"\n") < 20:
                got += s.recv(65536)
            assert got.splitlines() == [b"c%d-%02d" % (i, k) for k in range(20)]
    finally:
        for s in socks:
            s.close()
        server.close()


def test_empty_lines_count_against_lines_per_poll(short_dir):
    stepped = _Stepped(short_dir, per_line_s=0.0, lines_per_poll=8)
    server = stepped.server
    (s,) = stepped.connect(1)
    try:
        s.sendall(b"\n" * 8 + b"after\n")
        time.sleep(0.1)
        server.poll(0)
        assert stepped.handled == []  # eight empty lines used this poll's share
        server.poll(0)
        assert stepped.handled == [b"after"]
    finally:
        s.close()
        server.close()


# -------------------------------------------------------------------- 4. file descriptors


def test_accept_out_of_descriptors_pauses_that_listener_and_keeps_serving(short_dir, caplog,
                                                                          monkeypatch):
    stepped = _Stepped(short_dir, per_line_s=0.0)
    server = stepped.server
    (old,) = stepped.connect(1)
    (listener,) = [sock for sock, transport in server._listeners.values()
                   if transport == "unix"]
    attempts: list[int] = []
    real_accept = socket.socket.accept
    failing = [True]

    def accept(sock: socket.socket):
        if sock.fileno() == listener.fileno():
            attempts.append(1)
            if failing[0]:
                raise OSError(errno.EMFILE, "Too many open files")
        return real_accept(sock)

    monkeypatch.setattr(socket.socket, "accept", accept)
    new = socket.socket(socket.AF_UNIX)
    new.settimeout(5)
    try:
        with caplog.at_level(logging.INFO, logger="nhfd.daemon.server"):
            new.connect(str(server.unix_path))  # waits in the kernel's backlog
            server.poll(1.0)  # the old server raised EMFILE out of poll: the daemon stopped
            assert attempts == [1]
            assert listener.fileno() not in server.selector.get_map()
            # Paused: the ready listener is not retried in a spin, and the client already
            # connected is still answered.
            old.sendall(b"hello\n")
            for _ in range(20):
                server.poll(0.01)
            assert attempts == [1]
            assert old.recv(4096) == b"hello\n"
            # Past the pause it tries again; still failing, it pauses again without a new log.
            stepped.now += ACCEPT_BACKOFF_S
            server.poll(0.5)
            assert attempts == [1, 1]
            stepped.now += ACCEPT_BACKOFF_S
            failing[0] = False
            server.poll(0.5)
            assert attempts == [1, 1, 1] and len(server.connections) == 2
            new.sendall(b"late\n")
            server.poll(1.0)
            assert new.recv(4096) == b"late\n"
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert warnings == [f"unix listener: accept failed (Too many open files); not accepting "
                            f"for {ACCEPT_BACKOFF_S:g} s at a time until descriptors are free; "
                            "connected clients are still served"]
        assert "unix listener: accepting connections again" in caplog.messages
        assert server.refused["unix accept failed"] == 2
    finally:
        new.close()
        old.close()
        server.close()


def test_refusals_are_logged_with_the_peer_once_then_summarised(short_dir, caplog):
    stepped = _Stepped(short_dir, per_line_s=0.0, max_clients=1)
    server = stepped.server
    (kept,) = stepped.connect(1)
    extra = []
    try:
        with caplog.at_level(logging.WARNING, logger="nhfd.daemon.server"):
            for _ in range(3):
                s = socket.socket(socket.AF_UNIX)
                s.settimeout(5)
                s.connect(str(server.unix_path))
                extra.append(s)
                server.poll(1.0)
                assert json.loads(s.recv(4096))["error"]["code"] == protocol.BUSY.code
            first = caplog.messages[:]
            stepped.now += 60.0
            server.poll(0)
        assert len(first) == 1
        assert first[0].startswith("unix connection refused (busy): {'transport': 'unix', "
                                   "'uid': ")
        assert caplog.messages[1:] == ["unix connection refused (busy): 2 more in the last 60 s"]
        assert server.refused["unix connection refused (busy)"] == 3
    finally:
        for s in [kept, *extra]:
            s.close()
        server.close()


def test_the_daemon_raises_its_soft_open_files_limit_at_start(short_dir, mecom_twin):
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 1024:
        pytest.skip(f"the hard limit on open files here is {hard}")
    wanted = Config.model_validate(_overlay({}, {})).daemon.paths.open_files
    expected = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    cfg = write_config(short_dir, mecom_twin)

    def low_limit() -> None:  # in the child: a distribution's default soft limit, or lower
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, hard))

    proc = subprocess.Popen([sys.executable, "-m", "nhfd.cli.main", "serve", "--config", cfg],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=low_limit)
    try:
        sock = short_dir / "run" / "control.sock"

        def answers() -> bool:
            assert proc.poll() is None, proc.stderr.read()
            try:
                with Client(sock, timeout_s=2) as c:
                    return c.status()["daemon"]["pid"] == proc.pid
            except (OSError, RpcError):
                return False

        wait_until(answers, 20, "the daemon's socket")
        assert resource.prlimit(proc.pid, resource.RLIMIT_NOFILE) == (expected, hard)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
        log = proc.stderr.read()
        assert f"open files: soft limit {expected} (daemon.paths.open_files = {wanted}" in log
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_the_unit_sets_the_open_files_limit_to_the_default_open_files():
    unit = (REPO / "packaging" / "systemd" / "nhfd.service").read_text()
    lines = [line for line in unit.splitlines() if line.startswith("LimitNOFILE=")]
    default = Config.model_validate(_overlay({}, {})).daemon.paths.open_files
    assert lines == [f"LimitNOFILE={default}"]
    assert f"open_files = {default}" in default_text()


# ------------------------------------------------------------------------------ nesting


def test_deep_nesting_is_a_parse_error_and_the_daemon_keeps_serving(short_dir, mecom_twin):
    r = Running(bench_config(short_dir, mecom_twin), short_dir)
    try:
        with socket.socket(socket.AF_UNIX) as s:
            s.settimeout(10)
            s.connect(str(r.socket))
            deep = b"[" * 30_000 + b"]" * 30_000  # under max_line_bytes: it reaches the parser
            # A few hundred levels in the params of a method that is audited: the parser took
            # it, and the audit log's copy of the refused params raised RecursionError, which
            # ended the old daemon.
            nest = b"[" * 600 + b"]" * 600
            audited = b'{"jsonrpc":"2.0","id":2,"method":"stop","params":{"x":' + nest + b"}}"
            s.sendall(deep + b"\n" + audited + b"\n" + STATUS)
            got = b""
            while got.count(b"\n") < 3:
                chunk = s.recv(1 << 16)
                assert chunk, got
                got += chunk
        first, second, third = (json.loads(line) for line in got.splitlines())
        assert first["error"] == {"code": -32700, "message": "parse error: nested too deeply"}
        assert second["error"]["code"] == -32700
        assert second["error"]["message"] == ("parse error: nested too deeply (more than "
                                              f"{protocol.MAX_NESTING} levels of arrays and "
                                              "objects)")
        assert third["result"]["daemon"]["state"] == "ready"
        assert r.thread.is_alive()
    finally:
        r.stop()


def test_nesting_up_to_the_cap_parses_and_one_more_level_does_not():
    depth = protocol.MAX_NESTING
    ok = "[" * (depth - 1) + '{"a": 1}' + "]" * (depth - 1)
    assert protocol._nesting(protocol.loads(ok)) == depth
    with pytest.raises(RpcError, match=rf"more than {depth} levels") as info:
        protocol.loads("[" * depth + '{"a": 1}' + "]" * depth)
    assert info.value.code == protocol.PARSE_ERROR.code
