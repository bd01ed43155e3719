"""`nhfd bench geometry`: calibration's dot geometry and image ops against OpenCV and kornia.

Part 1, the camera geometry on the simulated bench's random benches (`TrueBench.randomised`,
seeds `--seed` ... `--seed + --benches - 1`, never used to tune anything). Each bench shows the
dot hologram (`nhfd.calib.patterns.dots_frame`) to its twin camera through a coarse green
sweep like `nhfd calib capture`'s (11 stage positions, +-2.5 mm about the nearest millimetre to
the bench's SLM plane); the image is the sweep's maximum, as `locate` fits it. Every bench is
fitted twice: the whole view, and with the left third of the view cut away (part of the lattice
out of view). Four methods, each detection -> identification -> similarity:

- detection `dots`: `detect_dots` (band-pass, illumination envelope, local maxima; its filters
  are OpenCV's); `blob`: OpenCV's `SimpleBlobDetector` (on the image blurred 1.2 px, scaled to
  8 bits between its median and 99.9th percentile; threshold from 100, area >= 8 px, blobs
  >= 8 px apart: tuned on benches 2000-2007, which this benchmark does not use by default),
  strongest first;
- fit `ransac`: the dots that OpenCV's `estimateAffinePartial2D` (RANSAC, 1 px) keeps under the
  better mirror hypothesis, then least squares on them (`fit_geometry`, the default: `dots+ransac`);
  `lstsq`: least squares on every identified dot, those beyond 1 px or 4 sigma dropped and
  refitted (`fit_geometry` before OpenCV).

The dots are identified by `identify_dots` in every method: the layout leaves lattice sites
empty at random (so that a mirror or a half turn is found, not assumed), which OpenCV's grid
finders (`findCirclesGrid`) cannot take; a ChArUco board would need a hologram that images an
intensity chart through the relay's half-band aperture (not tried). Errors against the bench's
truth: scale (relative), rotation (degrees) and the SLM centre's position (camera pixels); a
failure is an error raised or a wrong mirror. Times are per image (detection, identification,
fit), the median.

Part 2, each library against the code it replaces (or would replace), same values expected
(to 1e-4), times the median of `--repeats`: `detect_dots`'s filters (OpenCV's `GaussianBlur`
and `dilate`, used, against the NumPy convolutions and sliding-window maximum they replaced,
kept here as the baseline); the bench model's image warp `to_slm_grid` (kornia's `warp_affine`,
used, against the NumPy grid of camera positions and torch `grid_sample` it replaced), at the
test panel's size and a 1080p panel's; evaluation's SSIM map (`ssim_map`, one depthwise
11 x 11 `conv2d` of the five moments, kept, against `kornia.metrics.ssim`) on 15 520 x 520
float32 images, each also measured against the same definition in float64.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import kornia
import numpy as np
import torch
import torch.nn.functional as F
from numpy.lib.stride_tricks import sliding_window_view

from nhfd.benchmarks.machine import describe
from nhfd.calib.capture import SimBenchIO
from nhfd.calib.geometry import (
    ENVELOPE_FLOOR,
    ENVELOPE_SIGMA_PX,
    Geometry,
    GeometryError,
    detect_dots,
    fit_geometry,
    fit_similarity,
    identify_dots,
    ransac_inliers,
    smooth,
)
from nhfd.calib.patterns import DotLayout, PatternSpec, dot_layout, dots_frame
from nhfd.drivers.simcamera import TrueBench
from nhfd.optics.camera_grid import EDGE_MARGIN_PX, to_slm_grid
from nhfd.optics.quality import SSIM_WINDOW_PX, ssim_map

PANEL_HW = (128, 128)
METHODS = ("dots+ransac", "dots+lstsq", "blob+ransac", "blob+lstsq")
# The coarse sweep's positions about the bench's SLM plane, rounded to the millimetre (mm).
SWEEP_MM = np.linspace(-2.5, 2.5, 11)
AGREE = 1e-4


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("geometry", help="dot geometry, warps and SSIM vs OpenCV and kornia",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--benches", type=int, default=40, help="random benches (default 40)")
    p.add_argument("--seed", type=int, default=500, help="first bench seed (default 500)")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats; the median is kept")
    p.add_argument("--out", default="out/bench/geometry.json", help="JSON file to write")
    p.set_defaults(handler=run)


# -- the compared methods -----------------------------------------------------------------------


def blob_detect(image: np.ndarray) -> np.ndarray:
    """OpenCV's blob detector -> centres [N, 2] (col, row), strongest first."""
    a = cv2.GaussianBlur(np.asarray(image, np.float64), (0, 0), 1.2)
    a = a - np.median(a)
    a = np.clip(a / max(float(np.percentile(a, 99.9)), 1e-300), 0, 1)
    u8 = (a * 255).astype(np.uint8)
    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor, p.blobColor = True, 255
    p.minThreshold, p.maxThreshold, p.thresholdStep = 100, 250, 10
    p.filterByArea, p.minArea, p.maxArea = True, 8, 400
    p.filterByCircularity = p.filterByInertia = p.filterByConvexity = False
    p.minDistBetweenBlobs = 8
    pts = np.array([k.pt for k in cv2.SimpleBlobDetector_create(p).detect(u8)]).reshape(-1, 2)
    rc = np.rint(pts[:, ::-1]).astype(int).clip(0, np.array(a.shape) - 1)
    return pts[np.argsort(-a[rc[:, 0], rc[:, 1]], kind="stable")]


