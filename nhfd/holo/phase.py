"""Phase heuristics for the light field's rays (docs/physics.md, "Wavefront inversion (inverse
STFT, overlap-add with hop 1)").

- "depth" (default): the phase of the spherical wave converging on the ray's point,
  `Phi = -(2 pi / lambda) z_h (1 / cos(theta) - 1)`, with `z_h` from the view's rendered depth
  through the scene's mapping and `1 / cos(theta) = sqrt(1 + tau_x^2 + tau_y^2)` for the 2-D
  direction. With `propagate`'s convention (positive z toward the viewer, kernel
  `exp(+i 2 pi z sqrt(1/lambda^2 - f^2))`) a wave converging on a point at `z_h > 0` has the
  phase `-k sqrt(r^2 + z_h^2)` on the reference plane: the minus sign above (the constant
  `-k z_h` is dropped). The focus test checks this sign.
- "zero": `Phi = 0` (focuses at the wrong depth except at z_h = 0; for comparison).
- "random": uniform in [0, 2 pi), from a numpy Generator seeded by (seed, colour, iy, ix), so
  results do not depend on the order views arrive in.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch

from nhfd.optics.color import srgb_to_amplitude
from nhfd.scene.lightfield import DepthMapping

PhaseMode = Literal["depth", "zero", "random"]
PHASE_MODES: tuple[str, ...] = ("depth", "zero", "random")

# Hologram depths are clipped to this magnitude (m): depths near the camera (d -> 0) would give
# z_h -> infinity; nothing that far is in any volume, and the clip keeps every phase finite.
Z_H_CLIP_M = 1.0


def sec_minus_one(tau_x: float, tau_y: float) -> float:
    """`1 / cos(theta) - 1` for slopes (tau_x, tau_y), without cancellation at small angles."""
    t2 = float(tau_x) ** 2 + float(tau_y) ** 2
    return t2 / (1.0 + math.sqrt(1.0 + t2))


def as_tensor(a: np.ndarray | torch.Tensor) -> torch.Tensor:
    """float32 tensor view of a numpy array or tensor (no copy when already float32)."""
    t = a if isinstance(a, torch.Tensor) else torch.from_numpy(np.asarray(a))
    return t.to(torch.float32)


def hologram_depth(depth: np.ndarray | torch.Tensor, mapping: DepthMapping) -> torch.Tensor:
    """`z_h` [H, W] float32 (m) of a view's depth map (camera z, scene units): 0 where nothing was
    drawn (depth <= 0 or NaN; the renderer's depth is 0 exactly where alpha is 0, and the
    amplitude there is 0 anyway), clipped to +-Z_H_CLIP_M. float32 is enough: the phase it feeds
    is a few radians, ~1e-6 relative error."""
    d = as_tensor(depth)
    z = d.reciprocal().mul_(mapping.b_m).add_(mapping.a_m)
    z = z.nan_to_num_(nan=0.0, posinf=Z_H_CLIP_M, neginf=-Z_H_CLIP_M)
    z = z.clamp_(-Z_H_CLIP_M, Z_H_CLIP_M)
    return torch.where(d > 0, z, 0.0)


def view_phase(
    mode: PhaseMode,
    shape_hw: tuple[int, int],
    *,
    wavelength_m: float,
    tau_x: float,
    tau_y: float,
    z_h_m: torch.Tensor | None = None,
    seed: int = 0,
    key: tuple[int, int, int] = (0, 0, 0),
) -> torch.Tensor | None:
    """Phase [H, W] float32 (rad) of one view's rays, or None for "zero" (saves the work).

    `z_h_m` ([H, W], m) is needed for "depth"; `seed` and `key` = (colour, iy, ix) for "random".
    """
    if mode == "zero":
        return None
    if mode == "depth":
        if z_h_m is None:
            raise ValueError("depth-aware phase needs the view's hologram depth z_h_m")
        scale = -2.0 * math.pi / wavelength_m * sec_minus_one(tau_x, tau_y)
        return z_h_m * scale
    if mode == "random":
        rng = np.random.default_rng([int(seed), *(int(v) for v in key)])
        return torch.from_numpy(rng.random(shape_hw, dtype=np.float32)) * (2.0 * math.pi)
    raise ValueError(f"phase mode {mode!r}: must be one of {PHASE_MODES}")


def srgb_amplitude(srgb: np.ndarray | torch.Tensor) -> torch.Tensor:
    """`sqrt(srgb_to_linear(x))` float32 of an array or tensor (`nhfd.optics.srgb_to_amplitude`)."""
    return srgb_to_amplitude(as_tensor(srgb))


def view_spectrum(
    srgb: np.ndarray | torch.Tensor,
    phase: torch.Tensor | None,
) -> torch.Tensor:
    """`sqrt(L_lin) exp(i Phi)` [H, W] complex64 of one view's colour channel (sRGB, [H, W]).

    Values above 1 (saturated) and below 0 are clamped as `srgb_to_linear` does; NaN becomes 0."""
    amp = srgb_amplitude(srgb)
    if phase is None:
        return amp.to(torch.complex64)
    return torch.polar(amp, phase)
