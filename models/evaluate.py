"""`nhfd eval`: hologram quality on held-out views, next to the two baselines.

Measures (docs/physics.md, "Measuring hologram quality"): focal-stack PSNR and SSIM from
`nhfd.optics.focal_stack_quality` (linear intensity after the aperture, the fixed planes of
`quality_planes`, inside the scene's pixels, one robust percentile of the target), per plane and
overall, for the model, an all-black prediction and the 2D hologram; the per-depth-bin focus
check (pixels binned by their mapped depth; the plane whose image best correlates with the view
must lie within half the filtered depth of field of the target's); quality against the angular
distance to the nearest training pose; and a PNG of predicted vs target focal slices.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from nhfd.models.data import HoloData
from nhfd.models.export import OnnxModel, run_training_poses
from nhfd.models.inputs import ALPHA_CONTENT
from nhfd.models.loss import Optics
from nhfd.models.metadata import expected_from_manifest
from nhfd.models.net import predict, to_field
from nhfd.models.train import load_run
from nhfd.optics import (
    Aperture,
    KernelCache,
    Quality,
    focal_stack,
    hologram_2d,
    linear_to_srgb,
    quality_planes,
    srgb_to_linear,
    stack_quality,
)

FOCUS_BINS = 5
FOCUS_SWEEP = 61  # 0.1 mm steps over the default +-3 mm volume
FOCUS_MIN_PIXELS = 64
# Network input [C,H,W] (nhfd.models.inputs) -> field [3,H,W] (amplitude-scale units)
Predictor = Callable[[torch.Tensor], torch.Tensor]


def torch_predictor(run_dir: str | Path) -> tuple[Predictor, dict]:
    """A run's network, and what it is (`train_poses`: its training poses, or None)."""
    net, info = load_run(run_dir)

    def run(x: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            amp, phase = predict(net, x)
        return to_field(amp, phase, 1.0)

    return run, {"source": str(run_dir), "kind": "torch run", "profile":
                 info["options"].get("profile"), "net": info["net"],
                 "inputs": net.spec.inputs, "train_poses": run_training_poses(info)}  # fmt: skip


def onnx_predictor(path: str | Path, manifest: dict) -> tuple[Predictor, dict]:
    """An ONNX model checked against the dataset's `manifest` as a predictor (input [C, H, W] ->
    field [3, H, W] complex64), and what it is (source, kind, profile, net, inputs,
    `train_poses`)."""
    model = OnnxModel(path, expected=expected_from_manifest(manifest))

    def run(x: torch.Tensor) -> torch.Tensor:
        amp, phase = model(x.numpy())
        return torch.polar(torch.from_numpy(amp), torch.from_numpy(phase))

    return run, {"source": str(path), "kind": "onnx", "profile": model.metadata.get("profile"),
                 "net": model.metadata.get("net"), "inputs": model.inputs,
                 "train_poses": model.metadata.get("train_poses")}  # fmt: skip


def _directions(positions: np.ndarray, centre: np.ndarray) -> np.ndarray:
    d = np.asarray(positions, np.float64) - np.asarray(centre, np.float64)
    return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)


def _positions(manifest: dict) -> np.ndarray:
    return np.array([-np.asarray(p["R"], np.float64).T @ np.asarray(p["t"], np.float64)
                     for p in manifest["poses"]])  # fmt: skip


def nearest_train_angle_deg(manifest: dict, index: int, trained: dict | None = None) -> float:
    """Angle (degrees, seen from the scene's centre) between view `index` of `manifest` and the
    nearest training pose: the model's own (`trained`, its metadata's `train_poses`) when
    given, else the manifest's train split (right only for the dataset the model was trained
    on: a fresh dataset's own training views would read 0)."""
    if trained:
        centre = np.asarray(trained["center"], np.float64)
        train_dirs = _directions(np.asarray(trained["positions"]), centre)
        view_dir = _directions(_positions(manifest)[index], centre)
    else:
        train = manifest["splits"].get("train", [])
        if not train:
            return float("nan")
        dirs = _directions(_positions(manifest), manifest.get("center", [0, 0, 0]))
        train_dirs, view_dir = dirs[train], dirs[index]
    if len(train_dirs) == 0:
        return float("nan")
    cos = np.clip(train_dirs @ view_dir, -1, 1)
    return float(np.degrees(np.arccos(cos.max())))