def _lstsq_dropping_outliers(xy: np.ndarray, pts: np.ndarray) -> Geometry:
    """The fit before OpenCV: least squares, dots beyond 1 px or 4 sigma dropped and refitted."""
    geo = fit_similarity(xy, pts)
    keep = np.linalg.norm(geo.to_camera(xy) - pts, axis=1) < max(1.0, 4 * geo.rms_px)
    return fit_similarity(xy[keep], pts[keep]) if keep.sum() < len(keep) else geo


def fit_with(method: str, image: np.ndarray, layout: DotLayout) -> Geometry:
    if method == "dots+ransac":
        return fit_geometry(image, layout)[0]
    pts = blob_detect(image) if method.startswith("blob") else detect_dots(image)
    idx = identify_dots(pts, layout)
    ok = idx >= 0
    xy, pts = layout.xy_m[idx[ok]], pts[ok]
    if method.endswith("ransac"):
        keep = ransac_inliers(xy, pts)
        return fit_similarity(xy[keep], pts[keep])
    return _lstsq_dropping_outliers(xy, pts)


# -- part 1: random benches ---------------------------------------------------------------------


def bench_image(seed: int) -> tuple[PatternSpec, np.ndarray, dict[str, Any]]:
    """The dot image of a random bench's coarse sweep and the truth in its camera pixels."""
    bench = TrueBench.randomised(seed)
    spec = PatternSpec(PANEL_HW, bench.pitch_m, bench.wavelengths_m)
    io = SimBenchIO(bench, PANEL_HW, noise_seed=seed)
    io.show(dots_frame(spec))
    io.set_lasers((0.0, 1.0, 0.0))
    images = []
    for dz in SWEEP_MM:
        io.move_stage(round(bench.stage_at_slm_mm) + float(dz))
        images.append(io.capture(1)[0])
    top, left, _, _ = bench.roi_for_panel(PANEL_HW)
    col, row = bench.slm_to_camera_px(0.0, 0.0)
    truth = {"px_per_m": bench.magnification / bench.camera_pitch_m,
             "rotation_deg": bench.rotation_deg % 360, "mirror_x": bench.mirror_x,
             "centre_px": (col - left, row - top)}
    return spec, np.max(images, axis=0), truth


