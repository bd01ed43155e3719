"""`nhfd bench hostile`: the attacks of issue 32 on a lit, armed daemon; what each costs the
operator (status latency, heartbeat disarms, memory) and whether `nhfctl laser off` still works.

Every scenario starts a fresh `nhfd serve` as its own process on the simulated bench, as `nhfd
bench safety` does: the READYBeam twin is hosted by this process (`devices.laser = "readybeam"`
on the twin's pty, a guardian the daemon spawns). The lasers are armed and red is lit at 5 %
before the attack, so a disarm by starvation shows as light going off on the twin. During the
attack window (`--duration-s`):

- a Unix-socket client here calls `status` every 20 ms and times each reply (median, p99; a
  call that fails or times out is counted as a failure, never left out);
- the daemon's resident memory (VmRSS in /proc/<pid>/status) is read every 50 ms;
- the attackers are processes of their own (forked), so they compete with the daemon for the
  CPU but not with the laser twin or the status client for this process's GIL.

At the end of the window, with the attackers still at it, `nhfctl laser off` runs as a command
(`python -m nhfd.cli.nhfctl --socket ... laser off`, falling back to the guardian as it does for
an operator); "ms to dark" is the twin's `dark_since()` minus the moment the command started
(interpreter start-up included), read from the device's record, never the daemon's word.
Disarms are the guardian's own, as the daemon audits them ("laser disarmed by the guardian:
<reason>") within the window; starvation is a reason naming the heartbeat. Late heartbeats and
the largest gap come from `status.laser.guardian`.

Scenarios (names for --scenarios):
  idle             nothing: the baseline.
  tcp-lockout      100 plain TCP connections to daemon.server.tcp_port that never send a byte; each
                   the daemon closes or refuses is opened again 1 s later.
  newline-flood    two peers, one on TCP (never authenticated) and one on the Unix socket, each
                   sending b"\\n" * 2^20 in a loop, reconnecting whenever dropped.
  deep-json        `stop` requests whose params nest 30,000 and 600 levels deep, one after the
                   other on the Unix socket, as fast as the replies come.
  web-connections  1,100 connections to the web view's port that send nothing; each closed or
                   refused is opened again 1 s later (needs aiohttp).
  web-flood        one token holder sending the page's `{"id", "op": "stop"}` over its
                   WebSocket as fast as it can, reconnecting when closed (needs aiohttp).
  hostile-scenes   load_scene of each hostile file, built small in a folder of
                   daemon.paths.scene_dirs, repeated for the window: a gzip-bomb .spz, a zstd .spz
                   declaring 2^28 points, a .sog zip bomb, a .glb with byteStride 0 and count
                   2^28, a .gltf whose buffer is ../outside.bin, one whose buffer is /dev/zero,
                   an ASCII .ply declaring 4e9 vertices. Each must be refused, naming its cause.
  hostile-models   the shipped model and scene loaded, then load_model of copies whose nhfd
                   metadata has amplitude_scale NaN, and input_multiple 0, repeated for the
                   window: each must be refused naming the field, and the shipped model must
                   keep serving (a new view is rendered afterwards).

Goals, printed beside the figures (on 2 cores): no disarm by starvation, no crash, the
daemon's RSS at most 200 MB above its start; `laser off` succeeds and the twin is dark within
1 s; status p99 under 100 ms, except under floods the bounds visibly refuse (refusals counted).
The exit code is 1 when a safety fact fails (the daemon died, the light went off during the
attack, `laser off` failed or the twin was not dark within --timeout-s, a hostile file or model
was accepted); the timing and memory goals are reported, not enforced, since a shared machine's
load moves them. Results: a markdown table (also written beside the JSON as .md) and JSON.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import json
import math
import multiprocessing
import os
import resource
import selectors
import shutil
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import onnx
import zstandard

from nhfd import __version__
from nhfd.benchmarks.load import config_text, rss_mb
from nhfd.benchmarks.machine import describe
from nhfd.benchmarks.safety import DEVICES, LIT_PCT, Bench
from nhfd.daemon.client import Client
from nhfd.drivers.twins.mecom_twin import MecomTwin
from nhfd.models.metadata import METADATA_KEY

# -- goals and measurement settings -------------------------------------------------------------

STATUS_EVERY_S = 0.02  # the status client's period (the measurement)
RSS_EVERY_S = 0.05  # VmRSS sampling period
GOAL_STATUS_P99_MS = 100.0
GOAL_RSS_GROWTH_MB = 200.0
GOAL_DARK_MS = 1000.0
# A connection the daemon closed or refused is opened again this long after: the attack keeps
# its pressure up without turning into a connect flood of its own.
REOPEN_S = 1.0
TCP_CONNECTIONS = 100
WEB_CONNECTIONS = 1100
NEWLINES = b"\n" * (1 << 20)
DEEP_LEVELS = (30_000, 600)
# How long an attacker may take to be under way (a web client imports aiohttp and logs in).
ATTACKER_READY_S = 20.0
# Waiting for each load job; the daemon's own scene-read limit is 120 s.
LOAD_WAIT_S = 150.0
HUGE = 1 << 28  # the declared counts of the files

# The goals as the JSON records them.
GOALS = {"starvation_disarms": 0, "crash": False, "rss_growth_mb_max": GOAL_RSS_GROWTH_MB,
         "laser_off_dark_ms_max": GOAL_DARK_MS, "status_p99_ms_max": GOAL_STATUS_P99_MS,
         "status_p99_waived": "under a flood whose refusals are counted"}


# -- the daemon, configured for the attack ------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class HostileBench(Bench):
    """`safety.Bench` with what an attack needs: a TCP port, the web view with a token file,
    and its own copies of the model and scene, so hostile files written beside them lie inside
    daemon.paths.model_dirs and daemon.paths.scene_dirs. Without a model the whole temporary root is
    the scene and model directory (the hostile scenes go in root/scenes)."""

    def __init__(self, *, model: Path | None = None, scene: Path | None = None,
                 tcp: bool = False, web: bool = False) -> None:
        # Bench.__init__ writes its fixed configuration and starts the daemon at once: the
        # same steps here, with the extra settings in the configuration.
        self.root = Path(tempfile.mkdtemp(prefix="nhfd-hostile-", dir="/tmp"))
        self.pids: set[int] = set()
        self.scenes = self.root / "scenes"
        self.models = self.root / "models"
        self.scenes.mkdir()
        self.models.mkdir()
        self.model: Path | None = None
        self.scene: Path | None = None
        if model is not None and scene is not None:
            self.model = Path(shutil.copy2(model, self.models / model.name))
            self.scene = Path(shutil.copy2(scene, self.scenes / scene.name))
        self.tcp_port = free_port() if tcp else None
        self.web_port = free_port() if web else None
        self.web_token = os.urandom(16).hex() if web else None
        self.twin = MecomTwin()
        self.twin.start()
        try:
            self._start()
        except BaseException:  # nothing of a bench that never started is left behind
            self.twin.close()
            shutil.rmtree(self.root, ignore_errors=True)
            raise

    def _start(self) -> None:
        """The configuration, then `nhfd serve` on it."""
        text = config_text(self.root, self.model, self.scene, DEVICES, self.twin.port_path)
        # config_text ends inside [daemon.server]: these keys join it.
        if self.tcp_port is not None:
            text += f"tcp_port = {self.tcp_port}\n"
        if self.web_token is not None:
            token_file = self.root / "web.token"
            token_file.write_text(self.web_token + "\n")
            token_file.chmod(0o600)
            text += (f"[daemon.web]\nenabled = true\nport = {self.web_port}\n"
                     f'token_file = "{token_file}"\n')
        parsed = tomllib.loads(text)["daemon"]["server"]
        if parsed.get("tcp_port", 0) != (self.tcp_port or 0):
            raise RuntimeError("config_text no longer ends in [daemon.server]: tcp_port went "
                               "elsewhere")
        self.config_path = self.root / "nhfd.toml"
        self.config_path.write_text(text)
        self.log = (self.root / "serve.log").open("w")
        self.proc = subprocess.Popen([sys.executable, "-m", "nhfd.cli.main", "serve",
                                      "--config", str(self.config_path)],
                                     stdout=subprocess.DEVNULL, stderr=self.log)
        self.socket = self.root / "run" / "control.sock"

    def wait_listening(self, port: int, timeout_s: float = 60.0) -> None:
        """Until the daemon accepts on `port` (the web view starts on its own thread)."""
        end = time.monotonic() + timeout_s
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"nhfd serve exited with {self.proc.returncode}: "
                                   f"{self.log_tail()}")
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                return
            except OSError:
                if time.monotonic() > end:
                    raise TimeoutError(f"nothing listens on port {port} after {timeout_s:g} s: "
                                       f"{self.log_tail()}") from None
                time.sleep(0.1)

    def light_for(self, arm_s: float) -> None:
        """Arm for `arm_s` (the whole scenario: an expiry is not an attack), red at LIT_PCT."""
        with self.client() as c:
            c.call("laser", action="arm", duration_s=arm_s)
            c.call("laser", action="power", channel="red", power_pct=LIT_PCT)
            c.call("laser", action="enable", channel="red")
        if not self.lit():
            raise RuntimeError("the twin does not emit after arm, power and enable")

    def lit(self) -> bool:
        return any(p > 0 for p in self.twin.emitting().values())

    def audit_records(self) -> list[dict[str, Any]]:
        """Every record of the audit log and its rotated files."""
        out = []
        for path in sorted(self.root.glob("audit.jsonl*")):
            for line in path.read_text(errors="replace").splitlines():
                with contextlib.suppress(ValueError):
                    record = json.loads(line)
                    if isinstance(record, dict):
                        out.append(record)
        return out

    def audit_bytes(self) -> int:
        return sum(p.stat().st_size for p in self.root.glob("audit.jsonl*"))

    def log_lines(self) -> int:
        self.log.flush()
        return (self.root / "serve.log").read_bytes().count(b"\n")


# -- the measurement around an attack ------------------------------------------------------------


def latency_summary(ms: list[float]) -> dict[str, Any]:
    """Median, p99 (nearest rank) and max of status round trips in ms."""
    if not ms:
        return {"n": 0, "median_ms": None, "p99_ms": None, "max_ms": None}
    ordered = sorted(ms)
    p99 = ordered[max(0, math.ceil(0.99 * len(ordered)) - 1)]
    return {"n": len(ordered), "median_ms": round(statistics.median(ordered), 2),
            "p99_ms": round(p99, 2), "max_ms": round(ordered[-1], 2)}


class Monitor:
    """The status client (every STATUS_EVERY_S, timed) and the RSS sampler (every
    RSS_EVERY_S), each on a thread of this process."""

    def __init__(self, bench: HostileBench) -> None:
        self.bench = bench
        self.latencies_ms: list[float] = []
        self.failures: list[str] = []
        self.rss_peak_mb = rss_mb(bench.proc.pid) or 0.0
        self._timing = threading.Event()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._status, daemon=True),
                         threading.Thread(target=self._rss, daemon=True)]

    def start(self) -> None:
        self._timing.set()
        for t in self._threads:
            t.start()

    def stop_timing(self) -> None:
        """Status latency is the attack's: no longer timed once `laser off` starts."""
        self._timing.clear()

    def stop(self) -> None:
        self._timing.clear()
        self._stop.set()
        for t in self._threads:
            t.join(10)

    def _status(self) -> None:
        client = None
        while not self._stop.is_set():
            t0 = time.perf_counter()
            try:
                if client is None:
                    client = self.bench.client(timeout_s=5.0)
                client.status()
                if self._timing.is_set():
                    self.latencies_ms.append((time.perf_counter() - t0) * 1e3)
            except Exception as exc:  # counted and shown: a lock-out is a result
                if self._timing.is_set():
                    self.failures.append(f"{type(exc).__name__}: {exc}"[:200])
                if client is not None:
                    with contextlib.suppress(Exception):
                        client.close()
                client = None
            self._stop.wait(STATUS_EVERY_S)
        if client is not None:
            with contextlib.suppress(Exception):
                client.close()

    def _rss(self) -> None:
        while not self._stop.is_set():
            now = rss_mb(self.bench.proc.pid)
            if now is not None:
                self.rss_peak_mb = max(self.rss_peak_mb, now)
            self._stop.wait(RSS_EVERY_S)


