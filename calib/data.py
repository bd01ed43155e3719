"""The capture directory's format, and reading it back with errors that name the file at fault.

Layout of a capture directory (written by `nhfd.calib.capture`):

    manifest.json          what was shown, where and how, rewritten after every image so an
                           interrupted capture resumes where it stopped
    frames/NAME.npy        every SLM frame shown, uint8 [H, W, 3]
    images/KEY.npz         `image` float32 (linear, dark subtracted), `saturated` bool
    dark.npz               the dark frame (lasers off)
    daemon/                through a daemon only: the frame being shown and the last capture,
                           exchanged as .npy files (scratch)
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.config import Config

from .patterns import PatternSpec

MANIFEST = "manifest.json"
MANIFEST_VERSION = 1
FRAMES_DIR = "frames"
IMAGES_DIR = "images"
DARK = "dark.npz"


def default_camera_pitch_m() -> float:
    """The configured camera's pixel pitch (m): `devices.camera_settings.pixel_pitch_um`; what a
    capture whose plan does not record it was taken with."""
    return Config().devices.camera_settings.pixel_pitch_um * 1e-6


class CalibrationDataError(ValueError):
    """A capture directory is missing, foreign, incomplete or corrupt; the message names it."""


@dataclass
class CaptureData:
    """A complete capture directory read back: its `root`, the manifest (`records` lists every
    image) and the patterns' `spec`."""
    root: Path
    manifest: dict[str, Any]
    spec: PatternSpec

    def records(self, sweep: str, colour: int | None = None) -> list[dict[str, Any]]:
        """The records of one sweep ("coarse", "grating", "flat" or "fine"), of one colour (0 R, 1
        G, 2 B) or of all."""
        return [r for r in self.manifest["records"] if r.get("sweep") == sweep
                and (colour is None or r["colour"] == colour)]

    def image(self, rec: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """(linear image [h, w] float64, saturated mask [h, w] bool) of one record."""
        return load_image(self.root / rec["file"], rec["key"])


def load_image(path: Path, key: str = "") -> tuple[np.ndarray, np.ndarray]:
    """A captured image file: (linear image `[h, w]` float64, saturated mask `[h, w]` bool; all
    False when the file has none). CalibrationDataError naming the file (and capture `key`) when it
    is missing, unreadable, not 2-D, not finite or its mask does not match."""
    name = f"{path} (capture {key!r})" if key else str(path)
    if not path.is_file():
        raise CalibrationDataError(f"{name}: missing")
    try:
        with np.load(path) as z:
            image = np.asarray(z["image"], np.float64)
            sat = np.asarray(z["saturated"], bool) if "saturated" in z else \
                np.zeros(image.shape, bool)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise CalibrationDataError(f"{name}: corrupt or unreadable ({exc})") from None
    if image.ndim != 2 or image.size == 0:
        raise CalibrationDataError(f"{name}: expected a 2-D mono image, got {image.shape}")
    if not np.isfinite(image).all():
        raise CalibrationDataError(f"{name}: holds NaN or Inf")
    if sat.shape != image.shape:
        raise CalibrationDataError(f"{name}: saturation mask {sat.shape} != image {image.shape}")
    return image, sat


def load_frame(root: Path, manifest: dict[str, Any], name: str) -> np.ndarray:
    """An SLM frame the capture showed (uint8 [H, W, 3]), named in the manifest."""
    rel = manifest.get("frames", {}).get(name)
    if rel is None:
        raise CalibrationDataError(f"{root / MANIFEST}: frame {name!r} is not listed")
    path = root / rel
    if not path.is_file():
        raise CalibrationDataError(f"{path} (frame {name!r}): missing")
    try:
        frame = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise CalibrationDataError(f"{path} (frame {name!r}): corrupt or unreadable "
                                   f"({exc})") from None
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise CalibrationDataError(f"{path} (frame {name!r}): expected uint8 [H, W, 3], got "
                                   f"{frame.dtype} {frame.shape}")
    return frame


def load_capture(root: Path | str) -> CaptureData:
    """A complete capture directory (`root`, holding `manifest.json`), checked: CalibrationDataError
    naming the file when it is missing, foreign, of another version, incomplete or corrupt."""
    root = Path(root)
    path = root / MANIFEST
    if not path.is_file():
        raise CalibrationDataError(f"{path}: missing (not a calibration capture directory)")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise CalibrationDataError(f"{path}: corrupt ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("kind") != "nhfd-calib-capture":
        raise CalibrationDataError(f"{path}: not an nhfd calibration capture manifest")
    if manifest.get("version") != MANIFEST_VERSION:
        raise CalibrationDataError(f"{path}: manifest version {manifest.get('version')!r}, "
                                   f"this nhfd reads {MANIFEST_VERSION}")
    if not manifest.get("complete"):
        raise CalibrationDataError(f"{path}: the capture is incomplete (resume it with "
                                   "`nhfd calib capture --out DIR`)")
    try:
        spec = PatternSpec.from_dict(manifest["spec"])
        for r in manifest["records"]:
            r["key"], r["file"], r["colour"], r["stage_mm"]
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationDataError(f"{path}: malformed manifest ({exc!r})") from None
    return CaptureData(root, manifest, spec)
