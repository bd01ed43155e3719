"""The inverse STFT against a direct per-hogel implementation, and its building blocks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nhfd.holo import (
    InverseSTFT,
    hann_window,
    patch_offsets,
    sec_minus_one,
    srgb_amplitude,
    view_spectrum,
)
from nhfd.optics import srgb_to_linear


def direct_istft(spectra: np.ndarray, window: int, k_x: np.ndarray, k_y: np.ndarray) -> np.ndarray:
    """docs/physics.md literally: per hogel, the W x W spectrum (zero outside the given bins) is
    inverse-DFT'd (no 1/W^2) into a patch over offsets -W/2..W/2-1, Hann-windowed, overlap-added
    with hop 1, and normalised by the window sum. `spectra` [Ky, Kx, H, W] complex."""
    _, _, h, w = spectra.shape
    win = hann_window(window)
    win2 = win[:, None] * win[None, :]
    off = patch_offsets(window)
    out = np.zeros((h, w), np.complex128)
    for y in range(h):
        for x in range(w):
            spec = np.zeros((window, window), np.complex128)
            for iy, ky in enumerate(k_y):
                for ix, kx in enumerate(k_x):
                    spec[ky % window, kx % window] = spectra[iy, ix, y, x]
            full = np.fft.ifft2(spec) * window * window
            patch = full[np.ix_(off % window, off % window)] * win2
            for my, ny in enumerate(off):
                for mx, nx in enumerate(off):
                    yy, xx = y + ny, x + nx
                    if 0 <= yy < h and 0 <= xx < w:
                        out[yy, xx] += patch[my, mx]
    return out / win.sum() ** 2


@pytest.mark.parametrize(("window", "k"), [(6, [-1, 0, 1]), (8, [-2, -1, 0, 1]), (4, [-2, 1])])
def test_matches_direct_per_hogel_implementation(window: int, k: list[int]) -> None:
    rng = np.random.default_rng(window)
    h, w = 11, 13
    kk = np.array(k)
    spectra = rng.normal(size=(len(k), len(k), h, w)) + 1j * rng.normal(size=(len(k), len(k), h, w))
    ref = direct_istft(spectra, window, kk, kk)
    inv = InverseSTFT((h, w), window, kk, kk)
    # Any order of arrival gives the same field.
    order = [(iy, ix) for iy in range(len(k)) for ix in range(len(k))]
    for j in rng.permutation(len(order)):
        iy, ix = order[j]
        inv.add(iy, ix, torch.from_numpy(spectra[iy, ix]).to(torch.complex64))
    got = inv.result().numpy()
    assert got.dtype == np.complex64
    err = np.linalg.norm(got - ref) / np.linalg.norm(ref)
    assert err < 1e-5, err
    assert np.abs(got - ref).max() < 1e-5 * np.abs(ref).max()


def test_different_bins_per_axis_and_missing_views() -> None:
    rng = np.random.default_rng(3)
    h, w, window = 9, 10, 6
    kx, ky = np.array([-2, 0, 2]), np.array([-1, 1])
    spectra = rng.normal(size=(2, 3, h, w)) + 1j * rng.normal(size=(2, 3, h, w))
    spectra[1, 2] = 0  # a view never added counts as zero
    inv = InverseSTFT((h, w), window, kx, ky)
    for iy in range(2):
        for ix in range(3):
            if (iy, ix) != (1, 2):
                inv.add(iy, ix, torch.from_numpy(spectra[iy, ix]))
    ref = direct_istft(spectra, window, kx, ky)
    assert np.abs(inv.result().numpy() - ref).max() < 1e-5 * np.abs(ref).max()


def test_rejects_bad_input() -> None:
    inv = InverseSTFT((4, 5), 4, [0, 1], [0, 1])
    with pytest.raises(ValueError, match="shape"):
        inv.add(0, 0, torch.zeros(5, 4, dtype=torch.complex64))
    with pytest.raises(ValueError, match="outside"):
        inv.add(2, 0, torch.zeros(4, 5, dtype=torch.complex64))
    inv.add(0, 0, torch.zeros(4, 5, dtype=torch.complex64))
    with pytest.raises(ValueError, match="already"):
        inv.add(0, 0, torch.zeros(4, 5, dtype=torch.complex64))
    with pytest.raises(ValueError, match="even"):
        InverseSTFT((4, 5), 5, [0], [0])


def test_point_at_reference_plane_is_a_centred_spot() -> None:
    """All views see the point at the same pixel (z_h = 0), zero phase: the field is a spot
    there, symmetric but for the window's half-pixel offset."""
    h = w = 33
    window, k = 8, np.arange(-2, 2)
    inv = InverseSTFT((h, w), window, k, k)
    s = torch.zeros(h, w, dtype=torch.complex64)
    s[16, 16] = 1.0
    for iy in range(len(k)):
        for ix in range(len(k)):
            inv.add(iy, ix, s)
    a = inv.result().abs().numpy()
    assert np.unravel_index(a.argmax(), a.shape) in {(16, 16), (15, 15), (15, 16), (16, 15)}
    assert a[a > 0.05 * a.max()].size <= window * window


def test_hann_window_has_no_zero_end_points() -> None:
    for window in (2, 12, 16):
        win = hann_window(window)
        assert win.min() > 0
        np.testing.assert_allclose(win, win[::-1], atol=1e-15)
        assert win.max() <= 1.0
    np.testing.assert_array_equal(patch_offsets(6), [-3, -2, -1, 0, 1, 2])


def test_srgb_amplitude_matches_optics() -> None:
    x = torch.cat([torch.linspace(-0.5, 1.5, 20001), torch.tensor([0.04045, 0.0, 1.0, 7.0])])
    np.testing.assert_allclose(
        srgb_amplitude(x).numpy(), srgb_to_linear(x).sqrt().numpy(), rtol=2e-6, atol=1e-7
    )
    assert srgb_amplitude(torch.tensor([float("nan")])).item() == 0.0
    s = view_spectrum(np.full((2, 3), 1.0, np.float32), torch.full((2, 3), math.pi / 2))
    np.testing.assert_allclose(s.numpy(), 1j * np.ones((2, 3)), atol=1e-6)


def test_sec_minus_one() -> None:
    for tx, ty in [(0.0, 0.0), (1e-4, 0.0), (0.02, -0.015), (1.0, 1.0)]:
        exact = math.expm1(0.5 * math.log1p(tx * tx + ty * ty))  # accurate at small angles
        assert sec_minus_one(tx, ty) == pytest.approx(exact, rel=1e-9, abs=1e-300)
    # No cancellation at tiny angles: 1/cos - 1 ~ tau^2 / 2.
    assert sec_minus_one(1e-9, 0.0) == pytest.approx(5e-19, rel=1e-9)
