"""Poses, the resumable dataset builder, and shards."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from nhfd.dataset.build import build, load_manifest, shard_name
from nhfd.dataset.poses import PoseSampler, load_poses, save_poses
from nhfd.dataset.shard import ExampleSettings, read_shard, write_shard
from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import make_gaussians
from nhfd.scene.io import save_ply


def sampler(**kw) -> PoseSampler:
    base = dict(center=(0.0, 0.0, 0.0), up="+z", radius=(1.0, 1.2), n_train=20, n_interp=5,
                n_extrap=4, seed=3)  # fmt: skip
    base.update(kw)
    return PoseSampler(**base)


def test_pose_splits_follow_the_documented_sectors():
    s = sampler()
    poses = s.sample()
    assert [p.split for p in poses].count("train") == 20
    assert [p.split for p in poses].count("interp") == 5
    assert [p.split for p in poses].count("extrap") == 4
    train = sorted(p.azimuth_deg for p in poses if p.split == "train")
    # Stratified: one training pose in each of the 20 equal slices of [-30, 30].
    np.testing.assert_array_equal(np.floor((np.array(train) + 30) / 3), np.arange(20))
    for p in poses:
        assert 1.0 <= p.radius <= 1.2
        assert np.linalg.norm(p.position) == pytest.approx(p.radius)  # no jitter: exact orbit
        if p.split == "interp":
            # Halfway between two neighbouring training azimuths.
            i = np.searchsorted(train, p.azimuth_deg)
            assert p.azimuth_deg == pytest.approx(0.5 * (train[i - 1] + train[i]))
        if p.split == "extrap":
            assert 32.0 <= p.azimuth_deg <= 42.0  # held-out sector past the training one
    # Deterministic in the seed.
    assert s.sample() == poses
    assert sampler(seed=4).sample() != poses


def test_sampled_cameras_look_at_the_centre():
    for p in sampler(n_train=5).sample():
        r, t = p.matrices()
        cam = Camera(r, t, 100.0, 100.0, 32.0, 24.0, 64, 48)
        c = cam.R @ np.zeros(3) + cam.t
        assert c[2] > 0
        assert c[0] / c[2] == pytest.approx(0.0, abs=1e-12)
        assert c[1] / c[2] == pytest.approx(0.0, abs=1e-12)


def test_pose_sampler_rejects_bad_ranges():
    with pytest.raises(ValueError, match="elevation_deg"):
        sampler(elevation_deg=(10.0, 95.0))
    with pytest.raises(ValueError, match="radius"):
        sampler(radius=(0.0, 1.0))


def test_poses_file_round_trip_and_errors(tmp_path):
    poses = sampler(n_train=3, n_interp=1, n_extrap=1).sample()
    path = tmp_path / "poses.json"
    save_poses(path, poses)
    back = load_poses(path)
    assert [p.split for p in back] == [p.split for p in poses]
    np.testing.assert_allclose(back[0].matrices()[0], poses[0].matrices()[0])
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([{"R": [[1, 0, 0], [0, 2, 0], [0, 0, 1]], "t": [0, 0, 1]}]))
    with pytest.raises(ValueError, match="pose 0: R is not a rotation"):
        load_poses(bad)
    bad.write_text(json.dumps([{"position": [0, 0, 0]}]))
    with pytest.raises(ValueError, match="needs R and t, or position and look_at"):
        load_poses(bad)


def _tiny_scene(path):
    """Three small bright Gaussians at different depths around the origin."""
    means = np.array([[0.0, 0.0, 0.0], [0.03, 0.01, 0.08], [-0.03, -0.01, -0.08]])
    g = make_gaussians(means, np.tile([1.0, 0, 0, 0], (3, 1)), np.full((3, 3), 0.01),
                       np.full(3, 0.9), np.full((3, 1, 3), 1.0))  # fmt: skip
    save_ply(path, g)
    return g


SMALL = ExampleSettings(width_px=40, height_px=32, fov_x_deg=30.0, panel_hw=(48, 64),
                        amplitude_samples=256)  # fmt: skip


def _poses():
    return sampler(radius=(1.0, 1.0), n_train=2, n_interp=1, n_extrap=0,
                   elevation_deg=(0.0, 0.0), azimuth_deg=(-5.0, 5.0)).sample()  # fmt: skip


def test_build_resume_and_refuse(tmp_path):
    scene = tmp_path / "tiny.ply"
    _tiny_scene(scene)
    out = tmp_path / "ds"
    poses = _poses()
    m = build(scene, out, poses, SMALL, seed=1)
    # One scene mapping for all views, from the depth pass: nearest content at z_max.
    mp = m["mapping"]
    assert 0 < mp["d_near"] < mp["d_far"]
    assert mp["a_m"] + mp["b_m"] / mp["d_near"] == pytest.approx(3e-3)
    assert m["amplitude_scale"]["value"] > 0
    assert m["splits"] == {"train": [0, 1], "interp": [2], "extrap": []}
    shards = [read_shard(out / shard_name(i)) for i in range(3)]
    for s in shards:
        assert s["field"].shape == (3, 32, 40) and s["field"].dtype == np.complex64
        assert s["meta"]["manifest_key"] == m["key"]
        assert np.abs(s["field"]).max() > 0
    # Interrupt: one shard lost, a half-written temporary left behind. Resume rebuilds only it.
    (out / shard_name(1)).unlink()
    (out / "view_00001.abc.tmp").write_bytes(b"partial")
    before = os.stat(out / shard_name(0)).st_mtime_ns
    build(scene, out, poses, SMALL, seed=1)
    assert os.stat(out / shard_name(0)).st_mtime_ns == before
    assert not list(out.glob("*.tmp"))
    again = read_shard(out / shard_name(1))
    np.testing.assert_array_equal(again["field"], shards[1]["field"])  # deterministic
    # Other settings into the same folder: refused, unless forced.
    with pytest.raises(ValueError, match="built with other settings"):
        build(scene, out, poses, SMALL, seed=2)
    assert load_manifest(out)["key"] == m["key"]


def test_workers_do_not_change_results(tmp_path):
    scene = tmp_path / "tiny.ply"
    _tiny_scene(scene)
    poses = _poses()[:2]
    build(scene, tmp_path / "one", poses, SMALL, seed=5, workers=1)
    build(scene, tmp_path / "two", poses, SMALL, seed=5, workers=2)
    for i in range(2):
        a = read_shard(tmp_path / "one" / shard_name(i))
        b = read_shard(tmp_path / "two" / shard_name(i))
        tol = 1e-6 * np.abs(a["field"]).max()
        np.testing.assert_allclose(a["field"], b["field"], rtol=0, atol=tol)
        np.testing.assert_array_equal(a["rgb"], b["rgb"])


def test_corrupt_shard_is_detected(tmp_path):
    path = tmp_path / "view_00000.npz"
    ex = {"rgb": np.zeros((3, 2, 2), np.float32), "depth": np.zeros((2, 2), np.float32),
          "alpha": np.zeros((2, 2), np.float32), "field": np.zeros((3, 2, 2), np.complex64),
          "amp_samples": np.zeros(0, np.float32)}  # fmt: skip
    write_shard(path, ex, {"manifest_key": "k"})
    assert read_shard(path)["meta"] == {"manifest_key": "k"}
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(ValueError, match="unreadable shard"):
        read_shard(path)


def test_show_writes_a_picture(tmp_path):
    from nhfd.dataset.show import show

    scene = tmp_path / "tiny.ply"
    _tiny_scene(scene)
    build(scene, tmp_path / "ds", _poses()[:1], SMALL, seed=1)
    info = show(tmp_path / "ds", 0, tmp_path / "s.png")
    assert info["planes_mm"] == pytest.approx([3.0, 0.0, -3.0])
    assert (tmp_path / "s.png").stat().st_size > 1000
    with pytest.raises(ValueError, match=r"has views 0\.\.0"):
        show(tmp_path / "ds", 5, tmp_path / "x.png")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--size", "abc"], "--size 'abc' is not of the form WxH"),
        (["--size", "0x10"], "width and height must be 1..8192 px"),
        (["--workers", "0"], "--workers 0: must be >= 1"),
        (["--azimuth", "30,-30"], "--azimuth '30,-30': need LOW <= HIGH"),
    ],
)
def test_build_cli_errors_name_the_value(tmp_path, capsys, argv, message):
    from nhfd.cli.main import main

    scene = tmp_path / "tiny.ply"
    _tiny_scene(scene)
    code = main(["dataset", "build", "--scene", str(scene), "--out", str(tmp_path / "d"), *argv])
    assert code == 2
    assert message in capsys.readouterr().err
