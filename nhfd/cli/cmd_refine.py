"""`nhfd refine`: one view's frame above the network's, offline (docs/refine.md).

    exact   the view's own light-field inversion, double-phase coded (no network)
    sgd     the SLM phase optimised through the calibrated bench model, from the network's frame
            (with --model) or the exact one
    citl    sgd, then the same loop with the camera in it: here on the simulated bench only
            (--sim), which this command calibrates (into OUT/calibration, reused) and whose
            simulated laser it arms itself at --power

A scene without a model is refined through `scene_info` (the configured optics, a 40-degree
camera, the view's own depth mapping) and `amplitude_scale_of` (the dataset's rule for one
field). Writes OUT/frame.npy (grey [K, 3, Hr, Wr]: K subframes of the frame's region),
OUT/frame_k.png (each subframe's region, R G B), OUT/report.json and OUT/report.md.

The pieces (`prepare`, `exact_frame`, `sgd_frame`, `citl_frame`, `twin_calibration`,
`sim_devices`) are what `nhfd bench quality` measures with.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from pydantic import ValidationError

from nhfd.calib.capture import CapturePlan, SimBenchIO, capture
from nhfd.calib.citl import CameraLoop
from nhfd.calib.fit import fit_capture
from nhfd.calib.patterns import PatternSpec
from nhfd.calibration import Calibration, CalibrationFileError, active_calibration
from nhfd.cli.args import parse_wxh
from nhfd.config import Config, RefineSettings, load_config
from nhfd.device_settings import COLOURS
from nhfd.drivers.factory import BenchDevices, make_bench
from nhfd.drivers.simcamera import TrueBench
from nhfd.model_info import ModelInfo
from nhfd.models.export import load_model
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.frame import compute_frame
from nhfd.pipeline.refine import (
    SCENE_FOV_X_DEG,
    BenchForward,
    Capture,
    Refined,
    RefineReport,
    Target,
    amplitude_scale_of,
    exact_reference,
    grey_phase,
    psnr_db,
    refine,
    scene_info,
    stack_loss,
    target_from_field,
    view_planes,
)
from nhfd.pipeline.settings import frame_settings
from nhfd.pipeline.view import Scene, scene_frame
from nhfd.scene.io import read_scene
from nhfd.scene.suggest import suggest_camera
from nhfd.views import Orbit, View

DEFAULT_SIZE = "512x288"
DEFAULT_OUT = "out/refine"
TIERS = ("exact", "sgd", "citl")
# The settings the command line overrides, each checked through RefineSettings.
OVERRIDES = ("iterations", "seconds", "subframes", "planes")
# A scene without a model: an orbit at this azimuth and elevation (deg), at this multiple of
# the distance `nhfd scene info` suggests (its framing fills 80% of the window: a little
# farther keeps the whole object inside the window's edge, which the loss leaves out).
NO_MODEL_VIEW = (0.0, 15.0, 1.5)
# The simulated bench (--sim): the panel is the window plus this margin on each side (the
# twin simulates the whole panel, so every camera capture costs in proportion to it; the
# frame's region reaches 24 px beyond the window at the packaged optics).
SIM_PANEL_MARGIN_PX = 64
SIM_BENCH_SEED = 7  # TrueBench.randomised: phase sign -1, no mirror, M ~ 1.12
SIM_POWER_PCT = 10.0  # the simulated laser's cap
SIM_ARM_S = 900.0  # the longest arming the laser accepts
# A progress line every this many iterations (citl: every iteration, each is D x C x K
# captures).
PROGRESS_EVERY = 10


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("refine", help="a view's frame above the network's: exact, sgd or citl",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", required=True, metavar="PATH", help="the splat scene")
    p.add_argument("--model", metavar="ONNX",
                   help="the scene's model (sgd then starts from its frame); without one the "
                        "scene is refined through scene_info, from its exact frame")
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

def _bounds(name: str) -> str:
    """RefineSettings' allowed range of `name`, e.g. "1 <= iterations <= 100000"."""
    lo = hi = ""
    for m in RefineSettings.model_fields[name].metadata:
        for attr, sym in (("ge", "<="), ("gt", "<")):
            if getattr(m, attr, None) is not None:
                lo = f"{getattr(m, attr):g} {sym} "
        for attr, sym in (("le", "<="), ("lt", "<")):
            if getattr(m, attr, None) is not None:
                hi = f" {sym} {getattr(m, attr):g}"
    return f"{lo}{name}{hi}"


