"""Acceptance (issue 8) on the simulated bench: the fit recovers the true bench's parameters.

The true bench is richer than the fitted model (wiggly tables, crosstalk, fill factor, zero
order, Gaussian source, sensor noise and response): tolerances are the issue's."""

from __future__ import annotations

import numpy as np
from nhfd.drivers.simcamera import TrueBench


def _dof_m(bench: TrueBench, colour: int) -> float:
    # Depth of field of the filtered system (optics.md): 8 p^2 / lambda at the default aperture.
    return 8 * bench.pitch_m**2 / bench.wavelengths_m[colour]


def test_sign_and_mirror_are_found(bench: TrueBench, fitted) -> None:
    assert fitted.phase_sign == bench.phase_sign == -1
    assert fitted.mirror_x is bench.mirror_x
    assert fitted.residuals["sign_margin_sigma"] > 10


def test_magnification_and_rotation(bench: TrueBench, fitted) -> None:
    assert abs(fitted.magnification / bench.magnification - 1) < 0.005
    assert abs(fitted.rotation_deg - bench.rotation_deg % 360) < 0.2
    assert fitted.magnification_std < 0.005 * fitted.magnification


def test_stage_scale(bench: TrueBench, fitted) -> None:
    assert abs(fitted.stage_scale / bench.stage_scale - 1) < 0.005
    # The scale is tied to 1 / M^2; the focus peaks measure it independently and agree (the
    # check a bench whose stage does not move the camera along the axis would fail).
    assert abs(fitted.residuals["longitudinal_vs_lateral"]) < 0.02


def test_depth_offsets(bench: TrueBench, fitted) -> None:
    # Where green images the SLM plane, and the per-colour offsets, within 5% of the depth of
    # field (in SLM space). Measured on this seed with the bench-model fit: 1.8%, R 2.1%, B 1.3%
    # (the focus-peak estimator alone: 12.3%, 13.1%, 7.7%).
    s0_err_m = (fitted.stage_at_slm_mm - bench.stage_at_slm_mm) * 1e-3 * bench.stage_scale
    assert abs(s0_err_m) < 0.05 * _dof_m(bench, 1)
    for c in (0, 2):
        assert abs(fitted.z_offset_m[c] - bench.z_offset_m[c]) < 0.05 * _dof_m(bench, c)
    # The reported uncertainty is not the formal one of an exact model (under 1 um): it comes
    # from the images' scatter about the fitted line (measured 4.6 um here, against an 18 um
    # error: systematic model mismatch near the SLM plane is correlated between images).
    assert 2e-6 < fitted.stage_at_slm_std_mm * 1e-3 * bench.stage_scale < 0.05 * _dof_m(bench, 1)


def test_phase_curves_and_intensity(bench: TrueBench, fitted) -> None:
    for c in range(3):
        true = np.asarray(bench.phase_tables[c])
        got = np.asarray(fitted.phase_tables_rad[c])
        rms = np.sqrt(((got - true) ** 2).mean()) / (true[-1] - true[0])
        assert rms < 0.03, f"colour {c}: {rms:.2%} RMS of range"
        # The linear curve of the nominal stroke is far off: the fit did something.
        nominal = 2 * np.pi * np.arange(256) / 256
        assert np.sqrt(((nominal - true) ** 2).mean()) / (true[-1] - true[0]) > 2 * rms
    rel = np.asarray(fitted.intensity) / fitted.intensity[1]
    true_rel = np.asarray(bench.electrons_per_s) / bench.electrons_per_s[1]
    assert np.all(np.abs(rel / true_rel - 1) < 0.03)
