"""`nhfd.scene.cull`: a scene reduced to its pose envelope renders the envelope's views as the
original does (exactly for splats no view draws, within the grey-level budget for faint splats
and dropped SH bands), and only what the envelope cannot show goes.

Scenes are small and synthetic, built so that what must go (and what must stay) is known."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nhfd.cli.main import main
from nhfd.dataset.envelope import dataset_envelope
from nhfd.dataset.poses import Pose
from nhfd.dataset.shard import ExampleSettings, camera_distance
from nhfd.scene.cameras import Camera, intrinsics_from_fov, look_at
from nhfd.scene.cull import (
    GREY_LEVEL,
    envelope_light_field_cameras,
    max_weights,
    reduce_scene,
    truncate_sh,
    visible_anywhere,
)
from nhfd.scene.gaussians import Gaussians, make_gaussians
from nhfd.scene.io import load_scene, save_ply
from nhfd.scene.lightfield import DepthMapping, view_camera
from nhfd.scene.raster import render

W, H, FOV_DEG = 64, 48, 50.0


def camera(eye=(0.0, 0.0, 0.0), target=(0.0, 0.0, 1.0)) -> Camera:
    r, t = look_at(np.array(eye), np.array(target), "-y")
    fx, fy, cx, cy = intrinsics_from_fov(W, H, FOV_DEG)
    return Camera(r, t, fx, fy, cx, cy, W, H, near=0.05)


def light_field(cam: Camera, step: float = 0.04) -> list[Camera]:
    """The camera and its sideways-moved neighbours: a small light field (one rotation)."""
    return [cam.translated(dx, dy) for dx in (-step, 0.0, step) for dy in (-step, 0.0, step)]


def envelope() -> list[Camera]:
    return light_field(camera()) + light_field(camera((0.3, -0.1, 0.0), (0.1, 0.0, 2.5)))


def splats(rng, n, lo, hi, scale=(0.02, 0.06), opacity=(0.3, 0.9), sh_degree=0) -> dict:
    k = (sh_degree + 1) ** 2
    sh = np.zeros((n, k, 3))
    sh[:, 0] = rng.uniform(-1.2, 1.2, (n, 3))  # colour 0.5 + C0 * dc in about [0.16, 0.84]
    return dict(means=rng.uniform(lo, hi, (n, 3)), quats=rng.normal(size=(n, 4)),
                scales=rng.uniform(*scale, (n, 3)), opacities=rng.uniform(*opacity, n), sh=sh)


def scene(*parts: dict) -> Gaussians:
    return make_gaussians(**{k: np.concatenate([p[k] for p in parts]) for k in parts[0]})


def change(a: Gaussians, b: Gaussians, cams) -> float:
    """Largest change of clipped sRGB or alpha between the two scenes' renders of `cams`."""
    worst = 0.0
    for cam in cams:
        ra, rb = render(a, cam), render(b, cam)
        worst = max(worst, float(np.abs(np.clip(ra.rgb, 0, 1) - np.clip(rb.rgb, 0, 1)).max()),
                    float(np.abs(ra.alpha - rb.alpha).max()))
    return worst


def rows(g: Gaussians) -> set:
    return {tuple(m) for m in np.round(g.means, 5)}


# --- drawn in no view ---------------------------------------------------------------------


def test_splats_no_envelope_view_draws_go_and_every_envelope_view_is_unchanged():
    rng = np.random.default_rng(7)
    front = splats(rng, 150, (-0.6, -0.45, 2.0), (0.6, 0.45, 3.0))
    behind = splats(rng, 40, (-1.0, -1.0, -3.0), (1.0, 1.0, -1.0))
    aside = splats(rng, 30, (8.0, -1.0, 2.0), (10.0, 1.0, 3.0))
    g = scene(front, behind, aside)
    cams = envelope()
    reduced, report = reduce_scene(g, cams, prune_sh=False, cull_faint=False)
    assert (report.n_gaussians_in, report.n_culled_frustum, report.n_kept) == (220, 70, 150)
    assert rows(reduced) == rows(scene(front))
    # Never composited in any envelope view: every envelope view is the same image.
    assert change(g, reduced, cams) <= 1e-6
    assert report.max_grey_change <= 1e-6 / GREY_LEVEL
    # A view outside the envelope (turned round) sees what was culled.
    back = camera(target=(0.0, 0.0, -1.0))
    assert change(g, reduced, [back]) > 0.1


