"""How much to zero-pad before an angular-spectrum propagation.

A propagation by z is a convolution whose kernel reaches `s = |z| tan(theta) / p` pixels for the
widest angle theta the field carries (after the aperture and the band limit). On a periodic FFT
grid of length `Npad`, an output sample inside the original `N` samples is free of wrap-around
exactly when `Npad >= N + s`: the padding only has to hold one kernel reach, not two. The band
limit caps the reach at `Npad / 2`, so `Npad = 2N` (the "2x" policy) is always enough; "auto"
takes the least of the two, rounded up to a 5-smooth FFT size.

That is enough against wrap-around, not for the aperture: a field that fills the aperture's band
on its own grid spills over the cutoff once zero-padded, and each padded grid cuts a different
share of the spill (README, "Padding accuracy": `auto` 3.5% and `2x` 1% from 4x).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from nhfd.optics import _validate
from nhfd.optics.aperture import Aperture

Policy = Literal["none", "2x", "auto"]
POLICIES: tuple[str, ...] = ("none", "2x", "auto")

# Pixels added to the geometric reach: the kernel's band-limited tails extend a little beyond it.
GUARD_PX = 8


@dataclass(frozen=True)
class PaddingPlan:
    """The padded FFT shape for an `H x W` field, and the kernel reach it was sized for."""

    policy: str
    shape_hw: tuple[int, int]
    padded_hw: tuple[int, int]
    reach_px: tuple[int, int]

    def describe(self) -> str:
        """The plan in words: policy, `H x W -> Hp x Wp` and the kernel reach (px)."""
        (h, w), (hp, wp) = self.shape_hw, self.padded_hw
        return (
            f"padding {self.policy}: {h} x {w} -> {hp} x {wp} "
            f"(kernel reach {self.reach_px[0]} x {self.reach_px[1]} px)"
        )


def next_fast_len(n: int) -> int:
    """Smallest 5-smooth integer >= n (fast on pocketfft and cuFFT alike)."""
    n = max(1, int(n))
    best = 2 ** math.ceil(math.log2(n))
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best


def kernel_reach_px(
    z_m: float,
    pitch_m: float,
    wavelength_m: float,
    fx_per_px: float,
    fy_per_px: float,
) -> float:
    """How far (pixels, along x) light at frequency (fx, fy) cycles/pixel travels over |z|."""
    lx, ly = wavelength_m * fx_per_px / pitch_m, wavelength_m * fy_per_px / pitch_m
    cos2 = 1.0 - lx * lx - ly * ly
    if cos2 <= 1e-12:
        return math.inf
    return abs(z_m) * lx / math.sqrt(cos2) / pitch_m


def plan_padding(
    shape_hw: tuple[int, int],
    pitch_m: float,
    wavelengths_m: tuple[float, ...],
    max_abs_z_m: float,
    aperture: Aperture | None,
    policy: Policy | tuple[int, int] = "auto",
) -> PaddingPlan:
    """Choose the padded shape for propagating an `H x W` field by up to `max_abs_z_m`.

    `policy` is "none", "2x", "auto", or an explicit `(Hpad, Wpad)` (each >= the field's size).
    """
    h, w = _validate.shape_hw("shape_hw", shape_hw)
    pitch = _validate.pitch("pitch_m", pitch_m)
    z = abs(_validate.distance("z_m", max_abs_z_m))
    reach = [0, 0]
    n_col = len(wavelengths_m)
    for c, lam in enumerate(wavelengths_m):
        if aperture is None:
            fx, fy = 0.5, 0.5
        else:
            fx, fy = aperture.widest_frequency_per_px(c, n_col)
        # The square's corner is the widest along both axes; circle and diamond are symmetric.
        r = kernel_reach_px(z, pitch, lam, fx, fy)
        r = r if math.isfinite(r) else float(2 * max(h, w))
        reach = [max(reach[0], math.ceil(r)), max(reach[1], math.ceil(r))]
    if isinstance(policy, tuple):
        padded = _validate.shape_hw("padding", policy)
        if padded[0] < h or padded[1] < w:
            raise ValueError(f"padding = {policy}: must be at least the field's size {(h, w)}")
        name = "explicit"
    elif policy == "none":
        padded, name = (h, w), "none"
    elif policy == "2x":
        padded, name = (2 * h, 2 * w), "2x"
    elif policy == "auto":
        name = "auto"
        padded = tuple(
            n if r == 0 else min(next_fast_len(n + r + GUARD_PX), next_fast_len(2 * n))
            for n, r in zip((h, w), reach, strict=True)
        )
    else:
        raise ValueError(f"padding = {policy!r}: must be one of {POLICIES} or (Hpad, Wpad)")
    return PaddingPlan(name, (h, w), (int(padded[0]), int(padded[1])), (reach[0], reach[1]))
