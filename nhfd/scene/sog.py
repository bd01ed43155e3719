"""PlayCanvas SOG scenes, version 2: `meta.json` plus lossless WebP images, as a folder or as a
zip bundle (`.sog`). Read only.

Layout (playcanvas/splat-transform src/lib/readers/read-sog.ts and writers/write-sog.ts, 3.7.0):
Gaussian i is pixel i of every image (row-major; the images may hold more pixels than
`count`), each RGBA8:

* `means.files` = [low bytes, high bytes]: per axis a 16-bit value v, lerped between
  `means.mins` and `means.maxs` and then un-log-transformed, x = sign(t) (exp(|t|) - 1).
* `quats.files[0]`: r g b are the three smaller components of the w x y z quaternion, each
  (byte / 255 * 2 - 1) / sqrt 2, in w x y z order skipping the largest; a = 252 + index of the
  largest, which is positive and recovered from the unit norm.
* `scales.files[0]`: r g b index `scales.codebook` (256 log-scales).
* `sh0.files[0]`: r g b index `sh0.codebook` (256 DC coefficients f_dc); a = opacity * 255.
* `shN` (optional): `files` = [centroids, labels]; the labels image holds a 16-bit palette
  entry per Gaussian (r + 256 g); entry e's coefficient j is texel (row e // 64, column
  (e % 64) * C + j) of the centroids image (width 64 * C, C = 3, 8 or 15 for `bands` 1-3),
  whose r g b index `shN.codebook`.

Axes: SOG declares none; splat-transform writes and reads it in the .ply's own frame (its
Transform.PLY), so the values are kept as they are, as for a PlayCanvas compressed .ply.
"""

from __future__ import annotations

import io
import json
import math
import os
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from nhfd.scene.gaussians import SceneFileError, malformed_as_scene_error
from nhfd.scene.limits import (
    MARGIN_BYTES,
    MAX_GAUSSIANS,
    check_count,
    check_max_gaussians,
    contained,
    open_regular,
    read_capped,
)

__all__ = ["ZIP_MAGIC", "read_sog"]

ZIP_MAGIC = b"PK\x03\x04"
_SH_COEFFS = {1: 3, 2: 8, 3: 15}
# For the index of the largest component (w x y z), the slots the three stored values fill.
_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
SOG_META = "meta.json"
# meta.json holds three 256-entry codebooks and a few names (about 10 KB).
_MAX_META_BYTES = 1 << 20
# A lossless WebP file of random pixels is about 4 bytes a pixel; more than 5 is not an image
# of the size its header states.
_BYTES_PER_PIXEL = 5
# A bundle's zip directory: about 8 members, under a kilobyte (a directory of millions of
# entries would cost gigabytes as zipfile's objects before any member is read).
_MAX_ZIP_DIRECTORY_BYTES = 1 << 20
_EOCD = struct.Struct("<4s4H2LH")  # end of central directory record
_ZIP64_LOCATOR = struct.Struct("<4sLQL")
_ZIP64_END = struct.Struct("<4sQ2H2L4Q")


def read_sog(path: Path, max_gaussians: int = MAX_GAUSSIANS) -> dict[str, np.ndarray]:
    """Activated arrays (means, quats wxyz, scales, opacities, sh) from a SOG folder, its
    `meta.json`, or a `.sog` zip bundle.

    Bounded: a count above `max_gaussians` is refused before any image is read; meta.json may
    hold _MAX_META_BYTES; an image may hold the pixels the count needs plus the writers'
    padding (checked from its header, before it is decoded) and its file five bytes a pixel; a
    zip member is inflated no further than that, whatever size it declares. A folder's images
    are regular files inside the folder."""
    check_max_gaussians(max_gaussians)
    files = _Files(path)
    try:
        return _read(path, files, max_gaussians)
    finally:
        files.close()


def _read(path: Path, files: _Files, max_gaussians: int) -> dict[str, np.ndarray]:
    try:
        meta = json.loads(files.read(SOG_META, _MAX_META_BYTES))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise SceneFileError(f"{path}: unreadable SOG meta.json ({e})") from e
    if not isinstance(meta, dict):
        raise SceneFileError(f"{path}: SOG meta.json is not a JSON object")
    version = meta.get("version")
    if version != 2:
        raise SceneFileError(
            f"{path}: unsupported SOG version {version!r} (supported: 2; a meta.json without "
            "'version' is the deprecated version 1)"
        )
    with malformed_as_scene_error(path, "SOG meta.json"):
        return _decode(path, files, meta, max_gaussians)


