"""Niantic .spz scenes, versions 2 to 4: read them, and write versions 3 and 4.

Layout (nianticlabs/spz README.md and src/cc/load-spz.cc; the v4 container as written by the
reference packer in @adobe/spz 0.2.3 and read by playcanvas/splat-transform
src/lib/readers/read-spz.ts):

* v2, v3: one gzip stream holding a 16-byte header `<I magic 'NGSP' (0x5053474e), I version,
  I count, B sh_degree, B fractional_bits, B flags, B reserved>` then the attribute blocks.
* v4: an uncompressed 32-byte header (the same first 15 bytes, then `B stream_count,
  I toc_offset`, 12 reserved bytes), extension records `<I type, I length, payload>` in
  [32, toc_offset) (nianticlabs/spz extensions/README.md), a table of `<Q compressed,
  Q uncompressed>` per stream, then one zstd stream per attribute block.

Attribute blocks, in this order, N Gaussians:
  positions  [N, 3] signed 24-bit little-endian fixed point, `fractional_bits` fraction bits
  alphas     [N]    opacity * 255 (activated opacity, not a logit)
  colours    [N, 3] f_dc * 0.15 * 255 + 127.5 (the DC coefficient, scaled by 0.15, not SH_C0)
  scales     [N, 3] (log(scale) + 10) * 16
  rotations  v2: [N, 3] quaternion x y z as byte / 127.5 - 1, w = +sqrt(1 - |xyz|^2);
             v3, v4: [N] uint32 "smallest three": top 2 bits = index of the largest of x y z w,
             then the other three in x y z w order, the first in the highest bits, each a sign
             bit above a 9-bit magnitude of |q| / sqrt(1/2)
  sh         [N, K-1, 3] bytes (sh * 128 + 128), coefficient-major with the colour inner

Axes: "SPZ stores data internally in an RUB coordinate system" (README), converted here to the
project's RDF frame; the Adobe coordinate-system extension (type 0xADBE0003, payload one uint32
in the order of spz::CoordinateSystem) overrides that when a v4 file carries it. Note that
splat-transform and gsply write .spz without converting axes (their files of RDF scenes read
back turned 180 degrees about x); the reference packer converts when told the source frame.
The antialiasing flag (0x1) is not kept: `Gaussians` has no field for it.
"""

from __future__ import annotations

import gzip
import itertools
import math
import os
import struct
import zlib
from pathlib import Path
from typing import BinaryIO

import numpy as np

from nhfd.scene.axes import RUB, flip_axes, signs_from_letters
from nhfd.scene.gaussians import Gaussians, SceneFileError
from nhfd.scene.limits import (
    MARGIN_BYTES,
    MAX_GAUSSIANS,
    GzipStream,
    check_count,
    check_max_gaussians,
    open_regular,
    read_zstd,
)

__all__ = ["SPZ_MAGIC", "read_spz", "save_spz"]

SPZ_MAGIC = b"NGSP"  # 0x5053474e little-endian
_LEGACY = struct.Struct("<4sIIBBBB")  # 16 bytes
_V4 = struct.Struct("<4sIIBBBBI12x")  # 32 bytes
_TOC_ENTRY = struct.Struct("<QQ")
_COLOUR_SCALE = 0.15  # load-spz.cc colorScale
_SQRT_HALF = math.sqrt(0.5)
_EXT_COORDINATES = 0xADBE0003
# spz::CoordinateSystem, in order (splat-types.h; @adobe/spz spz.d.ts).
_SYSTEMS = ("UNSPECIFIED", "LDB", "RDB", "LUB", "RUB", "LDF", "RDF", "LUF", "RUF",
            "LFD", "RFD", "LFU", "RFU", "LBD", "RBD", "LBU", "RBU")
_MAX_DEGREE = 3  # Gaussians holds SH up to degree 3; .spz allows 4
# The reference packer rounds SH bytes to buckets of 8 (degree 1) and 16 (degree 2, 3) so the
# gzip/zstd streams compress better (PackOptions sh1Bits = 5, shRestBits = 4).
_SH_BUCKET = {1: 8, 2: 16, 3: 16}
# Room for a v4 file's extension records (the coordinate system's is 12 bytes): the file may
# be no larger than its streams need plus this and MARGIN_BYTES.
_MAX_EXTENSION_BYTES = 1 << 20


def _block_sizes(n: int, degree: int, version: int) -> list[int]:
    rest = (degree + 1) ** 2 - 1
    return [9 * n, n, 3 * n, 3 * n, (3 if version == 2 else 4) * n, 3 * rest * n]


