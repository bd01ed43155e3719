"""The reference-plane field -> the coded grey region (optics.md): propagation to the SLM plane
on the window plus the kernel's reach, double-phase coding with the model's amplitude scale and
`coding.zero_below`, the calibrated phase -> grey curves, uint8."""

from __future__ import annotations

import numpy as np
import torch

from nhfd.optics import KernelCache, RegionPropagator, double_phase_grey, region_propagators

from .settings import FrameSettings, frame_region, zero_pattern


class Encoder:
    """Reference-plane field -> coded grey region; owns the kernel cache, the zero pattern and
    the propagation's scratch buffers (so not thread-safe: one per worker process and refocus)."""

    def __init__(self, settings: FrameSettings, cache_bytes: int = 256 * 2**20) -> None:
        self.settings = settings
        self.region = frame_region(settings)
        self.cache = KernelCache(cache_bytes)
        self.curves = settings.curves()
        self._zero: np.ndarray | None = None
        self._gain_map: torch.Tensor | None = None
        self._groups: list[RegionPropagator] | None = None

    @property
    def zero(self) -> np.ndarray:
        """The whole panel coding zero amplitude `[3, H, W]` uint8 (what surrounds the region)."""
        if self._zero is None:  # 6 MB at 1920 x 1080: only where a full panel is wanted
            self._zero = zero_pattern(self.settings)
        return self._zero

    def to_slm(self, reference: torch.Tensor) -> torch.Tensor:
        """Window field `[3, h, w]` on the reference plane -> region field on the SLM plane.

        The same field as `propagate` of the zero-padded region by each colour's depth with the
        aperture (and the relay's conjugate pupil when calibrated), to float32 rounding; the
        result may be a crop of a larger fresh tensor (not contiguous), and carries no autograd
        history."""
        r = self.region
        ref = reference.detach().to(torch.complex64)
        h, w = ref.shape[-2:]
        if (ref.dim() != 3 or h + r.window_top > r.height or w + r.window_left > r.width):
            raise ValueError(f"reference of shape {tuple(reference.shape)}: expected [C, h, w] "
                             f"inside the {r.height} x {r.width} region")
        groups = self.groups()
        if len(groups) == 1:
            return groups[0].propagate(ref)
        out = torch.empty((ref.shape[0], r.height, r.width), dtype=torch.complex64)
        for g in groups:
            out[g.colours] = g.propagate(ref[g.colours])
        return out

    def groups(self) -> list[RegionPropagator]:
        """The propagation per group of colours sharing a depth (built once, kernels cached)."""
        if self._groups is None:
            s, r = self.settings, self.region
            self._groups = region_propagators(
                (r.height, r.width), (r.window_top, r.window_left), s.pitch_m, s.wavelengths_m,
                s.colour_propagation_z_m, s.aperture, s.padding, self.cache, s.zernike_rad,
                s.zernike_wavelength_m)
        return self._groups

    def amplitude_gain_map(self) -> torch.Tensor | None:
        """[3, h, w] factors on the region's SLM-plane field that undo the source's profile
        (None without one): A(window centre) / A(x), at most max_amplitude_gain."""
        s, r = self.settings, self.region
        if not s.source_profile:
            return None
        if self._gain_map is None:
            ph, pw = s.panel_hw
            rows = torch.arange(r.top, r.top + r.height, dtype=torch.float64)
            cols = torch.arange(r.left, r.left + r.width, dtype=torch.float64)
            y = (rows - (ph - 1) / 2) * s.pitch_m
            x = (cols - (pw - 1) / 2) * s.pitch_m
            yc = (r.top + r.window_top + (s.window_hw[0] - 1) / 2 - (ph - 1) / 2) * s.pitch_m
            xc = (r.left + r.window_left + (s.window_hw[1] - 1) / 2 - (pw - 1) / 2) * s.pitch_m
            maps = []
            for waist, x0, y0 in s.source_profile:
                # Amplitude exp(-r^2 / w^2): its inverse relative to the window's centre.
                r2 = (x[None, :] - x0) ** 2 + (y[:, None] - y0) ** 2
                rc2 = (xc - x0) ** 2 + (yc - y0) ** 2
                maps.append(torch.clamp(torch.exp((r2 - rc2) / waist**2),
                                        max=s.max_amplitude_gain))
            self._gain_map = torch.stack(maps).float()
        return self._gain_map

    def code(self, slm_field: torch.Tensor) -> tuple[np.ndarray, tuple[float, ...]]:
        """SLM-plane region field -> grey `[3, h, w]` uint8 and the clipped fraction per colour.

        One fused pass (`double_phase_grey`): the gain map, double-phase coding with the
        model's amplitude scale and zero_below, and the phase curves. No antialias pass: the
        propagation kernel already applied the aperture."""
        s = self.settings
        return double_phase_grey(slm_field, s.amplitude_scale, self.curves, sign=s.phase_sign,
                                 invert=s.grey_invert, zero_below=s.zero_below,
                                 gain=self.amplitude_gain_map())


def reference_field(amplitude: np.ndarray, phase: np.ndarray, amplitude_scale: float
                    ) -> torch.Tensor:
    """The network's outputs -> the complex reference-plane field in the dataset's units."""
    amp = torch.from_numpy(np.ascontiguousarray(amplitude, np.float32)) * float(amplitude_scale)
    return torch.polar(amp, torch.from_numpy(np.ascontiguousarray(phase, np.float32)))
