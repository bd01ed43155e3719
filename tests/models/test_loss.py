"""The focal-stack loss: zero for identical fields, growing with defocus; plane choice."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from nhfd.models.data import HoloData, centre_crop_edges, random_crop
from nhfd.models.loss import (
    FocalStackLoss,
    Optics,
    box_ssim,
    choose_planes,
    spectral_field_error,
    uniform_planes,
)
from nhfd.optics import propagate


def test_loss_is_zero_for_identical_fields_and_grows_with_defocus(tiny_data):
    data = HoloData(tiny_data, splits=("train",))
    optics = Optics.from_manifest(data.manifest)
    loss = FocalStackLoss(optics)
    target = data.splits["train"].field[:1]
    planes = uniform_planes(optics.volume_m, 5)
    same = loss(target.clone(), target, planes, [0, 2])
    assert float(same["l2"]) == 0.0
    assert abs(float(same["loss"])) < 1e-5
    values = []
    for dz_mm in (0.25, 0.5, 1.0, 2.0):
        moved = propagate(target, dz_mm * 1e-3, optics.pitch_m, optics.wavelengths_m,
                          aperture=optics.aperture)  # fmt: skip
        values.append(float(loss(moved, target, planes, [0, 2])["loss"]))
    assert values[0] > 0
    assert all(b > a for a, b in itertools.pairwise(values)), values


def test_spectral_field_error_sees_defocus_that_a_plain_field_l2_barely_sees(tiny_data):
    """Zero for identical fields; grows with defocus; and relative to a plain field L2 it weighs
    a depth error (phase growing with |f|^2) more than a same-energy error at low frequency."""
    data = HoloData(tiny_data, splits=("train",))
    optics = Optics.from_manifest(data.manifest)
    target = data.splits["train"].field[:1]
    padded = FocalStackLoss(optics).padded_hw(target)
    assert float(spectral_field_error(target.clone(), target, optics.aperture, padded)) == 0.0
    errors, plain = [], []
    for dz_mm in (0.25, 0.5, 1.0, 2.0):
        moved = propagate(target, dz_mm * 1e-3, optics.pitch_m, optics.wavelengths_m,
                          aperture=optics.aperture)  # fmt: skip
        errors.append(float(spectral_field_error(moved, target, optics.aperture, padded)))
        plain.append(float((moved - target).abs().square().sum() / target.abs().square().sum()))
    assert errors[0] > 0
    assert all(b > a for a, b in itertools.pairwise(errors)), errors
    assert errors[0] > 2 * plain[0], (errors[0], plain[0])
    # The same relative energy as a broad smooth bump (low frequencies) costs far less.
    h, w = target.shape[-2:]
    yy, xx = torch.meshgrid(torch.arange(h) - h / 2, torch.arange(w) - w / 2, indexing="ij")
    bump = torch.exp(-(xx**2 + yy**2) / (2 * (h / 8) ** 2))
    bump = bump * (plain[0] * target.abs().square().sum() / (3 * bump.square().sum())).sqrt()
    assert float(spectral_field_error(target + bump, target, optics.aperture,
                                      padded)) < 0.1 * errors[0]  # fmt: skip


def test_spectral_field_error_pads_like_propagation_and_leaves_out_the_margin(tiny_data):
    """Zero-padded, an error on one edge is not tied to the opposite edge (the FFT's wrap); and
    an error inside the left-out margin costs next to nothing."""
    data = HoloData(tiny_data, splits=("train",))
    optics = Optics.from_manifest(data.manifest)
    loss = FocalStackLoss(optics)
    target = data.splits["train"].field[:1]
    h, w = target.shape[-2:]
    padded, m = loss.padded_hw(target), loss.margin
    # A field that is the same on the left and right edges: periodic, the wrap hides its jump
    # to zero beyond the window; padded, that jump is an error the SLM would show.
    edge = torch.zeros_like(target)
    edge[..., :, : m // 2] = 1.0
    edge[..., :, -(m // 2) :] = 1.0
    wrapped = float(spectral_field_error(target + edge, target, optics.aperture, (h, w)))
    zero_padded = float(spectral_field_error(target + edge, target, optics.aperture, padded))
    assert zero_padded > 1.5 * wrapped, (zero_padded, wrapped)
    # Noise confined to the left margin band: counted in full, then left out.
    noise = torch.zeros_like(target)
    noise[..., :, : m // 2] = torch.randn((*target.shape[:-1], m // 2),
                                          generator=torch.Generator().manual_seed(0))  # fmt: skip
    full = float(spectral_field_error(target + noise, target, optics.aperture, padded))
    cut = float(spectral_field_error(target + noise, target, optics.aperture, padded,
                                     (0, 0, m, 0)))  # fmt: skip
    assert cut < 0.05 * full, (cut, full)
    with pytest.raises(ValueError, match="padded_hw"):
        spectral_field_error(target, target, optics.aperture, (h - 1, w))


def test_the_field_term_is_off_by_default_and_checked(tiny_data):
    data = HoloData(tiny_data, splits=("train",))
    optics = Optics.from_manifest(data.manifest)
    target = data.splits["train"].field[:1]
    moved = propagate(target, 1e-3, optics.pitch_m, optics.wavelengths_m, aperture=optics.aperture)
    planes = uniform_planes(optics.volume_m, 3)
    base = float(FocalStackLoss(optics)(moved, target, planes)["loss"])
    with_field = float(FocalStackLoss(optics, field_weight=0.5)(moved, target, planes)["loss"])
    loss = FocalStackLoss(optics)
    expected = 0.5 * float(spectral_field_error(moved, target, optics.aperture,
                                                loss.padded_hw(moved),
                                                loss.margin_crop(moved, (True,) * 4)))  # fmt: skip
    assert with_field - base == pytest.approx(expected, rel=1e-4)
    with pytest.raises(ValueError, match="field_weight"):
        FocalStackLoss(optics, field_weight=-1.0)


def test_margin_masks_the_band_that_propagation_contaminates(tiny_data):
    optics = Optics.from_manifest(HoloData(tiny_data, splits=("train",)).manifest)
    loss = FocalStackLoss(optics)
    # 3 mm at 8 um, 660 nm, quarter-band square aperture: about 8 px of reach + 8 guard.
    assert 12 <= loss.margin <= 20
    stack = loss.stack(torch.ones(1, 3, 64, 64, dtype=torch.complex64), [0.0, 1e-3])
    assert stack.shape == (1, 2, 3, 64 - 2 * loss.margin, 64 - 2 * loss.margin)
    only_left = loss.stack(torch.ones(1, 3, 64, 64, dtype=torch.complex64), [0.0],
                           (False, False, True, False))  # fmt: skip
    assert only_left.shape == (1, 1, 3, 64, 64 - loss.margin)


def test_a_whole_view_is_not_masked_so_junk_on_its_border_costs(tiny_data):
    """A crop that is the whole view has no light missing beyond its edges, so nothing may be
    masked there: otherwise the network learns to leave junk on the window's border, and the
    SLM shows it."""
    data = HoloData(tiny_data, splits=("train",))
    optics = Optics.from_manifest(data.manifest)
    loss = FocalStackLoss(optics)
    split = data.splits["train"]
    h, w = split.rgb.shape[-2:]
    *_, edges = random_crop(split, [0], (h, w), np.random.default_rng(0))
    assert edges == (False, False, False, False)
    *_, inner = random_crop(split, [0], (h // 2, w // 2), np.random.default_rng(0))
    assert centre_crop_edges((h, w), (h // 2, w // 2)) == (True, True, True, True)
    assert sum(inner) >= 2  # a half-size crop leaves at least one edge of each axis inside
    target = split.field[:1]
    junk = target.clone()
    peak = float(target.abs().max())
    junk[..., :3, :] = peak  # a bright band on the top border, where the scene has nothing
    planes = uniform_planes(optics.volume_m, 3)
    masked = float(loss(junk, target, planes, [], (True, True, True, True))["l2"])
    whole = float(loss(junk, target, planes, [], edges)["l2"])
    assert whole > 10 * max(masked, 1e-12)


def test_planes_follow_the_depth_histogram():
    rng = np.random.default_rng(0)
    zh = np.full((40, 40), np.nan)
    zh[:, :30] = 1.5e-3
    zh[:, 30:] = -2.0e-3
    picks = [choose_planes(zh, (-3e-3, 3e-3), 4, 0, rng, 1e-4) for _ in range(20)]
    flat = {z for p in picks for z in p}
    assert flat <= {1.5e-3, -2.0e-3}  # only where the content is
    with_random = choose_planes(zh, (-3e-3, 3e-3), 4, 2, rng, 1e-4)
    assert all(-3e-3 <= z <= 3e-3 for z in with_random)
    assert all(abs(z / 1e-4 - round(z / 1e-4)) < 1e-6 for z in with_random)  # on the cache grid
    empty = choose_planes(np.full((8, 8), np.nan), (-3e-3, 3e-3), 3, 0, rng, 1e-4)
    assert len(empty) >= 1


def test_box_ssim_is_one_for_identical_images_and_lower_otherwise():
    x = torch.rand(2, 32, 32)
    assert float(box_ssim(x, x)) == pytest_approx(1.0)
    assert float(box_ssim(x, torch.rand(2, 32, 32))) < 0.5


def pytest_approx(v):
    import pytest

    return pytest.approx(v, abs=1e-5)


def test_vgg_term_loads_only_a_local_file(tiny_data, tmp_path):
    import pytest

    from nhfd.models.vgg import VGGFeatures

    optics = Optics.from_manifest(HoloData(tiny_data, splits=("train",)).manifest)
    with pytest.raises(FileNotFoundError, match="nothing is downloaded"):
        FocalStackLoss(optics, perceptual="vgg", vgg_weights=str(tmp_path / "none.pth"))
    path = tmp_path / "vgg16.pth"
    torch.save({k: v for k, v in VGGFeatures().state_dict().items()
                if k.startswith("features.")}, path)  # fmt: skip
    loss = FocalStackLoss(optics, perceptual="vgg", vgg_weights=str(path))
    assert "VGG-16" in loss.describe()
    target = torch.rand(1, 3, 64, 64).to(torch.complex64)
    out = loss(target * 0.5, target, [0.0, 1e-3], [0, 1])
    assert torch.isfinite(out["loss"]) and float(out["perceptual"]) > 0