def read_spz(path: Path, max_gaussians: int = MAX_GAUSSIANS) -> dict[str, np.ndarray]:
    """Activated arrays (means, quats wxyz, scales, opacities, sh) in the project's frame.

    Bounded by the header: a count above `max_gaussians` is refused before any data is
    inflated, and no more is read or inflated than the declared Gaussians need plus
    MARGIN_BYTES (a gzip or zstd bomb is cut off there and refused)."""
    check_max_gaussians(max_gaussians)
    with open_regular(path, path, "the scene file") as f:
        if f.read(4) == SPZ_MAGIC:
            f.seek(0)
            return _read_v4(path, f, max_gaussians)
        f.seek(0)
        return _read_gzip(path, f, max_gaussians)


def _read_gzip(path: Path, f: BinaryIO, max_gaussians: int) -> dict[str, np.ndarray]:
    stream = GzipStream(f, path)
    try:
        head = stream.take(_LEGACY.size)
        if len(head) < _LEGACY.size:
            raise SceneFileError(f"{path}: truncated .spz header ({len(head)} of 16 bytes)")
        magic, version, n, degree, frac, _flags, _ = _LEGACY.unpack_from(head)
        _check_header(path, magic, version, degree, frac, allowed=(2, 3))
        check_count(path, "the .spz header", n, max_gaussians)
        sizes = _block_sizes(n, degree, version)
        need = _LEGACY.size + sum(sizes)
        # Deflate stores data it cannot shrink with 5 bytes a 64 KiB block; gzip adds a header
        # and a trailer: more compressed input than this cannot be an honest stream.
        stream.max_input = need + need // 64 + MARGIN_BYTES
        body = stream.take(need - _LEGACY.size)
        if _LEGACY.size + len(body) < need:
            raise SceneFileError(
                f"{path}: truncated .spz data: {n} Gaussians need {need} bytes, the stream "
                f"holds {_LEGACY.size + len(body)}"
            )
        # Read on to the stream's end (its CRC is checked there), but no further than a margin.
        extra = len(stream.take(MARGIN_BYTES + 1))
    except EOFError as e:
        raise SceneFileError(f"{path}: truncated .spz data (gzip stream ends early: {e})") from e
    except zlib.error as e:
        raise SceneFileError(f"{path}: corrupt .spz gzip stream ({e})") from e
    if extra > MARGIN_BYTES:
        raise SceneFileError(
            f"{path}: the .spz gzip stream inflates to more than the {need:,} bytes its {n:,} "
            f"Gaussians need plus {MARGIN_BYTES:,} (a decompression bomb, or not an .spz file)"
        )
    offsets = np.cumsum([0, *sizes])
    view = memoryview(body)  # the blocks as views: no second copy of the data
    return _decode([view[a:b] for a, b in itertools.pairwise(offsets)], n, degree, frac, version,
                   RUB)


def _check_header(path: Path, magic: bytes, version: int, degree: int, frac: int,
                  allowed: tuple[int, ...]) -> None:
    if magic != SPZ_MAGIC:
        raise SceneFileError(f"{path}: not an .spz file (magic {magic!r}, expected b'NGSP')")
    if version not in allowed:
        where = "in a gzip stream" if allowed == (2, 3) else "with an uncompressed NGSP header"
        raise SceneFileError(
            f"{path}: unsupported .spz version {version} {where} (supported: "
            f"{', '.join(map(str, allowed))}; versions 2-4 in all)"
        )
    if degree > _MAX_DEGREE:
        raise SceneFileError(f"{path}: .spz SH degree {degree} is not supported (0-{_MAX_DEGREE})")
    if frac > 23:
        raise SceneFileError(f"{path}: .spz fractional_bits {frac} out of range (0-23)")


