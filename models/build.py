"""`nhfd model build`: one scene to an evaluated, exported model, in resumable stages.

Stages, in order (`STAGES`), each writing under the output folder OUT:

1. `scene`: load the scene, its up axis (declared by the format or guessed, `--up` overrides)
   and the suggested camera distance; the pose sampler around it -> `scene.json`.
2. `reduce`: the scene reduced to what the dataset's views can show -> `scene.ply` (`_reduce`).
3. `dataset`: `nhfd.dataset.build` into `dataset/` (its own resume: shards already written are
   kept).
4. `train`: `nhfd.models.train` into `run/` (its own resume: the checkpoint).
5. `export`: `model.onnx` (float32, checked against torch), and a static int8 and an fp16
   candidate (`nhfd.models.half`) in `candidates/` when the recipe asks.
6. `eval`: `nhfd.models.evaluate` of each variant on the held-out views, next to the 2D-hologram
   and black baselines, with the focus check -> `eval/<variant>/`; the int8 and fp16 models are
   kept (`model-int8.onnx`, `model-fp16.onnx`) only within `INT8_MAX_LOSS_DB` of the float one.
7. `report`: `report.json` (the figures) and `contact_sheet.png` (`nhfd.models.contact_sheet`).

`build.json` records each stage as started, then finished, with the key of its inputs: a hash
of the stage's own settings chained with the previous stage's key. A rerun skips a finished stage
whose key and outputs are unchanged, continues an unfinished one (the dataset's shards and the
training checkpoint), and refuses, without `force`, a folder built from another scene, recipe
or settings. Every file is written to a temporary name and renamed into place.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import resource
import shutil
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from nhfd import __version__
from nhfd.config import ModelSettings, OpticsSettings, SLMSettings, device_choice
from nhfd.dataset.build import build as build_dataset
from nhfd.dataset.build import check_device, sha256_file, shard_name, write_json_atomic
from nhfd.dataset.envelope import dataset_envelope
from nhfd.dataset.poses import EXTRAP_SHARE, INTERP_SHARE, PoseSampler, orbit_sampler
from nhfd.dataset.shard import ExampleSettings
from nhfd.models.contact_sheet import contact_sheet
from nhfd.models.data import HoloData
from nhfd.models.evaluate import evaluate
from nhfd.models.export import OnnxModel, export_onnx
from nhfd.models.half import convert_fp16
from nhfd.models.quantise import (
    INT8_MAX_LOSS_DB,
    int8_within_loss,
    quantise_int8,
    record_heldout_loss,
)
from nhfd.models.train import RESUMABLE_CHANGES, TrainOptions, train
from nhfd.optics import quality_planes
from nhfd.scene.cull import reduce_scene
from nhfd.scene.io import load_scene, save_ply, scene_format
from nhfd.scene.suggest import detect_up_axis, format_hint

STAGES = ("scene", "reduce", "dataset", "train", "export", "eval", "report")
STATE = "build.json"
# How often a running stage's time so far is written into STATE (a killed attempt loses less).
ATTEMPT_RECORD_S = 10.0
FORMAT = "nhfd-model-build"
FORMAT_VERSION = 1
# The reduced-precision candidates, in the order they are built and evaluated; each is kept
# only within INT8_MAX_LOSS_DB of the float model's held-out PSNR (quantise.py: the daemon's
# int8 rule too).
CANDIDATES = ("int8", "fp16")
# Seconds per unit of work on this project's 2-core machine, the estimate before a stage has
# run (then the measured rate of the finished stages scales what is left): the reduction per
# pose-pixel (the donut's 130 poses at 1024 x 576, about 2 min), a dataset example per
# worker (the shipped donut build, 130 examples in 7 min 40 s on 2 workers), a training step per
# pixel of the crop (257 ms at 384 x 224, the shipped run), an export with its check, an
# evaluated view per pixel, and the report. A dataset example on a GPU: 24 in 7.1 s on an H200
# (docs/gpu.md).
PRIOR_S = {"reduce_per_px": 1.0e-6, "example": 7.0, "gpu_example": 0.3,
           "step_per_px": 0.257 / (384 * 224),
           "export": 20.0, "int8": 10.0, "fp16": 2.0, "eval_per_px": 2.0 / (512 * 288),
           "report": 10.0}  # fmt: skip
SPEED_STAGES = ("dataset", "train", "eval")


@dataclass(frozen=True)
class Recipe:
    """A resolved recipe: `nhfd.config.BuildRecipe` with [model]'s values filled in."""

    name: str
    views: int
    width_px: int
    height_px: int
    fov_x_deg: float
    azimuth_deg: tuple[float, float]
    elevation_deg: tuple[float, float]
    radius_scale: tuple[float, float]
    phase: str
    seed: int
    eval_views: int
    sheet_views: int
    int8: bool
    train: TrainOptions = field(default_factory=TrainOptions)
    # export an fp16 candidate too (`nhfd.models.half`), kept like the int8 one
    fp16: bool = True
    # Reduce the scene to what the dataset's views can show (`nhfd.scene.cull.reduce_scene`)
    # within this many grey levels per pixel.
    reduce: bool = True
    reduce_grey_levels: float = 1.0

    @staticmethod
    def from_config(model: ModelSettings, name: str | None = None, *, device: str = "cpu",
                    progress: bool = True) -> Recipe:  # fmt: skip
        """The recipe `name` (default [model.build].profile) of a configuration's `[model]`
        section, its training options from the same section (`TrainOptions.from_config`)."""
        b = model.build
        name = name or b.profile
        if name not in b.profiles:
            raise ValueError(f"--profile {name!r}: not one of the recipes "
                             f"{', '.join(sorted(b.profiles))} ([model.build.profiles])")
        r = b.profiles[name]
        options = TrainOptions.from_config(
            model, r.network or None, steps=r.steps or None,
            crop_width_px=r.crop_width_px or None, crop_height_px=r.crop_height_px or None,
            device=device, progress=progress,
        )  # fmt: skip
        return Recipe(name, r.views, r.width_px, r.height_px, r.fov_x_deg,
                      tuple(r.azimuth_deg), tuple(r.elevation_deg), tuple(r.radius_scale),
                      r.phase, r.seed, r.eval_views, r.sheet_views, r.int8, options,
                      reduce=r.reduce, reduce_grey_levels=r.reduce_grey_levels,
                      fp16=r.fp16)  # fmt: skip

    def to_json(self) -> dict:
        """The recipe as its stages' keys see it: training options that change neither the
        weights nor their number of steps are left out (the device may change on resume)."""
        out = asdict(self)
        out["train"] = {k: v for k, v in out["train"].items()
                        if k not in RESUMABLE_CHANGES or k == "steps"}  # fmt: skip
        return out


