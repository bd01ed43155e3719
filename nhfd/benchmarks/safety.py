"""`nhfd bench safety`: time from each fault to every laser channel dark, on the twin's record.

Each trial starts `nhfd serve` as its own process on the simulated bench with the READYBeam twin
hosted by this process (`devices.laser = "readybeam"` on the twin's pty; the daemon spawns its
guardian on a socket in a temporary directory), arms, sets red to 5 % and enables it, then
injects one fault and waits (at most `--timeout-s`) for the twin's emission record to show every
channel dark. The time is the twin's `dark_since()` minus the moment the fault was sent, both on
this process's monotonic clock: the proof is the device's record, never the daemon's word.

Faults: SIGTERM, SIGINT and SIGKILL of the daemon; SIGKILL of the frame worker (the daemon loads
the shipped model and scene so the worker exists); SIGSTOP of the daemon (SIGCONT afterwards);
SIGKILL and SIGSTOP of the guardian; `shutdown` over the socket. A channel still lit after the
timeout is a failure row ("not off within N s"), never left out.

`--fuzz N` adds the malformed-request figure: N generated bad requests on one connection (the
generator of tests/daemon/test_daemon.py), each answered with a JSON-RPC error (notifications
excepted), the daemon's state and the lasers unchanged.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from nhfd import __version__
from nhfd.benchmarks.machine import describe
from nhfd.daemon.client import Client, DaemonUnavailable
from nhfd.drivers.guardian import wait_gone
from nhfd.drivers.twins.mecom_twin import MecomTwin

from .load import config_text

FAULTS: tuple[str, ...] = (
    "SIGTERM daemon", "SIGINT daemon", "SIGKILL daemon", "SIGKILL frame worker",
    "SIGSTOP daemon", "SIGKILL guardian", "SIGSTOP guardian", "shutdown (RPC)",
)
LIT_PCT = 5.0  # red's power while a fault is injected: under the default 10 % cap


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("safety", help="time from each fault to every laser off",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--faults", default=",".join(FAULTS),
                   help=f"comma-separated faults (default all): {', '.join(FAULTS)}")
    p.add_argument("--repeats", type=int, default=3, help="trials per fault")
    p.add_argument("--timeout-s", type=float, default=5.0,
                   help="how long a channel may stay lit before the trial counts as a failure")
    p.add_argument("--fuzz", type=int, default=0, help="malformed requests to send (0 = none)")
    p.add_argument("--model", default="models/nhf-donut-512.onnx",
                   help="model for the frame-worker fault")
    p.add_argument("--scene", default="models/scenes/donut.ply")
    p.add_argument("--json", default="out/bench/safety.json", help="JSON results file")
    p.set_defaults(handler=run)


# -- one daemon on the bench --------------------------------------------------------------------


# The daemon of every trial: the real readybeam driver on the twin's pty, no other device to
# wait for.
DEVICES = ['laser = "readybeam"', 'slm = "simulated"', 'stage = "none"', 'camera = "none"',
           'navigator = "none"']


class Bench:
    """`nhfd serve` on a temporary runtime directory, its laser the twin in this process."""

    def __init__(self, model: Path | None = None, scene: Path | None = None) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="nhfd-safety-", dir="/tmp"))
        self.twin = MecomTwin()
        self.twin.start()
        cfg = self.root / "nhfd.toml"
        cfg.write_text(config_text(self.root, model, scene, DEVICES, self.twin.port_path))
        self.log = (self.root / "serve.log").open("w")
        self.proc = subprocess.Popen([sys.executable, "-m", "nhfd.cli.main", "serve",
                                      "--config", str(cfg)],
                                     stdout=subprocess.DEVNULL, stderr=self.log)
        self.socket = self.root / "run" / "control.sock"
        self.pids: set[int] = set()  # guardians it spawned, for the clean-up

    def client(self, timeout_s: float = 10.0) -> Any:
        return Client(self.socket, timeout_s=timeout_s)

    def wait_ready(self, frames: bool, timeout_s: float = 120.0) -> dict[str, Any]:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"nhfd serve exited with {self.proc.returncode}: "
                                   f"{self.log_tail()}")
            try:
                with self.client() as c:
                    st = c.status()
                if not frames or (st["frames"]["state"] == "running" and st["scene"] \
                        and st["model"] != "none loaded"):
                    self.note_guardian(st)
                    return st
            except DaemonUnavailable:
                pass
            time.sleep(0.1)
        raise TimeoutError(f"nhfd serve not ready within {timeout_s:g} s: {self.log_tail()}")

    def note_guardian(self, status: dict[str, Any]) -> None:
        pid = status["laser"]["guardian"]["spawned_pid"]
        if pid:
            self.pids.add(int(pid))

    def light(self) -> None:
        with self.client() as c:
            c.call("laser", action="arm", duration_s=60.0)
            c.call("laser", action="power", channel="red", power_pct=LIT_PCT)
            c.call("laser", action="enable", channel="red")
        if not any(p > 0 for p in self.twin.emitting().values()):
            raise RuntimeError("the twin does not emit after arm, power and enable")

    def dark_after(self, t0: float, timeout_s: float) -> float | None:
        """Seconds from t0 until every channel was dark on the twin's record; None if a channel
        is still lit after timeout_s."""
        end = t0 + timeout_s
        while True:
            since = self.twin.dark_since()
            if since is not None and not any(p > 0 for p in self.twin.emitting().values()):
                return max(0.0, since - t0)
            if time.monotonic() > end:
                return None
            time.sleep(0.002)

    def log_tail(self, n: int = 600) -> str:
        self.log.flush()
        return (self.root / "serve.log").read_text()[-n:].replace("\n", " | ")

    def close(self) -> None:
        """Everything this trial started ends: stopped processes continued, the daemon shut
        down (it stops its guardian), guardians left behind terminated by pid."""
        for pid in [self.proc.pid, *self.pids]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        if self.proc.poll() is None:
            with contextlib.suppress(Exception), self.client(timeout_s=5) as c:
                self.note_guardian(c.status())
                c.call("shutdown")
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(15)
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait(10)
        for pid in self.pids:  # a guardian that outlived its daemon (SIGKILL) holds the port
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGTERM)
        for pid in self.pids:
            if not wait_gone(pid, 5.0):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
        self.twin.close()
        self.log.close()
        shutil.rmtree(self.root, ignore_errors=True)



# -- faults -------------------------------------------------------------------------------------


def _signal(pid: int, sig: signal.Signals) -> None:
    os.kill(pid, sig)


def _resume(pid: int) -> None:
    """SIGCONT a stopped process, if it is still there: the daemon kills and replaces a hung
    guardian, so by the time the trial ends the stopped one is usually gone."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGCONT)


