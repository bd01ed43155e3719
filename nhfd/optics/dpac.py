"""Double-phase amplitude coding and phase-to-grey quantisation (docs/physics.md, "Double-phase
amplitude coding and the SLM").

A complex field `a exp(i phi)` (a <= 1) equals the mean of `exp(i (phi + acos a))` and
`exp(i (phi - acos a))`. Writing the two on a pixel checkerboard leaves the wanted field plus an
error term moved to the corners of the band, which the Fourier aperture removes; so the target must
be band-limited (the aperture's own band) for the coding to be accurate.

The definition and its two fast paths (gsplat's way: the plain reference beside the fast code):

- `double_phase_grey_reference`: THE REFERENCE. Field `[C, H, W]` -> grey levels, in float64 and
  plain torch operations: `double_phase` (the coding) then `phase_to_grey` (the curves' lookup,
  the sign, the inversion), the zero pattern on empty pixels and the clipped fraction. Slow;
  used by tests and for checking.
- `double_phase_grey`: the CPU coder (numba, `nhfd.optics._coding`), one fused pass.
- `device_grey`: the device coder (torch elementwise passes on the field's device, a lookup table
  for calibrated curves).

tests/optics/test_coders_against_reference.py checks both fast coders against the reference at
the full panel and at the extremes; there the criterion and the measured agreement are stated.
`double_phase` alone (the coded phase, float32 for a complex64 field) serves the demos and the
calibration patterns.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from nhfd.optics import _coding, _validate
from nhfd.optics._coding import LUT_BINS
from nhfd.optics.aperture import Aperture, apply_aperture
from nhfd.spec import GREY_LEVELS, TWO_PI, PhaseCurve, zero_grey

# acos has an infinite gradient at 1; amplitudes are clamped just below it. The float32 number
# nearest 1 - 1e-6 (1 - 1.0133e-6), so that the float32 coders and the float64 reference clamp
# at the same amplitude (1 - 1e-6 itself gave clipped pixels phases 9.4e-6 rad apart).
AMPLITUDE_CEILING = float(np.float32(1.0 - 1e-6))
# Amplitudes below this fraction of the scale are coded as exact zeros. Their phase is noise (FFT
# round-off, propagation tails, speckle near-zeros); coded as is, it makes the checkerboard term
# full-band and it leaks through the aperture as haze over the whole window. Measured on the demo
# target (focal-stack intensity error of the phase-only display vs the complex field): 507% with
# no threshold, 73% at 1e-3, 26% at 1e-2, 21% at 3e-2, 23% at 1e-1.
ZERO_BELOW = 0.03
# Amplitudes (relative to the scale) below float32's smallest normal number are coded as zeros
# whatever zero_below says (also at zero_below = 0): amplitude 0 has no phase, and the coders
# used to give such a pixel phase 0 on both parities (a flat mirror, whose light passes the
# aperture) instead of the zero pattern.
AMPLITUDE_FLOOR = float(np.finfo(np.float32).tiny)


def empty_below(zero_below: float) -> float:
    """The amplitude (relative to the scale) below which a pixel is coded as zero amplitude:
    `zero_below`, or AMPLITUDE_FLOOR when that is larger."""
    return max(float(zero_below), AMPLITUDE_FLOOR)


@dataclass(frozen=True)
class DoublePhase:
    """The coded phase `[..., C, H, W]` (radians, in [-pi, pi)) and, per colour channel `[C]`,
    the fraction of pixels whose amplitude exceeded the scale and was clipped."""

    phase_rad: torch.Tensor
    clipped_fraction: torch.Tensor


def checkerboard(
    shape_hw: tuple[int, int], device: torch.device | str | None = None
) -> torch.Tensor:
    """+1 on (0,0) and (1,1), -1 on (0,1) and (1,0): `[H, W]` float32."""
    h, w = shape_hw
    rows = torch.arange(h, device=device)[:, None]
    cols = torch.arange(w, device=device)[None, :]
    return 1.0 - 2.0 * ((rows + cols) % 2).to(torch.float32)


def wrap_phase(phase: torch.Tensor) -> torch.Tensor:
    """Wrap to [-pi, pi)."""
    return torch.remainder(phase + math.pi, TWO_PI) - math.pi


def double_phase(
    field: torch.Tensor,
    amplitude_scale: float,
    *,
    antialias: Aperture | None = None,
    zero_below: float = ZERO_BELOW,
) -> DoublePhase:
    """Code a complex field `[..., C, H, W]` as one phase per pixel.

    Args:
        field: the wanted field on the SLM plane.
        amplitude_scale: the fixed amplitude that maps to full modulation (a dataset's or model's
            scale, never a per-frame maximum: brightness would flicker as the view moves).
        antialias: when given, low-pass the field by this aperture first.
        zero_below: amplitudes (relative to the scale) below this are coded as exact zeros:
            a pure checkerboard, which the aperture blocks, instead of noise-driven phases.
    """
    scale = _validate.positive("amplitude_scale", amplitude_scale)
    u = _validate.field("field", field)
    if antialias is not None:
        u = apply_aperture(u, antialias)
    phase, over, _ = _double_phase_core(u, scale, zero_below)
    clipped = over.flatten(-2).float().mean(-1)
    while clipped.dim() > 1:
        clipped = clipped.mean(0)
    return DoublePhase(phase, clipped)


def _double_phase_core(u: torch.Tensor, scale: float, zero_below: float
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The coding's formula, in `u`'s precision (complex64: float32, complex128: float64).

    `u` `[..., C, H, W]` (finite), `scale` the amplitude of full modulation. Returns the coded
    phase `[..., C, H, W]` (rad, in [-pi, pi)), `over` (amplitude / scale > 1: clipped) and
    `empty` (coded as zero amplitude), both `[..., C, H, W]` bool:

        a     = clamp(|u| / scale, 0, AMPLITUDE_CEILING)
        empty = a < max(zero_below, AMPLITUDE_FLOOR); there a = 0 and the phase is 0
        phase = wrap(arg(u) - arg(sum of u over the channel) + acos(a) * (+1 on (row + col)
                even, -1 on odd))
    """
    amp = u.abs() / scale
    over = amp > 1.0
    amp = amp.clamp(0.0, AMPLITUDE_CEILING)
    # Circular mean phase per channel (amplitude-weighted: zero-amplitude pixels carry no phase).
    mean = torch.angle(u.sum(dim=(-2, -1), keepdim=True))
    empty = amp < empty_below(zero_below)
    amp = torch.where(empty, torch.zeros_like(amp), amp)
    phi = torch.where(empty, torch.zeros_like(amp), torch.angle(u) - mean)
    offset = torch.acos(amp) * checkerboard(tuple(u.shape[-2:]), u.device)
    real = torch.float64 if u.dtype == torch.complex128 else torch.float32
    return wrap_phase((phi + offset).to(real)), over, empty