def refine_settings(base: RefineSettings, overrides: dict[str, Any]) -> RefineSettings:
    """`base` (the configuration's `[refine]`) with `overrides` (None: keep), validated as
    RefineSettings: a ValueError naming `refine.<key>`, the value and the allowed range."""
    given = {k: v for k, v in overrides.items() if v is not None}
    try:
        return RefineSettings.model_validate({**base.model_dump(), **given})
    except ValidationError as exc:
        problems = []
        for e in exc.errors():
            key = ".".join(str(p) for p in e["loc"])
            allowed = _bounds(key) if key in RefineSettings.model_fields else ""
            problems.append(f"refine.{key} = {e.get('input')!r}: "
                            + (f"must be {allowed}" if allowed else str(e["msg"])))
        raise ValueError("; ".join(problems)) from None


def parse_view(text: str) -> View:
    """'AZ,EL,R' -> an orbit view (ValueError naming --view and the form)."""
    parts = text.split(",")
    try:
        az, el, r = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"--view {text!r}: expected AZ,EL,R (azimuth and elevation in degrees, "
                         "radius in scene units), e.g. 10,20,0.7") from None
    return View(Orbit(az, el, r))


# -- the scene, the view and the frame settings -------------------------------------------------

def load_scene(path: str | Path) -> Scene:
    """A splat scene as frames use it (its Gaussians and the frame orbit views are about)."""
    load = read_scene(path)
    return Scene(load.gaussians, scene_frame(load.gaussians, str(path)))


def suggested_radius(scene: Scene, window_hw: tuple[int, int], azimuth_deg: float,
                     elevation_deg: float) -> float:
    """The orbit radius at which `nhfd scene info`'s camera frames the scene in the window
    (a SCENE_FOV_X_DEG camera: `scene_info`'s)."""
    h, w = window_hw
    cam = suggest_camera(scene.gaussians, w, h, scene.frame.up, fov_x_deg=SCENE_FOV_X_DEG,
                         azimuth_deg=azimuth_deg, elevation_deg=elevation_deg)
    position = -cam.R.T @ cam.t
    return float(np.linalg.norm(position - np.asarray(scene.frame.center)))


def default_view(scene: Scene, info: ModelInfo | None, window_hw: tuple[int, int]) -> View:
    """The middle of the model's pose envelope; without a model (or an envelope), an orbit at
    NO_MODEL_VIEW."""
    env = info.pose_envelope if info is not None else None
    if env is not None and env.azimuth_deg and env.elevation_deg and env.distance:
        return View(Orbit(sum(env.azimuth_deg) / 2, sum(env.elevation_deg) / 2,
                          sum(env.distance) / 2))
    az, el, k = NO_MODEL_VIEW
    return View(Orbit(az, el, k * suggested_radius(scene, window_hw, az, el)))


def sim_panel_hw(window_hw: tuple[int, int], margin_px: int = SIM_PANEL_MARGIN_PX
                 ) -> tuple[int, int]:
    """The simulated bench's panel: the window plus `margin_px` on each side."""
    return window_hw[0] + 2 * margin_px, window_hw[1] + 2 * margin_px


@dataclass
class Prepared:
    """A view ready to refine: the model's (or `scene_info`'s) info, the encoder (its amplitude
    scale the model's, or `amplitude_scale_of` the view's field), the view's exact reference
    field `[C, h, w]`, the target at its content planes, the bench model at those planes, the
    exact frame `[C, Hr, Wr]` uint8, and the seconds all that took."""

    view: View
    info: ModelInfo
    encoder: Encoder
    reference: torch.Tensor
    target: Target
    model: BenchForward
    exact_grey: np.ndarray
    seconds: float


