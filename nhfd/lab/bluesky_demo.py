"""A Bluesky focus scan on the simulated bench, and its plot.

    python -m nhfd.lab.bluesky_demo --out docs/figures/bluesky_focus_scan.png

Starts a daemon in this process on the simulated bench (a 128 x 128 panel, the simulated
camera, stage and laser), shows a lattice of dots focused `FOCUS_MM` beyond the reference plane
(the calibration's dot hologram, `nhfd.calib.patterns`), captures a dark frame, arms green over
the Unix socket (a person running the demo arms, as in `nhfd demo`) and runs
`bluesky.plans.scan([camera], focus, ...)` through `nhfd.lab.bluesky`'s devices. The dots blur,
sharpen at `FOCUS_MM` and blur again: the plot shows each capture's sharpness against the focus
readback, with thumbnails.

The daemon's focus is uncalibrated here (`stage = stage_at_reference_mm + z_mm`), with the
reference at the stage reading that images the SLM itself; the simulated relay's longitudinal
magnification M^2 turns a dot depth d behind the SLM into d M^2 of stage travel, so the dots are
designed at `FOCUS_MM / M^2`.
"""

from __future__ import annotations

import argparse
import contextlib
import shutil
import tempfile
import threading
import time
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from bluesky import RunEngine
from bluesky.plans import scan
from ophyd.status import Status

from nhfd.calib.patterns import PatternSpec, dots_frame
from nhfd.config import Config, _overlay, default_text
from nhfd.daemon.client import Client
from nhfd.daemon.service import Daemon
from nhfd.drivers.simcamera import TrueBench

from .bluesky import NhfdBench, connect

PANEL_HW = (128, 128)
# The focus (mm, the daemon's z_mm) at which the dots are sharp.
FOCUS_MM = 0.5
EXPOSURE_S = 0.02
DARK_FRAMES = 4
ARM_S = 120.0
PATTERN = "bluesky_dots.npy"