ANGLE_FROM_METADATA = "the poses the model was trained on (its metadata's train_poses)"
ANGLE_FALLBACK = ("the evaluated dataset's train split: the model records no training poses "
                  "(exported before they were recorded, or its dataset folder was gone); right "
                  "only when the evaluated dataset is the one it was trained on")


def focus_check(
    field: torch.Tensor, target: torch.Tensor, rgb: torch.Tensor, zh: torch.Tensor,
    optics: Optics, cache: KernelCache,
) -> list[dict]:  # fmt: skip
    """Per depth bin (green channel): the sweep plane whose intensity best correlates with the
    view's linear intensity, for the prediction and for the target. A bin passes when the
    prediction focuses within half the filtered depth of field of where the target does.

    The reference is the target's focus, not the bin's mapped depth: the targets are the light
    field's holograms, occlusion included. Where a surface is rough at the pixel scale, nearer
    splats hide farther ones in the off-axis views, so the content focuses in front of the
    central view's alpha-weighted depth (`tests/holo/test_focus.py` reproduces it; 0.1-0.45 mm
    on the donut, most in the far bin). That offset is reported per bin (`target_offset_mm`)
    as a check on the chain; isolated points and flat or sloped layers show none."""
    lo, hi = optics.volume_m
    g = 1 if len(optics.wavelengths_m) > 1 else 0
    lam = optics.wavelengths_m[g]
    ap = Aperture(optics.aperture.shape, (optics.aperture.cutoffs(len(optics.wavelengths_m))[g],))
    sweep = np.linspace(lo, hi, FOCUS_SWEEP).tolist()
    fields = torch.stack([field[g : g + 1], target[g : g + 1]]).to(torch.complex64)
    stacks = focal_stack(fields, sweep, optics.pitch_m, [lam], ap, cache=cache)[:, :, 0]
    view = srgb_to_linear(rgb[g].to(stacks.device))
    edges = np.linspace(lo, hi, FOCUS_BINS + 1)
    tol = ap.half_depth_of_field_m(0, 1, lam, optics.pitch_m)
    out = []
    z = zh.numpy()
    for b in range(FOCUS_BINS):
        sel = np.isfinite(z) & (z >= edges[b]) & (z <= edges[b + 1])
        if sel.sum() < FOCUS_MIN_PIXELS:
            continue
        m = torch.from_numpy(sel).to(stacks.device)
        v = view[m] - view[m].mean()
        best = []
        for s in range(2):
            x = stacks[s][:, m]  # [Z, P]
            x = x - x.mean(dim=1, keepdim=True)
            corr = (x @ v) / (x.norm(dim=1) * v.norm()).clamp(min=1e-20)
            best.append(sweep[int(corr.argmax())])
        centre = float(z[sel].mean())
        out.append({"bin_mm": [edges[b] * 1e3, edges[b + 1] * 1e3], "pixels": int(sel.sum()),
                    "content_mm": centre * 1e3, "predicted_focus_mm": best[0] * 1e3,
                    "target_focus_mm": best[1] * 1e3,
                    "target_offset_mm": (best[1] - centre) * 1e3, "tolerance_mm": tol * 1e3,
                    "pass": abs(best[0] - best[1]) <= tol + 1e-12})  # fmt: skip
    return out


def stacks_quality(fields: dict[str, torch.Tensor], target: torch.Tensor,
                   mask: torch.Tensor | None, *, planes_m: Sequence[float], pitch_m: float,
                   wavelengths_m: Sequence[float], aperture: Aperture, cache: KernelCache
                   ) -> dict[str, Quality]:
    """`focal_stack_quality` of each named field `[C, H, W]` against `target`, and of "black"
    (an all-dark prediction, whose stack is zero): the target propagated once for all of them,
    with the fields in one call."""
    stacks = focal_stack(torch.stack([*fields.values(), target]).to(torch.complex64), planes_m,
                         pitch_m, wavelengths_m, aperture, cache=cache)
    seen = {**dict(zip(fields, stacks[:-1], strict=True)), "black": torch.zeros_like(stacks[-1])}
    return {name: stack_quality(stack, stacks[-1], planes_m=planes_m, mask=mask)
            for name, stack in seen.items()}