def prepare(config: Config, scene: Scene, view: View, window_hw: tuple[int, int],
            panel_hw: tuple[int, int], settings: RefineSettings, *,
            calibration: Calibration | None = None, info: ModelInfo | None = None) -> Prepared:
    """`refine_view`'s steps up to the optimisation, kept apart so that the tiers of one view
    share them (and the time they took is counted once per tier): the encoder for `info` (a
    model's; None: `scene_info` and the view's own amplitude scale) on a `panel_hw` panel, the
    view's exact reference at `settings.planes` content planes, the target and the exact
    frame. `config`: the whole configuration (frame settings join [slm], [coding], [optics])."""
    if window_hw[0] > panel_hw[0] or window_hw[1] > panel_hw[1]:
        raise ValueError(f"--size {window_hw[1]}x{window_hw[0]} does not fit the panel "
                         f"{panel_hw[1]} x {panel_hw[0]} (slm.width_px x height_px)")
    t0 = time.perf_counter()
    own_scale = info is None
    if info is None:
        info = scene_info(config.optics, config.slm, view, scene, window_hw)
    base = frame_settings(config, info, calibration, refocus_m=view.refocus_m)
    s = dataclasses.replace(base, panel_hw=tuple(panel_hw), window_hw=tuple(window_hw))
    encoder = Encoder(s)
    reference = exact_reference(view, scene, info, window_hw)
    if own_scale:  # no model: the amplitude scale a dataset of this one view would have
        scale = amplitude_scale_of(reference, encoder)
        info = dataclasses.replace(info, amplitude_scale=scale)
        encoder = Encoder(dataclasses.replace(s, amplitude_scale=scale))
    planes = view_planes(view, scene, info, window_hw, settings.planes)
    target = target_from_field(reference, planes, encoder)
    with torch.no_grad():
        exact_grey, _ = encoder.code(encoder.to_slm(reference))
    return Prepared(view, info, encoder, reference, target, BenchForward(encoder, planes),
                    exact_grey, time.perf_counter() - t0)


def model_loss(p: Prepared, grey: np.ndarray) -> float:
    """The bench model's loss of a frame `[C, Hr, Wr]` or `[K, C, Hr, Wr]` against the target."""
    g = np.asarray(grey)
    g = g[None] if g.ndim == 3 else g
    with torch.no_grad():
        return float(stack_loss(p.model(grey_phase(g, p.encoder)).mean(0), p.target))


def exact_frame(p: Prepared) -> Refined:
    """The exact tier: the reference's double-phase frame, scored by the bench model (as
    `refine_view` reports it)."""
    loss = model_loss(p, p.exact_grey)
    report = RefineReport("exact", 0, p.seconds, loss, psnr_db(loss), psnr_db(loss), "exact")
    return Refined(p.exact_grey[None], report)


def sgd_frame(p: Prepared, settings: RefineSettings, *, start: np.ndarray | None = None,
              progress: Callable[[int, float, float], None] | None = None, seed: int = 0
              ) -> Refined:
    """The sgd tier from `start` (the network's frame `[C, Hr, Wr]`) or the exact frame."""
    first = p.exact_grey if start is None else start
    return refine(first, p.target, p.model, settings, seed=seed, progress=progress)


def citl_frame(p: Prepared, sgd: Refined, settings: RefineSettings, loop: Capture, *,
               progress: Callable[[int, float, float], None] | None = None, seed: int = 0
               ) -> Refined:
    """The citl tier: the camera's loop from sgd's frame (`refine_view`'s last step)."""
    return refine(sgd.grey, p.target, p.model, settings, capture=loop, seed=seed,
                  progress=progress)


# -- the simulated bench ----------------------------------------------------------------------

def _twin_key(twin: TrueBench, panel_hw: tuple[int, int]) -> str:
    return hashlib.sha256(f"{twin!r} {tuple(panel_hw)}".encode()).hexdigest()[:16]