def test_a_splat_centred_outside_the_image_whose_ellipse_reaches_in_is_kept():
    """Conservative by the renderer's own extent: the centre projects beyond the right edge, the
    ellipse (`opacity * exp(-q) >= 1/255`) still covers pixels, so it stays; a small one at the
    same place is drawn nowhere and goes."""
    cam = camera()
    z = 2.0
    x_edge = (W - cam.cx) / cam.fx * z  # world x of the image's right edge at depth z
    big = dict(means=[[x_edge + 0.15, 0.0, z]], quats=[[1.0, 0, 0, 0]], scales=[[0.1] * 3],
               opacities=[0.9], sh=np.ones((1, 1, 3)))
    small = {**big, "means": [[x_edge + 0.15, 0.3, z]], "scales": [[0.01] * 3]}
    g = scene(big, small)
    seen = visible_anywhere(g, [cam])
    assert seen.tolist() == [True, False]
    assert float(render(g.subset(np.array([0])), cam).alpha.max()) > 0.1  # it does show


def test_light_field_views_are_all_in_the_envelope():
    """A splat only the moved views of a light field reach is kept, though the central view
    does not draw it."""
    cam = camera()
    z = 2.0
    x_edge = (W - cam.cx) / cam.fx * z
    g = scene(dict(means=[[x_edge + 0.1, 0.0, z]], quats=[[1.0, 0, 0, 0]],
                   scales=[[0.004] * 3], opacities=[0.9], sh=np.ones((1, 1, 3))))
    assert not visible_anywhere(g, [cam])[0]
    assert visible_anywhere(g, light_field(cam, step=0.1))[0]


# --- faint splats ---------------------------------------------------------------------------


def test_max_weights_are_alpha_times_transmittance():
    """One splat centred on a pixel centre weighs its opacity; a second straight behind it
    weighs its opacity times the first's transmittance."""
    cam = camera()
    z = 2.0
    x, y = 0.5 * z / cam.fx, 0.5 * z / cam.fy  # projects onto the centre of pixel (24, 32)
    a, b = 0.6, 0.5
    # The front splat is wide and the back one narrow, so the back one weighs most at its
    # centre, where the front one's alpha is its opacity.
    g = scene(dict(means=[[x, y, z], [1.5 * x, 1.5 * y, 1.5 * z]], quats=[[1.0, 0, 0, 0]] * 2,
                   scales=[[0.5] * 3, [0.01] * 3], opacities=[a, b], sh=np.ones((2, 1, 3))))
    w = max_weights(g, [cam])
    a, b = float(np.float32(a)), float(np.float32(b))  # as stored
    assert w[0] == pytest.approx(a, rel=1e-12)
    assert w[1] == pytest.approx(b * (1 - a), rel=1e-6)


def hidden_scene(rng):
    # Six nearly opaque layers at z = 2..2.25 that cover the whole view (T < 1e-4 behind them),
    # with splats behind them that no envelope view can see.
    wall = [dict(means=[[0.0, 0.0, 2.0 + 0.05 * i]], quats=[[1.0, 0, 0, 0]], scales=[[1.5] * 3],
                 opacities=[0.99], sh=np.full((1, 1, 3), 0.5)) for i in range(6)]
    hidden = splats(rng, 50, (-0.5, -0.4, 3.0), (0.5, 0.4, 4.0))
    return wall, hidden


def test_hidden_splats_go_and_the_change_stays_within_a_grey_level():
    rng = np.random.default_rng(11)
    wall, hidden = hidden_scene(rng)
    g = scene(*wall, hidden)
    cams = envelope()
    reduced, report = reduce_scene(g, cams)
    assert report.n_culled_frustum == 0  # the hidden splats are in every frustum
    assert report.n_culled_contribution >= 50
    assert not rows(reduced) & rows(scene(hidden))
    assert len(reduced) >= 1 and report.n_kept == len(reduced)
    assert change(g, reduced, cams) <= GREY_LEVEL
    assert report.max_grey_change <= 1.0


