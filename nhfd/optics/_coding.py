"""Numba kernels of the fused double-phase coder (`nhfd.optics.dpac.double_phase_grey`).

One pass sums each channel's field (its circular mean phase), a second codes every pixel:
amplitude gain, amplitude / scale with the clipped count, the clamp and zero_below, the phase
relative to the mean plus or minus acos(a) on the checkerboard, the sign and the grey level, written
as uint8; a pixel below zero_below (or of amplitude 0: `dpac.empty_below`) gets the zero pattern's
grey level (`nhfd.spec.zero_grey`, the blank frame's). Same definitions as the reference,
`dpac.double_phase_grey_reference` (`double_phase` + `phase_to_grey` in float64;
tests/optics/test_coders_against_reference.py), computed differently:

- The amplitude is computed exactly as torch does it (hypotf is sqrt((double) re^2 + im^2)
  rounded to float32, divided by the float32 scale), so the clipped count and the zero_below test
  are the torch path's, pixel for pixel.
- The phase `angle(u) - mean +- acos(a)` is the argument of `u e^{-i mean} (a +- i sqrt(1 - a^2))`,
  one atan2 (a Cephes-style polynomial, branch-free so the loop vectorises; libm's scalar atan2f
  and acosf cost ~40 ns a pixel, more than the whole torch path) in float64 instead of three
  float32 roundings. Grey levels therefore agree with the torch path except within ~1e-6 rad of a
  decision boundary, where they differ by one step of the curve (tests/optics/test_coding.py;
  against the float64 reference, tests/optics/test_coders_against_reference.py).
- Grey levels: the default curve rounds like `phase_to_grey`; any other curve is the nearest level
  on the circle through a 4096-bin table (`dpac.LevelTables`): a bin holding one decision boundary
  makes `_nearest_level`'s own comparison between the boundary's two levels, one holding none
  has a constant level, one holding several (curves much longer than 2 pi) is searched. The same
  levels as `_nearest_level` for the same phase, exactly (tests/optics/test_coding.py).

numba compiles the kernels (or loads them from its cache) on their first call, not on import.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

TWO_PI = 2 * math.pi
HALF_PI = 0.5 * math.pi
QUARTER_PI = 0.25 * math.pi
TAN_PI_8 = 0.41421356237309503
# Bins of [0, 2 pi) in the tables of curves other than the default one (dpac.LevelTables).
LUT_BINS = 4096
# The phase `_coded_phase` returns for a pixel coded as zero amplitude (a real phase is >= 0).
EMPTY = -1.0

# atan(x) = x + x^3 P(x^2) / Q(x^2) on |x| <= tan(pi / 8) (Cephes atan.c), Horner form.
_P0, _P1, _P2, _P3, _P4 = (-8.750608600031904122785e-1, -1.615753718733365076637e1,
                           -7.500855792314704667340e1, -1.228866684490136173410e2,
                           -6.485021904942025371773e1)
_Q0, _Q1, _Q2, _Q3, _Q4 = (2.485846490142306297962e1, 1.650270098316988542046e2,
                           4.328810604912902668951e2, 4.853903996359136964868e2,
                           1.945506571482613964425e2)


# error_model="numpy": a float division never checks for zero (no branch, so loops vectorise).
@njit(cache=True, inline="always", error_model="numpy")
def _atan2(y, x):
    """atan2 in float64 without libm (selects only, so a loop around it vectorises); ~1e-16."""
    ax = abs(x)
    ay = abs(y)
    mx = max(ax, ay)
    mn = min(ax, ay)
    t = mn / mx
    t = t if mx > 0.0 else 0.0
    big = t > TAN_PI_8
    r = (t - 1.0) / (t + 1.0) if big else t
    z = r * r
    p = (((_P0 * z + _P1) * z + _P2) * z + _P3) * z + _P4
    q = ((((z + _Q0) * z + _Q1) * z + _Q2) * z + _Q3) * z + _Q4
    a = r + r * z * p / q
    a = a + QUARTER_PI if big else a
    a = HALF_PI - a if ay > ax else a
    a = math.pi - a if x < 0.0 else a
    return -a if y < 0.0 else a


@njit(cache=True, inline="always", error_model="numpy")
def _coded_phase(re, im, parity, scale, zero_below, ceiling, rr, ri, sign):
    """One pixel: (the coded phase in [0, 2 pi] (float64, before the curve), amplitude > 1,
    non-finite). re, im: the field (float32, gain applied)."""
    # |u| as torch's hypotf (double sqrt rounded to float32), / scale in float32.
    mag = np.float32(math.sqrt(np.float64(re) * re + np.float64(im) * im))
    amp = mag / scale
    a = min(max(amp, np.float32(0.0)), ceiling)
    empty = a < zero_below
    # arg(u e^{-i mean} (a +- i sqrt(1 - a^2))), + on even rows + cols; an empty pixel's
    # (the unit vector (0, +-1)) is not used: `code_rows` writes the zero pattern's grey there.
    a64 = 0.0 if empty else np.float64(a)
    s = math.sqrt(1.0 - a64 * a64)
    s = -s if parity else s
    wr = 1.0 if empty else re * rr - im * ri
    wi = 0.0 if empty else re * ri + im * rr
    p = _atan2(wi * a64 + wr * s, wr * a64 - wi * s) * sign
    p = p + TWO_PI if p < 0.0 else p
    # EMPTY marks the pixel for the zero pattern's grey level (nhfd.spec.zero_grey).
    p = EMPTY if empty else p
    return p, amp > np.float32(1.0), not math.isfinite(amp)


@njit(parallel=True, cache=True)
def channel_sums(u, h, w, gain, has_gain, out):
    """out[c, i] = sum over j < w of u[c, i, j] (x gain), complex128, for the rows i < h."""
    n_c = u.shape[0]
    for k in prange(n_c * h):
        c = k // h
        i = k - c * h
        sr = 0.0
        si = 0.0
        if has_gain:
            for j in range(w):
                v = u[c, i, j]
                g = gain[c, i, j]
                sr += v.real * g
                si += v.imag * g
        else:
            for j in range(w):
                v = u[c, i, j]
                sr += v.real
                si += v.imag
        out[c, i] = complex(sr, si)


@njit(parallel=True, cache=True, error_model="numpy")
def code_rows(u, h, w, gain, has_gain, scale, zero_below, ceiling, rot, sign, tables, invert,
              zero, out, clipped, bad):
    """Double-phase code u[:, :h, :w] (complex64; u C-contiguous, so rows load as vectors) into
    grey levels out [C, h, w] (uint8).

    scale, zero_below, ceiling: float32. rot [C]: e^{-i mean} (complex128). sign: +-1.0.
    tables: `nhfd.optics.dpac.LevelTables` (the curves). zero [C, 2] (uint8): the grey levels
    of amplitude 0 on even and odd pixels (`nhfd.spec.zero_grey`, sign and inversion applied),
    written where the amplitude is below zero_below. clipped, bad [C * H]: per row, the count
    of amplitudes > 1 and of non-finite amplitudes (their grey level is arbitrary)."""
    n_c = u.shape[0]
    for k in prange(n_c * h):
        c = k // h
        i = k - c * h
        rr = rot[c].real
        ri = rot[c].imag
        phase = np.empty(w)
        n_clip = 0
        n_bad = 0
        # The phases: one vectorised loop (with or without the gain).
        if has_gain:
            for j in range(w):
                v = u[c, i, j]
                g = gain[c, i, j]
                p, over, nonfinite = _coded_phase(v.real * g, v.imag * g, (i + j) & 1, scale,
                                                  zero_below, ceiling, rr, ri, sign)
                phase[j] = p
                n_clip += over
                n_bad += nonfinite
        else:
            for j in range(w):
                v = u[c, i, j]
                p, over, nonfinite = _coded_phase(v.real, v.imag, (i + j) & 1, scale,
                                                  zero_below, ceiling, rr, ri, sign)
                phase[j] = p
                n_clip += over
                n_bad += nonfinite
        clipped[k] = n_clip
        bad[k] = n_bad
        # The grey levels.
        top = 255 if invert else 0
        step = -1 if invert else 1
        z_even = zero[c, i & 1]
        z_odd = zero[c, (i + 1) & 1]
        if tables.default[c]:
            for j in range(w):
                p = phase[j]
                g = top + step * _default_level(max(p, 0.0))
                out[c, i, j] = (z_odd if j & 1 else z_even) if p < 0.0 else g
        else:
            for j in range(w):
                p = phase[j]
                if p < 0.0:
                    out[c, i, j] = z_odd if j & 1 else z_even
                else:
                    out[c, i, j] = top + step * _table_level(p, tables, c)


@njit(cache=True, inline="always", error_model="numpy")
def _default_level(p):
    """round(p / 2 pi * 256) mod 256, as phase_to_grey's default curve (p in [0, 2 pi])."""
    return np.int64(np.rint(p / TWO_PI * 256.0)) & 255


