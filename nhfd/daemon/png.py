"""16-bit greyscale PNGs of camera images (snapshots). Standard library zlib only: no imaging
library in the daemon for one file format."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np


def write_png16(path: Path, image: np.ndarray) -> None:
    """A 16-bit greyscale PNG (image in [0, 1], clipped), written atomically."""
    a = np.clip(np.nan_to_num(np.asarray(image, np.float64)), 0.0, 1.0)
    if a.ndim == 3:  # colour captures: written as the mean over channels
        a = a.mean(axis=0)
    h, w = a.shape
    raw = np.round(a * 65535).astype(">u2")
    rows = b"".join(b"\x00" + raw[r].tobytes() for r in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(rows, 6)) + chunk(b"IEND", b""))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(png)
    tmp.replace(path)
