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
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.scene.gaussians import SceneFileError, malformed_as_scene_error

__all__ = ["ZIP_MAGIC", "read_sog"]

ZIP_MAGIC = b"PK\x03\x04"
_SH_COEFFS = {1: 3, 2: 8, 3: 15}
# For the index of the largest component (w x y z), the slots the three stored values fill.
_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def read_sog(path: Path) -> dict[str, np.ndarray]:
    """Activated arrays (means, quats wxyz, scales, opacities, sh) from a SOG folder, its
    `meta.json`, or a `.sog` zip bundle."""
    files = _Files(path)
    try:
        meta = json.loads(files.read("meta.json"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
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
        return _decode(path, files, meta)


class _Files:
    """The bundle's members by name, from a zip or from the folder holding meta.json."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.zip = None
        if path.is_dir():
            self.folder = path
        elif path.name.lower() == "meta.json":
            self.folder = path.parent
        else:
            try:
                self.zip = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError) as e:
                raise SceneFileError(f"{path}: unreadable SOG zip bundle ({e})") from e

    def read(self, name: str) -> bytes:
        try:
            if self.zip is not None:
                return self.zip.read(name)
            return (self.folder / name).read_bytes()
        except (KeyError, FileNotFoundError) as e:
            raise SceneFileError(f"{self.path}: SOG bundle has no {name}") from e
        except (OSError, zipfile.BadZipFile, EOFError) as e:
            raise SceneFileError(f"{self.path}: cannot read SOG member {name} ({e})") from e

    def picture(self, name: str) -> np.ndarray:
        """[H, W, 4] uint8 RGBA (WebP decoded by Pillow; lossless, so the bytes written)."""
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(io.BytesIO(self.read(name))) as im:
                return np.asarray(im.convert("RGBA"))
        except (UnidentifiedImageError, OSError) as e:
            raise SceneFileError(f"{self.path}: unreadable SOG image {name} ({e})") from e

    def image(self, name: str, count: int) -> np.ndarray:
        """[count, 4] uint8 RGBA, the first `count` pixels in row-major order."""
        rgba = self.picture(name).reshape(-1, 4)
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


def _decode(path: Path, files: _Files, meta: dict[str, Any]) -> dict[str, np.ndarray]:
    n = int(meta["count"])
    if n < 0:
        raise SceneFileError(f"{path}: SOG count is {n}; it must be >= 0")
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
    c, entries = _SH_COEFFS[bands], int(sh_n["count"])
    labels = files.image(sh_n["files"][1], n)
    label = labels[:, 0].astype(np.int64) + 256 * labels[:, 1].astype(np.int64)
    if (label >= entries).any():
        raise SceneFileError(f"{path}: SOG shN label {label.max()} is past the palette ({entries})")
    centroids = files.picture(sh_n["files"][0])
    if centroids.shape[1] != 64 * c or centroids.shape[0] < math.ceil(entries / 64):
        raise SceneFileError(
            f"{path}: SOG centroids image is {centroids.shape[1]}x{centroids.shape[0]}; "
            f"{entries} entries of {c} coefficients need {64 * c}x{math.ceil(entries / 64)}"
        )
    texels = centroids[(label // 64)[:, None], (label % 64)[:, None] * c + np.arange(c)]
    return _codebook(path, meta, "shN")[texels[..., :3]]  # [N, C, 3]
