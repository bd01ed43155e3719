"""The dataset builder beyond one process: parts of N (`--shard K/N`) merged, Ray tasks on a local
two-worker instance, a worker killed mid-build; each compared byte for byte with the
single-process build of the same dataset."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from nhfd.dataset.build import CRASH_ENV, build, merge, parse_shard, shard_indices
from nhfd.dataset.poses import PoseSampler
from nhfd.dataset.shard import ExampleSettings
from nhfd.scene.gaussians import make_gaussians
from nhfd.scene.io import save_ply

SMALL = ExampleSettings(width_px=40, height_px=32, fov_x_deg=30.0, panel_hw=(48, 64),
                        amplitude_samples=256)  # fmt: skip
# The example the crash test's worker dies on (not the first: other tasks are running then).
CRASH_INDEX = 2


def _poses():
    return PoseSampler(center=(0.0, 0.0, 0.0), up="+z", radius=(1.0, 1.1), n_train=3,
                       n_interp=1, n_extrap=1, seed=3, elevation_deg=(0.0, 10.0),
                       azimuth_deg=(-8.0, 8.0)).sample()  # fmt: skip


def _scene(path: Path) -> Path:
    """Three small bright Gaussians at different depths around the origin."""
    means = np.array([[0.0, 0.0, 0.0], [0.03, 0.01, 0.08], [-0.03, -0.01, -0.08]])
    g = make_gaussians(means, np.tile([1.0, 0, 0, 0], (3, 1)), np.full((3, 3), 0.01),
                       np.full(3, 0.9), np.full((3, 1, 3), 1.0))  # fmt: skip
    save_ply(path, g)
    return path


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _assert_same_bytes(a: Path, b: Path) -> None:
    fa, fb = _files(a), _files(b)
    assert sorted(fa) == sorted(fb)
    assert "manifest.json" in fa and len(fa) == len(_poses()) + 1
    for name in fa:
        assert fa[name] == fb[name], f"{name} differs"


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The scene and its single-process build (torch on every core here; one thread in each pool
    or Ray worker)."""
    root = tmp_path_factory.mktemp("dist")
    scene = _scene(root / "tiny.ply")
    import torch

    threads = torch.get_num_threads()
    try:
        m = build(scene, root / "single", _poses(), SMALL, seed=7, workers=1)
    finally:
        torch.set_num_threads(threads)
    return scene, root / "single", m


def test_parts_merge_into_the_single_build(reference, tmp_path):
    scene, single, m = reference
    out = tmp_path / "parts"
    p1 = build(scene, out, _poses(), SMALL, seed=7, shard=(1, 2))
    # Part 1 alone: examples 0, 2, 4 exist, the manifest is still the plan.
    assert sorted(p.name for p in out.glob("view_*.npz")) == [
        "view_00000.npz", "view_00002.npz", "view_00004.npz"]  # fmt: skip
    assert p1["amplitude_scale"] is None
    with pytest.raises(ValueError, match=r"2 of 5 shards are missing .* \(examples 1, 3\)"):
        merge(out)
    # Part 2 finds every shard present and completes the manifest.
    p2 = build(scene, out, _poses(), SMALL, seed=7, shard=(2, 2))
    assert p2["amplitude_scale"] == m["amplitude_scale"]
    _assert_same_bytes(single, out)
    # An explicit merge of a complete folder rewrites the same bytes.
    merge(out)
    _assert_same_bytes(single, out)
    # A part run again finds its shards valid and builds nothing.
    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("view_*.npz")}
    again = build(scene, out, _poses(), SMALL, seed=7, shard=(1, 2))
    assert "build_timing" not in again
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("view_*.npz")} == stamps
    _assert_same_bytes(single, out)


def test_a_part_with_other_settings_is_refused_naming_the_setting(reference, tmp_path):
    scene, _, _ = reference
    out = tmp_path / "mixed"
    build(scene, out, _poses(), SMALL, seed=7, shard=(1, 2))
    with pytest.raises(ValueError, match=r"settings\.width_px: 40 != 48"):
        build(scene, out, _poses(), replace(SMALL, width_px=48), seed=7, shard=(2, 2))
    with pytest.raises(ValueError, match=r"seed: 7 != 8"):
        build(scene, out, _poses(), SMALL, seed=8, shard=(2, 2))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("0/2", "--shard '0/2': need N >= 1 and K in 1..N"),
        ("3/2", "--shard '3/2': need N >= 1 and K in 1..N"),
        ("1/0", "--shard '1/0': need N >= 1 and K in 1..N"),
        ("a/b", "--shard 'a/b' is not of the form K/N"),
        ("1/2/3", "--shard '1/2/3' is not of the form K/N"),
    ],
)
def test_bad_shard_values_name_the_value(text, message, tmp_path, capsys):
    with pytest.raises(ValueError) as err:
        parse_shard(text)
    assert str(err.value).startswith(message)
    from nhfd.cli.main import main

    code = main(["dataset", "build", "--scene", str(_scene(tmp_path / "s.ply")),
                 "--out", str(tmp_path / "d"), "--shard", text])  # fmt: skip
    assert code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "d").exists()  # refused before anything is rendered


def test_parts_cover_every_example_once():
    for n in (1, 2, 3, 7):
        parts = [shard_indices(10, (k, n)) for k in range(1, n + 1)]
        assert sorted(i for p in parts for i in p) == list(range(10))
    assert shard_indices(10, (2, 3)) == [1, 4, 7]


# ---- Ray: one local two-worker instance shared by the Ray tests (its start takes seconds).


@pytest.fixture(scope="module")
def ray_local(tmp_path_factory):
    ray = pytest.importorskip("ray", reason="Ray is the optional extra nhfd[ray]")
    crash_dir = tmp_path_factory.mktemp("crash")
    # Workers inherit the environment of the instance: the crash hook is set here, and armed
    # (by a file) only in the test that wants a worker to die.
    os.environ[CRASH_ENV] = f"{CRASH_INDEX}:{crash_dir}"
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        yield crash_dir
    finally:
        ray.shutdown()
        os.environ.pop(CRASH_ENV, None)


def test_ray_build_equals_the_single_build(reference, ray_local, tmp_path):
    scene, single, _ = reference
    out = tmp_path / "ray"
    m = build(scene, out, _poses(), SMALL, seed=7, executor="ray", workers=2)
    assert m["build_timing"]["examples"] == len(_poses())
    _assert_same_bytes(single, out)
    assert not (ray_local / "crashed").exists()


def test_a_killed_ray_worker_is_retried_and_the_build_completes(reference, ray_local, tmp_path):
    scene, single, _ = reference
    (ray_local / "armed").write_text("")
    try:
        build(scene, tmp_path / "killed", _poses(), SMALL, seed=7, executor="ray", workers=2)
    finally:
        (ray_local / "armed").unlink()
    # A worker process (not this one) died building the example; its retry wrote the shard.
    dead_pid = int((ray_local / "crashed").read_text())
    assert dead_pid != os.getpid()
    _assert_same_bytes(single, tmp_path / "killed")
