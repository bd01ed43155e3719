"""`to_slm_grid` (kornia's warp_affine) against analytic values: bilinear sampling of an image
that is linear in the camera's coordinates returns that function exactly, wherever the SLM
pixel centre falls, so every value checks the geometry, the pixel-centre convention and the
affine map's direction."""

from __future__ import annotations

import numpy as np

from nhfd.calib.geometry import Geometry
from nhfd.optics.camera_grid import EDGE_MARGIN_PX, to_slm_grid

PANEL_HW = (48, 64)
PITCH_M = 8e-6


def test_a_linear_image_is_sampled_exactly_at_every_slm_pixel_centre():
    ih, iw = 150, 170
    rows, cols = np.mgrid[0:ih, 0:iw]
    image = 0.3 + 0.002 * cols - 0.0035 * rows
    # The panel's image runs past the camera's left edge: those pixels are invalid.
    geo = Geometry(2.6e5, 181.7, True, (40.3, 70.9), 0.0, 0, 0.0, 0.0)
    vals, ok = to_slm_grid(image, geo, PANEL_HW, PITCH_M)
    h, w = PANEL_HW
    r, c = np.mgrid[0:h, 0:w]
    xy = np.stack([(c - (w - 1) / 2) * PITCH_M, (r - (h - 1) / 2) * PITCH_M], -1)
    cam = geo.to_camera(xy.reshape(-1, 2)).reshape(h, w, 2)
    inside = (cam[..., 0] >= 0) & (cam[..., 0] <= iw - 1) & (cam[..., 1] >= 0) & \
        (cam[..., 1] <= ih - 1)
    m = EDGE_MARGIN_PX
    inner = (r >= m) & (r < h - m) & (c >= m) & (c < w - m)
    assert np.array_equal(ok, inside & inner)
    assert 0.3 * ok.size < ok.sum() < (inner.sum() - 1)  # some cut off, most in view
    want = 0.3 + 0.002 * cam[..., 0] - 0.0035 * cam[..., 1]
    assert np.abs(vals - want)[ok].max() < 1e-12