def resolve_device(name: str) -> str:
    """`cpu`, `cuda`, `cuda:N`, or `auto` (CUDA when torch sees a device, else the CPU), as
    "cpu" or "cuda:N"; a CUDA device torch does not see is refused (`device_choice`)."""
    import torch

    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    return device_choice(name, "--device", cuda_count=count)


def _key(*parts: Any) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def _copy_atomic(src: Path, dst: Path) -> None:
    tmp = dst.with_name(dst.name + ".tmp")
    shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def _stat_key(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


def record_outputs(out: Path, entry: dict) -> None:
    """Record the sha256 (and size and mtime) of each of a finished stage's outputs (paths
    relative to OUT). Called when it finishes and again after every later stage, which may
    legitimately rewrite an earlier stage's file (eval writes its record into the models): only
    files whose size or mtime moved are hashed again."""
    hashes, stats = entry.setdefault("output_sha256", {}), entry.setdefault("output_stat", {})
    for o in entry.get("result", {}).get("outputs", []):
        path = out / o
        if not path.is_file():
            continue
        key = _stat_key(path)
        if stats.get(o) != key or o not in hashes:
            hashes[o], stats[o] = sha256_file(path), key


def changed_outputs(out: Path, entry: dict) -> list[str]:
    """The outputs of a finished stage that are missing or whose bytes changed since it
    finished (a build recorded before the hashes were: existence only). Empty: still done."""
    outputs = entry.get("result", {}).get("outputs", [])
    hashes = entry.get("output_sha256", {})
    return [o for o in outputs if not (out / o).is_file()
            or (o in hashes and sha256_file(out / o) != hashes[o])]


def carried_time(entry: dict | None) -> dict[str, float]:
    """Seconds and CPU seconds of the earlier attempts at an unfinished stage: those that
    ended by an exception (`partial`) and the one that was killed (its `attempt`, as last
    written by `AttemptClock`)."""
    entry = entry or {}
    parts = [entry.get("partial") or {}, entry.get("attempt") or {}]
    return {k: float(sum(p.get(k, 0.0) for p in parts)) for k in ("seconds", "cpu_s")}


class AttemptClock:
    """While a stage runs, hands its attempt's time so far to `record` every `every_s` (from a
    thread; `record` writes it into the build state), so an attempt that is killed (SIGKILL,
    out of memory, a power cut) still counts towards the stage's time on resume, to within
    `every_s`. Leaving the block hands `record` None: the attempt ended in this process."""

    def __init__(self, record: Callable[[dict[str, float] | None], None],
                 every_s: float = 10.0) -> None:
        self.record, self.every_s = record, every_s
        self.t0, self.cpu0 = time.perf_counter(), _cpu_s()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="attempt-clock")

    def elapsed(self) -> dict[str, float]:
        """The attempt's time so far: wall `seconds` and `cpu_s` (this process's CPU seconds)."""
        return {"seconds": time.perf_counter() - self.t0, "cpu_s": _cpu_s() - self.cpu0}

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            self.record(self.elapsed())

    def __enter__(self) -> AttemptClock:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.record(None)