def _read_v4(path: Path, f: BinaryIO, max_gaussians: int) -> dict[str, np.ndarray]:
    import zstandard  # for its error type; only v4 needs zstd

    head = f.read(_V4.size)
    if len(head) < _V4.size:
        raise SceneFileError(f"{path}: truncated .spz header ({len(head)} of 32 bytes)")
    magic, version, n, degree, frac, _flags, n_streams, toc = _V4.unpack_from(head)
    _check_header(path, magic, version, degree, frac, allowed=(4,))
    check_count(path, "the .spz header", n, max_gaussians)
    sizes = _block_sizes(n, degree, version)[: 6 if degree else 5]  # no SH stream at degree 0
    if n_streams != len(sizes):
        raise SceneFileError(
            f"{path}: .spz declares {n_streams} streams; SH degree {degree} needs {len(sizes)}"
        )
    # The header, extension records, the table of streams, then streams no longer than their
    # data (zstd stores blocks it cannot shrink with 3 bytes a 128 KiB block) and a margin.
    cap = (_V4.size + _MAX_EXTENSION_BYTES + n_streams * _TOC_ENTRY.size + sum(sizes)
           + sum(sizes) // 64 + MARGIN_BYTES)
    file_bytes = os.fstat(f.fileno()).st_size
    data = head + f.read(cap + 1 - _V4.size) if file_bytes <= cap else b""
    if file_bytes > cap or len(data) > cap:
        raise SceneFileError(
            f"{path}: .spz file is {max(file_bytes, len(data)):,} bytes, more than the {cap:,} its "
            f"{n:,} Gaussians can need"
        )
    signs = _declared_frame(path, data[_V4.size : toc])
    offset = toc + n_streams * _TOC_ENTRY.size
    if toc < _V4.size or offset > len(data):
        raise SceneFileError(f"{path}: truncated .spz data (table of streams at {toc} is cut off)")
    blocks = []
    view = memoryview(data)
    for i, size in enumerate(sizes):
        packed, unpacked = _TOC_ENTRY.unpack_from(data, toc + i * _TOC_ENTRY.size)
        if unpacked != size:
            raise SceneFileError(
                f"{path}: .spz stream {i} holds {unpacked} bytes; {n} Gaussians need {size}"
            )
        if offset + packed > len(data):
            raise SceneFileError(f"{path}: truncated .spz data (stream {i} is cut off)")
        try:
            block = read_zstd(view[offset : offset + packed], size)
        except zstandard.ZstdError as e:
            raise SceneFileError(f"{path}: corrupt .spz zstd stream {i} ({e})") from e
        if len(block) != size:
            raise SceneFileError(
                f"{path}: .spz stream {i} unpacks to {'more than ' if len(block) > size else ''}"
                f"{len(block)} bytes, not {size}"
            )
        blocks.append(block)
        offset += packed
    return _decode([*blocks, b""][:6], n, degree, frac, version, signs)


def _declared_frame(path: Path, ext: bytes) -> tuple[float, float, float]:
    """Axis signs from the coordinate-system extension, or RUB (the README's frame)."""
    signs, at = RUB, 0
    while at + 8 <= len(ext):
        kind, length = struct.unpack_from("<II", ext, at)
        if kind == _EXT_COORDINATES and length == 4 and at + 12 <= len(ext):
            (code,) = struct.unpack_from("<I", ext, at + 8)
            name = _SYSTEMS[code] if code < len(_SYSTEMS) else f"code {code}"
            found = RUB if name == "UNSPECIFIED" else signs_from_letters(name)
            if found is None:
                raise SceneFileError(
                    f"{path}: .spz declares coordinate system {name}; only frames that negate "
                    f"axes (R/L, U/D, F/B in x y z order) are supported"
                )
            signs = found
        at += 8 + length
    return signs


def _decode(blocks: list[bytes] | list[memoryview], n: int, degree: int, frac: int, version: int,
            signs: tuple[float, float, float]) -> dict[str, np.ndarray]:
    pos_b, alpha_b, colour_b, scale_b, rot_b, sh_b = (np.frombuffer(b, np.uint8) for b in blocks)
    p = pos_b.reshape(n, 3, 3).astype(np.int32)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    fixed = fixed - ((fixed & 0x800000) << 1)  # sign-extend 24 bits
    k = (degree + 1) ** 2
    # float32, as make_gaussians keeps them: (byte - 128) / 128 is exact in it, and the DC,
    # computed in float64, is rounded once either way. Half the memory of float64: the SH
    # are most of a Gaussian's values.
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = (colour_b.reshape(n, 3) / 255.0 - 0.5) / _COLOUR_SCALE
    sh[:, 1:] = (sh_b.reshape(n, k - 1, 3).astype(np.float32) - 128.0) / 128.0
    arrays = dict(
        means=fixed / float(1 << frac),
        quats=_unpack_quats(rot_b, n, version),
        scales=np.exp(scale_b.reshape(n, 3) / 16.0 - 10.0),
        opacities=alpha_b / 255.0,
        sh=sh,
    )
    flip_axes(arrays, signs)
    return arrays


def _unpack_quats(b: np.ndarray, n: int, version: int) -> np.ndarray:
    """[N, 4] w x y z from the rotation block."""
    if version == 2:
        xyz = b.reshape(n, 3) / 127.5 - 1.0
        w = np.sqrt(np.maximum(0.0, 1.0 - (xyz**2).sum(1)))
        return np.concatenate([w[:, None], xyz], axis=1)
    comp = b.view("<u4").astype(np.int64)
    largest = comp >> 30
    xyzw = np.zeros((n, 4))
    for slot in (3, 2, 1, 0):  # the last stored component sits in the lowest bits
        here = largest != slot
        mag = (comp & 511) * (_SQRT_HALF / 511.0)
        xyzw[here, slot] = np.where((comp >> 9) & 1, -mag, mag)[here]
        comp = np.where(here, comp >> 10, comp)
    rows = np.arange(n)
    xyzw[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (xyzw**2).sum(1)))
    return xyzw[:, [3, 0, 1, 2]]


