"""The daemon takes phase curves, sign, per-colour focus offsets and the focus mapping from
`[calibration] file`, and with them reaches the focal-stack quality of the true parameters."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from nhfd.calibration import CalibrationFileError, CalibrationStore
from nhfd.config import Config
from nhfd.drivers.simcamera import TrueBench
from nhfd.model_info import ModelInfo
from nhfd.pipeline.settings import frame_settings

from .twin_stack import (
    amplitude_for,
    panel_frame,
    sharpest_dz,
    small,
    spot_field,
    stack_psnr,
    target_field,
    target_stack,
)

METADATA = ModelInfo(inputs="rgb", train_size_hw=(64, 64), pitch_m=8e-6,
                     wavelengths_m=(6.6e-7, 5.2e-7, 4.5e-7), z0_m=4e-3, aperture_shape="square",
                     cutoff_per_px=(0.25,) * 3, volume_m=(-3e-3, 3e-3), amplitude_scale=1.0,
                     input_multiple=16, fov_x_deg=40.0)


def test_frames_use_calibration(fitted, tmp_path: Path) -> None:
    path = fitted.save(tmp_path / "calibration.toml")
    plain = Config()
    assert CalibrationStore.of(plain).active() is None
    s0 = frame_settings(plain, METADATA, CalibrationStore.of(plain).active())
    assert s0.phase_sign == 1 and all(c.is_default for c in s0.curves())
    cfg = Config.model_validate({"calibration": {"file": str(path)}})
    s1 = frame_settings(cfg, METADATA, CalibrationStore.of(cfg).active())
    assert s1.phase_sign == fitted.phase_sign == -1
    assert [c.phase_rad for c in s1.curves()] == [tuple(t) for t in fitted.phase_tables_rad]
    cal = CalibrationStore.of(cfg).active()
    assert cal is not None and cal.source == str(path)
    # Focus: depth z0 + z from the SLM maps through the fitted scale.
    assert cal.stage_mm_for(4e-3 + 1e-3) - cal.stage_mm_for(4e-3) == pytest.approx(
        1.0 / cal.stage_scale)


def test_unreadable_configured_file_is_an_error(tmp_path: Path) -> None:
    cfg = Config.model_validate({"calibration": {"file": str(tmp_path / "nope.toml")}})
    with pytest.raises(CalibrationFileError, match=r"nope\.toml"):
        CalibrationStore.of(cfg).active()


def _settings_with(cal, tmp_path: Path, name: str):
    path = cal.save(tmp_path / name)
    config = Config.model_validate({"calibration": {"file": str(path)}})
    return small(frame_settings(config, METADATA, CalibrationStore.of(config).active()))


def test_per_colour_focus_offsets_applied(bench: TrueBench, fitted, tmp_path: Path) -> None:
    """A bench whose red focuses 0.6 mm beyond green and blue 0.6 mm short of it (half a depth
    of field): with the calibration's offsets, the daemon's frame puts a spot at the reference
    plane in focus at the same stage setting for every colour; ignoring them, red and blue are
    sharpest 0.6 mm away."""
    offsets = (600e-6, 0.0, -600e-6)
    twin = dataclasses.replace(bench, z_offset_m=offsets)
    with_offsets = _settings_with(dataclasses.replace(fitted, z_offset_m=offsets), tmp_path,
                                  "offsets.toml")
    assert with_offsets.colour_propagation_z_m == pytest.approx(
        tuple(-(METADATA.z0_m + o) for o in offsets))
    ignored = dataclasses.replace(with_offsets, colour_offset_m=())
    field = spot_field(with_offsets)
    amp = amplitude_for(with_offsets, field)
    dzs = np.array([-600e-6, 0.0, 600e-6])  # three planes keep it lean; the shifts are whole steps
    stage = lambda z: fitted.stage_mm_for(z, 1)  # noqa: E731 (the daemon's `focus`: green's)
    got = sharpest_dz(twin, panel_frame(with_offsets, field, amp), stage, with_offsets, dzs)
    assert got == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)
    off = sharpest_dz(twin, panel_frame(ignored, field, amp), stage, ignored, dzs)
    assert off == pytest.approx([-600e-6, 0.0, 600e-6], abs=1e-9)


def test_acceptance_focal_stack_psnr(bench: TrueBench, fitted, tmp_path: Path) -> None:
    """Issue 8's acceptance: with the fitted calibration applied (curves, sign, offsets, the
    stage mapping), each colour's twin-camera focal-stack PSNR against the target is within
    0.5 dB of the daemon configured with the bench's true parameters."""
    calibrated = _settings_with(fitted, tmp_path, "calibration.toml")
    nominal = small(frame_settings(Config(), METADATA, None))
    true = dataclasses.replace(
        nominal, phase_sign=bench.phase_sign, phase_tables_rad=bench.phase_tables,
        colour_offset_m=tuple(o - bench.z_offset_m[1] for o in bench.z_offset_m))
    field = target_field(true)
    target = target_stack(field, true)
    amp = amplitude_for(true, field)
    psnr_true = stack_psnr(bench, panel_frame(true, field, amp),
                           lambda z: bench.stage_mm_for(z, 1), target, true)
    psnr_cal = stack_psnr(bench, panel_frame(calibrated, field, amp),
                          lambda z: fitted.stage_mm_for(z, 1), target, calibrated)
    psnr_nominal = stack_psnr(bench, panel_frame(nominal, field, amp),
                              lambda z: bench.stage_mm_for(z, 1), target, nominal)
    for c in range(3):
        assert psnr_cal[c] > psnr_true[c] - 0.5, (psnr_cal, psnr_true)
        # The measure sees calibration at all: uncalibrated coding (linear curves, sign +1 on
        # a sign -1 bench) is far worse.
        assert psnr_nominal[c] < psnr_true[c] - 3.0, (psnr_nominal, psnr_true)
