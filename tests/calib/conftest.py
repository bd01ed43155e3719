"""One simulated capture per test run (it is the slow part: ~100 images through the twin
camera), on a bench drawn at random with a fixed seed, fitted once: both pytest-xdist workers
read the one capture and its fitted calibration file (`made_once`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from nhfd.calib.capture import CapturePlan, SimBenchIO, capture
from nhfd.calib.fit import fit_capture
from nhfd.calib.patterns import PatternSpec
from nhfd.calibration import Calibration
from nhfd.drivers.simcamera import TrueBench
from tests.conftest import made_once

# Drawn by TrueBench.randomised: phase sign -1 and no mirror (both non-default), M ~ 1.12.
BENCH_SEED = 7
PANEL_HW = (128, 128)


def small_spec(bench: TrueBench) -> PatternSpec:
    return PatternSpec(PANEL_HW, bench.pitch_m, bench.wavelengths_m, refs=(0, 96, 176),
                       tests=tuple(range(8, 256, 20)))


def small_plan(bench: TrueBench) -> CapturePlan:
    # The lab knows roughly where the SLM plane is (10 mm); the bench's is drawn in [8, 12].
    return CapturePlan(stage_center_mm=10.0, stage_range_mm=2.5, coarse_step_mm=0.5,
                       fine_steps=13, camera_pitch_m=bench.camera_pitch_m)


@pytest.fixture(scope="session")
def bench() -> TrueBench:
    return TrueBench.randomised(BENCH_SEED)


@pytest.fixture(scope="session")
def captured(bench: TrueBench, tmp_path_factory: pytest.TempPathFactory) -> Path:
    def make(folder: Path) -> None:
        capture(folder / "capture", SimBenchIO(bench, PANEL_HW, noise_seed=3), small_spec(bench),
                small_plan(bench))

    return made_once(tmp_path_factory, f"calib-capture-{BENCH_SEED}", make) / "capture"


@pytest.fixture(scope="session")
def fitted(captured: Path, tmp_path_factory: pytest.TempPathFactory) -> Calibration:
    """The capture's fit, as its calibration file reads back (what the daemon applies)."""
    def make(folder: Path) -> None:
        cal = fit_capture(captured)
        back = Calibration.load(cal.save(folder / "calibration.toml"))
        # Every fitted value reads back exactly (test_files round-trips the loaded one again).
        assert replace(back, created="", source="") == replace(cal, created="", source="")

    folder = made_once(tmp_path_factory, f"calib-fit-{BENCH_SEED}", make)
    return Calibration.load(folder / "calibration.toml")
