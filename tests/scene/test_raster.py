"""The CPU rasteriser against a dense brute-force reference written here, analytic single-splat
images, the extremes the issue lists, and the shared donut scene.

The reference (`dense_reference`) follows the stated 3DGS / gsplat semantics directly in float64
NumPy: every Gaussian is evaluated at every pixel centre `(j + 0.5, i + 0.5)`, Gaussians are
composited front to back in order of camera-space z of their centres, alpha is
`min(0.99, opacity * exp(-q))` and skipped below 1/255, and a pixel stops before the Gaussian that
would take its transmittance below 1e-4. It shares no code with `nhfd.scene._kernels`.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from nhfd.scene.cameras import Camera, intrinsics_from_fov, look_at, orbit
from nhfd.scene.gaussians import Gaussians, make_gaussians
from nhfd.scene.raster import RasterSettings, render

# --- the reference ---------------------------------------------------------------------------

# Real spherical-harmonic normalisations written from their closed forms (3DGS basis and signs).
PI = math.pi
C0 = 0.5 * math.sqrt(1 / PI)
C1 = math.sqrt(3 / (4 * PI))
C2 = (
    math.sqrt(15 / (4 * PI)),
    -math.sqrt(15 / (4 * PI)),
    math.sqrt(5 / (16 * PI)),
    -math.sqrt(15 / (4 * PI)),
    math.sqrt(15 / (16 * PI)),
)
C3 = (
    -math.sqrt(35 / (32 * PI)),
    math.sqrt(105 / (4 * PI)),
    -math.sqrt(21 / (32 * PI)),
    math.sqrt(7 / (16 * PI)),
    -math.sqrt(21 / (32 * PI)),
    math.sqrt(105 / (16 * PI)),
    -math.sqrt(35 / (32 * PI)),
)
ALPHA_MIN, ALPHA_MAX, T_MIN = 1 / 255, 0.99, 1e-4


def sh_basis(d: np.ndarray, k: int) -> np.ndarray:
    """[N, k] real SH basis of unit directions d [N, 3] (3DGS ordering and signs)."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    xx, yy, zz = x * x, y * y, z * z
    cols = [np.full_like(x, C0)]
    if k > 1:
        cols += [-C1 * y, C1 * z, -C1 * x]
    if k > 4:
        cols += [
            C2[0] * x * y,
            C2[1] * y * z,
            C2[2] * (2 * zz - xx - yy),
            C2[3] * x * z,
            C2[4] * (xx - yy),
        ]
    if k > 9:
        cols += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return np.stack(cols, axis=1)


