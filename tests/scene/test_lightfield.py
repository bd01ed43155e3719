"""Light-field sampling and the translated-camera views of docs/physics.md."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nhfd.scene.cameras import Camera, intrinsics_from_fov, look_at
from nhfd.scene.gaussians import make_gaussians
from nhfd.scene.lightfield import (
    DepthMapping,
    directions,
    hogel_window,
    iter_views,
    render_light_field,
    shared_windows,
)

PITCH_M = 8e-6
RED_M, GREEN_M, BLUE_M = 660e-9, 520e-9, 450e-9


def test_window_follows_the_volume_and_aperture():
    # docs/physics.md: +-3 mm at 660 nm with the half-band aperture needs W = 16 (15.5 px cone), and
    # the central 8 x 8 directions pass: 64 views for red.
    assert hogel_window(RED_M, PITCH_M, 3e-3, 0.25) == 16
    k, tau = directions(16, RED_M, PITCH_M, 0.25)
    np.testing.assert_array_equal(k, np.arange(-4, 4))
    # tau_k = tan(asin(lambda k / (W p))).
    np.testing.assert_allclose(tau, np.tan(np.arcsin(RED_M * k / (16 * PITCH_M))), rtol=1e-12)
    # Narrower aperture or shallower volume: fewer samples.
    assert hogel_window(RED_M, PITCH_M, 1e-3, 0.25) < 16
    assert len(directions(16, RED_M, PITCH_M, 0.125)[0]) == 4


def test_shared_directions_coincide_within_rounding():
    lams = (RED_M, GREEN_M, BLUE_M)
    windows, mismatch = shared_windows(lams, PITCH_M, 3e-3, 0.25)
    assert windows == [18, 14, 12]
    assert mismatch < 0.03
    k_ref, tau_ref = directions(windows[0], RED_M, PITCH_M, 0.25)
    for lam, w in zip(lams, windows, strict=True):
        # Each colour still covers its own cone...
        assert w >= hogel_window(lam, PITCH_M, 3e-3, 0.25)
        # ...and a shorter wavelength passes a narrower cone: its bins are the central subset of
        # red's, with the same slopes within the rounding of W to even.
        k, tau = directions(w, lam, PITCH_M, 0.25)
        assert set(k) <= set(k_ref)
        np.testing.assert_allclose(tau, tau_ref[np.searchsorted(k_ref, k)], rtol=mismatch + 1e-4)


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"wavelength_m": 660.0, "pitch_m": PITCH_M, "f_cut_per_px": 0.25}, "wavelength"),
        ({"wavelength_m": RED_M, "pitch_m": 0.0, "f_cut_per_px": 0.25}, "pitch"),
        ({"wavelength_m": RED_M, "pitch_m": PITCH_M, "f_cut_per_px": 0.6}, "cutoff"),
    ],
)
def test_invalid_optics_name_the_parameter(kwargs, fragment):
    with pytest.raises(ValueError, match=fragment):
        directions(16, **kwargs)


def test_mapping_puts_near_at_z_max():
    m = DepthMapping.from_range(1.0, 3.0, -3e-3, 3e-3)
    assert m.z_h(1.0) == pytest.approx(3e-3)
    assert m.z_h(3.0) == pytest.approx(-3e-3)
    with pytest.raises(ValueError, match="d_near"):
        DepthMapping.from_range(3.0, 1.0, -3e-3, 3e-3)


def _point_scene(depths: list[float]) -> tuple:
    """Small round Gaussians about 20 px apart, each about 1.2 px wide on screen (wide enough for
    a sampled centroid to be exact to 0.01 px), seen by a camera at the origin looking along +z."""
    n = len(depths)
    fx = intrinsics_from_fov(96, 96, 30)[0]
    means = np.array([[(i - 1) * 0.12 * d, -0.05 * d, d] for i, d in enumerate(depths)])
    g = make_gaussians(
        means,
        np.tile([1.0, 0, 0, 0], (n, 1)),
        np.array([[1.2 * d / fx] * 3 for d in depths]),
        np.full(n, 0.9),
        np.full((n, 1, 3), 1.5),
    )
    r, t = look_at([0, 0, 0], [0, 0, 1], "-y")
    fx, fy, cx, cy = intrinsics_from_fov(96, 96, 30)
    return g, Camera(r, t, fx, fy, cx, cy, 96, 96, near=0.05)


def _centroid(alpha: np.ndarray, around: tuple[float, float], radius: float = 6.0):
    ys, xs = np.mgrid[: alpha.shape[0], : alpha.shape[1]] + 0.5
    m = alpha * ((xs - around[0]) ** 2 + (ys - around[1]) ** 2 < radius**2)
    return float((m * xs).sum() / m.sum()), float((m * ys).sum() / m.sum())


def test_view_disparity_is_linear_in_tau_and_zero_at_the_reference_plane():
    # Three points: near (z_max), on the reference plane (z_h = 0), far (z_min).
    d_near, d_far = 0.8, 1.6
    m = DepthMapping.from_range(d_near, d_far, -3e-3, 3e-3)
    d_zero = -m.b_m / m.a_m  # inverse depth -a/b: z_h = 0
    depths = [d_near, d_zero, d_far]
    g, cam = _point_scene(depths)
    w = hogel_window(RED_M, PITCH_M, 3e-3, 0.25)
    _, tau = directions(w, RED_M, PITCH_M, 0.25)
    central = [
        (cam.fx * g.means[i, 0] / d + cam.cx, cam.fy * g.means[i, 1] / d + cam.cy)
        for i, d in enumerate(depths)
    ]
    moved = {0: 0.0, 1: 0.0, 2: 0.0}
    for iy, ix, view in iter_views(g, cam, m, PITCH_M, tau, tau):
        for i, d in enumerate(depths):
            z_h = float(m.z_h(d))
            # docs/physics.md: a point at z_h sits at u = u_0 - z_h tau / p in view tau.
            expect = (
                central[i][0] - z_h * tau[ix] / PITCH_M,
                central[i][1] - z_h * tau[iy] / PITCH_M,
            )
            got = _centroid(view.alpha, expect)
            assert got == pytest.approx(expect, abs=0.02), (i, iy, ix)
            moved[i] = max(moved[i], math.hypot(got[0] - central[i][0], got[1] - central[i][1]))
    # The extreme views move the near and far points by several pixels, the z_h = 0 point not.
    assert moved[0] > 5 and moved[2] > 5
    assert moved[1] < 0.02


def test_light_field_shapes_and_central_view():
    g, cam = _point_scene([1.0])
    m = DepthMapping.from_range(0.8, 1.6, -3e-3, 3e-3)
    lf = render_light_field(g, cam, m, BLUE_M, PITCH_M, 12, 0.25)
    n = len(lf.k_x)
    assert lf.rgb.shape == (n, n, 3, 96, 96) and lf.depth.shape == (n, n, 96, 96)
    assert np.isfinite(lf.rgb).all() and np.isfinite(lf.depth).all()
    # Every view sees the point at its depth (a lateral move keeps depth along the axis).
    views = zip(lf.depth.reshape(-1, 96, 96), lf.alpha.reshape(-1, 96, 96), strict=True)
    for view_depth, view_alpha in views:
        assert view_depth[view_alpha > 0.5] == pytest.approx(1.0, rel=1e-3)


def test_gsplat_backend_without_cuda_says_what_is_missing():
    from nhfd.scene import gsplat_backend
    from nhfd.scene.raster import render

    g, cam = _point_scene([1.0])
    if gsplat_backend.available():
        pytest.skip("CUDA and gsplat present: the GPU path is used")
    with pytest.raises(RuntimeError, match="CUDA device and the gsplat package"):
        render(g, cam, backend="gsplat")
    # "auto" falls back to the CPU and still draws the point.
    assert render(g, cam, backend="auto").alpha.max() > 0.5
    with pytest.raises(ValueError, match="backend must be one of"):
        render(g, cam, backend="opengl")
