"""Scene files: the shared real scenes, round trips through every writer, the compressed .ply bit
layout on a hand-built file, and the errors bad files get."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import plyfile
import pytest

from nhfd.scene.gaussians import SH_C0, Gaussians, SceneFileError, make_gaussians
from nhfd.scene.io import (
    load_scene,
    save_compressed_ply,
    save_ply,
    save_splat,
    scene_summary,
)

SQRT_HALF = math.sqrt(0.5)

# (file, Gaussians, SH degree): counts from ../shared/data/README.md; tiny-sh has 45 f_rest bytes.
SHARED = [
    ("donut.ply", 45_624, 0),
    ("guitar.compressed.ply", 90_854, 0),
    ("tiny-sh.compressed.ply", 64, 3),
]


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    """Random Gaussians with colours in [0, 1] and f_rest inside the compressed range [-4, 4]."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    sh = rng.normal(0.0, 0.5, (n, k, 3))
    sh[:, 0] = (rng.uniform(0.0, 1.0, (n, 3)) - 0.5) / SH_C0
    return make_gaussians(
        means=rng.normal(0.0, 2.0, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        scales=np.exp(rng.uniform(-6.0, 0.0, (n, 3))),
        opacities=rng.uniform(0.01, 0.99, n),
        sh=np.clip(sh, -3.9, 3.9) if degree else sh,
    )


def write_ply(path: Path, **elements: np.ndarray) -> Path:
    plyfile.PlyData(
        [plyfile.PlyElement.describe(arr, name) for name, arr in elements.items()], byte_order="<"
    ).write(str(path))
    return path


def struct(fields: dict[str, list[float] | list[int]], kind: str) -> np.ndarray:
    """A structured array with one column per entry of `fields`, all of dtype `kind`."""
    n = len(next(iter(fields.values())))
    arr = np.empty(n, dtype=[(name, kind) for name in fields])
    for name, values in fields.items():
        arr[name] = values
    return arr


def quat_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """1 - |<a, b>|: zero when a and b are the same rotation (q and -q included)."""
    return 1.0 - np.abs((a.astype(np.float64) * b).sum(1))


# --- the shared real scenes ------------------------------------------------------------------


@pytest.mark.parametrize(("name", "count", "degree"), SHARED)
def test_shared_scene_loads_with_known_count_and_plausible_values(
    shared_scenes: Path, name: str, count: int, degree: int
) -> None:
    g = load_scene(shared_scenes / name)
    assert len(g) == count
    assert g.sh_degree == degree
    np.testing.assert_allclose(np.linalg.norm(g.quats, axis=1), 1.0, atol=1e-5)
    assert g.opacities.min() >= 0.0 and g.opacities.max() <= 1.0
    extent = scene_summary(g)["extent"]
    assert g.scales.min() > 0.0
    # No splat is bigger than the scene; the median one is a small fraction of it (tiny-sh is 64
    # splats cut from a larger scene, hence the loose bound).
    assert g.scales.max() < extent
    assert np.median(g.scales.max(1)) < 0.2 * extent
    colour = g.base_colors()
    assert 0.0 <= np.median(colour) <= 1.0
    assert ((colour > -0.25) & (colour < 1.25)).mean() > 0.97


def test_compressed_opacity_byte_is_activated_opacity(shared_scenes: Path) -> None:
    # A trained scene has many nearly transparent and many nearly opaque splats. Were the alpha
    # byte a logit mapped to [0, 1], sigmoid would squeeze every opacity into [0.5, 0.73].
    op = load_scene(shared_scenes / "guitar.compressed.ply").opacities
    assert (op < 0.05).mean() > 0.1
    assert (op > 0.9).mean() > 0.1


@pytest.mark.parametrize("name", ["guitar.compressed.ply", "tiny-sh.compressed.ply"])
def test_compressed_scene_converted_to_float_ply_is_unchanged(
    shared_scenes: Path, tmp_path: Path, name: str
) -> None:
    a = load_scene(shared_scenes / name)
    save_ply(tmp_path / "float.ply", a)
    b = load_scene(tmp_path / "float.ply")
    assert len(b) == len(a) and b.sh_degree == a.sh_degree
    np.testing.assert_array_equal(b.means, a.means)
    np.testing.assert_array_equal(b.sh, a.sh)
    # Reloading renormalises the quaternion in float32 once more: a unit or so in the last place.
    np.testing.assert_allclose(b.quats, a.quats, rtol=0, atol=2.5e-7)
    # float32 rounding of the stored log-scale (|log s| up to ~20 here) and of the logit.
    np.testing.assert_allclose(b.scales, a.scales, rtol=3e-6)
    np.testing.assert_allclose(b.opacities, a.opacities, atol=1e-6)


def test_compressed_scene_recompresses_to_the_same_values(
    shared_scenes: Path, tmp_path: Path
) -> None:
    # guitar's chunk bounds are tight, and our writer quantises as SuperSplat 2.7 did, so
    # re-encoding the decoded scene is lossless. (tiny-sh's bounds are wider than its splats, so
    # only its SH bytes survive exactly: see the next test.)
    a = load_scene(shared_scenes / "guitar.compressed.ply")
    save_compressed_ply(tmp_path / "again.ply", a)
    b = load_scene(tmp_path / "again.ply")
    np.testing.assert_array_equal(b.means, a.means)
    np.testing.assert_array_equal(b.opacities, a.opacities)
    np.testing.assert_array_equal(b.sh[:, 1:], a.sh[:, 1:])
    np.testing.assert_allclose(b.sh[:, 0], a.sh[:, 0], atol=1e-5)  # colour lerp in float32
    np.testing.assert_allclose(b.scales, a.scales, rtol=1e-5)
    assert quat_distance(b.quats, a.quats).max() < 1e-6


def test_compressed_sh_bytes_survive_recompression(shared_scenes: Path, tmp_path: Path) -> None:
    # Bucket-centre decoding, then the writer's trunc((f / 8 + 0.5) * 256), gives the byte back.
    a = load_scene(shared_scenes / "tiny-sh.compressed.ply")
    save_compressed_ply(tmp_path / "again.ply", a)
    np.testing.assert_array_equal(load_scene(tmp_path / "again.ply").sh[:, 1:], a.sh[:, 1:])


# --- round trips ------------------------------------------------------------------------------


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_float_ply_round_trip_is_exact(tmp_path: Path, degree: int) -> None:
    g = random_gaussians(300, degree)
    save_ply(tmp_path / "g.ply", g)
    h = load_scene(tmp_path / "g.ply")
    assert h.sh_degree == degree
    np.testing.assert_array_equal(h.means, g.means)
    np.testing.assert_array_equal(h.sh, g.sh)
    np.testing.assert_allclose(h.quats, g.quats, atol=1e-6)
    np.testing.assert_allclose(h.scales, g.scales, rtol=1e-6)
    np.testing.assert_allclose(h.opacities, g.opacities, atol=1e-6)


def test_float_ply_with_normals_loads_the_same(tmp_path: Path) -> None:
    g = random_gaussians(20, 1)
    save_ply(tmp_path / "plain.ply", g)
    plain = plyfile.PlyData.read(str(tmp_path / "plain.ply"))["vertex"].data
    # The original INRIA writer puts nx ny nz after x y z.
    names = list(plain.dtype.names)
    with_normals = np.zeros(len(plain), dtype=[(n, "<f4") for n in [*names[:3], "nx", "ny", "nz",
                                                                     *names[3:]]])
    for n in names:
        with_normals[n] = plain[n]
    h = load_scene(write_ply(tmp_path / "normals.ply", vertex=with_normals))
    np.testing.assert_array_equal(h.sh, load_scene(tmp_path / "plain.ply").sh)
    np.testing.assert_array_equal(h.means, g.means)


def test_splat_round_trip_within_its_quantisation(tmp_path: Path) -> None:
    g = random_gaussians(500, 2)
    save_splat(tmp_path / "g.splat", g)
    h = load_scene(tmp_path / "g.splat")
    assert h.sh_degree == 0  # .splat keeps only the base colour
    np.testing.assert_array_equal(h.means, g.means)  # float32 fields are exact
    np.testing.assert_array_equal(h.scales, g.scales)
    # Colour and opacity are bytes: rounding error <= 0.5/255.
    np.testing.assert_allclose(h.base_colors(), g.base_colors(), atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(h.opacities, g.opacities, atol=0.5 / 255 + 1e-6)
    # Quaternion components are rounded to 1/128 (error <= 1/256 each, then renormalised).
    np.testing.assert_allclose(h.quats, g.quats, atol=1 / 128)


def test_compressed_ply_round_trip_within_its_quantisation(tmp_path: Path) -> None:
    g = random_gaussians(600, 3)  # three chunks, the last one partial
    save_compressed_ply(tmp_path / "g.compressed.ply", g)
    h = load_scene(tmp_path / "g.compressed.ply")
    assert len(h) == len(g) and h.sh_degree == 3
    which = np.arange(len(g)) // 256
    for c in range(3):
        sel = which == c
        span = np.ptp(g.means[sel], axis=0)
        bits = np.array([2047, 1023, 2047])  # 11-10-11
        err = np.abs(h.means[sel] - g.means[sel])
        assert (err <= 0.5 * span / bits + 1e-5).all()
        log_span = np.ptp(np.log(g.scales[sel]), axis=0)
        log_err = np.abs(np.log(h.scales[sel]) - np.log(g.scales[sel]))
        assert (log_err <= 0.5 * log_span / bits + 1e-5).all()
        colour_span = np.ptp(g.base_colors()[sel], axis=0)
        colour_err = np.abs(h.base_colors()[sel] - g.base_colors()[sel])
        assert (colour_err <= 0.5 * colour_span / 255 + 1e-5).all()
    np.testing.assert_allclose(h.opacities, g.opacities, atol=0.5 / 255 + 1e-6)
    # 10 bits over [-1/sqrt2, 1/sqrt2]: about 7e-4 per component.
    assert quat_distance(h.quats, g.quats).max() < 2e-6
    # f_rest bytes: 1/32-wide buckets decoded at their centre.
    np.testing.assert_allclose(h.sh[:, 1:], g.sh[:, 1:], atol=1 / 64 + 1e-6)


# --- the compressed .ply bit layout, on a file built by hand -----------------------------------

CHUNK = {
    "min_x": [-1.0], "min_y": [-2.0], "min_z": [-3.0],
    "max_x": [1.0], "max_y": [2.0], "max_z": [3.0],
    "min_scale_x": [-5.0], "min_scale_y": [-4.0], "min_scale_z": [-3.0],
    "max_scale_x": [-1.0], "max_scale_y": [0.0], "max_scale_z": [1.0],
    "min_r": [0.2], "min_g": [0.1], "min_b": [0.0],
    "max_r": [0.8], "max_g": [0.9], "max_b": [1.0],
}  # fmt: skip

VERTEX = {
    # 11-10-11 bits, x on top: all ones = max corner, zero = min corner, x alone = 2047 << 21.
    "packed_position": [0xFFFFFFFF, 0, 2047 << 21],
    # Scales: min corner, max corner, y alone (10 bits at 11).
    "packed_scale": [0, 0xFFFFFFFF, 1023 << 11],
    # r g b a bytes, r on top.
    "packed_color": [0xFF00FF80, 0x000000FF, 0x00FF0033],
    # 2-bit largest index (of w x y z) on top, then the other three, 10 bits each, 512 ~ 0:
    #   w largest, (x, y, z) = (0, 0, 1/sqrt2)  -> 90 degrees about z;
    #   z largest, (w, x, y) = (1/sqrt2, 0, 0)  -> the same rotation, stored the other way;
    #   x largest, (w, y, z) = (0, 0, 0)        -> 180 degrees about x.
    "packed_rotation": [(0 << 30) | (512 << 20) | (512 << 10) | 1023,
                        (3 << 30) | (1023 << 20) | (512 << 10) | 512,
                        (1 << 30) | (512 << 20) | (512 << 10) | 512],
}  # fmt: skip


def test_hand_built_compressed_ply_decodes_to_expected_values(tmp_path: Path) -> None:
    # 9 f_rest bytes (degree 1), channel-major: f_rest_0..2 are red's three bases,
    # f_rest_3..5 green's. 0 -> -4, 255 -> +4, 128 -> bucket centre (128.5 / 256 - 0.5) * 8.
    sh_bytes = {f"f_rest_{i}": [128] * 3 for i in range(9)}
    sh_bytes["f_rest_0"] = [0] * 3
    sh_bytes["f_rest_1"] = [255] * 3
    sh_bytes["f_rest_3"] = [0] * 3
    path = write_ply(
        tmp_path / "hand.compressed.ply",
        chunk=struct(CHUNK, "<f4"),
        vertex=struct(VERTEX, "<u4"),
        sh=struct(sh_bytes, "u1"),
    )
    g = load_scene(path)
    assert len(g) == 3 and g.sh_degree == 1

    np.testing.assert_allclose(g.means, [[1, 2, 3], [-1, -2, -3], [1, -2, -3]], atol=1e-6)
    np.testing.assert_allclose(
        np.log(g.scales), [[-5, -4, -3], [-1, 0, 1], [-5, 0, -3]], atol=1e-6
    )
    np.testing.assert_allclose(
        g.base_colors(), [[0.8, 0.1, 1.0], [0.2, 0.1, 0.0], [0.2, 0.9, 0.0]], atol=1e-6
    )
    np.testing.assert_allclose(g.opacities, [128 / 255, 1.0, 0x33 / 255], atol=1e-7)

    # About 7e-4 off exact: 512/1023 is not exactly one half.
    np.testing.assert_allclose(g.quats[0], [SQRT_HALF, 0, 0, SQRT_HALF], atol=2e-3)
    np.testing.assert_allclose(g.quats[1], [SQRT_HALF, 0, 0, SQRT_HALF], atol=2e-3)
    np.testing.assert_allclose(g.quats[2], [0, 1, 0, 0], atol=2e-3)

    centre = (128.5 / 256 - 0.5) * 8
    np.testing.assert_allclose(g.sh[:, 1:, 0], [[-4.0, 4.0, centre]] * 3, atol=1e-6)
    np.testing.assert_allclose(g.sh[:, 1:, 1], [[-4.0, centre, centre]] * 3, atol=1e-6)


def test_compressed_ply_without_chunk_colours_uses_plain_bytes(tmp_path: Path) -> None:
    chunk = {k: v for k, v in CHUNK.items() if not k.endswith(("_r", "_g", "_b"))}
    path = write_ply(tmp_path / "old.ply", chunk=struct(chunk, "<f4"), vertex=struct(VERTEX, "<u4"))
    g = load_scene(path)
    assert g.sh_degree == 0
    np.testing.assert_allclose(
        g.base_colors(), [[1.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]], atol=1e-6
    )


# --- bad files -----------------------------------------------------------------------------------


def test_truncated_ply_names_file_and_problem(tmp_path: Path) -> None:
    save_ply(tmp_path / "g.ply", random_gaussians(100, 0))
    data = (tmp_path / "g.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) - 100])
    with pytest.raises(SceneFileError, match=r"cut\.ply: truncated data"):
        load_scene(tmp_path / "cut.ply")


def test_missing_properties_are_named(tmp_path: Path) -> None:
    g = random_gaussians(10, 0)
    save_ply(tmp_path / "g.ply", g)
    full = plyfile.PlyData.read(str(tmp_path / "g.ply"))["vertex"].data
    keep = [n for n in full.dtype.names if n not in ("opacity", "rot_3")]
    partial = np.empty(len(full), dtype=[(n, "<f4") for n in keep])
    for n in keep:
        partial[n] = full[n]
    with pytest.raises(
        SceneFileError, match=r"partial\.ply: .*missing required properties: opacity, rot_3"
    ):
        load_scene(write_ply(tmp_path / "partial.ply", vertex=partial))


def test_wrong_f_rest_count_is_an_error(tmp_path: Path) -> None:
    g = random_gaussians(5, 1)
    save_ply(tmp_path / "g.ply", g)
    full = plyfile.PlyData.read(str(tmp_path / "g.ply"))["vertex"].data
    keep = [n for n in full.dtype.names if n != "f_rest_8"]
    partial = np.empty(len(full), dtype=[(n, "<f4") for n in keep])
    for n in keep:
        partial[n] = full[n]
    with pytest.raises(SceneFileError, match=r"sh8\.ply: .*has 8 f_rest_\* properties"):
        load_scene(write_ply(tmp_path / "sh8.ply", vertex=partial))


def test_wrong_chunk_count_is_an_error(tmp_path: Path) -> None:
    two_chunks = {k: v * 2 for k, v in CHUNK.items()}
    path = write_ply(
        tmp_path / "chunks.ply", chunk=struct(two_chunks, "<f4"), vertex=struct(VERTEX, "<u4")
    )
    with pytest.raises(
        SceneFileError,
        match=r"chunks\.ply: wrong element counts: 'chunk' has 2 rows but 3 vertices need "
        r"ceil\(3/256\) = 1",
    ):
        load_scene(path)


def test_splat_size_not_multiple_of_32_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "bad.splat").write_bytes(bytes(65))
    with pytest.raises(SceneFileError, match=r"bad\.splat: .*65 bytes is not a multiple of 32"):
        load_scene(tmp_path / "bad.splat")


def test_unknown_format_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "scene.bin").write_bytes(b"\x00" * 64)
    with pytest.raises(SceneFileError, match=r"scene\.bin: unknown scene format"):
        load_scene(tmp_path / "scene.bin")
    (tmp_path / "fake.ply").write_bytes(b"solid cube\n")
    with pytest.raises(SceneFileError, match=r"fake\.ply: not a PLY file"):
        load_scene(tmp_path / "fake.ply")


def nan_scene(n: int, bad: np.ndarray) -> Gaussians:
    """`n` random Gaussians with NaN positions at `bad` (built directly: make_gaussians would drop
    them)."""
    g = random_gaussians(n, 0)
    means = g.means.copy()
    means[bad] = np.nan
    return Gaussians(means, g.quats, g.scales, g.opacities, g.sh)


@pytest.mark.parametrize("suffix", [".ply", ".splat"])
def test_all_nan_file_is_an_error(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"nan{suffix}"
    (save_ply if suffix == ".ply" else save_splat)(path, nan_scene(8, np.arange(8)))
    with pytest.raises(SceneFileError, match=r"nan\.(ply|splat): no usable Gaussians, all 8"):
        load_scene(path)


def test_some_nan_gaussians_are_dropped_with_the_count(tmp_path: Path) -> None:
    save_ply(tmp_path / "some.ply", nan_scene(10, np.array([1, 4, 7])))
    with pytest.warns(UserWarning, match=r"some\.ply: dropped 3 of 10 Gaussians") as record:
        g = load_scene(tmp_path / "some.ply")
    assert record[0].filename == __file__  # reported at the caller's line
    assert len(g) == 7
    assert np.isfinite(g.means).all()


# --- summary -------------------------------------------------------------------------------------


def test_scene_summary_of_a_known_scene() -> None:
    n = 101
    means = np.zeros((n, 3))
    means[:, 0] = np.arange(n)  # x = 0..100, so percentiles are exact: 1 and 99
    g = make_gaussians(
        means, np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), 0.5), np.full(n, 0.25),
        np.zeros((n, 4, 3)),
    )
    s = scene_summary(g)
    assert s["count"] == n and s["sh_degree"] == 1
    assert s["bounds_min"] == [0.0, 0.0, 0.0] and s["bounds_max"] == [100.0, 0.0, 0.0]
    assert s["robust_min"] == pytest.approx([1.0, 0, 0])
    assert s["robust_max"] == pytest.approx([99.0, 0, 0])
    assert s["centre"] == pytest.approx([50.0, 0, 0])
    assert s["extent"] == pytest.approx(98.0)
    assert s["mean_opacity"] == pytest.approx(0.25)
    assert s["median_scale"] == pytest.approx(0.5)