def test_many_faint_splats_that_add_up_stay():
    """Forty splats behind a half-transparent one each weigh about half a grey level, but together
    they make about twenty: a per-splat cut alone would break the budget; the check keeps them."""
    cam = camera()
    front = dict(means=[[0.0, 0.0, 2.0]], quats=[[1.0, 0, 0, 0]], scales=[[0.3] * 3],
                 opacities=[0.5], sh=np.zeros((1, 1, 3)))
    n = 40
    faint = dict(means=np.column_stack([np.zeros(n), np.zeros(n), 2.5 + 0.02 * np.arange(n)]),
                 quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.3),
                 opacities=np.full(n, 0.0045), sh=np.full((n, 1, 3), 1.77))  # colour ~1
    g = scene(front, faint)
    w = max_weights(g, [cam])
    assert (w[1:] < GREY_LEVEL).all()  # each below one grey level on its own
    assert change(g, g.subset(np.array([0])), [cam]) > 10 * GREY_LEVEL  # together far above
    reduced, report = reduce_scene(g, [cam])
    assert change(g, reduced, [cam]) <= GREY_LEVEL
    assert report.n_kept >= 30


def test_no_budget_culls_nothing_faint():
    rng = np.random.default_rng(11)
    wall, hidden = hidden_scene(rng)
    _, report = reduce_scene(scene(*wall, hidden), [camera()], grey_levels=0.0)
    assert report.n_culled_contribution == 0 and report.n_kept == 56


# --- SH bands ---------------------------------------------------------------------------------


def sh_scene(band2_scale: float) -> Gaussians:
    """Degree 2: band 1 moves colours by tenths (far above a grey level), band 2 by
    `band2_scale` (basis values reach about 1.1)."""
    rng = np.random.default_rng(5)
    p = splats(rng, 60, (-0.6, -0.45, 2.0), (0.6, 0.45, 3.0), opacity=(0.6, 0.95), sh_degree=2)
    p["sh"][:, 0] = rng.uniform(-0.4, 0.4, (60, 3))  # colours about 0.5 +- 0.1: never clipped
    p["sh"][:, 1:4] = rng.uniform(-0.25, 0.25, (60, 3, 3))
    p["sh"][:, 4:9] = rng.uniform(-1, 1, (60, 5, 3)) * band2_scale
    return scene(p)


def sh_envelope() -> list[Camera]:
    # Views from well apart, so the view-dependent bands vary across the envelope.
    return [camera(eye, (0.0, 0.0, 2.5)) for eye in ((0.0, 0.0, 0.0), (1.2, 0.0, 0.3),
                                                      (-0.8, 0.8, 0.4))]  # fmt: skip


@pytest.mark.parametrize(("band2_scale", "kept_degree"), [(0.2 / 255, 1), (8.0 / 255, 2)])
def test_sh_bands_go_only_while_the_change_stays_within_a_grey_level(band2_scale, kept_degree):
    g, cams = sh_scene(band2_scale), sh_envelope()
    reduced, report = reduce_scene(g, cams, cull_faint=False)
    assert (report.sh_degree_in, report.sh_degree_out) == (2, kept_degree)
    assert reduced.sh_degree == kept_degree
    # The kept degree is within the budget, and one band fewer is not (checked here directly).
    assert change(g, truncate_sh(g, kept_degree), cams) <= GREY_LEVEL
    assert change(g, truncate_sh(g, kept_degree - 1), cams) > GREY_LEVEL
    assert report.sh_grey_change <= 1.0


def test_bad_arguments_say_what_is_allowed():
    g, cams = sh_scene(0.0), sh_envelope()
    with pytest.raises(ValueError, match=r"grey_levels must be in \[0, 255\], got -1"):
        reduce_scene(g, cams, grey_levels=-1)
    with pytest.raises(ValueError, match="grey_levels"):
        reduce_scene(g, cams, grey_levels=float("nan"))
    with pytest.raises(ValueError, match="at least one envelope camera"):
        reduce_scene(g, [])
    with pytest.raises(ValueError, match=r"SH degree must be in \[0, 2\], got 3"):
        truncate_sh(g, 3)


