"""Double-phase coding and phase-to-grey quantisation."""

from __future__ import annotations

import math

import pytest
import torch

from nhfd.optics import (
    Aperture,
    PhaseCurve,
    apply_aperture,
    double_phase,
    grey_to_phase,
    phase_to_grey,
)
from nhfd.optics.dpac import _nearest_level

from .fields import band_limited

HALF_BAND = Aperture("square", (0.25,))


def decoded(phase: torch.Tensor) -> torch.Tensor:
    """What the 4f relay passes of a phase-only field: the aperture-filtered exp(i phase)."""
    return apply_aperture(torch.polar(torch.ones_like(phase), phase), HALF_BAND)


def smooth_target(cutoff: float, n: int = 256) -> torch.Tensor:
    """Amplitude in [0.2, 0.8], band-limited to `cutoff` cycles/pixel (a DC term plus a
    band-limited field of max modulus 0.3)."""
    return (0.5 + 0.3 * band_limited((1, n, n), cutoff)).to(torch.complex64)


@pytest.mark.parametrize(("cutoff", "bound"), [(1 / 16, 0.01), (1 / 8, 0.05)])
def test_filtered_double_phase_reproduces_smooth_target(cutoff, bound):
    target = smooth_target(cutoff)
    coded = double_phase(target, 1.0)
    assert float(coded.clipped_fraction) == 0
    # Coding removes the circular mean phase: compare up to that global phase.
    aligned = target * torch.exp(-1j * torch.angle(target.sum()))
    err = float((decoded(coded.phase_rad) - aligned).norm() / aligned.norm())
    assert err < bound


def test_without_the_aperture_the_checkerboard_term_is_large():
    target = smooth_target(1 / 16)
    coded = double_phase(target, 1.0)
    raw = torch.polar(torch.ones_like(coded.phase_rad), coded.phase_rad)
    aligned = target * torch.exp(-1j * torch.angle(target.sum()))
    assert float((raw - aligned).norm() / aligned.norm()) > 0.5


def test_zero_amplitude_outside_the_window_stays_dark():
    n, w = 192, 96
    target = torch.zeros(1, n, n, dtype=torch.complex64)
    s = (n - w) // 2
    target[..., s : s + w, s : s + w] = smooth_target(1 / 16, w)
    coded = double_phase(target, 1.0)
    i = decoded(coded.phase_rad).abs().square()[0]
    inside = float(i[s : s + w, s : s + w].mean())
    ring = torch.ones(n, n, dtype=torch.bool)
    ring[s - 16 : s + w + 16, s - 16 : s + w + 16] = False  # 16 px away from the window
    assert float(i[ring].mean()) < 1e-3 * inside
    # Zero *phase* outside (a flat mirror) would light the surroundings instead.
    mirror = coded.phase_rad.clone()
    mirror[0][ring] = 0.0
    assert float(decoded(mirror).abs().square()[0][ring].mean()) > 0.5 * inside


def test_amplitude_above_scale_is_clipped_and_reported():
    u = torch.full((3, 8, 8), 0.5, dtype=torch.complex64)
    u[1, :2] = 2.0  # a quarter of the green channel is over the scale
    coded = double_phase(u, 1.0)
    assert coded.clipped_fraction.tolist() == [0.0, 0.25, 0.0]
    assert torch.isfinite(coded.phase_rad).all()
    assert float(coded.phase_rad.min()) >= -math.pi and float(coded.phase_rad.max()) < math.pi


def test_fixed_scale_not_per_frame_maximum():
    u = smooth_target(1 / 16, 64)
    a, b = double_phase(u, 2.0), double_phase(0.5 * u, 2.0)
    # Halving the field halves the decoded amplitude: no renormalisation by the frame's maximum.
    ratio = decoded(b.phase_rad).abs().mean() / decoded(a.phase_rad).abs().mean()
    assert abs(float(ratio) - 0.5) < 0.01


def test_extremes_are_finite():
    for u in (torch.zeros(3, 9, 7), torch.ones(3, 9, 7), torch.full((3, 9, 7), 1e30)):
        assert torch.isfinite(double_phase(u, 1.0).phase_rad).all()
    with pytest.raises(ValueError, match="amplitude_scale"):
        double_phase(torch.ones(3, 4, 4), 0.0)