def rotation_matrices(q: np.ndarray) -> np.ndarray:
    """[N, 3, 3] from wxyz quaternions: R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]_x."""
    q = q.astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, v = q[:, 0], q[:, 1:]
    cross = np.zeros((len(q), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2] = -v[:, 2], v[:, 1]
    cross[:, 1, 0], cross[:, 1, 2] = v[:, 2], -v[:, 0]
    cross[:, 2, 0], cross[:, 2, 1] = -v[:, 1], v[:, 0]
    return (
        (w * w - (v * v).sum(1))[:, None, None] * np.eye(3)
        + 2 * v[:, :, None] * v[:, None, :]
        + 2 * w[:, None, None] * cross
    )


def dense_reference(
    g: Gaussians, cam: Camera, eps2d: float = 0.3, antialias: bool = False, clamp: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb [3, H, W], alpha [H, W], depth [H, W]) in float64, every Gaussian at every pixel.
    `clamp=False` drops the Jacobian's tan-FOV clamp (only to show that a test depends on it)."""
    w_px, h_px = cam.width_px, cam.height_px
    rgb = np.zeros((3, h_px, w_px))
    trans = np.ones((h_px, w_px))
    zsum = np.zeros((h_px, w_px))
    done = np.zeros((h_px, w_px), bool)
    if len(g) == 0:
        return rgb, 1 - trans, zsum
    rot = np.asarray(cam.R, np.float64)
    pc = g.means.astype(np.float64) @ rot.T + np.asarray(cam.t, np.float64)
    m = rotation_matrices(g.quats) * g.scales.astype(np.float64)[:, None, :]
    cov_c = rot @ (m @ m.transpose(0, 2, 1)) @ rot.T
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
    tx, ty = x / z, y / z
    if clamp:
        tx = np.clip(tx, -(cx / fx + 0.15 * w_px / fx), (w_px - cx) / fx + 0.15 * w_px / fx)
        ty = np.clip(ty, -(cy / fy + 0.15 * h_px / fy), (h_px - cy) / fy + 0.15 * h_px / fy)
    jac = np.zeros((len(g), 2, 3))
    jac[:, 0, 0] = fx / z
    jac[:, 0, 2] = -fx * tx / z
    jac[:, 1, 1] = fy / z
    jac[:, 1, 2] = -fy * ty / z
    cov2 = jac @ cov_c @ jac.transpose(0, 2, 1)
    det0 = np.linalg.det(cov2)
    cov2 = cov2 + eps2d * np.eye(2)
    det = np.linalg.det(cov2)
    opac = g.opacities.astype(np.float64)
    if antialias:
        opac = opac * np.sqrt(np.maximum(det0 / det, 0.0))
    conic = np.linalg.inv(cov2)
    u, v = fx * x / z + cx, fy * y / z + cy
    # Camera-frame direction from the camera centre to the mean, in world axes, for SH.
    dirs = pc @ rot
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    k = g.sh.shape[1]
    colour = np.maximum(
        0.5 + np.einsum("nk,nkc->nc", sh_basis(dirs, k), g.sh.astype(np.float64)), 0.0
    )
    keep = np.flatnonzero((z >= cam.near) & (z <= cam.far))
    order = keep[np.argsort(z[keep], kind="stable")]
    px = np.arange(w_px) + 0.5
    py = np.arange(h_px)[:, None] + 0.5
    for n in order:
        dx, dy = px - u[n], py - v[n]
        a, b, c = conic[n, 0, 0], conic[n, 0, 1], conic[n, 1, 1]
        q = 0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy)
        al = np.minimum(ALPHA_MAX, opac[n] * np.exp(-q))
        active = (al >= ALPHA_MIN) & ~done
        new_t = trans * (1 - al)
        stop = active & (new_t < T_MIN)
        done |= stop
        draw = active & ~stop
        wgt = np.where(draw, al * trans, 0.0)
        rgb += wgt * colour[n][:, None, None]
        zsum += wgt * z[n]
        trans = np.where(draw, new_t, trans)
    alpha = 1 - trans
    depth = np.where(alpha > 0, zsum / np.where(alpha > 0, alpha, 1), 0.0)
    return rgb, alpha, depth


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - b) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


# --- scene and camera builders ---------------------------------------------------------------


def dc_for(colour) -> np.ndarray:
    """The f_dc giving `colour` (any shape, elementwise) at SH degree 0."""
    return (np.asarray(colour, np.float64) - 0.5) / C0


def gaussians(means, scales, opacities, colours=None, quats=None) -> Gaussians:
    """Degree-0 Gaussians; `scales` scalar (isotropic), [N] (isotropic each) or [N, 3]."""
    means = np.asarray(means, np.float64).reshape(-1, 3)
    n = len(means)
    scales = np.asarray(scales, np.float64)
    scales = np.broadcast_to(scales if scales.ndim == 2 else scales.reshape(-1, 1), (n, 3))
    if quats is None:
        quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    cols = np.ones((n, 3)) if colours is None else np.asarray(colours, np.float64)
    return make_gaussians(
        means, quats, scales, np.broadcast_to(opacities, (n,)), dc_for(cols)[:, None, :]
    )


def axis_camera(
    width: int, height: int, f: float, cx: float | None = None, cy: float | None = None, **kw: float
) -> Camera:
    """A camera at the origin looking down +z (identity pose)."""
    return Camera(
        np.eye(3),
        np.zeros(3),
        f,
        f,
        width / 2 if cx is None else cx,
        height / 2 if cy is None else cy,
        width,
        height,
        **kw,
    )


