"""Up-axis detection and the suggested camera (nhfd.scene.suggest)."""

from __future__ import annotations

import numpy as np
import pytest

from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import Gaussians, make_gaussians
from nhfd.scene.io import load_scene, save_compressed_ply, save_ply
from nhfd.scene.suggest import (
    FILL,
    detect_up_axis,
    format_hint,
    robust_frame,
    suggest_camera,
)


def scene_from_means(means: np.ndarray, scale: float = 0.01) -> Gaussians:
    n = means.shape[0]
    return make_gaussians(
        means=means,
        quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        scales=np.full((n, 3), scale),
        opacities=np.full(n, 0.9),
        sh=np.zeros((n, 1, 3)),
    )


def slab(rng: np.random.Generator, flat_axis: int, bulk_sign: float, n: int = 2000) -> Gaussians:
    """A 2 x 2 x 0.3 slab, flat along `flat_axis`, 70% of its points in the 0.03 nearest the
    `bulk_sign` face: an object seen from that side (more Gaussians on top)."""
    m = rng.uniform(-1.0, 1.0, (n, 3))
    t = np.where(rng.random(n) < 0.7, rng.uniform(0.27, 0.3, n), rng.uniform(0.0, 0.3, n))
    m[:, flat_axis] = bulk_sign * t
    return scene_from_means(m)