def errors(geo: Geometry, truth: dict[str, Any], cut_px: int) -> tuple[float, float, float]:
    d_rot = (geo.rotation_deg - truth["rotation_deg"] + 180) % 360 - 180
    cx, cy = truth["centre_px"]
    return (abs(geo.px_per_m / truth["px_per_m"] - 1), abs(d_rot),
            math.hypot(geo.shift_px[0] - (cx - cut_px), geo.shift_px[1] - cy))


def compare_methods(args: argparse.Namespace) -> dict[str, Any]:
    cases = []
    for k in range(args.benches):
        spec, image, truth = bench_image(args.seed + k)
        lay = dot_layout(spec)
        cut = image.shape[1] // 3
        cases += [(lay, image, truth, 0), (lay, image[:, cut:], truth, cut)]
    errs: dict[str, list] = {m: [] for m in METHODS}
    fails: dict[str, list] = {m: [] for m in METHODS}
    times: dict[str, list] = {m: [] for m in METHODS}
    # Methods take turns on each case, so a change in the machine's load hits them alike.
    for n, (lay, image, truth, cut) in enumerate(cases):
        for method in METHODS:
            t0 = time.perf_counter()
            try:
                geo = fit_with(method, image, lay)
            except GeometryError as exc:
                fails[method].append(f"case {n}: {exc}")
                continue
            finally:
                times[method].append(time.perf_counter() - t0)
            if geo.mirror_x != truth["mirror_x"]:
                fails[method].append(f"case {n}: wrong mirror")
                continue
            errs[method].append((n, *errors(geo, truth, cut)))
    out: dict[str, Any] = {}
    default = {row[0]: row[1:] for row in errs[METHODS[0]]}
    for method in METHODS:
        e = np.asarray([row[1:] for row in errs[method]]).reshape(-1, 3)
        # Case by case against the default, where both succeeded: [lower, higher] error counts.
        pairs = np.asarray([(default[row[0]], row[1:]) for row in errs[method]
                            if row[0] in default]).reshape(-1, 2, 3)
        vs_default = {name: [int((pairs[:, 1, k] < pairs[:, 0, k]).sum()),
                             int((pairs[:, 1, k] > pairs[:, 0, k]).sum())]
                      for k, name in enumerate(("scale", "rotation", "centre"))}
        rms = np.sqrt((e**2).mean(axis=0)) if len(e) else [math.nan] * 3
        mx = e.max(axis=0) if len(e) else [math.nan] * 3
        out[method] = {"cases": len(cases), "failures": len(fails[method]),
                       "why": fails[method],
                       "scale_rms": float(rms[0]), "scale_max": float(mx[0]),
                       "rotation_rms_deg": float(rms[1]), "rotation_max_deg": float(mx[1]),
                       "centre_rms_px": float(rms[2]), "centre_max_px": float(mx[2]),
                       "ms_per_image": 1e3 * statistics.median(times[method]),
                       "vs_default_lower_higher": vs_default}
    return out


# -- part 2: same values, faster? ---------------------------------------------------------------


def _numpy_smooth(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """detect_dots's blur before OpenCV: separable NumPy convolutions (the baseline)."""
    r = max(1, math.ceil(3 * sigma_px))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_px) ** 2)
    k /= k.sum()
    a = np.pad(np.asarray(image, np.float64), r, mode="reflect")
    a = np.apply_along_axis(lambda v: np.convolve(v, k, mode="valid"), 0, a)
    return np.apply_along_axis(lambda v: np.convolve(v, k, mode="valid"), 1, a)


