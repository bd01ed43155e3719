"""The CPU Gaussian-splat rasteriser: EWA splatting with tile binning, compiled with numba.

Algorithm (3DGS / gsplat semantics, written for two CPU cores):

1. Camera-space means and covariances, once per scene and pose (`_kernels.prepare`); one depth
   sort of the centres, shared by every view that only translates the camera sideways (light
   fields), since a lateral move does not change depth along the optical axis.
2. Per view, per Gaussian: EWA projection `J W S W^T J^T` with `x/z`, `y/z` clamped to 1.3x the
   field of view, the 0.3 px low-pass dilation (or, with `antialias`, the dilation plus opacity
   scaled by `sqrt(det / det_dilated)`, Mip-Splatting's variant), near/far and frustum culling,
   and an opacity-aware extent: the ellipse where `opacity * exp(-q) >= 1/255`, not 3 sigma.
3. Exact ellipse-rectangle tests pick the 16 x 16 tiles each Gaussian touches; one stable counting
   sort by tile over Gaussians already in depth order gives each tile's depth-sorted list.
4. Per tile, front to back: alpha = min(0.99, opacity * exp(-q)), skipped below 1/255; a pixel
   stops before the Gaussian that would take its transmittance below 1e-4; a tile stops when all
   its pixels have. Only each ellipse's pixels are visited.

Outputs: sRGB colour as trained (composited on black), alpha, and expected depth (the
alpha-weighted mean of the centres' camera z, 0 where nothing was drawn; alpha says where).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import Gaussians


@dataclass(frozen=True)
class RasterSettings:
    """`tile_px`: tile edge; `eps2d_px2`: the low-pass dilation added to the 2D covariance's
    diagonal (px^2); `antialias`: also scale opacity to keep each splat's energy (use it for scenes
    trained with it, e.g. Mip-Splatting)."""

    tile_px: int = 16
    eps2d_px2: float = 0.3
    antialias: bool = False

    def __post_init__(self) -> None:
        if not (1 <= self.tile_px <= 256):
            raise ValueError(f"tile_px must be in [1, 256], got {self.tile_px}")
        if not (0 <= self.eps2d_px2 < 100):
            raise ValueError(f"eps2d_px2 must be in [0, 100), got {self.eps2d_px2}")


@dataclass
class Render:
    """One rendered view: `rgb` [3, H, W], `alpha` [H, W], `depth` [H, W], all float32."""

    rgb: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    stats: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Prepared:
    """View-independent work for one scene and one camera rotation/position."""

    pc: np.ndarray
    cov: np.ndarray
    order: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray


def prepare(g: Gaussians, cam: Camera) -> Prepared:
    """Camera-space means/covariances and the depth order of `g` for `cam`'s pose."""
    from nhfd.scene import _kernels as k

    if len(g) == 0:
        z = np.zeros
        return Prepared(z((0, 3)), z((0, 6)), z(0, np.int64), g.opacities, g.sh)
    pc, cov = k.prepare(g.means, g.quats, g.scales, cam.R, cam.t)
    z = pc[:, 2]
    # Only centres in front of the near plane can be drawn; sort just those.
    idx = np.flatnonzero((z >= cam.near) & (z <= cam.far))
    order = idx[np.argsort(z[idx], kind="stable")]
    return Prepared(pc, cov, order, g.opacities, g.sh)


def render_prepared(
    prep: Prepared,
    cam: Camera,
    shift: tuple[float, float] = (0.0, 0.0),
    settings: RasterSettings = RasterSettings(),
    out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> Render:
    """Render `cam` (its intrinsics and size) with the camera centre moved by `(dx, dy, 0)` in its
    own frame (`shift`, scene units) relative to the pose `prep` was made for.

    `out`: optional C-contiguous float32 arrays `(rgb [3, H, W], alpha [H, W], depth [H, W])` to
    render into (every pixel is written), e.g. slices of a light field: no allocation, no copy.
    """
    from nhfd.scene import _kernels as k

    w, h, tile = int(cam.width_px), int(cam.height_px), settings.tile_px
    if out is None:
        rgb = np.empty((3, h, w), np.float32)
        alpha = np.empty((h, w), np.float32)
        depth = np.empty((h, w), np.float32)
    else:
        rgb, alpha, depth = out
        for name, a, shape in (("rgb", rgb, (3, h, w)), ("alpha", alpha, (h, w)),
                               ("depth", depth, (h, w))):  # fmt: skip
            if a.shape != shape or a.dtype != np.float32 or not a.flags.c_contiguous:
                raise ValueError(f"out {name} must be C-contiguous float32 {shape}")
    stats: dict = {"gaussians_in_front": int(prep.order.shape[0]), "visible": 0, "tile_pairs": 0}
    if prep.order.shape[0] == 0:
        for a in (rgb, alpha, depth):
            a.fill(0.0)
        return Render(rgb, alpha, depth, stats)
    t0 = time.perf_counter()
    rec, counts = k.project_view(
        prep.pc, prep.cov, prep.opacities, prep.sh, prep.order,
        np.array(shift, np.float64), cam.R, float(cam.fx), float(cam.fy), float(cam.cx),
        float(cam.cy), w, h, float(cam.near), float(cam.far), float(settings.eps2d_px2),
        bool(settings.antialias), tile,
    )  # fmt: skip
    t1 = time.perf_counter()
    offsets = np.zeros(counts.shape[0] + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    n_tiles = ((w + tile - 1) // tile) * ((h + tile - 1) // tile)
    tiles = k.fill_tile_ids(rec, counts, offsets, tile, w, h)
    starts, gauss = k.sort_by_tile(tiles, counts, offsets, n_tiles)
    t2 = time.perf_counter()
    k.composite(rec, starts, gauss, tile, w, h, rgb, alpha, depth)
    t3 = time.perf_counter()
    stats.update(
        visible=int((counts > 0).sum()),
        tile_pairs=int(offsets[-1]),
        project_ms=1e3 * (t1 - t0),
        bin_ms=1e3 * (t2 - t1),
        composite_ms=1e3 * (t3 - t2),
    )
    return Render(rgb, alpha, depth, stats)


BACKENDS = ("cpu", "gsplat", "auto")


def render(
    g: Gaussians,
    cam: Camera,
    settings: RasterSettings = RasterSettings(),
    backend: str = "cpu",
    device: str = "cuda",
) -> Render:
    """Render one view of `g` from `cam`.

    `backend`: "cpu" (this module), "gsplat" (CUDA; see gsplat_backend), or "auto" (gsplat when
    CUDA and gsplat are present, else the CPU). `device`: the CUDA device gsplat renders on
    ("cuda": the current one, or "cuda:N").
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend != "cpu" and len(g):
        from nhfd.scene import gsplat_backend

        if backend == "gsplat" or gsplat_backend.available():
            t0 = time.perf_counter()
            rgb, alpha, depth = gsplat_backend.render_gsplat(
                g, cam, settings.eps2d_px2, settings.antialias, device
            )
            return Render(
                rgb,
                alpha,
                depth,
                {"backend": "gsplat", "total_ms": 1e3 * (time.perf_counter() - t0)},
            )
    return render_prepared(prepare(g, cam), cam, (0.0, 0.0), settings)