def _reset_peak_rss() -> bool:
    """Reset this process's peak resident set (Linux >= 4.0: "5" > /proc/self/clear_refs)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    """This process's peak resident set since the last reset (VmHWM), else since it started."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _children_peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024


def _cpu_s() -> float:
    """CPU seconds of this process and its finished children (the dataset's workers): on a
    shared machine, the work a stage did, whatever else ran beside it."""
    me, kids = (resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _fmt_s(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = max(0, round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m" if h else (f"{m}m{s:02d}s" if m else f"{s}s")


@dataclass
class Context:
    """What the stages share: the scene, the output folder, the recipe and the configuration's
    `[optics]` and `[slm]` sections (the bench the dataset is made for), the finished stages'
    results, and where progress goes."""

    scene: Path
    out: Path
    recipe: Recipe
    optics: OpticsSettings
    slm: SLMSettings
    up: str | None
    workers: int
    log: Callable[[str], None]
    progress: bool
    results: dict[str, dict] = field(default_factory=dict)
    force_stage: bool = False  # the stage's inputs changed (--force): start it over

    def path(self, name: str) -> Path:
        """The output folder's file `name`."""
        return self.out / name


# Stage functions: each takes the Context and returns its result (JSON), with "outputs": the
# files (relative to OUT) that must exist for the stage to count as done.


def _scene(ctx: Context) -> dict:
    r = ctx.recipe
    g = load_scene(ctx.scene)
    fmt = scene_format(ctx.scene)
    if ctx.up:
        up, reason = ctx.up, "given (--up)"
    else:
        up, reason = detect_up_axis(g, format_hint(ctx.scene))
    sampler = orbit_sampler(g, up, width_px=r.width_px, height_px=r.height_px,
                            fov_x_deg=r.fov_x_deg, views=r.views, azimuth_deg=r.azimuth_deg,
                            elevation_deg=r.elevation_deg, radius_scale=r.radius_scale,
                            seed=r.seed)  # fmt: skip
    center = np.asarray(sampler.center)
    dist = sampler.radius[0] / r.radius_scale[0]
    result = {"path": str(ctx.scene), "format": fmt, "gaussians": len(g), "up": up,
              "up_reason": reason, "center": [float(v) for v in center],
              "suggested_distance": dist, "sampler": sampler.describe(),
              "outputs": ["scene.json"]}  # fmt: skip
    write_json_atomic(ctx.path("scene.json"), result)
    return result


def _reduce(ctx: Context) -> dict:
    """The scene the dataset renders, written as `scene.ply`: reduced to what the dataset's
    cameras (every pose's depth pass and light field, `dataset_envelope`) can show within the
    recipe's grey levels (`nhfd.scene.cull.reduce_scene`), or the whole scene when the recipe
    says `reduce = false`. The envelope's mapping, light-field views and focal planes go in the
    report either way: they are what the dataset will use."""
    g = load_scene(ctx.scene)
    out: dict = {"reduced": False, "gaussians": len(g), "outputs": ["scene.ply"]}
    if ctx.recipe.reduce:
        sampler, poses = _poses(ctx)
        env = dataset_envelope(g, poses, np.asarray(sampler.center), _example_settings(ctx))
        g, report = reduce_scene(g, env.cameras, grey_levels=ctx.recipe.reduce_grey_levels)
        ctx.log(f"reduce: {report.summary()}")
        out.update(reduced=True, gaussians=len(g), **report.to_dict(),
                   envelope={"poses": env.n_poses, "views_per_pose": env.views_per_pose,
                             "cameras": len(env.cameras),
                             "focal_planes_mm": [round(z * 1e3, 4) for z in env.focal_planes_m],
                             "mapping": env.mapping_report})  # fmt: skip
    tmp = ctx.path("scene.ply.tmp")
    save_ply(tmp, g)
    os.replace(tmp, ctx.path("scene.ply"))
    return out


def _poses(ctx: Context):
    s = ctx.results["scene"]["sampler"]
    sampler = PoseSampler(**{k: tuple(v) if isinstance(v, list) else v for k, v in s.items()})
    return sampler, sampler.sample()


def _example_settings(ctx: Context) -> ExampleSettings:
    r = ctx.recipe
    return ExampleSettings.from_config(ctx.optics, ctx.slm, width_px=r.width_px,
                                       height_px=r.height_px, fov_x_deg=r.fov_x_deg,
                                       phase=r.phase)  # fmt: skip


def _dataset_device(ctx: Context) -> tuple[str, int]:
    """Where the dataset is built, and by how many processes: on the training GPU when gsplat
    renders there (in this process: on an H200 the donut's 130 examples took 80 s in 16 CPU
    workers, and 24 took 7.1 s on the GPU), else in the CPU's workers."""
    device = ctx.recipe.train.device
    if not device.startswith("cuda"):
        return "cpu", ctx.workers
    try:
        return check_device(device), 1
    except ValueError as exc:  # gsplat absent: the GPU still trains
        ctx.log(f"dataset on the CPU: {exc}")
        return "cpu", ctx.workers


def _dataset(ctx: Context) -> dict:
    sampler, poses = _poses(ctx)
    device, workers = _dataset_device(ctx)
    bar = None
    if ctx.progress:
        from tqdm import tqdm

        bar = tqdm(total=len(poses), unit="view", desc="dataset", file=sys.stderr)

    def progress(done: int, total: int, res: dict) -> None:
        if bar is not None:
            bar.n = done
            bar.refresh()

    try:
        manifest = build_dataset(
            ctx.path("scene.ply"), ctx.path("dataset"), poses, _example_settings(ctx),
            seed=ctx.recipe.seed, sampler=sampler.describe(), workers=workers,
            force=ctx.force_stage, progress=progress, device=device,
        )  # fmt: skip
    finally:
        if bar is not None:
            bar.close()
    return {"manifest_key": manifest["key"], "mapping": manifest["mapping"],
            "sampling": manifest["sampling"], "splits": {k: len(v) for k, v in
                                                         manifest["splits"].items()},
            "envelope": manifest["envelope"], "build_timing": manifest.get("build_timing"),
            # Every shard, so that a shard changed after the build is seen (its hash) on resume.
            "outputs": ["dataset/manifest.json",
                        *(f"dataset/{shard_name(i)}" for i in range(len(poses)))]}  # fmt: skip


def _train(ctx: Context) -> dict:
    res = train(ctx.path("dataset"), ctx.path("run"), ctx.recipe.train, force=ctx.force_stage,
                log=ctx.log)  # fmt: skip
    return {"step": res.step, "last_loss": res.last_loss,
            "seconds_per_step": res.seconds_per_step, "resumed_from": res.resumed_from,
            "outputs": ["run/checkpoint.pt", "run/run.json"]}  # fmt: skip


def _export(ctx: Context) -> dict:
    # The dataset rendered the reduced scene.ply; the user serves the original file.
    res = export_onnx(ctx.path("run"), ctx.path("model.onnx"), source_scene=ctx.scene)
    out = {"float": {"path": "model.onnx", "max_abs_diff_vs_torch": res.max_abs_diff,
                     "parameters": res.metadata["parameters"],
                     "bytes": ctx.path("model.onnx").stat().st_size},
           "outputs": ["model.onnx"]}  # fmt: skip
    makers = {
        "int8": lambda tmp: quantise_int8(
            res.path, tmp, HoloData(ctx.path("dataset"), max_views={"interp": 1, "extrap": 1}),
            int(res.metadata["input_multiple"]), OnnxModel(res.path).inputs),
        "fp16": lambda tmp: convert_fp16(res.path, tmp),
    }  # fmt: skip
    for name in CANDIDATES:
        if not getattr(ctx.recipe, name):
            continue
        cand = ctx.path("candidates")
        cand.mkdir(exist_ok=True)
        tmp = cand / f"model-{name}.tmp.onnx"
        makers[name](tmp)
        os.replace(tmp, cand / f"model-{name}.onnx")
        out[name] = {"path": f"candidates/model-{name}.onnx",
                     "bytes": (cand / f"model-{name}.onnx").stat().st_size}
        out["outputs"].append(f"candidates/model-{name}.onnx")
    return out


def _eval_views(ctx: Context) -> int | None:
    return ctx.recipe.eval_views or None


def _eval(ctx: Context) -> dict:
    ex = ctx.results["export"]
    data = HoloData(ctx.path("dataset"), splits=("interp", "extrap"),
                    max_views=({"interp": ctx.recipe.eval_views, "extrap": ctx.recipe.eval_views}
                               if ctx.recipe.eval_views else None))  # fmt: skip
    # The focal stacks and their scores on the training device (66 s of a GPU build on 16
    # CPU cores, docs/gpu.md); the networks run in onnxruntime on the CPU.
    device = ctx.recipe.train.device if ctx.recipe.train.device.startswith("cuda") else "cpu"
    out: dict = {"variants": {}, "outputs": [], "device": device}
    for variant in ("float", *CANDIDATES):
        if not isinstance(ex.get(variant), dict):  # an older build's fp16 note
            continue
        folder = ctx.path("eval") / variant
        kw = dict(data=data, out_dir=folder, log=ctx.log)
        try:
            res = evaluate(ctx.path(ex[variant]["path"]), ctx.path("dataset"), device=device,
                           **kw)
        except RuntimeError as exc:  # a CUDA error: the same scores on the CPU, and why
            if device == "cpu":
                raise
            ctx.log(f"eval on {device} failed ({type(exc).__name__}: {exc}); on the CPU instead")
            out["device"], out["device_error"] = "cpu", f"{type(exc).__name__}: {exc}"
            device = "cpu"
            res = evaluate(ctx.path(ex[variant]["path"]), ctx.path("dataset"), **kw)
        s = res["summary"]
        out["variants"][variant] = {**{k: v for k, v in s["all"].items()},
                                    "splits": {k: v for k, v in s.items()
                                               if k in ("interp", "extrap")},
                                    "psnr_vs_angle": s["psnr_vs_angle"],
                                    "focus_tolerance_mm": s["focus_tolerance_mm"],
                                    "angle_reference": res["model"]["angle_reference"]}
        out["outputs"].append(f"eval/{variant}/eval.json")
    f = out["variants"]["float"]
    for name in CANDIDATES:
        if name not in out["variants"]:
            continue
        q = out["variants"][name]
        loss = f["model_psnr_db"] - q["model_psnr_db"]
        keep = int8_within_loss(loss)
        q["loss_vs_float_db"] = loss
        q["kept"] = keep
        if name == "int8":  # the figures travel inside the int8 file: the daemon serves by them
            record_heldout_loss(ctx.path(ex["int8"]["path"]), ctx.path(ex["float"]["path"]),
                                float_psnr_db=f["model_psnr_db"], int8_psnr_db=q["model_psnr_db"],
                                views=int(q.get("views") or 0))  # fmt: skip
        dst = ctx.path(f"model-{name}.onnx")
        if keep:
            _copy_atomic(ctx.path(ex[name]["path"]), dst)
            out["outputs"].append(f"model-{name}.onnx")
        else:
            dst.unlink(missing_ok=True)
        ctx.log(f"{name}: {q['model_psnr_db']:.2f} dB against float {f['model_psnr_db']:.2f} dB "
                f"({loss:+.2f} dB): " + (f"kept, model-{name}.onnx" if keep else
                                         f"dropped (more than {INT8_MAX_LOSS_DB} dB)"))
    return out


def _report(ctx: Context) -> dict:
    sheet = contact_sheet(ctx.path("model.onnx"), ctx.path("dataset"),
                          ctx.path("contact_sheet.png"), n_views=ctx.recipe.sheet_views)
    report = build_report(ctx, sheet)
    write_json_atomic(ctx.path("report.json"), report)
    return {"sheet": sheet, "outputs": ["report.json", "contact_sheet.png"]}


def build_report(ctx: Context, sheet: dict | None = None) -> dict:
    """The figures of a build (report.json): scene, reduction, dataset (mapping, light-field
    views, focal planes), training, each variant's held-out quality against the baselines and
    the focus check, and each stage's time and peak memory."""
    res = ctx.results
    ds = res["dataset"]
    ev = res["eval"]["variants"]
    f = ev["float"]
    state = _read_state(ctx.out) or {}
    return {
        "format": "nhfd-model-build-report",
        "scene": {k: res["scene"][k] for k in ("path", "format", "gaussians", "up",
                                               "up_reason", "center", "suggested_distance")},
        "profile": ctx.recipe.name,
        "recipe": ctx.recipe.to_json(),
        "reduce": {k: v for k, v in res["reduce"].items() if k != "outputs"},
        "dataset": {
            "views": ds["splits"],
            "depth_mapping": ds["mapping"],
            "light_field_views": [{"wavelength_nm": s["wavelength_nm"], "window": s["window"],
                                   "n_views": s["n_views"]} for s in ds["sampling"]],
            "envelope": ds["envelope"],
        },
        "focal_planes_mm": {"quality": [z * 1e3 for z in _quality_planes(ctx)],
                            "contact_sheet": (sheet or {}).get("planes_mm")},
        "train": {k: v for k, v in res["train"].items() if k != "outputs"},
        "models": {
            "float": {**res["export"]["float"], "served": True},
            **{name: {**res["export"][name], "kept": ev[name]["kept"],
                      "path": f"model-{name}.onnx" if ev[name]["kept"] else None}
               for name in CANDIDATES if name in ev},
        },
        "heldout": {
            variant: {k: v[k] for k in (
                "views", "model_psnr_db", "hologram_2d_psnr_db", "black_psnr_db", "model_ssim",
                "hologram_2d_ssim", "margin_over_2d_db", "focus_bins_passed", "focus_bins",
                "focus_target_offset_mm", "focus_tolerance_mm", "splits", "psnr_vs_angle",
                "angle_reference") if k in v} | (
                {"loss_vs_float_db": v["loss_vs_float_db"], "kept": v["kept"]}
                if variant in CANDIDATES else {})
            for variant, v in ev.items()
        },
        "checks": {
            "beats_black": f["model_psnr_db"] > f["black_psnr_db"],
            "margin_over_2d_db": f["margin_over_2d_db"],
            "focus_bins_passed_fraction": (f["focus_bins_passed"] / f["focus_bins"]
                                           if f["focus_bins"] else None),
        },
        "contact_sheet": sheet,
        "stages": {k: {"seconds": v.get("seconds"), "cpu_s": v.get("cpu_s"),
                       "peak_rss_mb": v.get("peak_rss_mb"),
                       "children_peak_rss_mb": v.get("children_peak_rss_mb"),
                       "skipped_in_last_run": v.get("skipped", False)}
                   for k, v in state.get("stages", {}).items()},
        "nhfd_version": __version__,
    }


def _quality_planes(ctx: Context) -> tuple[float, ...]:
    v = ctx.optics.volume_mm
    return quality_planes((v[0] * 1e-3, v[1] * 1e-3))


STAGE_FUNCS: dict[str, Callable[[Context], dict]] = {
    "scene": _scene, "reduce": _reduce, "dataset": _dataset, "train": _train,
    "export": _export, "eval": _eval, "report": _report,
}


def _stage_params(ctx: Context, stage: str) -> Any:
    """What a stage's result depends on besides the stages before it."""
    r = ctx.recipe
    if stage == "scene":
        return {"sha256": sha256_file(ctx.scene), "size": [r.width_px, r.height_px],
                "fov": r.fov_x_deg, "up": ctx.up, "views": r.views, "az": r.azimuth_deg,
                "el": r.elevation_deg, "radius": r.radius_scale, "seed": r.seed}
    if stage == "reduce":
        return {"reduce": r.reduce, "grey_levels": r.reduce_grey_levels}
    if stage == "dataset":
        return _example_settings(ctx).to_json()
    if stage == "train":
        return r.to_json()["train"]
    if stage == "export":
        return {"int8": r.int8, "fp16": r.fp16}
    if stage == "eval":
        return {"views": r.eval_views, "int8_max_loss_db": INT8_MAX_LOSS_DB}
    return {"sheet_views": r.sheet_views}


def _work(ctx: Context, stage: str) -> float:
    """The prior estimate of a stage's seconds on 2 cores (`PRIOR_S`)."""
    r = ctx.recipe
    px = r.width_px * r.height_px
    held = round(r.views * INTERP_SHARE) + round(r.views * EXTRAP_SHARE)
    n_eval = min(held, 2 * r.eval_views) if r.eval_views else held
    if stage == "reduce":
        return r.views * px * PRIOR_S["reduce_per_px"] * r.reduce
    if stage == "dataset":
        if r.train.device.startswith("cuda"):  # built on the GPU (`_dataset_device`)
            return r.views * PRIOR_S["gpu_example"]
        return r.views * PRIOR_S["example"] / max(1, ctx.workers)
    if stage == "train":
        crop = min(r.train.crop_width_px, r.width_px) * min(r.train.crop_height_px, r.height_px)
        scale = 0.1 if r.train.device.startswith("cuda") else 1.0
        return r.train.steps * PRIOR_S["step_per_px"] * crop * scale
    if stage == "export":
        return PRIOR_S["export"] + PRIOR_S["int8"] * r.int8 + PRIOR_S["fp16"] * r.fp16
    if stage == "eval":
        return n_eval * (1 + r.int8 + r.fp16) * PRIOR_S["eval_per_px"] * px
    if stage == "report":
        return PRIOR_S["report"]
    return 1.0


def _read_state(out: Path) -> dict | None:
    path = out / STATE
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError:
        raise ValueError(f"{path}: not valid JSON; remove it or use --force") from None


@dataclass
class BuildResult:
    """A finished build: its folder, its report.json, the stages this run ran and those it
    skipped as already done."""

    out: Path
    report: dict
    ran: list[str]
    skipped: list[str]


def run_build(
    scene: str | Path,
    out: str | Path,
    recipe: Recipe,
    optics: OpticsSettings,
    slm: SLMSettings,
    *,
    force: bool = False,
    up: str | None = None,
    workers: int | None = None,
    log: Callable[[str], None] | None = None,
    progress: bool = True,
) -> BuildResult:
    """Build (or resume) the model of `scene` into the folder `out` (see the module docstring),
    for the bench of a configuration's `[optics]` and `[slm]` sections (the dataset's optics,
    panel and pitch)."""
    say = log or (lambda msg: print(msg, file=sys.stderr))
    scene, out = Path(scene), Path(out)
    if not scene.exists():
        raise FileNotFoundError(f"{scene}: no such scene file")
    if workers is not None and workers < 1:
        raise ValueError(f"--workers {workers}: must be >= 1")
    state = _read_state(out) if out.exists() else None
    scene_sha = sha256_file(scene)
    if out.exists() and any(out.iterdir()) and state is None and not force:
        raise ValueError(f"{out} exists and holds files that are not a model build (no {STATE}); "
                         "use another --out, or --force to build into it")  # fmt: skip
    if state is not None and (state.get("scene_sha256") != scene_sha
                              or state.get("profile") != recipe.name) and not force:
        raise ValueError(
            f"{out} holds a build of {state.get('scene')} with profile {state.get('profile')!r}, "
            f"not of {scene} with profile {recipe.name!r}; use another --out, or --force to "
            "replace it"
        )
    out.mkdir(parents=True, exist_ok=True)
    if state is None or state.get("scene_sha256") != scene_sha or \
            state.get("profile") != recipe.name:
        state = {"format": FORMAT, "format_version": FORMAT_VERSION, "stages": {}}
    state.update(scene=str(scene), scene_sha256=scene_sha, profile=recipe.name,
                 recipe=recipe.to_json(), nhfd_version=__version__)
    ctx = Context(scene, out, recipe, optics, slm, up, workers or max(1, os.cpu_count() or 1),
                  say, progress)  # fmt: skip

    # Keys first: a changed stage (and so every one after it) is refused before anything runs.
    keys, prev = {}, ""
    for stage in STAGES:
        prev = keys[stage] = _key(prev, stage, _stage_params(ctx, stage))
    changed = [s for s in STAGES if s in state["stages"] and state["stages"][s]["key"] != keys[s]]
    if changed and not force:
        raise ValueError(
            f"{out}: the {changed[0]} stage was built with other settings (the recipe, the "
            f"configuration or the code changed); use another --out, or --force to redo it and "
            "the stages after it"
        )
    t_all = time.perf_counter()
    estimate = {s: _work(ctx, s) for s in STAGES}
    speed = 1.0  # measured / estimated over the stages run so far
    ran, skipped = [], []
    lock = threading.Lock()  # the attempt clock's thread writes the state file too

    def save() -> None:
        with lock:
            write_json_atomic(out / STATE, state)

    for i, stage in enumerate(STAGES, 1):
        entry = state["stages"].get(stage)
        finished = bool(entry and entry.get("done") and entry["key"] == keys[stage])
        changed = changed_outputs(out, entry) if finished and not ran else []
        # Once a stage runs, every stage after it runs too: its inputs were rewritten.
        if finished and not ran and not changed:
            ctx.results[stage] = entry["result"]
            entry["skipped"] = True
            skipped.append(stage)
            say(f"[{i}/{len(STAGES)}] {stage}: skipped (done, inputs unchanged)")
            continue
        if changed:
            # Outputs changed after the stage finished (a corrupted shard, an edited file): they
            # go, and the stage continues from what is intact, as an interrupted one does.
            say(f"[{i}/{len(STAGES)}] {stage}: {len(changed)} output(s) changed since it "
                f"finished ({', '.join(changed[:3])}{', ...' if len(changed) > 3 else ''}); "
                "rebuilding them")
            for o in changed:
                (out / o).unlink(missing_ok=True)
            entry["done"] = False
        left = sum(estimate[s] for s in STAGES[i - 1:] if s not in ctx.results) * speed
        say(f"[{i}/{len(STAGES)}] {stage}: about {_fmt_s(estimate[stage] * speed)}; "
            f"{_fmt_s(time.perf_counter() - t_all)} elapsed, about {_fmt_s(left)} left")
        # An unfinished stage with the same inputs continues (the dataset's shards, the
        # training checkpoint); one whose inputs changed, or that is redone, starts over.
        ctx.force_stage = bool(entry) and (entry["key"] != keys[stage] or entry.get("done"))
        # Time spent by earlier attempts at the same stage (failed or killed) counts toward
        # its time.
        before = carried_time(None if ctx.force_stage or changed else entry)
        state["stages"][stage] = {"key": keys[stage], "done": False, "started": time.time(),
                                  "partial": before}  # fmt: skip
        save()
        reset = _reset_peak_rss()
        children0 = _children_peak_mb()

        def record(spent: dict[str, float] | None, entry: dict = state["stages"][stage]) -> None:
            with lock:
                if spent is None:
                    entry.pop("attempt", None)
                else:
                    entry["attempt"] = spent
                write_json_atomic(out / STATE, state)

        clock = AttemptClock(record, ATTEMPT_RECORD_S)
        try:
            with clock:
                result = STAGE_FUNCS[stage](ctx)
        except BaseException:
            spent = clock.elapsed()
            with lock:
                state["stages"][stage]["partial"] = {k: before[k] + spent[k] for k in spent}
            save()
            raise
        spent = clock.elapsed()
        seconds, cpu_s = before["seconds"] + spent["seconds"], before["cpu_s"] + spent["cpu_s"]
        ctx.results[stage] = result
        children = _children_peak_mb()
        with lock:
            state["stages"][stage].update(
                done=True, result=result, seconds=seconds, cpu_s=cpu_s,
                peak_rss_mb=_peak_rss_mb() if reset else None,
                children_peak_rss_mb=children if children > children0 else None, skipped=False,
            )  # fmt: skip
            for e in state["stages"].values():  # this stage's, and what it rewrote of others'
                if e.get("done"):
                    record_outputs(out, e)
        save()
        ran.append(stage)
        # The machine's speed against the estimates, from the long stages only (a stage of a
        # second or two says nothing about the rest).
        timed = [s for s in ran if s in SPEED_STAGES]
        if timed:
            speed = (sum(state["stages"][s]["seconds"] for s in timed)
                     / max(sum(estimate[s] for s in timed), 1e-9))
        say(f"[{i}/{len(STAGES)}] {stage}: done in {_fmt_s(seconds)} ({cpu_s:.0f} CPU s)")
    if ran:  # the report's stage table then has every stage's time, its own included
        write_json_atomic(out / "report.json", build_report(ctx, ctx.results["report"]["sheet"]))
        record_outputs(out, state["stages"]["report"])  # rewritten just now, by the build
    write_json_atomic(out / STATE, state)
    report = json.loads((out / "report.json").read_text())
    return BuildResult(out, report, ran, skipped)


def recipe_with(recipe: Recipe, **train_overrides) -> Recipe:
    """`recipe` with some training options replaced (tests, benchmarks)."""
    return replace(recipe, train=replace(recipe.train, **train_overrides))
