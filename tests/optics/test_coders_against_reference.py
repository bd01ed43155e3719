"""The two fast double-phase coders against the reference (`double_phase_grey_reference`):
numba's CPU pass (`double_phase_grey`) and the torch device pass (`device_grey`, on the CPU here
and on CUDA when torch sees a GPU).

Where: the full panel as the encoder codes it for a 1920 x 1080 window with 2x padding (the
region is the panel, 1080 x 1920, given to the coder as the top-left crop of the 2160 x 3840
padded propagation grid, read in place), on seeded random fields; and a small field of extremes
(zero amplitude, amplitudes at zero_below and a few float32 steps either side, the clip edge
and far above it, phases at +-pi and coded phases at the 0 / 2 pi wrap, gain 0). The default
curve and calibrated curves (one per colour, one over 2 pi), both signs, inverted or not.

The criterion. The reference computes in float64; the fast coders round the amplitude, the
scale and zero_below to float32 (numba computes the phase in float64 from there; the device
coder in float32, and looks a calibrated curve up in a 65536-bin table). So a pixel may differ
from the reference only where rounding can move it across a decision:

- next to zero_below: its float64 amplitude within 2^-21 (relative) of the threshold, where
  it may be coded as zero amplitude in one and not in the other; or
- next to a level boundary: one level apart on the curve's circle of levels, and the
  reference's phase within `tolerance_rad` of a decision boundary of the curve, that is
  5e-7 rad (numba) or 2e-6 rad (device; + pi / 65536, half a table bin, with a calibrated
  curve), plus the amplitude's rounding carried through acos (2^-21 a / sqrt(1 - a^2)).

Every other pixel is identical, and so is every zero-amplitude decision away from zero_below.
The clipped fractions differ at most by the pixels within 2^-21 of amplitude 1.

Measured (the full-panel cases below, seed 0, 6.2 M pixels a field, on this project's 2-core CPU
machine): numba differed from the reference on 6 to 12 pixels a field (at most 1.9e-6 of them;
the farthest 1.0e-7 rad from a boundary); the device coder on 29 and 32 with the default curve
(5.1e-6; 5.4e-7 rad) and on 5058 and 5188 with the calibrated curves (8.3e-4: its table; 4.8e-5
rad, half a bin). All one level apart, none near zero_below; one clipped pixel of a colour (at
amplitude 1 within float32 rounding) counted by the reference and not by the fast coders. On the
extremes field (8 curve / sign / inversion cases, both zero_below) numba differed nowhere and the
device coder on 4 pixels of 73,728, and the zero_below edges, float32 steps included, were decided
alike. The allowed fractions below are two to four times the largest measured. (Before
AMPLITUDE_CEILING was rounded to float32, the clipped pixels' phases differed by 9.4e-6 rad and
about 300 pixels a field differed.)
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nhfd.optics import PhaseCurve
from nhfd.optics.dpac import (
    AMPLITUDE_CEILING,
    AMPLITUDE_FLOOR,
    DEVICE_LUT_BINS,
    ZERO_BELOW,
    device_curves,
    device_grey,
    double_phase_grey,
    double_phase_grey_reference,
    empty_below,
)
from nhfd.spec import zero_pattern

TWO_PI = 2 * math.pi
SCALE = 2.5
PANEL_HW = (1080, 1920)  # the coded region of a 1920 x 1080 window: the panel
PADDED_HW = (2160, 3840)  # optics.padding = "2x": the propagation's grid, the region its crop
DEFAULT = (PhaseCurve.linear(),)
# A calibration's curves, one per colour: over 2 pi (levels interleave on the circle), short
# of 2 pi, and a gamma-like one.
CALIBRATED = (PhaseCurve(tuple(0.3 + 7.4 * (g / 255) ** 1.3 for g in range(256))),
              PhaseCurve(tuple(0.1 + 5.2 * (g / 255) ** 0.8 for g in range(256))),
              PhaseCurve(tuple(2.3 * math.pi * (g / 255) ** 1.2 for g in range(256))))
ROUNDING = 2.0**-21  # relative: a few float32 roundings of an amplitude
BASE_TOLERANCE_RAD = {"numba": 5e-7, "device": 2e-6}
# The allowed fraction of differing pixels (about twice the measured, module docstring).
# The device coder's allowance with the default curve is four times the measured: CUDA's float32
# atan2 may be less accurate than the CPU's.
ALLOWED_FRACTION = {("numba", True): 5e-6, ("numba", False): 5e-6,
                    ("device", True): 2e-5, ("device", False): 2e-3}
CUDA = pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                     reason="needs CUDA"))


def boundary_distance_rad(phase_rad: np.ndarray, curve: PhaseCurve) -> np.ndarray:
    """Per phase (rad, any real), the distance on the circle to the nearest phase at which
    `curve`'s nearest level changes: half-steps of the rounding for the default curve, else
    the midpoints between neighbouring wrapped levels (and across 2 pi)."""
    p = np.remainder(phase_rad, TWO_PI)
    if curve.is_default:
        step = TWO_PI / 256
        x = p / step
        return np.abs(x - np.floor(x) - 0.5) * step
    v = np.sort(np.remainder(curve.phase_rad, TWO_PI))
    b = np.sort(np.remainder(np.concatenate([(v[:-1] + v[1:]) / 2, [(v[-1] + v[0] + TWO_PI) / 2]]),
                            TWO_PI))
    i = np.searchsorted(b, p)
    hi = np.where(i < len(b), b[np.minimum(i, len(b) - 1)], b[0] + TWO_PI)
    lo = np.where(i > 0, b[np.maximum(i - 1, 0)], b[-1] - TWO_PI)
    return np.minimum(hi - p, p - lo)


def levels_apart(a: np.ndarray, b: np.ndarray, curve: PhaseCurve, invert: bool) -> np.ndarray:
    """How many levels apart two grey images `[H, W]` are on the curve's circle of levels (the
    order of its wrapped phases: 255 and 0 are neighbours on the default curve)."""
    rank = np.argsort(np.argsort(np.remainder(curve.phase_rad, TWO_PI), kind="stable"),
                      kind="stable")
    ga, gb = (255 - a, 255 - b) if invert else (a, b)
    d = np.abs(rank[ga.astype(np.int64)] - rank[gb.astype(np.int64)])
    return np.minimum(d, len(rank) - d)


def tolerance_rad(coder: str, curve: PhaseCurve, amplitude: np.ndarray) -> np.ndarray:
    """How far from a decision boundary the fast coder's phase may land on its other side."""
    a = np.minimum(amplitude, AMPLITUDE_CEILING)
    lut = coder == "device" and not curve.is_default
    return (BASE_TOLERANCE_RAD[coder] + ROUNDING * a / np.sqrt(1.0 - a * a)
            + (math.pi / DEVICE_LUT_BINS if lut else 0.0))


