"""Reduce a scene to what its pose envelope can show (issue 24, part 3).

The dataset renders every pose's light field; Gaussians that no view draws, or draws too faintly
to move a pixel by a grey level, and SH bands that change no pixel by a grey level, only cost
render time. `reduce_scene` removes them in three steps, each against the same renderer
(`raster`, `_kernels`) the dataset uses:

1. **Drawn nowhere** (exact, over *every* envelope camera). A Gaussian is culled only if the
   renderer's own projection (`_kernels.project_view`: centre inside `[near, far]`, opacity at
   least 1/255, and its opacity-aware ellipse `opacity * exp(-q) >= 1/255` meeting a tile's
   pixel centres) bins it into no tile of any camera. Such a Gaussian is never composited, so
   every envelope view renders bit for bit the same without it. Light-field views of one pose
   share its rotation and depth order, so one `prepare` serves them, and each further view
   projects only the Gaussians no earlier view drew: the pass costs about one projection of
   the scene per pose.
2. **SH bands** (measured on the check views). The highest band is dropped while the rendered
   change against the original scene stays within `grey_levels / 255` on every check view
   (sRGB clipped to [0, 1], and alpha); the first band that would exceed it is kept.
3. **Faint Gaussians** (weighed on more views, checked on the check views). Each Gaussian's
   largest compositing weight `alpha * T` is recorded by a copy of the compositor over the check
   views and, of every light field in the envelope, its unmoved and four corner views
   (`weight_cameras`: occlusion changes most between them). Gaussians below a threshold
   (starting at what is left of the budget after step 2) are dropped, and the threshold halves
   until the reduced scene renders within `grey_levels / 255` of the original on every check
   view. Gaussians that none of those views draws are kept (their weight was not measured).

Steps 2 and 3 render the check views: all envelope cameras when there are at most
`check_views`, else `check_views` of them spread evenly over the list (a dataset's envelope has
~10^4 light-field views). The report's `max_grey_change` is the final scene's largest change
against the original over the check views, in grey levels; frustum culling adds nothing to it
anywhere in the envelope. Views that were not checked can change more (docs/scenes.md gives the
change measured on held-out views of the shared scenes).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np
from numba import njit, prange

from nhfd.scene import _kernels as k
from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import Gaussians
from nhfd.scene.lightfield import DepthMapping, view_camera
from nhfd.scene.raster import RasterSettings, prepare, render

GREY_LEVEL = 1.0 / 255.0
DEFAULT_CHECK_VIEWS = 24
DEFAULT_TIMING_VIEWS = 4
# Halvings of the contribution threshold before giving up on step 3 (1/2^8 of a grey level).
MAX_HALVINGS = 8
DEFAULT_RASTER = RasterSettings()

__all__ = [
    "GREY_LEVEL",
    "CullReport",
    "envelope_light_field_cameras",
    "max_change",
    "max_weights",
    "reduce_scene",
    "truncate_sh",
    "visible_anywhere",
    "weight_cameras",
]


@dataclass(frozen=True)
class CullReport:
    """What `reduce_scene` kept and what it saved.

    `n_culled_frustum`: drawn by no envelope camera (outside every frustum, behind the near
    plane, or too faint for the renderer to draw at all). `max_grey_change`: the largest change of
    any checked pixel (sRGB clipped to [0, 1], or alpha) between the original and the reduced
    scene, in grey levels (1/255); `sh_grey_change` the part of it measured after dropping SH
    bands only; `sh_next_grey_change` what dropping the band that was kept would have changed
    (None when no band was kept above degree 0, or SH was not pruned). `render_s_before` /
    `_after`: seconds to render `n_views_timed` envelope views (per view the best of three, the
    two scenes alternating) with the original and the reduced scene; on a shared machine they
    move with its load, so `tile_pairs_before` / `_after` give the same views' work as the
    (Gaussian, tile) pairs composited, which does not."""

    n_gaussians_in: int
    n_kept: int
    n_culled_frustum: int
    n_culled_contribution: int
    sh_degree_in: int
    sh_degree_out: int
    max_grey_change: float
    sh_grey_change: float
    grey_levels: float
    contribution_threshold: float
    n_views_envelope: int
    n_views_checked: int
    n_views_timed: int
    n_views_weighed: int
    render_s_before: float
    render_s_after: float
    sh_next_grey_change: float | None = None
    tile_pairs_before: int = 0
    tile_pairs_after: int = 0

    @property
    def kept_fraction(self) -> float:
        """Gaussians kept over Gaussians in (1.0 for an empty scene)."""
        return self.n_kept / self.n_gaussians_in if self.n_gaussians_in else 1.0

    @property
    def render_saved_fraction(self) -> float:
        """The share of render time saved on the timed views (0 when not timed)."""
        b = self.render_s_before
        return (b - self.render_s_after) / b if b > 0 else 0.0

    @property
    def work_saved_fraction(self) -> float:
        """The share of (Gaussian, tile) pairs saved on the timed views (0 when not counted)."""
        b = self.tile_pairs_before
        return (b - self.tile_pairs_after) / b if b > 0 else 0.0

    def to_dict(self) -> dict:
        """Every field and the three fractions, JSON-ready."""
        return {**asdict(self), "kept_fraction": self.kept_fraction,
                "render_saved_fraction": self.render_saved_fraction,
                "work_saved_fraction": self.work_saved_fraction}

    def summary(self) -> str:
        """One line for a person: Gaussians kept, SH degrees, the largest change in grey levels
        and the render time saved (ms)."""
        return (f"kept {self.n_kept} of {self.n_gaussians_in} Gaussians "
                f"({100 * self.kept_fraction:.1f}%: {self.n_culled_frustum} drawn in no view, "
                f"{self.n_culled_contribution} too faint), SH degree {self.sh_degree_in} -> "
                f"{self.sh_degree_out}; max change {self.max_grey_change:.2f} grey levels over "
                f"{self.n_views_checked} of {self.n_views_envelope} views; render "
                f"{1e3 * self.render_s_before:.1f} -> {1e3 * self.render_s_after:.1f} ms "
                f"({100 * self.render_saved_fraction:.0f}% saved, {self.n_views_timed} views; "
                f"{100 * self.work_saved_fraction:.0f}% fewer splat-tile pairs)")


def envelope_light_field_cameras(
    cameras: Sequence[Camera],
    mapping: DepthMapping,
    pitch_m: float,
    taus: Sequence[np.ndarray],
) -> list[Camera]:
    """Every view a dataset renders for these pose cameras: each camera's light field for each
    set of slopes in `taus` (one per group of colours sharing views), as `lightfield.iter_views`
    places them (`view_camera`), pose-major."""
    out = []
    for cam in cameras:
        for tau in taus:
            for ty in np.asarray(tau, np.float64):
                for tx in np.asarray(tau, np.float64):
                    out.append(view_camera(cam, mapping, pitch_m, float(tx), float(ty))[1])
    return out


def _groups(cameras: Sequence[Camera]) -> list[tuple[Camera, list[tuple[int, Camera, tuple]]]]:
    """Cameras that differ only by a sideways move in their own frame (a light field): one
    `prepare` each. Returns `(base, [(index, camera, shift)])`, shift as `render_prepared`
    takes it (`Camera.translated(dx, dy)` has `t' = t - (dx, dy, 0)`)."""
    groups: dict[tuple, tuple[Camera, list]] = {}
    for i, cam in enumerate(cameras):
        key = (cam.R.tobytes(), float(cam.t[2]), float(cam.near), float(cam.far))
        if key not in groups:
            groups[key] = (cam, [])
        base, members = groups[key]
        d = base.t - cam.t
        members.append((i, cam, (float(d[0]), float(d[1]))))
    return list(groups.values())


def _project(prep, cam: Camera, shift: tuple, order: np.ndarray, settings: RasterSettings):
    return k.project_view(
        prep.pc, prep.cov, prep.opacities, prep.sh, order, np.array(shift, np.float64), cam.R,
        float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy), int(cam.width_px),
        int(cam.height_px), float(cam.near), float(cam.far), float(settings.eps2d_px2),
        bool(settings.antialias), settings.tile_px,
    )  # fmt: skip


def visible_anywhere(g: Gaussians, cameras: Sequence[Camera],
                     settings: RasterSettings = DEFAULT_RASTER) -> np.ndarray:
    """Boolean [N]: the renderer bins the Gaussian into at least one tile of at least one camera
    (the exact test `render` applies; a Gaussian outside it is never composited)."""
    seen = np.zeros(len(g), bool)
    if len(g) == 0:
        return seen
    for base, members in _groups(cameras):
        prep = prepare(g, base)
        for _, cam, shift in members:
            todo = prep.order[~seen[prep.order]]
            if todo.shape[0] == 0:
                break
            _, counts = _project(prep, cam, shift, todo, settings)
            seen[todo[counts > 0]] = True
    return seen


@njit(parallel=True, fastmath=True, cache=True)
def _max_weights_kernel(rec, starts, gauss, tile, width, height, out):
    """`_kernels.composite`'s loop (its tiles, row spans and blending step), recording each record's
    largest weight `alpha * T` instead of accumulating colour. Tiles run in parallel, so each
    thread keeps its own maxima."""
    nx = (width + tile - 1) // tile
    n_tiles = starts.shape[0] - 1
    n_threads = out.shape[0]
    for part in prange(n_threads):
        for t in range(part, n_tiles, n_threads):
            x0, y0, w, h = k.tile_box(t, nx, tile, width, height)
            trans = np.ones((h, w))
            done = np.zeros((h, w), np.bool_)
            n_done = 0
            n_pix = h * w
            for p in range(starts[t], starts[t + 1]):
                if n_done == n_pix:
                    break
                o = gauss[p]
                r = rec[o]
                u, v, a, b, c = r[k.U], r[k.V], r[k.CA], r[k.CB], r[k.CC]
                op, smax = r[k.OP], r[k.SMAX]
                for yy in range(h):
                    j0, j1, dy = k.row_span(u, v, a, b, c, smax, y0 + yy, x0, w)
                    for xx in range(j0, j1 + 1):
                        if done[yy, xx]:
                            continue
                        dx = x0 + xx + 0.5 - u
                        al = min(k.ALPHA_MAX,
                                 op * math.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)))
                        wgt, ended = k.blend(trans, done, yy, xx, al)
                        n_done += ended
                        if wgt > out[part, o]:
                            out[part, o] = wgt


def max_weights(g: Gaussians, cameras: Sequence[Camera],
                settings: RasterSettings = DEFAULT_RASTER) -> np.ndarray:
    """Float64 [N]: each Gaussian's largest compositing weight `alpha * T` over the pixels of
    `cameras`; +inf for a Gaussian none of them bins into a tile (not measured)."""
    import numba

    best = np.full(len(g), -1.0)
    if len(g) == 0:
        return best
    for base, members in _groups(cameras):
        prep = prepare(g, base)
        if prep.order.shape[0] == 0:
            continue
        for _, cam, shift in members:
            rec, counts = _project(prep, cam, shift, prep.order, settings)
            w, h, tile = int(cam.width_px), int(cam.height_px), settings.tile_px
            offsets = np.zeros(counts.shape[0] + 1, np.int64)
            np.cumsum(counts, out=offsets[1:])
            tiles = k.fill_tile_ids(rec, counts, offsets, tile, w, h)
            n_tiles = ((w + tile - 1) // tile) * ((h + tile - 1) // tile)
            starts, gauss = k.sort_by_tile(tiles, counts, offsets, n_tiles)
            out = np.zeros((numba.get_num_threads(), counts.shape[0]))
            _max_weights_kernel(rec, starts, gauss, tile, w, h, out)
            np.maximum.at(best, prep.order, np.where(counts > 0, out.max(0), -1.0))
    return np.where(best < 0, np.inf, best)


def weight_cameras(cameras: Sequence[Camera]) -> list[Camera]:
    """Of each light field (cameras sharing a rotation), the unmoved views and the four corner
    views (extreme sideways moves): where occlusion differs most across the field."""
    out = []
    for _, members in _groups(cameras):
        shifts = np.array([m[2] for m in members])
        pick = set(np.flatnonzero((shifts == 0).all(1)).tolist())
        for sx in (shifts[:, 0].min(), shifts[:, 0].max()):
            for sy in (shifts[:, 1].min(), shifts[:, 1].max()):
                pick.add(int(np.argmin(np.hypot(shifts[:, 0] - sx, shifts[:, 1] - sy))))
        out.extend(members[i][1] for i in sorted(pick))
    return out


def truncate_sh(g: Gaussians, degree: int) -> Gaussians:
    """`g` with SH bands above `degree` dropped."""
    if not 0 <= degree <= g.sh_degree:
        raise ValueError(f"SH degree must be in [0, {g.sh_degree}], got {degree}")
    return replace(g, sh=np.ascontiguousarray(g.sh[:, : (degree + 1) ** 2]))


def _shown(r) -> tuple[np.ndarray, np.ndarray]:
    return np.clip(r.rgb, 0.0, 1.0), r.alpha


def max_change(g: Gaussians, cameras: Sequence[Camera], reference: Sequence,
               settings: RasterSettings = DEFAULT_RASTER) -> float:
    """Largest absolute change (full scale 1) of clipped sRGB or alpha between `g`'s renders of
    `cameras` and `reference` (`(rgb, alpha)` per camera)."""
    worst = 0.0
    for cam, (rgb0, a0) in zip(cameras, reference, strict=True):
        rgb, a = _shown(render(g, cam, settings))
        worst = max(worst, float(np.abs(rgb - rgb0).max()), float(np.abs(a - a0).max()))
    return worst


def _spread(n: int, count: int) -> list[int]:
    if n <= count:
        return list(range(n))
    return sorted({round(float(v)) for v in np.linspace(0, n - 1, count)})


def _render_seconds(a: Gaussians, b: Gaussians, cameras: Sequence[Camera],
                    settings: RasterSettings, rounds: int = 3) -> tuple[float, float, int, int]:
    """Seconds to render `cameras` with `a` and with `b`: per view the best of `rounds`, the two
    scenes alternating, so that load from other processes on a shared machine falls on both;
    and the (Gaussian, tile) pairs each composited, a measure of work that no load changes."""
    seconds, pairs = [0.0, 0.0], [0, 0]
    for cam in cameras:
        best, work = [math.inf, math.inf], [0, 0]
        for _ in range(rounds):
            for j, g in enumerate((a, b)):
                t0 = time.perf_counter()
                stats = render(g, cam, settings).stats
                best[j] = min(best[j], time.perf_counter() - t0)
                work[j] = int(stats.get("tile_pairs", 0))
        for j in range(2):
            seconds[j] += best[j]
            pairs[j] += work[j]
    return seconds[0], seconds[1], pairs[0], pairs[1]


def reduce_scene(
    gaussians: Gaussians,
    cameras: Sequence[Camera],
    *,
    grey_levels: float = 1.0,
    settings: RasterSettings = DEFAULT_RASTER,
    check_views: int = DEFAULT_CHECK_VIEWS,
    timing_views: int = DEFAULT_TIMING_VIEWS,
    prune_sh: bool = True,
    cull_faint: bool = True,
) -> tuple[Gaussians, CullReport]:
    """The part of `gaussians` that the envelope `cameras` (every view the dataset will render,
    light-field views included; see `envelope_light_field_cameras`) can show, within
    `grey_levels` grey levels (1/255 of full scale) per pixel; see the module docstring."""
    g = gaussians
    if not (isinstance(grey_levels, (int, float)) and math.isfinite(grey_levels)
            and 0.0 <= grey_levels <= 255.0):
        raise ValueError(f"grey_levels must be in [0, 255], got {grey_levels}")
    cameras = list(cameras)
    if not cameras:
        raise ValueError("cameras: need at least one envelope camera, got none")
    if any(not isinstance(c, Camera) for c in cameras):
        raise ValueError("cameras must be nhfd.scene.cameras.Camera objects")
    if check_views < 1 or timing_views < 0:
        raise ValueError(f"check_views must be >= 1 and timing_views >= 0, got {check_views} "
                         f"and {timing_views}")
    tol = grey_levels * GREY_LEVEL
    n_in, deg_in = len(g), g.sh_degree

    seen = visible_anywhere(g, cameras, settings)
    reduced = g if seen.all() else g.subset(np.flatnonzero(seen))
    n_frustum = n_in - len(reduced)

    checks = [cameras[i] for i in _spread(len(cameras), check_views)]
    reference = [_shown(render(g, cam, settings)) for cam in checks]

    sh_change, sh_next = 0.0, None
    while prune_sh and reduced.sh_degree > 0:
        candidate = truncate_sh(reduced, reduced.sh_degree - 1)
        change = max_change(candidate, checks, reference, settings)
        if change > tol:
            sh_next = change / GREY_LEVEL
            break
        reduced, sh_change = candidate, change

    n_faint, threshold, change_now, n_weighed = 0, 0.0, sh_change, 0
    if cull_faint and len(reduced) and tol - sh_change > 0:
        weighed = checks + weight_cameras(cameras)
        n_weighed = len(weighed)
        weights = max_weights(reduced, weighed, settings)
        t = tol - sh_change
        for _ in range(MAX_HALVINGS + 1):
            drop = weights < t
            if not drop.any():
                break
            candidate = reduced.subset(np.flatnonzero(~drop))
            change = max_change(candidate, checks, reference, settings)
            if change <= tol:
                reduced, n_faint, threshold, change_now = candidate, int(drop.sum()), t, change
                break
            t /= 2

    if change_now == 0.0 and len(reduced) < n_in:
        # Only frustum culling ran: equal by construction; measured all the same.
        change_now = max_change(reduced, checks, reference, settings)
    timed = [checks[i] for i in _spread(len(checks), timing_views)] if timing_views else []
    if reduced is g:
        before, _, pairs_before, _ = _render_seconds(g, g, timed, settings, rounds=2)
        after, pairs_after = before, pairs_before
    else:
        before, after, pairs_before, pairs_after = _render_seconds(g, reduced, timed, settings)
    report = CullReport(
        n_gaussians_in=n_in, n_kept=len(reduced), n_culled_frustum=n_frustum,
        n_culled_contribution=n_faint, sh_degree_in=deg_in, sh_degree_out=reduced.sh_degree,
        max_grey_change=change_now / GREY_LEVEL, sh_grey_change=sh_change / GREY_LEVEL,
        grey_levels=float(grey_levels), contribution_threshold=threshold,
        n_views_envelope=len(cameras), n_views_checked=len(checks), n_views_timed=len(timed),
        n_views_weighed=n_weighed, render_s_before=before, render_s_after=after,
        sh_next_grey_change=sh_next, tile_pairs_before=pairs_before,
        tile_pairs_after=pairs_after,
    )  # fmt: skip
    return reduced, report

