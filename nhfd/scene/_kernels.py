"""Numba kernels of the CPU rasteriser (see raster.py for the algorithm and conventions).

Per view: `project_view` (parallel over Gaussians) -> `fill_tile_ids` (parallel) ->
`sort_by_tile` (one counting sort, stable, over Gaussians already in depth order) ->
`composite` (parallel over tiles). Everything view-independent (camera-space means and
covariances) comes from `prepare`, once per light field.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from nhfd.scene.gaussians import SH_C0

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4

SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

# Per-Gaussian projection record, float64 columns.
U, V, CA, CB, CC, Z, OP, SMAX, RX, RY, COL_R, COL_G, COL_B = range(13)
NREC = 13


@njit(parallel=True, cache=True)
def prepare(means, quats, scales, R, t):
    """Camera-space means [N, 3] and covariances [N, 6] (xx, xy, xz, yy, yz, zz), float64."""
    n = means.shape[0]
    pc = np.empty((n, 3))
    cov = np.empty((n, 6))
    for i in prange(n):
        for r in range(3):
            pc[i, r] = (R[r, 0] * means[i, 0] + R[r, 1] * means[i, 1] + R[r, 2] * means[i, 2]
                        + t[r])
        w, x, y, z = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        g = np.empty((3, 3))
        g[0, 0] = 1 - 2 * (y * y + z * z)
        g[0, 1] = 2 * (x * y - w * z)
        g[0, 2] = 2 * (x * z + w * y)
        g[1, 0] = 2 * (x * y + w * z)
        g[1, 1] = 1 - 2 * (x * x + z * z)
        g[1, 2] = 2 * (y * z - w * x)
        g[2, 0] = 2 * (x * z - w * y)
        g[2, 1] = 2 * (y * z + w * x)
        g[2, 2] = 1 - 2 * (x * x + y * y)
        # M = R_cam @ R_gauss @ diag(s): camera-space covariance is M M^T.
        m = np.empty((3, 3))
        for r in range(3):
            for c in range(3):
                m[r, c] = (R[r, 0] * g[0, c] + R[r, 1] * g[1, c] + R[r, 2] * g[2, c]) * scales[i, c]
        k = 0
        for r in range(3):
            for c in range(r, 3):
                cov[i, k] = m[r, 0] * m[c, 0] + m[r, 1] * m[c, 1] + m[r, 2] * m[c, 2]
                k += 1
    return pc, cov


@njit(cache=True, inline="always")
def _sh_color(sh, i, c, dx, dy, dz, k):
    v = SH_C0 * sh[i, 0, c]
    if k > 1:
        v += SH_C1 * (-dy * sh[i, 1, c] + dz * sh[i, 2, c] - dx * sh[i, 3, c])
    if k > 4:
        xx, yy, zz = dx * dx, dy * dy, dz * dz
        v += (SH_C2[0] * dx * dy * sh[i, 4, c] + SH_C2[1] * dy * dz * sh[i, 5, c]
              + SH_C2[2] * (2 * zz - xx - yy) * sh[i, 6, c] + SH_C2[3] * dx * dz * sh[i, 7, c]
              + SH_C2[4] * (xx - yy) * sh[i, 8, c])
        if k > 9:
            v += (SH_C3[0] * dy * (3 * xx - yy) * sh[i, 9, c]
                  + SH_C3[1] * dx * dy * dz * sh[i, 10, c]
                  + SH_C3[2] * dy * (4 * zz - xx - yy) * sh[i, 11, c]
                  + SH_C3[3] * dz * (2 * zz - 3 * xx - 3 * yy) * sh[i, 12, c]
                  + SH_C3[4] * dx * (4 * zz - xx - yy) * sh[i, 13, c]
                  + SH_C3[5] * dz * (xx - yy) * sh[i, 14, c]
                  + SH_C3[6] * dx * (xx - 3 * yy) * sh[i, 15, c])
    return max(v + 0.5, 0.0)


@njit(cache=True, inline="always")
def _min_on_segment(a, b, c, dx0, dx1, dy):
    """Min over dx in [dx0, dx1] of q = 0.5 a dx^2 + b dx dy + 0.5 c dy^2 (a > 0)."""
    d = -b * dy / a
    d = min(max(d, dx0), dx1)
    return 0.5 * a * d * d + b * d * dy + 0.5 * c * dy * dy


@njit(cache=True, inline="always")
def _tile_hit(rec, x0, x1, y0, y1):
    """Exact test: does the ellipse {q <= smax} meet the rectangle of pixel centres
    [x0, x1] x [y0, y1]? The minimum of a convex quadratic over a rectangle is at the centre when
    the centre is inside, else on one of the four edges."""
    u, v = rec[U], rec[V]
    if x0 <= u <= x1 and y0 <= v <= y1:
        return True
    a, b, c, smax = rec[CA], rec[CB], rec[CC], rec[SMAX]
    dx0, dx1, dy0, dy1 = x0 - u, x1 - u, y0 - v, y1 - v
    q = min(_min_on_segment(a, b, c, dx0, dx1, dy0), _min_on_segment(a, b, c, dx0, dx1, dy1))
    # Vertical edges: the same form with the roles of x and y swapped.
    q = min(q, _min_on_segment(c, b, a, dy0, dy1, dx0), _min_on_segment(c, b, a, dy0, dy1, dx1))
    return q <= smax


@njit(cache=True, inline="always")
def _floor_clamped(x, lo, hi):
    """floor(x) clamped to [lo, hi], clamping first: huge splats seen from inside give
    coordinates far beyond int64, where a float-to-int cast is undefined."""
    return math.floor(min(max(x, lo - 1.0), hi + 1.0)) if x == x else lo


@njit(cache=True, inline="always")
def tile_box(t, nx, tile, width, height):
    """Tile `t`'s origin and size in pixels (x0, y0, w, h): row-major tiles of `tile` px, `nx`
    per row, cut at the image's right and bottom edges."""
    ty, tx = t // nx, t % nx
    x0, y0 = tx * tile, ty * tile
    return x0, y0, min(tile, width - x0), min(tile, height - y0)