def laser_off(bench: HostileBench, timeout_s: float) -> dict[str, Any]:
    """`nhfctl laser off` as an operator runs it; the twin's time to dark from its start."""
    lit_before = bench.lit()
    t0 = time.monotonic()
    cmd = subprocess.Popen([sys.executable, "-m", "nhfd.cli.nhfctl", "--socket",
                            str(bench.socket), "--config", str(bench.config_path), "--json",
                            "laser", "off"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True)
    dark = bench.dark_after(t0, timeout_s)
    try:
        out, err = cmd.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        cmd.kill()
        out, err = cmd.communicate()
    command_ms = (time.monotonic() - t0) * 1e3
    by = None
    with contextlib.suppress(ValueError, IndexError, AttributeError):
        by = json.loads(out.strip().splitlines()[-1]).get("switched_off_by")
    return {"rc": cmd.returncode, "ok": cmd.returncode == 0 and dark is not None,
            "lit_before": lit_before, "switched_off_by": by,
            "ms_to_dark": None if dark is None else round(dark * 1e3, 1),
            "command_ms": round(command_ms, 1), "stderr": err.strip()[-300:]}


# -- attacks ------------------------------------------------------------------------------------


class Attack:
    """What a scenario does during its window: `start` returns once it is under way, `hold`
    lasts the window, `stop` ends it and returns its counts. The base class is the idle
    baseline."""

    flood = False  # a flood whose refusals, when counted, waive the status p99 goal

    def start(self) -> None:
        pass

    def hold(self, duration_s: float) -> None:
        time.sleep(duration_s)

    def stop(self) -> dict[str, Any]:
        return {}

    def summary(self, counts: dict[str, Any]) -> tuple[str, int]:
        """Notes for the table, and how many of the attack's requests or connections the
        daemon visibly refused or dropped."""
        return "", 0

    def failed(self, counts: dict[str, Any]) -> list[str]:
        """Safety facts this attack itself checks (hostile input accepted, ...): the failed
        ones, described."""
        return []


def _raise_open_files(wanted: int) -> int:
    """Raise this process's soft open-files limit towards `wanted` (the hard limit caps it)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if soft < target:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


def hold_connections(port: int, n: int, refused_marker: bytes, stop: Any, ready: Any,
                     out: Any) -> None:
    """Attacker: keep up to n connections to port open, sending nothing; a connection the
    server closes is reopened REOPEN_S later. Counts what came back: an answer containing
    `refused_marker` (the server's busy reply), another answer, a close without a word."""
    limit = _raise_open_files(n + 64)
    n = min(n, limit - 64)
    sel = selectors.DefaultSelector()
    counts = {"connections": n, "opened": 0, "connected": 0, "refused": 0, "answered": 0,
              "closed_unanswered": 0, "connect_failed": 0, "open_max": 0, "open_files": limit}
    reopen_at = [0.0] * n
    socks: dict[int, socket.socket] = {}
    state: dict[int, dict[str, Any]] = {}
    connected = 0

    def drop(slot: int, now: float) -> None:
        nonlocal connected
        s = socks.pop(slot)
        if state[slot]["connected"]:
            connected -= 1
        with contextlib.suppress(KeyError, ValueError):
            sel.unregister(s)
        s.close()
        reopen_at[slot] = now + REOPEN_S

    first = True
    while not stop.is_set():
        now = time.monotonic()
        for slot in range(n):
            if slot not in socks and now >= reopen_at[slot]:
                s = socket.socket()
                s.setblocking(False)
                s.connect_ex(("127.0.0.1", port))
                socks[slot] = s
                state[slot] = {"connected": False, "answer": b""}
                sel.register(s, selectors.EVENT_READ | selectors.EVENT_WRITE, slot)
                counts["opened"] += 1
        if first:
            ready.set()
            first = False
        for key, mask in sel.select(0.05):
            slot, s = key.data, key.fileobj
            st = state[slot]
            if not st["connected"]:
                if s.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR):
                    counts["connect_failed"] += 1
                    drop(slot, now)
                    continue
                st["connected"] = True
                connected += 1
                counts["connected"] += 1
                sel.modify(s, selectors.EVENT_READ, slot)
                if not mask & selectors.EVENT_READ:
                    continue
            try:
                data = s.recv(65536)
            except OSError:
                data = b""
            if data:
                st["answer"] += data[:4096]
                continue
            answer = st["answer"]
            if refused_marker in answer:
                counts["refused"] += 1
            elif answer:
                counts["answered"] += 1
            else:
                counts["closed_unanswered"] += 1
            drop(slot, now)
        counts["open_max"] = max(counts["open_max"], connected)
    counts["open_at_end"] = connected
    for s in socks.values():
        s.close()
    out.put(counts)


def newline_flood(target: tuple[str, Any], stop: Any, ready: Any, out: Any) -> None:
    """Attacker: send b"\\n" * 2^20 in a loop to a TCP port (("tcp", port)) or the Unix socket
    (("unix", path)), reconnecting whenever the daemon drops the connection."""
    kind, where = target
    counts = {"connects": 0, "mib_sent": 0, "dropped": 0, "connect_failed": 0, "stalled": 0}
    while not stop.is_set():
        s = socket.socket(socket.AF_UNIX if kind == "unix" else socket.AF_INET)
        s.settimeout(2.0)
        try:
            s.connect(str(where) if kind == "unix" else ("127.0.0.1", where))
        except OSError:
            counts["connect_failed"] += 1
            s.close()
            time.sleep(0.005)
            continue
        counts["connects"] += 1
        ready.set()
        try:
            while not stop.is_set():
                s.sendall(NEWLINES)
                counts["mib_sent"] += 1
        except TimeoutError:
            counts["stalled"] += 1  # the daemon stopped reading: not a drop
        except OSError:
            counts["dropped"] += 1
        finally:
            s.close()
    out.put(counts)


def nested_stop(levels: int, request_id: int) -> bytes:
    """A `stop` request whose params hold a list nested `levels` deep."""
    return (b'{"jsonrpc":"2.0","method":"stop","params":{"x":' + b"[" * levels + b"]" * levels
            + b'},"id":' + str(request_id).encode() + b"}\n")


def deep_json(path: str, stop: Any, ready: Any, out: Any) -> None:
    """Attacker: the DEEP_LEVELS requests in turn on the Unix socket, each reply read before the
    next pair; replies counted by error code."""
    lines = b"".join(nested_stop(levels, i) for i, levels in enumerate(DEEP_LEVELS, 1))
    counts: dict[str, Any] = {"sent": 0, "replies": 0, "parse_errors": 0, "other_errors": {},
                              "results": 0, "dropped": 0}
    while not stop.is_set():
        s = socket.socket(socket.AF_UNIX)
        s.settimeout(5.0)
        try:
            s.connect(path)
            ready.set()
            buf = b""
            while not stop.is_set():
                s.sendall(lines)
                counts["sent"] += len(DEEP_LEVELS)
                want = counts["replies"] + len(DEEP_LEVELS)
                while counts["replies"] < want:
                    chunk = s.recv(65536)
                    if not chunk:
                        raise ConnectionError("closed")
                    *done, buf = (buf + chunk).split(b"\n")
                    for line in done:
                        reply = json.loads(line)
                        counts["replies"] += 1
                        code = (reply.get("error") or {}).get("code")
                        if code is None:
                            counts["results"] += 1
                        elif code == -32700:
                            counts["parse_errors"] += 1
                        else:
                            counts["other_errors"][str(code)] = \
                                counts["other_errors"].get(str(code), 0) + 1
        except (OSError, ConnectionError, ValueError):
            counts["dropped"] += 1
            time.sleep(0.005)
        finally:
            s.close()
    out.put(counts)


def web_flood(port: int, token: str, stop: Any, ready: Any, out: Any) -> None:
    """Attacker: one token holder (the page's cookie) sending `{"id", "op": "stop"}` over the
    WebSocket as fast as aiohttp writes, reconnecting whenever the server closes it."""
    import asyncio  # this process's own loop, after the fork

    import aiohttp  # optional: the `web` extra

    counts: dict[str, Any] = {"sent": 0, "connects": 0, "connect_failed": 0, "replies_ok": 0,
                              "replies_error": {}, "refused": 0, "close_codes": {}}
    url = f"http://127.0.0.1:{port}"

    async def drain(ws: Any) -> None:
        async for msg in ws:
            if msg.type != aiohttp.WSMsgType.TEXT:
                continue
            data = json.loads(msg.data)
            if data.get("type") == "reply":
                if data.get("ok"):
                    counts["replies_ok"] += 1
                else:
                    name = str((data.get("error") or {}).get("name"))
                    counts["replies_error"][name] = counts["replies_error"].get(name, 0) + 1
            elif data.get("type") == "refused":
                counts["refused"] += int(data.get("count") or 1)

    async def main() -> None:
        jar = aiohttp.CookieJar(unsafe=True)  # the cookie of a numeric host
        async with aiohttp.ClientSession(cookie_jar=jar) as session:
            async with session.get(f"{url}/?token={token}", allow_redirects=False) as r:
                counts["login_status"] = r.status
            while not stop.is_set():
                try:
                    ws = await session.ws_connect(f"{url}/ws", max_msg_size=0)
                except (aiohttp.ClientError, OSError):
                    counts["connect_failed"] += 1
                    await asyncio.sleep(0.05)
                    continue
                counts["connects"] += 1
                ready.set()
                reader = asyncio.create_task(drain(ws))
                try:
                    while not stop.is_set() and not ws.closed:
                        counts["sent"] += 1
                        await ws.send_str(json.dumps({"id": counts["sent"], "op": "stop"}))
                        if counts["sent"] % 64 == 0:
                            await asyncio.sleep(0)  # the reader's turn
                except (aiohttp.ClientError, OSError, RuntimeError):
                    pass  # closed under us: reconnect
                await ws.close()
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(reader, 2.0)
                code = str(ws.close_code)
                counts["close_codes"][code] = counts["close_codes"].get(code, 0) + 1

    asyncio.run(main())
    out.put(counts)


class Peers(Attack):
    """Attackers as forked processes: each gets a stop event, a ready event and a queue for
    its counts."""

    def __init__(self, peers: dict[str, tuple[Callable[..., None], tuple[Any, ...]]]) -> None:
        self.peers = peers
        ctx = multiprocessing.get_context("fork")
        self._stop = ctx.Event()
        self._parts = {name: (ctx.Process(target=fn, args=(*args, self._stop, ready, q),
                                          daemon=True), ready, q)
                       for name, (fn, args) in peers.items()
                       for ready, q in [(ctx.Event(), ctx.Queue())]}

    def start(self) -> None:
        for proc, _, _ in self._parts.values():
            proc.start()
        end = time.monotonic() + ATTACKER_READY_S
        for name, (proc, ready, _) in self._parts.items():
            if not ready.wait(max(0.0, end - time.monotonic())):
                raise RuntimeError(f"attacker {name!r} not under way within "
                                   f"{ATTACKER_READY_S:g} s (exit code {proc.exitcode})")

    def stop(self) -> dict[str, Any]:
        self._stop.set()
        counts: dict[str, Any] = {}
        for name, (proc, _, q) in self._parts.items():
            try:
                counts[name] = q.get(timeout=15)
            except Exception:  # queue.Empty: it died; say so
                counts[name] = {"error": f"no counts (exit code {proc.exitcode})"}
            proc.join(5)
            if proc.is_alive():
                proc.kill()
                proc.join(5)
        return counts


class HeldConnections(Peers):
    """Many connections opened and held silent on one port, reopened when closed; a refusal
    reads `refusal` (the busy error's code, or the 503 status line)."""

    flood = True

    def __init__(self, port: int, count: int, refusal: bytes, refused_as: str) -> None:
        super().__init__({"held": (hold_connections, (port, count, refusal))})
        self.refused_as = refused_as

    def summary(self, counts: dict[str, Any]) -> tuple[str, int]:
        c = counts["held"]
        refused = c.get("refused", 0) + c.get("closed_unanswered", 0)
        return (f"{c.get('opened', 0)} connects: {c.get('refused', 0)} {self.refused_as}, "
                f"{c.get('closed_unanswered', 0)} closed unanswered, at most "
                f"{c.get('open_max', 0)} open at once", refused)


class NewlineFlood(Peers):
    flood = True

    def __init__(self, bench: HostileBench) -> None:
        super().__init__({"tcp": (newline_flood, (("tcp", bench.tcp_port),)),
                          "unix": (newline_flood, (("unix", str(bench.socket)),))})

    def summary(self, counts: dict[str, Any]) -> tuple[str, int]:
        parts, dropped = [], 0
        for name in ("tcp", "unix"):
            c = counts[name]
            dropped += c.get("dropped", 0) + c.get("stalled", 0)
            parts.append(f"{name}: {c.get('mib_sent', 0)} MiB sent, {c.get('dropped', 0)} "
                         f"drops, {c.get('stalled', 0)} stalls")
        return "; ".join(parts), dropped


class DeepJson(Peers):
    flood = True

    def __init__(self, bench: HostileBench) -> None:
        super().__init__({"unix": (deep_json, (str(bench.socket),))})

    def summary(self, counts: dict[str, Any]) -> tuple[str, int]:
        c = counts["unix"]
        others = sum(c.get("other_errors", {}).values())
        return (f"{c.get('sent', 0)} requests, {c.get('parse_errors', 0)} parse errors, "
                f"{c.get('results', 0)} results, {others} other errors, "
                f"{c.get('dropped', 0)} drops", c.get("parse_errors", 0) + c.get("dropped", 0))

    def failed(self, counts: dict[str, Any]) -> list[str]:
        c = counts["unix"]
        # Both depths are past the daemon's limit (32): any result means one was run.
        return [f"{c['results']} deep requests were run, not refused"] \
            if c.get("results") else []


class WebFlood(Peers):
    flood = True

    def __init__(self, bench: HostileBench) -> None:
        super().__init__({"web": (web_flood, (bench.web_port, bench.web_token))})

    def summary(self, counts: dict[str, Any]) -> tuple[str, int]:
        c = counts["web"]
        errors = c.get("replies_error", {})
        closes = c.get("close_codes", {})
        sent, done = c.get("sent", 0), c.get("replies_ok", 0)
        # A message over the socket's rate is dropped unanswered (a `refused` notice at most
        # once a second, often not before the socket is closed for flooding): what got no
        # reply was refused.
        unanswered = max(0, sent - done - sum(errors.values()))
        refused = unanswered + sum(errors.values()) + closes.get("1008", 0)
        shown = ", ".join(f"{n} {k}" for k, n in sorted(errors.items())) or "none"
        return (f"{sent} messages on {c.get('connects', 0)} sockets: {done} done, errors: "
                f"{shown}, {unanswered} unanswered ({c.get('refused', 0)} in refused notices); "
                f"{closes.get('1008', 0)} sockets closed for flooding (1008)", refused)


# -- hostile files ------------------------------------------------------------------------------


@dataclass
class HostileFile:
    """A file that must be refused, and words its refusal must contain (its cause)."""

    name: str  # relative to the folder it was built in
    what: str
    cause: tuple[str, ...]  # any of these in the job's error
    path: Path = field(default=Path())


def gzip_of(head: bytes, zeros: int) -> bytes:
    """A gzip stream of `head` then `zeros` zero bytes, compressed piece by piece (never holding
    the inflated data: tests/scene/test_hostile_files.py builds its bombs with it too)."""
    co = zlib.compressobj(9, zlib.DEFLATED, 16 + zlib.MAX_WBITS)
    out = [co.compress(head)]
    piece = bytes(1 << 20)
    for _ in range(zeros >> 20):
        out.append(co.compress(piece))
    out.append(co.compress(bytes(zeros & ((1 << 20) - 1))))
    return b"".join(out) + co.flush()


def zstd_zeros(n: int) -> bytes:
    """One zstd frame of n zero bytes whose header states its size (as the reference packer's
    frames do), compressed piece by piece."""
    buf = io.BytesIO()
    with zstandard.ZstdCompressor().stream_writer(buf, size=n, closefd=False) as w:
        for _ in range(n >> 20):
            w.write(bytes(1 << 20))
        w.write(bytes(n & ((1 << 20) - 1)))
    return buf.getvalue()


def splat_gltf(count: int = 1) -> tuple[dict[str, Any], bytes]:
    """A glTF KHR_gaussian_splatting document of `count` Gaussians (SH degree 0) and its
    buffer: the harmless base the hostile glTF files change one thing of."""
    columns = {"POSITION": ("VEC3", 3), "KHR_gaussian_splatting:ROTATION": ("VEC4", 4),
               "KHR_gaussian_splatting:SCALE": ("VEC3", 3),
               "KHR_gaussian_splatting:OPACITY": ("SCALAR", 1),
               "KHR_gaussian_splatting:SH_DEGREE_0_COEF_0": ("VEC3", 3)}
    blob, views, accessors = b"", [], []
    for name, (kind, width) in columns.items():
        values = [0.0, 0.0, 0.0, 1.0] if name.endswith("ROTATION") else [0.5] * width
        data = struct.pack(f"<{width}f", *values) * count
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        accessors.append({"bufferView": len(views) - 1, "componentType": 5126,
                          "count": count, "type": kind})
        blob += data
    doc = {"asset": {"version": "2.0"}, "extensionsUsed": ["KHR_gaussian_splatting"],
           "buffers": [{"byteLength": len(blob)}], "bufferViews": views,
           "accessors": accessors,
           "meshes": [{"primitives": [{
               "attributes": {name: i for i, name in enumerate(columns)}, "mode": 0,
               "extensions": {"KHR_gaussian_splatting": {"kernel": "ellipse"}}}]}],
           "nodes": [{"mesh": 0}]}
    return doc, blob


def glb(doc: dict[str, Any], blob: bytes) -> bytes:
    """A binary glTF: header, JSON chunk, BIN chunk, each padded to 4 bytes."""
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    blob += bytes(-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<II", len(js), 0x4E4F534A)
            + js + struct.pack("<II", len(blob), 0x004E4942) + blob)


INRIA_PROPERTIES = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0",
                    "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


def build_hostile_scenes(folder: Path, bomb_bytes: int) -> list[HostileFile]:
    """The issue's hostile scene files, small on disk, in `folder` (created)."""
    folder.mkdir(parents=True, exist_ok=True)
    files = []

    def add(name: str, data: bytes | str, what: str, *cause: str) -> None:
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data.encode() if isinstance(data, str) else data)
        files.append(HostileFile(name, what, cause, path))

    # .spz v3 declaring one Gaussian (45 bytes of SH degree 1, all zero), then bomb_bytes more.
    head = struct.pack("<4sIIBBBB", b"NGSP", 3, 1, 1, 12, 0, 0)
    add("bomb.spz", gzip_of(head + bytes(45), bomb_bytes),
        f".spz gzip bomb (inflates to {bomb_bytes >> 20} MiB)", "inflates to more than")
    # .spz v4 (zstd) declaring 2^28 points: each stream a 1 MiB frame, the table the sizes 2^28
    # points need.
    sizes = [9 * HUGE, HUGE, 3 * HUGE, 3 * HUGE, 4 * HUGE]
    frame = zstd_zeros(1 << 20)
    spz4 = struct.pack("<4sIIBBBBI12x", b"NGSP", 4, HUGE, 0, 12, 0, len(sizes), 32)
    spz4 += b"".join(struct.pack("<QQ", len(frame), u) for u in sizes) + frame * len(sizes)
    add("zstd-2e28.spz", spz4, "zstd .spz declaring 2^28 points", f"declares {HUGE:,} Gaussians")
    # .sog zip bomb: meta.json for one Gaussian, its first image bomb_bytes of zeros.
    meta = {"version": 2, "count": 1,
            "means": {"mins": [0, 0, 0], "maxs": [1, 1, 1],
                      "files": ["means_l.webp", "means_u.webp"]},
            "scales": {"codebook": [0.0] * 256, "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"codebook": [0.0] * 256, "files": ["sh0.webp"]}}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("meta.json", json.dumps(meta))
        with z.open("means_l.webp", "w", force_zip64=True) as member:
            for _ in range(bomb_bytes >> 20):
                member.write(bytes(1 << 20))
    add("bomb.sog", buf.getvalue(), f".sog zip bomb (a {bomb_bytes >> 20} MiB member)",
        f"means_l.webp declares {bomb_bytes:,} bytes")
    # .glb whose every view has byteStride 0 and every accessor count 2^28.
    doc, blob = splat_gltf()
    for view in doc["bufferViews"]:
        view["byteStride"] = 0
    for acc in doc["accessors"]:
        acc["count"] = HUGE
    add("stride0.glb", glb(doc, blob), ".glb, byteStride 0, count 2^28",
        f"declares {HUGE:,} Gaussians", "byteStride is 0")
    # .gltf whose buffer is ../outside.bin (a real buffer, one folder up), and one whose
    # buffer is /dev/zero.
    doc, blob = splat_gltf()
    (folder / "outside.bin").write_bytes(blob)
    doc["buffers"][0]["uri"] = "../outside.bin"
    add("in/escape.gltf", json.dumps(doc), ".gltf buffer ../outside.bin",
        "'../outside.bin' resolves to", "outside the scene's folder")
    doc["buffers"][0]["uri"] = "/dev/zero"
    add("zero.gltf", json.dumps(doc), ".gltf buffer /dev/zero", "'/dev/zero' resolves to")
    # ASCII .ply declaring 4e9 vertices, one row written.
    props = "".join(f"property float {p}\n" for p in INRIA_PROPERTIES)
    add("4e9.ply", (f"ply\nformat ascii 1.0\nelement vertex 4000000000\n{props}end_header\n"
                    + " ".join(["0"] * len(INRIA_PROPERTIES)) + "\n"),
        "ASCII .ply declaring 4e9 vertices", "declares 4,000,000,000 Gaussians")
    return files


def hostile_model(src: Path, dst: Path, key: str, value: Any) -> Path:
    """`src` saved as `dst` with its nhfd metadata's `key` set to `value` (NaN written as
    Python's json writes it: the file says NaN)."""
    model = onnx.load(str(src))
    for prop in model.metadata_props:
        if prop.key == METADATA_KEY:
            meta = json.loads(prop.value)
            meta[key] = value
            prop.value = json.dumps(meta)
            break
    else:
        raise ValueError(f"{src}: no {METADATA_KEY!r} metadata to change")
    onnx.save(model, str(dst))
    return dst


def pose_envelope(model: Path) -> dict[str, Any]:
    for prop in onnx.load(str(model), load_external_data=False).metadata_props:
        if prop.key == METADATA_KEY:
            return json.loads(prop.value).get("pose_envelope") or {}
    return {}


class Loads(Attack):
    """Loads of hostile files, repeated until the window has passed (at least once each);
    every one must fail with its cause in the job's error."""

    method = ""

    def __init__(self, bench: HostileBench, files: list[HostileFile]) -> None:
        self.bench, self.files = bench, files
        self.results: dict[str, dict[str, Any]] = {
            f.name: {"what": f.what, "loads": 0, "refused": 0, "cause_named": 0,
                     "error": None, "accepted": [], "seconds": []} for f in files}

    def hold(self, duration_s: float) -> None:
        end = time.monotonic() + duration_s
        with self.bench.client(timeout_s=30) as c:
            while True:
                for f in self.files:
                    self._load(c, f)
                if time.monotonic() >= end:
                    return

    def _load(self, c: Client, f: HostileFile) -> None:
        r = self.results[f.name]
        t0 = time.monotonic()
        job = c.wait_job(int(c.call(self.method, path=str(f.path))["job"]),
                         timeout_s=LOAD_WAIT_S, poll_s=0.05)
        r["seconds"].append(round(time.monotonic() - t0, 3))
        r["loads"] += 1
        if job["state"] == "failed":
            r["refused"] += 1
            # The temporary root means nothing to a reader of the table.
            error = str(job["error"]).replace(f"{self.bench.root}/", "")
            r["error"] = r["error"] or error
            r["cause_named"] += any(word in error for word in f.cause)
        else:
            r["accepted"].append(f"{job['state']}: {job['error'] or job['result']}"[:300])

    def stop(self) -> dict[str, Any]:
        for r in self.results.values():
            secs = r.pop("seconds")
            r["median_s"] = round(statistics.median(secs), 3) if secs else None
        return {"files": self.results}

    def summary(self, counts: dict[str, Any]) -> tuple[str, int]:
        files = counts["files"]
        refused = sum(r["refused"] for r in files.values())
        loads = sum(r["loads"] for r in files.values())
        named = sum(r["cause_named"] for r in files.values())
        return (f"{refused} of {loads} loads refused ({len(files)} files), {named} naming "
                "the cause", refused)

    def failed(self, counts: dict[str, Any]) -> list[str]:
        out = []
        for name, r in counts["files"].items():
            if r["refused"] < r["loads"]:
                out.append(f"{name} accepted: {r['accepted'][:1]}")
            elif r["cause_named"] < r["loads"]:
                out.append(f"{name} refused without naming its cause: {r['error']}")
        return out


class HostileScenes(Loads):
    method = "load_scene"

    def __init__(self, bench: HostileBench, bomb_bytes: int) -> None:
        super().__init__(bench, build_hostile_scenes(bench.scenes, bomb_bytes))


class HostileModels(Loads):
    method = "load_model"

    def __init__(self, bench: HostileBench) -> None:
        assert bench.model is not None
        shipped = bench.model
        files = []
        for key, value, name in (("amplitude_scale", math.nan, "nan-amplitude-scale.onnx"),
                                 ("input_multiple", 0, "input-multiple-0.onnx")):
            path = hostile_model(shipped, bench.models / name, key, value)
            files.append(HostileFile(name, f"{key} = {value}", (f"metadata {key}",), path))
        super().__init__(bench, files)
        self.envelope = pose_envelope(shipped)

    def stop(self) -> dict[str, Any]:
        counts = super().stop()
        counts["still_serving"] = self._still_serving()
        return counts

    def _still_serving(self) -> dict[str, Any]:
        """The shipped model is the one loaded, and a new view is rendered with it."""
        az = self.envelope.get("azimuth_deg") or [-20.0, 20.0]
        el = self.envelope.get("elevation_deg") or [0.0, 20.0]
        dist = self.envelope.get("distance") or [2.0, 2.0]
        with self.bench.client(timeout_s=30) as c:
            before = c.status()["frames"]
            c.call("set_view", orbit={"azimuth_deg": sum(az) / 2 + (az[1] - az[0]) / 4,
                                      "elevation_deg": sum(el) / 2, "radius": sum(dist) / 2})
            end = time.monotonic() + 60
            frames = before
            while time.monotonic() < end:
                frames = c.status()["frames"]
                if frames["frames_shown"] > before["frames_shown"]:
                    break
                time.sleep(0.05)
        return {"model": frames["model"], "is_shipped": frames["model"] == str(self.bench.model),
                "frames_shown_before": before["frames_shown"],
                "frames_shown_after": frames["frames_shown"],
                "new_frame": frames["frames_shown"] > before["frames_shown"]}

    def summary(self, counts: dict[str, Any]) -> tuple[str, int]:
        notes, refused = super().summary(counts)
        s = counts["still_serving"]
        return (notes + ("; the shipped model still serves (a new frame)" if s["is_shipped"]
                         and s["new_frame"] else "; the shipped model NOT serving"), refused)

    def failed(self, counts: dict[str, Any]) -> list[str]:
        out = super().failed(counts)
        s = counts["still_serving"]
        if not (s["is_shipped"] and s["new_frame"]):
            out.append(f"after the refusals the model is {s['model']} and new frame: "
                       f"{s['new_frame']}")
        return out


# -- scenarios ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Scenario:
    key: str  # the --scenarios name
    title: str  # the table's
    make: Callable[[HostileBench, argparse.Namespace], Attack]
    tcp: bool = False
    web: bool = False
    frames: bool = False


SCENARIOS: tuple[Scenario, ...] = (
    Scenario("idle", "idle", lambda b, a: Attack()),
    Scenario("tcp-lockout", "tcp lock-out (100 silent TCP connections)",
             lambda b, a: HeldConnections(b.tcp_port, TCP_CONNECTIONS, b"1001", "busy replies"),
             tcp=True),
    Scenario("newline-flood", "newline flood (TCP unauthenticated + Unix)",
             lambda b, a: NewlineFlood(b), tcp=True),
    Scenario("deep-json", "deep JSON (30,000 and 600 levels)", lambda b, a: DeepJson(b)),
    Scenario("web-connections", "web connections (1,100 idle)",
             lambda b, a: HeldConnections(b.web_port, WEB_CONNECTIONS, b" 503 ", "got 503"),
             web=True),
    Scenario("web-flood", "web message flood (one token holder)",
             lambda b, a: WebFlood(b), web=True),
    Scenario("hostile-scenes", "hostile scenes",
             lambda b, a: HostileScenes(b, a.bomb_mib << 20)),
    Scenario("hostile-models", "hostile models", lambda b, a: HostileModels(b), frames=True),
)
BY_KEY = {s.key: s for s in SCENARIOS}


def guardian_counters(status: dict[str, Any]) -> tuple[int, float]:
    g = status["laser"]["guardian"]
    return int(g.get("late_heartbeats") or 0), float(g.get("max_heartbeat_gap_ms") or 0.0)


def safety_failures(row: dict[str, Any], attack_failed: list[str]) -> list[str]:
    """The safety facts a row fails (these set the exit code): the daemon died, the light went
    off during the attack, `laser off` failed, or the attack's own check (hostile input
    accepted)."""
    out = []
    if not row["daemon_alive"]:
        out.append("the daemon died")
    if not row["lit_until_laser_off"] or row["starvation_disarms"]:
        out.append(f"the light went off during the attack ({row['guardian_disarms']} guardian "
                   f"disarms: {', '.join(row['disarm_reasons']) or 'none audited'})")
    off = row["laser_off"]
    if not off["ok"]:
        out.append(f"laser off failed: exit code {off['rc']}, dark after "
                   f"{off['ms_to_dark']} ms: {off['stderr'][-120:]}")
    return out + attack_failed


def goals(row: dict[str, Any], flood: bool) -> list[str]:
    """The goals a row misses, described ([]: all met). Status p99 over the goal is waived
    under a flood the daemon visibly refused (its refusals counted in the row)."""
    missed = []
    if not row["daemon_alive"]:
        missed.append("crashed")
    if row["starvation_disarms"] or not row["lit_until_laser_off"]:
        missed.append("disarmed during the attack")
    growth = row["rss_mb"]["peak"] - row["rss_mb"]["start"]
    if growth > GOAL_RSS_GROWTH_MB:
        missed.append(f"RSS +{growth:.0f} MB")
    off = row["laser_off"]
    if not off["ok"] or off["ms_to_dark"] is None or off["ms_to_dark"] > GOAL_DARK_MS:
        missed.append(f"laser off dark after {off['ms_to_dark']} ms")
    if row["status_failures"]:
        missed.append(f"{row['status_failures']} status calls failed")
    p99 = row["status"]["p99_ms"]
    if p99 is not None and p99 >= GOAL_STATUS_P99_MS and not (flood and row["refused"]):
        missed.append(f"status p99 {p99:.0f} ms")
    return missed


def run_scenario(sc: Scenario, args: argparse.Namespace) -> dict[str, Any]:
    """One scenario on a fresh daemon: its row of the table."""
    if sc.web and importlib.util.find_spec("aiohttp") is None:
        return {"scenario": sc.title, "key": sc.key,
                "skipped": "aiohttp is not installed (the web view needs the `web` extra: "
                           "pip install 'nhfd[web]')"}
    model = Path(args.model).resolve() if sc.frames else None
    scene = Path(args.scene).resolve() if sc.frames else None
    bench = HostileBench(model=model, scene=scene, tcp=sc.tcp, web=sc.web)
    attack: Attack | None = None
    under_way = False
    monitor: Monitor | None = None
    try:
        bench.wait_ready(frames=sc.frames, timeout_s=300.0 if sc.frames else 120.0)
        for port in (bench.tcp_port, bench.web_port):
            if port is not None:
                bench.wait_listening(port)
        attack = sc.make(bench, args)
        # Armed for the whole scenario with a margin: an expiry mid-attack is not the attack's.
        bench.light_for(min(900.0, 3 * args.duration_s + 120.0))
        with bench.client() as c:
            late0, gap0 = guardian_counters(c.status())
        rss0 = rss_mb(bench.proc.pid) or 0.0
        audit0, log0 = bench.audit_bytes(), bench.log_lines()
        under_way = True
        attack.start()
        monitor = Monitor(bench)
        monitor.start()
        t_start = time.time()
        attack.hold(args.duration_s)
        lit = bench.lit()
        t_off = time.time()
        monitor.stop_timing()
        off = laser_off(bench, args.timeout_s)  # the attackers still at it
        monitor.stop()
        under_way = False
        counts = attack.stop()
        alive = bench.proc.poll() is None
        late1, gap1 = late0, gap0
        if alive:
            with contextlib.suppress(Exception), bench.client() as c:
                late1, gap1 = guardian_counters(c.status())
        # The guardian's own disarms within the window (laser off's is the daemon's, after it).
        disarms = [str(r["what"]).split(": ", 1)[-1] for r in bench.audit_records()
                   if str(r.get("what", "")).startswith("laser disarmed by the guardian")
                   and t_start <= float(r.get("unix_s") or 0.0) <= t_off]
        notes, refused = attack.summary(counts)
        row: dict[str, Any] = {
            "scenario": sc.title, "key": sc.key, "duration_s": args.duration_s,
            "status": latency_summary(monitor.latencies_ms),
            "status_failures": len(monitor.failures),
            "status_failure_samples": monitor.failures[:3],
            "guardian_disarms": len(disarms), "disarm_reasons": disarms,
            "starvation_disarms": sum("heartbeat" in r for r in disarms),
            "late_heartbeats": late1 - late0, "max_heartbeat_gap_ms": gap1,
            "max_heartbeat_gap_ms_before": gap0, "lit_until_laser_off": lit,
            "rss_mb": {"start": round(rss0, 1), "peak": round(monitor.rss_peak_mb, 1),
                       "end": round(rss_mb(bench.proc.pid) or 0.0, 1) if alive else None},
            "daemon_alive": alive, "laser_off": off,
            "audit_bytes_added": bench.audit_bytes() - audit0,
            "log_lines_added": bench.log_lines() - log0,
            "attack": counts, "refused": refused, "notes": notes,
        }
        row["failed"] = safety_failures(row, attack.failed(counts))
        row["goals_missed"] = goals(row, attack.flood)
        if not alive:
            row["log_tail"] = bench.log_tail(1500)
        return row
    finally:
        if monitor is not None:
            monitor.stop()
        if attack is not None and under_way:
            with contextlib.suppress(Exception):
                attack.stop()
        bench.close()


# -- output -------------------------------------------------------------------------------------


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| scenario | status median / p99 ms | disarms | RSS start / peak MB "
             "| laser off ok, ms to dark | notes | goals |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "skipped" in r or "error" in r:
            why = f"skipped: {r['skipped']}" if "skipped" in r else f"ERROR: {r['error']}"
            lines.append(f"| {r['scenario']} | {why.replace('|', '/')} | | | | | |")
            continue
        st = r["status"]
        status = f"{_ms(st['median_ms'])} / {_ms(st['p99_ms'])}"
        if r["status_failures"]:
            status += f" ({r['status_failures']} failed)"
        disarms = str(r["guardian_disarms"])
        if r["disarm_reasons"]:
            disarms += f" ({'; '.join(r['disarm_reasons'])})"
        disarms += (f"; {r['late_heartbeats']} late beats, max gap "
                    f"{r['max_heartbeat_gap_ms']:.0f} ms")
        off = r["laser_off"]
        laser = (f"yes, {off['ms_to_dark']:.0f} ({off['switched_off_by']})" if off["ok"]
                 else f"NO (exit {off['rc']}, dark after {_ms(off['ms_to_dark'])} ms)")
        if not off["lit_before"]:
            laser += ", already dark"
        notes = (f"{r['notes']}; audit +{r['audit_bytes_added'] / 1024:.0f} KiB, log "
                 f"+{r['log_lines_added']} lines").lstrip("; ")
        if r["failed"]:
            notes += "; FAILED: " + "; ".join(r["failed"])
        missed = r["goals_missed"]
        goal = "missed: " + ", ".join(missed) if missed else "met"
        if not missed and st["p99_ms"] is not None and st["p99_ms"] >= GOAL_STATUS_P99_MS:
            goal = f"met (p99 over {GOAL_STATUS_P99_MS:.0f} ms under a refused flood)"
        rss = r["rss_mb"]
        lines.append(f"| {r['scenario']} | {status} | {disarms} | {rss['start']:.0f} / "
                     f"{rss['peak']:.0f} | {laser} | {notes} | {goal} |")
    return "\n".join(lines)


def per_file(rows: list[dict[str, Any]]) -> str:
    """The hostile files' own table: refused, the job's error, the load's time."""
    out = []
    for r in rows:
        files = (r.get("attack") or {}).get("files")
        if not files:
            continue
        out += [f"\n{r['scenario']}:\n", "| file | refused | median s | the job's error |",
                "|---|---|---|---|"]
        for name, f in files.items():
            refused = f"{f['refused']} of {f['loads']}"
            error = (f["error"] or "").replace("|", "\\|")
            out.append(f"| {name} ({f['what']}) | {refused} | {f['median_s']} | {error} |")
    return "\n".join(out)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("hostile", help="attacks on a lit daemon: status, disarms, memory, "
                       "laser off", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenarios", default=",".join(s.key for s in SCENARIOS),
                   help=f"comma-separated scenarios (default all): "
                        f"{', '.join(s.key for s in SCENARIOS)}")
    p.add_argument("--duration-s", type=float, default=8.0,
                   help="attack window per scenario (s); the hostile loads repeat for it, at "
                        "least once each (default 8)")
    p.add_argument("--timeout-s", type=float, default=5.0,
                   help="how long after `laser off` starts a channel may stay lit before the "
                        "row fails (default 5)")
    p.add_argument("--bomb-mib", type=int, default=256,
                   help="what the .spz and .sog bombs inflate to (MiB; built at run time, about "
                        "1 KiB on disk per MiB; default 256)")
    p.add_argument("--model", default="models/nhf-donut-512.onnx",
                   help="the model the hostile-models scenario serves (copied)")
    p.add_argument("--scene", default="models/scenes/donut.ply",
                   help="the scene it renders (copied)")
    p.add_argument("--json", default="out/bench/hostile.json",
                   help="JSON results file; the markdown table is written beside it as .md")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    keys = [k.strip().replace(" ", "-") for k in args.scenarios.split(",") if k.strip()]
    unknown = [k for k in keys if k not in BY_KEY]
    if unknown or not keys:
        raise SystemExit(f"--scenarios: no scenario {unknown[0] if unknown else '(none)'!r}; "
                         f"one of: {', '.join(BY_KEY)}")
    if args.duration_s <= 0:
        raise SystemExit(f"--duration-s = {args.duration_s:g}: more than 0")
    if args.bomb_mib < 1:
        raise SystemExit(f"--bomb-mib = {args.bomb_mib}: at least 1")
    if "hostile-models" in keys:
        for f in (Path(args.model), Path(args.scene)):
            if not f.is_file():
                raise SystemExit(f"{f}: not found (the hostile-models scenario serves it)")
    command = (f"nhfd bench hostile --scenarios {','.join(keys)} --duration-s "
               f"{args.duration_s:g} --bomb-mib {args.bomb_mib}")
    machine = describe()
    load_start = [round(x, 2) for x in os.getloadavg()]
    rows = []
    for i, key in enumerate(keys, 1):
        print(f"[{i}/{len(keys)}] {key}: {args.duration_s:g} s ...", flush=True)
        t0 = time.monotonic()
        try:
            row = run_scenario(BY_KEY[key], args)
        except Exception as exc:  # the bench itself failed (a daemon that never started...)
            row = {"scenario": BY_KEY[key].title, "key": key,
                   "error": f"{type(exc).__name__}: {exc}"[:600]}
            row["failed"] = [f"the scenario did not run: {row['error']}"]
        rows.append(row)
        if "skipped" in row or "error" in row:
            why = row.get("skipped") or row["error"]
            print(f"[{i}/{len(keys)}] {key}: {'skipped' if 'skipped' in row else 'ERROR'}: "
                  f"{why}", flush=True)
            continue
        st = row["status"]
        print(f"[{i}/{len(keys)}] {key}: status {_ms(st['median_ms'])} / {_ms(st['p99_ms'])} "
              f"ms, {row['guardian_disarms']} disarms, RSS peak {row['rss_mb']['peak']:.0f} MB, "
              f"laser off {'ok' if row['laser_off']['ok'] else 'FAILED'} "
              f"({_ms(row['laser_off']['ms_to_dark'])} ms to dark); "
              f"{time.monotonic() - t0:.0f} s", flush=True)
    load_end = [round(x, 2) for x in os.getloadavg()]
    head = (f"`{command}` on {machine['cpu']}, {machine['cores']} cores, Python "
            f"{machine['python']} (load average {load_start[0]:g} at the start, "
            f"{load_end[0]:g} at the end)\n\n"
            f"Goals: no disarm by starvation, no crash, RSS at most {GOAL_RSS_GROWTH_MB:.0f} MB "
            f"above the start; `nhfctl laser off` ok and dark within {GOAL_DARK_MS:.0f} ms "
            f"(from the command's start); status p99 under {GOAL_STATUS_P99_MS:.0f} ms except "
            "under floods the bounds visibly refuse.\n\n")
    text = head + table(rows) + "\n" + per_file(rows) + "\n"
    print(text)
    failed = [f"{r['key']}: {f}" for r in rows for f in r.get("failed", [])]
    out = {"nhfd_version": __version__, "machine": machine, "command": command,
           "load_average_start": load_start, "load_average_end": load_end,
           "duration_s": args.duration_s, "goals": GOALS, "rows": rows, "failed": failed}
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    path.with_suffix(".md").write_text(text)
    print(f"wrote {path} and {path.with_suffix('.md')}")
    for f in failed:
        print(f"FAILED: {f}", file=sys.stderr)
    return 1 if failed else 0
