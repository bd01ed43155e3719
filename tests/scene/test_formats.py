"""Scene formats users have: Niantic .spz (v2-v4), PlayCanvas SOG, glTF KHR_gaussian_splatting.

The fixtures in tests/data/formats were made from the shared scenes by independent converters
(see its README); each must render the view its source .ply renders, its declared axes must land
where the format says, and a bad file must get a `SceneFileError` naming the file and the fault.
"""

from __future__ import annotations

import base64
import functools
import gzip
import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import Gaussians, SceneFileError, make_gaussians
from nhfd.scene.io import load_scene
from nhfd.scene.raster import render
from nhfd.scene.spz import save_spz
from nhfd.scene.suggest import detect_up_axis, format_hint, suggest_camera

FIXTURES = Path(__file__).resolve().parents[1] / "data" / "formats"
MIN_PSNR_DB = 40.0
# (source .ply, an up axis for the test camera): donut is a z-up Blender scene, tiny-sh (SH
# degree 3) a COLMAP one.
SOURCES = {"donut-crop": "+z", "tiny-sh": "-y"}
COVERED_ALPHA = 0.01  # a pixel counts as covered above this render alpha


@functools.cache
def source_view(name: str) -> tuple[Camera, np.ndarray, np.ndarray]:
    """A small framing camera for the source .ply, its render [3, H, W] in [0, 1] and where
    that render is covered [H, W]."""
    g = load_scene(FIXTURES / f"{name}.ply")
    cam = suggest_camera(g, 96, 72, SOURCES[name])
    out = render(g, cam)
    return cam, np.clip(out.rgb, 0.0, 1.0), out.alpha > COVERED_ALPHA


def psnr_db(g: Gaussians, name: str) -> float:
    """PSNR of g's render against the source's, over the pixels either covers: the empty
    background (85-90% of these views) would otherwise add about 9 dB for nothing."""
    cam, ref, covered = source_view(name)
    out = render(g, cam)
    img = np.clip(out.rgb, 0.0, 1.0).astype(np.float64)
    mask = covered | (out.alpha > COVERED_ALPHA)
    return float(10.0 * np.log10(1.0 / np.mean(((img - ref) ** 2)[:, mask])))