@njit(cache=True, inline="always")
def row_span(u, v, a, b, c, smax, y, x0, w):
    """Row `y`'s pixels (columns j0..j1 of the tile starting at `x0`, `w` wide) whose centres lie
    inside a splat's ellipse q <= smax, and the row's offset dy from the splat's centre;
    j1 < j0 when none. The span follows from the quadratic in dx."""
    dy = y + 0.5 - v
    disc = (b * dy) ** 2 - a * (c * dy * dy - 2.0 * smax)
    if disc < 0:
        return 0, -1, dy
    sq = math.sqrt(disc)
    j0 = max(-_floor_clamped(-(u + (-b * dy - sq) / a - 0.5 - x0), -w, 0), 0)
    j1 = min(_floor_clamped(u + (-b * dy + sq) / a - 0.5 - x0, -1, w - 1), w - 1)
    return j0, j1, dy


@njit(cache=True, inline="always")
def blend(trans, done, yy, xx, al):
    """One splat's front-to-back step at a pixel: its weight alpha * T, with T updated (0.0
    where the pixel is done or the splat too faint there), and 1 when this step spent the
    pixel's transmittance (it is done from now on), else 0."""
    if done[yy, xx] or al < ALPHA_MIN:
        return 0.0, 0
    tr = trans[yy, xx]
    nt = tr * (1.0 - al)
    if nt < T_MIN:
        done[yy, xx] = True
        return 0.0, 1
    trans[yy, xx] = nt
    return al * tr, 0


@njit(cache=True, inline="always")
def _tile_range(rec, tile, width, height):
    """Tiles whose pixel centres (j + 0.5) can fall inside the ellipse's bounding box."""
    nx = (width + tile - 1) // tile
    ny = (height + tile - 1) // tile
    tx0 = _floor_clamped((rec[U] - rec[RX] - 0.5) / tile, 0, nx - 1)
    tx1 = _floor_clamped((rec[U] + rec[RX] - 0.5) / tile, 0, nx - 1)
    ty0 = _floor_clamped((rec[V] - rec[RY] - 0.5) / tile, 0, ny - 1)
    ty1 = _floor_clamped((rec[V] + rec[RY] - 0.5) / tile, 0, ny - 1)
    return max(tx0, 0), min(tx1, nx - 1), max(ty0, 0), min(ty1, ny - 1), nx


