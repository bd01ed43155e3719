"""The scene-level depth mapping (docs/physics.md, "The hologram volume and the scene-to-volume
mapping").

One mapping per *scene*: `d_near`, `d_far` are robust percentiles of the rendered depth over many
poses (pixels with alpha > 0.5), then `z_h(d) = a + b / d` puts `d_near` at `z_max` and `d_far` at
`z_min`. Either end can be fixed by the caller. The report says where each value came from and how
much the mapping exaggerates depth against a physically scaled display, `b / (p fx)^2`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from nhfd.scene.lightfield import DepthMapping

DEFAULT_PERCENTILES = (1.0, 99.0)
DEFAULT_ALPHA_MIN = 0.5
# Per depth map, at most this many depths are kept (evenly spaced ranks of the sorted valid
# depths, each weighted by the share it stands for): memory stays bounded for hundreds of
# 1024 x 576 maps, and a pooled percentile is off by at most 1/this in rank.
DEFAULT_SAMPLES_PER_MAP = 65536


def depth_exaggeration(mapping: DepthMapping, pitch_m: float, fx_px: float) -> float:
    """How much the mapping stretches depth against a physically scaled display: `b / (p fx)^2`.

    Lateral scale at depth d is `p fx / d` (hologram metres per scene unit), so a physical display
    has `dz = (p fx / d)^2 dd`; the mapping has `dz = b / d^2 dd`; their ratio is `b / (p fx)^2`.
    """
    if not (pitch_m > 0 and fx_px > 0):
        raise ValueError(f"need pitch_m > 0 and fx_px > 0, got {pitch_m} and {fx_px}")
    return float(mapping.b_m / (pitch_m * fx_px) ** 2)


def _sampled_depths(depth: np.ndarray, alpha: np.ndarray, alpha_min: float, cap: int):
    d = np.asarray(depth, np.float64)
    a = np.asarray(alpha, np.float64)
    if d.shape != a.shape:
        raise ValueError(f"depth {d.shape} and alpha {a.shape} maps must have the same shape")
    valid = d[(a > alpha_min) & np.isfinite(d) & (d > 0)]
    n = valid.size
    if n <= cap:
        return valid, np.ones(n)
    # The middle rank of each of `cap` equal blocks: consistent with the midpoint CDF below.
    ranks = np.floor((np.arange(cap) + 0.5) * n / cap).astype(np.int64)
    return np.partition(valid, ranks)[ranks], np.full(cap, n / cap)


def _weighted_percentile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    order = np.argsort(values, kind="stable")
    v, w = values[order], weights[order]
    # Midpoint rule on the weighted CDF; equals np.percentile's "linear" method for unit weights
    # up to the interpolation at the ends (immaterial for robust 1 / 99 % percentiles).
    cdf = (np.cumsum(w) - 0.5 * w) / w.sum()
    return float(np.interp(q / 100.0, cdf, v))


def scene_depth_range(
    depth_maps: Iterable[np.ndarray],
    alpha_maps: Iterable[np.ndarray],
    *,
    percentiles: tuple[float, float] = DEFAULT_PERCENTILES,
    alpha_min: float = DEFAULT_ALPHA_MIN,
    samples_per_map: int = DEFAULT_SAMPLES_PER_MAP,
) -> dict:
    """Robust `(d_near, d_far)` of a scene from depth maps rendered at many poses.

    Args:
        depth_maps, alpha_maps: matching `[H, W]` float maps (scene units; depth is camera z, 0
            where nothing was drawn), one pair per pose; iterables are consumed once, so a
            generator keeps one map in memory at a time.
        percentiles: lower and upper percentile (0-100) of the pooled valid depths.
        alpha_min: a pixel counts where alpha > alpha_min (edges and haze are not content).
        samples_per_map: per-map cap on kept depths (see DEFAULT_SAMPLES_PER_MAP).

    Returns:
        dict with `d_near`, `d_far`, `percentiles`, `alpha_min`, `n_maps`, `n_pixels` (valid
        pixels pooled), `d_min`, `d_max` (the extremes seen).
    """
    lo_q, hi_q = percentiles
    if not (0.0 <= lo_q < hi_q <= 100.0):
        raise ValueError(f"percentiles = {percentiles}: need 0 <= low < high <= 100")
    if samples_per_map < 2:
        raise ValueError(f"samples_per_map = {samples_per_map}: need at least 2")
    vals, wts, n_maps, n_pix = [], [], 0, 0
    for depth, alpha in zip(depth_maps, alpha_maps, strict=True):
        v, w = _sampled_depths(depth, alpha, alpha_min, samples_per_map)
        vals.append(v)
        wts.append(w)
        n_maps += 1
        n_pix += round(float(w.sum()))
    if n_pix == 0:
        raise ValueError(
            f"no pixel with alpha > {alpha_min} in {n_maps} depth maps: the scene is not in view "
            "of these poses (fix d_near and d_far by hand, or check the poses)"
        )
    v, w = np.concatenate(vals), np.concatenate(wts)
    d_near = _weighted_percentile(v, w, lo_q)
    d_far = _weighted_percentile(v, w, hi_q)
    if not d_far > d_near:
        # A flat scene (one depth): give the volume a sliver of depth so the mapping exists.
        d_near, d_far = d_near * (1 - 1e-3), d_far * (1 + 1e-3)
    return {
        "d_near": d_near,
        "d_far": d_far,
        "percentiles": (float(lo_q), float(hi_q)),
        "alpha_min": float(alpha_min),
        "n_maps": n_maps,
        "n_pixels": n_pix,
        "d_min": float(v.min()),
        "d_max": float(v.max()),
    }


def scene_mapping(
    z_min_m: float,
    z_max_m: float,
    pitch_m: float,
    fx_px: float,
    *,
    depth_range: dict | None = None,
    d_near: float | None = None,
    d_far: float | None = None,
) -> tuple[DepthMapping, dict]:
    """The scene's `DepthMapping` for the volume `[z_min_m, z_max_m]` and its report.

    `d_near` / `d_far` given here override the measured `depth_range` (from `scene_depth_range`);
    at least one source must supply each. Returns `(mapping, report)`; the report holds `d_near`,
    `d_far`, their `source` ("measured" / "override" each), `z_min_m`, `z_max_m`, `a_m`, `b_m`,
    `pitch_m`, `fx_px`, `depth_exaggeration` (`b / (p fx)^2`) and the measured range if any.
    """
    measured = depth_range or {}
    near = d_near if d_near is not None else measured.get("d_near")
    far = d_far if d_far is not None else measured.get("d_far")
    if near is None or far is None:
        raise ValueError("d_near and d_far: give depth_range (measured) or both values")
    mapping = DepthMapping.from_range(float(near), float(far), z_min_m, z_max_m)
    report = {
        "d_near": float(near),
        "d_far": float(far),
        "source": {
            "d_near": "override" if d_near is not None else "measured",
            "d_far": "override" if d_far is not None else "measured",
        },
        "z_min_m": float(z_min_m),
        "z_max_m": float(z_max_m),
        "a_m": mapping.a_m,
        "b_m": mapping.b_m,
        "pitch_m": float(pitch_m),
        "fx_px": float(fx_px),
        "depth_exaggeration": depth_exaggeration(mapping, pitch_m, fx_px),
    }
    if depth_range is not None:
        report["measured"] = dict(depth_range)
    if not math.isfinite(report["depth_exaggeration"]):
        raise ValueError("depth exaggeration is not finite: check pitch_m and fx_px")
    return mapping, report