def test_report_counts_add_up_and_serialise():
    rng = np.random.default_rng(3)
    wall, hidden = hidden_scene(rng)
    g = scene(*wall, hidden, splats(rng, 10, (-1, -1, -3), (1, 1, -2)))
    _, report = reduce_scene(g, envelope(), timing_views=2)
    d = json.loads(json.dumps(report.to_dict()))
    assert d["n_gaussians_in"] == d["n_kept"] + d["n_culled_frustum"] + d["n_culled_contribution"]
    assert d["n_culled_frustum"] == 10
    assert d["n_views_envelope"] == 18 and d["n_views_checked"] == 18 and d["n_views_timed"] == 2
    assert d["render_s_before"] > 0 and d["render_s_after"] > 0
    # Fewer splats composited: the work (splat-tile pairs) of the timed views goes down.
    assert 0 < d["tile_pairs_after"] < d["tile_pairs_before"]
    assert f"kept {d['n_kept']} of {len(g)}" in report.summary()


# --- the dataset's envelope and the command -------------------------------------------------


def test_envelope_cameras_are_the_light_field_views():
    cam = camera()
    mapping = DepthMapping(-0.02, 0.05)
    taus = [np.array([-1e-3, 0.0, 1e-3])]
    cams = envelope_light_field_cameras([cam], mapping, 8e-6, taus)
    assert len(cams) == 9
    for i, (ty, tx) in enumerate((ty, tx) for ty in taus[0] for tx in taus[0]):
        expect = view_camera(cam, mapping, 8e-6, tx, ty)[1]
        assert np.array_equal(cams[i].t, expect.t) and cams[i].cx == expect.cx
    assert np.array_equal(cams[4].t, cam.t) and cams[4].cx == cam.cx  # tau = 0: the pose itself


def test_dataset_envelope_holds_every_view_the_build_renders():
    rng = np.random.default_rng(2)
    g = scene(splats(rng, 80, (-0.5, -0.4, 2.0), (0.5, 0.4, 3.0)))
    settings = ExampleSettings(width_px=64, height_px=36)
    poses = []
    for eye in ((0.0, 0.0, 0.0), (0.4, 0.0, 0.1)):
        r, t = look_at(np.array(eye), np.array([0.0, 0.0, 2.5]), "-y")
        poses.append(Pose(tuple(map(tuple, r)), tuple(t), "train"))
    env = dataset_envelope(g, poses, np.array([0.0, 0.0, 2.5]), settings)
    per_pose = env.views_per_pose
    assert per_pose == len(env.sampling[0]["k"]) ** 2  # shared views: the longest wavelength's
    assert len(env.cameras) == 2 * (1 + per_pose)
    assert (env.cameras[0].width_px, env.cameras[0].height_px) == (16, 9)  # the depth pass
    central = settings.camera(poses[1], camera_distance(poses[1], np.array([0.0, 0.0, 2.5])))
    middle = env.cameras[2 + per_pose + per_pose // 2]  # pose 1, bin k = 0
    assert np.allclose(middle.t, central.t, atol=1e-15) and middle.cx == central.cx


def test_scene_reduce_command_writes_the_reduced_scene(tmp_path, capsys):
    rng = np.random.default_rng(4)
    g = scene(splats(rng, 60, (-0.3, -0.3, -0.3), (0.3, 0.3, 0.3)),
              splats(rng, 5, (-0.3, -0.3, -0.3), (0.3, 0.3, 0.3), opacity=(0.001, 0.003)))
    src, out = tmp_path / "s.ply", tmp_path / "reduced.ply"
    save_ply(src, g)
    code = main(["scene", "reduce", str(src), "-o", str(out), "--views", "2", "--size", "64x36",
                 "--up=-y", "--check-views", "4", "--json"])
    assert code == 0
    d = json.loads(capsys.readouterr().out)
    assert d["reduction"]["n_culled_frustum"] >= 5  # below 1/255 opacity: drawn in no view
    assert len(load_scene(out)) == d["reduction"]["n_kept"]
    assert d["envelope"]["n_poses"] == 2
    assert d["reduction"]["max_grey_change"] <= 1.0


def test_scene_reduce_rejects_a_bad_budget(tmp_path, capsys):
    code = main(["scene", "reduce", str(tmp_path / "absent.ply"), "--grey-levels", "300"])
    assert code == 2
    assert "--grey-levels 300: must be in [0, 255]" in capsys.readouterr().err
