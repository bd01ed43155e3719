"""The reference plane and the hologram window (docs/physics.md, "The hologram volume and the
scene-to-volume mapping").

The network predicts the field on a reference plane `z0` in front of the SLM, over a centred
window of the panel; outside the window the amplitude is zero. The runtime takes that field to the
SLM plane by propagating `-z0`. Because the aperture bounds the angles, the result is non-zero only
within the window plus the kernel's reach, so propagation runs on that region alone and is then
placed on the panel: exact for what the display can show, and far cheaper than the whole panel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from nhfd.optics import _validate
from nhfd.optics.aperture import Aperture
from nhfd.optics.asm import propagate
from nhfd.optics.cache import KernelCache
from nhfd.optics.padding import GUARD_PX, Policy, kernel_reach_px


def window_offset(panel_hw: tuple[int, int], window_hw: tuple[int, int]) -> tuple[int, int]:
    """Top-left corner (row, col) of a window centred on the panel."""
    (ph, pw), (wh, ww) = _validate.shape_hw("panel_hw", panel_hw), window_hw
    if wh > ph or ww > pw:
        raise ValueError(f"window {window_hw} does not fit the panel {panel_hw}")
    return (ph - wh) // 2, (pw - ww) // 2


def place_window(window: torch.Tensor, panel_hw: tuple[int, int]) -> torch.Tensor:
    """Put a `[..., C, h, w]` field centred on a zero `[..., C, H, W]` panel."""
    h, w = window.shape[-2:]
    top, left = window_offset(panel_hw, (h, w))
    panel = window.new_zeros((*window.shape[:-2], *panel_hw))
    panel[..., top : top + h, left : left + w] = window
    return panel


def crop_window(panel: torch.Tensor, window_hw: tuple[int, int]) -> torch.Tensor:
    """The centred `[..., C, h, w]` window of a `[..., C, H, W]` panel field."""
    top, left = window_offset(tuple(panel.shape[-2:]), window_hw)
    return panel[..., top : top + window_hw[0], left : left + window_hw[1]]


def margin_px(
    z_m: float, pitch_m: float, wavelengths_m: Sequence[float], aperture: Aperture | None
) -> int:
    """How far (pixels) a propagation by `z_m` spreads the field beyond its support."""
    lams = _validate.wavelengths(wavelengths_m)
    reach = 0.0
    for c, lam in enumerate(lams):
        fx, fy = (0.5, 0.5) if aperture is None else aperture.widest_frequency_per_px(c, len(lams))
        reach = max(reach, kernel_reach_px(z_m, pitch_m, lam, fx, fy))
    return math.ceil(reach) + GUARD_PX if math.isfinite(reach) else 10**9


def reference_to_slm(
    window_field: torch.Tensor,
    panel_hw: tuple[int, int],
    z0_m: float,
    pitch_m: float,
    wavelengths_m: Sequence[float],
    *,
    aperture: Aperture | None,
    padding: Policy | tuple[int, int] = "auto",
    cache: KernelCache | None = None,
) -> torch.Tensor:
    """Field `[..., C, h, w]` on the reference plane's window -> field `[..., C, H, W]` on the
    whole SLM panel (propagated by `-z0_m`, filtered by the aperture)."""
    z0 = _validate.positive("z0_m", z0_m)
    h, w = window_field.shape[-2:]
    top, left = window_offset(panel_hw, (h, w))
    m = margin_px(z0, pitch_m, wavelengths_m, aperture)
    # The region the propagated field can reach, clipped to the panel.
    r0, r1 = max(0, top - m), min(panel_hw[0], top + h + m)
    c0, c1 = max(0, left - m), min(panel_hw[1], left + w + m)
    region = window_field.new_zeros((*window_field.shape[:-2], r1 - r0, c1 - c0))
    region = region.to(_validate.field("window_field", window_field).dtype)
    region[..., top - r0 : top - r0 + h, left - c0 : left - c0 + w] = window_field
    moved = propagate(
        region, -z0, pitch_m, wavelengths_m, padding=padding, aperture=aperture, cache=cache
    )
    panel = moved.new_zeros((*moved.shape[:-2], *panel_hw))
    panel[..., r0:r1, c0:c1] = moved
    return panel


def slm_to_reference(
    panel_field: torch.Tensor,
    z0_m: float,
    pitch_m: float,
    wavelengths_m: Sequence[float],
    *,
    aperture: Aperture | None,
    padding: Policy | tuple[int, int] = "auto",
    cache: KernelCache | None = None,
) -> torch.Tensor:
    """Field on the whole SLM panel -> field on the reference plane (whole panel), by `+z0_m`."""
    z0 = _validate.positive("z0_m", z0_m)
    return propagate(
        panel_field, z0, pitch_m, wavelengths_m, padding=padding, aperture=aperture, cache=cache
    )
