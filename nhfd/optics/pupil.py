"""The relay's pupil phase: Zernike aberrations on the Fourier plane (docs/physics.md,
"The bench, the camera and calibration").

A calibration fits the relay's aberrations as Zernike coefficients (`nhfd.calib.bench_model`);
the frame pipeline's propagation kernels carry their conjugate (`nhfd.optics.region`), and the
bench models (the calibration's, refinement's) apply them with `apply_pupil`. Both take
the phase from here, on the `fftfreq` grid the angular spectrum method uses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

# Zernike terms of the pupil phase: Noll j = 5 (oblique astigmatism) to 11 (primary spherical).
# Piston is invisible, tilt is the geometry's shift, defocus the depth offsets.
FIRST_NOLL = 5
N_ZERNIKE = 7


def zernike(j: int, rho: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Zernike polynomial, Noll index j in 5..11 (RMS 1 over the unit disk; even j cos, odd j
    sin), written out: the twin (`nhfd.drivers.simcamera`) has its own general form."""
    r2 = rho * rho
    if j == 5:
        return math.sqrt(6) * r2 * torch.sin(2 * theta)
    if j == 6:
        return math.sqrt(6) * r2 * torch.cos(2 * theta)
    if j == 7:
        return math.sqrt(8) * (3 * r2 - 2) * rho * torch.sin(theta)
    if j == 8:
        return math.sqrt(8) * (3 * r2 - 2) * rho * torch.cos(theta)
    if j == 9:
        return math.sqrt(8) * r2 * rho * torch.sin(3 * theta)
    if j == 10:
        return math.sqrt(8) * r2 * rho * torch.cos(3 * theta)
    if j == 11:
        return math.sqrt(5) * (6 * r2 * r2 - 6 * r2 + 1)
    raise ValueError(f"Noll index {j}: only {FIRST_NOLL}..{FIRST_NOLL + N_ZERNIKE - 1}")


def pupil_phase(hw: tuple[int, int], cutoff_per_px: float, zernike_rad: tuple[float, ...],
                scale: float = 1.0, device: torch.device | str | None = None) -> torch.Tensor:
    """The relay's pupil phase [H, W] (float64 radians) on the fftfreq grid of an H x W field
    of SLM pixels: `scale * sum_k a_k Z_{5+k}(rho, theta)`, rho = |f| / cutoff (f in cycles per
    pixel; the square iris's corners reach sqrt 2), theta from +x (columns) toward +y (rows).
    `scale` = lambda_ref / lambda converts coefficients given at lambda_ref to a colour."""
    fy = torch.fft.fftfreq(hw[0], dtype=torch.float64, device=device)[:, None]
    fx = torch.fft.fftfreq(hw[1], dtype=torch.float64, device=device)[None, :]
    rho = torch.sqrt(fx**2 + fy**2) / cutoff_per_px
    theta = torch.atan2(fy.expand_as(rho), fx.expand_as(rho))
    out = torch.zeros_like(rho)
    for k, a in enumerate(zernike_rad):
        if a:
            out += a * zernike(FIRST_NOLL + k, rho, theta)
    return out * scale


def pupil_scales(zernike_wavelength_m: float, wavelengths_m: Sequence[float]
                 ) -> tuple[float, ...]:
    """Each colour's `scale` (lambda_ref / lambda) for coefficients given at
    `zernike_wavelength_m`, the middle colour's wavelength when 0: one rule for the encoder's
    precompensating kernels and the bench models that apply the pupil."""
    lam_ref = zernike_wavelength_m or wavelengths_m[len(wavelengths_m) // 2]
    return tuple(lam_ref / lam for lam in wavelengths_m)


def pupil_transfer(field_hw: tuple[int, int], cutoff_per_px: float,
                   zernike_rad: tuple[float, ...], scale: float = 1.0,
                   device: torch.device | str | None = None) -> torch.Tensor:
    """exp(i pupil_phase) `[2H, 2W]` complex64 for an H x W field: what `apply_pupil`
    multiplies the field's 2x-padded spectrum by (complex64: the phase is exact to 1e-7 rad, and
    at 1920 x 1080 three colours' transfers take 230 MB rather than 460)."""
    ph = pupil_phase((2 * field_hw[0], 2 * field_hw[1]), cutoff_per_px, zernike_rad, scale,
                     device)
    return torch.polar(torch.ones_like(ph), ph).to(torch.complex64)


def apply_pupil(field: torch.Tensor, cutoff_per_px: float, zernike_rad: tuple[float, ...],
                scale: float = 1.0, transfer: torch.Tensor | None = None) -> torch.Tensor:
    """A field [..., H, W] through the pupil phase, zero-padded 2x so that the aberrated
    spread does not wrap around the panel (a spectral product: it commutes with the ASM), on
    the field's device. `transfer`: `pupil_transfer` of these arguments, kept by a caller that
    applies the same pupil every step (refinement: evaluating the Zernike terms each step cost
    as much as the FFTs)."""
    if not any(zernike_rad):
        return field
    h, w = field.shape[-2:]
    if transfer is None:
        transfer = pupil_transfer((h, w), cutoff_per_px, zernike_rad, scale, field.device)
    if tuple(transfer.shape) != (2 * h, 2 * w):
        raise ValueError(f"pupil transfer {tuple(transfer.shape)}: expected [{2 * h}, {2 * w}] "
                         f"for a field of {h} x {w}")
    spec = torch.fft.fft2(field.to(torch.complex128), s=(2 * h, 2 * w))
    return torch.fft.ifft2(spec * transfer)[..., :h, :w].to(field.dtype)
