"""Hostile scene files (issue 32, items 6 and 7): every reader bounds what it reads and inflates
by the count the file declares, refuses counts above `max_gaussians`, reads only regular files,
keeps a scene's references inside its own folder; the daemon reads a scene in a child process
under `[daemon.paths] scene_memory_mb` and `[daemon.paths] max_gaussians`.

Each hostile file is built here, small on disk. Where a test measures memory it is the peak
that `tracemalloc` sees (Python objects and numpy arrays) while the file is read: a bounded
reader stays at a few MiB where the old one inflated or allocated what the file asked for.
Tests whose file would have made the old readers read forever (/dev/zero) or allocate many
gigabytes pass `max_gaussians` explicitly, so the old code fails them at once (no such
argument) instead of taking the machine down.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import struct
import threading
import tracemalloc
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from nhfd.benchmarks.hostile import gzip_of, zstd_zeros
from nhfd.config import Config
from nhfd.daemon.jobs import JobRunner
from nhfd.daemon.methods import METHODS
from nhfd.daemon.protocol import Params
from nhfd.daemon.scene_check import read_scene_counts
from nhfd.scene.gaussians import SceneFileError
from nhfd.scene.io import (
    MAX_GAUSSIANS,
    load_scene,
    read_scene,
    save_compressed_ply,
    save_splat,
)
from nhfd.worker_messages import SceneLoaded

from .test_formats import FIXTURES, make_glb, one_gaussian_body, one_splat_glb, split_glb

SOG_TINY = FIXTURES / "tiny-sh.sog.d"
# What a bounded read of these small hostile files may allocate at its peak; each old reader
# allocated at least 16 MiB (most 64 MiB) on the file that tests it.
PEAK_BOUND_BYTES = 8 << 20
BOMB_BYTES = 64 << 20  # what each bomb inflates to


@contextlib.contextmanager
def peak_bytes() -> Iterator[list[int]]:
    """The peak of traced allocations inside the block, in [0] when it ends."""
    box = [0]
    tracemalloc.start()
    try:
        yield box
    finally:
        box[0] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()


def refused(path: Path, match: str, **kwargs: int) -> int:
    """Read `path`, expect a SceneFileError matching `match`; the read's peak bytes."""
    with peak_bytes() as peak, pytest.raises(SceneFileError, match=match):
        read_scene(path, **kwargs)
    return peak[0]


def spz_v4(n: int, streams: list[bytes], unpacked: list[int]) -> bytes:
    """A .spz v4 of SH degree 0 declaring n Gaussians, with these streams and table sizes."""
    head = struct.pack("<4sIIBBBBI12x", b"NGSP", 4, n, 0, 12, 0, len(streams), 32)
    toc = b"".join(struct.pack("<QQ", len(s), u) for s, u in zip(streams, unpacked, strict=True))
    return head + toc + b"".join(streams)


# --- .spz -----------------------------------------------------------------------------------


def test_spz_gzip_bomb_is_cut_off_after_what_its_count_needs(tmp_path: Path) -> None:
    # One Gaussian's 45 bytes, then 64 MiB of zeros: 65 KB on disk.
    head = struct.pack("<4sIIBBBB", b"NGSP", 3, 1, 1, 12, 0, 0) + one_gaussian_body()
    (tmp_path / "bomb.spz").write_bytes(gzip_of(head, BOMB_BYTES))
    assert (tmp_path / "bomb.spz").stat().st_size < 100_000
    peak = refused(tmp_path / "bomb.spz", r"bomb\.spz: the \.spz gzip stream inflates to more "
                   r"than the 45 bytes its 1 Gaussians need plus 65,536")
    assert peak < PEAK_BOUND_BYTES, peak
    # The same Gaussian without the zeros still loads (RUB (1, 2, 3) in OpenCV axes): the cut is
    # after the data, not in it.
    (tmp_path / "one.spz").write_bytes(gzip_of(head, 0))
    np.testing.assert_allclose(load_scene(tmp_path / "one.spz").means, [[1.0, -2.0, -3.0]])


