"""The reference-plane field -> the coded grey region (docs/physics.md): propagation to the SLM
plane on the window plus the kernel's reach, double-phase coding with the model's amplitude scale
and `coding.zero_below`, the calibrated phase -> grey curves, uint8.

On the CPU the coding is numba's fused pass (`nhfd.optics.double_phase_grey`). On a CUDA device
(`Encoder(settings, device=...)`) the propagation runs there with its kernels and buffers, and the
coding is `nhfd.optics.device_grey`: the same definitions in torch on the device, whose uint8
result alone is copied to the host (`nhfd.pipeline.device.HostCopy`)."""

from __future__ import annotations

import numpy as np
import torch

from nhfd.optics import (
    DeviceCurves,
    KernelCache,
    RegionPropagator,
    device_curves,
    device_grey,
    double_phase_grey,
    region_propagators,
)

from .device import CudaGraphs, HostCopy, resolve_device
from .settings import FrameSettings, frame_region, zero_pattern


class Encoder:
    """Reference-plane field -> coded grey region; owns the kernel cache, the zero pattern and
    the propagation's scratch buffers (so not thread-safe: one per worker process and refocus)."""

    def __init__(self, settings: FrameSettings, cache_bytes: int = 256 * 2**20,
                 device: torch.device | str = "cpu", *, device_coding: bool | None = None,
                 cuda_graphs: bool = False) -> None:
        """`device`: where propagation and coding run ("cpu", "cuda:N", or a torch device;
        "auto" as `daemon.frames.device`). `device_coding`: code with `device_grey` (torch) instead
        of numba's pass; the default is True exactly on CUDA (tests set it on the CPU to check the
        device path's arithmetic against the CPU's). `cuda_graphs` (`daemon.frames.cuda_graphs`):
        the device frame path replays its stages as CUDA graphs (`graphs`; no effect on the CPU)."""
        self.device = resolve_device(device, "device")
        self.device_coding = (self.device.type != "cpu" if device_coding is None
                              else bool(device_coding))
        self.host = HostCopy(self.device)
        # The graphs capture this encoder's kernels, curves and amplitude scale: they live and
        # die with it (the worker builds a new encoder for a new model, scene or refocus).
        self.graphs = CudaGraphs(self.device, cuda_graphs)
        self.settings = settings
        self.region = frame_region(settings)
        self.cache = KernelCache(cache_bytes)
        self.curves = settings.curves()
        self._zero: np.ndarray | None = None
        self._gain_map: torch.Tensor | None = None
        self._source: torch.Tensor | None = None
        self._groups: list[RegionPropagator] | None = None
        self._curves_dev: DeviceCurves | None = None

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
        ref = reference.detach().to(self.device, torch.complex64)
        h, w = ref.shape[-2:]
        if (ref.dim() != 3 or h + r.window_top > r.height or w + r.window_left > r.width):
            raise ValueError(f"reference of shape {tuple(reference.shape)}: expected [C, h, w] "
                             f"inside the {r.height} x {r.width} region")
        groups = self.groups()
        if len(groups) == 1:
            return groups[0].propagate(ref)
        out = torch.empty((ref.shape[0], r.height, r.width), dtype=torch.complex64,
                          device=self.device)
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
                s.zernike_wavelength_m, device=self.device)
        return self._groups

    def source_amplitude(self) -> torch.Tensor | None:
        """[3, Hr, Wr] the illumination's amplitude on the region relative to the window's
        centre, A(x) / A(window centre), from the calibrated source profile (None without
        one): what the bench multiplies the SLM's field by."""
        s, r = self.settings, self.region
        if not s.source_profile:
            return None
        if self._source is None:
            ph, pw = s.panel_hw
            rows = torch.arange(r.top, r.top + r.height, dtype=torch.float64)
            cols = torch.arange(r.left, r.left + r.width, dtype=torch.float64)
            y = (rows - (ph - 1) / 2) * s.pitch_m
            x = (cols - (pw - 1) / 2) * s.pitch_m
            yc = (r.top + r.window_top + (s.window_hw[0] - 1) / 2 - (ph - 1) / 2) * s.pitch_m
            xc = (r.left + r.window_left + (s.window_hw[1] - 1) / 2 - (pw - 1) / 2) * s.pitch_m
            maps = []
            for waist, x0, y0 in s.source_profile:
                # Amplitude exp(-r^2 / w^2) (w the 1/e^2 intensity radius), relative to the
                # window's centre.
                r2 = (x[None, :] - x0) ** 2 + (y[:, None] - y0) ** 2
                rc2 = (xc - x0) ** 2 + (yc - y0) ** 2
                maps.append(torch.exp((rc2 - r2) / waist**2))
            self._source = torch.stack(maps)
        return self._source

    def amplitude_gain_map(self) -> torch.Tensor | None:
        """[3, h, w] factors on the region's SLM-plane field that undo the source's profile
        (None without one): A(window centre) / A(x), at most max_amplitude_gain."""
        source = self.source_amplitude()
        if source is None:
            return None
        if self._gain_map is None:
            gain = torch.clamp(source.reciprocal(), max=self.settings.max_amplitude_gain)
            self._gain_map = gain.float().to(self.device)
        return self._gain_map

    def code(self, slm_field: torch.Tensor) -> tuple[np.ndarray, tuple[float, ...]]:
        """SLM-plane region field -> grey `[3, h, w]` uint8 and the clipped fraction per colour.

        One fused pass (`double_phase_grey`): the gain map, double-phase coding with the
        model's amplitude scale and zero_below, and the phase curves. No antialias pass: the
        propagation kernel already applied the aperture. With `device_coding`, `device_grey`
        on the device and one host copy of its result."""
        s = self.settings
        if self.device_coding:
            grey, clipped, bad = self.host.fetch(*self.code_on_device(slm_field))
            return grey, self.check_coded(clipped, bad)
        return double_phase_grey(slm_field, s.amplitude_scale, self.curves, sign=s.phase_sign,
                                 invert=s.grey_invert, zero_below=s.zero_below,
                                 gain=self.amplitude_gain_map())


    def code_on_device(self, slm_field: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`device_grey` of the region field with this encoder's settings, on its device: grey
        `[3, h, w]` uint8, the clipped fraction `[3]` and the count of non-finite amplitudes
        (both tensors, read on the host after the frame's one copy: `check_coded`)."""
        s = self.settings
        return device_grey(slm_field, s.amplitude_scale, self._device_curves(), sign=s.phase_sign,
                           invert=s.grey_invert, zero_below=s.zero_below,
                           gain=self.amplitude_gain_map())

    def check_coded(self, clipped: np.ndarray, bad: np.ndarray) -> tuple[float, ...]:
        """The clipped fractions as `code` returns them, or the ValueError a field with NaN or
        Inf gets (nothing non-finite leaves the package)."""
        n_bad = int(np.asarray(bad).sum())
        if n_bad:
            raise ValueError(f"field contains {n_bad} non-finite amplitudes (NaN or Inf) on "
                             f"{self.device}")
        return tuple(float(f) for f in np.asarray(clipped))

    def _device_curves(self) -> DeviceCurves:
        if self._curves_dev is None:
            s = self.settings
            self._curves_dev = device_curves(tuple(self.curves), s.phase_sign, s.grey_invert,
                                             len(s.wavelengths_m), str(self.device))
        return self._curves_dev


def reference_field(amplitude: np.ndarray | torch.Tensor, phase: np.ndarray | torch.Tensor,
                    amplitude_scale: float) -> torch.Tensor:
    """The network's outputs -> the complex reference-plane field in the dataset's units (on
    the outputs' device when they are tensors)."""
    if isinstance(amplitude, torch.Tensor):
        return torch.polar(amplitude.float() * float(amplitude_scale),
                           torch.as_tensor(phase, dtype=torch.float32, device=amplitude.device))
    amp = torch.from_numpy(np.ascontiguousarray(amplitude, np.float32)) * float(amplitude_scale)
    return torch.polar(amp, torch.from_numpy(np.ascontiguousarray(phase, np.float32)))
