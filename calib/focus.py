"""Depth mapping and phase sign from the dot focal stacks.

Each dot `k` of the dot hologram is designed to focus at `z_k` (SLM space). Imaged through the
bench, it is sharpest at the stage reading

    s_peak = s0 + (sign z_k - offset_c) / scale          (colour c, offset_G = 0 by definition)

where `scale` is SLM-space metres per metre of stage travel (1 / M^2 for a camera behind a relay
of lateral magnification M), `s0` the reading at which green images the SLM plane and `sign` the
bench's phase sign (a conjugate hologram focuses at -z_k). The peaks are estimated per dot (a
log-parabola through the samples around the maximum, then a symmetry refinement: the on-axis
intensity of a square pupil is even in defocus), and the line is fitted by least squares with
outliers rejected; its covariance gives the uncertainties.

The peaks are biased by about a tenth of the depth of field (sampled, lopsided curves that
neighbouring dots and the coding haze interfere with), which is enough for the phase sign (the
slope's sign, tens of sigma) and as the starting point of the model fit in
`nhfd.calib.bench_model`, which gives the calibration's depth mapping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

STAGE_M_PER_MM = 1e-3


class FocusError(ValueError):
    """The focal stacks do not determine the depth mapping; the message says why."""


def dot_metric(stack: np.ndarray, colrow: np.ndarray, radius_px: float) -> np.ndarray:
    """Mean intensity in a disk around each dot: [S, h, w] stack, [N, 2] positions -> [S, N]
    (NaN where the disk leaves the image)."""
    s, h, w = stack.shape
    r = math.ceil(radius_px)
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = dx**2 + dy**2 <= radius_px**2
    out = np.full((s, len(colrow)), np.nan)
    for k, (c, rw) in enumerate(colrow):
        ci, ri = round(c), round(rw)
        if ri - r < 0 or ci - r < 0 or ri + r >= h or ci + r >= w:
            continue
        win = stack[:, ri - r : ri + r + 1, ci - r : ci + r + 1]
        out[:, k] = win[:, disk].mean(axis=1)
    return out


def peak_position(x: np.ndarray, m: np.ndarray) -> float | None:
    """Where a sampled, even-shaped peak `m(x)` (x increasing) is highest, or None when the
    maximum lies at the sweep's end (the focus is not bracketed)."""
    if not np.isfinite(m).all() or len(x) < 5:
        return None
    k = int(np.argmax(m))
    if k < 2 or k > len(x) - 3:
        return None
    # Log-parabola (a Gaussian) through every sample above 30% of the peak, weighted by the
    # signal: the top of the curve carries the position, the tails mostly neighbours' light.
    sel = np.flatnonzero(m >= 0.3 * m[k])
    sel = sel[(sel >= k - 4) & (sel <= k + 4)]
    if len(sel) < 3:
        return None
    y = np.log(np.clip(m[sel], 1e-12, None))
    a, b, _ = np.polyfit(x[sel] - x[k], y, 2, w=m[sel] / m[k])
    if a >= 0:
        return None
    c = float(x[k] - b / (2 * a))
    if not x[0] < c < x[-1]:
        return None
    return c


@dataclass(frozen=True)
class DepthFit:
    """The stage <-> depth mapping. `stage_scale`: SLM-space metres per metre of stage;
    `stage_at_slm_mm`: the reading at which green images the SLM plane; `z_offset_m`: per
    colour (green 0). Standard deviations alongside; `rms_mm` is the residual of the peaks."""

    phase_sign: int
    stage_scale: float
    stage_at_slm_mm: float
    z_offset_m: tuple[float, float, float]
    stage_scale_std: float
    stage_at_slm_std_mm: float
    z_offset_std_m: tuple[float, float, float]
    rms_mm: float
    n_peaks: int
    sign_margin: float  # |slope| / its standard deviation

    def z_m(self, stage_mm: float, colour: int) -> float:
        """The SLM-space depth (m) that `colour` (0 R, 1 G, 2 B) images at the stage reading
        `stage_mm` (mm)."""
        return (stage_mm - self.stage_at_slm_mm) * STAGE_M_PER_MM * self.stage_scale + \
            self.z_offset_m[colour]

    def stage_mm_for(self, z_m: float, colour: int = 1) -> float:
        """The stage reading (mm) at which `colour` (0 R, 1 G, 2 B; default green) images the
        SLM-space depth `z_m` (m): the inverse of `z_m`."""
        return self.stage_at_slm_mm + (z_m - self.z_offset_m[colour]) / self.stage_scale / \
            STAGE_M_PER_MM


def fit_depth(peaks: list[tuple[int, float, float]]) -> DepthFit:
    """Fit `s_peak = b_c + a z` from (colour, designed z_m, peak stage mm) triples."""
    arr = np.asarray(peaks, np.float64).reshape(-1, 3)
    colours = arr[:, 0].astype(int)
    for c, name in enumerate("RGB"):
        zs = arr[colours == c, 1]
        if len(zs) == 0:
            raise FocusError(f"no bracketed focus for colour {name}: the per-colour focus "
                             "offset is undetermined (widen the stage sweep)")
    if len(np.unique(arr[:, 1])) < 2 or np.ptp(arr[:, 2]) == 0:
        raise FocusError("the dots focus at a single stage position: the stage scale is "
                         "undetermined (capture at several stage positions covering the dot "
                         "depths)")
    keep = np.ones(len(arr), bool)
    for _ in range(3):
        design = np.zeros((len(arr), 4))
        design[np.arange(len(arr)), colours] = 1.0
        design[:, 3] = arr[:, 1] * 1e3  # mm of designed depth
        sol, *_ = np.linalg.lstsq(design[keep], arr[keep, 2], rcond=None)
        res = arr[:, 2] - design @ sol
        mad = float(np.median(np.abs(res[keep] - np.median(res[keep])))) * 1.4826
        new = np.abs(res) <= max(4 * mad, 1e-6)
        if new.sum() < 6 or (new == keep).all():
            break
        keep = new
    d = design[keep]
    dof = max(1, int(keep.sum()) - 4)
    sigma2 = float(res[keep] @ res[keep]) / dof
    try:
        cov = sigma2 * np.linalg.inv(d.T @ d)
    except np.linalg.LinAlgError:
        raise FocusError("the depth mapping is singular: need dots at >= 2 depths per colour "
                         "and stage positions bracketing their focus") from None
    b_r, b_g, b_b, a = sol  # a: stage mm per mm of designed depth
    if a == 0 or not math.isfinite(a):
        raise FocusError("the stage scale is undetermined (zero slope)")
    sign = 1 if a > 0 else -1
    scale = 1.0 / abs(a)
    a_std = math.sqrt(cov[3, 3])
    scale_std = a_std / a**2
    b = (b_r, b_g, b_b)
    offsets = tuple((b_g - b[c]) * scale * STAGE_M_PER_MM for c in range(3))
    off_std = []
    for c in range(3):
        if c == 1:
            off_std.append(0.0)
            continue
        var = cov[1, 1] + cov[c, c] - 2 * cov[1, c]
        off_std.append(math.sqrt(max(var, 0.0)) * scale * STAGE_M_PER_MM)
    return DepthFit(sign, scale, float(b_g), offsets, scale_std,  # type: ignore[arg-type]
                    math.sqrt(cov[1, 1]), tuple(off_std),  # type: ignore[arg-type]
                    math.sqrt(sigma2), int(keep.sum()), abs(a) / max(a_std, 1e-300))