def test_spz_declaring_2_to_the_28_points_is_refused_before_inflating(tmp_path: Path) -> None:
    n = 1 << 28
    gz = gzip_of(struct.pack("<4sIIBBBB", b"NGSP", 3, n, 0, 12, 0, 0), 1 << 20)
    (tmp_path / "many.v3.spz").write_bytes(gz)
    limit = rf"declares 268,435,456 Gaussians, more than the limit of {MAX_GAUSSIANS:,}"
    assert refused(tmp_path / "many.v3.spz", rf"many\.v3\.spz: the \.spz header {limit}") \
        < PEAK_BOUND_BYTES
    # zstd: each stream's frame is 1 MiB of zeros; the table states the sizes 2^28 points need.
    sizes = [9 * n, n, 3 * n, 3 * n, 4 * n]
    (tmp_path / "many.v4.spz").write_bytes(spz_v4(n, [zstd_zeros(1 << 20)] * 5, sizes))
    assert (tmp_path / "many.v4.spz").stat().st_size < 1000
    assert refused(tmp_path / "many.v4.spz", rf"many\.v4\.spz: the \.spz header {limit}") \
        < PEAK_BOUND_BYTES


def test_spz_zstd_frame_inflating_past_its_stream_is_cut_off(tmp_path: Path) -> None:
    # One Gaussian: stream 0 (positions) should hold 9 bytes; its frame says, and holds, 64 MiB.
    streams = [zstd_zeros(BOMB_BYTES)] + [zstd_zeros(k) for k in (1, 3, 3, 4)]
    (tmp_path / "frame.spz").write_bytes(spz_v4(1, streams, [9, 1, 3, 3, 4]))
    peak = refused(tmp_path / "frame.spz",
                   r"frame\.spz: \.spz stream 0 unpacks to more than 10 bytes, not 9")
    assert peak < PEAK_BOUND_BYTES, peak


# --- PLY and .splat ---------------------------------------------------------------------------

INRIA = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
         "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


def ply_header(fmt: str, rows: int) -> bytes:
    props = "".join(f"property float {name}\n" for name in INRIA)
    return f"ply\nformat {fmt} 1.0\nelement vertex {rows}\n{props}end_header\n".encode()


def test_ascii_ply_declaring_4e9_vertices_is_refused_before_allocating(tmp_path: Path) -> None:
    path = tmp_path / "huge.ply"
    path.write_bytes(ply_header("ascii", 4_000_000_000) + b" ".join([b"0"] * 14) + b"\n")
    refused(path, r"huge\.ply: PLY element 'vertex' declares 4,000,000,000 Gaussians, more than "
            rf"the limit of {MAX_GAUSSIANS:,} Gaussians")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_shorter_than_its_declared_rows_is_refused_before_allocating(
        tmp_path: Path, fmt: str) -> None:
    # A million rows declared (under the limit), two written: plyfile would first allocate an
    # array for the million (56 MB).
    row = b"0 0 0 0 0 0 0 0 0 0 0 0 0 1\n" if fmt == "ascii" else struct.pack("<14f", *[0] * 14)
    path = tmp_path / f"{fmt}.ply"
    path.write_bytes(ply_header(fmt, 1_000_000) + row * 2)
    # ASCII: at least a character and a separator a value; binary: 14 floats of 4 bytes a row.
    need = 2 * 14 * 1_000_000 - 1 if fmt == "ascii" else 56 * 1_000_000
    peak = refused(path, rf"{fmt}\.ply: truncated data, the file is shorter than its header "
                   rf"declares: its 1,000,000 vertex rows need at least {need:,} bytes after the "
                   rf"header, the file has {len(row) * 2} bytes$")
    assert peak < PEAK_BOUND_BYTES, peak


# --- a maximum number of Gaussians, in every format -------------------------------------------