# --------------------------------------------------------------------------------------------
# Writing


def save_spz(path: str | Path, g: Gaussians, version: int = 4) -> None:
    """Write `g` as .spz `version` 3 (gzip) or 4 (zstd streams), in the format's RUB axes.

    Quantisation (the reference packer's): positions to 2^-12 scene units (fewer fraction bits
    only if a coordinate reaches 2048); opacity and colour (f_dc * 0.15) to 1/255; log-scale to
    1/16, clipped to [-10, 5.94]; quaternion components to 9 bits of [0, sqrt(1/2)]; SH to 1/128,
    in buckets of 8 (degree 1) or 16 (degrees 2, 3) steps, clipped to [-1, 127/128].
    """
    if version not in (3, 4):
        raise ValueError(f".spz version must be 3 or 4, got {version}")
    n, degree = len(g), g.sh_degree
    arrays = {"means": g.means.astype(np.float64), "quats": g.quats.astype(np.float64),
              "sh": g.sh.astype(np.float64)}
    flip_axes(arrays, RUB)
    frac = _fraction_bits(arrays["means"])
    fixed = np.rint(arrays["means"] * (1 << frac)).astype(np.int64)
    pos = np.stack([(fixed >> s) & 0xFF for s in (0, 8, 16)], axis=-1).astype(np.uint8)
    blocks = [
        pos.tobytes(),
        _byte(g.opacities.astype(np.float64) * 255.0),
        _byte(arrays["sh"][:, 0] * (_COLOUR_SCALE * 255.0) + 127.5),
        _byte((np.log(g.scales.astype(np.float64)) + 10.0) * 16.0),
        _pack_quats(arrays["quats"]).astype("<u4").tobytes(),
        _sh_bytes(arrays["sh"], degree),
    ]
    head = (SPZ_MAGIC, version, n, degree, frac, 0)
    if version == 3:
        raw = _LEGACY.pack(*head, 0) + b"".join(blocks)
        Path(path).write_bytes(gzip.compress(raw, mtime=0))
        return
    import zstandard

    kept = blocks[: 6 if degree else 5]  # no SH stream at degree 0
    streams = [zstandard.ZstdCompressor(level=12).compress(b) for b in kept]
    toc = b"".join(_TOC_ENTRY.pack(len(c), len(b)) for c, b in zip(streams, kept, strict=True))
    header = _V4.pack(*head, len(streams), _V4.size)
    Path(path).write_bytes(header + toc + b"".join(streams))


def _fraction_bits(means: np.ndarray) -> int:
    limit = (1 << 23) - 1
    biggest = float(np.abs(means).max()) if means.size else 0.0
    for frac in range(12, -1, -1):
        if biggest * (1 << frac) <= limit:
            return frac
    raise ValueError(f".spz positions must be below 2^23 scene units, got |x| = {biggest:g}")


def _byte(x: np.ndarray) -> bytes:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8).tobytes()


def _pack_quats(q_wxyz: np.ndarray) -> np.ndarray:
    q = q_wxyz[:, [1, 2, 3, 0]]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)
    rows = np.arange(q.shape[0])
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]  # q and -q: same rotation
    comp = largest.astype(np.int64)
    for slot in range(4):
        mag = np.rint(np.abs(q[:, slot]) / _SQRT_HALF * 511.0).astype(np.int64)
        field = ((q[:, slot] < 0).astype(np.int64) << 9) | np.minimum(mag, 511)
        comp = np.where(largest != slot, (comp << 10) | field, comp)
    return comp.astype(np.uint32)


def _sh_bytes(sh: np.ndarray, degree: int) -> bytes:
    if degree == 0:
        return b""
    q = np.rint(sh[:, 1:] * 128.0) + 128.0  # [N, K-1, 3]
    band = np.repeat(np.arange(1, degree + 1), [2 * d + 1 for d in range(1, degree + 1)])
    bucket = np.array([_SH_BUCKET[b] for b in band], np.float64)[None, :, None]
    q = np.floor((q + bucket // 2) / bucket) * bucket
    return np.clip(q, 0, 255).astype(np.uint8).tobytes()