@njit(cache=True, inline="always", error_model="numpy")
def _nearest_level(p, values, levels, n, starts):
    """The grey level whose wrapped phase is nearest to p (in [0, 2 pi]) on the circle, with the
    comparisons of dpac._nearest_level: hi = the first sorted value >= p (a scan from the bin's
    start index), the circle closed by +-2 pi at the ends, ties to the lower."""
    bins = starts.shape[0]
    b = min(max(np.int64(p * (bins / TWO_PI)), 0), bins - 1)
    hi = starts[b]
    while hi < n and values[hi] < p:
        hi += 1
    lo = hi - 1
    v_hi = values[hi] if hi < n else values[0] + TWO_PI
    v_lo = values[lo] if lo >= 0 else values[n - 1] - TWO_PI
    return levels[hi % n] if (v_hi - p) < (p - v_lo) else levels[lo % n]


@njit(cache=True, inline="always", error_model="numpy")
def _table_level(p, t, c):
    """Channel c's grey level for p in [0, 2 pi] through `LevelTables` t: the bin's one
    comparison (or its constant level), or a search where the bin holds several boundaries."""
    bins = t.starts.shape[1]
    b = min(max(np.int64(p * (bins / TWO_PI)), 0), bins - 1)
    if t.scan[c, b]:
        return _nearest_level(p, t.values[c], t.levels[c], t.counts[c], t.starts[c])
    return t.ghi[c, b] if (t.vhi[c, b] - p) < (p - t.vlo[c, b]) else t.glo[c, b]


@njit(cache=True)
def grey_levels(phase, tables, out):
    """out[c, k] = the grey level of phase[c, k] (float64 in [0, 2 pi]) through channel c's
    curve: the lookup `code_rows` uses, on its own (tests compare it with phase_to_grey)."""
    for c in range(phase.shape[0]):
        for k in range(phase.shape[1]):
            if tables.default[c]:
                out[c, k] = _default_level(phase[c, k])
            else:
                out[c, k] = _table_level(phase[c, k], tables, c)