def test_default_quantisation_formula_and_identity_round_trip():
    curve = [PhaseCurve.linear()]
    g = torch.arange(256, dtype=torch.uint8).reshape(1, 16, 16)
    phase = grey_to_phase(g, curve)
    assert torch.allclose(phase.double(), g.double() * 2 * math.pi / 256, atol=1e-6)
    assert torch.equal(phase_to_grey(phase, curve), g)
    assert torch.equal(phase_to_grey(phase - 2 * math.pi, curve), g)  # wrapped


def test_general_curve_path_agrees_with_the_formula_for_the_identity():
    p = torch.rand(1, 64, 64) * 20 - 10
    fast = phase_to_grey(p, [PhaseCurve.linear()])[0].long()
    general = _nearest_level(p[0], PhaseCurve.linear())
    assert torch.equal(fast, general)


@pytest.mark.parametrize("stroke", [0.8 * 2 * math.pi, 1.3 * 2 * math.pi])
def test_nonlinear_curves_pick_the_nearest_phase_on_the_circle(stroke):
    g = torch.arange(256, dtype=torch.float64)
    curve = PhaseCurve(tuple((stroke * (g / 256) ** 1.4).tolist()))
    wanted = torch.rand(1, 32, 32, dtype=torch.float64) * 2 * math.pi
    shown = grey_to_phase(phase_to_grey(wanted, [curve]), [curve])
    err = torch.remainder(shown.double() - wanted + math.pi, 2 * math.pi) - math.pi
    table = torch.tensor(curve.phase_rad, dtype=torch.float64)
    dist = torch.remainder(table[None, :] - wanted.reshape(-1, 1) + math.pi, 2 * math.pi) - math.pi
    best = dist.abs().min(dim=1).values
    assert torch.allclose(err.abs().reshape(-1), best, atol=1e-5)


def test_sign_and_inversion():
    curve = [PhaseCurve.linear()]
    p = torch.rand(3, 8, 8) * 6 - 3
    assert torch.equal(phase_to_grey(p, curve, sign=-1), phase_to_grey(-p, curve))
    assert torch.equal(phase_to_grey(p, curve, invert=True), 255 - phase_to_grey(p, curve))
    g = phase_to_grey(p, curve, sign=-1, invert=True)
    back = grey_to_phase(g, curve, sign=-1, invert=True)
    err = torch.remainder(back - p + math.pi, 2 * math.pi) - math.pi
    assert float(err.abs().max()) <= math.pi / 256 + 1e-5


def test_bad_curves_and_phases_are_refused():
    with pytest.raises(ValueError, match="increase strictly"):
        PhaseCurve((0.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="stroke_rad"):
        PhaseCurve.linear(-1.0)
    with pytest.raises(ValueError, match="NaN or Inf"):
        phase_to_grey(torch.full((1, 2, 2), float("nan")), [PhaseCurve.linear()])
    with pytest.raises(ValueError, match="sign"):
        phase_to_grey(torch.zeros(1, 2, 2), [PhaseCurve.linear()], sign=0)


def test_near_zero_amplitudes_are_coded_as_zeros_so_noise_phase_does_not_leak():
    n, w = 192, 96
    s = (n - w) // 2
    target = torch.zeros(1, n, n, dtype=torch.complex64)
    target[..., s : s + w, s : s + w] = smooth_target(1 / 16, w)
    # FFT round-off and propagation tails: tiny amplitudes with random phase around the content
    gen = torch.Generator().manual_seed(5)
    target = target + 1e-5 * torch.polar(
        torch.ones(1, n, n), 6.3 * torch.rand(1, n, n, generator=gen)
    )
    ring = torch.ones(n, n, dtype=torch.bool)
    ring[s - 16 : s + w + 16, s - 16 : s + w + 16] = False
    inside = float(decoded(double_phase(target, 1.0).phase_rad).abs().square()[0][~ring].mean())
    clean = decoded(double_phase(target, 1.0).phase_rad).abs().square()[0]
    noisy = decoded(double_phase(target, 1.0, zero_below=0.0).phase_rad).abs().square()[0]
    assert float(clean[ring].mean()) < 1e-3 * inside
    assert float(noisy[ring].mean()) > 0.1 * inside
