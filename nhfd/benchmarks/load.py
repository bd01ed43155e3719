"""`nhfd bench load`: idle CPU, then `status` latency and resident memory under the 8-client
`set_view` storm.

Idle first (`--idle` seconds each, 0 skips it): `nhfd serve` with nothing loaded (no model, no
scene, so no frame worker), once with the default simulated devices (every twin inside the daemon)
and once with the lasers on a twin this process hosts (`devices.laser = "readybeam"` on its pty,
no stage or camera: device peers outside the daemon, as on a real bench). The daemon's and the
laser guardian's CPU time is read from /proc/<pid>/stat over the window, with no client
connected. The storm's daemon (model and scene loaded) is measured the same way before its
storm starts, frame worker included.

Starts a real `nhfd serve` process on the simulated bench (the shipped model and the donut scene
by default, so the frame worker renders while the storm runs), then for `--duration` seconds:
`--clients` connections send `set_view` (orbits inside the model's pose envelope) as fast as they
get replies, while one more connection asks for `status` every `--status-every` seconds and
times each reply. Resident memory (VmRSS) of the daemon and of its frame worker is read after a
warm-up storm and again at the end: the growth is what a long session would accumulate. Ends by
checking that the daemon shows the last requested view, then shuts it down.

The clients are threads of this process: on a 2-core machine they compete with the daemon for
the CPU, as local clients on the bench's computer would.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from nhfd import __version__
from nhfd.benchmarks.machine import describe
from nhfd.daemon.client import Client
from nhfd.drivers.twins.apt_twin import AptTwin
from nhfd.drivers.twins.mecom_twin import MecomTwin
from nhfd.models.export import OnnxModel


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("load", help="status latency and memory under a set_view storm",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="models/nhf-donut-512.onnx",
                   help="model the daemon loads ('' = none: the storm without frames)")
    p.add_argument("--scene", default="models/scenes/donut.ply")
    p.add_argument("--clients", type=int, default=8, help="set_view clients")
    p.add_argument("--duration", type=float, default=60.0, help="measured storm (s)")
    # The frame cache (16 frames) and the kernels fill during the first ~15 s of a storm: memory
    # read before that would count filling caches as growth.
    p.add_argument("--warmup", type=float, default=20.0, help="storm before memory is read (s)")
    p.add_argument("--status-every", type=float, default=0.02, help="status period (s)")
    p.add_argument("--idle", type=float, default=20.0,
                   help="idle CPU window per configuration (s; 0 = no idle phase)")
    p.add_argument("--json", default="out/bench/load.json", help="JSON results file")
    p.add_argument("--print-json", action="store_true", help="print the JSON to stdout only")
    p.set_defaults(handler=run)


def rss_mb(pid: int | None) -> float | None:
    """Resident set size of a process (MiB), from /proc; None when it is gone."""
    if pid is None:
        return None
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def cpu_s(pid: int | None) -> float | None:
    """User plus system CPU time of a process, all its threads (s), from /proc; None when it
    is gone."""
    if pid is None:
        return None
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_percent(pids: dict[str, int | None], window_s: float) -> dict[str, float | None]:
    """% of one core each process used over the next window_s (None: no such process)."""
    before = {name: cpu_s(pid) for name, pid in pids.items()}
    t0 = time.monotonic()
    time.sleep(window_s)
    elapsed = time.monotonic() - t0
    after = {name: cpu_s(pid) for name, pid in pids.items()}
    out: dict[str, float | None] = {}
    for name in pids:
        a, b = before[name], after[name]
        out[name] = None if a is None or b is None else round(100 * (b - a) / elapsed, 3)
    return out


# The devices of the idle phases (nothing loaded). The second is a real bench's daemon: the real
# readybeam and apt drivers against twins outside it (their CPU is not the daemon's).
IDLE_DEVICES = {
    "default simulated devices": [],
    "laser and stage on outside peers": ['laser = "readybeam"', 'stage = "apt"',
                                         'camera = "none"', 'slm = "simulated"',
                                         'navigator = "none"'],
}


def config_text(root: Path, model: Path | None, scene: Path | None,
                 devices: list[str] | None = None, laser_port: str = "",
                 stage_port: str = "") -> str:
    """A daemon's configuration under `root` (runtime directory, audit log, snapshots), the
    guardian always spawned: `devices` lines (default: the simulated bench), the laser and
    stage ports of outside twins, and the model and scene to load at start, if any."""
    dirs = {"scene_dirs": [str(scene.parent)] if scene else [str(root)],
            "model_dirs": [str(model.parent)] if model else [str(root)]}
    if devices is None:
        devices = ['slm = "simulated"', 'laser = "simulated"', 'stage = "simulated"',
                   'camera = "none"', 'navigator = "none"']
    lines = [
        "[devices]", *devices,
        "[devices.readybeam]", f'port = "{laser_port}"',
        # A pty has no modem lines: the stage's line reset is skipped there.
        "[devices.apt]", f'port = "{stage_port}"', f"rts_reset = {str(not stage_port).lower()}",
        "[devices.readybeam.guardian]", f'socket_path = "{root / "laser.sock"}"',
        "[daemon.arming]", 'guardian = "spawn"',
        "[daemon.audit]", f'file = "{root / "audit.jsonl"}"',
        "[daemon.paths]", f'snapshot_dir = "{root / "snaps"}"',
        f"scene_dirs = {json.dumps(dirs['scene_dirs'])}",
        f"model_dirs = {json.dumps(dirs['model_dirs'])}",
    ]
    if model and scene:
        lines += [f'scene = "{scene}"', "[daemon.frames]", f'model = "{model}"']
    # [daemon.server] last: a caller's server keys (tcp_port, nhfd.benchmarks.hostile) join it.
    lines += ["[daemon.server]", f'runtime_dir = "{root / "run"}"']
    return "\n".join(lines) + "\n"


def _wait_ready(client_cls: Any, sock: Path, proc: subprocess.Popen[bytes], want_frames: bool,
                timeout_s: float = 180.0) -> Any:
    end = time.monotonic() + timeout_s
    client = None
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"nhfd serve exited with {proc.returncode}")
        try:
            client = client or client_cls(sock, timeout_s=30)
            st = client.status()
            if not want_frames or (st["frames"]["state"] == "running"
                                   and st["model"] != "none loaded" and st["scene"]):
                return client
            if st["errors"]:
                raise RuntimeError(f"daemon errors while loading: {st['errors'][-1]}")
        except OSError:
            client = None
        time.sleep(0.2)
    raise TimeoutError("the daemon did not get ready (model and scene loaded) in time")


def _serve(cfg: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "nhfd.cli.main", "serve", "--config",
                             str(cfg)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _stop(proc: subprocess.Popen[bytes], client: Any) -> None:
    with contextlib.suppress(Exception):
        client.call("shutdown")
        client.close()
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(30)
    if proc.poll() is None:
        proc.terminate()
        proc.wait(30)


def idle_pids(status: dict[str, Any], daemon_pid: int) -> dict[str, int | None]:
    return {"daemon": daemon_pid, "guardian": status["laser"]["guardian"]["spawned_pid"],
            "frame worker": status["frames"]["pid"] if status["frames"]["alive"] else None}


def idle(window_s: float, settle_s: float = 2.0) -> list[dict[str, Any]]:
    """Each IDLE_DEVICES configuration with nothing loaded: % of a core per process."""
    rows = []
    for name, devices in IDLE_DEVICES.items():
        root = Path(tempfile.mkdtemp(prefix="nhfd-idle-", dir="/tmp"))
        twins = [MecomTwin().start(), AptTwin().start()] if devices else []
        cfg = root / "nhfd.toml"
        cfg.write_text(config_text(root, None, None, devices,
                                    *(twin.port_path for twin in twins)))
        proc = _serve(cfg)
        try:
            client = _wait_ready(Client, root / "run" / "control.sock", proc, False)
            st = client.status()
            client.close()  # no client while it idles
            time.sleep(settle_s)  # the end of start-up is not idle
            pids = idle_pids(st, proc.pid)
            cpu = cpu_percent(pids, window_s)
            opened = sorted(k for k, v in st["devices"].items() if v["open"])
            rows.append({"configuration": name, "loaded": "nothing", "window_s": window_s,
                         "devices_open": opened, "cpu_pct_of_core": cpu})
            _stop(proc, Client(root / "run" / "control.sock", timeout_s=30))
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(30)
            for twin in twins:
                twin.close()
    return rows


def storm(sock: Path, args: argparse.Namespace, envelope: dict[str, Any], pid: int,
          worker_pid: int | None) -> dict[str, Any]:
    az = envelope.get("azimuth_deg") or [-20.0, 20.0]
    el = envelope.get("elevation_deg") or [0.0, 20.0]
    dist = envelope.get("distance") or [2.0, 2.0]
    stop = threading.Event()
    sent = [0] * args.clients
    last_seq = [0] * args.clients
    failures: list[str] = []

    def client_loop(i: int) -> None:
        rng = random.Random(i)
        with Client(sock, timeout_s=30) as c:
            while not stop.is_set():
                try:
                    r = c.call("set_view", orbit={
                        "azimuth_deg": rng.uniform(*az), "elevation_deg": rng.uniform(*el),
                        "radius": rng.uniform(*dist)})
                except Exception as exc:  # counted, reported; the storm goes on
                    failures.append(f"client {i}: {type(exc).__name__}: {exc}")
                    return
                sent[i] += 1
                last_seq[i] = r["seq"]

    latencies: list[float] = []
    measuring = threading.Event()

    def status_loop() -> None:
        with Client(sock, timeout_s=30) as c:
            while not stop.is_set():
                t0 = time.perf_counter()
                c.status()
                if measuring.is_set():
                    latencies.append((time.perf_counter() - t0) * 1e3)
                time.sleep(args.status_every)

    threads = [threading.Thread(target=client_loop, args=(i,), daemon=True)
               for i in range(args.clients)]
    threads.append(threading.Thread(target=status_loop, daemon=True))
    for t in threads:
        t.start()
    time.sleep(args.warmup)
    rss0 = {"daemon": rss_mb(pid), "worker": rss_mb(worker_pid)}
    peak = dict(rss0)
    sent0 = sum(sent)
    measuring.set()
    t0 = time.monotonic()
    while time.monotonic() - t0 < args.duration:
        time.sleep(0.25)
        for name, p in (("daemon", pid), ("worker", worker_pid)):
            now = rss_mb(p)
            if now is not None and (peak[name] is None or now > peak[name]):
                peak[name] = now
    elapsed = time.monotonic() - t0
    rss1 = {"daemon": rss_mb(pid), "worker": rss_mb(worker_pid)}
    stop.set()
    for t in threads:
        t.join(35)
    lat = np.asarray(latencies) if latencies else np.zeros(1)

    def growth(name: str) -> float | None:
        a, b = rss0[name], rss1[name]
        return None if a is None or b is None else round(b - a, 2)

    return {
        "clients": args.clients, "duration_s": round(elapsed, 2),
        "set_view_requests": sum(sent) - sent0,
        "set_view_per_s": round((sum(sent) - sent0) / elapsed, 1),
        "last_seq": max(last_seq), "failures": failures[:10],
        "status_requests": len(latencies),
        "status_ms": {"p50": round(float(np.percentile(lat, 50)), 3),
                      "p95": round(float(np.percentile(lat, 95)), 3),
                      "p99": round(float(np.percentile(lat, 99)), 3),
                      "max": round(float(lat.max()), 3)},
        "rss_mb": {"start": rss0, "end": rss1, "peak": peak,
                   "growth": {"daemon": growth("daemon"), "worker": growth("worker")}},
    }


def run(args: argparse.Namespace) -> int:
    model = Path(args.model).resolve() if args.model else None
    scene = Path(args.scene).resolve() if args.model else None
    for f in (model, scene):
        if f is not None and not f.is_file():
            raise FileNotFoundError(f"{f}: not found (--model '' runs the storm without frames)")
    envelope: dict[str, Any] = {}
    if model is not None:
        envelope = OnnxModel(model).metadata.get("pose_envelope") or {}
    load_start = [round(x, 2) for x in os.getloadavg()]  # the machine is shared: say how much
    idle_rows = idle(args.idle) if args.idle > 0 else []
    root = Path(tempfile.mkdtemp(prefix="nhfd-load-", dir="/tmp"))
    cfg = root / "nhfd.toml"
    cfg.write_text(config_text(root, model, scene))
    proc = _serve(cfg)
    try:
        sock = root / "run" / "control.sock"
        client = _wait_ready(Client, sock, proc, model is not None)
        st = client.status()
        worker_pid = st["frames"]["pid"] if model is not None else None
        if args.idle > 0 and model is not None:
            time.sleep(2.0)  # the end of start-up is not idle
            idle_rows.append({"configuration": "the storm's bench", "loaded": "model and scene",
                              "window_s": args.idle,
                              "cpu_pct_of_core": cpu_percent(idle_pids(st, proc.pid),
                                                             args.idle)})
        result = storm(sock, args, envelope, proc.pid, worker_pid)
        # The daemon must end on the newest request (latest wins) and still answer.
        end = time.monotonic() + 60
        while time.monotonic() < end:
            view = client.status()["view"]
            if model is None or view["applied_seq"] == view["seq"]:
                break
            time.sleep(0.1)
        view = client.status()["view"]
        result["ended_on_last_view"] = (view["seq"] == result["last_seq"]
                                        and (model is None or view["applied_seq"] == view["seq"]))
        result["frames_shown"] = client.status()["frames"]["frames_shown"]
        with contextlib.suppress(Exception):
            client.call("shutdown")
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(30)
    out = {"nhfd_version": __version__, "machine": describe(), "model": str(model or ""),
           "load_average_start": load_start,
           "load_average_end": [round(x, 2) for x in os.getloadavg()], "idle": idle_rows,
           "pid_daemon": proc.pid, **result}
    text = json.dumps(out, indent=1)
    if args.print_json:
        print(text)
        return 0 if result["ended_on_last_view"] and not result["failures"] else 1
    for row in idle_rows:
        cpu = ", ".join(f"{k} {v:.2f} %" for k, v in row["cpu_pct_of_core"].items()
                        if v is not None)
        print(f"idle, {row['loaded']} loaded, {row['configuration']} ({row['window_s']:g} s): "
              f"{cpu} of a core")
    s, m = result["status_ms"], result["rss_mb"]
    print(f"{args.clients} clients x set_view for {result['duration_s']} s: "
          f"{result['set_view_requests']} requests ({result['set_view_per_s']}/s), "
          f"{result['frames_shown']} frames shown, ended on the last view: "
          f"{result['ended_on_last_view']}")
    print(f"status latency ({result['status_requests']} calls): p50 {s['p50']:.2f} ms, "
          f"p95 {s['p95']:.2f} ms, p99 {s['p99']:.2f} ms, max {s['max']:.2f} ms")
    for name in ("daemon", "worker"):
        if m["start"][name] is not None:
            print(f"RSS {name}: {m['start'][name]:.1f} -> {m['end'][name]:.1f} MiB "
                  f"(growth {m['growth'][name]:+.1f}, peak {m['peak'][name]:.1f})")
    if result["failures"]:
        print("failures:", *result["failures"], sep="\n  ")
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(f"wrote {path}")
    return 0 if result["ended_on_last_view"] and not result["failures"] else 1
