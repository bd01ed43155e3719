"""The calibration the daemon applies must be fitted for the configured bench: other wavelengths
or another pitch are refused by field, expected and found value, within documented tolerances;
a refused hot swap keeps the accepted version."""

from __future__ import annotations

from pathlib import Path

import pytest

from nhfd.calibration import (
    PITCH_REL_TOL,
    WAVELENGTH_REL_TOL,
    CalibrationFileError,
    CalibrationStore,
)
from nhfd.config import Config
from tests.daemon.test_bad_inputs import write_calibration

NOMINAL = (6.6e-7, 5.2e-7, 4.5e-7)  # the default optics.wavelengths_nm, in metres


def _store(path: Path) -> CalibrationStore:
    return CalibrationStore.of(Config.model_validate({"calibration": {"file": str(path)}}))


@pytest.mark.parametrize(("wavelengths_m", "pitch_m", "refusal"), [
    ((1.064e-6, 5.2e-7, 4.5e-7), 8e-6,
     "bench.wavelengths_m[0] = 1.064e-06 m, expected 6.6e-07 m (from optics.wavelengths_nm[0]) "
     "within 0.5%"),
    (NOMINAL, 3.74e-6, "bench.pitch_m = 3.74e-06 m, expected 8e-06 m (from slm.pitch_um) "
                       "within 0.1%"),
    ((6.6e-7, 5.2e-7 * (1 + 1.2 * WAVELENGTH_REL_TOL), 4.5e-7), 8e-6, "bench.wavelengths_m[1]"),
    (NOMINAL, 8e-6 * (1 - 1.2 * PITCH_REL_TOL), "bench.pitch_m = 7.9904e-06 m"),
])
def test_a_calibration_for_another_bench_is_refused_by_field(tmp_path, wavelengths_m, pitch_m,
                                                             refusal):
    path = write_calibration(tmp_path / "cal.toml", wavelengths_m=wavelengths_m, pitch_m=pitch_m)
    with pytest.raises(CalibrationFileError) as info:
        _store(path).active()
    assert str(info.value).startswith(f"calibration file {path}: {refusal}")


def test_a_wavelength_that_is_not_a_number_is_refused(tmp_path):
    path = write_calibration(tmp_path / "cal.toml")
    text = path.read_text()
    assert "wavelengths_m = [6.6e-07, 5.2e-07, 4.5e-07]" in text
    path.write_text(text.replace("4.5e-07]", "nan]", 1))  # TOML's nan, as a hand edit would
    with pytest.raises(CalibrationFileError, match=r"bench\.wavelengths_m\[2\] = nan m, expected "
                                                   r"4\.5e-07 m"):
        _store(path).active()


def test_within_the_tolerances_it_applies(tmp_path):
    near = tuple(w * (1 + 0.8 * WAVELENGTH_REL_TOL) for w in NOMINAL)
    path = write_calibration(tmp_path / "cal.toml", wavelengths_m=near,  # type: ignore[arg-type]
                             pitch_m=8e-6 * (1 - 0.8 * PITCH_REL_TOL))
    store = _store(path)
    cal = store.active()
    assert cal is not None and cal.wavelengths_m == pytest.approx(near, rel=1e-12)
    assert store.refusal() is None


def test_a_refused_hot_swap_keeps_the_accepted_version(tmp_path):
    path = write_calibration(tmp_path / "cal.toml", stage_at_slm_mm=5.0)
    store = _store(path)
    assert store.active().stage_at_slm_mm == 5.0
    write_calibration(tmp_path / "new.toml", stage_at_slm_mm=2.0, pitch_m=3.74e-6).replace(path)
    assert store.active().stage_at_slm_mm == 5.0
    assert store.refusal().startswith(
        f"calibration file {path}: bench.pitch_m = 3.74e-06 m, expected 8e-06 m")
    path.unlink()  # gone from disk: the accepted version stays too
    assert store.active().stage_at_slm_mm == 5.0
    assert "not found" in store.refusal()
    write_calibration(tmp_path / "new.toml", stage_at_slm_mm=3.0).replace(path)
    assert store.active().stage_at_slm_mm == 3.0
    assert store.refusal() is None


def test_stores_are_values_not_a_process_cache(tmp_path):
    """Two stores over one file share nothing: the one that accepted a version keeps it through
    a refused swap, while a fresh store (a new command, a new process) has nothing to keep and
    raises; the worker's store, started with the daemon's accepted version, keeps that one."""
    path = write_calibration(tmp_path / "cal.toml", stage_at_slm_mm=5.0)
    daemon = _store(path)
    accepted = daemon.active()
    write_calibration(tmp_path / "new.toml", pitch_m=3.74e-6).replace(path)
    assert daemon.active() is accepted
    with pytest.raises(CalibrationFileError, match=r"bench\.pitch_m = 3\.74e-06 m"):
        _store(path).active()
    worker = CalibrationStore.of(Config.model_validate({"calibration": {"file": str(path)}}),
                                 accepted=accepted)
    assert worker.active() is accepted
    assert worker.refusal().endswith(f"keeping {accepted.label}")


def test_a_refusal_is_new_once_per_file_version(tmp_path):
    path = write_calibration(tmp_path / "cal.toml", stage_at_slm_mm=5.0)
    store = _store(path)
    assert store.new_refusal() is None
    write_calibration(tmp_path / "a.toml", pitch_m=3.74e-6).replace(path)
    first = store.new_refusal()
    assert first is not None and "3.74e-06" in first
    assert store.new_refusal() is None and store.refusal() == first
    write_calibration(tmp_path / "b.toml", wavelengths_m=(1.064e-6, 5.2e-7, 4.5e-7)).replace(path)
    second = store.new_refusal()
    assert second is not None and "1.064e-06" in second
    assert store.new_refusal() is None


def test_no_file_configured_is_no_calibration():
    store = CalibrationStore.of(Config())
    assert store.active() is None and store.refusal() is None and store.new_refusal() is None
