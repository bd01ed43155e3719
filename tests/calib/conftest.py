"""One simulated capture per test session (it is the slow part: ~100 images through the twin
camera), on a bench drawn at random with a fixed seed, fitted once."""

from __future__ import annotations

from pathlib import Path

import pytest

from nhfd.calib.capture import CapturePlan, SimBenchIO, capture
from nhfd.calib.fit import fit_capture
from nhfd.calib.patterns import PatternSpec
from nhfd.drivers.simcamera import TrueBench

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
    out = tmp_path_factory.mktemp("calib") / "capture"
    capture(out, SimBenchIO(bench, PANEL_HW, noise_seed=3), small_spec(bench), small_plan(bench))
    return out


@pytest.fixture(scope="session")
def fitted(captured: Path):
    return fit_capture(captured)
