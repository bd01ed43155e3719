"""The torch-free vocabulary of the panel (layer L0): grey levels, phase curves, the zero pattern.

NumPy and the standard library only, so the daemon's control plane (`nhfd.daemon`) and the
calibration loader (`nhfd.calibration`, `nhfd.calibration`) can use these without
importing torch; `nhfd.optics` re-exports `PhaseCurve` and codes fields with these definitions.

The zero pattern is the one definition of what the panel shows for zero amplitude: the blank
frame, the panel around a coded window and the coder's empty pixels all come from `zero_grey`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

GREY_LEVELS = 256
# Plausible optics in SI units (the optics core and the light-field renderer refuse values
# outside): a value beyond is almost always a unit slip, nanometres or micrometres given as
# metres, which would otherwise give a silently wrong, finite answer.
WAVELENGTH_RANGE_M = (100e-9, 10e-6)
PITCH_RANGE_M = (0.1e-6, 1e-3)
TWO_PI = 2 * math.pi
# Double-phase coding of amplitude 0: phase 0 +- acos(0), + on pixels whose row + column is even.
# The two phases cancel on the checkerboard, whose light the Fourier aperture blocks.
ZERO_PHASE_RAD = (math.pi / 2, -math.pi / 2)


@dataclass(frozen=True)
class PhaseCurve:
    """The panel's phase response at one wavelength: `phase_rad[g]` for grey level g, increasing.

    The range may be less or more than 2 pi; quantisation picks the grey level whose phase is
    nearest on the circle.
    """

    phase_rad: tuple[float, ...]

    def __post_init__(self) -> None:
        table = tuple(float(v) for v in self.phase_rad)
        if len(table) < 2 or not all(math.isfinite(v) for v in table):
            raise ValueError("phase curve needs >= 2 finite phase values")
        if any(b <= a for a, b in itertools.pairwise(table)):
            raise ValueError("phase curve must increase strictly with grey level")
        object.__setattr__(self, "phase_rad", table)

    @classmethod
    def linear(cls, stroke_rad: float = TWO_PI, levels: int = GREY_LEVELS) -> PhaseCurve:
        """Grey g shows `stroke * g / levels` (the default quantisation when stroke = 2 pi)."""
        stroke = float(stroke_rad)
        if not math.isfinite(stroke) or stroke <= 0:
            raise ValueError(f"phase stroke_rad = {stroke_rad!r}: must be a finite number > 0")
        return cls(tuple(stroke * g / levels for g in range(levels)))

    @property
    def is_default(self) -> bool:
        """Whether this is the linear 2 pi curve over 256 levels (quantisation then rounds)."""
        return self == PhaseCurve.linear()


def phase_curves(stroke_rad: Sequence[float],
                 tables_rad: Sequence[Sequence[float]] = ()) -> list[PhaseCurve]:
    """The curves in use: measured tables (a calibration) when given, else linear curves of the
    configured strokes (`slm.phase_stroke_rad`)."""
    if tables_rad:
        return [PhaseCurve(tuple(t)) for t in tables_rad]
    return [PhaseCurve.linear(stroke) for stroke in stroke_rad]


def nearest_level(phase_rad: float, curve: PhaseCurve) -> int:
    """The grey level whose phase is nearest to `phase_rad` (any real) on the circle: the rule
    of `nhfd.optics.phase_to_grey` (rounding for the default curve; otherwise the sorted wrapped
    table, closed by +-2 pi at its ends, ties to the lower neighbour), in float64."""
    if not math.isfinite(phase_rad):
        raise ValueError(f"phase_rad = {phase_rad!r}: must be finite")
    p = float(np.remainder(np.float64(phase_rad), TWO_PI))
    if curve.is_default:
        return int(np.rint(p / TWO_PI * GREY_LEVELS)) % GREY_LEVELS
    wrapped = np.remainder(np.asarray(curve.phase_rad, np.float64), TWO_PI)
    order = np.argsort(wrapped, kind="stable")
    values = wrapped[order]
    n = len(values)
    hi = int(np.searchsorted(values, p, side="left"))
    lo = hi - 1
    v_hi = values[hi] if hi < n else values[0] + TWO_PI
    v_lo = values[lo] if lo >= 0 else values[-1] - TWO_PI
    return int(order[hi % n] if (v_hi - p) < (p - v_lo) else order[lo % n])


def zero_grey(curves: Sequence[PhaseCurve], sign: int, invert: bool) -> np.ndarray:
    """`[C, 2]` uint8: per colour, the grey levels coding amplitude 0 on the even (row + column)
    and the odd pixels of the checkerboard, through the curves, the phase sign and the grey
    inversion the frames use."""
    if sign not in (1, -1):
        raise ValueError(f"sign = {sign!r}: must be +1 or -1")
    out = np.empty((len(curves), 2), np.uint8)
    for c, curve in enumerate(curves):
        for parity, phase in enumerate(ZERO_PHASE_RAD):
            g = nearest_level(sign * phase, curve)
            out[c, parity] = GREY_LEVELS - 1 - g if invert else g
    return out


def zero_pattern(panel_hw: tuple[int, int], curves: Sequence[PhaseCurve], sign: int,
                 invert: bool) -> np.ndarray:
    """`[C, H, W]` uint8 grey levels that show nothing: `zero_grey` on the pixel checkerboard.
    The blank frame, and the panel around every coded window."""
    h, w = (int(v) for v in panel_hw)
    if h < 1 or w < 1:
        raise ValueError(f"panel_hw = {panel_hw!r}: must be >= 1 pixel each way")
    pair = zero_grey(curves, sign, invert)
    odd = (np.arange(h)[:, None] + np.arange(w)[None, :]) % 2
    return np.ascontiguousarray(pair[:, odd])