def test_scene_summary_of_an_empty_scene() -> None:
    s = scene_summary(Gaussians.empty(2))
    assert s["count"] == 0 and s["sh_degree"] == 2 and s["centre"] is None


@pytest.mark.parametrize("save", [save_ply, save_compressed_ply])
def test_file_with_no_gaussians_is_an_empty_scene(tmp_path: Path, save) -> None:
    save(tmp_path / "empty.ply", Gaussians.empty(1))
    g = load_scene(tmp_path / "empty.ply")
    assert len(g) == 0 and g.sh_degree == 1


# --- plausibility: one check for the daemon and `nhfd scene info` ------------------------------


def random_data_ply(path: Path, n: int = 20_000, seed: int = 0) -> Path:
    """A valid INRIA .ply header over random float32 data (random bit patterns)."""
    from nhfd.scene.io import INRIA_REQUIRED

    rng = np.random.default_rng(seed)
    dtype = np.dtype([(name, "<f4") for name in INRIA_REQUIRED])
    return write_ply(path, vertex=np.frombuffer(rng.bytes(n * dtype.itemsize), dtype).copy())


def test_random_data_with_a_valid_header_is_not_a_scene(tmp_path: Path) -> None:
    path = random_data_ply(tmp_path / "random.ply")
    with pytest.raises(SceneFileError) as info:
        load_scene(path)
    message = str(info.value)
    assert message.startswith(f"{path}: not a plausible scene: ")
    dropped = int(message.split(": ")[2].split(" of ")[0])
    assert 0.5 * 20_000 < dropped < 20_000 and "of 20000 Gaussians" in message


