"""Propagation of a window to the region of the panel around it, reduced to what it needs.

The frame pipeline's step from the reference plane to the SLM (`nhfd.pipeline.encoder`): a
window field `[C, h, w]`, zero outside the window, propagated with the angular spectrum method's
kernels (`nhfd.optics.asm.propagation_kernels`, through a `KernelCache`) to the window plus the
margin the kernel reaches (`[C, Hr, Wr]`), each colour by its own depth, optionally with the
conjugate of the relay's pupil phase (`nhfd.optics.pupil`) folded into its kernel. The same
values as `propagate` of the zero-padded region, to float32 rounding, in a fraction of the
transforms.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from nhfd.optics import fft
from nhfd.optics.aperture import Aperture
from nhfd.optics.asm import propagation_kernels, transfer_function
from nhfd.optics.cache import KernelCache
from nhfd.optics.padding import plan_padding
from nhfd.optics.pupil import pupil_phase, pupil_scales


class RegionPropagator:
    """Colours propagated together (one padded grid, one stacked kernel), and the kernel reduced
    to what the propagation needs: the Fourier aperture (folded into the kernel) passes about a
    quarter of the padded spectrum, so only the rows and columns of frequencies it keeps are
    transformed, multiplied and transformed back.

    The padded field is zero outside the window, so the forward transform runs along rows over
    the window's rows only, then along columns over the kept columns only; the inverse runs along
    columns over the kept columns, then along rows over the region's rows only. The same sums as
    `propagate`'s 2D transforms, less those that multiply exact zeros, with the same kernel
    values: equal to it to float32 rounding (tests/pipeline/test_encoder.py).

    The column transforms run on a transposed copy (`[n, kept columns, Hp]`: along the last
    axis, all colours in one call; along dim -2 torch makes two transposing copies of its own).
    The zero-padded inputs of the four transforms are kept between calls (~50 MB at 1024 x 576)
    and written only where they are not zero: fresh ones cost page faults and zero fills that
    measured more than the column transforms themselves. So not thread-safe."""

    def __init__(self, colours: slice, padded_hw: tuple[int, int], kernel: torch.Tensor,
                 offset: tuple[int, int], region_hw: tuple[int, int]) -> None:
        self.colours = colours
        self.padded_hw = padded_hw
        self.region_hw = region_hw
        self.offset = offset
        self.device = kernel.device
        kept = kernel != 0
        self.row_runs = _runs(kept.any(-1).any(0))
        self.col_runs = _runs(kept.any(-2).any(0))
        cols = torch.tensor([i for a, b in self.col_runs for i in range(a, b)], dtype=torch.long,
                            device=kernel.device)
        reduced = kernel.index_select(-1, cols)
        # Per run of kept rows: the kernel there, kept columns only, transposed: [n, nc, run].
        self.kernels = [reduced[:, a:b].transpose(-1, -2).contiguous() for a, b in self.row_runs]
        self.n_cols = len(cols)
        self._buffers: tuple[torch.Tensor, ...] = ()
        self._window_hw = (0, 0)

    def _scratch(self, n: int, h: int, w: int) -> tuple[torch.Tensor, ...]:
        if not self._buffers or self._window_hw != (h, w) or self._buffers[0].shape[0] != n:
            (hp, wp), (hr, _wr), nc = self.padded_hw, self.region_hw, self.n_cols
            z, d = torch.complex64, self.device
            self._buffers = (torch.zeros((n, h, wp), dtype=z, device=d),
                             torch.zeros((n, nc, hp), dtype=z, device=d),
                             torch.zeros((n, nc, hp), dtype=z, device=d),
                             torch.zeros((n, hr, wp), dtype=z, device=d))
            self._window_hw = (h, w)
        return self._buffers

    def propagate(self, window: torch.Tensor) -> torch.Tensor:
        """Window field `[n, h, w]` -> region field `[n, Hr, Wr]` (a crop of a fresh tensor)."""
        hr, wr = self.region_hw
        r0, c0 = self.offset
        n, h, w = window.shape
        if not self.col_runs or not self.row_runs:  # the kernel passes nothing
            return torch.zeros((n, hr, wr), dtype=torch.complex64, device=self.device)
        padded, columns, spectrum, back_rows = self._scratch(n, h, w)
        # Forward along rows: the window's rows, zero-padded to Wp.
        padded[..., c0 : c0 + w] = window
        rows = fft.fft(padded, dim=-1)
        # Along columns: the kept columns, transposed, at the window's rows of Hp.
        _gather_t(columns[..., r0 : r0 + h], rows, self.col_runs)
        del rows
        forward = fft.fft(columns, dim=-1)
        # Times the kernel on its kept rows (zero elsewhere), back along columns.
        for (a, b), k in zip(self.row_runs, self.kernels, strict=True):
            torch.mul(forward[..., a:b], k, out=spectrum[..., a:b])
        del forward
        back = fft.ifft(spectrum, dim=-1)
        # Back along rows: the region's rows, the kept columns (zero elsewhere).
        _scatter_t(back_rows, back[..., :hr], self.col_runs)
        del back
        return fft.ifft(back_rows, dim=-1)[..., :wr]


def region_propagators(region_hw: tuple[int, int], window_at: tuple[int, int], pitch_m: float,
                       wavelengths_m: Sequence[float], z_m: Sequence[float], aperture: Aperture,
                       padding: str = "auto", cache: KernelCache | None = None,
                       zernike_rad: Sequence[float] = (), zernike_wavelength_m: float = 0.0,
                       device: torch.device | str = "cpu") -> list[RegionPropagator]:
    """The propagation of a window at `window_at` (row, column) inside a `region_hw` region, per
    group of colours sharing a depth: colour c by `z_m[c]` (metres) at `wavelengths_m[c]`, through
    `aperture`. With `zernike_rad` (Noll j = 5, 6, ... in radians at `zernike_wavelength_m`, the
    middle colour's wavelength when 0) each colour's kernel carries the conjugate pupil phase.
    The kernels come through `cache`, under the keys `propagate` uses; they, the scratch buffers
    and the output live on `device` (the input window must be there too)."""
    cache = cache if cache is not None else KernelCache()
    zs, lams = tuple(float(z) for z in z_m), tuple(float(v) for v in wavelengths_m)
    device = torch.device(device)
    if any(zernike_rad):
        groups = _kernels_precompensated(region_hw, pitch_m, lams, zs, aperture, padding, cache,
                                         tuple(zernike_rad), zernike_wavelength_m, device)
    else:
        groups = _kernels(region_hw, pitch_m, lams, zs, aperture, padding, cache, device)
    return [RegionPropagator(colours, hw, kernel, window_at, region_hw)
            for colours, hw, kernel in groups]


def _kernels(hw: tuple[int, int], pitch_m: float, lams: tuple[float, ...],
             zs: tuple[float, ...], aperture: Aperture, padding: str, cache: KernelCache,
             device: torch.device) -> list[tuple[slice, tuple[int, int], torch.Tensor]]:
    """(colours, padded shape, kernels [n, Hp, Wp]) per group of colours, on `device`."""
    if len(set(zs)) == 1:
        plan = plan_padding(hw, pitch_m, lams, abs(zs[0]), aperture,
                            padding)  # type: ignore[arg-type]
        k = propagation_kernels(plan, pitch_m, lams, (zs[0],), aperture, True, torch.complex64,
                                device, cache)
        return [(slice(0, len(zs)), plan.padded_hw, k[0])]
    # Per-colour depths (calibrated focus offsets): one kernel per colour, each cached.
    cutoffs = aperture.cutoffs(len(zs))
    out = []
    for c, z in enumerate(zs):
        lam = (lams[c],)
        ap = Aperture(aperture.shape, (cutoffs[c],))
        plan = plan_padding(hw, pitch_m, lam, abs(z), ap, padding)  # type: ignore[arg-type]
        k = propagation_kernels(plan, pitch_m, lam, (z,), ap, True, torch.complex64, device, cache)
        out.append((slice(c, c + 1), plan.padded_hw, k[0]))
    return out


def _kernels_precompensated(hw: tuple[int, int], pitch_m: float, lams: tuple[float, ...],
                            zs: tuple[float, ...], aperture: Aperture, padding: str,
                            cache: KernelCache, zernike_rad: tuple[float, ...],
                            zernike_wavelength_m: float, device: torch.device,
                            ) -> list[tuple[slice, tuple[int, int], torch.Tensor]]:
    """Per colour: the ASM kernel times the conjugate of the relay's pupil phase, cached under a
    key that names the aberration (a kernel for other coefficients is never reused). Computed
    on the CPU (float64 pupil phases), then moved to `device` once."""
    cutoffs = aperture.cutoffs(len(zs))
    scales = pupil_scales(zernike_wavelength_m, lams)
    out = []
    for c, z in enumerate(zs):
        lam = lams[c]
        ap = Aperture(aperture.shape, (cutoffs[c],))
        plan = plan_padding(hw, pitch_m, (lam,), abs(z), ap, padding)  # type: ignore[arg-type]

        def kernel(plan: object = plan, z: float = z, lam: float = lam, ap: Aperture = ap,
                   c: int = c) -> torch.Tensor:
            padded_hw = plan.padded_hw  # type: ignore[attr-defined]
            k = transfer_function(padded_hw, pitch_m, [lam], [z], aperture=ap)[0, 0]
            ph = pupil_phase(padded_hw, cutoffs[c], zernike_rad, scales[c])
            return (k * torch.polar(torch.ones_like(ph), -ph).to(k.dtype)).to(device)

        key = ("asm-pupil", plan.padded_hw, pitch_m, lam, z, ap, zernike_rad, scales[c],
               str(device))  # fmt: skip
        out.append((slice(c, c + 1), plan.padded_hw, cache.get(key, kernel)[None]))
    return out


def _runs(mask: torch.Tensor) -> list[tuple[int, int]]:
    """The [start, stop) runs of True in a 1-D bool tensor."""
    m = [bool(v) for v in mask.tolist()]
    out, i = [], 0
    while i < len(m):
        if m[i]:
            j = i
            while j < len(m) and m[j]:
                j += 1
            out.append((i, j))
            i = j
        else:
            i += 1
    return out


def _gather_t(dst: torch.Tensor, src: torch.Tensor, runs: list[tuple[int, int]]) -> None:
    """dst[..., k, i] = src[..., i, the k-th index of the runs]: the runs of src's columns,
    transposed into dst's rows."""
    k = 0
    for a, b in runs:
        dst[..., k : k + b - a, :] = src[..., a:b].transpose(-1, -2)
        k += b - a


def _scatter_t(dst: torch.Tensor, src: torch.Tensor, runs: list[tuple[int, int]]) -> None:
    """The inverse of `_gather_t`: dst[..., i, the k-th index of the runs] = src[..., k, i]."""
    k = 0
    for a, b in runs:
        dst[..., a:b] = src[..., k : k + b - a, :].transpose(-1, -2)
        k += b - a