def _tiny_as(tmp_path: Path, name: str) -> Path:
    g = load_scene(FIXTURES / "tiny-sh.ply")
    path = tmp_path / name
    (save_splat if name.endswith(".splat") else save_compressed_ply)(path, g)
    return path


@pytest.mark.parametrize(("name", "count"), [
    ("tiny-sh.ply", 64), ("tiny-sh.compressed.ply", 64), ("tiny-sh.splat", 64),
    ("tiny-sh.v2.spz", 64), ("tiny-sh.v3.spz", 64), ("tiny-sh.v4.spz", 64),
    ("tiny-sh.glb", 64), ("tiny-sh.sog.d", 64), ("donut-crop.sog", 2108),
])
def test_a_file_declaring_more_than_max_gaussians_is_refused(
        tmp_path: Path, name: str, count: int) -> None:
    path = FIXTURES / name if (FIXTURES / name).exists() else _tiny_as(tmp_path, name)
    with pytest.raises(SceneFileError, match=rf"declares {count:,} Gaussians, more than the limit "
                                             rf"of {count - 1:,} Gaussians \(max_gaussians"):
        read_scene(path, max_gaussians=count - 1)
    assert len(read_scene(path, max_gaussians=count).gaussians) == count


@pytest.mark.parametrize("bad", [0, -1, 1_000_000_001, 2.5, True, "10"])
def test_max_gaussians_itself_is_checked(bad: object) -> None:
    with pytest.raises(ValueError, match=rf"max_gaussians = {bad!r}; allowed: an integer in "
                                         r"\[1, 1,000,000,000\]"):
        read_scene(FIXTURES / "tiny-sh.ply", max_gaussians=bad)  # type: ignore[arg-type]


# --- glTF -------------------------------------------------------------------------------------


def test_glb_accessors_are_checked_against_their_views_and_buffers(tmp_path: Path) -> None:
    doc, blob = split_glb(one_splat_glb())

    def variant(name: str, change) -> Path:
        d = json.loads(json.dumps(doc))
        change(d)
        (tmp_path / name).write_bytes(make_glb(d, blob))
        return tmp_path / name

    def stride_0(d: dict, count: int) -> None:
        d["bufferViews"][0]["byteStride"] = 0
        for acc in d["accessors"]:
            acc["count"] = count

    # byteStride 0 repeats one element `count` times: 1,000 here would load as 1,000 copies.
    path = variant("stride0.glb", lambda d: stride_0(d, 1000))
    peak = refused(path, r"stride0\.glb: POSITION: bufferView 0 byteStride is 0; allowed: 12 "
                   r"\(its element's size\) to 252")
    assert peak < PEAK_BOUND_BYTES
    # With 2^28 the old reader allocated 2^28 x 12 bytes, then 8 per value (9.6 GB).
    path = variant("huge.glb", lambda d: stride_0(d, 1 << 28))
    refused(path, r"huge\.glb: POSITION \(accessor 0\) count declares 268,435,456 Gaussians, "
            rf"more than the limit of {MAX_GAUSSIANS:,}", max_gaussians=MAX_GAUSSIANS)
    # A negative offset, and a negative index (Python's "last"), are not glTF's.
    path = variant("negative.glb", lambda d: d["accessors"][0].update(byteOffset=-4))
    refused(path, r"negative\.glb: POSITION \(accessor 0, bufferView 0\): byteOffset is -4; "
            r"allowed: an integer >= 0")
    path = variant("last.glb", lambda d: d["accessors"][0].update(bufferView=-1))
    refused(path, r"last\.glb: POSITION: bufferViews\[-1\] does not exist")
    # A view past its buffer's declared byteLength (the BIN chunk is longer than it says).
    path = variant("past.glb", lambda d: d["buffers"][0].update(byteLength=8))
    refused(path, r"past\.glb: truncated data: POSITION runs past its buffer")


def gltf_with_buffer(folder: Path, uri: str) -> Path:
    """tiny-sh.glb as a .gltf in `folder` whose buffer 0 is `uri`; the buffer's bytes are
    what the caller puts there."""
    doc, _ = split_glb((FIXTURES / "tiny-sh.glb").read_bytes())
    doc["buffers"][0]["uri"] = uri
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.gltf").write_text(json.dumps(doc))
    return folder / "scene.gltf"


