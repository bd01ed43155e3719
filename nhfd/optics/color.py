"""sRGB <-> linear intensity (IEC 61966-2-1). Holograms encode linear intensity; rendered splat
colours are sRGB-encoded, and pictures for people are converted back."""

from __future__ import annotations

import torch

# The sRGB transfer function: linear segment below the knee, offset power law above it.
KNEE_SRGB = 0.04045
KNEE_LINEAR = 0.0031308
SLOPE = 12.92
OFFSET = 0.055
GAMMA = 2.4


def srgb_to_linear(srgb: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded values (any shape, clamped to [0, 1]) to linear intensity in [0, 1]."""
    x = srgb.clamp(0.0, 1.0)
    return torch.where(x <= KNEE_SRGB, x / SLOPE, ((x + OFFSET) / (1 + OFFSET)) ** GAMMA)


def srgb_to_amplitude(srgb: torch.Tensor) -> torch.Tensor:
    """`sqrt(srgb_to_linear(x))`, fused: the power is GAMMA / 2 and the square root is taken only
    on the linear segment. NaN becomes 0. It runs once per light-field view and pixel, where the
    unfused form cost about five times as much."""
    x = torch.nan_to_num(srgb.float(), nan=0.0).clamp_(0.0, 1.0)
    hi = x.add(OFFSET).mul_(1.0 / (1 + OFFSET)).pow_(GAMMA / 2)
    return torch.where(x <= KNEE_SRGB, x.mul(1.0 / SLOPE).sqrt_(), hi)


def linear_to_srgb(linear: torch.Tensor) -> torch.Tensor:
    """Linear intensity (any shape, clamped to [0, 1]) to sRGB-encoded values in [0, 1]."""
    x = linear.clamp(0.0, 1.0)
    return torch.where(
        x <= KNEE_LINEAR, x * SLOPE, (1 + OFFSET) * x.clamp(min=1e-12) ** (1 / GAMMA) - OFFSET
    )