def _pixels_for(count: int) -> int:
    """The most pixels an image of `count` Gaussians may hold: the count, rows and columns of
    padding (splat-transform rounds both sides up to multiples of 4, at most 4 sqrt(count) + 16
    pixels more) and a small image's worth."""
    return count + 8 * math.isqrt(count) + 4096


def _zip_directory_bytes(f: BinaryIO) -> int | None:
    """The central directory's size from the end records (zip64 included), or None where no
    end record is found (zipfile then says what is wrong)."""
    size = os.fstat(f.fileno()).st_size
    tail_bytes = min(size, _EOCD.size + 0xFFFF)  # the record and the longest comment
    f.seek(size - tail_bytes)
    tail = f.read(tail_bytes)
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or at + _EOCD.size > len(tail):
        return None
    *_, entries, directory, _offset, _comment = _EOCD.unpack_from(tail, at)
    locator = at - _ZIP64_LOCATOR.size
    if (entries == 0xFFFF or directory == 0xFFFFFFFF) and locator >= 0:
        sig, _disk, record_at, _disks = _ZIP64_LOCATOR.unpack_from(tail, locator)
        if sig == b"PK\x06\x07" and record_at + _ZIP64_END.size <= size:
            f.seek(record_at)
            record = f.read(_ZIP64_END.size)
            if record[:4] == b"PK\x06\x06":
                directory = _ZIP64_END.unpack(record)[-2]
    return directory