def random_scene(seed: int, n: int, degree: int) -> Gaussians:
    """A cloud around the origin: random rotations, anisotropic log-uniform scales (some large),
    opacities up to 1 (some exactly 1), coloured DC and SH rest, a few far outside the view."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    means = rng.uniform(-1.0, 1.0, (n, 3)) * [1.2, 1.0, 1.0]
    means[: n // 10] *= 3.0  # a few far out, some beyond the view (culled or clamped)
    scales = np.exp(rng.uniform(np.log(0.01), np.log(0.35), (n, 3)))
    opac = rng.uniform(0.02, 1.0, n)
    opac[rng.random(n) < 0.15] = 1.0
    sh = rng.normal(0.0, 0.25, (n, k, 3))
    sh[:, 0] = dc_for(rng.uniform(0.0, 1.0, (n, 3)))
    return make_gaussians(means, rng.normal(size=(n, 4)), scales, opac, sh)


def scene_camera(
    seed: int, width: int, height: int, fov: float = 60.0, radius: float = 3.2
) -> Camera:
    rng = np.random.default_rng(1000 + seed)
    d = rng.normal(size=3)
    eye = radius * d / np.linalg.norm(d)
    r, t = look_at(eye, rng.normal(0, 0.1, 3), "+z")
    fx, fy, cx, cy = intrinsics_from_fov(width, height, fov)
    return Camera(r, t, fx, fy, cx + 0.37, cy - 0.21, width, height, near=0.05)


def assert_finite(out) -> None:
    for name in ("rgb", "alpha", "depth"):
        arr = getattr(out, name)
        assert arr.dtype == np.float32, name
        assert np.isfinite(arr).all(), f"{name} has non-finite values"


def assert_matches_reference(g: Gaussians, cam: Camera, settings: RasterSettings) -> None:
    out = render(g, cam, settings)
    assert out.rgb.shape == (3, cam.height_px, cam.width_px)
    assert out.alpha.shape == out.depth.shape == (cam.height_px, cam.width_px)
    assert_finite(out)
    rgb, alpha, depth = dense_reference(g, cam, settings.eps2d_px2, settings.antialias)
    assert alpha.max() > 0.5, "test scene does not cover the view"
    p = psnr(out.rgb, rgb)
    assert p >= 45.0, f"rgb PSNR {p:.1f} dB against the dense reference"
    assert psnr(out.alpha, alpha) >= 45.0
    # Almost every pixel agrees tightly; only pixels on the 1/255 / 1e-4 thresholds may differ.
    assert np.mean(np.abs(out.alpha - alpha) > 1e-4) < 0.002
    assert np.mean(np.abs(out.rgb - rgb) > 1e-4) < 0.002
    sel = alpha > 0.5
    rel = np.abs(out.depth[sel] - depth[sel]) / depth[sel]
    assert rel.max() <= 0.01, f"depth off by {rel.max():.3%} where alpha > 0.5"
    np.testing.assert_array_equal(out.depth[out.alpha == 0], 0.0)


# --- 1. the dense reference on random scenes -------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("degree", [0, 3])
@pytest.mark.parametrize(("width", "height"), [(64, 48), (97, 61)])
def test_matches_dense_reference(seed: int, degree: int, width: int, height: int) -> None:
    g = random_scene(seed, 60 + 80 * seed, degree)
    assert_matches_reference(g, scene_camera(seed, width, height), RasterSettings())


@pytest.mark.parametrize("tile", [8, 16, 32, 5])
@pytest.mark.parametrize("antialias", [False, True])
def test_matches_dense_reference_tiles_and_antialias(tile: int, antialias: bool) -> None:
    g = random_scene(10 + tile, 300, 1 if antialias else 2)
    settings = RasterSettings(tile_px=tile, antialias=antialias)
    assert_matches_reference(g, scene_camera(7, 97, 61), settings)


def needles(seed: int, n: int) -> Gaussians:
    """Thin splats (0.003 across, up to 0.5 long): with a small dilation their conics are large,
    which takes the compositor off its incremental-exp path."""
    rng = np.random.default_rng(seed)
    sc = np.full((n, 3), 0.003)
    sc[np.arange(n), rng.integers(0, 3, n)] = rng.uniform(0.05, 0.5, n)
    return make_gaussians(
        rng.uniform(-1, 1, (n, 3)),
        rng.normal(size=(n, 4)),
        sc,
        rng.uniform(0.3, 1, n),
        dc_for(rng.uniform(0, 1, (n, 3)))[:, None],
    )


@pytest.mark.parametrize(
    ("case", "settings"),
    [
        ("needles", RasterSettings(eps2d_px2=0.0)),
        ("needles", RasterSettings(eps2d_px2=0.02, tile_px=8)),
        ("needles", RasterSettings(eps2d_px2=0.05, antialias=True)),
        ("tile1", RasterSettings(tile_px=1)),
        ("tile256", RasterSettings(tile_px=256)),
        ("pp_outside", RasterSettings()),
        ("fx_ne_fy", RasterSettings(tile_px=13)),
    ],
)
def test_matches_dense_reference_unusual_settings(case: str, settings: RasterSettings) -> None:
    g = needles(3, 150) if case == "needles" else random_scene(5, 150, 1)
    cam = scene_camera(5, 97, 61)
    if case == "pp_outside":  # principal point off the image (light-field views shift it)
        cam = replace(cam, cx=-12.0, cy=70.5)
    elif case == "fx_ne_fy":
        cam = replace(cam, fx=cam.fx * 1.4, fy=cam.fy * 0.7)
    assert_matches_reference(g, cam, settings)


def test_tan_fov_clamp_of_splats_outside_the_view() -> None:
    """Large splats centred beyond 1.15x the field of view reach into the image; their footprint
    follows the clamped Jacobian (the unclamped one would give a visibly different image)."""
    rng = np.random.default_rng(21)
    n = 24
    side = rng.choice([-1.0, 1.0], (n, 2))
    tan = np.where(rng.random((n, 1)) < 0.5, [1.0, 0.0], [0.0, 1.0])  # push out in x or in y
    xy = side * (tan * rng.uniform(0.9, 1.6, (n, 1)) + (1 - tan) * rng.uniform(0, 0.5, (n, 1)))
    z = rng.uniform(1.5, 3.0, n)
    means = np.c_[xy * z[:, None], z]
    g = make_gaussians(
        means,
        rng.normal(size=(n, 4)),
        rng.uniform(0.3, 0.9, (n, 3)),
        rng.uniform(0.3, 1.0, n),
        dc_for(rng.uniform(0, 1, (n, 3)))[:, None],
    )
    fx, fy, cx, cy = intrinsics_from_fov(64, 48, 60.0)
    cam = Camera(np.eye(3), np.zeros(3), fx, fy, cx, cy, 64, 48)
    lim_x, lim_y = (64 - cx) / fx + 0.15 * 64 / fx, (48 - cy) / fy + 0.15 * 48 / fy
    outside = (np.abs(means[:, 0] / z) > lim_x) | (np.abs(means[:, 1] / z) > lim_y)
    assert outside.all()
    assert_matches_reference(g, cam, RasterSettings())
    unclamped = dense_reference(g, cam, clamp=False)[0]
    assert psnr(render(g, cam).rgb, unclamped) < 35.0


def test_antialias_changes_the_image_as_the_reference_does() -> None:
    """A guard that the reference's antialias branch is exercised: small splats dim noticeably."""
    g = random_scene(3, 200, 0)
    cam = scene_camera(3, 64, 48)
    plain = render(g, cam, RasterSettings()).alpha
    aa = render(g, cam, RasterSettings(antialias=True)).alpha
    assert aa.sum() < 0.98 * plain.sum()
    assert (aa <= plain + 1e-6).mean() > 0.95


