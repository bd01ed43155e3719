"""Evaluation's SSIM map against analytic values (Gaussian window 11, sigma 1.5, K1 0.01,
K2 0.03, reflect padding; docs/physics.md). `nhfd bench geometry` compares it with kornia's."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from nhfd.optics.quality import SSIM_SIGMA_PX, SSIM_WINDOW_PX, ssim_map

C1 = 0.01**2
C2 = 0.03**2
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


def test_the_depthwise_blur_is_the_plain_convolution() -> None:
    """`ssim_map` blurs its moments as one depthwise convolution (the fast path on the CPU);
    the plain batch of one-channel convolutions beside it gives the same map to 1e-12."""
    g = torch.Generator().manual_seed(7)
    x = torch.rand(3, 37, 61, generator=g, dtype=torch.float64)
    y = (x + 0.1 * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    k = torch.arange(SSIM_WINDOW_PX, dtype=torch.float64) - SSIM_WINDOW_PX // 2
    w = torch.exp(-(k**2) / (2 * SSIM_SIGMA_PX**2))
    w = (w[:, None] * w[None, :] / w.sum() ** 2)[None, None]
    pad = SSIM_WINDOW_PX // 2
    m = torch.stack([x, y, x * x, y * y, x * y], dim=1).reshape(-1, 1, 37, 61)
    mx, my, mxx, myy, mxy = F.conv2d(F.pad(m, (pad,) * 4, mode="reflect"), w).reshape(
        3, 5, 37, 61).unbind(1)
    vx, vy, cov = mxx - mx * mx, myy - my * my, mxy - mx * my
    plain = ((2 * mx * my + C1) * (2 * cov + C2)) / ((mx * mx + my * my + C1) * (vx + vy + C2))
    assert (ssim_map(x, y) - plain).abs().max() < 1e-12
    assert 0.2 < float(plain.mean()) < 0.95  # images alike but not the same: a real test
