"""The measures of captured focal stacks (issue 34's benchmark): PSNR/SSIM after the camera's
free gain per colour, and speckle contrast."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nhfd.optics import colour_gains, speckle_contrast, stack_quality

PLANES = (-1e-3, 0.0, 1e-3)


def _target(seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.uniform(0.5, 1.5, (3, 3, 40, 50)))


def test_colour_gains_recover_each_colours_scale() -> None:
    t = _target(1)
    scale = torch.tensor([2.0, 0.5, 7.0], dtype=torch.float64)
    seen = t / scale[:, None, None]
    mask = torch.ones(40, 50, dtype=torch.bool)
    assert torch.allclose(colour_gains(seen, t, mask), scale, rtol=1e-12)
    dark = seen.clone()
    dark[:, 1] = 0  # a colour that shows nothing gets gain 1, not a division by zero
    assert colour_gains(dark, t, mask)[1] == 1.0


def test_stack_quality_fits_the_cameras_gain_only_when_asked() -> None:
    t = _target(2)
    seen = 0.3 * t
    mask = torch.ones(40, 50, dtype=torch.bool)
    assert stack_quality(seen, t, planes_m=PLANES, mask=mask, fit_gains=True).psnr_db == 120.0
    raw = stack_quality(seen, t, planes_m=PLANES, mask=mask)
    assert raw.psnr_db < 20 and raw.ssim < 0.99
    with pytest.raises(ValueError, match=r"\[D, C, H, W\] with D = 2 planes"):
        stack_quality(seen, t, planes_m=PLANES[:2])


def test_speckle_contrast_is_zero_for_the_target_and_one_for_developed_speckle() -> None:
    t = torch.ones(1, 3, 200, 200, dtype=torch.float64)
    mask = torch.ones(200, 200, dtype=torch.bool)
    assert speckle_contrast(2.0 * t, t, mask) == pytest.approx(0.0, abs=1e-12)
    # Fully developed speckle: exponentially distributed intensity, contrast 1.
    rng = np.random.default_rng(3)
    speckle = torch.from_numpy(rng.exponential(1.0, t.shape))
    assert speckle_contrast(speckle, t, mask) == pytest.approx(1.0, abs=0.02)
    # The mean of K independent patterns: 1 / sqrt(K).
    four = torch.from_numpy(rng.exponential(1.0, (4, *t.shape))).mean(0)
    assert speckle_contrast(four, t, mask) == pytest.approx(0.5, abs=0.02)