def inject(bench: Bench, fault: str, status: dict[str, Any]) -> Callable[[], None]:
    """Send the fault now; returns what undoes it afterwards (a SIGCONT) or a no-op."""
    daemon = bench.proc.pid
    guardian = status["laser"]["guardian"]["spawned_pid"]
    if fault in ("SIGTERM daemon", "SIGINT daemon", "SIGKILL daemon", "SIGSTOP daemon"):
        _signal(daemon, getattr(signal, fault.split()[0]))
    elif fault == "SIGKILL frame worker":
        _signal(int(status["frames"]["pid"]), signal.SIGKILL)
    elif fault in ("SIGKILL guardian", "SIGSTOP guardian"):
        _signal(int(guardian), getattr(signal, fault.split()[0]))
    elif fault == "shutdown (RPC)":
        with bench.client() as c:
            c.call("shutdown")
    else:
        raise ValueError(f"fault {fault!r}: one of {', '.join(FAULTS)}")
    if fault == "SIGSTOP daemon":
        return lambda: _resume(daemon)
    if fault == "SIGSTOP guardian":
        return lambda: _resume(int(guardian))
    return lambda: None


def trial(fault: str, timeout_s: float, model: Path | None, scene: Path | None) -> float | None:
    """One fault on a fresh daemon: seconds to every channel dark (None: not within
    timeout_s)."""
    worker = fault == "SIGKILL frame worker"
    bench = Bench(model if worker else None, scene if worker else None)
    try:
        status = bench.wait_ready(frames=worker)
        bench.light()
        t0 = time.monotonic()
        undo = inject(bench, fault, status)
        dark = bench.dark_after(t0, timeout_s)
        undo()
        return dark
    finally:
        bench.close()


