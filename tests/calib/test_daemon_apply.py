"""The daemon takes phase curves, sign and focus mapping from `[calibration] file`."""

from __future__ import annotations

from pathlib import Path

import pytest
from nhfd.calib.active import active_calibration
from nhfd.calib.calibration import CalibrationFileError

from nhfd.config import Config
from nhfd.daemon.frames import frame_settings

METADATA = {"train_size_hw": [64, 64], "pitch_m": 8e-6, "wavelengths_m": [6.6e-7, 5.2e-7, 4.5e-7],
            "z0_m": 4e-3, "aperture_shape": "square", "cutoff_per_px": [0.25] * 3,
            "amplitude_scale": 1.0}


def test_frames_use_calibration(fitted, tmp_path: Path) -> None:
    path = fitted.save(tmp_path / "calibration.toml")
    plain = Config()
    assert active_calibration(plain) is None
    s0 = frame_settings(plain, METADATA)
    assert s0.phase_sign == 1 and all(c.is_default for c in s0.curves())
    cfg = Config.model_validate({"calibration": {"file": str(path)}})
    s1 = frame_settings(cfg, METADATA)
    assert s1.phase_sign == fitted.phase_sign == -1
    assert [c.phase_rad for c in s1.curves()] == [tuple(t) for t in fitted.phase_tables_rad]
    cal = active_calibration(cfg)
    assert cal is not None and cal.source == str(path)
    # Focus: depth z0 + z from the SLM maps through the fitted scale.
    assert cal.stage_mm_for(4e-3 + 1e-3) - cal.stage_mm_for(4e-3) == pytest.approx(
        1.0 / cal.stage_scale)


def test_unreadable_configured_file_is_an_error(tmp_path: Path) -> None:
    cfg = Config.model_validate({"calibration": {"file": str(tmp_path / "nope.toml")}})
    with pytest.raises(CalibrationFileError, match=r"nope\.toml"):
        active_calibration(cfg)
