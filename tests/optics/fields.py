"""Test fields with known properties."""

from __future__ import annotations

import torch

from nhfd.optics import Aperture
from nhfd.optics.aperture import apply_aperture


def band_limited(shape: tuple[int, ...], cutoff_per_px: float, dtype=torch.complex128):
    """Random complex field band-limited (square) to `cutoff_per_px`, max |U| = 1."""
    v = torch.randn(shape, dtype=torch.complex128)
    v = apply_aperture(v, Aperture("square", (cutoff_per_px,)))
    return (v / v.abs().max()).to(dtype)


def envelope(h: int, w: int, radius: float = 0.45) -> torch.Tensor:
    """Smooth super-Gaussian support in the centre of an h x w grid (radius as a fraction of
    the half size): content compact inside the window, smooth at the pixel scale."""
    y = torch.linspace(-1, 1, h, dtype=torch.float64)[:, None]
    x = torch.linspace(-1, 1, w, dtype=torch.float64)[None, :]
    return torch.exp(-(((y**2 + x**2) / radius**2) ** 3))


def gaussian_beam(n: int, waist_px: float, pitch_m: float, tilt_per_px: float = 0.0):
    """Gaussian beam amplitude exp(-r^2 / w0^2) with an optional linear phase (tilt) along x."""
    c = (torch.arange(n, dtype=torch.float64) - n / 2)[None, :]
    r2 = c**2 + c.T**2
    u = torch.exp(-r2 / waist_px**2) * torch.exp(2j * torch.pi * tilt_per_px * c)
    return u[None].to(torch.complex128)