def test_order_is_camera_z_not_distance() -> None:
    """A is nearer in z (4) but farther in distance (5) than B (z = 4.5 on axis): A is in front."""
    g = gaussians([[3.0, 0, 4.0], [0, 0, 4.5]], 1e3, 0.9, colours=[(1, 0, 0), (0, 1, 0)])
    out = render(g, axis_camera(16, 16, 20.0))
    a = 0.9  # q < 1e-5 over the image for these huge splats
    np.testing.assert_allclose(out.rgb[0], a, atol=1e-4)
    np.testing.assert_allclose(out.rgb[1], (1 - a) * 0.9, atol=1e-4)
    np.testing.assert_allclose(out.depth, (a * 4.0 + (1 - a) * 0.9 * 4.5) / out.alpha, rtol=1e-4)


# --- 2. analytic single splats ---------------------------------------------------------------


def isotropic_alpha(cam: Camera, u: float, v: float, var_px2: float, op: float) -> np.ndarray:
    j = np.arange(cam.width_px) + 0.5
    i = np.arange(cam.height_px)[:, None] + 0.5
    val = op * np.exp(-((j - u) ** 2 + (i - v) ** 2) / (2 * var_px2))
    val = np.minimum(val, 0.99)
    return np.where(val >= 1 / 255, val, 0.0)


def ewa_alpha(cam: Camera, x: float, y: float, z: float, s: float, op: float) -> np.ndarray:
    """Alpha of one isotropic Gaussian (std s, camera-frame centre inside the view) in `cam` at
    identity pose: cov2 = s^2 J J^T + 0.3 I, cut at 1/255."""
    f = cam.fx
    u, v = f * x / z + cam.cx, f * y / z + cam.cy
    jac = np.array([[f / z, 0, -f * x / z**2], [0, f / z, -f * y / z**2]])
    conic = np.linalg.inv(s * s * jac @ jac.T + 0.3 * np.eye(2))
    jj, ii = np.meshgrid(np.arange(cam.width_px) + 0.5, np.arange(cam.height_px) + 0.5)
    d = np.stack([jj - u, ii - v])
    val = np.minimum(op * np.exp(-0.5 * np.einsum("aij,ab,bij->ij", d, conic, d)), 0.99)
    return np.where(val >= 1 / 255, val, 0.0)


