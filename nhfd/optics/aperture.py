"""The Fourier aperture: the band the display can show (docs/physics.md, "The Fourier
aperture").

One model is used everywhere (light-field directions, targets, the training loss, evaluation, the
runtime and the simulated camera). Cutoffs are per colour in cycles per pixel (`f_cut * pitch`),
so the same aperture object serves any pitch.

Conventions, on the `fftfreq` grid of whatever array is filtered (k = integer bin, N = length):
- square:  -c <= k/N < c on both axes (half-open, as an fftfreq grid is; docs/physics.md);
- circle:  (kx/Nx)^2 + (ky/Ny)^2 < c^2;
- diamond: |kx/Nx| + |ky/Ny| < 2c (same area as the square; c = 1/4 gives docs/physics.md's
  diamond).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

from nhfd.optics import _validate, fft

Shape = Literal["square", "circle", "diamond"]
SHAPES: tuple[str, ...] = ("square", "circle", "diamond")


@dataclass(frozen=True)
class Aperture:
    """Fourier aperture of the 4f relay. `cutoff_per_px[c]` is `f_cut * pitch` for colour c, in
    (0, 0.5]; a single value applies to every colour."""

    shape: Shape = "square"
    cutoff_per_px: tuple[float, ...] = (0.25, 0.25, 0.25)

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise ValueError(f"aperture shape = {self.shape!r}: must be one of {SHAPES}")
        cut = tuple(float(c) for c in self.cutoff_per_px)
        if not cut:
            raise ValueError("aperture cutoff_per_px is empty: give one cutoff per colour")
        for i, c in enumerate(cut):
            if not (math.isfinite(c) and 0 < c <= 0.5):
                raise ValueError(
                    f"aperture cutoff_per_px[{i}] = {c!r}: must be in (0, 0.5] cycles per pixel"
                )
        object.__setattr__(self, "cutoff_per_px", cut)

    def cutoffs(self, n_colours: int) -> tuple[float, ...]:
        """Cutoff per colour channel in cycles per pixel, broadcasting a single value."""
        if len(self.cutoff_per_px) == 1:
            return self.cutoff_per_px * n_colours
        if len(self.cutoff_per_px) != n_colours:
            raise ValueError(
                f"aperture has {len(self.cutoff_per_px)} cutoffs for {n_colours} colour channels"
            )
        return self.cutoff_per_px

    def half_depth_of_field_m(
        self, colour: int, n_colours: int, wavelength_m: float, pitch_m: float
    ) -> float:
        """Half the depth of field of the filtered system for one colour, `1 / (4 lambda
        f_cut^2)` with `f_cut = cutoff / pitch` (docs/physics.md, "The Fourier aperture":
        `lambda / (2 NA^2)` with `NA = lambda f_cut`; `4 p^2 / lambda` at the default half-band
        cutoff): the focus test's tolerance."""
        _validate.wavelength("wavelength_m", wavelength_m)
        f_cut = self.cutoffs(n_colours)[colour] / _validate.pitch("pitch_m", pitch_m)
        return 1.0 / (4.0 * wavelength_m * f_cut * f_cut)

    def widest_frequency_per_px(self, colour: int, n_colours: int) -> tuple[float, float]:
        """The passband point (fx, fy), in cycles per pixel, with the largest x tilt: the one that
        spreads a point furthest along x (used to size padding and window margins)."""
        c = self.cutoffs(n_colours)[colour]
        if self.shape == "square":
            return (min(c, 0.5), min(c, 0.5))
        if self.shape == "circle":
            return (min(c, 0.5), 0.0)
        return (min(2 * c, 0.5), 0.0)


def frequency_indices(n: int, device: torch.device | str | None = None) -> torch.Tensor:
    """Integer `fftfreq` bins k (as float64) for an axis of n samples: 0, 1, ..., -1."""
    return torch.fft.fftfreq(n, d=1.0 / n, dtype=torch.float64, device=device).round()


def aperture_mask(
    shape_hw: tuple[int, int],
    aperture: Aperture,
    n_colours: int,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Boolean pass mask `[C, H, W]` on the unshifted `fftfreq` grid of an `H x W` array."""
    h, w = _validate.shape_hw("shape_hw", shape_hw)
    fy = (frequency_indices(h, device) / h)[:, None]
    fx = (frequency_indices(w, device) / w)[None, :]
    masks = []
    for c in aperture.cutoffs(n_colours):
        if aperture.shape == "square":
            m = (fx >= -c) & (fx < c) & (fy >= -c) & (fy < c)
        elif aperture.shape == "circle":
            m = fx**2 + fy**2 < c**2
        else:
            m = fx.abs() + fy.abs() < 2 * c
        masks.append(m)
    return torch.stack(masks)


def apply_aperture(field: torch.Tensor, aperture: Aperture) -> torch.Tensor:
    """Filter a field `[..., C, H, W]` by the aperture (the 4f relay's iris), same shape/dtype.

    The filter is applied on the array's own periodic grid: pad first if content near one edge
    must not leak to the other.
    """
    u = _validate.field("field", field)
    mask = aperture_mask(tuple(u.shape[-2:]), aperture, u.shape[-3], u.device)
    return fft.ifft2(fft.fft2(u) * mask)
