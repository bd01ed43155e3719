"""The refinement benchmarks' inputs: `nhfd bench pipeline --rest-ms` and `nhfd bench refine`'s
devices and workload are checked before anything runs, naming the flag and the allowed range."""

from __future__ import annotations

import pytest
import torch

from nhfd.benchmarks.pipeline import _rest_range
from nhfd.benchmarks.refine import PUPIL_ZERNIKE_RAD, devices, workload


def test_rest_range_is_min_max_in_milliseconds() -> None:
    assert _rest_range("3500,4500") == (3500.0, 4500.0)
    for bad in ("4500,3500", "-1,5", "1,70000", "400", "a,b"):
        with pytest.raises(ValueError, match=r"--rest-ms"):
            _rest_range(bad)


def test_refine_bench_devices_start_with_the_cpu_baseline() -> None:
    assert devices("cpu") == [torch.device("cpu")]
    with pytest.raises(ValueError, match=r"--devices"):
        devices("cpu,gpu7")


def test_refine_bench_workload_is_the_configured_panel_with_a_pupil() -> None:
    enc, reference, planes = workload((64, 96), 3, torch.device("cpu"))
    s = enc.settings
    assert s.window_hw == (64, 96) and s.zernike_rad == PUPIL_ZERNIKE_RAD
    assert reference.shape == (3, 64, 96) and len(planes) == 3
    lo, hi = planes[0], planes[-1]
    assert lo < 0 < hi  # across the volume, both sides of the reference plane
    # The amplitude scale leaves the field unclipped (1 % headroom on its SLM-plane peak).
    peak = float(enc.to_slm(reference).abs().max())
    assert s.amplitude_scale == pytest.approx(1.01 * peak, rel=1e-6)
    with pytest.raises(ValueError, match=r"--size 4000x64: must fit the 1920 x 1080 panel"):
        workload((64, 4000), 3, torch.device("cpu"))