def check_against_reference(coder: str, grey: np.ndarray, clipped: np.ndarray, ref, curves,
                            sign: int, invert: bool, zero_below: float) -> int:
    """The module's criterion for one fast coder's output; returns how many pixels differ."""
    want = ref.grey.numpy()
    assert grey.shape == want.shape and grey.dtype == np.uint8
    amplitude = ref.amplitude.numpy()
    threshold = empty_below(zero_below)
    near_empty = np.abs(amplitude - threshold) <= ROUNDING * threshold
    phase = ref.phase_rad.numpy() * sign
    per = list(curves) * len(want) if len(curves) == 1 else list(curves)
    differ = grey != want
    for c, curve in enumerate(per):
        d = differ[c] & ~near_empty[c]
        if not d.any():
            continue
        empty = amplitude[c][d] < threshold
        apart = levels_apart(grey[c][d], want[c][d], curve, invert)
        dist = boundary_distance_rad(phase[c][d], curve)
        tol = tolerance_rad(coder, curve, amplitude[c][d])
        bad = empty | (apart != 1) | (dist > tol)
        assert not bad.any(), (
            f"{coder}, colour {c}: {int(bad.sum())} pixel(s) differ unexplained; the first: "
            f"amplitude {amplitude[c][d][bad][0]!r}, reference grey {want[c][d][bad][0]}, "
            f"got {grey[c][d][bad][0]}, {apart[bad][0]} level(s) apart, "
            f"{dist[bad][0]:.3g} rad from a boundary (tolerance {tol[bad][0]:.3g})")
    near_one = (np.abs(amplitude - 1.0) <= ROUNDING).sum(axis=(-2, -1))
    pixels = want.shape[-2] * want.shape[-1]
    assert np.all(np.abs(np.asarray(clipped) - ref.clipped_fraction.numpy()) * pixels
                  <= near_one + 1e-6)
    return int(differ.sum())