class _Files:
    """The bundle's members by name, from a zip or from the folder holding meta.json."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.zip: zipfile.ZipFile | None = None
        self.file: BinaryIO | None = None
        self.folder = path
        if path.is_dir():
            self.folder = path
        elif path.name.lower() == SOG_META:
            self.folder = path.parent
        else:
            self.file = open_regular(path, path, "the scene file")
            directory = _zip_directory_bytes(self.file)
            if directory is not None and directory > _MAX_ZIP_DIRECTORY_BYTES:
                self.file.close()
                raise SceneFileError(
                    f"{path}: SOG zip directory is {directory:,} bytes, more than the "
                    f"{_MAX_ZIP_DIRECTORY_BYTES:,} allowed (a bundle holds about 8 members)"
                )
            try:
                self.zip = zipfile.ZipFile(self.file)
            except (zipfile.BadZipFile, OSError) as e:
                self.file.close()
                raise SceneFileError(f"{path}: unreadable SOG zip bundle ({e})") from e

    def close(self) -> None:
        if self.file is not None:
            self.file.close()

    def read(self, name: str, cap_bytes: int) -> bytes:
        """Member `name`, at most `cap_bytes` long (SceneFileError naming both if longer)."""
        if not isinstance(name, str):
            raise SceneFileError(f"{self.path}: SOG file name {name!r} is not a string")
        what = f"SOG member {name}"
        try:
            if self.zip is None:
                if self.folder is not self.path and name == SOG_META:
                    target = self.path  # the scene file itself, named by its meta.json
                else:
                    target = contained(self.folder, name, self.path, "SOG file name")
                return read_capped(target, self.path, what, cap_bytes)
            info = self.zip.getinfo(name)
            if info.file_size > cap_bytes:
                raise SceneFileError(
                    f"{self.path}: {what} declares {info.file_size:,} bytes, more than the "
                    f"{cap_bytes:,} bytes allowed"
                )
            # Streamed with a cap as well: the declared size is what the file says, not what
            # the data inflates to.
            with self.zip.open(info) as member:
                data = member.read(cap_bytes + 1)
            if len(data) > cap_bytes:
                raise SceneFileError(f"{self.path}: {what} inflates to more than the "
                                     f"{cap_bytes:,} bytes allowed")
            return data
        except (KeyError, FileNotFoundError) as e:
            raise SceneFileError(f"{self.path}: SOG bundle has no {name}") from e
        except (OSError, zipfile.BadZipFile, EOFError, zlib.error) as e:
            raise SceneFileError(f"{self.path}: cannot read SOG member {name} ({e})") from e

    def picture(self, name: str, max_pixels: int) -> np.ndarray:
        """[H, W, 4] uint8 RGBA (WebP decoded by Pillow; lossless, so the bytes written), of at
        most `max_pixels` pixels: the size is checked from the header, before decoding."""
        from PIL import Image, UnidentifiedImageError

        data = self.read(name, _BYTES_PER_PIXEL * max_pixels + MARGIN_BYTES)
        try:
            with Image.open(io.BytesIO(data), formats=["WEBP"]) as im:
                width, height = im.size
                if width * height > max_pixels:
                    raise SceneFileError(
                        f"{self.path}: SOG image {name} is {width}x{height} pixels, more than "
                        f"the {max_pixels:,} its Gaussians can need"
                    )
                return np.asarray(im.convert("RGBA"))
        except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as e:
            raise SceneFileError(f"{self.path}: unreadable SOG image {name} ({e})") from e

    def image(self, name: str, count: int) -> np.ndarray:
        """[count, 4] uint8 RGBA, the first `count` pixels in row-major order."""
        rgba = self.picture(name, _pixels_for(count)).reshape(-1, 4)
        if rgba.shape[0] < count:
            raise SceneFileError(
                f"{self.path}: SOG image {name} has {rgba.shape[0]} pixels for {count} Gaussians"
            )
        return rgba[:count]


def _codebook(path: Path, meta: dict[str, Any], key: str) -> np.ndarray:
    book = np.asarray(meta[key]["codebook"], np.float64)
    if book.shape != (256,):
        raise SceneFileError(f"{path}: SOG {key}.codebook has {book.size} entries, expected 256")
    return book


def _decode(path: Path, files: _Files, meta: dict[str, Any],
            max_gaussians: int) -> dict[str, np.ndarray]:
    n = check_count(path, "SOG meta.json count", meta["count"], max_gaussians)
    lo = files.image(meta["means"]["files"][0], n)[:, :3].astype(np.float64)
    hi = files.image(meta["means"]["files"][1], n)[:, :3].astype(np.float64)
    mins, maxs = (np.asarray(meta["means"][k], np.float64).reshape(3) for k in ("mins", "maxs"))
    t = mins + (maxs - mins) * (lo + 256.0 * hi) / 65535.0
    means = np.sign(t) * np.expm1(np.abs(t))

    q = files.image(meta["quats"]["files"][0], n).astype(np.int64)
    largest = q[:, 3] - 252
    if ((largest < 0) | (largest > 3)).any():
        raise SceneFileError(f"{path}: SOG quats alpha must be 252-255 (index of the largest)")
    small = (q[:, :3] / 255.0 * 2.0 - 1.0) / math.sqrt(2.0)
    quats = np.zeros((n, 4))
    np.put_along_axis(quats, _OTHERS[largest], small, axis=1)
    quats[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - (small**2).sum(1)))

    scale_idx = files.image(meta["scales"]["files"][0], n)[:, :3]
    scales = np.exp(_codebook(path, meta, "scales")[scale_idx])
    sh0 = files.image(meta["sh0"]["files"][0], n)
    dc = _codebook(path, meta, "sh0")[sh0[:, :3]]
    return dict(means=means, quats=quats, scales=scales, opacities=sh0[:, 3] / 255.0,
                sh=np.concatenate([dc[:, None, :], _rest(path, files, meta, n)], axis=1))


def _rest(path: Path, files: _Files, meta: dict[str, Any], n: int) -> np.ndarray:
    """[N, K-1, 3] higher-order SH from the palette, or [N, 0, 3] without `shN`."""
    sh_n = meta.get("shN")
    if not sh_n:
        return np.zeros((n, 0, 3))
    bands = sh_n["bands"]
    if bands not in _SH_COEFFS:
        raise SceneFileError(f"{path}: SOG shN.bands is {bands!r}, expected 1, 2 or 3")
    c, entries = _SH_COEFFS[bands], sh_n["count"]
    if isinstance(entries, bool) or not isinstance(entries, int) or not 1 <= entries <= 1 << 16:
        raise SceneFileError(f"{path}: SOG shN.count is {entries!r}; allowed: 1 to 65536 "
                             "(the labels are 16-bit)")
    labels = files.image(sh_n["files"][1], n)
    label = labels[:, 0].astype(np.int64) + 256 * labels[:, 1].astype(np.int64)
    if (label >= entries).any():
        raise SceneFileError(f"{path}: SOG shN label {label.max()} is past the palette ({entries})")
    centroids = files.picture(sh_n["files"][0], 64 * c * math.ceil(entries / 64))
    if centroids.shape[1] != 64 * c or centroids.shape[0] < math.ceil(entries / 64):
        raise SceneFileError(
            f"{path}: SOG centroids image is {centroids.shape[1]}x{centroids.shape[0]}; "
            f"{entries} entries of {c} coefficients need {64 * c}x{math.ceil(entries / 64)}"
        )
    texels = centroids[(label // 64)[:, None], (label % 64)[:, None] * c + np.arange(c)]
    return _codebook(path, meta, "shN")[texels[..., :3]]  # [N, C, 3]
