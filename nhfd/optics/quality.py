"""Hologram quality as docs/physics.md defines it ("Measuring hologram quality").

Focal stacks are compared in linear intensity after the aperture, on a fixed set of planes, inside
a mask of the scene's pixels, with prediction and target normalised by the same robust percentile
of the target (one scale for all planes and colours, so colour balance counts). The baselines, an
all-black prediction and the 2D hologram, go through the very same function.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from nhfd.optics import _validate
from nhfd.optics.aperture import Aperture
from nhfd.optics.asm import propagate
from nhfd.optics.cache import KernelCache
from nhfd.optics.color import srgb_to_linear
from nhfd.optics.padding import Policy

# PSNR of identical stacks would be infinite; report this ceiling instead (never Inf).
PSNR_CEILING_DB = 120.0
SSIM_WINDOW_PX = 11
SSIM_SIGMA_PX = 1.5


@dataclass(frozen=True)
class Quality:
    """Focal-stack PSNR (dB) and SSIM, overall and per plane (`[D]`)."""

    psnr_db: float
    ssim: float
    planes_m: tuple[float, ...]
    psnr_per_plane_db: tuple[float, ...]
    ssim_per_plane: tuple[float, ...]


def quality_planes(volume_m: tuple[float, float], n: int = 5) -> tuple[float, ...]:
    """The fixed evaluation planes: `n` evenly from z_min to z_max, plus the reference plane 0."""
    z_min, z_max = (_validate.finite("volume_m", v) for v in volume_m)
    if not z_min < z_max or n < 2:
        raise ValueError(f"volume_m = {volume_m}, n = {n}: need z_min < z_max and n >= 2")
    planes = {round(z_min + (z_max - z_min) * i / (n - 1), 12) for i in range(n)} | {0.0}
    return tuple(sorted(planes))


def focal_stack(
    field: torch.Tensor,
    planes_m: Sequence[float],
    pitch_m: float,
    wavelengths_m: Sequence[float],
    aperture: Aperture | None,
    *,
    padding: Policy | tuple[int, int] = "auto",
    cache: KernelCache | None = None,
) -> torch.Tensor:
    """Linear intensity `[..., D, C, H, W]` of `field` `[..., C, H, W]` seen through the aperture
    at each plane."""
    stack = propagate(
        field, list(planes_m), pitch_m, wavelengths_m,
        padding=padding, aperture=aperture, cache=cache,
    )
    return stack.abs().square()


def hologram_2d(view_srgb: torch.Tensor, like: torch.Tensor | None = None,
                mask: torch.Tensor | None = None) -> torch.Tensor:
    """The "2D hologram" baseline: `sqrt` of the view's linear intensity with zero phase,
    `[..., C, H, W]` sRGB in [0, 1] -> complex64.

    `like`: a target field `[..., C, H, W]`; the baseline is then scaled to the target's energy
    (inside `mask` [H, W] if given), one factor for all colours. Without it the baseline is in
    sRGB-linear amplitude units, which differ from a hologram's by the inversion's gain (about
    3.4x on the donut dataset): its focal stack would be dark and its PSNR unfairly low (6.8 dB
    instead of 21 dB there)."""
    flat = torch.sqrt(srgb_to_linear(view_srgb.float())).to(torch.complex64)
    if like is None:
        return flat
    sel = (lambda t: t[..., mask]) if mask is not None else (lambda t: t)
    want = sel(like.abs().square()).sum()
    have = sel(flat.abs().square()).sum()
    return flat * torch.sqrt(want / have) if have > 0 else flat


def _gaussian_window(like: torch.Tensor) -> torch.Tensor:
    x = torch.arange(SSIM_WINDOW_PX, dtype=like.dtype, device=like.device) - SSIM_WINDOW_PX // 2
    g = torch.exp(-(x**2) / (2 * SSIM_SIGMA_PX**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :])[None, None]


def ssim_map(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """SSIM map of images in [0, 1], `[N, H, W]` -> `[N, H, W]` (Gaussian window 11, sigma 1.5,
    K1 = 0.01, K2 = 0.03; reflect padding keeps the map the images' size), in the images' dtype.
    In float32 the map is within about 3e-4 of the float64 one (the variances are differences of
    nearby moments); `nhfd bench geometry` measures it, and compares with kornia's."""
    c1, c2 = 0.01**2, 0.03**2
    win = _gaussian_window(x)
    pad = SSIM_WINDOW_PX // 2
    stack = torch.stack([x, y, x * x, y * y, x * y], dim=1).reshape(-1, 1, *x.shape[-2:])
    mode = "reflect" if min(x.shape[-2:]) > pad else "replicate"
    padded = F.pad(stack, (pad, pad, pad, pad), mode=mode)
    # Each image its own channel of one depthwise convolution: the same sums as a batch of
    # one-channel images, but CPU torch's depthwise kernel ran it 10x faster (0.03 against
    # 0.3 s for 5 planes x 3 colours x 5 moments at 512 x 288; `nhfd bench geometry`).
    n = padded.shape[0]
    blurred = F.conv2d(padded.reshape(1, n, *padded.shape[-2:]), win.expand(n, 1, -1, -1),
                       groups=n)
    mx, my, mxx, myy, mxy = blurred.reshape(x.shape[0], 5, *x.shape[-2:]).unbind(1)
    vx, vy, cov = mxx - mx * mx, myy - my * my, mxy - mx * my
    return ((2 * mx * my + c1) * (2 * cov + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))


def focal_stack_quality(
    prediction: torch.Tensor,
    target: torch.Tensor,
    *,
    planes_m: Sequence[float],
    pitch_m: float,
    wavelengths_m: Sequence[float],
    aperture: Aperture | None,
    mask: torch.Tensor | None = None,
    percentile: float = 99.5,
    padding: Policy | tuple[int, int] = "auto",
    cache: KernelCache | None = None,
) -> Quality:
    """PSNR and SSIM of the prediction's focal stack against the target's.

    Args:
        prediction, target: complex fields `[C, H, W]` on the same plane (the reference plane).
        planes_m: the fixed planes to compare on (see `quality_planes`).
        mask: `[H, W]` bool, the scene's pixels (None: all pixels).
        percentile: the target intensity percentile (inside the mask, over all planes and
            colours) that both stacks are divided by before clipping to [0, 1].
    """
    if prediction.shape != target.shape or prediction.dim() != 3:
        raise ValueError(
            f"prediction {tuple(prediction.shape)} and target {tuple(target.shape)} must both be "
            "[C, H, W]"
        )
    if not 0 < percentile <= 100:
        raise ValueError(f"percentile = {percentile}: must be in (0, 100]")
    h, w = target.shape[-2:]
    if mask is None:
        mask = torch.ones((h, w), dtype=torch.bool, device=target.device)
    if mask.shape != (h, w) or not mask.any():
        raise ValueError(f"mask must be a non-empty [H, W] = [{h}, {w}] boolean image")
    kw = dict(padding=padding, cache=cache)
    stacks = focal_stack(
        torch.stack([prediction, target]).to(torch.complex64),
        planes_m, pitch_m, wavelengths_m, aperture, **kw,
    )
    return stack_quality(stacks[0], stacks[1], planes_m=planes_m, mask=mask,
                         percentile=percentile)


def _psnr_db(mse: float) -> float:
    return min(PSNR_CEILING_DB, -10 * math.log10(max(mse, 1e-30)))


def colour_gains(seen: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The least-squares gain per colour `[C]` that brings intensities `seen` `[D, C, H, W]` to
    `target` over the `mask` `[H, W]` pixels of every plane: what a camera's exposure and each
    laser's power leave free (never below 0; 1 for a dark colour)."""
    s, t = seen[..., mask].double(), target[..., mask].double()  # [D, C, M]
    num = (s * t).sum(dim=(0, 2))
    den = (s * s).sum(dim=(0, 2))
    return torch.where(den > 0, num.clamp(min=0) / den.clamp(min=1e-300), torch.ones_like(den))


def stack_quality(seen: torch.Tensor, target: torch.Tensor, *, planes_m: Sequence[float],
                  mask: torch.Tensor | None = None, percentile: float = 99.5,
                  fit_gains: bool = False) -> Quality:
    """PSNR and SSIM of a focal stack of intensities `seen` `[D, C, H, W]` (a simulation's, or
    a camera's mapped onto the target's grid) against `target`'s, both divided by the target's
    `percentile` inside `mask` `[H, W]` and clipped to [0, 1]. `fit_gains`: first scale each
    colour of `seen` by `colour_gains` (a camera's images are in arbitrary units)."""
    if seen.shape != target.shape or seen.dim() != 4 or seen.shape[0] != len(planes_m):
        raise ValueError(f"seen {tuple(seen.shape)} and target {tuple(target.shape)} must both "
                         f"be [D, C, H, W] with D = {len(planes_m)} planes")
    h, w = target.shape[-2:]
    if mask is None:
        mask = torch.ones((h, w), dtype=torch.bool, device=target.device)
    if mask.shape != (h, w) or not mask.any():
        raise ValueError(f"mask must be a non-empty [H, W] = [{h}, {w}] boolean image")
    if fit_gains:
        seen = seen * colour_gains(seen, target, mask).to(seen.dtype)[:, None, None]
    inside = target[..., mask]
    scale = torch.quantile(inside.flatten().double()[:16_000_000], percentile / 100).item()
    scale = scale if scale > 0 else 1.0
    p = (seen / scale).clamp(0, 1).float()
    t = (target / scale).clamp(0, 1).float()
    se = ((p - t) ** 2)[..., mask]  # [D, C, M]
    mse_plane = se.mean(dim=(1, 2))
    ssim = ssim_map(p.flatten(0, 1), t.flatten(0, 1)).reshape(p.shape)[..., mask].mean(dim=(1, 2))
    return Quality(
        psnr_db=_psnr_db(float(se.mean())),
        ssim=float(ssim.mean()),
        planes_m=tuple(float(z) for z in planes_m),
        psnr_per_plane_db=tuple(_psnr_db(float(m)) for m in mse_plane),
        ssim_per_plane=tuple(float(s) for s in ssim),
    )


def speckle_contrast(seen: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                     bright: float = 0.25) -> float:
    """Speckle contrast std(r) / mean(r) of r = seen / target over the bright pixels (target at
    least `bright` of its 99.5th percentile, inside `mask` `[H, W]`), pooled over planes and
    colours of `[D, C, H, W]` intensity stacks, after `colour_gains`: 0 for a display that
    shows the target's intensity exactly, about 1 for fully developed speckle."""
    seen = seen.double() * colour_gains(seen, target, mask)[:, None, None]
    t = target.double()
    peak = torch.quantile(t[..., mask].flatten()[:16_000_000], 0.995).item()
    keep = (t >= bright * peak) & mask if peak > 0 else torch.zeros_like(t, dtype=torch.bool)
    if not keep.any():
        raise ValueError("speckle_contrast: the target has no bright pixels inside the mask")
    r = seen[keep] / t[keep]
    return float(r.std() / r.mean().clamp(min=1e-300))
