"""The focal-stack loss (the paper's Eqs. 8-9) and how its planes are chosen.

Prediction and target fields, both in units of the dataset's amplitude scale, are filtered by the
Fourier aperture and propagated with `nhfd.optics.propagate` (`padding="auto"`, a shared
`KernelCache`) to a few planes of the volume and compared as intensities: an L2 term plus a
perceptual term (a box-window SSIM by default, VGG-16 features as an option) on a couple of those
planes. A crop's propagated edge sees nothing of the content outside the crop, for the prediction
and the target alike; the band that this contaminates (the kernel's reach plus a guard) is left
out of every term.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from nhfd.models.vgg import VGGFeatures
from nhfd.optics import Aperture, KernelCache, aperture_mask, fft, plan_padding, propagate
from nhfd.optics.refplane import margin_px

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
# The SSIM's intensities are divided by this percentile of the target's (one scale per step).
SSIM_PERCENTILE = 0.99


@dataclass(frozen=True)
class Optics:
    """What the loss needs of the bench (SI units), from a dataset manifest."""

    pitch_m: float
    wavelengths_m: tuple[float, ...]
    aperture: Aperture
    volume_m: tuple[float, float]

    @staticmethod
    def from_manifest(manifest: dict) -> Optics:
        """The optics a dataset manifest's `settings` record (pitch, wavelengths and volume in
        m, the aperture)."""
        s = manifest["settings"]
        return Optics(
            pitch_m=float(s["pitch_m"]),
            wavelengths_m=tuple(float(v) for v in s["wavelengths_m"]),
            aperture=Aperture(s["aperture_shape"], tuple(float(c) for c in s["cutoff_per_px"])),
            volume_m=(float(s["volume_m"][0]), float(s["volume_m"][1])),
        )

    def margin_px(self) -> int:
        """Pixels at each crop edge that propagation anywhere in the volume contaminates."""
        z = max(abs(v) for v in self.volume_m)
        return margin_px(z, self.pitch_m, self.wavelengths_m, self.aperture)


def box_ssim(x: torch.Tensor, y: torch.Tensor, window_px: int = 7) -> torch.Tensor:
    """Mean SSIM of `[N, H, W]` images (values around [0, 1]) with a `window_px` box window, no
    padding ("valid"): five average-pools, cheap forward and backward."""
    stack = torch.stack([x, y, x * x, y * y, x * y], dim=1)
    m = F.avg_pool2d(stack, window_px, stride=1)
    mx, my, mxx, myy, mxy = m.unbind(1)
    vx, vy, cov = mxx - mx * mx, myy - my * my, mxy - mx * my
    s = ((2 * mx * my + SSIM_C1) * (2 * cov + SSIM_C2)) / (
        (mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2)
    )
    return s.mean()


def uniform_planes(volume_m: tuple[float, float], n: int) -> list[float]:
    """`n` evenly spaced planes from z_min to z_max (the middle one when n = 1)."""
    lo, hi = volume_m
    if n <= 1:
        return [0.5 * (lo + hi)]
    return [lo + (hi - lo) * i / (n - 1) for i in range(n)]


def choose_planes(
    zh_m: np.ndarray | None,
    volume_m: tuple[float, float],
    n_depth: int,
    n_random: int,
    rng: np.random.Generator,
    step_m: float,
) -> list[float]:
    """Planes for one step: `n_depth` drawn from the histogram of the crop's mapped depth (the
    content pixels' `z_h`: model only where the scene is) and `n_random` uniformly in the volume.

    Rounded to `step_m` so that transfer functions repeat and the kernel cache hits; distinct and
    sorted. A crop without content draws all its planes uniformly.
    """
    lo, hi = volume_m
    values: list[float] = []
    finite = zh_m[np.isfinite(zh_m)] if zh_m is not None else np.zeros(0)
    if finite.size:
        values += list(rng.choice(np.clip(finite, lo, hi), size=n_depth, replace=True))
    else:
        n_random += n_depth
    values += list(rng.uniform(lo, hi, size=n_random))
    grid = sorted({round(round(v / step_m) * step_m, 9) for v in values})
    return [min(hi, max(lo, z)) for z in grid] or [0.5 * (lo + hi)]


def spectral_field_error(
    pred: torch.Tensor,
    target: torch.Tensor,
    aperture: Aperture,
    padded_hw: tuple[int, int],
    crop: tuple[int, int, int, int] = (0, 0, 0, 0),
) -> torch.Tensor:
    """Relative error of complex fields `[B, C, H, W]` on their own plane, inside the aperture,
    each spatial frequency weighted by `|f|^2` (0 at DC): `|g(P - T)|^2 / |g(T)|^2` summed over
    the kept pixels, where `g` filters by `|f|` inside the aperture. A scalar.

    Why weighted: a depth error `dz` of content multiplies its spectrum by
    `exp(i pi lambda dz |f|^2)`, so it lives in the high frequencies, which carry little of the
    field's energy. A plain field L2 barely sees it (measured: relative error 0.03, yet far
    content focused 1.8 mm short); the focal-stack L2 of intensities sees it only through
    defocus blur.

    `padded_hw`: the fields are zero-padded to it before filtering, as propagation pads them
    (the SLM shows nothing beyond its window; `FocalStackLoss.padded_hw`). The field's own size
    would wrap the window, tying each edge to the opposite one, which a network cannot see
    across. `crop` (top, bottom, left,
    right): pixels left out after filtering (the margin at a crop's cut edges)."""
    h, w = pred.shape[-2:]
    ph, pw = padded_hw
    if ph < h or pw < w:
        raise ValueError(f"padded_hw = {padded_hw}: must be at least the field's {(h, w)}")
    fy = torch.fft.fftfreq(ph, device=pred.device)[:, None]
    fx = torch.fft.fftfreq(pw, device=pred.device)[None, :]
    gain = (fx * fx + fy * fy).sqrt() * aperture_mask((ph, pw), aperture, pred.shape[-3],
                                                      pred.device)  # fmt: skip
    top, bottom, left, right = crop

    def filtered_energy(f: torch.Tensor) -> torch.Tensor:
        g = fft.ifft2(fft.fft2(f, s=(ph, pw)) * gain)
        return g[..., top : h - bottom, left : w - right].abs().square().sum()

    with torch.no_grad():
        ref = filtered_energy(target)
    return filtered_energy(pred - target) / ref.clamp(min=1e-30)


class FocalStackLoss:
    """L2 of focal-stack intensities plus a perceptual term, between complex fields.

    Call with `pred` and `target` `[B, C, H, W]` complex (amplitude-scale units), the planes (m)
    and the indices of the planes the perceptual term runs on. Returns a dict of scalar tensors:
    `loss` (what to minimise), `l2`, `perceptual`. With `field_weight` > 0 the loss adds
    `spectral_field_error` of the fields themselves.
    """

    def __init__(
        self,
        optics: Optics,
        *,
        perceptual: str = "ssim",
        perceptual_weight: float = 0.1,
        ssim_window_px: int = 7,
        vgg_weights: str | None = None,
        cache: KernelCache | None = None,
        mask_margin: bool = True,
        field_weight: float = 0.0,
    ) -> None:
        if perceptual not in ("ssim", "vgg", "none"):
            raise ValueError(f"perceptual = {perceptual!r}: must be ssim, vgg or none")
        if not (math.isfinite(field_weight) and field_weight >= 0):
            raise ValueError(f"field_weight = {field_weight!r}: must be a finite number >= 0")
        self.field_weight = float(field_weight)
        self.optics = optics
        self.perceptual = perceptual
        self.weight = float(perceptual_weight)
        self.window = int(ssim_window_px)
        self.cache = cache if cache is not None else KernelCache()
        self.margin = optics.margin_px() if mask_margin else 0
        self.vgg = None
        if perceptual == "vgg":
            if not vgg_weights:
                raise ValueError("perceptual = 'vgg' needs vgg_weights: a local VGG-16 file")
            self.vgg = VGGFeatures.from_file(vgg_weights)

    def describe(self) -> str:
        """The loss's terms and weights in words, for the training log."""
        term = {
            "ssim": f"box-window SSIM ({self.window} px) x {self.weight:g}",
            "vgg": f"VGG-16 features at half resolution x {self.weight:g}",
            "none": "none",
        }[self.perceptual]
        field = (f" + frequency-weighted field error x {self.field_weight:g}"
                 if self.field_weight else "")
        return (f"L2 of intensities + perceptual term: {term}{field}; "
                f"margin masked {self.margin} px on crop edges inside the view")

    def stack(
        self, field: torch.Tensor, planes_m: Sequence[float],
        interior_edges: Sequence[bool] = (True, True, True, True),
    ) -> torch.Tensor:  # fmt: skip
        """Intensities `[B, D, C, H, W]` after the aperture: one batched propagation (one forward
        FFT for all planes) on a padding sized for the whole volume, so every plane's kernel has
        the same shape and is cached on its own whatever the step's set of planes.

        `interior_edges` (top, bottom, left, right): which edges of the field were cut from a
        larger view. Only those are masked by the margin: light from beyond a cut edge is
        missing there, while beyond the view's own edge there is none, so masking it would leave
        the network free to put junk on the window's border (which the SLM would then show)."""
        o = self.optics
        inten = propagate(
            field, [float(z) for z in planes_m], o.pitch_m, o.wavelengths_m,
            padding=self.padded_hw(field), aperture=o.aperture, cache=self.cache,
        ).abs().square()  # fmt: skip
        top, bottom, left, right = self.margin_crop(field, interior_edges)
        h, w = inten.shape[-2:]
        return inten[..., top : h - bottom, left : w - right]

    def padded_hw(self, field: torch.Tensor) -> tuple[int, int]:
        """The padding for the whole volume, whatever planes a step draws."""
        o = self.optics
        z_max = max(abs(v) for v in o.volume_m)
        return plan_padding(tuple(field.shape[-2:]), o.pitch_m, o.wavelengths_m, z_max,
                            o.aperture).padded_hw  # fmt: skip

    def margin_crop(
        self, field: torch.Tensor, interior_edges: Sequence[bool]
    ) -> tuple[int, int, int, int]:
        """(top, bottom, left, right) pixels every term leaves out: the margin at cut edges."""
        m = self.margin
        h, w = field.shape[-2:]
        if not (m and h > 2 * m + 2 and w > 2 * m + 2):
            return (0, 0, 0, 0)
        top, bottom, left, right = (m if e else 0 for e in interior_edges)
        return top, bottom, left, right

    def __call__(
        self,
        pred: torch.Tensor,
        target: torch.Tensor,
        planes_m: Sequence[float],
        perceptual_planes: Sequence[int] = (),
        interior_edges: Sequence[bool] = (True, True, True, True),
    ) -> dict[str, torch.Tensor]:
        """The loss of `pred` against `target` ([B, C, H, W] complex) on `planes_m` (m): scalar
        tensors `loss`, `l2`, `perceptual`. ValueError when the shapes differ."""
        if pred.shape != target.shape:
            raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} differ")
        ip = self.stack(pred, planes_m, interior_edges)
        with torch.no_grad():
            it = self.stack(target, planes_m, interior_edges)
        l2 = (ip - it).square().mean()
        zero = l2.new_zeros(())
        perc = zero
        idx = [i for i in perceptual_planes if 0 <= i < len(planes_m)]
        if self.perceptual != "none" and idx and self.weight > 0:
            p, t = ip[:, idx], it[:, idx]  # [B, k, C, H, W]
            # One scale per step from the target: SSIM's constants assume values around [0, 1].
            flat = t.detach().flatten()
            sample = flat[:: max(1, flat.numel() // 200_000)]
            scale = torch.quantile(sample, SSIM_PERCENTILE).clamp(min=1e-8)
            p, t = p / scale, t / scale
            if self.perceptual == "ssim":
                win = min(self.window, *p.shape[-2:])
                perc = 1.0 - box_ssim(p.flatten(0, 2), t.flatten(0, 2), win)
            else:
                assert self.vgg is not None
                perc = self.vgg.distance(p.flatten(0, 1), t.flatten(0, 1))
        loss = l2 + self.weight * perc
        if self.field_weight:
            loss = loss + self.field_weight * spectral_field_error(
                pred, target, self.optics.aperture, self.padded_hw(pred),
                self.margin_crop(pred, interior_edges))
        return {"loss": loss, "l2": l2, "perceptual": perc}


def psnr_from_l2(l2: float, peak: float) -> float:
    """PSNR (dB) of an intensity L2 given the target's peak intensity (a rough validation
    figure; docs/physics.md's measure is `nhfd.optics.focal_stack_quality`)."""
    return 10 * math.log10(max(peak, 1e-30) ** 2 / max(l2, 1e-30))
