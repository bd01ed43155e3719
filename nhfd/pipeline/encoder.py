"""The reference-plane field -> the coded grey region (optics.md): propagation to the SLM plane
on the window plus the kernel's reach, double-phase coding with the model's amplitude scale and
`coding.zero_below`, the calibrated phase -> grey curves, uint8.

On the CPU the coding is numba's fused pass (`nhfd.optics.double_phase_grey`). On a CUDA device
(`Encoder(settings, device=...)`) the propagation runs there with its kernels and buffers, and the
coding is `device_grey`: the same definitions in torch on the device, whose uint8 result alone is
copied to the host (`nhfd.pipeline.device.HostCopy`)."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from nhfd.optics import KernelCache, RegionPropagator, double_phase_grey, region_propagators
from nhfd.optics.dpac import AMPLITUDE_CEILING, _nearest_level
from nhfd.spec import GREY_LEVELS, PhaseCurve, zero_grey

from .device import HostCopy, resolve_device
from .settings import FrameSettings, frame_region, zero_pattern

# Bins of [0, 2 pi) in the device coder's table of a curve other than the default one: a phase
# within half a bin (5e-5 rad) of a decision boundary may get the neighbouring level.
DEVICE_LUT_BINS = 65536


class Encoder:
    """Reference-plane field -> coded grey region; owns the kernel cache, the zero pattern and
    the propagation's scratch buffers (so not thread-safe: one per worker process and refocus)."""

    def __init__(self, settings: FrameSettings, cache_bytes: int = 256 * 2**20,
                 device: torch.device | str = "cpu", *, device_coding: bool | None = None
                 ) -> None:
        """`device`: where propagation and coding run ("cpu", "cuda:N", or a torch device;
        "auto" as `daemon.device`). `device_coding`: code with `device_grey` (torch) instead of
        numba's pass; the default is True exactly on CUDA (tests set it on the CPU to check the
        device path's arithmetic against the CPU's)."""
        self.device = resolve_device(device, "device")
        self.device_coding = (self.device.type != "cpu" if device_coding is None
                              else bool(device_coding))
        self.host = HostCopy(self.device)
        self.settings = settings
        self.region = frame_region(settings)
        self.cache = KernelCache(cache_bytes)
        self.curves = settings.curves()
        self._zero: np.ndarray | None = None
        self._gain_map: torch.Tensor | None = None
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
            self._gain_map = torch.stack(maps).float().to(self.device)
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


class DeviceCurves:
    """The phase -> grey curves as `device_grey` reads them, on one device: `lut` `[C, BINS]`
    uint8 (None when every curve is the default one: rounding), and `zero` `[C, 2]` uint8, the
    grey levels of amplitude 0 on even and odd pixels (`nhfd.spec.zero_grey`)."""

    def __init__(self, lut: torch.Tensor | None, zero: torch.Tensor) -> None:
        self.lut = lut
        self.zero = zero


@functools.lru_cache(maxsize=16)
def device_curves(curves: tuple[PhaseCurve, ...], sign: int, invert: bool, n_colours: int,
                  device: str) -> DeviceCurves:
    """One curve per colour (a single curve serves all), as `DeviceCurves` on `device`."""
    per = list(curves) * n_colours if len(curves) == 1 else list(curves)
    if len(per) != n_colours:
        raise ValueError(f"{len(curves)} phase curves for {n_colours} colour channels")
    zero = torch.from_numpy(zero_grey(per, sign, invert)).to(device)
    if all(c.is_default for c in per):
        return DeviceCurves(None, zero)
    centres = (torch.arange(DEVICE_LUT_BINS, dtype=torch.float64) + 0.5) * (
        2 * math.pi / DEVICE_LUT_BINS)
    rows = []
    for c in per:
        if c.is_default:
            g = torch.round(centres / (2 * math.pi) * GREY_LEVELS).long() % GREY_LEVELS
        else:
            g = _nearest_level(centres, c)
        rows.append(GREY_LEVELS - 1 - g if invert else g)
    return DeviceCurves(torch.stack(rows).to(torch.uint8).to(device), zero)


