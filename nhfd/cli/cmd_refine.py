"""`nhfd refine`: one view's frame above the network's, offline (docs/refine.md).

    exact   the view's own light-field inversion, double-phase coded (no network)
    sgd     the SLM phase optimised through the calibrated bench model, from the network's frame
            (with --model) or the exact one
    citl    sgd, then the same loop with the camera in it: here on the simulated bench only
            (--sim), which this command calibrates (into OUT/calibration, reused) and whose
            simulated laser it arms itself at --power

A scene without a model is seen through a 40-degree camera with the configured optics, its
depths mapped onto the volume from this view's own content, its brightness scaled as a
dataset of this one view would be. Writes OUT/frame.npy (grey [K, 3, Hr, Wr]: K subframes of
the frame's region), OUT/frame_k.png (each subframe's region, R G B), OUT/report.json and
OUT/report.md.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from nhfd.calib.citl import CameraLoop
from nhfd.calib.sim import (
    SIM_BENCH_SEED,
    SIM_POWER_PCT,
    sim_devices,
    sim_panel_hw,
    twin_calibration,
)
from nhfd.calibration import Calibration, CalibrationStore
from nhfd.cli.args import parse_wxh
from nhfd.config import load_config, refine_settings
from nhfd.drivers.simcamera import TrueBench
from nhfd.models.export import load_model
from nhfd.pipeline.frame import compute_frame
from nhfd.pipeline.refine import (
    Refined,
    citl_frame,
    exact_frame,
    prepare,
    psnr_db,
    sgd_frame,
)
from nhfd.pipeline.view import NO_MODEL_VIEW, default_view, scene_from_file
from nhfd.views import Orbit, View

DEFAULT_SIZE = "512x288"
DEFAULT_OUT = "out/refine"
TIERS = ("exact", "sgd", "citl")
# The settings the command line overrides, each checked through RefineSettings.
OVERRIDES = ("iterations", "seconds", "subframes", "planes")
# A progress line every this many iterations (citl: every iteration, each is D x C x K
# captures).
PROGRESS_EVERY = 10


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("refine", help="a view's frame above the network's: exact, sgd or citl",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", required=True, metavar="PATH", help="the splat scene")
    p.add_argument("--model", metavar="ONNX",
                   help="the scene's model (sgd then starts from its frame); without one the "
                        "scene is refined from its exact frame")
    p.add_argument("--quality", choices=TIERS, default="sgd",
                   help="the tier (default sgd); citl needs --sim")
    p.add_argument("--view", metavar="AZ,EL,R",
                   help="orbit about the scene centre: azimuth and elevation (deg), radius "
                        "(scene units); default: the middle of the model's pose envelope, or "
                        f"without a model azimuth {NO_MODEL_VIEW[0]:g}, elevation "
                        f"{NO_MODEL_VIEW[1]:g} at {NO_MODEL_VIEW[2]:g}x the distance "
                        "`nhfd scene info` suggests")
    p.add_argument("--size", default=DEFAULT_SIZE, metavar="WxH",
                   help=f"the window (default {DEFAULT_SIZE})")
    p.add_argument("--iterations", type=int, help="refine.iterations for this run")
    p.add_argument("--seconds", type=float, help="refine.seconds for this run")
    p.add_argument("--subframes", type=int, help="refine.subframes (K) for this run")
    p.add_argument("--planes", type=int, help="refine.planes for this run")
    p.add_argument("--sim", action="store_true",
                   help="the simulated bench (required for citl): a randomised twin, calibrated "
                        "first into OUT/calibration (reused when present); being simulated, "
                        "its laser is armed by this command at --power")
    p.add_argument("--power", type=float, default=SIM_POWER_PCT, metavar="PCT",
                   help=f"--sim: each colour's laser power in %% (default {SIM_POWER_PCT:g}, "
                        "the simulated laser's cap)")
    p.add_argument("--sim-seed", type=int, default=SIM_BENCH_SEED,
                   help=f"--sim: the twin's seed (default {SIM_BENCH_SEED})")
    p.add_argument("--config", help="configuration file (default: the search order)")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    p.set_defaults(handler=run)


# -- checking what was asked -------------------------------------------------------------------

def parse_view(text: str) -> View:
    """'AZ,EL,R' -> an orbit view (ValueError naming --view and the form)."""
    parts = text.split(",")
    try:
        az, el, r = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"--view {text!r}: expected AZ,EL,R (azimuth and elevation in degrees, "
                         "radius in scene units), e.g. 10,20,0.7") from None
    return View(Orbit(az, el, r))


# -- the command ------------------------------------------------------------------------------

class Progress:
    """Prints one line every `every` iterations (and the first): tier, iteration, seconds and
    the PSNR the loss stands for."""

    def __init__(self, label: str, every: int) -> None:
        self.label, self.every = label, max(1, every)

    def __call__(self, it: int, seconds: float, loss: float) -> None:
        if it % self.every == 0:
            print(f"  {self.label} iteration {it:4d}  {seconds:7.1f} s  "
                  f"PSNR {psnr_db(loss):5.1f} dB", flush=True)


def _check_citl(args: argparse.Namespace) -> None:
    if args.quality == "citl" and not args.sim:
        raise ValueError(
            "--quality citl needs --sim: nhfd refine drives only the simulated bench (whose "
            "laser it arms itself). A real bench's camera and lasers belong to the daemon, "
            "where citl is a view's quality (a person arms the lasers, nhfctl laser arm, sets "
            "each colour's power, then nhfctl set-view ... --quality citl); the daemon does not "
            "serve it yet, so for a real bench refine with --quality sgd here")
    if args.sim and not 0 < args.power <= 100:
        raise ValueError(f"--power {args.power:g}: must be in (0, 100] %")


def _write_pngs(out: Path, grey: np.ndarray) -> list[str]:
    names = []
    for k, g in enumerate(grey):
        name = f"frame_{k}.png"
        Image.fromarray(np.ascontiguousarray(np.asarray(g).transpose(1, 2, 0))).save(out / name)
        names.append(name)
    return names


def _report_md(report: dict[str, Any]) -> str:
    rows = ["| stage | iterations | seconds | PSNR start (dB) | PSNR best (dB) | stop |",
            "|---|---|---|---|---|---|"]
    for st in report["stages"]:
        rows.append(f"| {st['tier']} | {st['iterations']} | {st['seconds']:.1f} | "
                    f"{st['start_psnr_db']:.2f} | {st['psnr_db']:.2f} | {st['stop']} |")
    t = report["times_s"]
    v = report["view"]
    view = (f"orbit azimuth {v['azimuth_deg']:.1f} deg, elevation {v['elevation_deg']:.1f} "
            f"deg, radius {v['radius']:.3g}" if v.get("kind") == "orbit" else json.dumps(v))
    return "\n".join([
        f"# nhfd refine: {report['tier']}",
        "",
        f"- scene `{report['scene']}`, model `{report['model'] or 'none'}`",
        f"- view: {view}",
        f"- window {report['window_hw'][1]} x {report['window_hw'][0]}, panel "
        f"{report['panel_hw'][1]} x {report['panel_hw'][0]}, {report['subframes']} subframe(s)",
        "- planes (mm from the reference plane): "
        + ", ".join(f"{z * 1e3:+.3f}" for z in report["planes_m"]),
        f"- PSNR is the {'camera' if report['tier'] == 'citl' else 'bench model'}'s estimate "
        "against the exact target",
        "",
        *rows,
        "",
        f"Times: setup and exact target {t['prepare_s']:.1f} s, network frame "
        f"{t['network_s']:.1f} s, sgd {t['sgd_s']:.1f} s, citl {t['citl_s']:.1f} s; total "
        f"{t['total_s']:.1f} s.",
        "",
    ])


def run(args: argparse.Namespace) -> int:
    # Everything that can be refused is checked before anything is loaded or written.
    loaded = load_config(args.config)
    config = loaded.config
    settings = refine_settings(config.refine, {k: getattr(args, k) for k in OVERRIDES})
    _check_citl(args)
    w, h = parse_wxh(args.size)
    window_hw = (h, w)
    view = parse_view(args.view) if args.view else None
    scene_path = Path(args.scene)
    if not scene_path.exists():
        raise FileNotFoundError(f"--scene {scene_path}: not found")
    if args.model and not Path(args.model).exists():
        raise FileNotFoundError(f"--model {args.model}: not found")
    t_start = time.perf_counter()
    model = load_model(args.model, config) if args.model else None
    scene = scene_from_file(scene_path)
    info = model.info if model is not None else None
    view = view or default_view(scene, info, window_hw)
    out = Path(args.out)
    print(f"nhfd refine: {args.quality} of {scene_path.name}"
          f"{' with ' + Path(args.model).name if model else ' (no model)'}, "
          f"view: {view.describe()}, {w} x {h}, K = {settings.subframes}", flush=True)
    calibration: Calibration | None = None
    twin: TrueBench | None = None
    if args.sim:
        panel_hw = sim_panel_hw(window_hw)
        twin = TrueBench.randomised(args.sim_seed)
        calibration = twin_calibration(out / "calibration", twin, panel_hw)
    else:
        panel_hw = (config.slm.height_px, config.slm.width_px)
        calibration = CalibrationStore.of(config).active()
    p = prepare(config, view, scene, info=info, calibration=calibration, window_hw=window_hw,
                panel_hw=panel_hw, planes=settings.planes)
    print(f"  exact target at {len(p.target.planes_m)} plane(s) in {p.seconds:.1f} s", flush=True)
    times = {"prepare_s": p.seconds, "network_s": 0.0, "sgd_s": 0.0, "citl_s": 0.0}
    stages: list[Refined] = []
    start = None
    if args.quality == "exact":
        stages.append(exact_frame(p))
    else:
        if model is not None:
            t0 = time.perf_counter()
            start = compute_frame(view, scene, model, p.encoder).grey
            times["network_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        sgd = sgd_frame(p, settings, start=start, progress=Progress("sgd ", PROGRESS_EVERY))
        times["sgd_s"] = time.perf_counter() - t0
        stages.append(sgd)
        if args.quality == "citl":
            assert twin is not None and calibration is not None
            t0 = time.perf_counter()
            with sim_devices(twin, panel_hw, power_pct=args.power) as devices:
                loop = CameraLoop(devices, calibration, p.encoder)
                stages.append(citl_frame(p, sgd, settings, loop, progress=Progress("citl", 1)))
                captures = loop.captures
            times["citl_s"] = time.perf_counter() - t0
    best = stages[-1]
    times["total_s"] = time.perf_counter() - t_start
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "frame.npy", best.grey)
    pngs = _write_pngs(out, best.grey)
    r = p.encoder.region
    report: dict[str, Any] = {
        "tier": args.quality,
        "scene": str(scene_path),
        "model": str(args.model) if model is not None else None,
        "start": "network" if start is not None else "exact",
        "view": view.to_json(),
        "window_hw": list(window_hw),
        "panel_hw": list(panel_hw),
        "region": {"top": r.top, "left": r.left, "height": r.height, "width": r.width,
                   "window_top": r.window_top, "window_left": r.window_left},
        "subframes": int(best.grey.shape[0]),
        "planes_m": list(p.target.planes_m),
        "report": best.report.to_json(),
        "stages": [s.report.to_json() for s in stages],
        "history": {s.report.tier: [[i, round(t, 4), loss] for i, t, loss in s.history]
                    for s in stages},
        "settings": settings.model_dump(),
        "times_s": {k: round(v, 3) for k, v in times.items()},
        "calibration": calibration.label if calibration is not None else None,
        "files": ["frame.npy", *pngs, "report.json", "report.md"],
    }
    if args.sim:
        report["sim"] = {"seed": args.sim_seed, "power_pct": args.power,
                         "calibration": str(out / "calibration" / "calibration.toml"),
                         **({"captures": captures} if args.quality == "citl" else {})}
    (out / "report.json").write_text(json.dumps(report, indent=2))
    (out / "report.md").write_text(_report_md(report))
    for st in stages:
        rep = st.report
        judge = "the camera's" if rep.tier == "citl" else "the bench model's"
        print(f"{rep.tier}: PSNR {rep.start_psnr_db:.2f} -> {rep.psnr_db:.2f} dB ({judge} "
              f"estimate), {rep.iterations} iterations, stop: {rep.stop}", flush=True)
    print(f"{times['total_s']:.1f} s in all")
    rep = best.report
    print(f"wrote {out / 'frame.npy'} {list(best.grey.shape)}, {', '.join(pngs)}, "
          f"report.json, report.md")
    if not math.isfinite(rep.psnr_db):
        return 1
    return 0