def evaluate(
    source: str | Path,
    data_dir: str | Path,
    *,
    splits: tuple[str, ...] = ("interp", "extrap"),
    max_views: int | None = None,
    out_dir: str | Path | None = None,
    data: HoloData | None = None,
    log: Callable[[str], None] = print,
    device: str | torch.device = "cpu",
) -> dict:
    """Quality of a run folder or an exported .onnx on a dataset's held-out views. `device`:
    where the focal stacks, their scores and the focus check run (`nhfd model build
    --device cuda` evaluates there; the network runs where its predictor does)."""
    dev = torch.device(device)
    source = Path(source)
    limits = {s: max_views for s in splits} if max_views else None
    data = data or HoloData(data_dir, splits=splits, max_views=limits)
    if source.suffix == ".onnx":
        predictor, about = onnx_predictor(source, data.manifest)
    else:
        predictor, about = torch_predictor(source)
    trained = about.pop("train_poses", None)
    about["angle_reference"] = ANGLE_FROM_METADATA if trained else ANGLE_FALLBACK
    if not trained:
        log(f"angles to the nearest training pose: measured against {ANGLE_FALLBACK}")
    optics = Optics.from_manifest(data.manifest)
    planes = quality_planes(optics.volume_m)
    cache = KernelCache()
    kw = dict(planes_m=planes, pitch_m=optics.pitch_m, wavelengths_m=optics.wavelengths_m,
              aperture=optics.aperture, cache=cache)  # fmt: skip
    views, examples = [], []
    for split in splits:
        if split not in data.splits:
            continue
        s = data.splits[split]
        for j, index in enumerate(s.indices):
            rgb, target = s.rgb[j].to(dev), s.field[j].to(dev)
            mask = s.alpha[j] >= ALPHA_CONTENT
            mask = mask.to(dev) if mask.any() else None
            pred = predictor(s.inputs(about["inputs"], j)).to(dev)
            # Energy-matched to the target: a baseline in other units would be judged on its
            # brightness, not on its (missing) depth.
            flat = hologram_2d(rgb, like=target, mask=mask)
            q = stacks_quality({"model": pred, "hologram_2d": flat}, target, mask, **kw)
            focus = focus_check(pred, target, rgb, s.zh[j], optics, cache)
            views.append({
                "index": index, "split": split,
                "nearest_train_deg": nearest_train_angle_deg(data.manifest, index, trained),
                **{f"{k}_psnr_db": v.psnr_db for k, v in q.items()},
                **{f"{k}_ssim": v.ssim for k, v in q.items()},
                "model_psnr_per_plane_db": list(q["model"].psnr_per_plane_db),
                "model_ssim_per_plane": list(q["model"].ssim_per_plane),
                "hologram_2d_psnr_per_plane_db": list(q["hologram_2d"].psnr_per_plane_db),
                "focus": focus,
            })  # fmt: skip
            if j == 0:
                examples.append((split, index, *(t.cpu() for t in (rgb, pred, target, flat))))
    if not views:
        raise ValueError(f"{data_dir}: no views in the splits {', '.join(splits)}")
    summary = summarise(views, planes)
    result = {"model": about, "data": str(data.dir), "planes_m": list(planes),
              "summary": summary, "views": views}  # fmt: skip
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "eval.json").write_text(json.dumps(result, indent=1))
        if examples:
            result["png"] = str(slices_png(examples, planes, optics, cache, out / "eval.png"))
    for line in format_summary(summary, planes):
        log(line)
    return result


