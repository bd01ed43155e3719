"""Reference plane <-> SLM, and the quality measures."""

from __future__ import annotations

import pytest
import torch

from nhfd.optics import (
    Aperture,
    crop_window,
    focal_stack_quality,
    hologram_2d,
    linear_to_srgb,
    place_window,
    propagate,
    quality_planes,
    reference_to_slm,
    slm_to_reference,
)

from .fields import band_limited, envelope

P = 8e-6
RGB = (660e-9, 520e-9, 450e-9)


def test_window_placement_round_trip_and_zero_outside():
    w = torch.randn(3, 6, 10, dtype=torch.complex64)
    panel = place_window(w, (16, 20))
    assert torch.equal(crop_window(panel, (6, 10)), w)
    assert float(panel.abs().sum()) == pytest.approx(float(w.abs().sum()), rel=1e-6)
    with pytest.raises(ValueError, match="does not fit"):
        place_window(w, (4, 20))


def test_reference_to_slm_on_the_window_region_matches_the_whole_panel():
    ap = Aperture()
    # Content smooth to zero inside the window: a hard edge would put energy at the aperture's
    # band edge, where grids of different sizes sample the cutoff differently (~1e-3).
    window = band_limited((3, 96, 128), 0.1, torch.complex64) * envelope(96, 128, 0.6)
    panel_hw, z0 = (240, 320), 6e-3
    fast = reference_to_slm(window, panel_hw, z0, P, RGB, aperture=ap)
    full = propagate(place_window(window, panel_hw), -z0, P, RGB, padding="2x", aperture=ap)
    assert float((fast - full).norm() / full.norm()) < 1e-4
    back = crop_window(slm_to_reference(fast, z0, P, RGB, aperture=ap), (96, 128))
    ref = propagate(window, 0.0, P, RGB, aperture=ap)  # what the aperture passes of the window
    assert float((back - ref).norm() / ref.norm()) < 1e-3


def test_quality_planes_include_reference_and_ends():
    assert quality_planes((-3e-3, 3e-3), 5) == (-3e-3, -1.5e-3, 0.0, 1.5e-3, 3e-3)
    assert 0.0 in quality_planes((-2e-3, 4e-3), 4)
    with pytest.raises(ValueError, match="z_min < z_max"):
        quality_planes((1e-3, -1e-3))


def scene_with_depth(n: int = 128):
    """Three objects at three depths: the target field on the reference plane, the all-in-focus
    central view (sRGB) a renderer would produce, and the scene mask."""
    objects, depths = [], (-2e-3, 0.0, 2e-3)
    for k in range(3):
        img = torch.zeros(3, n, n)
        r0, c0 = 20 + 30 * k, 20 + 30 * k
        img[:, r0 : r0 + 28, c0 : c0 + 28] = torch.rand(3, 1, 1) * 0.8 + 0.2
        objects.append(img)
    target = sum(
        propagate(torch.sqrt(o).to(torch.complex64), -z, P, RGB, aperture=Aperture())
        for o, z in zip(objects, depths, strict=True)
    )
    view_linear = sum(objects)
    mask = view_linear.sum(0) > 0
    return target, linear_to_srgb(view_linear), mask


def test_baselines_rank_below_the_true_field():
    target, view, mask = scene_with_depth()
    kw = dict(
        planes_m=quality_planes((-2e-3, 2e-3), 5),
        pitch_m=P,
        wavelengths_m=RGB,
        aperture=Aperture(),
        mask=mask,
    )
    noisy = target + 0.02 * target.abs().mean() * torch.randn_like(target)
    q_true = focal_stack_quality(noisy, target, **kw)
    q_2d = focal_stack_quality(hologram_2d(view), target, **kw)
    q_black = focal_stack_quality(torch.zeros_like(target), target, **kw)
    assert q_true.psnr_db > q_2d.psnr_db + 3 > q_black.psnr_db + 3
    assert q_true.ssim > q_2d.ssim > q_black.ssim
    # Identical fields give the finite ceiling, never Inf.
    same = focal_stack_quality(target, target, **kw)
    assert same.psnr_db == 120.0 and same.ssim == pytest.approx(1.0, abs=1e-4)


def test_2d_hologram_baseline_can_match_the_targets_energy():
    from nhfd.optics import hologram_2d

    view = torch.rand(3, 16, 20)
    target = 3.4 * hologram_2d(view) * torch.exp(1j * torch.rand(3, 16, 20))
    mask = torch.zeros(16, 20, dtype=torch.bool)
    mask[4:12, 5:15] = True
    flat = hologram_2d(view, like=target, mask=mask)
    # Same energy inside the mask, zero phase, and the plain baseline is 3.4x weaker.
    assert torch.allclose(flat.abs()[:, mask].square().sum(), target.abs()[:, mask].square().sum(),
                          rtol=1e-5)  # fmt: skip
    assert torch.allclose(flat.angle(), torch.zeros(3, 16, 20))
    assert torch.allclose(flat.abs(), 3.4 * hologram_2d(view).abs(), rtol=1e-4)
