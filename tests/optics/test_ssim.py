"""Evaluation's SSIM map against analytic values (Gaussian window 11, sigma 1.5, K1 0.01,
K2 0.03, reflect padding; docs/physics.md). `nhfd bench geometry` compares it with kornia's."""

from __future__ import annotations

import torch

from nhfd.optics.quality import ssim_map

C1 = 0.01**2
# float32 against float64: the variances are differences of nearby moments (bench: 3.2e-4).
FLOAT32_TOL = 5e-4


def test_identical_images_score_one_and_flat_ones_their_luminance_term():
    x = torch.rand(2, 40, 50, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert torch.allclose(ssim_map(x, x), torch.ones_like(x), atol=1e-12)
    # Flat images have no variance or covariance: the map is the luminance term alone.
    a, b = 0.3, 0.7
    want = (2 * a * b + C1) / (a * a + b * b + C1)
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, FLOAT32_TOL)):
        flat = ssim_map(torch.full((1, 20, 20), a, dtype=dtype),
                        torch.full((1, 20, 20), b, dtype=dtype))
        assert flat.dtype == dtype
        assert (flat.double() - want).abs().max() < tol
    # Anti-correlated images score below zero (no clipping hides the sign).
    assert ssim_map(x, 1 - x).mean() < 0
    # Images smaller than the window still get a map of their own size.
    small = x[:1, :4, :4]
    assert torch.allclose(ssim_map(small, small), torch.ones_like(small), atol=1e-12)