def tiny_bin() -> bytes:
    return split_glb((FIXTURES / "tiny-sh.glb").read_bytes())[1]


def test_gltf_buffer_references_stay_inside_the_scenes_folder(tmp_path: Path) -> None:
    outside = tmp_path / "outside" / "x.bin"
    outside.parent.mkdir()
    outside.write_bytes(tiny_bin())  # a valid buffer: the old reader loaded it as the scene
    scene = tmp_path / "scenes"
    for uri, ref in (("../outside/x.bin", "../outside/x.bin"), (str(outside), str(outside)),
                     ("..%2Foutside%2Fx.bin", "../outside/x.bin")):
        refused(gltf_with_buffer(scene, uri),
                rf"scene\.gltf: glTF buffer 0 uri {re.escape(repr(ref))} resolves to "
                rf"{re.escape(str(outside.resolve()))}, outside the scene's folder "
                rf"{re.escape(str(scene.resolve()))}; only files inside it are read")
    (scene / "link.bin").symlink_to(outside)
    refused(gltf_with_buffer(scene, "link.bin"),
            rf"glTF buffer 0 uri 'link\.bin' resolves to {re.escape(str(outside.resolve()))}, "
            "outside the scene's folder")
    # Inside the folder, a subfolder included, the same bytes load.
    (scene / "sub").mkdir()
    (scene / "sub" / "x.bin").write_bytes(tiny_bin())
    g = load_scene(gltf_with_buffer(scene, "sub/x.bin"))
    np.testing.assert_array_equal(g.means, load_scene(FIXTURES / "tiny-sh.glb").means)


def test_gltf_buffer_naming_dev_zero_is_refused(tmp_path: Path) -> None:
    # The old reader read /dev/zero until memory ran out: max_gaussians makes it fail at once.
    refused(gltf_with_buffer(tmp_path, "/dev/zero"),
            r"glTF buffer 0 uri '/dev/zero' resolves to /dev/zero, outside the scene's folder",
            max_gaussians=MAX_GAUSSIANS)
    (tmp_path / "zero.bin").symlink_to("/dev/zero")
    refused(gltf_with_buffer(tmp_path, "zero.bin"), r"'zero\.bin' resolves to /dev/zero, "
            "outside", max_gaussians=MAX_GAUSSIANS)


@contextlib.contextmanager
def fifo_with_a_writer(path: Path) -> Iterator[None]:
    """A FIFO at `path` with a writer that gives every reader that opens it junk and closes:
    a reader that opens it (as the old readers did) fails on the junk instead of waiting for a
    writer forever. On leaving, the writer is let go (a reader that never came is stood in for)."""
    os.mkfifo(path)
    stop = threading.Event()

    def write() -> None:
        while True:
            fd = os.open(path, os.O_WRONLY)  # waits for a reader
            try:
                if stop.is_set():
                    return
                with contextlib.suppress(OSError):
                    os.write(fd, b"junk, not scene data\n")
            finally:
                os.close(fd)

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    try:
        yield
    finally:
        stop.set()
        while writer.is_alive():  # each non-blocking reader lets one waiting open() through
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
            writer.join(0.05)
            os.close(fd)