def _nearest_level(phase: torch.Tensor, curve: PhaseCurve) -> torch.Tensor:
    """Grey level (int64) whose phase is nearest to `phase` (any real) on the circle."""
    table = torch.tensor(curve.phase_rad, dtype=torch.float64, device=phase.device)
    wrapped = torch.remainder(table, TWO_PI)
    order = torch.argsort(wrapped)
    values, levels = wrapped[order], order
    p = torch.remainder(phase.to(torch.float64), TWO_PI)
    hi = torch.searchsorted(values, p).clamp(max=len(values))
    lo = hi - 1
    # Candidates on either side, with the circle closed by +-2 pi at the ends.
    v_hi = torch.where(hi < len(values), values[hi.clamp(max=len(values) - 1)], values[0] + TWO_PI)
    v_lo = torch.where(lo >= 0, values[lo.clamp(min=0)], values[-1] - TWO_PI)
    g_hi = levels[hi % len(values)]
    g_lo = levels[lo % len(values)]
    return torch.where((v_hi - p) < (p - v_lo), g_hi, g_lo)


def _curves_per_channel(
    curves: Sequence[PhaseCurve], n_colours: int, sign: int
) -> list[PhaseCurve]:
    """One curve per colour channel (a single curve serves all), after checking the sign."""
    if sign not in (1, -1):
        raise ValueError(f"sign = {sign!r}: must be +1 or -1")
    if len(curves) not in (1, n_colours):
        raise ValueError(f"{len(curves)} phase curves for {n_colours} colour channels")
    return list(curves) * n_colours if len(curves) == 1 else list(curves)


