"""`nhfd bench quality`: seconds per frame against the quality the camera captures, per tier.

On the simulated bench: a randomised twin (`TrueBench.randomised`) is calibrated (the capture
and the fit, into the output's folder, reused when present), then an aberration is added to it
that the calibration never saw. For a seeded set of views of the shipped donut (with its model)
and of a second scene without a model (the guitar, refined from its exact frame), each tier's
frame is made and then captured by the twin's camera through `nhfd.calib.citl.CameraLoop` at
the target's content planes:

  network  the network's double-phase frame (donut only); its seconds are the frame's
  exact    the view's light-field inversion; seconds: the view's preparation
           (`nhfd.pipeline.refine.prepare`: the render, the reference, the focal stack) and
           the coding
  sgd      K subframes optimised through the bench model from the network's frame (donut) or
           the exact one; seconds add the network frame (donut) and the optimisation
  citl     the camera in the loop from sgd's frame; seconds add the loop's steps (each D x C x
           K captures of the twin: its simulation and stage moves, not a real camera's)
  tuned    the frame of the model tuned through the run's calibration (`nhfd model tune`, on
           training poses only: the dataset's (--tune-dataset), the model's recorded ones, or
           for a model that records none a grid over its pose envelope, never the seeded
           views scored here), K = 1 (the network emits one frame); its seconds are the
           frame's, the tuning's are recorded beside them
  sgd-learned, tuned-learned
           sgd and tuned through the learned bench (`nhfd calib learn` on the run's bench and
           calibration, captured after the aberration was added; its folder beside the
           calibration is reused when present); its capture and fit seconds are recorded

The twin: `TrueBench.randomised(--bench-seed)`, or the fields of a TOML file (--twin FILE,
`TrueBench.from_toml`).

Scored: the captured stack's PSNR and SSIM against the exact target (`stack_quality`, a gain
per colour fitted), and its speckle contrast (`speckle_contrast`). `BENCH_LEAVES_OUT` lists
the physics the twin has and the bench model does not.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nhfd.benchmarks.machine import describe
from nhfd.calib.citl import CameraLoop
from nhfd.calib.learn import RECORD_NAME, LearnPlan, camera_loop, learn
from nhfd.calib.sim import arm_twin, sim_devices, sim_panel_hw, twin_calibration
from nhfd.calibration import Calibration, fingerprint
from nhfd.cli.args import parse_wxh
from nhfd.config import Config, load_config, refine_settings
from nhfd.dataset.build import sha256_file
from nhfd.drivers.simcamera import TrueBench
from nhfd.model_info import ModelInfo, scene_mismatch
from nhfd.models.export import load_model
from nhfd.optics.quality import speckle_contrast, stack_quality
from nhfd.pipeline.frame import compute_frame
from nhfd.pipeline.refine import (
    BenchForward,
    Prepared,
    Refined,
    citl_frame,
    learned_bench_for,
    model_loss,
    prepare,
    psnr_db,
    sgd_frame,
)
from nhfd.pipeline.tune import (
    TuneResult,
    TuneSettings,
    choose_views,
    tune_model,
    tuning_poses,
)
from nhfd.pipeline.view import Scene, scene_from_file, suggested_radius
from nhfd.views import Orbit, View

REPO = Path(__file__).resolve().parents[2]
DONUT = REPO / "models" / "scenes" / "donut.ply"
DONUT_MODEL = REPO / "models" / "nhf-donut-512.onnx"
GUITAR = REPO.parent / "shared" / "data" / "scenes" / "guitar.compressed.ply"
TIERS = ("network", "exact", "sgd", "citl", "tuned", "sgd-learned", "tuned-learned")
LEARNED_TIERS = ("sgd-learned", "tuned-learned")
# Where the JSON keeps each tuned tier's tuning record.
TUNED_RECORD = {"tuned": "tuned", "tuned-learned": "tuned_learned"}
BENCH_SEED = 7
# Coma and astigmatism (rad at green, Noll 5-7) the relay gains after its calibration.
UNKNOWN_ZERNIKE_RAD = (0.5, -0.3, 0.4)
# What the twin has and the bench model (`nhfd.pipeline.refine.BenchForward`) leaves out.
BENCH_LEAVES_OUT = (
    "the pixels' fill factor and the light reflected by the gaps between them "
    "(TrueBench.fill_factor, gap_reflectance)",
    "the liquid crystal's fringing crosstalk (the phase blurred across pixel edges, "
    "crosstalk_sigma_m)",
    "unmodulated (zero-order) light, coherent with the signal (zero_order_fraction)",
    "the camera: shot, read and dark noise, pixel gain and offset patterns (PRNU, DSNU), its "
    "response curve and 12-bit quantisation, integration over its pixels",
)


def leaves_out(zernike_rad: Sequence[float]) -> list[str]:
    """`BENCH_LEAVES_OUT`, with the aberration added after the calibration when there is one."""
    if not any(zernike_rad):
        return list(BENCH_LEAVES_OUT)
    return [*BENCH_LEAVES_OUT[:3],
            "an aberration added after the calibration: Zernike coma and astigmatism (Noll "
            f"5-7) {', '.join(f'{a:+g}' for a in zernike_rad)} rad at green",
            *BENCH_LEAVES_OUT[3:]]


def _zernike(text: str) -> tuple[float, ...]:
    """--unknown-zernike's comma list (rad), or 'none'."""
    if text.strip().lower() in ("none", "0", ""):
        return ()
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--unknown-zernike {text!r}: give radians at green for Noll 5, 6, "
                         "..., comma separated (e.g. 0.5,-0.3,0.4), or none") from None
    if not all(math.isfinite(v) and abs(v) <= 10 for v in values):
        raise ValueError(f"--unknown-zernike {text!r}: each within [-10, 10] rad")
    return values