def sim_config(root: Path, truth: TrueBench) -> Config:
    """The simulated bench, everything under `root`: a small panel, a camera region around it,
    fast stage moves and focus 0 at the SLM plane."""
    user = {
        "slm": {"width_px": PANEL_HW[1], "height_px": PANEL_HW[0]},
        "optics": {"hologram_width_px": PANEL_HW[1] // 2, "hologram_height_px": PANEL_HW[0] // 2},
        "devices": {"slm": "simulated", "laser": "simulated", "stage": "simulated",
                    "camera": "simulated", "navigator": "none",
                    "readybeam": {"guardian": {"socket_path": str(root / "laser.sock")}},
                    "slm_output": {"settle_ms": 1.0},
                    "apt": {"enable_settle_s": 0.0, "velocity_mm_s": 50.0,
                            "acceleration_mm_s2": 100.0, "require_homed": False}},
        "daemon": {"server": {"runtime_dir": str(root / "run")},
                   "arming": {"guardian": "spawn"},
                   "paths": {"snapshot_dir": str(root / "snaps"),
                             "pattern_dirs": [str(root / "calib")]},
                   "audit": {"file": str(root / "audit.jsonl")},
                   "bench": {"camera_roi_px": list(truth.roi_for_panel(PANEL_HW)),
                             "stage_at_reference_mm": truth.stage_at_slm_mm}},
    }
    return Config.model_validate(_overlay(tomllib.loads(default_text()), user))


def dots_pattern(config: Config, truth: TrueBench, focus_mm: float = FOCUS_MM) -> np.ndarray:
    """The calibration's dot lattice, every dot at the depth the camera sees at `focus_mm`. The
    pattern wants two depth groups: the second lies 1 um further, far inside the depth of focus
    (tens of um at the relay's aperture)."""
    depth_m = focus_mm * 1e-3 * truth.stage_scale
    spec = PatternSpec(panel_hw=PANEL_HW, pitch_m=config.slm.pitch_m,
                       wavelengths_m=tuple(config.optics.wavelengths_m),  # type: ignore[arg-type]
                       depths_m=(depth_m, depth_m + 1e-6), missing_fraction=0.0)
    return dots_frame(spec)


@dataclass
class SimBench:
    daemon: Daemon
    root: Path
    truth: TrueBench
    bench: NhfdBench


@contextlib.contextmanager
def simulated_bench(focus_mm: float = FOCUS_MM, *, arm: bool = True,
                    exposure_s: float = EXPOSURE_S) -> Iterator[SimBench]:
    """A daemon on the simulated bench showing the dots, green armed at its cap (`arm`), and
    `connect()`'s devices on its socket; shut down (lasers off) on exit."""
    root = Path(tempfile.mkdtemp(prefix="nhfd-bs-", dir="/tmp"))  # short: a Unix socket
    truth = TrueBench()
    config = sim_config(root, truth)
    daemon = Daemon(config, base_dir=root, env={}, handle_signals=False)
    daemon.start()
    loop = threading.Thread(target=daemon.run, name="nhfd-bluesky-daemon", daemon=True)
    loop.start()
    try:
        (root / "calib").mkdir(exist_ok=True)
        np.save(root / "calib" / PATTERN, dots_pattern(config, truth, focus_mm))
        client = Client(daemon.socket_path, timeout_s=30.0)
        bench = connect(client, exposure_s=exposure_s)
        bench.link.call("show_pattern", path=PATTERN)
        _wait(bench, "capture", path="bluesky/dark.npy", dark=True, frames=DARK_FRAMES,
              exposure_s=exposure_s)
        if arm:  # a person's act, over the Unix socket; never from the devices
            cap = config.devices.readybeam.max_power_pct[1]
            bench.link.call("laser", action="arm", duration_s=ARM_S)
            bench.link.call("laser", action="power", channel="green", power_pct=cap)
            bench.link.call("laser", action="enable", channel="green")
        yield SimBench(daemon, root, truth, bench)
        with contextlib.suppress(Exception):
            bench.link.call("laser", action="off")
        bench.close()
    finally:
        daemon.request_shutdown("bluesky demo over")
        loop.join(30)
        shutil.rmtree(root, ignore_errors=True)


def _wait(bench: NhfdBench, method: str, **params: Any) -> dict[str, Any]:
    """A job to its end; RuntimeError with the daemon's error when it fails."""
    status = Status(timeout=bench.link.job_timeout_s)
    out: dict[str, Any] = {}
    bench.link.start_job(method, method, params, status, out.update)
    status.wait()
    return out


def sharpness(image: np.ndarray) -> float:
    """Normalised variance, mean(I^2) / mean(I)^2: the dots gather their light into few pixels
    at focus and spread it out of focus, while the total stays (an exposure-free measure)."""
    i = np.clip(np.asarray(image, np.float64), 0.0, None)
    mean = float(i.mean())
    if mean <= 0:
        raise ValueError("an image without light: no sharpness (are the lasers on?)")
    return float((i**2).mean() / mean**2)


def run_scan(bench: NhfdBench, z0_mm: float, z1_mm: float, n: int) -> list[tuple[str, dict]]:
    """`scan([camera], focus, z0, z1, n)` in a RunEngine; the documents in order."""
    docs: list[tuple[str, dict]] = []
    # No context managers: the RunEngine then installs no SIGINT handler (this may be a thread).
    engine = RunEngine({}, context_managers=[])
    engine.subscribe(lambda name, doc: docs.append((name, doc)))
    engine(scan([bench.camera], bench.focus, z0_mm, z1_mm, n))
    return docs


def scan_table(docs: list[tuple[str, dict]], focus: str = "focus",
               camera: str = "camera") -> dict[str, np.ndarray]:
    """Focus readbacks, setpoints, stage readings, images and sharpness from a scan's events."""
    events = [d for name, d in docs if name == "event"]
    data = [e["data"] for e in events]
    images = np.stack([np.asarray(d[f"{camera}_image"]) for d in data])
    return {"focus_mm": np.array([d[focus] for d in data]),
            "setpoint_mm": np.array([d[f"{focus}_setpoint"] for d in data]),
            "stage_mm": np.array([d[f"{focus}_stage_mm"] for d in data]),
            "camera_stage_mm": np.array([d[f"{camera}_stage_mm"] for d in data]),
            "images": images, "sharpness": np.array([sharpness(i) for i in images])}


def plot(table: dict[str, np.ndarray], path: Path, focus_mm: float = FOCUS_MM,
         thumbnails: int = 5) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    z, s, images = table["focus_mm"], table["sharpness"], table["images"]
    best = int(np.argmax(s))
    picks = np.unique([*np.linspace(0, len(z) - 1, thumbnails).round().astype(int), best])
    fig = plt.figure(figsize=(2.0 * len(picks), 5.6))
    gs = fig.add_gridspec(2, len(picks), height_ratios=[1, 1.35])
    h, w = images.shape[-2:]
    crop = (slice(h // 4, 3 * h // 4), slice(w // 4, 3 * w // 4))  # the lattice's middle
    # The relay images the panel upside down: rotated upright, one brightness scale for all.
    norm = float(np.percentile(images[:, crop[0], crop[1]], 99.9)) or 1.0
    for k, i in enumerate(picks):
        ax = fig.add_subplot(gs[0, k])
        ax.imshow(np.clip(np.rot90(images[i][crop], 2) / norm, 0, 1) ** 0.5, cmap="gray",
                  vmin=0, vmax=1)
        ax.set_title(f"focus {z[i]:+.2f} mm", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    ax = fig.add_subplot(gs[1, :])
    ax.plot(z, s, "o-", color="C2", label="capture sharpness, mean(I²)/mean(I)²")
    ax.plot(z[picks], s[picks], "o", mfc="none", mec="k", ms=10, label="thumbnails above")
    ax.axvline(focus_mm, color="k", ls="--", lw=0.8, label=f"dots' depth (focus {focus_mm:g} mm)")
    ax.set_xlabel("focus readback, z_mm (daemon's hologram depth)")
    ax.set_ylabel("sharpness")
    ax.legend(fontsize=8)
    fig.suptitle("bluesky.plans.scan([camera], focus, ...) through nhfd.lab.bluesky on the "
                 "simulated bench", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m nhfd.lab.bluesky_demo", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("out/bluesky_focus_scan.png"))
    ap.add_argument("--start-mm", type=float, default=-0.5)
    ap.add_argument("--stop-mm", type=float, default=1.5)
    ap.add_argument("--num", type=int, default=11)
    args = ap.parse_args(argv)
    with simulated_bench() as sim:
        t0 = time.perf_counter()
        docs = run_scan(sim.bench, args.start_mm, args.stop_mm, args.num)
        scan_s = time.perf_counter() - t0
    table = scan_table(docs)
    plot(table, args.out)
    best = int(np.argmax(table["sharpness"]))
    print(f"{len(table['focus_mm'])} events; sharpest at focus {table['focus_mm'][best]:+.3f} mm "
          f"(dots at {FOCUS_MM:+.3f} mm); scan {scan_s:.1f} s; plot {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
