"""Acceptance (issue 8) on the simulated bench: the fit recovers the true bench's parameters.

The true bench is richer than the fitted model (wiggly tables, crosstalk, fill factor, zero
order, Gaussian source, sensor noise and response): tolerances are the issue's."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nhfd.calib.capture import SimBenchIO, capture
from nhfd.calib.fit import geometry_from, measure_response
from nhfd.calib.response import ResponseFit
from nhfd.drivers.simcamera import TrueBench

from .conftest import PANEL_HW, small_plan, small_spec

# More benches for the response and placement checks, chosen before they were ever run (not
# picked for passing). The session bench (BENCH_SEED) carries the full fit's checks.
OTHER_SEEDS = (101, 202, 303)
# Phase curve error (RMS, fraction of the true range) and intensity ratio error allowed (issue
# 8). On 13 benches the fit's phase errors were 1.3-2.2 % and its ratio errors up to 3.1 %
# (red): see docs/calibration.md, "Known biases".
PHASE_RMS_TOL = 0.03
INTENSITY_TOL = 0.03
# The fitted curve's error after its best single scale factor (fraction of the true range).
SHAPE_RMS_TOL = 0.01


def _dof_m(bench: TrueBench, colour: int) -> float:
    # Depth of field of the filtered system (docs/physics.md): 8 p^2 / lambda at the default
    # aperture.
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
    # field (in SLM space). Measured on this seed with the bench-model fit: 2.1%, R 0.8%, B 1.9%
    # (the focus-peak estimator alone: 12.3%, 13.1%, 7.7%).
    s0_err_m = (fitted.stage_at_slm_mm - bench.stage_at_slm_mm) * 1e-3 * bench.stage_scale
    assert abs(s0_err_m) < 0.05 * _dof_m(bench, 1)
    for c in (0, 2):
        assert abs(fitted.z_offset_m[c] - bench.z_offset_m[c]) < 0.05 * _dof_m(bench, c)
    # The reported uncertainty is not the formal one of an exact model (under 1 um): it comes
    # from the images' scatter about the fitted line (measured 4.6 um here, against an 18 um
    # error: systematic model mismatch near the SLM plane is correlated between images).
    assert 2e-6 < fitted.stage_at_slm_std_mm * 1e-3 * bench.stage_scale < 0.05 * _dof_m(bench, 1)


def _phase_rms(true: np.ndarray, table: np.ndarray) -> float:
    """RMS difference of two grey -> phase tables, relative to the true table's range."""
    return float(np.sqrt(((table - true) ** 2).mean()) / (true[-1] - true[0]))


def _shape_rms(true: np.ndarray, table: np.ndarray) -> float:
    """`_phase_rms` of the table times its best single scale factor: its error in shape."""
    return _phase_rms(true, table * float(table @ true) / float(table @ table))


def _check_response(bench: TrueBench, tables: tuple[tuple[float, ...], ...],
                    intensity: tuple[float, ...]) -> None:
    nominal = 2 * np.pi * np.arange(256) / 256
    for c in range(3):
        true = np.asarray(bench.phase_tables[c])
        got = np.asarray(tables[c])
        rms = _phase_rms(true, got)
        assert rms < PHASE_RMS_TOL, f"colour {c}: {rms:.2%} RMS of range"
        # Most of the fit's error is one scale factor (the panel's fringing compresses the
        # curve: docs/calibration.md, "Known biases"), and the nominal 2 pi curve's error for
        # green is about as large (its 520 nm stroke is close to 2 pi): comparing the two
        # holds on some benches only. In shape the fit is far better on every bench: a straight
        # line cannot follow the panel's S-shaped, wiggly response, which the fit measures
        # (0.34-0.55 % against the nominal's 1.06-3.36 % on 13 benches). A fit that returned the
        # nominal, or any straight curve, fails this.
        shape = _shape_rms(true, got)
        assert shape < SHAPE_RMS_TOL, f"colour {c}: {shape:.2%} RMS in shape"
        assert shape < 0.5 * _shape_rms(true, nominal), f"colour {c}: {shape:.2%} RMS in shape"
    rel = np.asarray(intensity) / intensity[1]
    true_rel = np.asarray(bench.electrons_per_s) / bench.electrons_per_s[1]
    assert np.all(np.abs(rel / true_rel - 1) < INTENSITY_TOL), rel / true_rel - 1


def test_phase_curves_and_intensity(bench: TrueBench, fitted) -> None:
    _check_response(bench, fitted.phase_tables_rad, fitted.intensity)


@pytest.fixture(scope="module", params=OTHER_SEEDS)
def response_capture(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
                     ) -> tuple[TrueBench, dict, ResponseFit]:
    """A bench, its coarse placement (`locate`) and its response fit, from a capture stopped
    after the gratings and flats (the depth fit is the session bench's)."""
    bench = TrueBench.randomised(request.param)
    plan = small_plan(bench)
    plan.stop_after = "grating"
    # The lab knows roughly where the SLM plane is: the bench's, to the millimetre.
    plan.stage_center_mm = float(round(bench.stage_at_slm_mm))
    out = tmp_path_factory.mktemp(f"calib{request.param}") / "capture"
    spec = small_spec(bench)
    capture(out, SimBenchIO(bench, PANEL_HW, noise_seed=3), spec, plan)
    manifest = json.loads((Path(out) / "manifest.json").read_text())
    recs = [r for r in manifest["records"] if r.get("sweep") in ("grating", "flat")]
    loc = manifest["located"]
    return bench, loc, measure_response(out, spec, recs, geometry_from(loc))


def test_response_on_other_benches(response_capture) -> None:
    bench, _, resp = response_capture
    _check_response(bench, resp.tables_rad, resp.intensity)


def test_placement_on_other_benches(response_capture) -> None:
    bench, loc, _ = response_capture
    assert loc["mirror_x"] is bench.mirror_x
    assert abs(loc["magnification"] / bench.magnification - 1) < 0.005
    assert abs(loc["rotation_deg"] - bench.rotation_deg % 360) < 0.2