@pytest.mark.parametrize(("cx", "cy"), [(32.0, 24.0), (30.3, 20.7)])
def test_single_isotropic_on_axis(cx: float, cy: float) -> None:
    f, s, z, op = 60.0, 0.05, 2.0, 0.8
    cam = axis_camera(64, 48, f, cx, cy)
    out = render(gaussians([[0, 0, z]], s, op, colours=[(0.2, 0.6, 1.0)]), cam)
    sigma_px = f * s / z
    expect = isotropic_alpha(cam, cx, cy, sigma_px**2 + 0.3, op)
    np.testing.assert_allclose(out.alpha, expect, atol=1e-4, rtol=0)
    for c, col in enumerate((0.2, 0.6, 1.0)):
        np.testing.assert_allclose(out.rgb[c], col * expect, atol=1e-4)
    drawn = out.alpha > 0
    np.testing.assert_allclose(out.depth[drawn], z, rtol=1e-5)
    assert (out.depth[~drawn] == 0).all()
    if cx == 32.0:  # symmetric sampling: the alpha-weighted centroid is the principal point
        jj, ii = np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5)
        tot = out.alpha.sum()
        assert abs((out.alpha * jj).sum() / tot - cx) < 1e-4
        assert abs((out.alpha * ii).sum() / tot - cy) < 1e-4


def test_single_isotropic_off_axis_lands_at_projection() -> None:
    f, s, op = 80.0, 0.06, 0.7
    x, y, z = 0.41, -0.23, 2.5
    cam = axis_camera(96, 64, f, 47.0, 33.0)
    out = render(gaussians([[x, y, z]], s, op), cam)
    u, v = f * x / z + 47.0, f * y / z + 33.0
    np.testing.assert_allclose(out.alpha, ewa_alpha(cam, x, y, z, s, op), atol=1e-4)
    jj, ii = np.meshgrid(np.arange(96) + 0.5, np.arange(64) + 0.5)
    tot = out.alpha.sum()
    assert abs((out.alpha * jj).sum() / tot - u) < 0.02
    assert abs((out.alpha * ii).sum() / tot - v) < 0.02
    np.testing.assert_allclose(out.depth[out.alpha > 0], z, rtol=1e-5)


def test_isotropic_gaussian_is_rotation_invariant() -> None:
    rng = np.random.default_rng(5)
    cam = scene_camera(5, 64, 48, radius=3.0)
    means = rng.normal(0, 0.3, (6, 3))
    scales = rng.uniform(0.05, 0.3, 6)
    base = render(gaussians(means, scales, 0.6), cam)
    assert base.alpha.max() > 0.3
    for _ in range(3):
        q = rng.normal(size=(6, 4))
        out = render(gaussians(means, scales, 0.6, quats=q), cam)
        np.testing.assert_allclose(out.alpha, base.alpha, atol=2e-6)
        np.testing.assert_allclose(out.rgb, base.rgb, atol=2e-6)


def test_anisotropic_gaussian_follows_its_rotation() -> None:
    """A splat long along x, turned 90 degrees about z, is long along the image's y."""
    cam = axis_camera(48, 48, 60.0)
    s = [0.2, 0.02, 0.02]
    g0 = make_gaussians([[0, 0, 2.0]], [[1, 0, 0, 0]], [s], [0.9], dc_for((1, 1, 1))[None, None])
    qz = [math.cos(PI / 4), 0, 0, math.sin(PI / 4)]
    g1 = make_gaussians([[0, 0, 2.0]], [qz], [s], [0.9], dc_for((1, 1, 1))[None, None])
    a0, a1 = render(g0, cam).alpha, render(g1, cam).alpha
    assert (a0 > 0.1).sum(1).max() > 3 * (a0 > 0.1).sum(0).max()  # wide along x (columns)
    np.testing.assert_allclose(a1, a0.T, atol=1e-5)


def test_view_dependent_colour_uses_direction_from_camera() -> None:
    """Degree-1 SH: coefficient 3 multiplies -C1 * x of the world direction camera -> mean."""
    cam = axis_camera(32, 32, 40.0)
    sh = np.zeros((1, 4, 3))
    sh[0, 0] = dc_for((0.5, 0.5, 0.5))
    sh[0, 3, 0] = 0.5  # red depends on the world x of the viewing direction
    mean = np.array([[0.6, 0.0, 2.0]])
    g = make_gaussians(mean, [[1, 0, 0, 0]], [[3.0] * 3], [1.0], sh)
    out = render(g, cam)
    d = mean[0] / np.linalg.norm(mean[0])
    red = 0.5 - C1 * d[0] * 0.5
    np.testing.assert_allclose(out.rgb[0] / out.alpha, red, rtol=1e-4)
    np.testing.assert_allclose(out.rgb[1] / out.alpha, 0.5, rtol=1e-4)