def twin_calibration(folder: Path, twin: TrueBench, panel_hw: tuple[int, int], *,
                     say: Callable[[str], None] = print) -> Calibration:
    """The twin's calibration on a `panel_hw` panel: `folder`/calibration.toml when it was
    fitted for this twin and panel (`twin.json` says so), else a capture (the small pattern
    set the calibration tests use: 3 reference and 13 test grey levels) into `folder`/capture
    and its fit (minutes at 416 x 640 on 2 cores)."""
    folder = Path(folder)
    toml, stamp = folder / "calibration.toml", folder / "twin.json"
    key = _twin_key(twin, panel_hw)
    if toml.is_file() and stamp.is_file():
        try:
            ok = json.loads(stamp.read_text()).get("key") == key
        except ValueError:
            ok = False
        if ok:
            try:
                cal = Calibration.load(toml)
            except CalibrationFileError as exc:
                say(f"calibration {toml}: {exc}; capturing again")
            else:
                say(f"calibration {toml} (reused: this twin and panel)")
                return cal
    folder.mkdir(parents=True, exist_ok=True)
    stamp.unlink(missing_ok=True)
    t0 = time.perf_counter()
    say(f"calibrating the simulated bench ({panel_hw[1]} x {panel_hw[0]} panel) into {folder}")
    spec = PatternSpec(tuple(panel_hw), twin.pitch_m, twin.wavelengths_m, refs=(0, 96, 176),
                       tests=tuple(range(8, 256, 20)))
    plan = CapturePlan(stage_center_mm=10.0, stage_range_mm=2.5, coarse_step_mm=0.5,
                       fine_steps=13, camera_pitch_m=twin.camera_pitch_m)
    capture(folder / "capture", SimBenchIO(twin, tuple(panel_hw), noise_seed=3), spec, plan,
            force=True)
    cal = fit_capture(folder / "capture")
    cal.save(toml)
    stamp.write_text(json.dumps({"key": key, "panel_hw": list(panel_hw),
                                 "seconds": round(time.perf_counter() - t0, 1)}))
    say(f"calibrated in {time.perf_counter() - t0:.0f} s: {toml}")
    return Calibration.load(toml)


@contextmanager
def sim_devices(twin: TrueBench, panel_hw: tuple[int, int], *, power_pct: float = SIM_POWER_PCT
                ) -> Iterator[BenchDevices]:
    """The simulated bench over `twin` (the packaged default devices: all simulated, a mono
    camera on the sensor region that holds the panel's image, as in its calibration), its
    laser armed (`SIM_ARM_S`; `arm_twin` re-arms) with every colour at `power_pct`. Closing
    switches every laser off."""
    d = Config().devices
    d = d.model_copy(update={"camera_settings": d.camera_settings.model_copy(
        update={"channels": "mono"})})
    with make_bench(d, panel_hw[1], panel_hw[0], bench=twin,
                    roi=twin.roi_for_panel(panel_hw)) as devices:
        arm_twin(devices)
        for name in COLOURS:
            devices.laser.set_power(name, power_pct)
        yield devices


def arm_twin(devices: BenchDevices) -> None:
    """Arm the simulated laser for SIM_ARM_S (before each citl frame: a long one may outlast
    an arming)."""
    devices.laser.arm(SIM_ARM_S)


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
        f"- scene `{report['scene']}`, model `{report['model'] or 'none (scene_info)'}`",
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
    scene = load_scene(scene_path)
    info = model.info if model is not None else None
    view = view or default_view(scene, info, window_hw)
    out = Path(args.out)
    print(f"nhfd refine: {args.quality} of {scene_path.name}"
          f"{' with ' + Path(args.model).name if model else ' (no model: scene_info)'}, "
          f"view {view.to_json()}, {w} x {h}, K = {settings.subframes}", flush=True)
    calibration: Calibration | None = None
    twin: TrueBench | None = None
    if args.sim:
        panel_hw = sim_panel_hw(window_hw)
        twin = TrueBench.randomised(args.sim_seed)
        calibration = twin_calibration(out / "calibration", twin, panel_hw)
    else:
        panel_hw = (config.slm.height_px, config.slm.width_px)
        calibration = active_calibration(config)
    p = prepare(config, scene, view, window_hw, panel_hw, settings, calibration=calibration,
                info=info)
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