def _numpy_filters(image: np.ndarray, q: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """detect_dots's band-pass, envelope and local maximum, in NumPy (the baseline)."""
    img = np.asarray(image, np.float64)
    s = _numpy_smooth(img, 1.2) - _numpy_smooth(img, 5.0)
    env = _numpy_smooth(np.clip(img, 0, None), ENVELOPE_SIGMA_PX)
    s = s / np.maximum(env, ENVELOPE_FLOOR * max(float(env.max()), 1e-300))
    padded = np.pad(s, q, mode="constant", constant_values=-np.inf)
    return s, sliding_window_view(padded, (2 * q + 1, 2 * q + 1)).max(axis=(-2, -1))


def _opencv_filters(image: np.ndarray, q: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """The same through OpenCV, as detect_dots computes it."""
    img = np.asarray(image, np.float64)
    s = smooth(img, 1.2) - smooth(img, 5.0)
    env = smooth(np.clip(img, 0, None), ENVELOPE_SIGMA_PX)
    s = s / np.maximum(env, ENVELOPE_FLOOR * max(float(env.max()), 1e-300))
    return s, cv2.dilate(s, np.ones((2 * q + 1, 2 * q + 1), np.uint8),
                         borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)


def grid_sample_to_slm_grid(image: np.ndarray, geo: Geometry, panel_hw: tuple[int, int],
                            pitch_m: float) -> tuple[np.ndarray, np.ndarray]:
    """`to_slm_grid` before kornia: a NumPy grid of camera positions and torch's `grid_sample`
    (the baseline)."""
    h, w = panel_hw
    rows, cols = np.mgrid[0:h, 0:w]
    xy = np.stack([(cols - (w - 1) / 2) * pitch_m, (rows - (h - 1) / 2) * pitch_m], -1)
    cam = geo.to_camera(xy.reshape(-1, 2))
    ih, iw = image.shape
    ok = (cam[:, 0] >= 0) & (cam[:, 1] >= 0) & (cam[:, 0] <= iw - 1) & (cam[:, 1] <= ih - 1)
    grid = torch.from_numpy(np.stack([cam[:, 0] / ((iw - 1) / 2) - 1,
                                      cam[:, 1] / ((ih - 1) / 2) - 1], -1)).double()
    vals = F.grid_sample(torch.from_numpy(np.asarray(image, np.float64))[None, None],
                         grid[None, None], mode="bilinear", align_corners=True)[0, 0, 0]
    m = EDGE_MARGIN_PX
    inner = (rows >= m) & (rows < h - m) & (cols >= m) & (cols < w - m)
    return vals.numpy().reshape(h, w), ok.reshape(h, w) & inner


def kornia_ssim_map(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """`ssim_map`'s definition through kornia (reflect padding, no eps in the denominator)."""
    return kornia.metrics.ssim(x[:, None], y[:, None], SSIM_WINDOW_PX, max_val=1.0, eps=0.0,
                               padding="same")[:, 0]


def _timed(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    fn()  # warm-up (first-call allocations, kernel selection)
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times), result


def same_values(args: argparse.Namespace) -> dict[str, Any]:
    spec, image, _ = bench_image(args.seed)
    r = args.repeats
    out: dict[str, Any] = {}
    t_np, (s_np, m_np) = _timed(lambda: _numpy_filters(image), r)
    t_cv, (s_cv, m_cv) = _timed(lambda: _opencv_filters(image), r)
    out["detect_dots filters"] = {
        "baseline": "NumPy convolve + sliding-window max",
        "library": "OpenCV GaussianBlur + dilate",
        "shape": list(image.shape), "baseline_ms": t_np, "library_ms": t_cv,
        "max_abs_diff": float(max(np.abs(s_np - s_cv).max(),
                                  np.abs(m_np - m_cv)[np.isfinite(m_np)].max()))}
    geo = fit_geometry(image, dot_layout(spec))[0]
    for hw in (PANEL_HW, (1080, 1920)):
        t_t, (v_t, ok_t) = _timed(
            lambda hw=hw: grid_sample_to_slm_grid(image, geo, hw, spec.pitch_m), r)
        t_k, (v_k, ok_k) = _timed(lambda hw=hw: to_slm_grid(image, geo, hw, spec.pitch_m), r)
        out[f"warp to SLM grid {hw[0]}x{hw[1]}"] = {
            "baseline": "NumPy grid + torch grid_sample",
            "library": "kornia warp_affine (to_slm_grid)", "shape": list(hw), "baseline_ms": t_t,
            "library_ms": t_k, "masks_equal": bool(np.array_equal(ok_t, ok_k)),
            "max_abs_diff": float(np.abs(v_t - v_k)[ok_t].max())}
    gen = torch.Generator().manual_seed(args.seed)
    # A focal stack's worth of images in [0, 1] (5 planes x 3 colours) and a noisy copy.
    x = F.avg_pool2d(torch.rand(15, 1, 520, 520, generator=gen), 9, 1)[:, 0].clamp(0, 1)
    y = (x + 0.05 * torch.randn(x.shape, generator=gen)).clamp(0, 1)
    t_s, s_ours = _timed(lambda: ssim_map(x, y), r)
    t_k, s_k = _timed(lambda: kornia_ssim_map(x, y), r)
    exact = ssim_map(x.double(), y.double())
    out["SSIM map (float32)"] = {
        "baseline": "ssim_map (one depthwise 11 x 11 conv2d)", "library": "kornia.metrics.ssim",
        "shape": list(x.shape), "baseline_ms": t_s, "library_ms": t_k,
        "max_abs_diff": float((s_ours - s_k).abs().max()),
        "mean_diff": float(abs(s_ours.double().mean() - s_k.double().mean())),
        "baseline_max_error_vs_float64": float((s_ours.double() - exact).abs().max()),
        "library_max_error_vs_float64": float((s_k.double() - exact).abs().max())}
    return out


def run(args: argparse.Namespace) -> int:
    if args.benches < 1 or args.repeats < 1:
        raise ValueError(f"--benches {args.benches}, --repeats {args.repeats}: must be >= 1")
    machine = describe()
    machine.update(opencv=cv2.__version__, kornia=kornia.__version__)
    print(f"machine: {machine}")
    methods = compare_methods(args)
    seeds = f"{args.seed}..{args.seed + args.benches - 1}"
    print(f"\ncamera geometry, {args.benches} random benches (seeds {seeds}) x 2 views:")
    print(f"{'method':<13}{'fail':>5}{'scale rms':>11}{'max':>9}{'rot rms':>9}{'max':>8}"
          f"{'centre rms':>11}{'max':>7}{'ms/image':>10}")
    for name, m in methods.items():
        print(f"{name:<13}{m['failures']:>5}{m['scale_rms']:>11.2e}{m['scale_max']:>9.2e}"
              f"{m['rotation_rms_deg']:>8.4f}°{m['rotation_max_deg']:>7.4f}°"
              f"{m['centre_rms_px']:>8.3f} px{m['centre_max_px']:>7.3f}"
              f"{m['ms_per_image']:>10.1f}")
        if name != METHODS[0]:
            print("    against " + METHODS[0] + ", cases with a lower / higher error: " +
                  ", ".join(f"{k} {lo} / {hi}" for k, (lo, hi) in
                            m["vs_default_lower_higher"].items()))
        for why in m["why"]:
            print(f"    {why}")
    same = same_values(args)
    print(f"\nsame values (agree to {AGREE:g}), median of {args.repeats}:")
    for name, s in same.items():
        verdict = "agree" if s["max_abs_diff"] <= AGREE else "DIFFER"
        print(f"{name:<28} {s['baseline']}: {s['baseline_ms']:8.2f} ms   {s['library']}: "
              f"{s['library_ms']:8.2f} ms   max |diff| {s['max_abs_diff']:.1e} ({verdict})")
        extra = {k: v for k, v in s.items() if k not in ("baseline", "library", "shape",
                                                         "baseline_ms", "library_ms",
                                                         "max_abs_diff")}
        if extra:
            print(" " * 29 + ", ".join(f"{k} {v:.1e}" if isinstance(v, float) else f"{k} {v}"
                                       for k, v in extra.items()))
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"machine": machine, "seeds": seeds, "methods": methods,
                                "same_values": same}, indent=2))
    print(f"wrote {path}")
    return 0