# --- 3. extremes -----------------------------------------------------------------------------


def test_camera_inside_the_scene() -> None:
    g = random_scene(4, 200, 3)
    r, t = look_at([0.05, -0.02, 0.03], [1.0, 0.3, 0.1], "+z")
    cam = Camera(r, t, 40.0, 40.0, 32.0, 24.0, 64, 48, near=0.01)
    assert_matches_reference(g, cam, RasterSettings())


@pytest.mark.parametrize("where", ["looking_away", "behind"])
def test_scene_behind_the_camera_gives_an_empty_image(where: str) -> None:
    g = random_scene(6, 150, 0)  # inside the cube [-3, 3]^3
    if where == "looking_away":
        r, t = look_at([0, -8.0, 0], [0, -20.0, 0], "+z")
    else:  # past the scene, facing away from it
        r, t = look_at([0, 0, 8.0], [0, 0, 30.0], "+y")
    fx, fy, cx, cy = intrinsics_from_fov(64, 48, 90)
    out = render(g, Camera(r, t, fx, fy, cx, cy, 64, 48))
    assert_finite(out)
    assert not out.alpha.any() and not out.rgb.any() and not out.depth.any()
    # ...and the same scene seen from the front is not empty (the setup is meaningful).
    r, t = look_at([0, -8.0, 0], [0, 0, 0], "+z")
    assert render(g, Camera(r, t, fx, fy, cx, cy, 64, 48)).alpha.max() > 0.5


def test_gaussians_behind_near_or_beyond_far_are_culled() -> None:
    cam = axis_camera(40, 30, 40.0, near=0.5, far=20.0)
    vis_means = [[0, 0, 3.0], [0.3, 0.2, 5.0]]
    visible = gaussians(vis_means, 0.2, 0.7, colours=[(1, 0, 0), (0, 1, 0)])
    # Big, opaque, on axis, white: each would change the whole image if it were drawn.
    cull_means = [[0, 0, 0.3], [0, 0, 0.0], [0, 0, -2.0], [0, 0, 0.4999], [0, 0, 20.5]]
    both = gaussians(
        cull_means + vis_means,
        [5.0, 5.0, 5.0, 5.0, 500.0, 0.2, 0.2],
        [1.0] * 5 + [0.7] * 2,
        colours=[(1, 1, 1)] * 5 + [(1, 0, 0), (0, 1, 0)],
    )
    ref = render(visible, cam)
    out = render(both, cam)
    assert_finite(out)
    assert ref.alpha.max() > 0.5
    np.testing.assert_array_equal(out.rgb, ref.rgb)
    np.testing.assert_array_equal(out.alpha, ref.alpha)
    np.testing.assert_array_equal(out.depth, ref.depth)
    # With a wider clip range the same splats are drawn (so the test above means something).
    wide = render(both, replace(cam, near=0.01, far=1e3))
    assert np.abs(wide.rgb - ref.rgb).min() > 0.01
    # Only its centre counts: a splat just in front of the near plane is drawn.
    near_ok = gaussians([[0, 0, 0.51]], 5.0, 0.8)
    assert render(near_ok, cam).alpha.min() > 0.7


def test_tiny_scale_is_the_dilation_kernel() -> None:
    cam = axis_camera(21, 17, 50.0, 10.3, 8.6)
    out = render(gaussians([[0, 0, 1.5]], 1e-6, 0.9), cam)
    assert_finite(out)
    np.testing.assert_allclose(out.alpha, isotropic_alpha(cam, 10.3, 8.6, 0.3, 0.9), atol=1e-4)
    # With antialias the opacity scales by sqrt(det/det_dilated) ~ 1e-9: nothing is drawn.
    aa = render(gaussians([[0, 0, 1.5]], 1e-6, 0.9), cam, RasterSettings(antialias=True))
    assert_finite(aa)
    assert not aa.alpha.any()


@pytest.mark.parametrize("z", [5.0, 0.5, -3.0])
def test_huge_scale_fills_the_view(z: float) -> None:
    """Scale 1e3 at z = 5, inside it at z = 0.5 (camera inside the splat), and behind (culled)."""
    cam = axis_camera(48, 32, 40.0, near=0.1)
    g = gaussians([[0.3, -0.2, z]], 1e3, 0.8, colours=[(0.9, 0.3, 0.1)])
    out = render(g, cam)
    assert_finite(out)
    if z < 0:
        assert not out.alpha.any()
        return
    np.testing.assert_allclose(out.alpha, 0.8, atol=1e-5)
    expect = np.broadcast_to(np.array([0.9, 0.3, 0.1])[:, None, None] * 0.8, out.rgb.shape)
    np.testing.assert_allclose(out.rgb, expect, atol=1e-5)
    np.testing.assert_allclose(out.depth, z, rtol=1e-5)
    aa = render(g, cam, RasterSettings(antialias=True))  # det ratio ~ 1: unchanged
    np.testing.assert_allclose(aa.alpha, 0.8, atol=1e-5)