def quat_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """1 - |<a, b>|: zero when a and b are the same rotation (q and -q included)."""
    return 1.0 - np.abs((a.astype(np.float64) * b).sum(1))


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    return make_gaussians(
        means=rng.normal(0.0, 2.0, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        scales=np.exp(rng.uniform(-9.0, 0.0, (n, 3))),
        opacities=rng.uniform(0.0, 1.0, n),
        sh=rng.uniform(-0.9, 0.9, (n, (degree + 1) ** 2, 3)),
    )


# --- Niantic .spz ---------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["v2", "v3", "v4", "gsply.v4"])
@pytest.mark.parametrize("name", sorted(SOURCES))
def test_spz_fixture_renders_like_its_source(name: str, kind: str) -> None:
    g = load_scene(FIXTURES / f"{name}.{kind}.spz")
    src = load_scene(FIXTURES / f"{name}.ply")
    assert len(g) == len(src) and g.sh_degree == src.sh_degree
    assert psnr_db(g, name) >= MIN_PSNR_DB


@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_fixture_values_are_the_source_in_opencv_axes(version: int) -> None:
    # The reference packer converted RDF -> RUB; reading converts back, so each value is the
    # source's within the format's steps: 2^-12 positions, 1/128 SH in buckets of 16 (degree 2-3)
    # and, for v3/v4, 9-bit quaternion components (v2 stores x y z in 8 bits).
    g = load_scene(FIXTURES / f"tiny-sh.v{version}.spz")
    src = load_scene(FIXTURES / "tiny-sh.ply")
    np.testing.assert_allclose(g.means, src.means, atol=0.5 / 4096 + 1e-6)
    assert quat_distance(g.quats, src.quats).max() < (1e-4 if version == 2 else 2e-6)
    np.testing.assert_allclose(g.sh[:, 1:], src.sh[:, 1:], atol=8 / 128 + 1e-6)
    np.testing.assert_allclose(g.opacities, src.opacities, atol=0.5 / 255 + 1e-6)


def test_spz_from_a_second_writer_is_the_source_in_opencv_axes() -> None:
    # gsply's v4 container (its own zstd streams) of the scene splat-transform turned 180
    # degrees about x (RDF -> RUB, SH rotated by splat-transform): the same covariances
    # (quaternions may differ by a sign-flip of the local axes) and SH to gsply's 1/128 steps.
    g = load_scene(FIXTURES / "tiny-sh.gsply.v4.spz")
    src = load_scene(FIXTURES / "tiny-sh.ply")
    np.testing.assert_allclose(g.means, src.means, atol=0.5 / 4096 + 1e-6)
    np.testing.assert_allclose(g.sh[:, 1:], src.sh[:, 1:], atol=0.5 / 128 + 1e-6)
    # Log-scales in 1/16 steps: a variance is off by up to exp(2 * 0.5 / 16) - 1 = 6.5%, plus
    # 9-bit rotation components (well under 1% of the largest variance).
    err = np.abs(covariances(g) - covariances(src)).max(axis=(1, 2))
    assert (err <= (math.expm1(1 / 16) + 0.01) * src.scales.astype(np.float64).max(1) ** 2).all()


def legacy_spz(version: int, body: bytes, n: int = 1, degree: int = 1, frac: int = 12) -> bytes:
    return gzip.compress(struct.pack("<4sIIBBBB", b"NGSP", version, n, degree, frac, 0, 0) + body)


def one_gaussian_body() -> bytes:
    """One RUB Gaussian at (1, 2, 3), rotated 90 degrees about +z, SH degree 1 with only the
    y basis of red set (byte 192 -> +0.5), built byte by byte from the README's layout."""
    pos = b"".join(struct.pack("<i", v * 4096)[:3] for v in (1, 2, 3))
    alpha, colour, scale = bytes([255]), bytes([128, 128, 128]), bytes([160, 160, 160])
    # Smallest three: largest = w (index 3); x, y, z follow, the first in the highest bits.
    # z = sqrt(1/2) is magnitude 511, sign 0; x = y = 0.
    rot = struct.pack("<I", (3 << 30) | (0 << 20) | (0 << 10) | 511)
    sh = bytes([192, 128, 128] + [128] * 6)  # coefficient-major, colour inner
    return pos + alpha + colour + scale + rot + sh


def test_spz_rub_axes_land_in_opencv_axes(tmp_path: Path) -> None:
    (tmp_path / "one.spz").write_bytes(legacy_spz(3, one_gaussian_body()))
    g = load_scene(tmp_path / "one.spz")
    # RUB (x right, y up, z back) -> OpenCV (x right, y down, z forward): y and z negated.
    np.testing.assert_allclose(g.means[0], [1.0, -2.0, -3.0], atol=1e-6)
    # A turn about the z axis stays a turn about z, but the flipped axis reverses its sense.
    s = math.sqrt(0.5)
    assert quat_distance(g.quats, np.array([[s, 0.0, 0.0, -s]]))[0] < 1e-6
    # The degree-1 y basis is odd in y: its coefficient changes sign; scale (160/16 - 10 = 0).
    np.testing.assert_allclose(g.sh[0, 1], [-0.5, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(g.scales[0], [1.0, 1.0, 1.0], rtol=1e-6)
    assert g.opacities[0] == 1.0


@pytest.mark.parametrize("version", [3, 4])
@pytest.mark.parametrize("degree", [0, 3])
def test_spz_write_read_round_trip(tmp_path: Path, version: int, degree: int) -> None:
    g = random_gaussians(700, degree)
    save_spz(tmp_path / "g.spz", g, version=version)
    h = load_scene(tmp_path / "g.spz")
    assert len(h) == len(g) and h.sh_degree == degree
    np.testing.assert_allclose(h.means, g.means, atol=0.5 / 4096 + 1e-6)
    np.testing.assert_allclose(np.log(h.scales), np.log(g.scales), atol=0.5 / 16 + 1e-5)
    np.testing.assert_allclose(h.opacities, g.opacities, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(h.sh[:, 0], g.sh[:, 0], atol=0.5 / (255 * 0.15) + 1e-5)
    assert quat_distance(h.quats, g.quats).max() < 5e-6
    if degree:
        # Buckets of 8 and 16 steps of 1/128: half a bucket each way.
        np.testing.assert_allclose(h.sh[:, 1:4], g.sh[:, 1:4], atol=4.5 / 128 + 1e-6)
        np.testing.assert_allclose(h.sh[:, 4:], g.sh[:, 4:], atol=8.5 / 128 + 1e-6)


@pytest.mark.parametrize("name", sorted(SOURCES))
def test_spz_writer_reproduces_the_reference_packer_bytes(tmp_path: Path, name: str) -> None:
    # The v3 fixture came from nianticlabs/spz's packer (RDF source declared); ours must quantise,
    # convert axes and lay out every byte the same way.
    save_spz(tmp_path / "ours.spz", load_scene(FIXTURES / f"{name}.ply"), version=3)
    ours = gzip.decompress((tmp_path / "ours.spz").read_bytes())
    assert ours == gzip.decompress((FIXTURES / f"{name}.v3.spz").read_bytes())


def test_spz_writer_stores_rub_axes(tmp_path: Path) -> None:
    g = make_gaussians([[1.0, 2.0, 3.0]], [[1.0, 0, 0, 0]], [[1.0, 1, 1]], [1.0],
                       np.zeros((1, 1, 3)))
    save_spz(tmp_path / "g.spz", g, version=3)
    raw = gzip.decompress((tmp_path / "g.spz").read_bytes())
    fixed = [int.from_bytes(raw[16 + 3 * i : 19 + 3 * i], "little", signed=True) for i in range(3)]
    assert fixed == [4096, -2 * 4096, -3 * 4096]


def test_spz_bad_files_name_file_and_problem(tmp_path: Path) -> None:
    good = legacy_spz(3, one_gaussian_body())

    def fails(name: str, data: bytes, match: str) -> None:
        (tmp_path / name).write_bytes(data)
        with pytest.raises(SceneFileError, match=match):
            load_scene(tmp_path / name)

    fails("cut.spz", good[: len(good) - 9], r"cut\.spz: truncated \.spz data \(gzip stream ends")
    fails("short.spz", legacy_spz(3, one_gaussian_body()[:-3]),
          r"short\.spz: truncated \.spz data: 1 Gaussians need 45 bytes, the stream holds 42")
    fails("magic.spz", gzip.compress(b"NGSX" + bytes(40)),
          r"magic\.spz: not an \.spz file \(magic b'NGSX', expected b'NGSP'\)")
    fails("v9.spz", legacy_spz(9, one_gaussian_body()),
          r"v9\.spz: unsupported \.spz version 9 in a gzip stream \(supported: 2, 3")
    fails("v5.spz", struct.pack("<4sIIBBBBI12x", b"NGSP", 5, 1, 0, 12, 0, 5, 32),
          r"v5\.spz: unsupported \.spz version 5 with an uncompressed NGSP header")
    fails("sh4.spz", legacy_spz(3, bytes(200), degree=4),
          r"sh4\.spz: \.spz SH degree 4 is not supported \(0-3\)")
    v4 = (FIXTURES / "donut-crop.v4.spz").read_bytes()
    fails("cut4.spz", v4[:-100], r"cut4\.spz: truncated \.spz data \(stream 4 is cut off\)")
    fails("head4.spz", v4[:20], r"head4\.spz: truncated \.spz header \(20 of 32 bytes\)")


# --- glTF KHR_gaussian_splatting -----------------------------------------------------------


def covariances(g: Gaussians) -> np.ndarray:
    """[N, 3, 3] R diag(s^2) R^T: what a renderer sees (a quaternion is one of several names)."""
    w, x, y, z = g.quats.astype(np.float64).T
    r = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)  # fmt: skip
    return r @ (g.scales.astype(np.float64)[:, :, None] ** 2 * r.transpose(0, 2, 1))


def split_glb(data: bytes) -> tuple[dict, bytes]:
    """The JSON document and BIN chunk of a .glb (12-byte header, then length/type chunks)."""
    n_json = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + n_json])
    n_bin = struct.unpack_from("<I", data, 20 + n_json)[0]
    return doc, data[28 + n_json : 28 + n_json + n_bin]


def make_glb(doc: dict, blob: bytes, version: int = 2) -> bytes:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    blob += bytes(-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<4sII", b"glTF", version, total) + struct.pack("<II", len(js), 0x4E4F534A)
            + js + struct.pack("<II", len(blob), 0x004E4942) + blob)


@pytest.mark.parametrize("name", sorted(SOURCES))
def test_glb_fixture_renders_like_its_source(name: str) -> None:
    g = load_scene(FIXTURES / f"{name}.glb")
    src = load_scene(FIXTURES / f"{name}.ply")
    assert len(g) == len(src) and g.sh_degree == src.sh_degree
    # float32 throughout: positions and SH (signs flipped twice) come back bit for bit.
    np.testing.assert_array_equal(g.means, src.means)
    np.testing.assert_array_equal(g.sh, src.sh)
    # float32 quaternions and scales: each covariance within 1e-5 of its largest variance.
    err = np.abs(covariances(g) - covariances(src)).max(axis=(1, 2))
    assert (err <= 1e-5 * src.scales.astype(np.float64).max(1) ** 2).all()
    assert psnr_db(g, name) >= MIN_PSNR_DB


@pytest.mark.parametrize("variant", ["external", "data-uri"])
def test_gltf_json_with_separate_buffer_reads_like_the_glb(tmp_path: Path, variant: str) -> None:
    doc, blob = split_glb((FIXTURES / "tiny-sh.glb").read_bytes())
    if variant == "external":
        (tmp_path / "my buffer.bin").write_bytes(blob)
        doc["buffers"][0]["uri"] = "my%20buffer.bin"
    else:
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(
            blob
        ).decode()
    (tmp_path / "scene.gltf").write_text(json.dumps(doc))
    g, h = load_scene(tmp_path / "scene.gltf"), load_scene(FIXTURES / "tiny-sh.glb")
    np.testing.assert_array_equal(g.means, h.means)
    np.testing.assert_array_equal(g.sh, h.sh)


def one_splat_glb(scale: float = 0.5) -> bytes:
    """One Gaussian at glTF (1, 2, 3), turned 90 degrees about +z, red y-basis SH = +0.5."""
    s = math.sqrt(0.5)
    columns = {
        "POSITION": ("VEC3", [1.0, 2.0, 3.0]),
        "KHR_gaussian_splatting:ROTATION": ("VEC4", [0.0, 0.0, s, s]),  # x y z w
        "KHR_gaussian_splatting:SCALE": ("VEC3", [scale, 0.25, 0.125]),
        "KHR_gaussian_splatting:OPACITY": ("SCALAR", [0.75]),
        "KHR_gaussian_splatting:SH_DEGREE_0_COEF_0": ("VEC3", [0.0, 0.0, 0.0]),
        "KHR_gaussian_splatting:SH_DEGREE_1_COEF_0": ("VEC3", [0.5, 0.0, 0.0]),
        "KHR_gaussian_splatting:SH_DEGREE_1_COEF_1": ("VEC3", [0.0, 0.0, 0.0]),
        "KHR_gaussian_splatting:SH_DEGREE_1_COEF_2": ("VEC3", [0.0, 0.0, 0.0]),
    }
    blob, views, accessors = b"", [], []
    for kind, values in columns.values():
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": 4 * len(values)})
        accessors.append({"bufferView": len(views) - 1, "componentType": 5126, "count": 1,
                          "type": kind})
        blob += struct.pack(f"<{len(values)}f", *values)
    doc = {
        "asset": {"version": "2.0"}, "extensionsUsed": ["KHR_gaussian_splatting"],
        "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors,
        "meshes": [{"primitives": [{
            "attributes": {name: i for i, name in enumerate(columns)}, "mode": 0,
            "extensions": {"KHR_gaussian_splatting": {"kernel": "ellipse"}},
        }]}],
        "nodes": [{"mesh": 0}],
    }  # fmt: skip
    return make_glb(doc, blob)


def test_gltf_y_up_axes_land_in_opencv_axes(tmp_path: Path) -> None:
    (tmp_path / "one.glb").write_bytes(one_splat_glb())
    g = load_scene(tmp_path / "one.glb")
    # glTF: +y up, +z forward, -x right (LUF) -> OpenCV RDF: x and y negated, z kept.
    np.testing.assert_allclose(g.means[0], [-1.0, -2.0, 3.0])
    # A turn about z stays a turn about z (F R F with F = diag(-1, -1, 1)): x' = -y', y' = x'.
    s = math.sqrt(0.5)
    assert quat_distance(g.quats, np.array([[s, 0.0, 0.0, s]]))[0] < 1e-7
    np.testing.assert_allclose(g.scales[0], [0.5, 0.25, 0.125])  # linear, as stored
    np.testing.assert_allclose(g.sh[0, 1], [-0.5, 0.0, 0.0])  # odd in y
    assert g.opacities[0] == 0.75


def test_gltf_bad_files_name_file_and_problem(tmp_path: Path) -> None:
    def fails(name: str, data: bytes, match: str) -> None:
        (tmp_path / name).write_bytes(data)
        with pytest.raises(SceneFileError, match=match):
            load_scene(tmp_path / name)

    good = one_splat_glb()
    fails("cut.glb", good[:-10],
          rf"cut\.glb: truncated \.glb data: the header declares {len(good)} bytes")
    fails("magic.glb", b"gLTF" + good[4:], r"magic\.glb: not a \.glb file")
    fails("v1.glb", good[:4] + struct.pack("<I", 1) + good[8:],
          r"v1\.glb: unsupported \.glb version 1 \(supported: 2\)")
    fails("bad.gltf", b'{"asset": {"version": "2.0"}, ',
          r"bad\.gltf: unreadable glTF JSON \(Expecting property name")
    fails("old.gltf", b'{"asset": {"version": "1.0"}}',
          r"old\.gltf: not a glTF 2\.0 document")
    fails("odd.gltf", b'{"asset": {"version": "2.0"}, "meshes": ["x"]}',
          r"odd\.gltf: malformed glTF \(AttributeError")
    fails("log.glb", one_splat_glb(scale=-2.0),
          r"log\.glb: KHR_gaussian_splatting:SCALE holds negative values")
    doc, blob = split_glb(good)
    doc["meshes"][0]["primitives"][0]["attributes"].pop("KHR_gaussian_splatting:OPACITY")
    fails("noop.glb", make_glb(doc, blob),
          r"noop\.glb: splat primitive lacks the required attribute KHR_gaussian_splatting:OPACITY")
    doc, blob = split_glb(good)
    doc["nodes"][0]["translation"] = [1.0, 0.0, 0.0]
    fails("moved.glb", make_glb(doc, blob), r"moved\.glb: a node transforms its splat mesh")
    doc, blob = split_glb(good)
    doc["bufferViews"][0]["byteLength"] = 4
    fails("short.glb", make_glb(doc, blob),
          r"short\.glb: truncated data: POSITION runs past its buffer")


# --- PlayCanvas SOG ---------------------------------------------------------------------------

SOG_TINY = FIXTURES / "tiny-sh.sog.d"


def nearest_source(g: Gaussians, src: Gaussians) -> np.ndarray:
    """For each Gaussian of g, the index of the source Gaussian with the nearest mean (the SOG
    writer reorders Gaussians along a Morton curve)."""
    d = np.linalg.norm(g.means[:, None, :].astype(np.float64) - src.means[None], axis=2)
    return d.argmin(1)


@pytest.mark.parametrize(
    ("name", "member"),
    [("donut-crop", "donut-crop.sog"), ("tiny-sh", "tiny-sh.sog.d"),
     ("tiny-sh", "tiny-sh.sog.d/meta.json")],
)
def test_sog_fixture_renders_like_its_source(name: str, member: str) -> None:
    g = load_scene(FIXTURES / member)
    src = load_scene(FIXTURES / f"{name}.ply")
    assert len(g) == len(src) and g.sh_degree == src.sh_degree
    assert psnr_db(g, name) >= MIN_PSNR_DB


def test_sog_values_are_the_source_in_its_own_axes() -> None:
    # SOG declares no axes and splat-transform keeps the .ply's: every Gaussian must sit on its
    # source (16-bit log-space positions) with no axis negated, one to one.
    g, src = load_scene(SOG_TINY), load_scene(FIXTURES / "tiny-sh.ply")
    j = nearest_source(g, src)
    assert sorted(j) == list(range(len(src)))
    np.testing.assert_allclose(g.means, src.means[j], atol=1e-5)
    assert quat_distance(g.quats, src.quats[j]).max() < 1e-4  # 8-bit smallest three
    # Opacity bytes: these sources sit on k/255 exactly, and a float32 logit round trip lands a
    # hair either side, which the writer's byte conversion may take one step down.
    np.testing.assert_allclose(g.opacities, src.opacities[j], atol=1 / 255 + 1e-6)
    # 64 Gaussians, a 64-entry palette: each SH vector is its own centroid, to codebook steps.
    np.testing.assert_allclose(g.sh[:, 1:], src.sh[j, 1:], atol=0.02)


def test_sog_bad_files_name_file_and_problem(tmp_path: Path) -> None:
    import shutil

    meta = json.loads((SOG_TINY / "meta.json").read_text())

    def bundle(name: str, doc: dict | str, drop: str = "", garble: str = "") -> Path:
        folder = tmp_path / name
        shutil.copytree(SOG_TINY, folder)
        (folder / "meta.json").write_text(doc if isinstance(doc, str) else json.dumps(doc))
        if drop:
            (folder / drop).unlink()
        if garble:
            (folder / garble).write_bytes(b"RIFF" + bytes(30))
        return folder

    def fails(path: Path, match: str) -> None:
        with pytest.raises(SceneFileError, match=match):
            load_scene(path)

    fails(bundle("json", '{"version": 2, "count": '), r"json: unreadable SOG meta\.json")
    fails(bundle("v1", {k: v for k, v in meta.items() if k != "version"}),
          r"v1: unsupported SOG version None \(supported: 2; .*deprecated version 1\)")
    fails(bundle("v3", meta | {"version": 3}), r"v3: unsupported SOG version 3")
    fails(bundle("nomeans", {k: v for k, v in meta.items() if k != "means"}),
          r"nomeans: malformed SOG meta\.json \(KeyError: 'means'\)")
    fails(bundle("noimg", meta, drop="quats.webp"), r"noimg: SOG bundle has no quats\.webp")
    fails(bundle("badimg", meta, garble="sh0.webp"), r"badimg: unreadable SOG image sh0\.webp")
    fails(bundle("many", meta | {"count": 100}), r"many: SOG image means_l\.webp has 64 pixels "
          r"for 100 Gaussians")
    book = meta | {"scales": meta["scales"] | {"codebook": [0.0] * 10}}
    fails(bundle("book", book), r"book: SOG scales\.codebook has 10 entries, expected 256")
    data = (FIXTURES / "donut-crop.sog").read_bytes()
    (tmp_path / "cut.sog").write_bytes(data[: len(data) // 2])
    fails(tmp_path / "cut.sog", r"cut\.sog: unreadable SOG zip bundle")


# --- declared up axis -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("member", "up"),
    [("tiny-sh.v2.spz", "-y"), ("tiny-sh.v4.spz", "-y"), ("tiny-sh.glb", "-y"),
     ("tiny-sh.sog.d", None), ("donut-crop.sog", None), ("tiny-sh.ply", None)],
)
def test_declared_up_axis_comes_from_the_format(member: str, up: str | None) -> None:
    path = FIXTURES / member
    found, reason = detect_up_axis(load_scene(path), format_hint(path))
    if up is None:  # no declared axes: the shape (or a convention) decides
        assert not reason.startswith("declared by the format")
    else:
        assert (found, reason.startswith("declared by the format")) == (up, True)
