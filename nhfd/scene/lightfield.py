"""The light field on the reference plane, rendered with translated cameras (docs/physics.md,
"Rendering the light field with translated cameras").

Directions are the STFT bins of a `W x W` hogel window: `fx_k = k / (W p)`, `tau_k =
tan(asin(lambda fx_k))`, and only bins inside the aperture, `-f_cut <= fx_k < f_cut` (half-open,
like an fftfreq grid), are rendered. View `(j, k)` is the central camera moved by
`(c_j, c_k, 0)` in its own frame, `c = b tau / (p f)`, with the principal point moved to
`cx - a tau_j / p`, `cy - a tau_k / p`, where `z_h = a + b / d` is the scene's depth mapping. A
point at hologram depth `z_h` then sits at `u = u_0 - z_h tau / p` in view `tau`.

All views share the pose's rotation, so camera-space covariances and the depth order are
computed once (`raster.prepare`); each view re-projects, re-bins and composites.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import Gaussians
from nhfd.scene.raster import RasterSettings, Render, prepare, render_prepared
from nhfd.spec import PITCH_RANGE_M, WAVELENGTH_RANGE_M


@dataclass(frozen=True)
class DepthMapping:
    """`z_h(d) = a_m + b_m / d`: scene depth `d` (scene units, along the central camera's axis) to
    hologram depth from the reference plane (m). One mapping per scene (docs/physics.md, "The
    hologram volume and the scene-to-volume mapping")."""

    a_m: float
    b_m: float

    @staticmethod
    def from_range(d_near: float, d_far: float, z_min_m: float, z_max_m: float) -> DepthMapping:
        """`d_near` lands at `z_max_m` (nearest the viewer) and `d_far` at `z_min_m`."""
        if not (math.isfinite(d_near) and math.isfinite(d_far) and 0 < d_near < d_far):
            raise ValueError(f"need 0 < d_near < d_far, got d_near={d_near}, d_far={d_far}")
        if not (z_min_m < z_max_m):
            raise ValueError(f"need z_min < z_max, got {z_min_m} and {z_max_m} m")
        b = (z_max_m - z_min_m) / (1.0 / d_near - 1.0 / d_far)
        return DepthMapping(z_min_m - b / d_far, b)

    def z_h(self, depth: np.ndarray) -> np.ndarray:
        """Hologram depth (m) of scene depth `depth`; NaN-free for depth > 0."""
        return self.a_m + self.b_m / np.asarray(depth, np.float64)


def _check_optics(wavelength_m: float, pitch_m: float, f_cut_per_px: float) -> None:
    (w_lo, w_hi), (p_lo, p_hi) = WAVELENGTH_RANGE_M, PITCH_RANGE_M
    if not (w_lo <= wavelength_m <= w_hi):
        raise ValueError(f"wavelength must be in [{w_lo * 1e9:g}, {w_hi * 1e9:g}] nm, got "
                         f"{wavelength_m * 1e9:.4g} nm")
    if not (p_lo <= pitch_m <= p_hi):
        raise ValueError(f"pitch must be in [{p_lo * 1e6:g}, {p_hi * 1e6:g}] um, got "
                         f"{pitch_m * 1e6:.4g} um")
    if not (0 < f_cut_per_px <= 0.5):
        raise ValueError(f"aperture cutoff must be in (0, 0.5] cycles/px, got {f_cut_per_px}")


def hogel_window(
    wavelength_m: float, pitch_m: float, z_abs_max_m: float, f_cut_per_px: float
) -> int:
    """The least even `W` whose window covers the widest cone in the volume:
    `W >= 2 max|z_h| tan(theta_cut) / p`, `sin(theta_cut) = lambda f_cut / p` (docs/physics.md,
    "Light field sampling (per wavelength)")."""
    _check_optics(wavelength_m, pitch_m, f_cut_per_px)
    if not (math.isfinite(z_abs_max_m) and z_abs_max_m > 0):
        raise ValueError(f"volume half depth must be positive, got {z_abs_max_m} m")
    sin_cut = wavelength_m * f_cut_per_px / pitch_m
    w = 2 * z_abs_max_m * math.tan(math.asin(sin_cut)) / pitch_m
    return max(2, 2 * math.ceil(w / 2 - 1e-9))


def directions(
    window: int, wavelength_m: float, pitch_m: float, f_cut_per_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """STFT bins inside the aperture: `(k, tau_k)`, k integers ascending, `tau = tan(theta)`."""
    _check_optics(wavelength_m, pitch_m, f_cut_per_px)
    if window < 2 or window % 2:
        raise ValueError(f"hogel window W must be an even integer >= 2, got {window}")
    k = np.arange(-window // 2, window // 2)
    k = k[(k / window >= -f_cut_per_px) & (k / window < f_cut_per_px)]
    sin_t = wavelength_m * k / (window * pitch_m)
    return k, np.tan(np.arcsin(sin_t))


def shared_windows(
    wavelengths_m: tuple[float, ...],
    pitch_m: float,
    z_abs_max_m: float,
    f_cut_per_px: float,
    max_extra: int = 8,
) -> tuple[list[int], float]:
    """Windows per colour whose directions coincide, so one set of views serves all colours.

    Equal slopes need `W proportional to lambda`; W must be an even integer, so this searches the
    longest wavelength's W from its minimum up to `max_extra` more for the choice whose rounded
    windows match best, keeping every colour at or above its own minimum. Returns the windows (in
    the order given) and the worst relative slope mismatch. With the defaults (660/520/450 nm,
    +-3 mm, half band): W = 18/14/12, mismatch 2.2% (W = 16 for red would give 9% for blue).
    """
    ref = int(np.argmax(wavelengths_m))
    lam_ref = wavelengths_m[ref]
    minimum = [hogel_window(lam, pitch_m, z_abs_max_m, f_cut_per_px) for lam in wavelengths_m]
    best: tuple[float, list[int]] | None = None
    for w_ref in range(minimum[ref], minimum[ref] + max_extra + 1, 2):
        ws = [max(2, 2 * round(w_ref * lam / lam_ref / 2)) for lam in wavelengths_m]
        if any(w < m for w, m in zip(ws, minimum, strict=True)):
            continue
        err = max(
            abs(w_ref * lam / lam_ref / w - 1) for w, lam in zip(ws, wavelengths_m, strict=True)
        )
        if best is None or err < best[0] - 1e-12:
            best = (err, ws)
    if best is None:
        raise ValueError(
            f"no shared hogel windows within {max_extra} of the minimum for {wavelengths_m} m"
        )
    return best[1], best[0]


def view_camera(
    cam: Camera, mapping: DepthMapping, pitch_m: float, tau_x: float, tau_y: float
) -> tuple[tuple[float, float], Camera]:
    """The camera-frame shift `(c_x, c_y)` (scene units) and the camera with the moved principal
    point for direction `(tau_x, tau_y)`."""
    shift = (
        mapping.b_m * tau_x / (pitch_m * cam.fx),
        mapping.b_m * tau_y / (pitch_m * cam.fy),
    )
    moved = cam.translated(
        shift[0], shift[1], -mapping.a_m * tau_x / pitch_m, -mapping.a_m * tau_y / pitch_m
    )
    return shift, moved


def iter_views(
    g: Gaussians,
    cam: Camera,
    mapping: DepthMapping,
    pitch_m: float,
    taus_x: np.ndarray,
    taus_y: np.ndarray,
    settings: RasterSettings | None = None,
    out: Callable[[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
) -> Iterator[tuple[int, int, Render]]:
    """Yield `(iy, ix, view)` for every direction, rows (y) outer: memory for one view at a time.

    Rendered against the central pose with the view's shift applied to camera-space means, so
    the one `prepare` (covariances, depth order) serves all views. `out(iy, ix)`, if given,
    returns the arrays to render that view into (see `raster.render_prepared`).
    """
    settings = settings or RasterSettings()
    prep = prepare(g, cam)
    for iy, ty in enumerate(np.asarray(taus_y, np.float64)):
        for ix, tx in enumerate(np.asarray(taus_x, np.float64)):
            shift, moved = view_camera(cam, mapping, pitch_m, float(tx), float(ty))
            # Shifting the prepared camera-space means is the same as rendering `moved` from
            # scratch; only its principal point is taken from it.
            intrinsics = replace(cam, cx=moved.cx, cy=moved.cy)
            dest = out(iy, ix) if out is not None else None
            yield iy, ix, render_prepared(prep, intrinsics, shift, settings, dest)


@dataclass
class LightField:
    """Views `[Ky, Kx, ...]`: `rgb` [Ky, Kx, 3, H, W], `depth` and `alpha` [Ky, Kx, H, W], float32;
    `k_x`, `k_y` the STFT bins and `tau_x`, `tau_y` their slopes."""

    rgb: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray
    k_x: np.ndarray
    k_y: np.ndarray
    tau_x: np.ndarray
    tau_y: np.ndarray
    seconds: float


def render_light_field(
    g: Gaussians,
    cam: Camera,
    mapping: DepthMapping,
    wavelength_m: float,
    pitch_m: float,
    window: int,
    f_cut_per_px: float,
    settings: RasterSettings | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> LightField:
    """Render every direction of one colour's light field that passes the aperture."""
    k, tau = directions(window, wavelength_m, pitch_m, f_cut_per_px)
    h, w, n = int(cam.height_px), int(cam.width_px), len(k)
    rgb = np.empty((n, n, 3, h, w), np.float32)
    depth = np.empty((n, n, h, w), np.float32)
    alpha = np.empty((n, n, h, w), np.float32)
    t0 = time.perf_counter()
    views = iter_views(g, cam, mapping, pitch_m, tau, tau, settings,
                       out=lambda iy, ix: (rgb[iy, ix], alpha[iy, ix], depth[iy, ix]))  # fmt: skip
    for done, _ in enumerate(views):
        if progress is not None:
            progress(done + 1, n * n)
    return LightField(rgb, depth, alpha, k, k, tau, tau, time.perf_counter() - t0)
