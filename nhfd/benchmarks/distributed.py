"""`nhfd bench distributed`: speed-up of 2 local workers against 1, dataset build and training.

Dataset build (the same small dataset of `--scene`, `--views` views at `--size`, built from
scratch each time into a fresh folder): one process on one thread and on two (the default: one
per core), 2 local processes (`--workers 2`, one thread each), and Ray tasks on a local Ray
instance of 1 and of 2 CPUs (`--executor ray`; the build time includes starting Ray and its
workers). Every build's shards are checked equal, byte for byte, to the first's. The speed-ups
compare the build times (the CLI's whole `build` call: depth pass, examples, merge), not the
process's start.

Training (a synthetic dataset, `--train-steps` steps of batch `--batch` at `--crop`): one
process on one thread, one process on two threads (torch's intra-op parallelism, the
alternative on one machine), and `torchrun --nproc-per-node 2` (DistributedDataParallel, gloo,
one thread each, half of each batch per process).

Each run is its own child process; its peak memory is the largest sum of resident memory over
the child and all its descendants (Ray's raylet and workers, torchrun's processes), sampled from
/proc every 50 ms. The machine is shared and noisy: figures are medians of `--repeats` runs.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from nhfd.benchmarks.machine import describe
from nhfd.cli.args import parse_wxh
from nhfd.models.synthetic import synthetic_dataset


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("distributed", help="2 local workers vs 1: dataset build and training",
                       description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--scene", default="models/scenes/donut.ply", help="scene of the dataset")
    p.add_argument("--views", type=int, default=8, help="dataset views (default 8)")
    p.add_argument("--size", default="256x144", help="dataset view WxH (default 256x144)")
    p.add_argument("--train-steps", type=int, default=20, help="training steps (default 20)")
    p.add_argument("--batch", type=int, default=4, help="training batch (default 4)")
    p.add_argument("--crop", default="128x128", help="training crop WxH (default 128x128)")
    p.add_argument("--repeats", type=int, default=1, help="runs of each case; median kept")
    p.add_argument("--no-ray", action="store_true", help="skip the Ray cases")
    p.add_argument("--no-train", action="store_true", help="skip the training cases")
    p.add_argument("--out", default="out/bench/distributed.json", help="JSON file to write")
    p.set_defaults(handler=run)


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(v) for v in text.split()]


def _tree_rss_bytes(root: int) -> int:
    """Resident memory of `root` and all its descendants."""
    total, stack, seen = 0, [root], set()
    page = os.sysconf("SC_PAGE_SIZE")
    while stack:
        pid = stack.pop()
        if pid in seen:
            continue
        seen.add(pid)
        try:
            total += int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * page
        except (OSError, IndexError, ValueError):
            continue
        stack.extend(_children(pid))
    return total


def measure(cmd: list[str], env: dict | None = None, timeout_s: float = 1800) -> dict:
    """Run `cmd`; its wall time, the largest resident memory of its process tree, and the JSON
    object its last stdout line holds (if any)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)  # fmt: skip
    peak = 0
    stop = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not stop.is_set():
            peak = max(peak, _tree_rss_bytes(proc.pid))
            stop.wait(0.05)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        out, err = proc.communicate(timeout=timeout_s)
    finally:
        stop.set()
        sampler.join()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:6])} ... exited {proc.returncode}: {err[-2000:]}")
    lines = [ln for ln in out.strip().splitlines() if ln.startswith("{")]
    return {**(json.loads(lines[-1]) if lines else {}), "process_wall_s": wall,
            "peak_rss_mib": peak / 2**20}  # fmt: skip


# The dataset build a child runs: the CLI's own pose sampling and settings, minus the printing.
_BUILD = """
import json, sys, time
t0 = time.perf_counter()
from nhfd.cli import cmd_dataset
from nhfd.dataset import build as b
kw = json.loads(sys.argv[1])
result = {}
real = b.build
def timed(*a, **k):
    t = time.perf_counter()
    m = real(*a, **k)
    result.update(m.get("build_timing", {}), build_s=time.perf_counter() - t)
    return m
cmd_dataset.build = timed
from nhfd.cli.main import main
code = main(kw["argv"])
print(json.dumps({**result, "process_s": time.perf_counter() - t0, "code": code}))
"""


def _build_case(args, scene: Path, root: Path, name: str, extra: list[str]) -> dict:
    w, h = parse_wxh(args.size, "--size")
    out = root / name
    argv = ["dataset", "build", "--scene", str(scene), "--out", str(out), "--views",
            str(args.views), "--size", f"{w}x{h}", *extra]  # fmt: skip
    runs = []
    for _ in range(args.repeats):
        shutil.rmtree(out, ignore_errors=True)
        runs.append(measure([sys.executable, "-c", _BUILD, json.dumps({"argv": argv})]))
    return _median_run(runs) | {"folder": str(out)}


def _median_run(runs: list[dict]) -> dict:
    keys = [k for k in runs[0] if isinstance(runs[0][k], int | float)]
    med = {k: statistics.median(r[k] for r in runs) for k in keys}
    return {**runs[0], **med, "runs": len(runs)}


def _same_bytes(a: Path, b: Path) -> bool:
    fa = sorted(p.name for p in a.iterdir())
    return fa == sorted(p.name for p in b.iterdir()) and all(
        (a / n).read_bytes() == (b / n).read_bytes() for n in fa
    )