def phase_to_grey(
    phase_rad: torch.Tensor,
    curves: Sequence[PhaseCurve],
    *,
    sign: int = 1,
    invert: bool = False,
) -> torch.Tensor:
    """Phase `[..., C, H, W]` -> grey levels (uint8), one curve per colour channel.

    `sign` = -1 writes the conjugate; `invert` writes `255 - grey`. With the default curve this is
    `round(wrap(phi) / 2 pi * 256) mod 256`.
    """
    per_channel = _curves_per_channel(curves, phase_rad.shape[-3], sign)
    if not torch.isfinite(phase_rad).all():
        raise ValueError("phase_rad contains NaN or Inf")
    signed = phase_rad * sign
    out = torch.empty(phase_rad.shape, dtype=torch.uint8, device=phase_rad.device)
    for c, curve in enumerate(per_channel):
        p = signed[..., c, :, :]
        if curve.is_default:
            grey = torch.round(torch.remainder(p.double(), TWO_PI) / TWO_PI * GREY_LEVELS)
            grey = grey.long() % GREY_LEVELS
        else:
            grey = _nearest_level(p, curve)
        out[..., c, :, :] = (GREY_LEVELS - 1 - grey if invert else grey).to(torch.uint8)
    return out


def grey_to_phase(
    grey: torch.Tensor,
    curves: Sequence[PhaseCurve],
    *,
    sign: int = 1,
    invert: bool = False,
) -> torch.Tensor:
    """Grey levels `[..., C, H, W]` -> the phase (float32 radians) the panel shows: the inverse of
    `phase_to_grey` up to quantisation and wrapping."""
    per_channel = _curves_per_channel(curves, grey.shape[-3], sign)
    out = torch.empty(grey.shape, dtype=torch.float32, device=grey.device)
    for c, curve in enumerate(per_channel):
        table = torch.tensor(curve.phase_rad, dtype=torch.float64, device=grey.device)
        g = grey[..., c, :, :].long()
        g = GREY_LEVELS - 1 - g if invert else g
        if g.numel() and (g.min() < 0 or g.max() >= len(table)):
            raise ValueError(f"grey levels outside the curve's 0..{len(table) - 1}")
        out[..., c, :, :] = (table[g] * sign).float()
    return out


class ReferenceCoding(NamedTuple):
    """What `double_phase_grey_reference` returns (all on the CPU):

    grey: `[C, H, W]` uint8, the grey levels the panel shows.
    clipped_fraction: `[C]` float64, per colour the fraction of pixels whose amplitude exceeded
        the scale (exact: the count / (H W)).
    phase_rad: `[C, H, W]` float64, the coded phase before the sign and the curve (rad, in
        [-pi, pi); +-pi/2 on empty pixels): for telling a pixel next to a decision boundary from
        a wrong one.
    amplitude: `[C, H, W]` float64, |u x gain| / scale before the clamp (unitless).
    """

    grey: torch.Tensor
    clipped_fraction: torch.Tensor
    phase_rad: torch.Tensor
    amplitude: torch.Tensor


