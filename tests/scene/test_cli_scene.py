"""`nhfd scene info|render`, called in-process through nhfd.cli.main.main."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from nhfd.cli.main import main
from nhfd.scene.gaussians import make_gaussians
from nhfd.scene.io import save_ply

# Three small, well separated Gaussians (world units) seen by `POSE`: a camera at z = -4
# looking along +z with image-up -y, so R = I, t = (0, 0, 4) and camera z = world z + 4.
MEANS = np.array([[0.0, 0.0, 0.0], [0.6, 0.3, 1.0], [-0.5, -0.25, 0.5]])
POSE = "lookat:0,0,-4,0,0,0"
SIZE = (160, 120)
FOV_DEG = 40.0


@pytest.fixture
def tiny_scene(tmp_path):
    n = len(MEANS)
    g = make_gaussians(
        means=MEANS,
        quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        scales=np.full((n, 3), 0.03),
        opacities=np.full(n, 0.95),
        sh=np.full((n, 1, 3), 1.0),
    )
    path = tmp_path / "tiny.ply"
    save_ply(path, g)
    return path


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(["scene", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_info_json_on_the_donut(shared_scenes, capsys):
    code, out, _ = run(capsys, "info", shared_scenes / "donut.ply", "--json")
    info = json.loads(out)
    assert code == 0
    assert (info["count"], info["sh_degree"], info["up_axis"]) == (45624, 0, "+z")
    assert info["suggested_camera"]["pose"].startswith("lookat:")


def test_info_text_prints_a_render_command_that_parses(tiny_scene, capsys):
    code, out, _ = run(capsys, "info", tiny_scene)
    assert code == 0 and "gaussians     3" in out
    line = next(x for x in out.splitlines() if x.startswith("render it:"))
    assert "--pose lookat:" in line and "--up=" in line


def test_render_writes_rgb_of_the_size_and_depth_at_each_gaussian(tiny_scene, tmp_path, capsys):
    rgb, depth, alpha = tmp_path / "v.png", tmp_path / "d.npy", tmp_path / "a.npy"
    code, out, _ = run(capsys, "render", tiny_scene, "-o", rgb, "--size", "160x120", "--pose",
                       POSE, "--up=-y", "--fov", FOV_DEG, "--depth", depth, "--alpha", alpha)
    assert code == 0 and "rendered in" in out
    assert Image.open(rgb).size == SIZE and Image.open(rgb).mode == "RGB"
    d, a = np.load(depth), np.load(alpha)
    assert d.shape == a.shape == (SIZE[1], SIZE[0]) and d.dtype == np.float32
    fx = 0.5 * SIZE[0] / np.tan(np.radians(FOV_DEG) / 2)
    z = MEANS[:, 2] + 4.0
    cols = np.floor(fx * MEANS[:, 0] / z + SIZE[0] / 2).astype(int)
    rows = np.floor(fx * MEANS[:, 1] / z + SIZE[1] / 2).astype(int)
    assert (a[rows, cols] > 0.5).all()
    np.testing.assert_allclose(d[rows, cols], z, rtol=0.01)


def test_render_png_depth_carries_near_and_far(tiny_scene, tmp_path, capsys):
    depth, alpha = tmp_path / "d.png", tmp_path / "a.png"
    code, _, _ = run(capsys, "render", tiny_scene, "-o", tmp_path / "v.png", "--size", "160x120",
                     "--pose", POSE, "--up=-y", "--depth", depth, "--alpha", alpha)
    assert code == 0
    meta = Image.open(depth).text
    near, far = float(meta["nhfd:depth_near"]), float(meta["nhfd:depth_far"])
    # The nearest and farthest Gaussians' centres, camera z = 4 and 5.
    assert near == pytest.approx(4.0, rel=0.01) and far == pytest.approx(5.0, rel=0.01)
    assert Image.open(alpha).mode == "L" and Image.open(alpha).size == SIZE


def test_default_pose_is_the_suggested_camera_info_prints(tiny_scene, tmp_path, capsys):
    _, out, _ = run(capsys, "info", tiny_scene, "--json", "--size", "96x64")
    args = json.loads(out)["suggested_camera"]["render_args"]
    assert run(capsys, "render", tiny_scene, "-o", tmp_path / "a.png", "--size", "96x64")[0] == 0
    assert run(capsys, "render", tiny_scene, "-o", tmp_path / "b.png", *args)[0] == 0
    a = np.asarray(Image.open(tmp_path / "a.png"), np.int16)
    b = np.asarray(Image.open(tmp_path / "b.png"), np.int16)
    assert a.max() > 0 and np.abs(a - b).max() <= 1


@pytest.mark.parametrize(
    ("option", "value", "says"),
    [
        ("--size", "0x5", "'0x5'"),
        ("--size", "abc", "'abc' is not of the form WxH"),
        ("--pose", "orbit:1,2", "orbit takes 3 numbers"),
        ("--pose", "spin:1,2,3", "expected one of orbit:AZ,EL,R"),
        ("--pose", "orbit:30,nan,1", "EL = 'nan' must be finite"),
        ("--pose", "lookat:0,0,x,0,0,0", "EZ = 'x' is not a number"),
        ("--pose", "orbit:30,20,0", "radius R must be positive"),
        ("--pose", "pos:0,0,-4,0,0,0,0", "quaternion"),
        ("--up", "up", "--up 'up' is not an axis"),
        ("--fov", "180", "--fov 180"),
        ("--depth", "d.tiff", "'d.tiff' must end in .png or .npy"),
    ],
)
def test_bad_values_exit_2_naming_the_value(tiny_scene, tmp_path, capsys, option, value, says):
    code, _, err = run(capsys, "render", tiny_scene, "-o", tmp_path / "v.png", f"{option}={value}")
    assert code == 2
    assert err.startswith("nhfd scene: error:") and says in err


def test_missing_and_unreadable_scene_files_exit_2_naming_the_file(tmp_path, capsys):
    code, _, err = run(capsys, "info", tmp_path / "nope.ply")
    assert code == 2 and "nope.ply" in err and "not found" in err
    bad = tmp_path / "bad.ply"
    bad.write_text("hello")
    code, _, err = run(capsys, "render", bad, "-o", tmp_path / "v.png")
    assert code == 2 and "bad.ply" in err and "not a PLY file" in err


def test_info_refuses_random_data_as_the_daemon_does(tmp_path, capsys):
    from tests.scene.test_io import random_data_ply

    path = random_data_ply(tmp_path / "random.ply")
    code, out, err = run(capsys, "info", path)
    assert code == 2 and out == ""
    assert err.startswith(f"nhfd scene: error: {path}: not a plausible scene: ")


def test_info_reports_the_dropped_gaussians(tmp_path, capsys):
    from tests.scene.test_io import nan_scene

    save_ply(tmp_path / "some.ply", nan_scene(10, np.array([1, 4, 7])))
    with pytest.warns(UserWarning, match="dropped 3 of 10"):
        code, out, _ = run(capsys, "info", tmp_path / "some.ply", "--json")
    assert code == 0
    assert {k: json.loads(out)[k] for k in ("count", "declared", "dropped")} == {
        "count": 7, "declared": 10, "dropped": 3}