def _train_case(args, data: Path, root: Path, name: str, nproc: int, threads: int) -> dict:
    cw, ch = parse_wxh(args.crop, "--crop")
    out = root / name
    train_args = ["train", "--data", str(data), "--out", str(out), "--steps",
                  str(args.train_steps), "--batch", str(args.batch), "--crop", f"{cw}x{ch}",
                  "--checkpoint-every", str(10**6), "--val-views", "1", "--threads",
                  str(threads), "--no-progress", "--force"]  # fmt: skip
    env = {k: v for k, v in os.environ.items()
           if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")}
    env["OMP_NUM_THREADS"] = str(threads)
    if nproc == 1:
        cmd = [sys.executable, "-m", "nhfd.cli.main", *train_args]
    else:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(nproc),
               "--standalone", "-m", "nhfd.cli.main", *train_args]  # fmt: skip
    runs = []
    for _ in range(args.repeats):
        r = measure(cmd, env=env)
        log = (out / "train_log.csv").read_text().splitlines()[1:]
        # Steps after the first (start-up and first-touch costs land in step 1).
        secs = [float(line.split(",")[-1]) for line in log[1:]]
        r["median_step_s"] = statistics.median(secs) if secs else float("nan")
        r["final_loss"] = float(log[-1].split(",")[2])
        runs.append(r)
    return _median_run(runs)


def run(args: argparse.Namespace) -> int:
    for name in ("views", "train_steps", "batch", "repeats"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} {getattr(args, name)}: must be >= 1")
    if args.batch % 2:
        raise ValueError(f"--batch {args.batch}: must be even (2 processes share each batch)")
    scene = Path(args.scene)
    if not scene.exists():
        raise FileNotFoundError(f"--scene {scene}: no such file")
    machine = describe()
    # Other users of a shared machine change every figure: the load says how much.
    machine["load_average_1min"] = os.getloadavg()[0]
    print(f"{machine}")
    report: dict = {"machine": machine, "scene": str(scene), "views": args.views,
                    "size": args.size, "dataset": {}, "train": {}}  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="nhfd-bench-dist-") as tmp:
        root = Path(tmp)
        cases = [("1 process, 1 thread", ["--threads", "1"]),
                 ("1 process, 2 threads", ["--threads", "2"]),
                 ("2 processes", ["--workers", "2"])]
        if not args.no_ray:
            try:
                import ray  # noqa: F401 (only whether it is installed)

                cases += [("ray, 1 worker", ["--executor", "ray", "--workers", "1"]),
                          ("ray, 2 workers", ["--executor", "ray", "--workers", "2"])]
            except ImportError:
                print("ray not installed (pip install 'nhfd[ray]'): Ray cases skipped")
        ref = None
        for i, (label, extra) in enumerate(cases):
            r = _build_case(args, scene, root, f"ds{i}", extra)
            folder = Path(r.pop("folder"))
            r["same_bytes_as_first"] = True if ref is None else _same_bytes(ref, folder)
            ref = ref or folder
            report["dataset"][label] = r
            print(f"dataset  {label:<20} build {r['build_s']:7.1f} s  process "
                  f"{r['process_wall_s']:7.1f} s  peak {r['peak_rss_mib']:6.0f} MiB  "
                  f"same bytes {r['same_bytes_as_first']}")
        _speedups(report["dataset"], "build_s", ("1 process, 1 thread", "2 processes"),
                  ("1 process, 2 threads", "2 processes"),
                  ("ray, 1 worker", "ray, 2 workers"))  # fmt: skip
        if not args.no_train:
            cw, ch = parse_wxh(args.crop, "--crop")
            data = root / "train_data"
            synthetic_dataset(data, size_hw=(ch, cw), splits=(2 * args.batch, 1, 1))
            for label, nproc, threads in (("1 process, 1 thread", 1, 1),
                                          ("1 process, 2 threads", 1, 2),
                                          ("torchrun, 2 processes", 2, 1)):  # fmt: skip
                r = _train_case(args, data, root, label.replace(" ", "_").replace(",", ""),
                                nproc, threads)  # fmt: skip
                report["train"][label] = r
                print(f"train    {label:<22} {r['median_step_s'] * 1e3:7.0f} ms/step  process "
                      f"{r['process_wall_s']:6.1f} s  peak {r['peak_rss_mib']:6.0f} MiB  "
                      f"loss {r['final_loss']:.5g}")
            _speedups(report["train"], "median_step_s",
                      ("1 process, 1 thread", "torchrun, 2 processes"),
                      ("1 process, 2 threads", "torchrun, 2 processes"))  # fmt: skip
    for section in ("dataset", "train"):
        for k, v in report[section].get("speedups", {}).items():
            print(f"speed-up {section}: {k}: {v:.2f}x")
    report["load_average_1min_after"] = os.getloadavg()[0]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))
    print(f"wrote {out}")
    return 0


def _speedups(section: dict, key: str, *pairs: tuple[str, str]) -> None:
    ups = {}
    for base, other in pairs:
        if base in section and other in section and section[other][key] > 0:
            ups[f"{other} vs {base}"] = section[base][key] / section[other][key]
    section["speedups"] = ups