def double_phase_grey_reference(
    field: torch.Tensor | np.ndarray,
    amplitude_scale: float,
    curves: Sequence[PhaseCurve],
    *,
    sign: int = 1,
    invert: bool = False,
    zero_below: float = ZERO_BELOW,
    gain: torch.Tensor | np.ndarray | None = None,
) -> ReferenceCoding:
    """THE REFERENCE of double-phase coding to grey levels, for checking the fast coders
    (`double_phase_grey`, `device_grey`): the same arguments, written for clarity in float64
    with plain torch operations, on the CPU.

    Args:
        field: `[C, H, W]` complex (any dtype; taken to complex128), the field on the SLM plane.
        amplitude_scale: the amplitude of full modulation (the field's units).
        curves: the phase -> grey curves, one per colour (or one for all).
        sign: +1, or -1 to write the conjugate.
        invert: write `255 - grey` (through the curve's level numbers).
        zero_below: amplitudes (relative to the scale) below this are coded as zero amplitude.
        gain: `[C, H, W]` real factors on the field (None: 1).

    The steps:

    1. u = field x gain (complex128); a NaN or Inf sample is a ValueError (the fast coders'
       message).
    2. `double_phase` of u (`_double_phase_core`, float64): amplitude a = |u| / scale, clipped
       where a > 1, clamped to [0, AMPLITUDE_CEILING]; empty where a < zero_below (or below
       AMPLITUDE_FLOOR); phase = wrap(arg(u) - circular mean phase of the channel + acos(a) on
       even (row + column), - acos(a) on odd).
    3. `phase_to_grey` (float64): x sign, wrapped to [0, 2 pi); the default curve rounds
       (`round(p / 2 pi * 256) mod 256`), another curve takes the level nearest on the circle
       (`_nearest_level`); inverted when asked.
    4. Empty pixels show the zero pattern (`nhfd.spec.zero_grey`, on the pixel's parity).

    The fast coders compute in float32 where this computes in float64 (the amplitude, the
    scale, zero_below and AMPLITUDE_CEILING rounded to float32; the phase in float32 on the
    device), so they may differ from it next to a decision: see
    tests/optics/test_coders_against_reference.py for the criterion and what was measured.
    Amplitudes past float32's range (|u x gain| / scale > 3.4e38), which the fast coders count
    as non-finite, are outside its domain.
    """
    scale = _validate.positive("amplitude_scale", amplitude_scale)
    u = torch.as_tensor(field).detach().cpu().to(torch.complex128)
    if u.dim() != 3 or min(u.shape) < 1:
        raise ValueError(f"field has shape {tuple(u.shape)}: expected [C, H, W] with C, H, W >= 1")
    n_c, h, w = u.shape
    per_channel = _curves_per_channel(curves, n_c, sign)
    if gain is not None:
        g = torch.as_tensor(gain).detach().cpu().to(torch.float64)
        if tuple(g.shape) != (n_c, h, w):
            raise ValueError(f"gain has shape {tuple(g.shape)}: expected the field's "
                             f"{(n_c, h, w)}")
        u = u * g
    u = _validate.field("field", u)
    amplitude = u.abs() / scale
    phase, over, empty = _double_phase_core(u, scale, zero_below)
    grey = phase_to_grey(phase, per_channel, sign=sign, invert=invert)
    zero = torch.from_numpy(zero_grey(per_channel, sign, invert))  # [C, 2]: even, odd pixels
    parity = (torch.arange(h)[:, None] + torch.arange(w)[None, :]) % 2  # [H, W]
    grey = torch.where(empty, zero[:, parity], grey)
    clipped = over.sum(dim=(-2, -1)).to(torch.float64) / (h * w)
    return ReferenceCoding(grey, clipped, phase, amplitude)


# -- the CPU coder (numba) ----------------------------------------------------------------------

def _rows_base(field: torch.Tensor | np.ndarray) -> tuple[np.ndarray, int, int]:
    """A C-contiguous complex64 array whose `[:, :h, :w]` is the field `[C, h, w]`: the field
    itself, the contiguous tensor it is the top-left crop of (a propagation's padded output,
    read in place), or a contiguous copy."""
    if isinstance(field, torch.Tensor):
        t = field.detach()
        if t.dim() != 3:
            raise ValueError(f"field has shape {tuple(t.shape)}: expected [C, H, W]")
        base = t._base
        if (not t.is_contiguous() and t.dtype == torch.complex64 and base is not None
                and base.dim() == 3 and base.is_contiguous() and base.device == t.device
                and t.data_ptr() == base.data_ptr() and t.stride() == base.stride()
                and t.shape[0] == base.shape[0]):
            return base.numpy(), t.shape[1], t.shape[2]
        field = t.numpy() if t.dtype == torch.complex64 else t.to(torch.complex64).numpy()
    u = np.ascontiguousarray(field, np.complex64)
    if u.ndim != 3 or min(u.shape) < 1:
        raise ValueError(f"field has shape {u.shape}: expected [C, H, W] with C, H, W >= 1")
    return u, u.shape[1], u.shape[2]