def _finite_scene(n: int, means: np.ndarray, scale: float) -> Gaussians:
    rng = np.random.default_rng(1)
    return make_gaussians(means=means, quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                          scales=np.full((n, 3), scale), opacities=np.full(n, 0.5),
                          sh=rng.uniform(-1, 1, (n, 1, 3)))


def test_finite_gaussians_far_out_or_larger_than_the_scene_are_refused(tmp_path: Path) -> None:
    from nhfd.scene.io import MAX_COORDINATE

    rng = np.random.default_rng(2)
    far = _finite_scene(100, rng.uniform(-1e36, 1e36, (100, 3)), 0.01)
    save_ply(tmp_path / "far.ply", far)  # nothing dropped: every value is a finite float32
    with pytest.raises(SceneFileError, match=r"far\.ply: not a plausible scene: its robust bounds "
                                             r".* reach 9\.\d+e\+35 scene units, beyond \+-1e\+06"):
        load_scene(tmp_path / "far.ply")
    edge = _finite_scene(100, rng.uniform(-0.5, 0.5, (100, 3)) * MAX_COORDINATE, 1.0)
    save_ply(tmp_path / "edge.ply", edge)  # within the bound: a kilometre-sized scene in mm
    assert len(load_scene(tmp_path / "edge.ply")) == 100
    blobs = _finite_scene(100, rng.uniform(-0.5, 0.5, (100, 3)), 2.0)
    save_ply(tmp_path / "blobs.ply", blobs)
    with pytest.raises(SceneFileError, match=r"blobs\.ply: not a plausible scene: the median "
                                             r"Gaussian's largest scale 2 is more than 0\.5 x the "
                                             r"robust extent 1\.6"):
        load_scene(tmp_path / "blobs.ply")


def test_read_scene_counts_what_it_dropped(tmp_path: Path, shared_scenes: Path) -> None:
    from nhfd.scene.io import read_scene

    save_ply(tmp_path / "some.ply", nan_scene(10, np.array([1, 4, 7])))
    load = read_scene(tmp_path / "some.ply")
    assert (len(load.gaussians), load.declared, load.dropped) == (7, 10, 3)
    assert load.counts()["dropped_reason"].startswith(f"{tmp_path / 'some.ply'}: dropped 3 of 10")
    # half dropped is still a scene with bad splats; more is not
    save_ply(tmp_path / "half.ply", nan_scene(10, np.arange(5)))
    assert read_scene(tmp_path / "half.ply").dropped == 5
    save_ply(tmp_path / "most.ply", nan_scene(10, np.arange(6)))
    with pytest.raises(SceneFileError, match=r"most\.ply: not a plausible scene: 6 of 10 "
                                             r"Gaussians \(60%\)"):
        read_scene(tmp_path / "most.ply")
    donut = read_scene(shared_scenes / "donut.ply")  # a real scene: all of it, nothing dropped
    assert (len(donut.gaussians), donut.declared, donut.dropped) == (45_624, 45_624, 0)
