"""Guesses about a scene that its file does not state: which way is up, and a camera that frames it.

Splat files carry no "up" and no viewpoint. `nhfd scene info` and `nhfd scene render` need both,
so this module makes documented, deterministic guesses; every caller can override them
(`--up`, `--pose`).

Up axis (`detect_up_axis`), a heuristic in this order:

1. Format convention. PlayCanvas/SuperSplat compressed .ply and antimatter15 .splat files are
   almost always trained from COLMAP reconstructions and exported without re-orienting, so they
   keep COLMAP/OpenCV axes where the capture camera's "up" is -y.
2. Shape (INRIA .ply or unknown format). Many object-centric scenes (Blender synthetic renders,
   turntable captures) are much flatter along their up axis than across it: the object sits on
   a ground plane. If the smallest robust extent (1st-99th percentile of the means) is clearly
   smaller than the other two (ratio below `FLAT_RATIO`), that axis is up. Its sign: such scenes
   are trained from views above the object, so the top carries more (and more detailed)
   Gaussians than the underside and the median lies above the mid-range; if the median is too
   close to the middle to tell, the axis's usual convention decides (+z for Blender's z-up, -y
   for OpenCV's y-down, + otherwise).
3. Otherwise -y, the COLMAP/OpenCV convention of the original 3DGS training code.

On the shared scenes: donut.ply (Blender synthetic, INRIA .ply) -> +z by shape (z extent 0.41x
the next, median at 66% of the z range); guitar and tiny-sh (compressed) -> -y by format.

Camera (`suggest_camera`): an orbit around the robust centre (per-axis median of the means) at
the distance where the robust bounding box's projected corners reach `FILL` (80%) of the
half-width or half-height, whichever binds first.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from nhfd.scene.cameras import Camera, intrinsics_from_fov, orbit
from nhfd.scene.gaussians import Gaussians
from nhfd.scene.io import scene_format

__all__ = ["FILL", "FLAT_RATIO", "detect_up_axis", "format_hint", "robust_frame",
           "suggest_camera"]

# An axis counts as "clearly thinnest" when its robust extent is below this fraction of the
# next smallest: the donut is at 0.41, the guitar's thinnest axis at 0.90 (a box-shaped blob).
FLAT_RATIO = 0.6
# The median must sit this far (fraction of the range) from the mid-range to decide the sign.
SIGN_MARGIN = 0.05
# Fewer Gaussians than this say nothing about shape; use the conventions only.
MIN_FOR_SHAPE = 16
# Fraction of the half-image the robust box's projection reaches.
FILL = 0.8
# Sign used when the shape names an axis but not its direction.
_CONVENTIONAL_SIGN = {0: "+x", 1: "-y", 2: "+z"}

_FORMAT_REASON = {
    "compressed": "PlayCanvas compressed .ply files conventionally keep COLMAP/OpenCV axes "
    "(y down)",
    "splat": ".splat files conventionally keep COLMAP/OpenCV axes (y down)",
    # Declared, not conventional: the loader converts these frames into OpenCV's.
    "spz": "declared by the format: .spz stores y-up (RUB) axes, converted to OpenCV",
    "gltf": "declared by the format: glTF is +Y up (LUF axes), converted to OpenCV",
}
HINTS = (None, "compressed", "splat", "ply", "spz", "gltf", "sog")


def format_hint(path: str | Path) -> str | None:
    """The file's format, one of `HINTS` (`nhfd.scene.io.scene_format`: the loader's own
    reading of the header), or None if it is none of these or unreadable."""
    return scene_format(path)


def robust_frame(g: Gaussians) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(centre, lo, hi)`: per-axis median and 1st/99th percentiles of the means (float64), so a
    few floaters far from the object neither move the centre nor set the framing."""
    if len(g) == 0:
        z = np.zeros(3)
        return z, z.copy(), z.copy()
    m = g.means.astype(np.float64)
    lo, hi = np.percentile(m, [1.0, 99.0], axis=0)
    return np.median(m, axis=0), lo, hi


def detect_up_axis(g: Gaussians, hint: str | None = None) -> tuple[str, str]:
    """A guess at the scene's up axis, one of `cameras.AXES`, and a one-line reason.

    `hint` is the file format (one of `HINTS`; see `format_hint`). Formats that declare their
    axes (.spz, glTF) decide; otherwise this is a heuristic (see the module docstring): it is
    right for the shared scenes and for the common conventions, and wrong for a scene that was
    re-oriented by hand; pass `--up` then.
    """
    if hint not in HINTS:
        raise ValueError(f"format hint must be one of {HINTS}, got {hint!r}")
    if hint in ("spz", "gltf"):
        return "-y", _FORMAT_REASON[hint]
    if hint in _FORMAT_REASON:
        return "-y", f"format convention: {_FORMAT_REASON[hint]}"
    shape = _up_from_shape(g)
    if shape is not None:
        return shape
    return "-y", ("no clearly flat axis (or too few Gaussians to tell); assuming the "
                  "COLMAP/OpenCV convention (y down)")