def _nonfinite(u: np.ndarray, h: int, w: int, gain: np.ndarray, bad: np.ndarray) -> ValueError:
    """The fused coder's refusal, as `_validate.finite_field`'s: the count of non-finite
    amplitudes (the coder's per-row counts `bad` [C * H]) and the first one's index, found in
    the first row that has one."""
    k = int(np.flatnonzero(bad)[0])
    c, i = divmod(k, h)
    g = gain[c, i] if gain.shape[0] > 1 else gain[0, 0]
    with np.errstate(all="ignore"):
        amp = np.abs(u[c, i, :w] * g)
    j = int(np.flatnonzero(~np.isfinite(amp))[0])
    return _validate.nonfinite_error("field", int(bad.sum()), (c, i, j))


class LevelTables(NamedTuple):
    """Per colour channel, how the fused coder (`nhfd.optics._coding`) turns a phase in
    [0, 2 pi] into a grey level: `default` (the default curve: rounding), else the curve's wrapped
    phases sorted (`values`, padded with +inf; `levels` their grey levels; `counts` how many) and,
    per bin of [0, 2 pi), the decision the bin needs: none (`glo` == `ghi`), the one comparison
    `_nearest_level` makes between its neighbours `vlo` and `vhi` (`glo` / `ghi` their levels), or
    (`scan`) a search of `values` from `starts` (the first index >= the bin's start)."""

    default: np.ndarray
    values: np.ndarray
    levels: np.ndarray
    counts: np.ndarray
    starts: np.ndarray
    vlo: np.ndarray
    vhi: np.ndarray
    glo: np.ndarray
    ghi: np.ndarray
    scan: np.ndarray


@functools.lru_cache(maxsize=16)
def level_tables(curves: tuple[PhaseCurve, ...]) -> LevelTables:
    """The fused coder's tables for one curve per channel. Exact: every bin holds at most one
    of `_nearest_level`'s decision boundaries (the midpoints of neighbouring levels on the
    circle) and decides it with `_nearest_level`'s own comparison, or is searched."""

    n_c, n = len(curves), max(len(c.phase_rad) for c in curves)
    values = np.full((n_c, n), np.inf)
    levels = np.zeros((n_c, n), np.int64)
    starts = np.zeros((n_c, LUT_BINS), np.int64)
    vlo, vhi = np.zeros((n_c, LUT_BINS)), np.zeros((n_c, LUT_BINS))
    glo, ghi = np.zeros((n_c, LUT_BINS), np.int64), np.zeros((n_c, LUT_BINS), np.int64)
    scan = np.zeros((n_c, LUT_BINS), np.bool_)
    width = TWO_PI / LUT_BINS
    # Bins a hair wider than they are: a phase that rounds into bin b lies inside it.
    margin = 1e-9
    lo_edge = np.arange(LUT_BINS) * width - margin
    hi_edge = (np.arange(LUT_BINS) + 1) * width + margin
    for c, curve in enumerate(curves):
        if curve.is_default:
            continue
        # The same float64 values and order as _nearest_level.
        wrapped = torch.remainder(torch.tensor(curve.phase_rad, dtype=torch.float64), TWO_PI)
        order = torch.argsort(wrapped)
        v = wrapped[order].numpy()
        k = len(v)
        values[c, :k], levels[c, :k] = v, order.numpy()
        starts[c] = np.searchsorted(v, lo_edge, side="left")
        # Decision boundaries: between neighbours, and across 2 pi.
        wrap = (v[-1] + v[0] + TWO_PI) / 2
        bounds = np.sort(np.concatenate([(v[:-1] + v[1:]) / 2,
                                         [wrap - TWO_PI if wrap >= TWO_PI else wrap]]))
        first = np.searchsorted(bounds, lo_edge, side="left")
        count = np.searchsorted(bounds, hi_edge, side="right") - first
        # A boundary on a level (two levels 2 pi apart): searched.
        count += np.array([np.isin(bounds[f : f + n_b], v).any()
                           for f, n_b in zip(first, count, strict=True)]) * 2
        centre = torch.from_numpy((np.arange(LUT_BINS) + 0.5) * width)
        flat = _nearest_level(centre, curve).numpy()
        glo[c], ghi[c] = flat, flat
        one = np.flatnonzero(count == 1)
        m = bounds[first[one]]
        hi = np.searchsorted(v, m, side="left")
        vhi[c, one] = np.where(hi < k, v[np.minimum(hi, k - 1)], v[0] + TWO_PI)
        vlo[c, one] = np.where(hi >= 1, v[np.maximum(hi - 1, 0)], v[-1] - TWO_PI)
        ghi[c, one] = levels[c, hi % k]
        glo[c, one] = levels[c, (hi - 1) % k]
        scan[c] = count >= 2
    default = np.array([c.is_default for c in curves])
    counts = np.array([len(c.phase_rad) for c in curves], np.int64)
    return LevelTables(default, values, levels, counts, starts, vlo, vhi, glo, ghi, scan)