def test_only_regular_files_are_read(tmp_path: Path) -> None:
    with fifo_with_a_writer(tmp_path / "fifo.bin"):
        refused(gltf_with_buffer(tmp_path, "fifo.bin"),
                rf"scene\.gltf: glTF buffer 0 uri 'fifo\.bin' \({re.escape(str(tmp_path))}/fifo"
                r"\.bin\) is a FIFO, not a regular file; only regular files are read")
    with fifo_with_a_writer(tmp_path / "fifo.ply"):
        refused(tmp_path / "fifo.ply", r"fifo\.ply: the scene file is a FIFO, not a regular file")
    (tmp_path / "adir.bin").mkdir()
    refused(gltf_with_buffer(tmp_path, "adir.bin"), r"'adir\.bin' \(.*adir\.bin\) is a "
            "directory, not a regular file")
    folder = tmp_path / "sog"
    shutil.copytree(SOG_TINY, folder)
    (folder / "quats.webp").unlink()
    (folder / "quats.webp").mkdir()
    refused(folder, r"sog: SOG member quats\.webp \(.*\) is a directory, not a regular file")
    # A scene file that is a device: read as a .splat it would never end.
    (tmp_path / "zero.splat").symlink_to("/dev/zero")
    refused(tmp_path / "zero.splat", r"zero\.splat: the scene file is a character device, not a "
            "regular file", max_gaussians=MAX_GAUSSIANS)


# --- SOG --------------------------------------------------------------------------------------


