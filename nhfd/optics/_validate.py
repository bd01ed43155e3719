"""Checks of physical parameters shared by the optics functions.

Invalid physics is a ValueError that names the parameter, the value and why; it is raised before
any tensor work so no NaN ever leaves this package.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import torch


def positive(name: str, value: float) -> float:
    v = float(value)
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} = {value!r}: must be a finite number > 0")
    return v


def finite(name: str, value: float) -> float:
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} = {value!r}: must be finite")
    return v


def wavelengths(values: float | Iterable[float], n_colours: int | None = None) -> tuple[float, ...]:
    """Wavelengths in metres as a tuple, one per colour channel (a single value broadcasts)."""
    seq = (values,) if isinstance(values, int | float) else tuple(values)
    if not seq:
        raise ValueError("wavelengths_m is empty: give one wavelength per colour channel")
    out = tuple(positive(f"wavelengths_m[{i}]", w) for i, w in enumerate(seq))
    if n_colours is not None and len(out) not in (1, n_colours):
        raise ValueError(
            f"wavelengths_m has {len(out)} values for {n_colours} colour channels: "
            f"give one per channel (or one for all)"
        )
    if n_colours is not None and len(out) == 1:
        out = out * n_colours
    return out


def shape_hw(name: str, shape: Sequence[int]) -> tuple[int, int]:
    if len(shape) != 2 or any(int(s) != s or s < 1 for s in shape):
        raise ValueError(f"{name} = {tuple(shape)}: must be two integers >= 1 (height, width)")
    return int(shape[0]), int(shape[1])


def field(name: str, tensor: torch.Tensor, min_dims: int = 3) -> torch.Tensor:
    """A field as complex64/complex128 `[..., C, H, W]`; real and half-precision inputs upcast."""
    if not isinstance(tensor, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
    if tensor.dim() < min_dims or any(s < 1 for s in tensor.shape[-2:]):
        raise ValueError(
            f"{name} has shape {tuple(tensor.shape)}: expected [..., C, H, W] with H, W >= 1"
        )
    if tensor.dtype in (torch.complex128, torch.float64):
        return tensor.to(torch.complex128)
    return tensor.to(torch.complex64)