def double_phase_grey(
    field: torch.Tensor | np.ndarray,
    amplitude_scale: float,
    curves: Sequence[PhaseCurve],
    *,
    sign: int = 1,
    invert: bool = False,
    zero_below: float = ZERO_BELOW,
    gain: torch.Tensor | np.ndarray | None = None,
) -> tuple[np.ndarray, tuple[float, ...]]:
    """`double_phase` then `phase_to_grey` in one pass: a field `[C, H, W]` (complex64; any
    strides) -> grey levels `[C, H, W]` uint8 and the clipped fraction per channel.

    `gain` (`[C, H, W]` float32, or None) multiplies the field first. The grey levels are
    `double_phase_grey_reference`'s except where float32 rounding of the amplitude moves a pixel
    across zero_below, or its phase across a decision boundary (then by one step of the curve;
    measured: 2e-6 of the pixels, tests/optics/test_coders_against_reference.py). A field with
    NaN or Inf is a ValueError. A top-left crop of a contiguous complex64 tensor (a padded
    propagation's output) is read in place; numba's threads (`numba.set_num_threads`) share the
    rows.
    """

    scale = _validate.positive("amplitude_scale", amplitude_scale)
    u, h, w = _rows_base(field)
    n_c = u.shape[0]
    per_channel = _curves_per_channel(curves, n_c, sign)
    tables = level_tables(tuple(per_channel))
    if gain is None:
        g = np.ones((1, 1, 1), np.float32)
    else:
        g = gain.detach().numpy() if isinstance(gain, torch.Tensor) else np.asarray(gain)
        g = np.ascontiguousarray(g, np.float32)
        if g.shape != (n_c, h, w):
            raise ValueError(f"gain has shape {g.shape}: expected the field's {(n_c, h, w)}")
    sums = np.empty((n_c, h), np.complex128)
    _coding.channel_sums(u, h, w, g, gain is not None, sums)
    # The circular mean phase per channel, rounded to float32 as double_phase's is.
    mean = np.angle(sums.sum(axis=1)).astype(np.float32).astype(np.float64)
    rot = np.exp(-1j * mean)
    out = np.empty((n_c, h, w), np.uint8)
    clipped = np.empty(n_c * h, np.int64)
    bad = np.empty(n_c * h, np.int64)
    _coding.code_rows(u, h, w, g, gain is not None, np.float32(scale),
                      np.float32(empty_below(zero_below)),
                      np.float32(AMPLITUDE_CEILING), rot, float(sign), tables, bool(invert),
                      zero_grey(per_channel, sign, invert), out, clipped, bad)
    if bad.any():
        raise _nonfinite(u, h, w, g, bad)
    fraction = clipped.reshape(n_c, h).sum(axis=1) / (h * w)
    return out, tuple(float(f) for f in fraction)