@njit(parallel=True, cache=True)
def project_view(pc, cov, opac, sh, order, campos_cam_shift, R, fx, fy, cx, cy,
                 width, height, near, far, eps2d, antialias, tile):
    """Project Gaussians `order` (depth-sorted indices) for one view.

    `campos_cam_shift` = (dx, dy): the view's camera centre moved by (dx, dy, 0) in camera frame.
    Returns records [M, NREC] in `order`'s order, and tile counts [M] (0 = culled).
    """
    m = order.shape[0]
    rec = np.zeros((m, NREC))
    counts = np.zeros(m, np.int64)
    sx, sy = campos_cam_shift[0], campos_cam_shift[1]
    k = sh.shape[1]
    lim_xp = (width - cx) / fx + 0.3 * (width / fx) * 0.5
    lim_xn = cx / fx + 0.3 * (width / fx) * 0.5
    lim_yp = (height - cy) / fy + 0.3 * (height / fy) * 0.5
    lim_yn = cy / fy + 0.3 * (height / fy) * 0.5
    for o in prange(m):
        i = order[o]
        x = pc[i, 0] - sx
        y = pc[i, 1] - sy
        z = pc[i, 2]
        if not (near <= z <= far):
            continue
        # EWA: the Jacobian of the perspective map, with x/z and y/z clamped to a little beyond
        # the field of view so that Gaussians far outside it do not blow up (3DGS / gsplat).
        txz = min(max(x / z, -lim_xn), lim_xp)
        tyz = min(max(y / z, -lim_yn), lim_yp)
        j00 = fx / z
        j02 = -fx * txz / z
        j11 = fy / z
        j12 = -fy * tyz / z
        sxx, sxy, sxz = cov[i, 0], cov[i, 1], cov[i, 2]
        syy, syz, szz = cov[i, 3], cov[i, 4], cov[i, 5]
        # cov2 = J S J^T with J = [[j00, 0, j02], [0, j11, j12]]
        a0 = j00 * sxx + j02 * sxz
        a1 = j00 * sxy + j02 * syz
        a2 = j00 * sxz + j02 * szz
        c00 = a0 * j00 + a2 * j02
        c01 = a1 * j11 + a2 * j12
        c11 = j11 * (j11 * syy + j12 * syz) + j12 * (j11 * syz + j12 * szz)
        det0 = c00 * c11 - c01 * c01
        c00 += eps2d
        c11 += eps2d
        det = c00 * c11 - c01 * c01
        if not det > 0:
            continue
        op = opac[i]
        if antialias:
            op *= math.sqrt(max(det0 / det, 0.0))
        if op < ALPHA_MIN:
            continue
        smax = math.log(255.0 * op)
        rx = math.sqrt(2.0 * smax * c00)
        ry = math.sqrt(2.0 * smax * c11)
        u = fx * x / z + cx
        v = fy * y / z + cy
        # Pixel centres span [0.5, width - 0.5] x [0.5, height - 0.5].
        if u + rx < 0.5 or u - rx > width - 0.5 or v + ry < 0.5 or v - ry > height - 0.5:
            continue
        r = rec[o]
        r[U] = u
        r[V] = v
        r[CA] = c11 / det
        r[CB] = -c01 / det
        r[CC] = c00 / det
        r[Z] = z
        r[OP] = op
        r[SMAX] = smax
        r[RX] = rx
        r[RY] = ry
        # SH view direction: from the (moved) camera centre to the mean, in world axes.
        if k > 1:
            dxw = R[0, 0] * x + R[1, 0] * y + R[2, 0] * z
            dyw = R[0, 1] * x + R[1, 1] * y + R[2, 1] * z
            dzw = R[0, 2] * x + R[1, 2] * y + R[2, 2] * z
            nrm = math.sqrt(dxw * dxw + dyw * dyw + dzw * dzw)
            dxw /= nrm
            dyw /= nrm
            dzw /= nrm
        else:
            dxw = dyw = dzw = 0.0
        r[COL_R] = _sh_color(sh, i, 0, dxw, dyw, dzw, k)
        r[COL_G] = _sh_color(sh, i, 1, dxw, dyw, dzw, k)
        r[COL_B] = _sh_color(sh, i, 2, dxw, dyw, dzw, k)
        tx0, tx1, ty0, ty1, _ = _tile_range(r, tile, width, height)
        n = 0
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                if _tile_hit(r, tx * tile + 0.5, tx * tile + tile - 0.5,
                             ty * tile + 0.5, ty * tile + tile - 0.5):
                    n += 1
        counts[o] = n
    return rec, counts


@njit(parallel=True, cache=True)
def fill_tile_ids(rec, counts, offsets, tile, width, height):
    """Tile id of every (Gaussian, tile) pair, grouped by Gaussian in depth order."""
    tiles = np.empty(offsets[-1], np.int32)
    for o in prange(rec.shape[0]):
        if counts[o] == 0:
            continue
        r = rec[o]
        tx0, tx1, ty0, ty1, nx = _tile_range(r, tile, width, height)
        p = offsets[o]
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                if _tile_hit(r, tx * tile + 0.5, tx * tile + tile - 0.5,
                             ty * tile + 0.5, ty * tile + tile - 0.5):
                    tiles[p] = ty * nx + tx
                    p += 1
    return tiles


