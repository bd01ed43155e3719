"""`nhfd calib capture|fit|report`: calibrate the bench against the simulation (issue 8).

`capture` drives the simulated twins directly (a `TrueBench`, optionally randomised with
`--sim-seed`) through `nhfd.calib.capture.SimBenchIO`; driving a running daemon is not wired
yet. `fit` writes calibration.toml; `report` writes PNGs next to the capture.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nhfd.cli.args import parse_wxh


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calib", help="capture focal stacks and fit the bench model",
                       description=__doc__)
    cmds = p.add_subparsers(dest="calib_command", metavar="COMMAND", required=True)
    c = cmds.add_parser("capture", help="capture (or resume) a calibration data set")
    c.add_argument("--out", required=True, help="capture directory")
    c.add_argument("--panel", default="128x128", help="SLM window WxH shown (default 128x128)")
    c.add_argument("--sim-seed", type=int, default=None,
                   help="randomise the simulated bench with this seed (default: TrueBench())")
    c.add_argument("--stage-center", type=float, default=10.0, help="stage mm (default 10)")
    c.add_argument("--stage-range", type=float, default=2.5, help="+- mm coarse sweep")
    c.add_argument("--fine-steps", type=int, default=13, help="fine sweep positions")
    c.add_argument("--force", action="store_true", help="overwrite an existing capture")
    c.set_defaults(handler=run_capture)
    f = cmds.add_parser("fit", help="fit the bench model to a capture")
    f.add_argument("dir", help="capture directory")
    f.add_argument("-o", "--out", default="calibration.toml", help="calibration file")
    f.set_defaults(handler=run_fit)
    r = cmds.add_parser("report", help="PNGs of a capture against its fit")
    r.add_argument("dir", help="capture directory")
    r.add_argument("--calibration", help="calibration.toml (default: fit now)")
    r.add_argument("-o", "--out", help="PNG folder (default DIR/report)")
    r.set_defaults(handler=run_report)


def _say(msg: str) -> None:
    print(msg, file=sys.stderr)


def run_capture(args: argparse.Namespace) -> int:
    from nhfd.calib.capture import CaptureError, CapturePlan, SimBenchIO, capture
    from nhfd.calib.patterns import PatternSpec
    from nhfd.drivers.simcamera import TrueBench

    w, h = parse_wxh(args.panel)
    bench = TrueBench.randomised(args.sim_seed) if args.sim_seed is not None else TrueBench()
    spec = PatternSpec((h, w), bench.pitch_m, bench.wavelengths_m)
    plan = CapturePlan(stage_center_mm=args.stage_center, stage_range_mm=args.stage_range,
                       fine_steps=args.fine_steps, camera_pitch_m=bench.camera_pitch_m)
    try:
        capture(args.out, SimBenchIO(bench, (h, w)), spec, plan, force=args.force,
                progress=_say)
    except CaptureError as exc:
        raise ValueError(str(exc)) from None
    return 0


def run_fit(args: argparse.Namespace) -> int:
    from nhfd.calib.fit import fit_capture

    cal = fit_capture(args.dir, progress=_say)
    path = cal.save(Path(args.out))
    print(f"wrote {path}")
    return 0


def run_report(args: argparse.Namespace) -> int:
    from nhfd.calib.calibration import Calibration
    from nhfd.calib.report import write_report

    cal = Calibration.load(args.calibration) if args.calibration else None
    for path in write_report(args.dir, cal, args.out):
        print(path)
    return 0