# -- the device coder (torch) -------------------------------------------------------------------

# The torch twin of `double_phase_grey`, for frames coded on a GPU (`nhfd.pipeline.encoder`).
# Bins of [0, 2 pi) in its table of a curve other than the default one: a phase within half a
# bin (5e-5 rad) of a decision boundary may get the neighbouring level.
DEVICE_LUT_BINS = 65536


class DeviceCurves(NamedTuple):
    """The phase -> grey curves as `device_grey` reads them, on one device: `lut` `[C, BINS]`
    uint8 (None when every curve is the default one: rounding), and `zero` `[C, 2]` uint8, the
    grey levels of amplitude 0 on even and odd pixels (`nhfd.spec.zero_grey`)."""

    lut: torch.Tensor | None
    zero: torch.Tensor


@functools.lru_cache(maxsize=16)
def device_curves(curves: tuple[PhaseCurve, ...], sign: int, invert: bool, n_colours: int,
                  device: str) -> DeviceCurves:
    """One curve per colour (a single curve serves all), as `DeviceCurves` on `device`: each
    row of the table is `phase_to_grey` of its bins' centres."""
    per = _curves_per_channel(curves, n_colours, sign)
    zero = torch.from_numpy(zero_grey(per, sign, invert)).to(device)
    if all(c.is_default for c in per):
        return DeviceCurves(None, zero)
    centres = (torch.arange(DEVICE_LUT_BINS, dtype=torch.float64) + 0.5) * (
        TWO_PI / DEVICE_LUT_BINS)
    lut = phase_to_grey(centres.expand(n_colours, 1, DEVICE_LUT_BINS), per, invert=invert)
    return DeviceCurves(lut[:, 0].to(device), zero)


def device_grey(field: torch.Tensor, amplitude_scale: float, curves: DeviceCurves, *,
                sign: int = 1, invert: bool = False, zero_below: float = ZERO_BELOW,
                gain: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`double_phase_grey` in torch on the field's device (elementwise passes, no
    host synchronisation): field `[C, h, w]` complex64 (any strides) -> grey `[C, h, w]` uint8,
    the clipped fraction per colour `[C]` float64 and the count of non-finite amplitudes `[]`.

    The same definitions: |u| (x gain) / scale, its clipped count and zero_below test exactly;
    the phase `arg(u e^{-i mean} (a +- i sqrt(1 - a^2)))`, + on even (row + column), the
    circular mean from a complex128 sum rounded to float32; the default curve rounds, another
    curve is looked up in `curves.lut`; a pixel below zero_below gets the zero pattern's level.
    The phase is float32 here (float64 in numba's pass), so a pixel within ~2e-6 rad of a
    decision boundary (or half a table bin of one) may differ from `double_phase_grey_reference`
    by one level of the curve (measured: 5e-6 of the pixels with the default curve, 8e-4 with a
    calibrated one; tests/optics/test_coders_against_reference.py)."""
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
    empty = (a < empty_below(zero_below)) | ~finite
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
    p = torch.where(p < 0, p + TWO_PI, p)
    if curves.lut is None:
        g = torch.round(p / TWO_PI * GREY_LEVELS).long() % GREY_LEVELS
        g = (GREY_LEVELS - 1 - g) if invert else g
        grey = g.to(torch.uint8)
    else:
        bins = curves.lut.shape[1]
        idx = (p * (bins / TWO_PI)).long().clamp(0, bins - 1)
        grey = torch.gather(curves.lut, 1, idx.reshape(c, -1)).reshape(c, h, w)
    zero = curves.zero[:, parity]  # [C, h, w]: the zero pattern's levels
    return torch.where(empty, zero, grey), clipped, bad