def test_huge_anisotropic_scales_stay_finite() -> None:
    """Needles and sheets 1e3 long and 1e-6 thin, some seen from inside, match the reference."""
    rng = np.random.default_rng(8)
    n = 12
    scales = np.full((n, 3), 1e-6)
    scales[np.arange(n), rng.integers(0, 3, n)] = 1e3
    scales[:4, 0] = 1e3
    g = make_gaussians(
        rng.normal(0, 1.0, (n, 3)) + np.array([0, 0, 3.0]),
        rng.normal(size=(n, 4)),
        scales,
        rng.uniform(0.1, 0.9, n),
        dc_for(rng.uniform(0, 1, (n, 3)))[:, None],
    )
    cam = axis_camera(40, 30, 30.0, near=0.01)
    out = render(g, cam)
    assert_finite(out)
    rgb, alpha, _ = dense_reference(g, cam)
    assert psnr(out.rgb, rgb) >= 45.0
    assert psnr(out.alpha, alpha) >= 45.0


def test_empty_scene() -> None:
    for degree in (0, 3):
        out = render(Gaussians.empty(degree), axis_camera(33, 17, 20.0))
        assert out.rgb.shape == (3, 17, 33) and out.alpha.shape == out.depth.shape == (17, 33)
        assert_finite(out)
        assert not out.rgb.any() and not out.alpha.any() and not out.depth.any()


def test_one_by_one_image() -> None:
    cam = axis_camera(1, 1, 10.0)
    out = render(gaussians([[0, 0, 2.0]], 0.1, 0.6, colours=[(1.0, 0.5, 0.0)]), cam)
    assert out.rgb.shape == (3, 1, 1)
    np.testing.assert_allclose(out.alpha[0, 0], 0.6, atol=1e-6)  # the centre lands on the pixel
    np.testing.assert_allclose(out.rgb[:, 0, 0], [0.6, 0.3, 0.0], atol=1e-6)
    np.testing.assert_allclose(out.depth[0, 0], 2.0, rtol=1e-6)
    g = random_scene(9, 100, 3)
    for seed in range(4):
        cam = scene_camera(seed, 1, 1, fov=20.0)
        out = render(g, cam)
        assert_finite(out)
        rgb, alpha, depth = dense_reference(g, cam)
        np.testing.assert_allclose(out.rgb, rgb, atol=1e-3)
        np.testing.assert_allclose(out.alpha, alpha, atol=1e-3)
        if alpha[0, 0] > 0.5:
            np.testing.assert_allclose(out.depth, depth, rtol=1e-2)


def test_very_large_image() -> None:
    w = h = 4096
    f = 3000.0
    cam = axis_camera(w, h, f)
    # The last centre lies 85 px right of the image; its tail (~110 px) still reaches in.
    pts = [[0.0, 0.0, 4.0], [-1.5, 1.0, 5.0], [3.2, -2.5, 4.5]]
    scales, op = [0.01, 0.01, 0.05], 0.9
    render(gaussians(pts, scales, op), axis_camera(8, 8, 5.0))  # compile outside the timing
    t0 = time.perf_counter()
    out = render(gaussians(pts, scales, op), cam)
    elapsed = time.perf_counter() - t0
    assert out.alpha.shape == (h, w) and out.rgb.shape == (3, h, w)
    assert np.isfinite(out.alpha).all() and np.isfinite(out.depth).all()
    rest = out.alpha.copy()
    for (x, y, z), s in zip(pts, scales, strict=True):
        u, v = f * x / z + w / 2, f * y / z + h / 2
        half = 200 if s > 0.01 else 40
        i0, j0 = int(v) - half, min(int(u) - half, w - 2 * half)
        win = Camera(np.eye(3), np.zeros(3), f, f, w / 2 - j0, h / 2 - i0, 2 * half, 2 * half)
        expect = ewa_alpha(win, x, y, z, s, op)
        got = out.alpha[i0 : i0 + 2 * half, j0 : j0 + 2 * half]
        np.testing.assert_allclose(got, expect, atol=1e-4)
        np.testing.assert_allclose(
            out.depth[i0 : i0 + 2 * half, j0 : j0 + 2 * half][expect > 0], z, rtol=1e-5
        )
        rest[i0 : i0 + 2 * half, j0 : j0 + 2 * half] = 0
    assert u > w and 0.01 < out.alpha[int(v), -1] < 0.5  # the off-image centre's tail is drawn
    assert not rest.any(), "alpha outside the three splats"
    assert elapsed < 10.0, f"4096 x 4096 render took {elapsed:.1f} s"


