"""The calibration file and the capture directory: round trip, clear errors, refusals."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from nhfd.calib.capture import Capture, CaptureError, SimBenchIO
from nhfd.calib.data import CalibrationDataError
from nhfd.calib.fit import fit_capture
from nhfd.calib.focus import FocusError, fit_depth
from nhfd.calibration import Calibration, CalibrationFileError

from .conftest import PANEL_HW, small_plan, small_spec


def test_calibration_round_trip(fitted, tmp_path: Path) -> None:
    path = fitted.save(tmp_path / "calibration.toml")
    back = Calibration.load(path)
    assert back.phase_tables_rad == fitted.phase_tables_rad
    assert back.phase_sign == fitted.phase_sign
    assert back.stage_scale == fitted.stage_scale
    assert back.z_offset_m == fitted.z_offset_m
    assert back.source == str(path)
    assert back.created  # stamped when written
    curves = back.phase_curves()
    assert [c.phase_rad for c in curves] == [tuple(t) for t in fitted.phase_tables_rad]
    # Depth -> stage: green's SLM plane is where the fit put it.
    assert back.stage_mm_for(0.0, 1) == pytest.approx(fitted.stage_at_slm_mm)


def test_calibration_file_errors(fitted, tmp_path: Path) -> None:
    with pytest.raises(CalibrationFileError, match="not found"):
        Calibration.load(tmp_path / "none.toml")
    bad = tmp_path / "corrupt.toml"
    bad.write_text("format = \"nhfd-calibration\"\nversion = [1,\n")
    with pytest.raises(CalibrationFileError, match="corrupt"):
        Calibration.load(bad)
    foreign = tmp_path / "foreign.toml"
    foreign.write_text("[tool.black]\nline-length = 99\n")
    with pytest.raises(CalibrationFileError, match="not an nhfd calibration"):
        Calibration.load(foreign)
    text = fitted.to_toml()
    newer = tmp_path / "newer.toml"
    newer.write_text(text.replace("version = 1", "version = 99", 1))
    with pytest.raises(CalibrationFileError, match="version 99"):
        Calibration.load(newer)
    # A decreasing phase table is refused by the loader, naming the file.
    broken = tmp_path / "broken.toml"
    broken.write_text(text.replace("R_rad = [0.0,", "R_rad = [9.0,", 1))
    with pytest.raises(CalibrationFileError, match=r"broken\.toml"):
        Calibration.load(broken)


def test_invalid_parameters_raise() -> None:
    with pytest.raises(ValueError, match="stage_scale"):
        Calibration((6.6e-7, 5.2e-7, 4.5e-7), 8e-6, 1, ((0.0,) * 256,) * 3, (0.0,) * 3,
                    -1.0, 0.0, 10.0, 0.0, (0.0,) * 3, (0.0,) * 3, 1.0, 0.0, 180.0, 0.0,
                    False, (0.0, 0.0), (1.0,) * 3, (0.0,) * 3)


def _copy(captured: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "copy"
    shutil.copytree(captured, dst)
    return dst


def test_missing_and_corrupt_capture_named(captured: Path, tmp_path: Path) -> None:
    d = _copy(captured, tmp_path)
    manifest = json.loads((d / "manifest.json").read_text())
    rec = next(r for r in manifest["records"] if r["sweep"] == "fine" and r["colour"] == 2)
    (d / rec["file"]).unlink()
    with pytest.raises(CalibrationDataError, match=rf"{rec['key']}.*missing"):
        fit_capture(d)
    (d / rec["file"]).write_bytes(b"not an npz at all")
    with pytest.raises(CalibrationDataError, match=rf"{rec['key']}.*corrupt"):
        fit_capture(d)


def test_incomplete_capture_refused(captured: Path, tmp_path: Path) -> None:
    d = _copy(captured, tmp_path)
    m = json.loads((d / "manifest.json").read_text())
    m["complete"] = False
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(CalibrationDataError, match="incomplete"):
        fit_capture(d)


def test_no_overwrite_without_force(bench, captured: Path) -> None:
    io = SimBenchIO(bench, PANEL_HW)
    with pytest.raises(CaptureError, match="--force"):
        Capture(captured, io, small_spec(bench), small_plan(bench))


def test_one_stage_position_leaves_scale_undetermined() -> None:
    peaks = [(c, z, 10.0) for c in range(3) for z in (-1.5e-3, 0.0, 1.5e-3)]
    with pytest.raises(FocusError, match="stage scale is undetermined"):
        fit_depth(peaks)


def test_colour_without_focus_refused() -> None:
    peaks = [(c, z, 10.0 + z * 1e3) for c in (0, 1) for z in (-1.5e-3, 0.0, 1.5e-3)]
    with pytest.raises(FocusError, match="colour B"):
        fit_depth(np.asarray(peaks).tolist())


@pytest.mark.parametrize("fraction, phase, message", [
    ("[0.03, 1.0, 0.03]", "[0.1, 0.1, 0.1]",
     r"zero_order\.unmodulated_fraction\[1\] = 1\.0: must be in 0\.\.0\.5"),
    ("[0.03, 0.03, nan]", "[0.1, 0.1, 0.1]",
     r"zero_order\.unmodulated_fraction\[2\] = nan: must be in 0\.\.0\.5"),
    ("[-0.01, 0.03, 0.03]", "[0.1, 0.1, 0.1]",
     r"zero_order\.unmodulated_fraction\[0\] = -0\.01: must be in 0\.\.0\.5"),
    ("[0.03, 0.03, 0.03]", "[0.1, inf, 0.1]", r"zero_order\.phase_rad\[1\] = inf: must be finite"),
    ("[0.03, 0.03]", "[0.1, 0.1, 0.1]", r"zero_order: need one unmodulated_fraction and one "
                                         r"phase_rad per colour"),
])
def test_unmodulated_light_out_of_range_is_refused(fitted, tmp_path: Path, fraction: str,
                                                   phase: str, message: str) -> None:
    """The unmodulated light a calibration records is the intensity fraction f of the light
    leaving the panel; a bench model adds it as sqrt(f / (1 - f)), unbounded as f nears 1. A file
    out of range is refused naming the file and the value, not read into NaN or Inf."""
    ok = replace(fitted, unmodulated_fraction=(0.03,) * 3, unmodulated_fraction_std=(0.001,) * 3,
                 unmodulated_phase_rad=(0.1,) * 3)
    text = ok.to_toml()
    lines = text.splitlines()
    i = lines.index("[zero_order]")
    for j in range(i, len(lines)):
        if lines[j].startswith("unmodulated_fraction ="):
            lines[j] = f"unmodulated_fraction = {fraction}"
        elif lines[j].startswith("phase_rad ="):
            lines[j] = f"phase_rad = {phase}"
    bad = tmp_path / "zero-order.toml"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibrationFileError, match=rf"zero-order\.toml.*{message}"):
        Calibration.load(bad)
    assert Calibration.load(ok.save(tmp_path / "ok.toml")).unmodulated_fraction == (0.03,) * 3