def device_grey(field: torch.Tensor, amplitude_scale: float, curves: DeviceCurves, *,
                sign: int = 1, invert: bool = False, zero_below: float = 0.03,
                gain: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`nhfd.optics.double_phase_grey` in torch on the field's device (elementwise passes, no
    host synchronisation): field `[C, h, w]` complex64 (any strides) -> grey `[C, h, w]` uint8,
    the clipped fraction per colour `[C]` float64 and the count of non-finite amplitudes `[]`.

    The same definitions: |u| (x gain) / scale, its clipped count and zero_below test exactly;
    the phase `arg(u e^{-i mean} (a +- i sqrt(1 - a^2)))`, + on even (row + column), the
    circular mean from a complex128 sum rounded to float32; the default curve rounds, another
    curve is looked up in `curves.lut`; a pixel below zero_below gets the zero pattern's level.
    The phase is float32 here (float64 in numba's pass), so a pixel within ~1e-6 rad of a
    decision boundary (or half a table bin of one) may differ by one level of the curve."""
    if sign not in (1, -1):
        raise ValueError(f"sign = {sign!r}: must be +1 or -1")
    if field.dim() != 3:
        raise ValueError(f"field has shape {tuple(field.shape)}: expected [C, H, W]")
    if not amplitude_scale > 0 or not math.isfinite(amplitude_scale):
        raise ValueError(f"amplitude_scale = {amplitude_scale!r}: must be finite and > 0")
    u = field.to(torch.complex64)
    c, h, w = u.shape
    re, im = u.real, u.imag
    if gain is not None:
        if tuple(gain.shape) != (c, h, w):
            raise ValueError(f"gain has shape {tuple(gain.shape)}: expected the field's "
                             f"{(c, h, w)}")
        re, im = re * gain, im * gain
    # |u| as numba's pass (and torch.abs): sqrt in double of float32 squares, rounded to float32.
    mag = torch.sqrt(re.double() ** 2 + im.double() ** 2).float()
    amp = mag / torch.tensor(amplitude_scale, dtype=torch.float32)
    finite = torch.isfinite(amp)
    bad = (~finite).sum()
    clipped = (amp > 1.0).sum(dim=(-2, -1)).double() / (h * w)
    a = amp.clamp(0.0, AMPLITUDE_CEILING)
    empty = (a < zero_below) | ~finite
    a = torch.where(empty, torch.zeros_like(a), a)
    # The circular mean phase per channel: complex128 sums, rounded to float32 as numba's is.
    sums = torch.complex(re.double().sum(dim=(-2, -1)), im.double().sum(dim=(-2, -1)))
    mean = torch.angle(sums).float().double()
    rr, ri = torch.cos(mean).float()[:, None, None], (-torch.sin(mean)).float()[:, None, None]
    wr = re * rr - im * ri
    wi = re * ri + im * rr
    rows = torch.arange(h, device=u.device)[:, None]
    cols = torch.arange(w, device=u.device)[None, :]
    parity = (rows + cols) % 2
    s = torch.sqrt(1.0 - a * a) * (1.0 - 2.0 * parity.float())
    p = torch.atan2(wi * a + wr * s, wr * a - wi * s) * float(sign)
    two_pi = 2 * math.pi
    p = torch.where(p < 0, p + two_pi, p)
    if curves.lut is None:
        g = torch.round(p / two_pi * GREY_LEVELS).long() % GREY_LEVELS
        g = (GREY_LEVELS - 1 - g) if invert else g
        grey = g.to(torch.uint8)
    else:
        bins = curves.lut.shape[1]
        idx = (p * (bins / two_pi)).long().clamp(0, bins - 1)
        grey = torch.gather(curves.lut, 1, idx.reshape(c, -1)).reshape(c, h, w)
    zero = curves.zero[:, parity]  # [C, h, w]: the zero pattern's levels
    return torch.where(empty, zero, grey), clipped, bad


def reference_field(amplitude: np.ndarray | torch.Tensor, phase: np.ndarray | torch.Tensor,
                    amplitude_scale: float) -> torch.Tensor:
    """The network's outputs -> the complex reference-plane field in the dataset's units (on
    the outputs' device when they are tensors)."""
    if isinstance(amplitude, torch.Tensor):
        return torch.polar(amplitude.float() * float(amplitude_scale),
                           torch.as_tensor(phase, dtype=torch.float32, device=amplitude.device))
    amp = torch.from_numpy(np.ascontiguousarray(amplitude, np.float32)) * float(amplitude_scale)
    return torch.polar(amp, torch.from_numpy(np.ascontiguousarray(phase, np.float32)))