def test_opaque_stack_terminates_transmittance() -> None:
    """Five flat splats of opacity 0.95: T after 3 is 1.25e-4 >= 1e-4, the 4th would take it to
    6.25e-6, so the pixel stops there and the 4th and 5th (white) contribute nothing."""
    cam = axis_camera(24, 20, 30.0)
    zs = [6.0, 3.0, 5.0, 2.0, 4.0]  # scrambled: the renderer has to sort
    cols = {2.0: (1, 0, 0), 3.0: (0, 1, 0), 4.0: (0, 0, 1), 5.0: (1, 1, 1), 6.0: (1, 1, 1)}
    g = gaussians([[0, 0, z] for z in zs], 1e3, 0.95, colours=[cols[z] for z in zs])
    out = render(g, cam)
    assert_finite(out)
    w = [0.95, 0.05 * 0.95, 0.05**2 * 0.95]
    np.testing.assert_allclose(out.rgb[0], w[0], atol=1e-6)
    np.testing.assert_allclose(out.rgb[1], w[1], atol=1e-6)
    np.testing.assert_allclose(out.rgb[2], w[2], atol=1e-6)  # + 1.2e-4 if the 4th were drawn
    np.testing.assert_allclose(out.alpha, sum(w), atol=1e-6)
    np.testing.assert_allclose(out.depth, (2 * w[0] + 3 * w[1] + 4 * w[2]) / sum(w), rtol=1e-6)
    # Cap at 0.99: one splat of opacity 1 lets 1% through to the one behind it.
    g2 = gaussians([[0, 0, 2.0], [0, 0, 3.0]], 1e3, 1.0, colours=[(1, 0, 0), (0, 1, 0)])
    out2 = render(g2, cam)
    np.testing.assert_allclose(out2.rgb[0], 0.99, atol=1e-6)
    np.testing.assert_allclose(out2.rgb[1], 0.01 * 0.99, atol=1e-6)


def test_opaque_stack_of_small_splats_matches_reference() -> None:
    """Many coincident opaque splats at a pixel, small enough that tiles split them."""
    rng = np.random.default_rng(11)
    n = 40
    means = np.c_[rng.normal(0, 0.05, (n, 2)), rng.uniform(2, 4, n)]
    g = make_gaussians(
        means,
        rng.normal(size=(n, 4)),
        rng.uniform(0.05, 0.3, (n, 3)),
        np.full(n, 1.0),
        dc_for(rng.uniform(0, 1, (n, 3)))[:, None],
    )
    assert_matches_reference(g, axis_camera(37, 29, 30.0, 18.2, 14.9), RasterSettings(tile_px=8))


# --- 4. the real scene -----------------------------------------------------------------------


def test_donut_renders_plausibly(shared_scenes: Path) -> None:
    from nhfd.scene.io import load_scene

    path = shared_scenes / "donut.ply"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    g = load_scene(path)
    centre = np.median(g.means, 0)
    r, t = orbit(centre, 30, 35, 0.35, "+z")
    fx, fy, cx, cy = intrinsics_from_fov(256, 144, 40)
    cam = Camera(r, t, fx, fy, cx, cy, 256, 144)
    out = render(g, cam)
    assert_finite(out)
    frac = float((out.alpha > 0.5).mean())
    assert 0.2 <= frac <= 0.8, f"alpha > 0.5 on {frac:.0%} of pixels"
    assert out.rgb.min() >= 0.0 and out.rgb.max() <= 1.2
    assert out.alpha.min() >= 0.0 and out.alpha.max() <= 1.0
    # Composited on black: rgb / alpha is a weighted mean of the splats' colours.
    cmax = np.maximum(g.base_colors(), 0).max(0)[:, None, None]
    assert (out.rgb <= cmax * out.alpha + 1e-5).all()
    # Depth lies between the nearest and farthest drawable centre.
    zc = (g.means.astype(np.float64) - cam.position) @ cam.R[2]
    zc = zc[(zc >= cam.near)]
    drawn = out.alpha > 0.5
    assert out.depth[drawn].min() >= zc.min() - 1e-6
    assert out.depth[drawn].max() <= zc.max() + 1e-6
    # Most of the donut is about the orbit radius away.
    med = float(np.median(out.depth[drawn]))
    assert 0.2 < med < 0.45, med