@njit(cache=True)
def sort_by_tile(tiles, counts, offsets, n_tiles):
    """Counting sort of the pairs by tile. Stable, so each tile's list stays in depth order."""
    starts = np.zeros(n_tiles + 1, np.int64)
    for p in range(tiles.shape[0]):
        starts[tiles[p] + 1] += 1
    for t in range(n_tiles):
        starts[t + 1] += starts[t]
    cursor = starts[:-1].copy()
    gauss = np.empty(tiles.shape[0], np.int32)
    for o in range(counts.shape[0]):
        for p in range(offsets[o], offsets[o] + counts[o]):
            t = tiles[p]
            gauss[cursor[t]] = o
            cursor[t] += 1
    return starts, gauss


@njit(parallel=True, fastmath=True, cache=True)
def composite(rec, starts, gauss, tile, width, height, rgb, alpha, depth):
    """Front-to-back alpha compositing per tile on a black background.

    For each Gaussian only the pixels inside its ellipse are visited (a row's span follows from
    the quadratic), and a tile stops when every pixel's transmittance is spent.
    """
    nx = (width + tile - 1) // tile
    n_tiles = starts.shape[0] - 1
    # prange hands each thread one contiguous block of iterations. Content is rarely spread
    # evenly over the image (the donut's top half had a third of the bottom's work), so walk the
    # tiles interleaved: block j holds the tiles whose index is in a few residue classes mod 16,
    # which are spread over the whole image.
    order = np.empty(n_tiles, np.int64)
    pos = 0
    for residue in range(16):
        for t in range(residue, n_tiles, 16):
            order[pos] = t
            pos += 1
    for ti in prange(n_tiles):
        t = order[ti]
        x0, y0, w, h = tile_box(t, nx, tile, width, height)
        trans = np.ones((h, w))
        acc = np.zeros((h, w, 4))
        done = np.zeros((h, w), np.bool_)
        n_done = 0
        n_pix = h * w
        for p in range(starts[t], starts[t + 1]):
            if n_done == n_pix:
                break
            r = rec[gauss[p]]
            u, v, a, b, c = r[U], r[V], r[CA], r[CB], r[CC]
            op, smax = r[OP], r[SMAX]
            col_r, col_g, col_b, zc = r[COL_R], r[COL_G], r[COL_B], r[Z]
            ea = math.exp(-a)
            for yy in range(h):
                j0, j1, dy = row_span(u, v, a, b, c, smax, y0 + yy, x0, w)
                if j1 < j0:
                    continue
                # Along a row q is quadratic in dx, so exp(-q) advances by a ratio that itself
                # shrinks by exp(-a) per pixel: two multiplies per pixel instead of an exp.
                # Very thin splats (large a) span a pixel or two and use exp directly, so the
                # ratio cannot overflow.
                dx = x0 + j0 + 0.5 - u
                gval = op * math.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy))
                incremental = a < 8.0
                step = math.exp(-(a * dx + 0.5 * a + b * dy)) if incremental else 0.0
                for xx in range(j0, j1 + 1):
                    if not incremental and xx > j0:
                        dx = x0 + xx + 0.5 - u
                        gval = op * math.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy))
                    al = min(ALPHA_MAX, gval)
                    if incremental:
                        gval *= step
                        step *= ea
                    wgt, ended = blend(trans, done, yy, xx, al)
                    n_done += ended
                    if wgt == 0.0:  # done, too faint, or spent here
                        continue
                    acc[yy, xx, 0] += wgt * col_r
                    acc[yy, xx, 1] += wgt * col_g
                    acc[yy, xx, 2] += wgt * col_b
                    acc[yy, xx, 3] += wgt * zc
        for yy in range(h):
            for xx in range(w):
                al = 1.0 - trans[yy, xx]
                rgb[0, y0 + yy, x0 + xx] = acc[yy, xx, 0]
                rgb[1, y0 + yy, x0 + xx] = acc[yy, xx, 1]
                rgb[2, y0 + yy, x0 + xx] = acc[yy, xx, 2]
                alpha[y0 + yy, x0 + xx] = al
                depth[y0 + yy, x0 + xx] = acc[yy, xx, 3] / al if al > 0 else 0.0