# The no-model scene's views: azimuth and elevation ranges (deg) at 1.5x the suggested distance.
NO_MODEL_AZIMUTH_DEG = (-30.0, 30.0)
NO_MODEL_ELEVATION_DEG = (5.0, 25.0)
NO_MODEL_DISTANCE = 1.5
# Views of a model's scene stay this fraction inside each end of its pose envelope.
ENVELOPE_INSET = 0.1
GOAL_SGD_OVER_NETWORK_DB = 3.0
GOAL_CITL_OVER_SGD_DB = 2.0
# The tuned tier's goals: captured PSNR at K = 1 on the model's scene (sgd's 27.35 dB on the
# calibrated twin, less 0.35), on another scene over its exact frame, at K = 4 with its speckle
# contrast, its frame's time against the network's, and the tuning's wall time.
GOAL_TUNED_K1_DB = 27.0
GOAL_TUNED_OVER_EXACT_DB = 2.5
GOAL_TUNED_K4_DB = 32.5
GOAL_TUNED_K4_SPECKLE = 0.10
GOAL_TUNED_FRAME_TIME_RATIO = 1.2
GOAL_TUNE_SECONDS = 900.0
# Through the learned bench, K = 1 on the model's scene: sgd within 0.5 dB of citl's 30.33 dB
# on the calibrated twin, the tuned network within 1 dB of it.
GOAL_SGD_LEARNED_K1_DB = 29.8
GOAL_TUNED_LEARNED_K1_DB = 29.3


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("quality", help="speed against captured quality of the frame tiers",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--views", type=int, default=2, help="seeded views per scene (default 2)")
    p.add_argument("--seed", type=int, default=0, help="the views' seed (default 0)")
    p.add_argument("--size", default="512x288", metavar="WxH",
                   help="the window (default 512x288; 1024x576 also)")
    p.add_argument("--subframes", default="1,4", metavar="K,...",
                   help="subframe counts for sgd and citl (default 1,4)")
    p.add_argument("--tiers", default=",".join(TIERS), help="tiers to run (default all)")
    p.add_argument("--iterations", type=int, default=100, help="sgd's steps (default 100)")
    p.add_argument("--citl-iterations", type=int, default=20,
                   help="citl's steps after sgd (default 20; each is D x C x K captures)")
    p.add_argument("--seconds", type=float, default=900.0,
                   help="each refinement's time budget (default 900)")
    p.add_argument("--tolerance", type=float, default=0.0,
                   help="refine.tolerance for every refinement (default 0: each runs its whole "
                        "budget, so a frame's seconds and quality are its budget's)")
    p.add_argument("--model", default=str(DONUT_MODEL), help="the donut's model")
    p.add_argument("--scene", default=str(DONUT), help="the model's scene")
    p.add_argument("--other-scene", default=str(GUITAR),
                   help="a second scene (default: the shared guitar); 'none' to skip")
    p.add_argument("--other-model", metavar="FILE",
                   help="the second scene's model: its network and tuned tiers run there too, "
                        "and the goal over its exact frame is judged (default: none, the "
                        "second scene refined without a model)")
    p.add_argument("--bench-seed", type=int, default=BENCH_SEED,
                   help=f"the twin's seed (TrueBench.randomised; default {BENCH_SEED})")
    p.add_argument("--twin", metavar="FILE",
                   help="a TOML file of TrueBench fields: the twin measured (instead of "
                        "--bench-seed's); unknown keys and values out of range are refused")
    tune_default = TuneSettings()
    p.add_argument("--tune-steps", type=int, default=tune_default.steps,
                   help=f"the tuned tier's tuning steps (default {tune_default.steps})")
    p.add_argument("--tune-seconds", type=float, default=tune_default.seconds,
                   help=f"the tuned tier's tuning time budget, s (default "
                        f"{tune_default.seconds:g})")
    p.add_argument("--tune-views", type=int, default=tune_default.views,
                   help=f"training views to tune on (default {tune_default.views}, at most the "
                        "training poses there are)")
    p.add_argument("--tune-ssim-weight", type=float, default=tune_default.ssim_weight,
                   help=f"the tuning loss's structural term's weight beside the MSE (default "
                        f"{tune_default.ssim_weight:g}; `nhfd model tune --ssim-weight`)")
    p.add_argument("--tune-dataset", metavar="DIR",
                   help="the model's dataset, for its training poses (default: the poses the "
                        "model records, else a grid over its pose envelope)")
    plan = LearnPlan()
    p.add_argument("--learn-patterns", type=int, default=plan.sgd_patterns,
                   help=f"the learned tiers' sgd training patterns (default {plan.sgd_patterns}; "
                        f"{plan.random_patterns} random and {plan.structured_patterns} "
                        "structured beside; `nhfd calib learn --patterns`)")
    p.add_argument("--learn-steps", type=int, default=plan.steps,
                   help=f"the learned bench's fit steps (default {plan.steps})")
    p.add_argument("--config", help="configuration file (default: the search order)")
    p.add_argument("--out", default="out/bench/quality.json", help="JSON file to write")
    p.add_argument("--calibration-dir", default=None,
                   help="the twin's calibration (default: quality-calibration-WxH beside --out; "
                        "reused when present)")
    p.add_argument("--plot", default="docs/figures/quality.png",
                   help="the figure to write ('' for none)")
    p.add_argument("--replot", metavar="JSON,...",
                   help="measure nothing: plot (--plot) the rows of these runs' JSON files in "
                        "one figure, a row measured in two files taken from the first; the "
                        "runs must share the machine (their seconds), size, twin and views")
    p.add_argument("--unknown-zernike", default=",".join(f"{a:g}" for a in UNKNOWN_ZERNIKE_RAD),
                   metavar="RAD,...",
                   help="the aberration added to the twin after its calibration, radians at "
                        "green for Noll 5, 6, ... (default: coma and astigmatism "
                        f"{','.join(f'{a:g}' for a in UNKNOWN_ZERNIKE_RAD)}; none: the "
                        "calibrated twin as it is)")
    p.set_defaults(handler=run)


# -- the figures (pure: tests check them) -------------------------------------------------------

def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else math.nan


# What runs plotted together must share: seconds are a machine's, PSNR a twin's and views'
# (the seeded views are checked for each scene two runs both measured).
REPLOT_SHARED = ("machine", "size", "twin")
# What a run's JSON must hold to be plotted, and each of its rows.
REPLOT_KEYS = (*REPLOT_SHARED, "window_hw", "views", "rows")
REPLOT_ROW_KEYS = ("scene", "view", "tier", "k", "seconds", "psnr_db", "ssim", "speckle",
                   "model_psnr_db")


def _views_by_scene(record: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    views: dict[str, list[dict[str, Any]]] = {}
    for v in record.get("views") or []:
        views.setdefault(v["scene"], []).append(v)
    return views


def merged_rows(records: Sequence[tuple[str, dict[str, Any]]]) -> list[dict[str, Any]]:
    """The rows of several runs' JSONs (`(name, record)`, in order) as one run's: a (scene,
    tier, K, view) measured in two files is taken from the first. A run whose machine, size,
    twin or seeded views of a scene both measured differ from the first's is refused naming
    the file and the field."""
    first_name, first = records[0]
    first_views = _views_by_scene(first)
    rows: dict[tuple[Any, ...], dict[str, Any]] = {}
    for name, record in records:
        for key in REPLOT_SHARED:
            if record.get(key) != first.get(key):
                raise ValueError(f"--replot {name}: another {key} than {first_name}'s "
                                 f"({record.get(key)!r} against {first.get(key)!r}); plot "
                                 "only runs of one machine, size, twin and views together")
        for scene, views in _views_by_scene(record).items():
            if views != first_views.get(scene, views):
                raise ValueError(f"--replot {name}: other {scene} views than {first_name}'s; "
                                 "plot only runs of one machine, size, twin and views together")
        for r in record.get("rows") or []:
            rows.setdefault((r["scene"], r["tier"], int(r["k"]), r["view"]), r)
    if not rows:
        raise ValueError(f"--replot {','.join(n for n, _ in records)}: no rows to plot")
    return list(rows.values())


def replot(files: str, plot: str) -> int:
    """`--replot`: the merged rows of `files` (comma-separated JSONs) in the figure `plot`, and
    their table printed; nothing measured."""
    if not plot:
        raise ValueError("--replot: needs --plot (the figure to write), not ''")
    names = [f.strip() for f in files.split(",") if f.strip()]
    records = []
    for name in names:
        if not Path(name).is_file():
            raise FileNotFoundError(f"--replot {name}: not found")
        try:
            record = json.loads(Path(name).read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"--replot {name}: not a bench quality JSON ({exc})") from None
        missing = [k for k in REPLOT_KEYS if not isinstance(record, dict) or k not in record]
        if not missing:
            missing = sorted({k for r in record["rows"] for k in REPLOT_ROW_KEYS if k not in r})
        if missing:
            raise ValueError(f"--replot {name}: not a bench quality JSON (no "
                             f"{', '.join(missing)})")
        records.append((name, record))
    rows = merged_rows(records)
    summary = summarise(rows)
    machine, (w, h) = records[0][1]["machine"], records[0][1]["window_hw"][::-1]
    print(table(summary))
    title = (f"captured PSNR against seconds per frame, {w} x {h}, simulated bench\n"
             f"{machine['cpu']}, {machine['cores']} cores; {len(records)} runs of nhfd bench "
             "quality")
    _plot(Path(plot), rows, summary, title)
    print(f"wrote {plot}")
    return 0


def summarise(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One entry per (scene, tier, K), in the rows' order: the views counted and the means of
    seconds per frame, captured PSNR, SSIM and speckle contrast, and the bench model's PSNR."""
    groups: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["tier"], int(r["k"])), []).append(r)
    out = []
    for (scene, tier, k), rs in groups.items():
        out.append({"scene": scene, "tier": tier, "k": k, "views": len(rs),
                    **{f"{key}_mean": _mean([float(r[key]) for r in rs])
                       for key in ("seconds", "psnr_db", "ssim", "speckle", "model_psnr_db")}})
    return out


def paired(rows: Sequence[dict[str, Any]], key: str, a: tuple[str, int], b: tuple[str, int]
           ) -> list[dict[str, Any]]:
    """`key` of tier/K `b` minus that of `a`, per (scene, view) that has both, in `a`'s row
    order: [{scene, view, a, b, diff}]."""
    index = {(r["scene"], r["view"], r["tier"], int(r["k"])): r for r in rows}
    out = []
    for r in rows:
        if (r["tier"], int(r["k"])) != a:
            continue
        other = index.get((r["scene"], r["view"], b[0], b[1]))
        if other is not None:
            out.append({"scene": r["scene"], "view": r["view"], "a": float(r[key]),
                        "b": float(other[key]), "diff": float(other[key]) - float(r[key])})
    return out


def goal_checks(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The issue's goals, each measured over the views that have both sides (mean of the paired
    differences) and met or not: sgd (K = 1) over the network's frame by at least
    GOAL_SGD_OVER_NETWORK_DB captured; citl over sgd (same K) by at least GOAL_CITL_OVER_SGD_DB
    captured; the largest K's speckle contrast below K = 1's (sgd and citl). A goal with no
    pairs is reported with `met` None."""
    ks = sorted({int(r["k"]) for r in rows if r["tier"] in ("sgd", "citl")})
    checks = []

    def check(goal: str, pairs: list[dict[str, Any]], ok: Callable[[float], bool],
              unit: str) -> None:
        mean = _mean([p["diff"] for p in pairs])
        checks.append({"goal": goal, "pairs": len(pairs), "mean_diff": mean, "unit": unit,
                       "diffs": [round(p["diff"], 3) for p in pairs],
                       "met": bool(ok(mean)) if pairs else None})

    check(f"sgd (K=1) over the network's double-phase frame >= +{GOAL_SGD_OVER_NETWORK_DB:g} dB "
          "captured", paired(rows, "psnr_db", ("network", 1), ("sgd", 1)),
          lambda d: d >= GOAL_SGD_OVER_NETWORK_DB, "dB")
    for k in ks:
        check(f"citl over sgd (K={k}) >= +{GOAL_CITL_OVER_SGD_DB:g} dB captured",
              paired(rows, "psnr_db", ("sgd", k), ("citl", k)),
              lambda d: d >= GOAL_CITL_OVER_SGD_DB, "dB")
    if len(ks) > 1 and ks[0] == 1:
        for tier in ("sgd", "citl"):
            check(f"{tier}: speckle contrast at K={ks[-1]} lower than at K=1",
                  paired(rows, "speckle", (tier, 1), (tier, ks[-1])), lambda d: d < 0, "")
    # The tuned tier: absolute goals as values ("diff" is the value itself).
    model_scene = next((r["scene"] for r in rows
                        if r["tier"] in ("network", "tuned", "tuned-learned")), None)

    def values(key: str, tier: str, k: int, on_model_scene: bool) -> list[dict[str, Any]]:
        return [{"diff": float(r[key])} for r in rows if r["tier"] == tier and int(r["k"]) == k
                and (r["scene"] == model_scene) == on_model_scene]

    check(f"tuned (K=1) captured PSNR on the model's scene >= {GOAL_TUNED_K1_DB:g} dB",
          values("psnr_db", "tuned", 1, True), lambda v: v >= GOAL_TUNED_K1_DB, "dB")
    check("tuned (K=1) SSIM >= the network's (paired)",
          paired(rows, "ssim", ("network", 1), ("tuned", 1)), lambda d: d >= 0, "")
    check(f"tuned (K=1) over the exact frame on another scene >= +{GOAL_TUNED_OVER_EXACT_DB:g} "
          "dB captured", [p for p in paired(rows, "psnr_db", ("exact", 1), ("tuned", 1))
                          if p["scene"] != model_scene],
          lambda d: d >= GOAL_TUNED_OVER_EXACT_DB, "dB")
    check(f"tuned (K=4) captured PSNR >= {GOAL_TUNED_K4_DB:g} dB",
          values("psnr_db", "tuned", 4, True), lambda v: v >= GOAL_TUNED_K4_DB, "dB")
    check(f"tuned (K=4) speckle contrast <= {GOAL_TUNED_K4_SPECKLE:g}",
          values("speckle", "tuned", 4, True), lambda v: v <= GOAL_TUNED_K4_SPECKLE, "")
    ratios = [{"scene": p["scene"], "view": p["view"], "diff": p["b"] / p["a"]}
              for p in paired(rows, "seconds", ("network", 1), ("tuned", 1)) if p["a"] > 0]
    check(f"tuned frame time / the network's (K=1) <= {GOAL_TUNED_FRAME_TIME_RATIO:g} (this "
          "run's frames; `nhfd bench pipeline` is the frame-time benchmark)", ratios,
          lambda v: v <= GOAL_TUNED_FRAME_TIME_RATIO, "x")
    tunes = {r["scene"]: float(r["tune_steps_s"]) for r in rows if r["tier"] == "tuned" and
             "tune_steps_s" in r}
    check(f"`model tune` steps' time <= {GOAL_TUNE_SECONDS:g} s (in all, resumes included, the "
          "views' preparation not; this run's steps and size)",
          [{"diff": v} for v in tunes.values()], lambda v: v <= GOAL_TUNE_SECONDS, "s")
    check("tuned (K=1) over sgd (K=1) >= 0 dB captured",
          paired(rows, "psnr_db", ("sgd", 1), ("tuned", 1)), lambda d: d >= 0, "dB")
    # Through the learned bench: absolute on the model's scene, and paired against the same
    # tier through the parametric one.
    for tier, goal_db in (("sgd-learned", GOAL_SGD_LEARNED_K1_DB),
                          ("tuned-learned", GOAL_TUNED_LEARNED_K1_DB)):
        check(f"{tier} (K=1) captured PSNR on the model's scene >= {goal_db:g} dB",
              values("psnr_db", tier, 1, True), lambda v, g=goal_db: v >= g, "dB")
        base = tier.removesuffix("-learned")
        check(f"{tier} (K=1) over {base} (K=1) >= 0 dB captured",
              paired(rows, "psnr_db", (base, 1), (tier, 1)), lambda d: d >= 0, "dB")
    return checks


def table(summary: Sequence[dict[str, Any]]) -> str:
    """The summary as a markdown table."""
    lines = ["| scene | tier | K | views | s / frame | captured PSNR (dB) | SSIM | speckle "
             "contrast | model's PSNR (dB) |", "|---|---|---|---|---|---|---|---|---|"]
    for s in summary:
        lines.append(f"| {s['scene']} | {s['tier']} | {s['k']} | {s['views']} | "
                     f"{s['seconds_mean']:.1f} | {s['psnr_db_mean']:.2f} | {s['ssim_mean']:.3f} "
                     f"| {s['speckle_mean']:.3f} | {s['model_psnr_db_mean']:.2f} |")
    return "\n".join(lines)


# -- the measurement ----------------------------------------------------------------------------

def aberrated(twin: TrueBench, zernike_rad: Sequence[float] = UNKNOWN_ZERNIKE_RAD) -> TrueBench:
    """The twin with `zernike_rad` (Noll 5, 6, ...) added to its relay's pupil."""
    z = list(twin.zernike_rad) + [0.0] * max(0, len(zernike_rad) - len(twin.zernike_rad))
    for i, a in enumerate(zernike_rad):
        z[i] += a
    return replace(twin, zernike_rad=tuple(z))


def seeded_views(rng: np.random.Generator, n: int, scene: Scene, info: ModelInfo | None,
                 window_hw: tuple[int, int]) -> list[View]:
    """`n` orbit views: inside the model's pose envelope (ENVELOPE_INSET from its ends), or
    without a model in NO_MODEL_AZIMUTH_DEG x NO_MODEL_ELEVATION_DEG at NO_MODEL_DISTANCE x
    the suggested distance."""
    env = info.pose_envelope if info is not None else None

    def inside(bounds: tuple[float, float]) -> float:
        lo, hi = bounds
        d = ENVELOPE_INSET * (hi - lo)
        return float(rng.uniform(lo + d, hi - d))

    views = []
    for _ in range(n):
        if env is not None and env.azimuth_deg and env.elevation_deg and env.distance:
            views.append(View(Orbit(inside(env.azimuth_deg), inside(env.elevation_deg),
                                    inside(env.distance))))
        else:
            az = float(rng.uniform(*NO_MODEL_AZIMUTH_DEG))
            el = float(rng.uniform(*NO_MODEL_ELEVATION_DEG))
            views.append(View(Orbit(az, el, NO_MODEL_DISTANCE
                                    * suggested_radius(scene, window_hw, az, el))))
    return views


class TimedLoop:
    """A capture that counts its calls' seconds (the camera's share of a citl frame)."""

    def __init__(self, loop: CameraLoop) -> None:
        self.loop, self.seconds = loop, 0.0

    def __call__(self, grey: np.ndarray, planes_m: Sequence[float]
                 ) -> tuple[np.ndarray, np.ndarray]:
        t0 = time.perf_counter()
        try:
            return self.loop(grey, planes_m)
        finally:
            self.seconds += time.perf_counter() - t0


def captured_quality(loop: CameraLoop, p: Prepared, grey: np.ndarray) -> dict[str, Any]:
    """The frame `grey` (`[C, Hr, Wr]` or `[K, C, Hr, Wr]`) captured at the target's planes:
    PSNR and SSIM against the target (gains fitted), per plane too, and speckle contrast."""
    g = np.asarray(grey)
    g = g[None] if g.ndim == 3 else g
    captured, seen = loop(g, p.target.planes_m)
    cap = torch.as_tensor(captured).float()
    mask = p.target.mask & torch.as_tensor(seen)
    q = stack_quality(cap, p.target.intensity, planes_m=p.target.planes_m, mask=mask,
                      fit_gains=True)
    return {"psnr_db": q.psnr_db, "ssim": q.ssim,
            "psnr_per_plane_db": [round(v, 3) for v in q.psnr_per_plane_db],
            "speckle": speckle_contrast(cap, p.target.intensity, mask),
            "seen_fraction": float(np.mean(seen))}


def _row(scene: str, view: int, tier: str, k: int, seconds: float, grey: np.ndarray,
         p: Prepared, loop: CameraLoop, refined: Refined | None = None,
         extra: dict[str, Any] | None = None) -> dict[str, Any]:
    q = captured_quality(loop, p, grey)
    row = {"scene": scene, "view": view, "tier": tier, "k": k, "seconds": seconds, **q,
           "model_psnr_db": psnr_db(model_loss(p, grey))}
    if refined is not None:
        row["refine"] = refined.report.to_json()
        row["history"] = [[i, round(t, 3), loss] for i, t, loss in refined.history]
    row.update(extra or {})
    print(f"  {scene} view {view} {tier:13s} K={k}: {seconds:7.1f} s/frame, captured "
          f"{q['psnr_db']:5.2f} dB, SSIM {q['ssim']:.3f}, speckle {q['speckle']:.3f} "
          f"(model {row['model_psnr_db']:.2f} dB)", flush=True)
    return row


def _plot(path: Path, rows: Sequence[dict[str, Any]], summary: Sequence[dict[str, Any]],
          title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    colours = {"network": "tab:grey", "tuned": "tab:purple", "exact": "tab:blue",
               "sgd": "tab:orange", "citl": "tab:green", "sgd-learned": "tab:red",
               "tuned-learned": "tab:pink"}
    markers = {1: "o", 2: "D", 4: "s", 8: "^"}
    from matplotlib.ticker import FuncFormatter, NullFormatter

    fig, axes = plt.subplots(1, len(scenes), figsize=(5.4 * len(scenes), 4.4), sharex=True,
                             squeeze=False)
    for ax, scene in zip(axes[0], scenes, strict=True):
        for r in rows:
            if r["scene"] == scene:
                ax.scatter(r["seconds"], r["psnr_db"], color=colours.get(r["tier"], "k"),
                           marker=markers.get(int(r["k"]), "v"), alpha=0.25, s=22,
                           edgecolors="none")
        for s in summary:
            if s["scene"] == scene:
                ax.scatter(s["seconds_mean"], s["psnr_db_mean"], color=colours.get(s["tier"], "k"),
                           marker=markers.get(s["k"], "v"), s=70, edgecolors="black",
                           linewidths=0.6, label=f"{s['tier']} K={s['k']}")
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("seconds per frame (log)")
        ax.set_ylabel("captured PSNR (dB)")
        ax.set_title(f"{scene} (faint: each view; bold: their mean)", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="best", framealpha=0.8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def tuned_key(scene: str, k: int) -> str:
    """Where the JSON keeps a scene's tuning record for K subframes ("donut", "donut K=4")."""
    return scene if k == 1 else f"{scene} K={k}"


def tune_for_bench(model_path: Path, scene: Scene, scene_path: Path, calibration: Calibration,
                   settings: TuneSettings, poses: Sequence[View], folder_root: Path,
                   config: Config, panel_hw: tuple[int, int]
                   ) -> tuple[TuneResult, float, Path]:
    """`nhfd model tune` of `model_path` through the run's `calibration` on `poses`, into a
    folder under `folder_root` named by what it was tuned with (a rerun with the same inputs
    resumes or reuses it): (the result, its wall seconds in this call, the folder)."""
    key = json.dumps({"model_sha256": sha256_file(model_path),
                      "calibration_sha256": fingerprint(calibration),
                      "settings": settings.key(), "steps": settings.steps,
                      "seconds": settings.seconds, "panel_hw": list(panel_hw),
                      "poses": [v.to_json() for v in poses]}, sort_keys=True)
    folder = folder_root / f"tuned-{hashlib.sha256(key.encode()).hexdigest()[:12]}"
    t0 = time.perf_counter()
    res = tune_model(model_path, scene, scene_path, calibration, folder, settings,
                     config=config, panel_hw=panel_hw, check_sizes=False, poses=poses,
                     say=lambda m: print(f"  tune: {m}", flush=True))
    if res is None:  # only with stop_after, which is not given
        raise RuntimeError(f"tuning into {folder} stopped early")
    return res, time.perf_counter() - t0, folder


def learn_for_bench(folder_root: Path, devices: Any, calibration: Calibration, config: Config,
                    plan: LearnPlan, bench_record: dict[str, Any], panel_hw: tuple[int, int]
                    ) -> tuple[Calibration, dict[str, Any]]:
    """`nhfd calib learn` on the run's bench (`devices`, armed) on top of `calibration`, into a
    folder under `folder_root` named by what it depends on (the calibration's fingerprint, the
    bench as captured, the plan, the panel): a rerun with the same inputs reuses it. (The
    calibration referencing the learned bench, its record: folder, reused or not, the capture
    and fit seconds, the captures and a real bench's expected capture time, held-out PSNR.)"""
    key = json.dumps({"calibration_sha256": fingerprint(calibration), "bench": bench_record,
                      "plan": asdict(plan), "panel_hw": list(panel_hw)}, sort_keys=True,
                     default=str)
    folder = folder_root / f"learned-{hashlib.sha256(key.encode()).hexdigest()[:12]}"
    cal_file, record_file = folder / "calibration.toml", folder / RECORD_NAME
    reused = cal_file.is_file() and record_file.is_file()
    if not reused:
        res = learn(camera_loop(devices, calibration), calibration, config, plan, folder,
                    panel_hw=panel_hw, say=lambda m: print(f"  learn: {m}", flush=True))
        for line in res.lines():
            print(f"  learn: {line}", flush=True)
    record = json.loads(record_file.read_text())
    return Calibration.load(cal_file), {
        "dir": str(folder), "reused": reused, "capture_s": record["capture_s"],
        "fit_s": record["fit_s"], "captures": plan.captures,
        "bench_capture_s": round(plan.bench_seconds(), 1), "steps": plan.steps,
        "held_out_patterns_db": record["held_out_patterns_db"],
        "held_out_plane_db": record["held_out_plane_db"]}


def through_learned(p: Prepared, calibration: Calibration) -> Prepared:
    """The prepared view with the bench model replaced by `calibration`'s learned bench (its
    weights checked for this bench's optics; a refused file raises, naming it)."""
    learned, refusal = learned_bench_for(calibration, p.encoder.settings, p.encoder.device)
    if learned is None:
        raise ValueError(f"{calibration.source or 'the calibration'}: no learned bench to "
                         f"measure the learned tiers with ({refusal or 'it references none'})")
    return replace(p, model=BenchForward(p.encoder, p.model.planes_m, learned))


def _ks(text: str) -> list[int]:
    try:
        ks = sorted({int(v) for v in text.split(",") if v.strip()})
    except ValueError:
        raise ValueError(f"--subframes {text!r}: expected a comma-separated list of integers "
                         "1..16, e.g. 1,4") from None
    if not ks or ks[0] < 1 or ks[-1] > 16:
        raise ValueError(f"--subframes {text!r}: each K must be 1..16 (refine.subframes)")
    return ks


@dataclass
class SceneRun:
    """A scene measured: its name, the scene and its file, and its model (None: refined
    without one) and the model's file."""

    name: str
    scene: Scene
    scene_path: Path
    model: Any
    model_path: Path | None


def _check_built_from(model: Any, model_path: Path, scene: Path, model_flag: str,
                      scene_flag: str) -> None:
    """Refuse a model whose metadata records another scene than the file it is measured on
    (without it, the network tiers would score a model on a scene it never saw). A model that
    records no scene passes here; the tuned tier refuses it itself."""
    hashes = scene_mismatch(model.metadata, sha256_file(scene))
    if hashes:
        raise ValueError(f"{model_flag} {model_path}: built from another scene than "
                         f"{scene_flag} {scene} ({hashes})")


def _scene_runs(args: argparse.Namespace, config: Config) -> list[SceneRun]:
    """The model's scene, then --other-scene (with --other-model's model, if given). Refused
    before anything is captured: a file not found, a model without a second scene."""
    other = None if not args.other_scene or args.other_scene.lower() == "none" \
        else Path(args.other_scene)
    if args.other_model and other is None:
        raise ValueError(f"--other-model {args.other_model}: needs --other-scene (its scene), "
                         "not 'none'")
    for flag, path in (("--other-scene", other), ("--other-model", args.other_model)):
        if path is not None and not Path(path).exists():
            raise FileNotFoundError(f"{flag} {path}: not found")
    scene_path = Path(args.scene)
    model = load_model(args.model, config)
    _check_built_from(model, Path(args.model), scene_path, "--model", "--scene")
    other_model = load_model(args.other_model, config) if args.other_model else None
    if other is not None and other_model is not None:
        _check_built_from(other_model, Path(args.other_model), other, "--other-model",
                          "--other-scene")
    runs = [SceneRun(scene_path.name.split(".")[0], scene_from_file(scene_path), scene_path,
                     model, Path(args.model))]
    if other is not None:
        runs.append(SceneRun(other.name.split(".")[0], scene_from_file(other), other,
                             other_model, Path(args.other_model) if args.other_model else None))
    return runs


def run(args: argparse.Namespace) -> int:
    if args.replot:
        return replot(args.replot, args.plot)
    t_all = time.perf_counter()
    config = load_config(args.config).config
    w, h = parse_wxh(args.size)
    window_hw = (h, w)
    ks = _ks(args.subframes)
    unknown_zernike = _zernike(args.unknown_zernike)
    tiers = [t.strip() for t in args.tiers.split(",") if t.strip()]
    unknown = [t for t in tiers if t not in TIERS]
    if unknown:
        raise ValueError(f"--tiers {args.tiers!r}: unknown {', '.join(unknown)}; one or more of "
                         f"{', '.join(TIERS)}")
    base = config.refine
    sgd_settings = {k: refine_settings(base, {"subframes": k, "iterations": args.iterations,
                                              "seconds": args.seconds,
                                              "tolerance": args.tolerance}) for k in ks}
    citl_settings = {k: refine_settings(s, {"iterations": args.citl_iterations})
                     for k, s in sgd_settings.items()}
    base = sgd_settings[ks[0]]
    tune_settings = None
    if "tuned" in tiers or "tuned-learned" in tiers:  # refused before anything is captured
        tune_settings = TuneSettings(steps=args.tune_steps, seconds=args.tune_seconds,
                                     views=args.tune_views, window_hw=window_hw,
                                     planes=base.planes, ssim_weight=args.tune_ssim_weight)
    twin = TrueBench.from_toml(args.twin) if args.twin else TrueBench.randomised(args.bench_seed)
    out = Path(args.out)
    panel_hw = sim_panel_hw(window_hw)
    cal_dir = Path(args.calibration_dir) if args.calibration_dir else \
        out.parent / f"quality-calibration-{w}x{h}"
    machine = describe()
    print(f"nhfd bench quality: {w} x {h} window on a {panel_hw[1]} x {panel_hw[0]} simulated "
          f"panel; {machine['cpu']}, {machine['cores']} cores", flush=True)
    runs = _scene_runs(args, config)  # files refused before the calibration's minutes
    t0 = time.perf_counter()
    calibration = twin_calibration(cal_dir, twin, panel_hw)
    calibration_s = time.perf_counter() - t0
    rows: list[dict[str, Any]] = []
    views_json: list[dict[str, Any]] = []
    result: dict[str, Any] = {
        "machine": machine, "size": f"{w}x{h}", "window_hw": list(window_hw),
        "panel_hw": list(panel_hw), "subframes": ks, "tiers": tiers,
        "iterations": {"sgd": args.iterations, "citl": args.citl_iterations,
                       "seconds": args.seconds, "tolerance": base.tolerance,
                       "patience": base.patience, "planes": base.planes,
                       "learning_rate_rad": base.learning_rate_rad,
                       "citl_learning_rate_rad": base.citl_learning_rate_rad},
        "twin": {"seed": None if args.twin else args.bench_seed, "file": args.twin,
                 "fields": {k: v for k, v in asdict(twin).items() if k != "phase_tables_rad"},
                 "added_after_calibration_zernike_rad": list(unknown_zernike),
                 "power_pct": 10.0},
        "bench_model_leaves_out": leaves_out(unknown_zernike),
        "calibration": {"dir": str(cal_dir), "seconds": round(calibration_s, 1)},
        "views": views_json, "rows": rows, "tuned": {},
    }
    learned_plan = None
    if any(t in tiers for t in LEARNED_TIERS):  # refused before anything is captured
        learned_plan = LearnPlan(window_hw=window_hw, sgd_patterns=args.learn_patterns,
                                 steps=args.learn_steps)
    rng = np.random.default_rng(args.seed)
    with sim_devices(aberrated(twin, unknown_zernike), panel_hw) as devices:
        learned_cal = None
        if learned_plan is not None:
            arm_twin(devices)
            print(f"learning the bench on top of the calibration into {cal_dir}", flush=True)
            learned_cal, result["learned"] = learn_for_bench(
                cal_dir, devices, calibration, config, learned_plan,
                {k: result["twin"][k] for k in ("seed", "file", "fields",
                                                "added_after_calibration_zernike_rad")},
                panel_hw)
            rec = result["learned"]
            print(f"learned bench: {rec['dir']} ({'reused' if rec['reused'] else 'learned'}; "
                  f"capture {rec['capture_s']:.0f} s, fit {rec['fit_s']:.0f} s; a real bench's "
                  f"capture about {rec['bench_capture_s'] / 60:.1f} min)", flush=True)
        learned_config = config.model_copy(update={"refine": config.refine.model_copy(
            update={"bench_model": "learned"})})
        for run_ in runs:
            name, scene, model = run_.name, run_.scene, run_.model
            info = model.info if model is not None else None
            if model is not None:  # warm-up: the renderer's kernels, the session
                warm = prepare(config, seeded_views(np.random.default_rng(99), 1, scene, info,
                                                    (64, 96))[0], scene, info=info,
                               window_hw=(64, 96), panel_hw=sim_panel_hw((64, 96)),
                               planes=base.planes)
                compute_frame(warm.view, scene, model, warm.encoder)
            # (tier, K) -> (the model, its tuning): K heads tuned on their mean per K
            tuned: dict[tuple[str, int], tuple[Any, TuneResult]] = {}
            if tune_settings is not None and model is not None:
                assert run_.model_path is not None
                # --tune-dataset is the first model's dataset
                dataset = args.tune_dataset if run_ is runs[0] else None
                poses, poses_from = tuning_poses(model.metadata, scene, info,
                                                 None if dataset is None else Path(dataset),
                                                 "--tune-dataset", tune_settings.views)
                ts = replace(tune_settings, views=min(tune_settings.views, len(poses)))
                for (tier, cal, cfg, suffix), k in itertools.product(
                        (("tuned", calibration, config, ""),
                         ("tuned-learned", learned_cal, learned_config, "-learned")), ks):
                    if tier not in tiers:
                        continue
                    assert cal is not None
                    bench = "learned" if suffix else "calibrated"
                    print(f"{name}: {tier} K={k}: tuning through the run's {bench} bench on "
                          f"{ts.views} of {len(poses)} poses ({poses_from}), {ts.steps} steps",
                          flush=True)
                    tk = replace(ts, subframes=k)
                    res, tune_s, folder = tune_for_bench(
                        run_.model_path, scene, run_.scene_path, cal, tk, poses,
                        out.parent / f"{out.stem}-tune-{name}{suffix}", cfg, panel_hw)
                    tuned[tier, k] = (load_model(res.path, config), res)
                    compute_frame(warm.view, scene, tuned[tier, k][0], warm.encoder)  # warmed
                    result.setdefault(TUNED_RECORD[tier], {})[tuned_key(name, k)] = {
                        "dir": str(folder), "poses_from": poses_from, "tune_s": round(tune_s, 1),
                        "steps": res.steps, "steps_s": round(res.seconds, 1),
                        "views": [v.to_json() for v in choose_views(poses, ts.views)],
                        "settings": tk.key(), "tuned_for": res.tuned_for}
            for i, view in enumerate(seeded_views(rng, args.views, scene, info, window_hw)):
                arm_twin(devices)  # each view's captures within an arming (tuning outlasts one)
                p = prepare(config, view, scene, info=info, calibration=calibration,
                            window_hw=window_hw, panel_hw=panel_hw, planes=base.planes)
                views_json.append({"scene": name, "view": i, **view.to_json(),
                                   "planes_m": list(p.target.planes_m)})
                print(f"{name} view {i}: {view.describe()}; exact target at "
                      f"{len(p.target.planes_m)} planes in {p.seconds:.1f} s", flush=True)
                loop = CameraLoop(devices, calibration, p.encoder)
                start, net_s = None, 0.0
                if model is not None:
                    t0 = time.perf_counter()
                    start = compute_frame(view, scene, model, p.encoder).grey
                    net_s = time.perf_counter() - t0
                    if "network" in tiers:
                        rows.append(_row(name, i, "network", 1, net_s, start, p, loop))
                p_learned = (through_learned(p, learned_cal) if learned_cal is not None
                             else None)
                for (tier, k), (net, res) in tuned.items():
                    t0 = time.perf_counter()
                    frame = compute_frame(view, scene, net, p.encoder)
                    grey = frame.grey if frame.subframes is None else frame.subframes
                    record = result[TUNED_RECORD[tier]][tuned_key(name, k)]
                    rows.append(_row(name, i, tier, k, time.perf_counter() - t0, grey,
                                     p if tier == "tuned" else p_learned, loop,
                                     extra={"tune_s": record["tune_s"],
                                            "tune_steps_s": round(res.seconds, 3),
                                            "tune_steps": res.steps}))
                if "exact" in tiers:
                    rows.append(_row(name, i, "exact", 1, p.seconds, p.exact_grey, p, loop))
                for k in ks:
                    if p_learned is not None and "sgd-learned" in tiers:
                        t0 = time.perf_counter()
                        sgd = sgd_frame(p_learned, sgd_settings[k], start=start, seed=i)
                        rows.append(_row(name, i, "sgd-learned", k,
                                         p.seconds + net_s + time.perf_counter() - t0,
                                         sgd.grey, p_learned, loop, sgd))
                    if "sgd" not in tiers and "citl" not in tiers:
                        continue
                    t0 = time.perf_counter()
                    sgd = sgd_frame(p, sgd_settings[k], start=start, seed=i)
                    sgd_s = p.seconds + net_s + time.perf_counter() - t0
                    if "sgd" in tiers:
                        rows.append(_row(name, i, "sgd", k, sgd_s, sgd.grey, p, loop, sgd))
                    if "citl" in tiers:
                        arm_twin(devices)
                        timed = TimedLoop(loop)
                        before = loop.captures
                        t0 = time.perf_counter()
                        citl = citl_frame(p, sgd, citl_settings[k], timed, seed=i)
                        citl_s = time.perf_counter() - t0
                        rows.append(_row(name, i, "citl", k, sgd_s + citl_s, citl.grey, p,
                                         loop, citl, {"captures": loop.captures - before,
                                                      "capture_s": timed.seconds,
                                                      "sgd_s": sgd_s}))
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_text(json.dumps(result, indent=2))  # what is done so far
    summary = summarise(rows)
    goals = goal_checks(rows)
    result.update(summary=summary, goals=goals,
                  seconds_total=round(time.perf_counter() - t_all, 1))
    out.write_text(json.dumps(result, indent=2))
    print()
    print(f"{machine['cpu']}, {machine['cores']} cores; window {w} x {h}; "
          f"{args.views} view(s) per scene")
    print(table(summary))
    print()
    for g in goals:
        verdict = {True: "met", False: "not met", None: "not measured"}[g["met"]]
        print(f"- {g['goal']}: mean {g['mean_diff']:+.3f}{' ' + g['unit'] if g['unit'] else ''}"
              f" over {g['pairs']} view(s): {verdict}")
    print("The bench model leaves out: " + "; ".join(leaves_out(unknown_zernike)))
    if args.plot:
        gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
        title = (f"captured PSNR against seconds per frame, {w} x {h}, simulated bench\n"
                 f"{machine['cpu']}, {machine['cores']} cores, {gpu} (frames on the CPU)")
        _plot(Path(args.plot), rows, summary, title)
        print(f"wrote {args.plot}")
    print(f"wrote {out} in {result['seconds_total']:.0f} s")
    return 0
