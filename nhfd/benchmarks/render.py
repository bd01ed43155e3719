"""`nhfd bench render`: CPU splat rendering against plain vectorised NumPy compositing.

Workloads (issue 3): one 1024 x 576 view of the donut and of the guitar from their suggested
cameras, and the 64-view light field of the red channel (+-3 mm volume, default aperture) of the
donut. The baseline composites the same projected Gaussians with NumPy, one Gaussian at a time
over its bounding box (same thresholds, same result), measured in the same run: machines here are
noisy, so the ratio is what carries over. Required on 2 cores: a view in <= 300 ms, the light field
in <= 10 s, >= 5x the baseline; goals 100 ms and 4 s.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from nhfd.benchmarks.machine import describe
from nhfd.cli.args import parse_wxh
from nhfd.dataset.shard import ExampleSettings
from nhfd.scene import _kernels as kernels
from nhfd.scene.io import load_scene
from nhfd.scene.lightfield import DepthMapping, directions, hogel_window, render_light_field
from nhfd.scene.raster import RasterSettings, prepare, render
from nhfd.scene.suggest import detect_up_axis, suggest_camera

DEFAULT_SCENES = ("donut.ply", "guitar.compressed.ply")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="CPU splat rendering vs NumPy compositing",
                       description=__doc__)  # fmt: skip
    p.add_argument("--scenes", nargs="+", default=None,
                   help="scene files (default: donut and guitar from ../shared/data/scenes)")
    p.add_argument("--size", default="1024x576", help="view WxH (default 1024x576)")
    p.add_argument("--repeats", type=int, default=5, help="timed views per scene; median kept")
    p.add_argument("--tile", type=int, default=None, help="tile edge in px (default: renderer's)")
    p.add_argument("--no-lightfield", action="store_true", help="skip the light-field workload")
    p.add_argument("--out", default="out/bench/render.json", help="JSON file to write")
    p.set_defaults(handler=run)


def numpy_composite(rec: np.ndarray, counts: np.ndarray, width: int, height: int) -> np.ndarray:
    """The baseline: composite projected records (from `_kernels.project_view`, depth order) one
    Gaussian at a time over its bounding box with NumPy. Returns rgb [3, H, W]."""

    trans = np.ones((height, width))
    live = np.ones((height, width), bool)
    acc = np.zeros((3, height, width))
    for r in rec[counts > 0]:
        x0 = max(int(np.ceil(r[kernels.U] - r[kernels.RX] - 0.5)), 0)
        x1 = min(int(np.floor(r[kernels.U] + r[kernels.RX] - 0.5)), width - 1)
        y0 = max(int(np.ceil(r[kernels.V] - r[kernels.RY] - 0.5)), 0)
        y1 = min(int(np.floor(r[kernels.V] + r[kernels.RY] - 0.5)), height - 1)
        if x1 < x0 or y1 < y0:
            continue
        dx = np.arange(x0, x1 + 1) + 0.5 - r[kernels.U]
        dy = (np.arange(y0, y1 + 1) + 0.5 - r[kernels.V])[:, None]
        q = 0.5 * (r[kernels.CA] * dx * dx + r[kernels.CC] * dy * dy) + r[kernels.CB] * dx * dy
        al = np.minimum(kernels.ALPHA_MAX, r[kernels.OP] * np.exp(-q))
        al[al < kernels.ALPHA_MIN] = 0.0
        t = trans[y0 : y1 + 1, x0 : x1 + 1]
        lv = live[y0 : y1 + 1, x0 : x1 + 1]
        nt = t * (1.0 - al)
        stop = lv & (al > 0) & (nt < kernels.T_MIN)
        keep = lv & (al > 0) & ~stop
        wgt = np.where(keep, al * t, 0.0)
        for c, col in enumerate((kernels.COL_R, kernels.COL_G, kernels.COL_B)):
            acc[c, y0 : y1 + 1, x0 : x1 + 1] += wgt * r[col]
        t[keep] = nt[keep]
        lv[stop] = False
    return acc.astype(np.float32)


def _median(times: list[float]) -> float:
    return statistics.median(times)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def _scene_paths(args: argparse.Namespace) -> list[Path]:
    if args.scenes:
        return [Path(s) for s in args.scenes]
    root = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "scenes"
    paths = [root / name for name in DEFAULT_SCENES]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise FileNotFoundError(f"default scenes not found: {missing}; pass --scenes FILE ...")
    return paths


def run(args: argparse.Namespace) -> int:
    w, h = parse_wxh(args.size, "--size")
    if args.repeats < 1 or w < 1 or h < 1:
        raise ValueError("--size and --repeats must be positive")
    settings = RasterSettings() if args.tile is None else RasterSettings(tile_px=args.tile)
    machine = describe()
    try:
        import numba

        machine["numba_threads"] = numba.get_num_threads()
    except ImportError:
        pass
    print(f"{w} x {h}, tile {settings.tile_px} px; {machine}")
    results: dict[str, dict] = {}
    donut = None
    for path in _scene_paths(args):
        g = load_scene(path)
        hint = "compressed" if path.name.endswith(".compressed.ply") else None
        up, _ = detect_up_axis(g, hint)
        cam = suggest_camera(g, w, h, up)
        render(g, cam, settings)  # warm-up: numba compile/cache load, page faults
        times, last = [], None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            last = render(g, cam, settings)
            times.append(time.perf_counter() - t0)
        view_s = _median(times)
        # Baseline: the same projected Gaussians composited with NumPy.
        prep = prepare(g, cam)
        rec, counts = kernels.project_view(
            prep.pc, prep.cov, prep.opacities, prep.sh, prep.order, np.zeros(2), cam.R,
            cam.fx, cam.fy, cam.cx, cam.cy, w, h, cam.near, cam.far, settings.eps2d_px2,
            settings.antialias, settings.tile_px,
        )  # fmt: skip
        t0 = time.perf_counter()
        base_rgb = numpy_composite(rec, counts, w, h)
        base_s = time.perf_counter() - t0
        agree = _psnr(last.rgb, base_rgb)
        results[path.name] = {
            "gaussians": len(g), "view_ms": 1e3 * view_s, "baseline_ms": 1e3 * base_s,
            "speedup": base_s / view_s, "psnr_vs_baseline_db": agree, "stats": last.stats,
        }  # fmt: skip
        pairs = last.stats["tile_pairs"]
        print(
            f"  {path.name:<24} {len(g):>7} Gaussians  view {1e3 * view_s:7.1f} ms  "
            f"numpy {1e3 * base_s:8.1f} ms  {base_s / view_s:5.1f}x  "
            f"(agree {agree:.1f} dB; {pairs} tile pairs)",
            flush=True,
        )
        if donut is None:
            donut = (g, cam, last, base_s)
    if not args.no_lightfield and donut is not None:
        g, cam, central, base_view_s = donut
        # Red (the widest cone, the most views) with the packaged configuration's optics.
        optics = ExampleSettings()
        lam, pitch = optics.wavelengths_m[0], optics.pitch_m
        f_cut, (z_min, z_max) = optics.cutoff_per_px[0], optics.volume_m
        d = central.depth[central.alpha > 0.5]
        mapping = DepthMapping.from_range(*np.percentile(d, [1, 99]), z_min, z_max)
        win = hogel_window(lam, pitch, max(abs(z_min), abs(z_max)), f_cut)
        n_views = len(directions(win, lam, pitch, f_cut)[0]) ** 2
        lf = render_light_field(g, cam, mapping, lam, pitch, win, f_cut, settings)
        # Baseline for the light field: the NumPy compositing time per view times the views
        # (projection excluded, which favours the baseline).
        base_lf_s = base_view_s * n_views
        results["lightfield"] = {
            "scene": _scene_paths(args)[0].name, "wavelength_nm": lam * 1e9, "window": win,
            "views": n_views, "seconds": lf.seconds, "baseline_s_estimated": base_lf_s,
            "speedup": base_lf_s / lf.seconds,
        }  # fmt: skip
        print(f"  light field, red, W={win}: {n_views} views in {lf.seconds:.2f} s "
              f"({1e3 * lf.seconds / n_views:.0f} ms/view); numpy ~{base_lf_s:.0f} s, "
              f"{base_lf_s / lf.seconds:.1f}x", flush=True)  # fmt: skip
    import numba

    machine["numba_layer"] = numba.threading_layer()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"size_wh": [w, h], "tile_px": settings.tile_px,
                               "results": results, "machine": machine}, indent=2))  # fmt: skip
    print(f"wrote {out}")
    return 0