def sog_zip(path: Path, replace: dict[str, bytes | int]) -> Path:
    """tiny-sh.sog.d as a zip bundle, with members replaced: bytes, or that many zero bytes
    (deflated, written piece by piece)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for member in sorted(SOG_TINY.iterdir()):
            new = replace.get(member.name, member.read_bytes())
            if isinstance(new, bytes):
                z.writestr(member.name, new)
                continue
            with z.open(member.name, "w", force_zip64=True) as f:
                for _ in range(new >> 20):
                    f.write(bytes(1 << 20))
    return path


def test_sog_zip_bomb_member_is_refused_by_its_declared_size(tmp_path: Path) -> None:
    path = sog_zip(tmp_path / "bomb.sog", {"means_l.webp": BOMB_BYTES})
    assert path.stat().st_size < 200_000
    # 64 Gaussians: images of at most 64 + 8 x 8 + 4096 pixels, 5 bytes a pixel, and a margin.
    cap = 5 * (64 + 64 + 4096) + 65536
    peak = refused(path, rf"bomb\.sog: SOG member means_l\.webp declares {BOMB_BYTES:,} bytes, "
                   rf"more than the {cap:,} bytes allowed")
    assert peak < PEAK_BOUND_BYTES, peak


def webp_of(width: int, height: int) -> bytes:
    """A lossless WebP of one colour: a few bytes on disk for any size."""
    out = io.BytesIO()
    Image.new("RGBA", (width, height), (1, 2, 3, 255)).save(out, "WEBP", lossless=True, method=0)
    return out.getvalue()


def test_sog_image_larger_than_its_count_needs_is_refused_before_decoding(tmp_path: Path) -> None:
    folder = tmp_path / "big"
    shutil.copytree(SOG_TINY, folder)
    (folder / "means_l.webp").write_bytes(webp_of(2048, 2048))  # 16 MiB decoded, 40 B on disk
    peak = refused(folder, r"big: SOG image means_l\.webp is 2048x2048 pixels, more than the "
                   r"4,224 its Gaussians can need")
    assert peak < PEAK_BOUND_BYTES, peak


def test_sog_image_names_stay_inside_the_scenes_folder(tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    shutil.copytree(SOG_TINY, outside)  # valid images: the old reader loaded them
    folder = tmp_path / "scene"
    shutil.copytree(SOG_TINY, folder)
    (folder / "quats.webp").unlink()  # only the one outside remains
    meta = json.loads((SOG_TINY / "meta.json").read_text())
    for name in ("../outside/quats.webp", str(outside / "quats.webp")):
        meta["quats"]["files"][0] = name
        (folder / "meta.json").write_text(json.dumps(meta))
        refused(folder / "meta.json", rf"SOG file name {re.escape(repr(name))} resolves to "
                rf"{re.escape(str(outside.resolve()))}/quats\.webp, outside the scene's folder "
                rf"{re.escape(str(folder.resolve()))}")
    # /dev/zero: the old reader read it until memory ran out.
    meta["quats"]["files"][0] = "/dev/zero"
    (folder / "meta.json").write_text(json.dumps(meta))
    refused(folder, r"SOG file name '/dev/zero' resolves to /dev/zero, outside",
            max_gaussians=MAX_GAUSSIANS)


# --- the daemon: a child process under a memory budget ----------------------------------------


def zero_spz(tmp_path: Path, n: int) -> Path:
    """n Gaussians of zero bytes, SH degree 0, as a gzip .spz: 20 bytes each inflated, a few
    KB on disk; all at the origin, so it is no plausible scene either."""
    head = struct.pack("<4sIIBBBB", b"NGSP", 3, n, 0, 12, 0, 0)
    (tmp_path / "zeros.spz").write_bytes(gzip_of(head, 20 * n))
    return tmp_path / "zeros.spz"


def test_the_daemons_scene_read_is_bounded_by_its_memory_budget(tmp_path: Path) -> None:
    path = zero_spz(tmp_path, 1_000_000)  # 20 MB of data, over 100 MB while decoding
    with pytest.raises(SceneFileError, match=rf"{path}: reading the scene needs more than "
                                             r"daemon\.paths\.scene_memory_mb = 64 MiB"):
        read_scene_counts(path, MAX_GAUSSIANS, 64)
    # The same read with room to decode gets as far as the file's content.
    with pytest.raises(SceneFileError, match=rf"{path}: not a plausible scene"):
        read_scene_counts(path, MAX_GAUSSIANS, 1024)
    with pytest.raises(SceneFileError, match=r"declares 1,000,000 Gaussians, more than the limit "
                                             r"of 999,999"):
        read_scene_counts(path, 999_999, 1024)
    assert read_scene_counts(FIXTURES / "tiny-sh.v4.spz", MAX_GAUSSIANS, 64) == {
        "gaussians": 64, "declared": 64, "dropped": 0, "dropped_reason": ""}


class _Frames:
    """The frame worker as load_scene sees it: records what it was asked to load."""

    def __init__(self) -> None:
        self.loaded: list[str] = []

    def load_scene(self, path: str) -> SceneLoaded:
        self.loaded.append(path)
        return SceneLoaded(path, 64, 64, 0, "", (0.0, 0.0, 0.0), "+z")


class _Host:
    def __init__(self, root: Path, **daemon: int) -> None:
        self.config = Config.model_validate({"daemon": daemon})
        self.base_dir, self.scene_dirs = root, [root.resolve()]
        self.load_jobs = JobRunner("load")
        self.frames, self.scene = _Frames(), None


def test_the_daemons_load_scene_applies_max_gaussians_and_scene_memory_mb(tmp_path: Path) -> None:
    shutil.copy(FIXTURES / "tiny-sh.v4.spz", tmp_path / "tiny.spz")
    zero_spz(tmp_path, 1_000_000)

    def load(host: _Host, name: str) -> object:
        reply = METHODS["load_scene"].func(host, None, Params({"path": name}))
        job = host.load_jobs.get(reply["job"])
        assert job is not None and job.done.wait(60)
        return job

    for limit in (63, 64):
        host = _Host(tmp_path, paths={"max_gaussians": limit})
        try:
            job = load(host, "tiny.spz")
        finally:
            host.load_jobs.close()
        if limit == 63:
            assert job.state == "failed"
            assert "declares 64 Gaussians, more than the limit of 63 Gaussians" in job.error
            assert host.frames.loaded == [] and host.scene is None  # the worker never asked
        else:
            assert job.state == "done", job.error
            assert host.frames.loaded == [str(tmp_path / "tiny.spz")]
            assert host.scene["gaussians"] == 64
    host = _Host(tmp_path, paths={"scene_memory_mb": 64})
    try:
        job = load(host, "zeros.spz")
        assert job.state == "failed"
        assert job.error.startswith(f"SceneFileError: {tmp_path / 'zeros.spz'}: reading the "
                                    "scene needs more than daemon.paths.scene_memory_mb = 64 MiB")
        assert host.frames.loaded == [] and host.scene is None
    finally:
        host.load_jobs.close()
