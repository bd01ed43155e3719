"""sRGB <-> linear intensity (IEC 61966-2-1). Holograms encode linear intensity; rendered splat
colours are sRGB-encoded, and pictures for people are converted back."""

from __future__ import annotations

import torch


def srgb_to_linear(srgb: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded values (any shape, clamped to [0, 1]) to linear intensity in [0, 1]."""
    x = srgb.clamp(0.0, 1.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: torch.Tensor) -> torch.Tensor:
    """Linear intensity (any shape, clamped to [0, 1]) to sRGB-encoded values in [0, 1]."""
    x = linear.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.clamp(min=1e-12) ** (1 / 2.4) - 0.055)
