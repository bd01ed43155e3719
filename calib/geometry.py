"""Camera geometry from the dot hologram: detect dots, identify them, fit a similarity.

The camera sees the SLM plane through `camera_px = A @ xy_m + t` with `A = k R(theta) F`, where
`k` is camera pixels per SLM metre (`magnification / camera_pitch_m`), `R` a rotation (about 180
degrees for a 4f relay) and `F = diag(-1, 1)` when a fold mirror flips x (else the identity).
Camera pixel coordinates are (col, row) with pixel centres at integers; SLM coordinates are
metres from the panel centre (x along columns, y along rows), as in `nhfd.drivers.simcamera`.

Dots are identified without assuming the rotation: the lattice's spacing and orientation (modulo
90 degrees) come from nearest-neighbour vectors, every detected dot gets integer lattice
coordinates, and the eight symmetries of the square lattice and every translation are scored
against the layout's pattern of empty sites (which has no symmetry), so a mirror or a 180 degree
turn is found, not assumed, and part of the lattice may be out of view.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from nhfd.optics.camera_grid import Geometry

from .patterns import DotLayout


class GeometryError(ValueError):
    """The dots do not determine the geometry (too few, ambiguous); the message says why."""


MIN_DOTS = 6


def smooth(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur (kernel out to 3 sigma, reflecting edges) of a 2-D image, in float64."""
    r = max(1, math.ceil(3 * sigma_px))
    # BORDER_REFLECT_101 is NumPy's "reflect" (the edge pixel not repeated).
    return cv2.GaussianBlur(np.asarray(image, np.float64), (2 * r + 1, 2 * r + 1), sigma_px,
                            borderType=cv2.BORDER_REFLECT_101)


# Illumination envelope (camera px): a Gaussian blur over several dot spacings' worth of
# light; and its floor, relative to its brightest, below which nothing counts as lit.
ENVELOPE_SIGMA_PX = 15.0
ENVELOPE_FLOOR = 0.03