def fast_coders(u: torch.Tensor, curves, sign: int, invert: bool, zero_below: float,
                gain: torch.Tensor | None, device: str
                ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """numba's grey and clipped fractions, and the device coder's (run on `device`)."""
    grey, clipped = double_phase_grey(u, SCALE, curves, sign=sign, invert=invert,
                                      zero_below=zero_below, gain=gain)
    dc = device_curves(tuple(curves), sign, invert, u.shape[0], device)
    d_grey, d_clipped, bad = device_grey(u.to(device), SCALE, dc, sign=sign, invert=invert,
                                         zero_below=zero_below,
                                         gain=None if gain is None else gain.to(device))
    assert int(bad) == 0
    return {"numba": (grey, np.asarray(clipped)),
            "device": (d_grey.cpu().numpy(), d_clipped.cpu().numpy())}


@pytest.fixture(scope="module")
def panel_field() -> tuple[torch.Tensor, torch.Tensor]:
    """A seeded field on the full panel, as the encoder hands it over: the top-left 1080 x 1920
    crop of a 2160 x 3840 complex64 grid. Amplitudes 0 to 1.3 x the scale (a third under
    zero_below or clipped), a block of exact zeros, uniform phases; and a gain map
    `[3, 1080, 1920]` in [0.6, 1.4]."""
    g = torch.Generator().manual_seed(0)
    grid = torch.zeros((3, *PADDED_HW), dtype=torch.complex64)
    u = grid[:, : PANEL_HW[0], : PANEL_HW[1]]
    amp = torch.rand((3, *PANEL_HW), generator=g) ** 2 * 1.3 * SCALE
    amp[:, :64, :64] = 0
    u.copy_(torch.polar(amp, (torch.rand((3, *PANEL_HW), generator=g) * 2 - 1) * math.pi))
    gain = 0.6 + 0.8 * torch.rand((3, *PANEL_HW), generator=g)
    return u, gain


@pytest.mark.parametrize("device", ["cpu", CUDA])
@pytest.mark.parametrize(("curves", "sign", "invert", "with_gain"), [
    (DEFAULT, 1, False, False),
    (DEFAULT, -1, True, True),
    (CALIBRATED, 1, True, False),
    (CALIBRATED, -1, False, True),
], ids=["default", "default-conjugate-inverted-gain", "calibrated-inverted",
        "calibrated-conjugate-gain"])
def test_the_fast_coders_are_the_reference_on_the_full_panel(panel_field, curves, sign, invert,
                                                              with_gain, device):
    u, gain_map = panel_field
    assert not u.is_contiguous() and u.shape == (3, *PANEL_HW)  # a crop, read in place
    gain = gain_map if with_gain else None
    ref = double_phase_grey_reference(u, SCALE, curves, sign=sign, invert=invert, gain=gain)
    # The field is what it should be: about a tenth clipped, many pixels coded as zeros.
    assert ref.clipped_fraction.min() > 0.05
    assert (ref.amplitude < ZERO_BELOW).double().mean() > 0.1
    out = fast_coders(u, curves, sign, invert, ZERO_BELOW, gain, device)
    for coder, (grey, clipped) in out.items():
        n = check_against_reference(coder, grey, clipped, ref, curves, sign, invert, ZERO_BELOW)
        assert n <= ALLOWED_FRACTION[coder, curves is DEFAULT] * grey.size, (coder, n)


def extreme_field(zero_below: float) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
    """`[3, 32, 96]` complex64: a background of 0.5 x the scale at phase 0 (so the circular mean
    phase is 0 or within rounding of it), and rows of extremes, each value on an even and an odd
    pixel, and beside its conjugate where its phase is not 0 or pi; the last row is background
    (the test puts its gain extremes there). Returns the field and masks `[3, 32, 96]` of the
    cases whose outcome the test states."""
    h, w = 32, 96
    f32 = np.float32
    u = np.full((3, h, w), 0.5 * SCALE, np.complex64)
    masks = {k: np.zeros((3, h, w), bool) for k in ("zero", "below", "clipped")}
    rows: list[tuple[str | None, list[complex]]] = []
    # Exact zeros, with every sign of zero.
    rows.append(("zero", [0j, complex(-0.0, 0.0), complex(0.0, -0.0), complex(-0.0, -0.0)]))
    # The zero_below edge: float32 amplitudes a few steps either side of threshold x scale, on
    # the real and imaginary axes (exact amplitudes), and 1e-3 away (clear of rounding).
    t = f32(empty_below(zero_below) * SCALE)
    steps = [t]
    up = down = t
    for _ in range(4):
        up, down = np.nextafter(up, f32(np.inf)), np.nextafter(down, f32(0))
        steps += [up, down]
    rows.append((None, [complex(s, 0) for s in steps] + [complex(0, -s) for s in steps]))
    rows.append((None, [complex(-s, 0) for s in steps] + [complex(0, s) for s in steps]))
    rows.append(("below", [complex(t * (1 - 1e-3), 0), complex(0, t * (1 - 1e-3)),
                           complex(-t * (1 - 1e-3), 0)]))
    rows.append((None, [complex(t * (1 + 1e-3), 0), complex(0, t * (1 + 1e-3)),
                           complex(-t * (1 + 1e-3), 0)]))
    # The clip edge: the scale and float32 steps around it, the ceiling, and far above.
    s1 = f32(SCALE)
    edge = [s1]
    up = down = s1
    for _ in range(4):
        up, down = np.nextafter(up, f32(np.inf)), np.nextafter(down, f32(0))
        edge += [up, down]
    edge += [f32(SCALE * AMPLITUDE_CEILING), f32(SCALE * (1 - 2e-6)), f32(SCALE * (1 - 1e-3))]
    rows.append((None, [complex(e, 0) for e in edge] + [complex(-e, 0) for e in edge]))
    rows.append(("clipped", [complex(SCALE * k, 0) for k in (1.001, 1.5, 10.0, 1e30)]
                 + [complex(-SCALE * 1.5, 0), complex(0, SCALE * 10)]))
    # Phases at +-pi (the sign of a zero imaginary part decides arg), and a float32 step off.
    for a in (0.2, 0.5, 0.9, 1.3):
        amp = f32(a * SCALE)
        rows.append((None, [complex(-amp, 0.0), complex(-amp, -0.0),
                            complex(-amp, amp * 1e-7), complex(-amp, -amp * 1e-7)]))
    # Coded phases at the 0 / 2 pi wrap of the curve's circle (phase -+ acos(a) on even / odd
    # pixels) and at the +-pi wrap of the coded phase.
    for a in (0.04, 0.3, 0.7, 0.999, 1.2):
        off = math.acos(min(a, AMPLITUDE_CEILING))
        for theta in (-off, off, math.pi - off, off - math.pi):
            for eps in (0.0, 1e-7, -1e-7):
                rows.append((None, [complex(a * SCALE * math.cos(theta + eps),
                                            a * SCALE * math.sin(theta + eps))]))
    # Pack: each value twice (even and odd pixel) and, off the real axis, its conjugate twice.
    cells: list[tuple[str | None, complex]] = []
    for name, values in rows:
        for v in values:
            vv = [v, v] if v.imag == 0 else [v, v, v.conjugate(), v.conjugate()]
            cells += [(name, x) for x in vv]
    per_row = w - 2  # the first two pixels of each row stay background
    assert len(cells) <= per_row * (h - 1)
    for k, (name, v) in enumerate(cells):
        i, j = divmod(k, per_row)
        u[:, i, 2 + j] = v
        if name:
            masks[name][:, i, 2 + j] = True
    field = torch.from_numpy(u)
    # Colour 2 gets every value rotated a quarter turn (the mean phase with it): the
    # imaginary axis for the real one.
    field[2] *= 1j
    return field, masks


@pytest.mark.parametrize("device", ["cpu", CUDA])
@pytest.mark.parametrize("zero_below", [ZERO_BELOW, 0.0])
@pytest.mark.parametrize("curves", [DEFAULT, CALIBRATED], ids=["default", "calibrated"])
def test_the_fast_coders_are_the_reference_at_the_extremes(curves, zero_below, device):
    u, masks = extreme_field(zero_below)
    h, w = u.shape[-2:]
    gain = torch.ones(u.shape)
    gain[:, -1, w // 2 :] = 0.0  # a gain of 0: amplitude 0, the zero pattern
    gain[:, -1, : w // 2] = 1e3  # a large gain: clipped
    for sign in (1, -1):
        for invert in (False, True):
            per = list(curves) * 3 if len(curves) == 1 else list(curves)
            zero = zero_pattern((h, w), per, sign, invert)
            for g in (None, gain):
                ref = double_phase_grey_reference(u, SCALE, curves, sign=sign, invert=invert,
                                                  zero_below=zero_below, gain=g)
                want = ref.grey.numpy()
                # The definition's facts at the extremes.
                assert np.array_equal(want[masks["zero"]], zero[masks["zero"]])
                assert np.array_equal(want[masks["below"]], zero[masks["below"]])
                assert (ref.amplitude.numpy()[masks["clipped"]] > 1).all()
                if g is not None:
                    assert np.array_equal(want[:, -1, w // 2 :], zero[:, -1, w // 2 :])
                out = fast_coders(u, curves, sign, invert, zero_below, g, device)
                for coder, (grey, clipped) in out.items():
                    check_against_reference(coder, grey, clipped, ref, curves, sign, invert,
                                            zero_below)
                    # Exact zeros, and amplitudes clear of zero_below, decide alike.
                    for case in ("zero", "below"):
                        assert np.array_equal(grey[masks[case]], zero[masks[case]]), (coder, case)


def test_amplitude_zero_is_the_zero_pattern_even_without_a_threshold():
    """zero_below = 0 codes every pixel's phase, but amplitude 0 has none: it gets the zero
    pattern (the fast coders used to write phase 0 on both parities there: a flat mirror).
    Amplitudes below float32's normal range count as 0 (AMPLITUDE_FLOOR)."""
    u = torch.full((1, 4, 6), 0.5 + 0.5j, dtype=torch.complex64)
    u[0, :2] = 0.0
    u[0, 3, :2] = AMPLITUDE_FLOOR * SCALE / 4  # subnormal / scale: below the floor
    u[0, 3, 2:4] = 1e-30  # tiny but a real phase
    zero = zero_pattern((4, 6), DEFAULT, 1, False)
    ref = double_phase_grey_reference(u, SCALE, DEFAULT, zero_below=0.0)
    grey, _ = double_phase_grey(u, SCALE, DEFAULT, zero_below=0.0)
    dev, _, _ = device_grey(u, SCALE, device_curves(DEFAULT, 1, False, 1, "cpu"), zero_below=0.0)
    for out in (ref.grey.numpy(), grey, dev.numpy()):
        assert np.array_equal(out[0, :2], zero[0, :2])
        assert np.array_equal(out[0, 3, :2], zero[0, 3, :2])
        assert not np.array_equal(out[0, 3, 2:4], zero[0, 3, 2:4])  # a phase of its own


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_a_non_finite_field_is_refused_by_all_three(device):
    """The reference and numba raise the same ValueError (count and first index); the device
    coder counts the non-finite amplitudes for its caller to refuse (`Encoder.check_coded`) and
    writes no NaN (grey is uint8)."""
    u, _ = extreme_field(ZERO_BELOW)
    u[2, 20, 7] = complex(float("inf"), 0.0)
    u[1, 9, 50] = complex(0.0, float("-inf"))
    u[1, 3, 20] = complex(float("nan"), float("nan"))
    message = r"field has 3 non-finite value\(s\) \(NaN or Inf\), the first at index \(1, 3, 20\)"
    with pytest.raises(ValueError, match=message) as ref:
        double_phase_grey_reference(u, SCALE, CALIBRATED)
    with pytest.raises(ValueError, match=message) as fused:
        double_phase_grey(u, SCALE, CALIBRATED)
    assert str(ref.value) == str(fused.value)
    dc = device_curves(CALIBRATED, 1, False, 3, device)
    _, _, bad = device_grey(u.to(device), SCALE, dc)
    assert int(bad) == 3
    # A gain that makes a finite pixel infinite is that pixel's fault in all three.
    gain = torch.ones(u.shape)
    gain[0, 5, 6] = float("inf")
    finite, _ = extreme_field(ZERO_BELOW)
    with pytest.raises(ValueError, match=r"1 non-finite value\(s\).*index \(0, 5, 6\)"):
        double_phase_grey_reference(finite, SCALE, DEFAULT, gain=gain)
    with pytest.raises(ValueError, match=r"1 non-finite value\(s\).*index \(0, 5, 6\)"):
        double_phase_grey(finite, SCALE, DEFAULT, gain=gain)
    dc = device_curves(DEFAULT, 1, False, 3, device)
    assert int(device_grey(finite.to(device), SCALE, dc, gain=gain.to(device))[2]) == 1