def measure(faults: list[str], repeats: int, timeout_s: float, model: Path | None = None,
            scene: Path | None = None, log: Callable[[str], None] = lambda s: None
            ) -> list[dict[str, Any]]:
    rows = []
    for fault in faults:
        times = []
        for i in range(repeats):
            dark = trial(fault, timeout_s, model, scene)
            times.append(None if dark is None else round(dark * 1e3, 1))
            log(f"{fault} #{i + 1}: " + (f"{times[-1]:.1f} ms" if dark is not None
                                         else f"not off within {timeout_s:g} s"))
        done = [t for t in times if t is not None]
        rows.append({"fault": fault, "times_ms": times, "timeout_s": timeout_s,
                     "all_off": len(done) == len(times),
                     "median_ms": round(statistics.median(done), 1) if done else None,
                     "max_ms": max(done) if len(done) == len(times) else None})
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| fault | trials | median ms | max ms | all off |", "|---|---|---|---|---|"]
    for r in rows:
        off = "yes" if r["all_off"] else (
            f"no: {r['times_ms'].count(None)} not off within {r['timeout_s']:g} s")
        med = "-" if r["median_ms"] is None else f"{r['median_ms']:.1f}"
        mx = "-" if r["max_ms"] is None else f"{r['max_ms']:.1f}"
        lines.append(f"| {r['fault']} | {len(r['times_ms'])} | {med} | {mx} | {off} |")
    return "\n".join(lines)


# -- malformed requests -------------------------------------------------------------------------


def bad_requests(n: int, seed: int, cap: int) -> tuple[list[bytes], int]:
    """n bad request lines (each must fail); returns them and how many expect a reply."""
    rng = random.Random(seed)
    junk = [b"{", b"}", b"[1,", b"nul", b'{"jsonrpc":"2.0"', b"\x00\x01", b'"str"', b"3",
            b'{"jsonrpc":"2.0","method":"status","id":NaN}', b'{"a":Infinity}', b"[]"]
    bad_values = [None, True, "x", [], {}, -1e308, 1e308, "NaN", [1, 2], 10**30, -1e7]
    methods = ["set_view", "focus", "laser", "snapshot", "load_scene", "load_model", "job",
               "status", "stop", "blank", "shutdown", "frobnicate", "", "Status"]
    lines, replies = [], 0
    for i in range(n):
        kind = rng.random()
        notify = rng.random() < 0.1
        rid = {} if notify else {"id": i}
        if kind < 0.15:
            lines.append(rng.choice(junk) + b"\n")
            replies += 1  # parse errors and invalid requests always get an (id null) reply
            continue
        if kind < 0.17:
            lines.append(b'{"pad":"' + b"x" * (cap + rng.randrange(1, 100)) + b'"}\n')
            replies += 1
            continue
        if kind < 0.22:
            num = rng.choice([b"1e400", b"-1e999", b"NaN", b"Infinity", b"-Infinity"])
            lines.append(b'{"jsonrpc":"2.0","method":"focus","params":{"z_mm":' + num
                         + b'},"id":' + str(i).encode() + b"}\n")
            replies += 1
            continue
        method = rng.choice(methods)
        v = rng.choice(bad_values)
        params = {
            "set_view": [{"orbit": {"azimuth_deg": v, "elevation_deg": 0, "radius": 1}},
                         {"pose": {"position": v, "quaternion_wxyz": [1, 0, 0, 0]}},
                         {"orbit": {"azimuth_deg": 0, "elevation_deg": 95, "radius": 1}},
                         {"relative": {"d_azimuth_deg": 1}}, {}],
            "focus": [{"z_mm": v}, {"z_mm": 50.0}, {"z_mm": 1.0, "speed": 3}],
            "laser": [{"action": "arm", "duration_s": v}, {"action": "fire"},
                      {"action": "power", "channel": "uv", "power_pct": 1.0},
                      {"action": "power", "channel": "red", "power_pct": v},
                      {"action": "arm", "duration_s": 1e9}],
            "snapshot": [{"path": "/etc/x.png"}, {"path": "../../x.png"}, {"frames": v},
                         {"path": v}],
            "load_scene": [{"path": "/etc/passwd"}, {"path": "../../../etc/hosts.ply"},
                           {"path": v}, {}],
            "load_model": [{"path": "/tmp/m.onnx"}, {"path": v}],
            "job": [{"id": v}, {"id": 0}],
            "status": [{"verbose": True}], "stop": [{"x": v}], "blank": [{"now": 1}],
            "shutdown": [{"force": True}],
        }.get(method, [{}])
        p = rng.choice(params)
        msg = {"jsonrpc": "2.0", "method": method, "params": p, **rid}
        if rng.random() < 0.05:
            msg["jsonrpc"] = "1.0"
        try:
            line = json.dumps(msg).encode() + b"\n"
        except ValueError:
            continue
        lines.append(line)
        # A notification is a *valid* request without an id: it never gets a reply. One that is
        # not a valid request (method "" here) is an Invalid Request, answered with id null.
        replies += 0 if notify and msg["jsonrpc"] == "2.0" and method else 1
    return lines, replies


