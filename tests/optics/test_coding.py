"""The fused double-phase coder (`double_phase_grey`, numba) against the torch path it replaces
(`double_phase` then `phase_to_grey`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nhfd.optics import PhaseCurve, double_phase, phase_to_grey
from nhfd.optics._coding import grey_levels
from nhfd.optics.dpac import double_phase_grey, level_tables

SCALE = 2.5
ZERO_BELOW = 0.03
LINEAR = PhaseCurve.linear()
# Measured-looking curves: a nonlinear response over more than 2 pi (levels past 2 pi interleave
# with the first ones on the circle), one short of 2 pi, one over 3 turns, and three turns each
# landing 1e-4 rad after the one before (bins with two decision boundaries: searched).
LONG = PhaseCurve(tuple(0.3 + 7.4 * (g / 255) ** 1.3 for g in range(256)))
SHORT = PhaseCurve(tuple(0.1 + 5.2 * (g / 255) ** 0.8 for g in range(256)))
TURNS = PhaseCurve(tuple(3.1 * 2 * math.pi * g / 256 for g in range(256)))
THRICE = PhaseCurve(tuple(2 * math.pi * g / 85 + 1e-4 * (g // 85) for g in range(256)))


def field(seed: int, shape: tuple[int, int, int] = (3, 96, 160)) -> torch.Tensor:
    """Amplitudes from 0 to 1.3 x the scale (some under zero_below, some clipped), exact zeros
    in a corner, uniform phases."""
    g = torch.Generator().manual_seed(seed)
    amp = torch.rand(shape, generator=g) ** 2 * 1.3 * SCALE
    amp[:, :8, :8] = 0
    return torch.polar(amp, (torch.rand(shape, generator=g) * 2 - 1) * math.pi)


def steps_apart(a: np.ndarray, b: np.ndarray, curves: list[PhaseCurve], invert: bool
                ) -> np.ndarray:
    """How many levels apart two grey frames are on each channel's circle of levels (the order of
    the curve's wrapped phases: 255 and 0 are neighbours on the default curve)."""
    out = np.zeros(a.shape, np.int64)
    for c in range(a.shape[0]):
        curve = curves[c % len(curves)]
        rank = np.argsort(np.argsort(np.remainder(curve.phase_rad, 2 * math.pi), kind="stable"),
                          kind="stable")
        n = len(rank)
        ga, gb = (255 - a[c], 255 - b[c]) if invert else (a[c], b[c])
        d = np.abs(rank[ga.astype(np.int64)] - rank[gb.astype(np.int64)])
        out[c] = np.minimum(d, n - d)
    return out


@pytest.mark.parametrize(("curves", "sign", "invert", "gain"), [
    ([LINEAR], 1, False, False),
    ([LONG, SHORT, LINEAR], -1, True, True),
    ([TURNS], 1, True, False),
    ([THRICE], -1, False, True),
])
def test_fused_coder_is_the_torch_path_within_one_level(curves, sign, invert, gain):
    u = field(1)
    g = (0.6 + torch.rand(u.shape, generator=torch.Generator().manual_seed(2))) if gain else None
    grey, clipped = double_phase_grey(u, SCALE, curves, sign=sign, invert=invert,
                                      zero_below=ZERO_BELOW, gain=g)
    coded = double_phase(u * g if gain else u, SCALE, zero_below=ZERO_BELOW)
    ref = phase_to_grey(coded.phase_rad, curves, sign=sign, invert=invert).numpy()
    assert grey.shape == ref.shape and grey.dtype == np.uint8
    # Clipping and zero_below are decided on the same float32 amplitudes: the same pixels.
    assert clipped == pytest.approx(coded.clipped_fraction.tolist(), abs=1e-6)
    assert 0.05 < min(clipped)
    # The phase is computed in float64 (torch: float32): a level differs only next to a
    # decision boundary, and then by one step.
    d = steps_apart(grey, ref, curves, invert)
    assert d.max() <= 1
    assert np.mean(d != 0) < 1e-3


@pytest.mark.parametrize("curve", [LINEAR, LONG, SHORT, TURNS, THRICE])
def test_level_lookup_is_exactly_phase_to_grey(curve):
    """The table lookup against `phase_to_grey` on the same float64 phases: random ones, and
    every decision boundary with its neighbouring floats (where a table could be off by one)."""
    rng = np.random.default_rng(0)
    v = np.sort(np.remainder(curve.phase_rad, 2 * math.pi))
    wrap = (v[-1] + v[0] + 2 * math.pi) / 2
    bounds = np.concatenate([(v[:-1] + v[1:]) / 2, [wrap % (2 * math.pi)], v])
    near, up, down = [bounds], bounds, bounds
    for _ in range(3):
        up, down = np.nextafter(up, np.inf), np.nextafter(down, -np.inf)
        near += [up, down]
    edges = np.arange(4097) * (2 * math.pi / 4096)
    phases = np.concatenate([rng.uniform(0, 2 * math.pi, 100_000), *near, edges, [0.0]])
    phases = np.clip(phases, 0.0, 2 * math.pi)[None]
    out = np.empty(phases.shape, np.int64)
    tables = level_tables((curve,))
    assert tables.scan.any() == (curve is THRICE)
    grey_levels(phases, tables, out)
    ref = phase_to_grey(torch.from_numpy(phases)[None], [curve]).numpy()[0]
    assert np.array_equal(out, ref)


def test_a_cropped_field_is_read_in_place_and_nan_is_refused():
    base = field(3, (3, 40, 72))
    crop = base[..., :50]  # a padded propagation's output, cropped: not contiguous
    assert not crop.is_contiguous()
    a = double_phase_grey(crop, SCALE, [LONG], zero_below=ZERO_BELOW)
    b = double_phase_grey(crop.contiguous(), SCALE, [LONG], zero_below=ZERO_BELOW)
    assert np.array_equal(a[0], b[0]) and a[1] == b[1]
    # Numpy input too (any strides).
    c = double_phase_grey(crop.numpy()[:, ::2], SCALE, [LONG], zero_below=ZERO_BELOW)
    assert c[0].shape == (3, 20, 50)
    bad = crop.clone()
    bad[1, 3, 4] = complex(float("nan"), 0.0)
    with pytest.raises(ValueError, match=r"1 non-finite value\(s\).*index \(1, 3, 4\)"):
        double_phase_grey(bad, SCALE, [LONG])
    with pytest.raises(ValueError, match="sign"):
        double_phase_grey(crop, SCALE, [LONG], sign=0)


def test_both_coders_refuse_a_non_finite_field_with_the_same_count_and_first_index():
    """The torch coder used to turn the channel into NaN phases and report 0 clipped."""
    u = field(4)
    u[2, 50, 7] = complex(float("inf"), 0.0)
    u[1, 90, 150] = complex(0.0, float("-inf"))
    u[1, 10, 20] = complex(float("nan"), float("nan"))
    message = r"field has 3 non-finite value\(s\) \(NaN or Inf\), the first at index \(1, 10, 20\)"
    with pytest.raises(ValueError, match=message) as torch_path:
        double_phase(u, SCALE)
    with pytest.raises(ValueError, match=message) as fused:
        double_phase_grey(u, SCALE, [LINEAR])
    assert str(torch_path.value) == str(fused.value)
    # A gain that makes a finite pixel infinite is the pixel's fault in the fused coder too.
    gain = np.ones((3, 96, 160), np.float32)
    gain[0, 5, 6] = np.inf
    with pytest.raises(ValueError, match=r"1 non-finite value\(s\).*index \(0, 5, 6\)"):
        double_phase_grey(field(4), SCALE, [LINEAR], gain=gain)