def detect_dots(image: np.ndarray, *, threshold: float = 0.4, radius_px: int = 4
                ) -> np.ndarray:
    """Bright compact spots -> centroids [N, 2] (col, row), camera pixels, strongest first.

    The image is band-passed (difference of Gaussians, 1.2 and 5 px) so the coding haze and the
    zero order's smooth background drop out, then divided by the local illumination (the image
    blurred by ENVELOPE_SIGMA_PX, floored at ENVELOPE_FLOOR of its peak), so that dots at the
    dim edge of a beam smaller than the panel count as much as those at its centre. A local
    maximum (none higher within 2 `radius_px`: an aberrated spot's side lobes are not dots)
    counts when it reaches `threshold` of the median of the ten strongest maxima (a robust
    "dot height" that a few hot or saturated pixels cannot set). Centroids are intensity means
    over a (2 radius + 1)^2 window of the band-passed image, clipped at zero."""
    img = np.nan_to_num(np.asarray(image, np.float64))
    if img.ndim != 2:
        raise GeometryError(f"dot image must be 2-D, got shape {img.shape}")
    s = smooth(img, 1.2) - smooth(img, 5.0)
    env = smooth(np.clip(img, 0, None), ENVELOPE_SIGMA_PX)
    s = s / np.maximum(env, ENVELOPE_FLOOR * max(float(env.max()), 1e-300))
    r = radius_px
    q = 2 * r
    # Grey dilation is the maximum over the square window (outside the image counts as -inf).
    local_max = cv2.dilate(s, np.ones((2 * q + 1, 2 * q + 1), np.uint8),
                           borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    lit = env >= ENVELOPE_FLOOR * max(float(env.max()), 1e-300)
    cand = np.argwhere((s >= local_max) & (s > 0) & lit)
    if len(cand) == 0:
        return np.zeros((0, 2))
    # Strongest first (identify_dots takes the lattice from the strongest).
    cand = cand[np.argsort(-s[cand[:, 0], cand[:, 1]], kind="stable")]
    values = s[cand[:, 0], cand[:, 1]]
    height = float(np.median(values[:10]))
    peaks = cand[values >= threshold * height]
    h, w = img.shape
    out = []
    for row, col in peaks:
        r0, r1 = max(0, row - r), min(h, row + r + 1)
        c0, c1 = max(0, col - r), min(w, col + r + 1)
        if r1 - r0 < 2 * r + 1 or c1 - c0 < 2 * r + 1:
            continue  # cut by the image edge: its centroid would be biased
        win = np.clip(s[r0:r1, c0:c1], 0, None)
        total = win.sum()
        if total <= 0:
            continue
        rr, cc = np.mgrid[r0:r1, c0:c1]
        out.append(((cc * win).sum() / total, (rr * win).sum() / total))
    return np.asarray(out, np.float64).reshape(-1, 2)


# The eight symmetries of the square lattice as integer matrices acting on (i, j).
_D4 = [np.array(m) for m in (
    [[1, 0], [0, 1]], [[0, -1], [1, 0]], [[-1, 0], [0, -1]], [[0, 1], [-1, 0]],
    [[-1, 0], [0, 1]], [[0, 1], [1, 0]], [[1, 0], [0, -1]], [[0, -1], [-1, 0]])]


def identify_dots(points: np.ndarray, layout: DotLayout) -> np.ndarray:
    """Index into the layout for each detected point (-1: not a dot of the layout)."""
    n = len(points)
    if n < MIN_DOTS:
        raise GeometryError(f"found {n} dots, need at least {MIN_DOTS}: is the dot hologram "
                            "in view and lit?")
    # The lattice's spacing and orientation from the stronger half of the points (detect_dots
    # lists them strongest first): stray detections (haze, an aberrated spot's side lobes, the
    # panel's edge) are weaker than the dots and would pull the nearest-neighbour spacing.
    strong = points[: max(MIN_DOTS, (n + 1) // 2)]
    d = np.linalg.norm(strong[:, None] - strong[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    nn = d.argmin(axis=1)
    vec = strong[nn] - strong
    length = np.linalg.norm(vec, axis=1)
    spacing = float(np.median(length))
    # Where the dots' brightness varies over the panel (crosstalk, unmodulated light), the
    # stronger half can be every other dot, whose nearest neighbours are the lattice's
    # diagonals: a lattice at 1/sqrt(2) of that spacing that most of the strong points sit on
    # (a neighbour among all the points at that distance) is the dots' own.
    d_all = np.linalg.norm(strong[:, None] - points[None], axis=-1)
    d_all[d_all == 0] = np.inf
    finer = spacing / math.sqrt(2)
    near = np.abs(d_all / finer - 1) < 0.1
    has = near.any(axis=1)
    if has.mean() > 0.5:  # each such point's step is to that neighbour (the rest, diagonals,
        vec[has] = points[near.argmax(axis=1)[has]] - strong[has]  # fall out of `steps`)
        length = np.linalg.norm(vec, axis=1)
        spacing = float(np.median(length[has]))
    # Orientation modulo 90 degrees: the mean of exp(4 i phi) over the lattice steps.
    steps = np.abs(length / spacing - 1) < 0.2
    if not steps.any():
        # Stray points only (haze, noise): no two at the lattice's spacing (which is their
        # median nearest-neighbour distance, so this takes scattered, uneven points).
        raise GeometryError(f"the {n} detected spots form no lattice: is the dot hologram "
                            "in view and in focus?")
    phi = np.arctan2(vec[steps, 1], vec[steps, 0])
    theta = float(np.angle(np.exp(4j * phi).mean()) / 4)
    basis = spacing * np.array([[math.cos(theta), -math.sin(theta)],
                                [math.sin(theta), math.cos(theta)]])
    lat = np.linalg.solve(basis, (points - points[0]).T).T
    # The lattice's origin by consensus of the strong points with a lattice neighbour (a
    # single point may be a stray detection): the circular mean of their fractional lattice
    # coordinates.
    frac = lat[: len(strong)][steps] if steps.sum() >= MIN_DOTS else lat
    lat -= np.angle(np.exp(2j * math.pi * frac).mean(axis=0)) / (2 * math.pi)
    ab = np.rint(lat).astype(int)
    on_lattice = np.linalg.norm(lat - ab, axis=1) < 0.3
    # Refine the lattice (origin and both steps) on the points that sit on it: stray points
    # bias the nearest-neighbour spacing, and a spacing a few percent off puts the far dots
    # between sites.
    for _ in range(3):
        if on_lattice.sum() < MIN_DOTS:
            break
        design = np.concatenate([np.ones((int(on_lattice.sum()), 1)), ab[on_lattice]], 1)
        sol, *_ = np.linalg.lstsq(design, points[on_lattice], rcond=None)
        if np.linalg.matrix_rank(design) < 3:
            break
        lat = np.linalg.solve(sol[1:].T, (points - sol[0]).T).T
        ab = np.rint(lat).astype(int)
        on_lattice = np.linalg.norm(lat - ab, axis=1) < 0.3
    nx, ny = layout.shape_ij
    present = np.zeros((nx, ny), bool)
    present[layout.ij[:, 0], layout.ij[:, 1]] = True
    index = -np.ones((nx, ny), int)
    index[layout.ij[:, 0], layout.ij[:, 1]] = np.arange(len(layout.ij))
    scores = []
    for t_idx, tm in enumerate(_D4):
        mapped0 = ab[on_lattice] @ tm.T
        for i0 in range(nx):
            for j0 in range(ny):
                m = mapped0 + np.array([i0, j0])
                inside = (m[:, 0] >= 0) & (m[:, 0] < nx) & (m[:, 1] >= 0) & (m[:, 1] < ny)
                hit = np.zeros(len(m), bool)
                hit[inside] = present[m[inside, 0], m[inside, 1]]
                # A detected dot on an empty or outside site contradicts the hypothesis.
                scores.append((int(hit.sum()) - 2 * int((~hit).sum()), t_idx, i0, j0))
    scores.sort(reverse=True)
    best, second = scores[0], scores[1]
    if best[0] < MIN_DOTS or best[0] - second[0] < 3:
        raise GeometryError(
            f"cannot identify the dot lattice: best match {best[0]}, next {second[0]} "
            f"({int(on_lattice.sum())} dots on the lattice): too few dots in view?")
    _, t_idx, i0, j0 = best
    m = ab @ _D4[t_idx].T + np.array([i0, j0])
    out = -np.ones(n, int)
    for k in np.flatnonzero(on_lattice):
        i, j = m[k]
        if 0 <= i < nx and 0 <= j < ny and present[i, j]:
            out[k] = index[i, j]
    return out


def fit_similarity(xy_m: np.ndarray, colrow: np.ndarray) -> Geometry:
    """Least-squares similarity (with or without the x mirror) from matched points; the model
    with the smaller residual wins."""
    n = len(xy_m)
    if n < 3:
        raise GeometryError(f"{n} matched dots: need at least 3 for a similarity")
    x, y = xy_m[:, 0], xy_m[:, 1]
    best = None
    for mirror in (False, True):
        xs = -x if mirror else x
        # col = p xs - q y + tx ; row = q xs + p y + ty
        rows = np.zeros((2 * n, 4))
        rows[:n] = np.stack([xs, -y, np.ones(n), np.zeros(n)], 1)
        rows[n:] = np.stack([y, xs, np.zeros(n), np.ones(n)], 1)
        rhs = np.concatenate([colrow[:, 0], colrow[:, 1]])
        sol, *_ = np.linalg.lstsq(rows, rhs, rcond=None)
        res = rhs - rows @ sol
        sse = float(res @ res)
        if best is None or sse < best[0]:
            best = (sse, mirror, sol, rows)
    assert best is not None
    sse, mirror, (p, q, tx, ty), rows = best
    dof = max(1, 2 * n - 4)
    sigma2 = sse / dof
    cov = sigma2 * np.linalg.inv(rows.T @ rows)
    k = math.hypot(p, q)
    # k = |(p, q)|, angle = atan2(q, p): first-order error propagation.
    jk = np.array([p / k, q / k])
    ja = np.array([-q / k**2, p / k**2])
    k_std = float(math.sqrt(max(0.0, jk @ cov[:2, :2] @ jk)))
    a_std = float(math.degrees(math.sqrt(max(0.0, ja @ cov[:2, :2] @ ja))))
    rot = math.degrees(math.atan2(q, p)) % 360.0
    return Geometry(k, rot, mirror, (float(tx), float(ty)), math.sqrt(sse / n), n, k_std, a_std)


# OpenCV's RANSAC reprojection threshold (camera px): four times the centroid scatter of
# in-focus dots on the simulated benches (0.25 px RMS); dots that sit further from the
# similarity (defocused depth groups, haze on a centroid) bias it and are left out.
RANSAC_THRESHOLD_PX = 1.0


def ransac_inliers(xy_m: np.ndarray, colrow: np.ndarray) -> np.ndarray:
    """Which matched dots fit one similarity to RANSAC_THRESHOLD_PX: OpenCV's
    `estimateAffinePartial2D` (rotation, uniform scale, shift) under both mirror hypotheses, the
    one with more inliers (then the smaller residual) kept. Its random sampling starts from a
    fixed seed on every call, so the same points give the same inliers."""
    best = None
    for mirror in (False, True):
        src = np.asarray(xy_m, np.float64) * np.array([-1.0 if mirror else 1.0, 1.0])
        m, inliers = cv2.estimateAffinePartial2D(
            src, np.asarray(colrow, np.float64), method=cv2.RANSAC,
            ransacReprojThreshold=RANSAC_THRESHOLD_PX, refineIters=0)
        if m is None:
            continue
        ok = inliers[:, 0] > 0
        res = np.linalg.norm(src[ok] @ m[:, :2].T + m[:, 2] - colrow[ok], axis=1)
        score = (int(ok.sum()), -float(res @ res))
        if best is None or score > best[0]:
            best = (score, ok)
    if best is None or best[0][0] < 3:
        raise GeometryError(f"no similarity fits 3 of the {len(xy_m)} identified dots to "
                            f"{RANSAC_THRESHOLD_PX} px")
    return best[1]


def fit_geometry(image: np.ndarray, layout: DotLayout) -> tuple[Geometry, np.ndarray, np.ndarray]:
    """Detect, identify and fit. Returns the geometry, the matched centroids [M, 2] and their
    layout indices [M]. The dots that fit are OpenCV's RANSAC inliers (`ransac_inliers`); the
    geometry and its uncertainties are the least-squares similarity on them (OpenCV's own
    refinement converges to the same similarity, within 1e-7, but gives no uncertainties).
    `nhfd bench geometry` compares this with the least squares alone and with OpenCV's blob
    detector on random benches."""
    pts = detect_dots(image)
    idx = identify_dots(pts, layout)
    ok = idx >= 0
    pts, idx = pts[ok], idx[ok]
    keep = ransac_inliers(layout.xy_m[idx], pts)
    pts, idx = pts[keep], idx[keep]
    return fit_similarity(layout.xy_m[idx], pts), pts, idx