def send_all(path: Path, lines: list[bytes], timeout_s: float = 60.0) -> list[Any]:
    """The lines on one connection, then a good `status` as an end mark; every reply before
    the mark's (the mark's own left out), however they arrive in chunks."""
    end = b'{"jsonrpc":"2.0","method":"status","id":"end"}\n'
    got: list[Any] = []
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(timeout_s)
        s.connect(str(path))
        writer = threading.Thread(target=s.sendall, args=(b"".join(lines) + end,), daemon=True)
        writer.start()
        buf = bytearray()
        while not got or not (isinstance(got[-1], dict) and got[-1].get("id") == "end"):
            chunk = s.recv(1 << 20)
            if not chunk:
                raise ConnectionError(f"the daemon hung up after {len(got)} replies")
            buf += chunk
            *done, rest = bytes(buf).split(b"\n")
            got += [json.loads(x) for x in done]
            buf = bytearray(rest)
        writer.join(timeout_s)
    return got[:-1]


STATE_KEYS = ("view", "scene", "model", "display", "jobs")


def fuzz(n: int, seed: int = 7) -> dict[str, Any]:
    """n bad requests against a fresh daemon: replies, their kinds, state and lasers after."""
    bench = Bench()
    try:
        bench.wait_ready(frames=False)
        audit = bench.root / "audit.jsonl"
        with bench.client() as c:
            before = c.status()
            lines, expected = bad_requests(n, seed, 65536)
            audit0 = audit.stat().st_size
            t0 = time.monotonic()
            got = send_all(bench.socket, lines)
            took = time.monotonic() - t0
            after = c.status()
        errors = sum(1 for r in got if isinstance(r, dict) and "error" in r and "result" not in r)
        return {
            "requests": len(lines), "replies_expected": expected, "replies": len(got),
            "all_errors": errors == len(got), "seconds": round(took, 3),
            "requests_per_s": round(len(lines) / took, 1),
            "state_unchanged": all(after[k] == before[k] for k in STATE_KEYS)
            and after["laser"]["armed"] is False and after["daemon"]["state"] == "ready",
            "max_emitted_pct": bench.twin.max_emitted_pct(),
            "audit_bytes_added": audit.stat().st_size - audit0,
        }
    finally:
        bench.close()


# -- the command --------------------------------------------------------------------------------


def run(args: argparse.Namespace) -> int:
    faults = [f.strip() for f in args.faults.split(",") if f.strip()]
    unknown = [f for f in faults if f not in FAULTS]
    if unknown:
        raise SystemExit(f"--faults: no fault {unknown[0]!r}; one of: {', '.join(FAULTS)}")
    if args.repeats < 1:
        raise SystemExit(f"--repeats = {args.repeats}: at least 1")
    model = scene = None
    if "SIGKILL frame worker" in faults:
        model, scene = Path(args.model).resolve(), Path(args.scene).resolve()
        for f in (model, scene):
            if not f.is_file():
                raise SystemExit(f"{f}: not found (the frame-worker fault loads it)")
    rows = measure(faults, args.repeats, args.timeout_s, model, scene,
                   log=lambda s: print(s, flush=True))
    out: dict[str, Any] = {"nhfd_version": __version__, "machine": describe(),
                           "load_average": [round(x, 2) for x in os.getloadavg()],
                           "faults": rows}
    print(table(rows))
    ok = all(r["all_off"] for r in rows)
    if args.fuzz:
        f = out["fuzz"] = fuzz(args.fuzz)
        print(f"fuzz: {f['requests']} malformed requests in {f['seconds']} s "
              f"({f['requests_per_s']}/s): {f['replies']} replies of {f['replies_expected']} "
              f"expected, all errors: {f['all_errors']}, state unchanged: "
              f"{f['state_unchanged']}, lasers max {f['max_emitted_pct']} %, audit log "
              f"+{f['audit_bytes_added']} bytes")
        ok = ok and f["all_errors"] and f["state_unchanged"] \
            and f["replies"] == f["replies_expected"]
    out["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")
    return 0 if ok else 1