def _up_from_shape(g: Gaussians) -> tuple[str, str] | None:
    """The clearly thinnest axis of the robust box, signed toward the bulk, or None."""
    if len(g) < MIN_FOR_SHAPE:
        return None
    centre, lo, hi = robust_frame(g)
    extent = hi - lo
    order = np.argsort(extent, kind="stable")
    thin, next_ = int(order[0]), int(order[1])
    if not extent[next_] > 0:
        return None
    ratio = float(extent[thin] / extent[next_])
    if ratio >= FLAT_RATIO:
        return None
    name = "xyz"[thin]
    frac = float((centre[thin] - lo[thin]) / extent[thin]) if extent[thin] > 0 else 0.5
    if abs(frac - 0.5) > SIGN_MARGIN:
        axis = ("+" if frac > 0.5 else "-") + name
        why = f"median at {frac:.0%} of the {name} range, so the bulk is on {axis}"
    else:
        axis = _CONVENTIONAL_SIGN[thin]
        why = f"median near the middle of the {name} range, sign by convention"
    return axis, (
        f"shape: the scene is flat along {name} (robust extent {ratio:.2f}x the next axis); {why}"
    )


def suggest_camera(
    g: Gaussians,
    width_px: int,
    height_px: int,
    up: str | np.ndarray,
    fov_x_deg: float = 40.0,
    azimuth_deg: float = 30.0,
    elevation_deg: float = 20.0,
) -> Camera:
    """An orbit camera around the robust centre that frames the robust box at about `FILL` of
    the image (the binding direction), near plane at 1% of the orbit radius. Deterministic."""
    fx, fy, cx, cy = intrinsics_from_fov(width_px, height_px, fov_x_deg)
    centre, lo, hi = robust_frame(g)
    corners = _box_corners(lo, hi, _min_half_size(g))
    # Image-plane limits as tan(angle) from the optical axis, at FILL of the half-image.
    tan_x, tan_y = FILL * cx / fx, FILL * cy / fy
    r_axis, _ = orbit(centre, azimuth_deg, elevation_deg, 1.0, up)
    radius = _framing_radius(corners - centre, r_axis, tan_x, tan_y)
    r, t = orbit(centre, azimuth_deg, elevation_deg, radius, up)
    return Camera(r, t, fx, fy, cx, cy, int(width_px), int(height_px), near=0.01 * radius)


def _min_half_size(g: Gaussians) -> float:
    """Smallest half-size per axis of the framed box: three times the median splat size, so a
    scene of one Gaussian (or a flat one) still gets a finite, non-zero framing distance."""
    if len(g) == 0:
        return 0.5  # nothing to frame: an arbitrary unit-sized view of the origin
    return max(3.0 * float(np.median(g.scales.max(1))), 1e-6)


def _box_corners(lo: np.ndarray, hi: np.ndarray, min_half: float) -> np.ndarray:
    mid, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, min_half)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    return mid + signs * half


def _framing_radius(rel: np.ndarray, r: np.ndarray, tan_x: float, tan_y: float) -> float:
    """Distance from the centre along the viewing axis at which the points `rel` (relative to the
    centre) just reach the image limits. Moving the camera back along its axis shrinks every
    projection monotonically, so bisect between a radius that surely fits and zero."""
    pc = rel @ r.T  # camera axes at radius 0 (camera at the centre); z grows by the radius

    def fill(radius: float) -> float:
        z = pc[:, 2] + radius
        if (z <= 0).any():
            return math.inf
        return float(max((np.abs(pc[:, 0]) / z).max() / tan_x,
                         (np.abs(pc[:, 1]) / z).max() / tan_y))

    reach = float(np.linalg.norm(rel, axis=1).max())
    # A sphere of radius `reach` seen from distance d spans asin(reach / d); this d fits it.
    hi = reach / math.sin(math.atan(min(tan_x, tan_y))) * 1.001
    lo_r = 0.0
    for _ in range(60):  # ~1e-18 relative: deterministic and far below a pixel
        mid = (lo_r + hi) / 2
        if fill(mid) > 1.0:
            lo_r = mid
        else:
            hi = mid
    return hi

