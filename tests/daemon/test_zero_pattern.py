"""One zero pattern (issue 22): under a calibration (phase sign -1, measured curves) the blank
frame, the panel around a view's coded window and the coder's zero are the same grey levels.
They were built three ways, and the blank and the surround ignored the calibration: grey (64, 192)
there, which under the measured curves and sign do not code zero amplitude, against the coder's."""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from nhfd import spec
from nhfd.calibration import Calibration, CalibrationStore
from nhfd.config import Config, _overlay
from nhfd.daemon.panel import Panel, blank_pattern
from nhfd.models.export import load_model
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.settings import frame_region, frame_settings

from .test_frames import FRONT_POSE, daemon_config, wait_for_frames

# Measured-looking curves: strokes other than 2 pi and a gamma, a different one per colour.
STROKES_RAD = (2.15 * np.pi, 1.9 * np.pi, 2.4 * np.pi)
GAMMAS = (1.15, 0.9, 1.3)


def write_measured_calibration(path: Path, config: Config) -> Path:
    """A calibration for the configured bench with phase sign -1 and non-nominal curves."""
    return measured_calibration(config, GAMMAS).save(path)


def measured_calibration(config: Config, gammas: tuple[float, ...]) -> Calibration:
    """The calibration `write_measured_calibration` writes, with per-colour curve `gammas`."""
    g = np.arange(256) / 255
    tables = tuple(tuple(float(v) for v in s * g**gamma) for s, gamma in
                   zip(STROKES_RAD, gammas, strict=True))
    return Calibration(
        wavelengths_m=tuple(config.optics.wavelengths_m), pitch_m=config.slm.pitch_m,
        phase_sign=-1, phase_tables_rad=tables, phase_table_std_rad=(0.0,) * 3,
        stage_scale=1.0, stage_scale_std=0.0, stage_at_slm_mm=5.0, stage_at_slm_std_mm=0.0,
        z_offset_m=(0.0, 0.0, 0.0), z_offset_std_m=(0.0, 0.0, 0.0), magnification=1.0,
        magnification_std=0.0, rotation_deg=0.0, rotation_std_deg=0.0, mirror_x=False,
        shift_px=(0.0, 0.0), intensity=(1.0, 1.0, 1.0), intensity_std=(0.0, 0.0, 0.0))


def checker_pair(frame: np.ndarray) -> list[tuple[int, int]]:
    """Per colour, the (even, odd) grey levels of a frame that is a pure checkerboard; fails
    naming the colour when it is not one."""
    pairs = []
    for c, plane in enumerate(frame):
        odd = (np.arange(plane.shape[0])[:, None] + np.arange(plane.shape[1])[None, :]) % 2 == 1
        even_levels, odd_levels = np.unique(plane[~odd]), np.unique(plane[odd])
        assert len(even_levels) == 1 and len(odd_levels) == 1, (c, even_levels, odd_levels)
        pairs.append((int(even_levels[0]), int(odd_levels[0])))
    return pairs


def test_blank_surround_and_coded_zero_are_one_pattern_under_a_calibration(
        short_dir, mecom_twin, tiny):
    from .conftest import Running, wait_until

    base = daemon_config(short_dir, mecom_twin, tiny,
                         paths={"scene": str(short_dir / "scenes" / "cloud.ply")},
                         frames={"model": str(short_dir / "models" / "tiny.onnx")})
    path = write_measured_calibration(short_dir / "calibration.toml", base)
    config = Config.model_validate(_overlay(base.model_dump(),
                                            {"calibration": {"file": str(path)}}))
    r = Running(config, short_dir)
    try:
        c = r.client()
        wait_for_frames(c)
        slm = r.daemon.bench.slm
        seq = c.call("set_view", pose=FRONT_POSE)["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq, 20, "the view")
        shown = slm.last_frame.copy()
        c.call("blank")
        wait_until(lambda: c.status()["display"] == "blank", 10, "the blank")
        blank = slm.last_frame.copy()
    finally:
        r.stop()

    # The coder the frame worker runs, on an all-zero field of the coded region.
    model = load_model(short_dir / "models" / "tiny.onnx", config)
    settings = frame_settings(config, model.info, CalibrationStore.of(config).active())
    assert settings.phase_sign == -1 and not any(cv.is_default for cv in settings.curves())
    encoder = Encoder(settings)
    region = frame_region(settings)
    coded, _ = encoder.code(torch.zeros((3, region.height, region.width), dtype=torch.complex64))
    # Even top-left corner: the region's checkerboard parity is the panel's.
    assert region.top % 2 == 0 and region.left % 2 == 0
    zero = checker_pair(coded)

    h, w = shown.shape[1:]
    odd = (np.arange(h)[:, None] + np.arange(w)[None, :]) % 2
    pattern = np.stack([np.where(odd == 1, o, e) for e, o in zero]).astype(np.uint8)

    # The surround: every pixel of the panel outside the coded region.
    outside = np.ones((h, w), bool)
    outside[region.rows, region.cols] = False
    assert outside.sum() > 0.3 * outside.size  # a real part of the panel
    for c in range(3):
        assert np.array_equal(shown[c][outside], pattern[c][outside]), (
            c, np.unique(shown[c][outside]), zero[c])
    assert checker_pair(blank) == zero
    # Not the configured curves' zero: the calibration's sign and curves moved it.
    assert zero != [(64, 192)] * 3


def test_the_panels_blank_is_the_zero_pattern_of_the_active_calibration(short_dir):
    """Without a daemon: `Panel.blank_frame` codes zero through the active calibration's curves
    and sign, and follows the file when a new version is swapped in."""
    from .conftest import bench_config

    base = bench_config(short_dir, None)
    path = write_measured_calibration(short_dir / "calibration.toml", base)
    config = Config.model_validate(_overlay(base.model_dump(),
                                            {"calibration": {"file": str(path)}}))
    panel = Panel(config, SimpleNamespace(slm=None, errors={"slm": None}),
                  CalibrationStore.of(config))
    s = config.slm
    hw = (s.height_px, s.width_px)

    def zero_of(cal: Calibration) -> np.ndarray:
        curves = spec.phase_curves(s.phase_stroke_rad, cal.phase_tables_rad)
        return spec.zero_pattern(hw, curves, cal.phase_sign, s.grey_invert)

    blank = panel.blank_frame()
    assert np.array_equal(blank, zero_of(Calibration.load(path)))
    assert not np.array_equal(blank, blank_pattern(config, None))  # not the configured curves
    assert panel.blank_frame() is blank  # one pattern per calibration version, not per frame

    swapped = measured_calibration(config, (1.0, 1.0, 1.0))
    swapped.save(path)
    os.utime(path, ns=(1, 1))  # a new version even within the file system's mtime resolution
    assert np.array_equal(panel.blank_frame(), zero_of(swapped))
    assert not np.array_equal(panel.blank_frame(), blank)
