"""Inverse STFT with hop 1 in the per-direction convolution form (docs/physics.md, "Wavefront
inversion (inverse STFT, overlap-add with hop 1)").

Per hogel h the `W x W` spectrum `S(h, k)` is inverse-DFT'd into a patch over the offsets
`n = -W/2 ... W/2 - 1` (relative to the hogel), windowed by a separable Hann window without zero
end points and overlap-added, normalised by the window sum:

    U(x) = sum_h sum_k S(h, k) w(x - h) exp(i 2 pi k . (x - h) / W) / (sum_n w(n))^2

Scale: no 1/W^2 factor, so one lit direction of constant spectrum `s` gives `s` times the window's
own transform at that bin. Regrouped per direction k, this is `S_k` convolved with the
modulated window `g_k(n) = w(n) exp(i 2 pi k n / W)`, which is separable: `g_k = g_kx(x) g_ky(y)`.
So each view costs one W-tap complex convolution along x, and each *row* of views (same k_y) one
W-tap convolution along y of the sum of that row's x-convolved views. Views can arrive one at a
time in any order; memory is the output plus one row buffer per unfinished row of views.

The window `w[m] = 0.5 - 0.5 cos(2 pi (m + 1) / (W + 1))`, m = 0..W-1, sits on offsets
`m - W/2`: its centre is at -1/2 px, so (for even W) the field is shifted by half a pixel up and
left of the views. The output covers the views' grid; light that the patches spread beyond it
(up to W/2 px) is cropped.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch


def hann_window(window: int) -> np.ndarray:
    """Hann window of length W without zero end points, float64:
    `w[m] = 0.5 - 0.5 cos(2 pi (m + 1) / (W + 1))`."""
    if window < 1:
        raise ValueError(f"window length must be >= 1, got {window}")
    m = np.arange(window)
    return 0.5 - 0.5 * np.cos(2 * np.pi * (m + 1) / (window + 1))


def patch_offsets(window: int) -> np.ndarray:
    """Pixel offsets of a hogel's patch relative to the hogel: -W/2 ... W/2 - 1 (W even)."""
    return np.arange(window) - window // 2


def modulated_window(window: int, k: int) -> np.ndarray:
    """`g_k(n) = w(n) exp(i 2 pi k n / W)` over `patch_offsets(W)`, complex128."""
    n = patch_offsets(window)
    return hann_window(window) * np.exp(2j * np.pi * k * n / window)


def _convolve_axis(
    out: torch.Tensor, src: torch.Tensor, taps: np.ndarray, offsets: np.ndarray, dim: int
) -> None:
    """`out(x) += sum_n taps(n) src(x - n)` along `dim` (-1: x, -2: y), cropped to out's extent
    (zero outside src): one strided multiply-add per tap, no temporaries."""
    size = src.shape[dim]
    for g, n in zip(taps, offsets, strict=True):
        n = int(n)
        lo, hi = max(0, n), min(size, size + n)
        if hi <= lo:
            continue
        o = out.narrow(dim, lo, hi - lo)
        s = src.narrow(dim, lo - n, hi - lo)
        o.add_(s, alpha=complex(g))


class InverseSTFT:
    """Accumulates one colour's views into the reference-plane field.

    Args:
        shape_hw: (H, W) of the views and of the result, pixels.
        window: the hogel window W (even).
        k_x, k_y: integer STFT bins of the views' columns (ix) and rows (iy).

    Feed each view's spectrum `S_k` ([H, W] complex, e.g. from `phase.view_spectrum`) once with
    `add(iy, ix, S)`, then call `result()`: complex64 [H, W]. A view never added counts as zero.
    `device`: where the field accumulates (default the CPU); spectra are moved there.
    """

    def __init__(
        self,
        shape_hw: tuple[int, int],
        window: int,
        k_x: Sequence[int],
        k_y: Sequence[int],
        device: torch.device | str | None = None,
    ) -> None:
        if window < 2 or window % 2:
            raise ValueError(f"hogel window W must be an even integer >= 2, got {window}")
        self.shape_hw = (int(shape_hw[0]), int(shape_hw[1]))
        self.window = int(window)
        self._offsets = patch_offsets(window)
        # complex64 taps, normalised once: (sum w)^2 folded into the x taps.
        norm = hann_window(window).sum() ** 2
        self._gx = [modulated_window(window, int(k)) / norm for k in k_x]
        self._gy = [modulated_window(window, int(k)) for k in k_y]
        self._n_x = len(self._gx)
        self._out = torch.zeros(self.shape_hw, dtype=torch.complex64, device=device)
        self._rows: dict[int, tuple[torch.Tensor, set[int]]] = {}
        self._done: set[tuple[int, int]] = set()

    def add(self, iy: int, ix: int, spectrum: torch.Tensor) -> None:
        """Add view (iy, ix): `spectrum` [H, W] complex (or real, meaning zero phase)."""
        if (iy, ix) in self._done:
            raise ValueError(f"view ({iy}, {ix}) was already added")
        if not (0 <= iy < len(self._gy) and 0 <= ix < self._n_x):
            raise ValueError(f"view ({iy}, {ix}) outside {len(self._gy)} x {self._n_x} directions")
        if tuple(spectrum.shape) != self.shape_hw:
            raise ValueError(f"view shape {tuple(spectrum.shape)} != {self.shape_hw}")
        s = spectrum.to(self._out.device, torch.complex64)
        if iy not in self._rows:
            self._rows[iy] = (torch.zeros_like(self._out), set())
        buf, seen = self._rows[iy]
        _convolve_axis(buf, s, self._gx[ix], self._offsets, -1)
        seen.add(ix)
        self._done.add((iy, ix))
        if len(seen) == self._n_x:
            self._flush(iy)

    def _flush(self, iy: int) -> None:
        buf, _ = self._rows.pop(iy)
        _convolve_axis(self._out, buf, self._gy[iy], self._offsets, -2)

    def result(self) -> torch.Tensor:
        """The field [H, W] complex64 (the views added so far; rows not yet complete included)."""
        for iy in list(self._rows):
            self._flush(iy)
        return self._out