def project(cam: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v) and camera z of world points, written out from the pinhole model."""
    pc = points @ cam.R.T + cam.t
    u = cam.fx * pc[:, 0] / pc[:, 2] + cam.cx
    v = cam.fy * pc[:, 1] / pc[:, 2] + cam.cy
    return np.stack([u, v], 1), pc[:, 2]


# --- up axis on the shared scenes ------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "up", "hint"),
    [("donut.ply", "+z", "ply"), ("guitar.compressed.ply", "-y", "compressed"),
     ("tiny-sh.compressed.ply", "-y", "compressed")],
)
def test_shared_scenes_get_their_known_up_axis(shared_scenes, name, up, hint):
    path = shared_scenes / name
    assert format_hint(path) == hint
    axis, reason = detect_up_axis(load_scene(path), format_hint(path))
    assert axis == up, reason


def test_donut_is_z_up_by_shape_even_without_a_format_hint(shared_scenes):
    axis, reason = detect_up_axis(load_scene(shared_scenes / "donut.ply"))
    assert axis == "+z" and "flat along z" in reason


# --- up axis rules on synthetic scenes -------------------------------------------------------


@pytest.mark.parametrize(("axis", "sign", "expect"),
                         [(2, 1.0, "+z"), (2, -1.0, "-z"), (1, -1.0, "-y"), (0, 1.0, "+x")])
def test_flat_scene_is_up_along_its_thin_axis_toward_the_bulk(axis, sign, expect):
    g = slab(np.random.default_rng(0), axis, sign)
    assert detect_up_axis(g, "ply")[0] == expect


def test_format_convention_beats_shape_for_compressed_and_splat():
    g = slab(np.random.default_rng(1), 2, 1.0)
    for hint in ("compressed", "splat"):
        axis, reason = detect_up_axis(g, hint)
        assert axis == "-y" and "convention" in reason


def test_round_blob_falls_back_to_opencv_y_down():
    g = scene_from_means(np.random.default_rng(2).normal(size=(500, 3)))
    axis, reason = detect_up_axis(g, "ply")
    assert axis == "-y" and "no clearly flat axis" in reason


def test_symmetric_flat_scene_takes_the_conventional_sign():
    m = np.random.default_rng(3).uniform(-1, 1, (2000, 3))
    m[:, 2] *= 0.1  # flat along z, symmetric: the median is mid-range
    axis, reason = detect_up_axis(scene_from_means(m))
    assert axis == "+z" and "convention" in reason


def test_tiny_and_empty_scenes_use_the_convention_and_bad_hints_are_refused():
    assert detect_up_axis(scene_from_means(np.zeros((1, 3))))[0] == "-y"
    assert detect_up_axis(Gaussians.empty())[0] == "-y"
    with pytest.raises(ValueError, match="format hint"):
        detect_up_axis(Gaussians.empty(), "obj")


def test_format_hint_reads_the_header_not_the_name(tmp_path):
    g = scene_from_means(np.zeros((3, 3)))
    save_compressed_ply(tmp_path / "a.ply", g)
    save_ply(tmp_path / "b.compressed.ply", g)
    (tmp_path / "c.splat").write_bytes(b"\0" * 32)
    assert format_hint(tmp_path / "a.ply") == "compressed"
    assert format_hint(tmp_path / "b.compressed.ply") == "ply"
    assert format_hint(tmp_path / "c.splat") == "splat"
    assert format_hint(tmp_path / "missing.ply") is None


# --- suggested camera ------------------------------------------------------------------------


def check_framing(g: Gaussians, cam: Camera) -> None:
    centre, lo, hi = robust_frame(g)
    uv, z = project(cam, centre[None])
    assert np.allclose(uv[0], [cam.width_px / 2, cam.height_px / 2], atol=1e-6)
    corners = np.array([[x, y, w] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for w in (lo[2], hi[2])])
    uv, z = project(cam, corners)
    assert (z > cam.near).all()
    assert (uv >= 0).all() and (uv <= [cam.width_px, cam.height_px]).all()
    # The binding direction reaches FILL of the half-image: framed, not lost in the middle.
    reach = np.abs(uv - [cam.cx, cam.cy]) / [cam.cx, cam.cy]
    assert reach.max() == pytest.approx(FILL, rel=1e-6)
    radius = np.linalg.norm(cam.position - centre)
    assert cam.near == pytest.approx(0.01 * radius)


@pytest.mark.parametrize(("w", "h", "up"), [(1024, 576, "+z"), (300, 900, "-y"), (1, 1, "+x")])
def test_suggested_camera_centres_and_frames_a_random_scene(w, h, up):
    g = scene_from_means(np.random.default_rng(4).normal([3.0, -1.0, 2.0], [1.0, 0.5, 2.0],
                                                          (1000, 3)))
    check_framing(g, suggest_camera(g, w, h, up))


def test_suggested_camera_frames_the_donut(shared_scenes):
    g = load_scene(shared_scenes / "donut.ply")
    check_framing(g, suggest_camera(g, 1024, 576, "+z"))


def test_suggested_camera_is_deterministic():
    g = scene_from_means(np.random.default_rng(5).normal(size=(300, 3)))
    a, b = suggest_camera(g, 640, 480, "-y"), suggest_camera(g, 640, 480, "-y")
    assert np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t) and a.near == b.near


def test_one_gaussian_and_empty_scenes_still_get_a_camera():
    one = scene_from_means(np.array([[1.0, 2.0, 3.0]]), scale=0.1)
    cam = suggest_camera(one, 64, 64, "+z")
    uv, z = project(cam, np.array([[1.0, 2.0, 3.0]]))
    assert np.allclose(uv[0], [32, 32]) and 0 < z[0] < 10
    cam = suggest_camera(Gaussians.empty(), 64, 64, "+z")
    assert np.isfinite(cam.position).all() and np.linalg.norm(cam.position) > 0


@pytest.mark.parametrize(
    ("name", "hint", "covered"),
    [
        ("donut.ply", None, (0.15, 0.8)),
        ("guitar.compressed.ply", "compressed", (0.02, 0.8)),  # a slim guitar: 3.6%
        ("tiny-sh.compressed.ply", "compressed", (0.005, 0.9)),
    ],
)
def test_shared_scenes_render_plausibly_from_their_suggested_cameras(
    shared_scenes, name, hint, covered
):
    from nhfd.scene.raster import render

    g = load_scene(shared_scenes / name)
    up, _ = detect_up_axis(g, hint)
    cam = suggest_camera(g, 160, 90, up)
    view = render(g, cam)
    opaque = float((view.alpha > 0.5).mean())
    # Something is in view, centred, and not filling the frame.
    assert covered[0] < opaque < covered[1], opaque
    ys, xs = np.nonzero(view.alpha > 0.5)
    assert abs(xs.mean() - 80) < 25 and abs(ys.mean() - 45) < 20
    # Colours of a trained scene stay (nearly) in the displayable range, depth near the camera's
    # distance to the centre.
    rgb = view.rgb[:, view.alpha > 0.5]
    assert np.isfinite(view.rgb).all() and float(np.quantile(rgb, 0.99)) < 1.5
    distance = float(np.linalg.norm(cam.position - np.median(g.means, axis=0)))
    assert 0.5 * distance < float(np.median(view.depth[view.alpha > 0.5])) < 1.5 * distance
