"""The camera's view of the SLM plane: the calibrated similarity between SLM metres and camera
pixels, and camera images resampled at the SLM's pixel centres through it.

`Geometry` is what `nhfd.calib.geometry` fits from the dot hologram; `calibrated_geometry` rebuilds
it from an applied calibration; `to_slm_grid` samples a camera image on the SLM's pixel grid.
Both the calibration's bench model and the camera in the loop (`citl`, in the frame worker and
offline) compare captures with simulations there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from kornia.geometry.transform import warp_affine

from nhfd.calibration import Calibration

# Pixels (SLM) left out along the panel's edge: the edge diffracts light that the model's
# missing background terms would otherwise have to explain.
EDGE_MARGIN_PX = 6


@dataclass(frozen=True)
class Geometry:
    """`camera_px = A @ xy_m + t`; `A = px_per_m R(rotation) F(mirror_x)`. Uncertainties are
    one standard deviation from the least-squares fit."""

    px_per_m: float
    rotation_deg: float
    mirror_x: bool
    shift_px: tuple[float, float]
    rms_px: float
    n_dots: int
    px_per_m_std: float
    rotation_std_deg: float

    @property
    def matrix(self) -> np.ndarray:
        """`A` [2, 2]: camera pixels per SLM metre, rotated and (with `mirror_x`) mirrored."""
        a = math.radians(self.rotation_deg)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        flip = np.diag([-1.0 if self.mirror_x else 1.0, 1.0])
        return self.px_per_m * rot @ flip

    def to_camera(self, xy_m: np.ndarray) -> np.ndarray:
        """SLM metres [N, 2] -> camera (col, row) [N, 2]."""
        return np.asarray(xy_m) @ self.matrix.T + np.asarray(self.shift_px)

    def to_slm(self, colrow: np.ndarray) -> np.ndarray:
        """Camera (col, row) [N, 2] -> SLM metres [N, 2]."""
        return (np.asarray(colrow) - np.asarray(self.shift_px)) @ np.linalg.inv(self.matrix).T

    def magnification(self, camera_pitch_m: float) -> float:
        """The relay's magnification for a camera of `camera_pitch_m` pixels."""
        return self.px_per_m * camera_pitch_m


def calibrated_geometry(cal: Calibration, camera_pitch_m: float) -> Geometry:
    """The calibration's SLM -> camera geometry (in the calibration capture's image, so on the
    same camera region of interest); the camera's pitch as recorded at the fit, else
    `camera_pitch_m` (the camera in use: `devices.camera_settings.pixel_pitch_um`)."""
    pitch = float(cal.fitted_on.get("camera_pitch_m") or camera_pitch_m)
    return Geometry(cal.magnification / pitch, cal.rotation_deg, cal.mirror_x, cal.shift_px,
                    0.0, 0, 0.0, 0.0)


def to_slm_grid(image: np.ndarray, geo: Geometry, panel_hw: tuple[int, int], pitch_m: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """A camera image `[Hc, Wc]` sampled (bilinearly) at the SLM pixel centres through the
    geometry: (`[H, W]` values, `[H, W]` bool: inside the image and EDGE_MARGIN_PX inside the
    panel). `pitch_m`: the SLM's pixel pitch."""
    h, w = panel_hw
    # SLM pixel (col, row) -> camera (col, row) is affine: camera = a @ (col, row) + b.
    a = geo.matrix * pitch_m
    b = geo.to_camera(np.array([[-(w - 1) / 2 * pitch_m, -(h - 1) / 2 * pitch_m]]))[0]
    forward = np.eye(3)
    forward[:2, :2], forward[:2, 2] = a, b
    # warp_affine takes the map from the source (camera) to the destination (SLM grid);
    # align_corners: pixel centres at integers, as the geometry counts them.
    vals = warp_affine(torch.from_numpy(np.asarray(image, np.float64))[None, None],
                       torch.from_numpy(np.linalg.inv(forward)[:2])[None], (h, w),
                       mode="bilinear", padding_mode="zeros", align_corners=True)[0, 0]
    rows, cols = np.arange(h)[:, None], np.arange(w)[None, :]
    cam_col = a[0, 0] * cols + a[0, 1] * rows + b[0]
    cam_row = a[1, 0] * cols + a[1, 1] * rows + b[1]
    ih, iw = image.shape
    ok = (cam_col >= 0) & (cam_row >= 0) & (cam_col <= iw - 1) & (cam_row <= ih - 1)
    m = EDGE_MARGIN_PX
    inner = (rows >= m) & (rows < h - m) & (cols >= m) & (cols < w - m)
    return vals.numpy(), ok & inner