def summarise(views: list[dict], planes) -> dict:
    """Per split and over "all": mean PSNR (dB) and SSIM of the model, the black and the 2D
    baselines, per-plane PSNR, focus bins passed; with PSNR against the angle (deg) to the
    nearest training pose and the focus tolerance (mm)."""
    out: dict = {}
    for split in [*sorted({v["split"] for v in views}), "all"]:
        vs = [v for v in views if split in ("all", v["split"])]
        focus = [b["pass"] for v in vs for b in v["focus"]]
        out[split] = {
            "views": len(vs),
            **{f"{k}_{m}": float(np.mean([v[f"{k}_{m}"] for v in vs]))
               for k in ("model", "black", "hologram_2d") for m in ("psnr_db", "ssim")},
            "model_psnr_per_plane_db": np.mean([v["model_psnr_per_plane_db"] for v in vs],
                                               axis=0).tolist(),
            "hologram_2d_psnr_per_plane_db": np.mean(
                [v["hologram_2d_psnr_per_plane_db"] for v in vs], axis=0).tolist(),
            "focus_bins_passed": int(sum(focus)),
            "focus_bins": len(focus),
            "focus_target_offset_mm": float(np.mean([b["target_offset_mm"] for v in vs
                                                     for b in v["focus"]] or [np.nan])),
            "margin_over_2d_db": float(np.mean([v["model_psnr_db"] - v["hologram_2d_psnr_db"]
                                                for v in vs])),
        }  # fmt: skip
    angles = [(v["nearest_train_deg"], v["model_psnr_db"]) for v in views]
    out["psnr_vs_angle"] = sorted(angles)
    out["focus_tolerance_mm"] = next((b["tolerance_mm"] for v in views for b in v["focus"]),
                                     float("nan"))
    return out


def format_summary(summary: dict, planes) -> list[str]:
    """`summarise`'s result as lines for a person: a table per split, the focus check, PSNR per
    focal plane (`planes` in m, shown in mm) and PSNR against the angle to training."""
    lines = [f"{'split':<8}{'views':>6}{'model dB':>10}{'2D dB':>8}{'black dB':>10}"
             f"{'model SSIM':>12}{'2D SSIM':>9}{'focus':>8}"]  # fmt: skip
    for split, s in summary.items():
        if not isinstance(s, dict):
            continue
        lines.append(
            f"{split:<8}{s['views']:>6}{s['model_psnr_db']:>10.2f}{s['hologram_2d_psnr_db']:>8.2f}"
            f"{s['black_psnr_db']:>10.2f}{s['model_ssim']:>12.3f}{s['hologram_2d_ssim']:>9.3f}"
            f"{s['focus_bins_passed']:>4}/{s['focus_bins']:<3}"
        )
    a = summary["all"]
    lines.append(f"focus: the model within {summary['focus_tolerance_mm']:.2f} mm of the "
                 f"target's focus in {a['focus_bins_passed']}/{a['focus_bins']} depth bins; the "
                 f"targets focus {a['focus_target_offset_mm']:+.2f} mm from the bins' mapped "
                 "depth on average")
    lines.append("per plane (mm): " + ", ".join(
        f"{z * 1e3:+.1f}: {p:.1f} (2D {q:.1f})" for z, p, q in
        zip(planes, a["model_psnr_per_plane_db"], a["hologram_2d_psnr_per_plane_db"], strict=True)
    ))  # fmt: skip
    lines.append("PSNR vs angle to nearest training pose: " + ", ".join(
        f"{d:.1f} deg: {p:.1f} dB" for d, p in summary["psnr_vs_angle"] if math.isfinite(d)))
    return lines


def slices_png(examples: list, planes, optics: Optics, cache: KernelCache, path: Path) -> Path:
    """Rows: target, model, 2D hologram; columns: the quality planes (sRGB of intensity)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = []
    for split, index, _rgb, pred, target, flat in examples:
        stacks = focal_stack(torch.stack([target, pred, flat]).to(torch.complex64), planes,
                             optics.pitch_m, optics.wavelengths_m, optics.aperture, cache=cache)
        scale = float(torch.quantile(stacks[0].flatten()[::7].double(), 0.995)) or 1.0
        for name, st in zip(("target", "model", "2D hologram"), stacks, strict=True):
            rows.append((f"{split} #{index} {name}", linear_to_srgb(st / scale)))
    fig, axes = plt.subplots(len(rows), len(planes), figsize=(2.2 * len(planes), 1.6 * len(rows)),
                             squeeze=False)  # fmt: skip
    for r, (label, st) in enumerate(rows):
        for c, z in enumerate(planes):
            ax = axes[r][c]
            ax.imshow(st[c].permute(1, 2, 0).numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(f"{z * 1e3:+.1f} mm", fontsize=8)
            if c == 0:
                ax.set_ylabel(label, fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
