"""`nhfd bench triggers`: calibration capture time with and without hardware triggers.

The same calibration capture (`nhfd.calib.capture`, up to the grating and flat frames: dark,
coarse sweep, locate, gratings and flats per colour) runs three times on the simulated bench, driven
through the drivers as the daemon's capture job drives them (`DevicesBenchIO`):

  settle   `[devices.trigger] source = "none"`: after each new frame the capture waits out the
           SLM's settle_ms (nhfd's default 50 ms: it must cover the display pipeline's latency
           and the liquid crystal's response, neither of which the host sees);
  trigger  `source = "slm_flip"`: the camera is armed and exposes `delay_ms` after the panel's
           flip edge; the host sleeps nothing;
  exposure `source = "camera_exposure"`: the camera's exposure-active line gates each frame's
           write (none during an exposure); the settle sleep stays. The simulated camera's
           exposure then takes its exposure time in wall time (in the other runs it takes none).

The simulated panel flips `--flip-latency-ms` after each write (one 60 Hz refresh by default)
and the trigger delay is the liquid crystal's response (`--delay-ms`). All runs see the same
frames, the same stage positions and the same camera noise; the figure is the wall time of each
capture, the time captures spent waiting for the panel, and whether all located the same bench
geometry. The stage moves at `--stage-mm-s` (the simulated APT stage's own motion).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.benchmarks.machine import describe
from nhfd.calib.capture import CapturePlan, DevicesBenchIO, capture
from nhfd.calib.patterns import PatternSpec
from nhfd.config import Config
from nhfd.device_settings import TRIGGER_SOURCES, TriggerSettings
from nhfd.drivers.factory import make_bench
from nhfd.drivers.simcamera import TrueBench

HELP = "calibration capture time with and without hardware triggers"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("triggers", help=HELP, description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--panel", type=int, default=128, help="square panel side, px (default 128)")
    p.add_argument("--settle-ms", type=float, default=None,
                   help="settle time without triggers (default: the configuration's, 50 ms)")
    p.add_argument("--flip-latency-ms", type=float, default=1000 / 60,
                   help="write-to-flip latency of the simulated panel (default one 60 Hz frame)")
    p.add_argument("--delay-ms", type=float, default=10.0,
                   help="the camera's trigger delay after the flip (default 10 ms)")
    p.add_argument("--stage-mm-s", type=float, default=20.0,
                   help="the simulated stage's velocity (default 20 mm/s)")
    p.add_argument("--stop-after", default="grating", choices=("coarse", "grating", "fine"),
                   help="last sweep captured (default grating)")
    p.add_argument("--out", default="out/bench/triggers.json", help="JSON file to write")
    p.set_defaults(handler=run)


def one(source: str, args: argparse.Namespace, workdir: Path) -> dict[str, Any]:
    d = Config().devices
    settle_ms = d.slm_output.settle_ms if args.settle_ms is None else args.settle_ms
    devices = d.model_copy(update={
        "slm_output": d.slm_output.model_copy(update={
            "settle_ms": settle_ms, "flip_latency_ms": args.flip_latency_ms}),
        "trigger": TriggerSettings(source=source, delay_ms=args.delay_ms),
        "apt": d.apt.model_copy(update={"velocity_mm_s": args.stage_mm_s,
                                        "acceleration_mm_s2": 100.0, "enable_settle_s": 0.0}),
    })
    bench = TrueBench()
    hw = (args.panel, args.panel)
    spec = PatternSpec(hw, bench.pitch_m, bench.wavelengths_m)
    # Power: the laser's default cap (10 %), so the driver need not clamp every request.
    plan = CapturePlan(stage_center_mm=10.0, stage_range_mm=1.0, coarse_step_mm=0.25,
                       fine_steps=9, power=d.readybeam.max_power_pct[1] / 100,
                       camera_pitch_m=bench.camera_pitch_m, stop_after=args.stop_after)
    with make_bench(devices, *hw, bench=bench, roi=bench.roi_for_panel(hw)) as b:
        b.camera.reseed(1)  # the same noise in both runs
        io = DevicesBenchIO(b, exposure_s=plan.exposure_s)
        t0 = time.perf_counter()
        manifest = capture(workdir / source, io, spec, plan)
        wall_s = time.perf_counter() - t0
        images = len(manifest["records"]) + 1  # + the dark frame
        return {
            "source": source, "settle_ms": 1e3 * b.slm.settle_s,
            "flip_latency_ms": args.flip_latency_ms,
            "delay_ms": args.delay_ms if source == "slm_flip" else None,
            "images": images, "frames_shown": b.slm.count, "wall_s": wall_s,
            "waited_s": io.waited_s, "per_image_ms": 1e3 * wall_s / images,
            "located": manifest["located"], "records": manifest["records"],
        }


def run(args: argparse.Namespace) -> int:
    if args.panel < 64:
        raise ValueError(f"--panel {args.panel}: must be >= 64 (the calibration patterns)")
    print(f"calibration capture (to {args.stop_after!r}) on the simulated bench, "
          f"{args.panel} x {args.panel} panel; {describe()}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="nhfd-triggers-") as tmp:
        for source in TRIGGER_SOURCES:
            row = one(source, args, Path(tmp))
            rows.append(row)
            how = (f"trigger, flip {row['flip_latency_ms']:.1f} ms + delay {row['delay_ms']:g} ms"
                   if source == "slm_flip" else
                   f"exposure line, settle {row['settle_ms']:g} ms"
                   if source == "camera_exposure" else f"settle {row['settle_ms']:g} ms")
            print(f"  {source:<15} {how:<40} {row['images']:4d} images "
                  f"({row['frames_shown']} frames)  {row['wall_s']:7.2f} s  waiting "
                  f"{row['waited_s']:6.2f} s  {row['per_image_ms']:6.1f} ms/image", flush=True)
        plain, trig, gated = rows
        # The same frames, positions and noise: a capture that saw a frame before it settled
        # (or an old one) would differ.
        diff = max(float(np.abs(np.load(Path(tmp) / "none" / r["file"])["image"]
                                - np.load(Path(tmp) / other / r["file"])["image"]).max())
                   for r in plain["records"] for other in TRIGGER_SOURCES[1:])
    same = all(abs(plain["located"][k] - row["located"][k]) <= 1e-6 * max(1.0, abs(
        plain["located"][k])) for k in ("magnification", "rotation_deg", "stage_at_slm_mm")
        for row in (trig, gated))
    print(f"  triggered / settle: {trig['wall_s'] / plain['wall_s']:.2f}x wall time, "
          f"{trig['waited_s']:.2f} s vs {plain['waited_s']:.2f} s waiting; exposure line / "
          f"settle: {gated['wall_s'] / plain['wall_s']:.2f}x, {gated['waited_s']:.2f} s waiting; "
          f"same located geometry: {same}; largest image difference {diff:.3g}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for row in rows:
        del row["records"]
    out.write_text(json.dumps({"rows": rows, "same_geometry": same,
                               "max_image_difference": diff, "machine": describe()}, indent=2))
    print(f"wrote {out}")
    return 0
