"""16-bit greyscale PNGs of camera images (snapshots), encoded by OpenCV (libpng).

OpenCV, not Pillow (both are dependencies): Pillow's PNG writer always filters its rows
adaptively and cannot be told not to, and the rows are written unfiltered here, as the
hand-written encoder this replaced did, for readers that take only unfiltered rows
(`nhfd.demos.serve.read_png16`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# zlib level of the image data: the hand-written encoder's (6); OpenCV's default is 1.
COMPRESSION = 6
PNG16_MAX = 65535


def to_uint16(image: np.ndarray) -> np.ndarray:
    """The 16-bit values [H, W] (uint16, native byte order) `write_png16` stores for `image`.

    `image`: [H, W], or [C, H, W] (a colour capture: stored as the mean over the channels),
    linear values in [0, 1] (dimensionless, full scale 1). Outside [0, 1] is clipped; NaN is
    stored as 0, +inf as 65535 and -inf as 0 (no error: a snapshot of a bad frame is still
    written). Each value is `round(v * 65535)`."""
    a = np.clip(np.nan_to_num(np.asarray(image, np.float64)), 0.0, 1.0)
    if a.ndim == 3:  # colour captures: written as the mean over channels
        a = a.mean(axis=0)
    if a.ndim != 2 or not a.size:
        raise ValueError(f"a PNG image is [H, W] or [C, H, W] and not empty, not {a.shape}")
    return np.round(a * PNG16_MAX).astype(np.uint16)


def write_png16(path: Path, image: np.ndarray) -> None:
    """A 16-bit greyscale PNG of `image` (see `to_uint16`: [H, W] or [C, H, W], linear values
    in [0, 1], clipped), written atomically (a hidden temporary file in the same folder,
    renamed over `path`; the folder is made). The samples are big-endian in the file, as PNG
    requires; rows unfiltered, zlib level `COMPRESSION`."""
    # Imported here: the daemon starts without OpenCV (about 20 MB) unless it writes a snapshot.
    import cv2

    ok, data = cv2.imencode(".png", to_uint16(image),
                            [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE,
                             cv2.IMWRITE_PNG_COMPRESSION, COMPRESSION])
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode the PNG")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data.tobytes())
    tmp.replace(path)


# The preview's range: these percentiles of the image map to grey 0 and 255 (a few hot or dead
# pixels do not set the scale).
PREVIEW_PERCENTILES = (0.1, 99.9)


def preview_path(path: Path) -> Path:
    """Where the 8-bit preview of the snapshot at `path` goes: `<stem>.preview.png` beside it."""
    return path.with_name(f"{path.stem}.preview.png")


def write_preview8(path: Path, image: np.ndarray) -> Path:
    """An 8-bit greyscale PNG of `image` ([H, W] or [C, H, W], as `to_uint16` takes it) scaled
    to its own range (`PREVIEW_PERCENTILES` -> 0 and 255), for a person to look at: a linear
    16-bit capture whose counts span 472-2283 of 65535 reads as black in an ordinary viewer.
    Written atomically at `preview_path(path)`, which it returns; the 16-bit file stays the
    data."""
    import cv2

    a = to_uint16(image).astype(np.float64)
    lo, hi = np.percentile(a, PREVIEW_PERCENTILES)
    scaled = np.clip((a - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.zeros_like(a)
    ok, data = cv2.imencode(".png", np.round(scaled * 255).astype(np.uint8))
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode the preview PNG")
    out = preview_path(path)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_bytes(data.tobytes())
    tmp.replace(out)
    return out
