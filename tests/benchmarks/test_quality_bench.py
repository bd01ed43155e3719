"""`nhfd bench quality`'s figures: the per-tier means, the paired goal checks (met or not, and
a goal with nothing to compare reported as such), the twin's aberration added after its
calibration, and the seeded views inside the model's pose envelope."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from nhfd.benchmarks.quality import (
    ENVELOPE_INSET,
    _zernike,
    aberrated,
    goal_checks,
    leaves_out,
    paired,
    seeded_views,
    summarise,
    table,
)
from nhfd.drivers.simcamera import TrueBench
from nhfd.model_info import PoseEnvelope


def _row(scene: str, view: int, tier: str, k: int, psnr: float, speckle: float,
         seconds: float = 1.0) -> dict:
    return {"scene": scene, "view": view, "tier": tier, "k": k, "seconds": seconds,
            "psnr_db": psnr, "ssim": psnr / 40, "speckle": speckle, "model_psnr_db": psnr + 5}


ROWS = [
    _row("donut", 0, "network", 1, 20.0, 0.30, 0.5),
    _row("donut", 0, "sgd", 1, 24.5, 0.25, 3.0),
    _row("donut", 0, "citl", 1, 26.0, 0.20, 60.0),
    _row("donut", 0, "sgd", 4, 25.0, 0.15, 9.0),
    _row("donut", 0, "citl", 4, 26.5, 0.12, 200.0),
    _row("donut", 1, "network", 1, 21.0, 0.32, 0.7),
    _row("donut", 1, "sgd", 1, 23.0, 0.27, 5.0),
    _row("donut", 1, "citl", 1, 26.5, 0.26, 80.0),
    _row("donut", 1, "sgd", 4, 24.0, 0.28, 11.0),  # K=4 worse here: the mean still decides
    _row("donut", 1, "citl", 4, 25.0, 0.10, 220.0),
    _row("guitar", 0, "sgd", 1, 30.0, 0.40, 4.0),
    _row("guitar", 0, "citl", 1, 30.5, 0.38, 70.0),
]


def test_summarise_means_each_scene_tier_and_k_over_its_views() -> None:
    s = {(e["scene"], e["tier"], e["k"]): e for e in summarise(ROWS)}
    assert len(s) == 7
    e = s["donut", "sgd", 1]
    assert e["views"] == 2
    assert e["psnr_db_mean"] == pytest.approx(23.75)
    assert e["seconds_mean"] == pytest.approx(4.0)
    assert e["speckle_mean"] == pytest.approx(0.26)
    assert e["ssim_mean"] == pytest.approx(23.75 / 40)
    assert e["model_psnr_db_mean"] == pytest.approx(28.75)
    assert s["guitar", "citl", 1]["views"] == 1
    assert s["donut", "citl", 4]["seconds_mean"] == pytest.approx(210.0)
    assert "| donut | sgd | 1 | 2 | 4.0 | 23.75 | 0.594 | 0.260 | 28.75 |" in \
        table(summarise(ROWS))


def test_paired_differences_match_scene_and_view() -> None:
    d = paired(ROWS, "psnr_db", ("sgd", 1), ("citl", 1))
    assert [(p["scene"], p["view"], p["diff"]) for p in d] == [
        ("donut", 0, 1.5), ("donut", 1, 3.5), ("guitar", 0, 0.5)]
    assert paired(ROWS, "psnr_db", ("network", 1), ("citl", 8)) == []


def test_goal_checks_report_the_mean_paired_gain_and_whether_it_is_met() -> None:
    goals = {g["goal"]: g for g in goal_checks(ROWS)}
    g = goals["sgd (K=1) over the network's double-phase frame >= +3 dB captured"]
    assert (g["pairs"], g["diffs"], g["met"]) == (2, [4.5, 2.0], True)
    assert g["mean_diff"] == pytest.approx(3.25)
    g = goals["citl over sgd (K=1) >= +2 dB captured"]
    assert g["mean_diff"] == pytest.approx((1.5 + 3.5 + 0.5) / 3) and g["met"] is False
    g = goals["citl over sgd (K=4) >= +2 dB captured"]
    assert g["diffs"] == [1.5, 1.0] and g["met"] is False
    g = goals["sgd: speckle contrast at K=4 lower than at K=1"]
    assert g["diffs"] == [-0.1, 0.01] and g["mean_diff"] == pytest.approx(-0.045)
    assert g["met"] is True
    g = goals["citl: speckle contrast at K=4 lower than at K=1"]
    assert g["diffs"] == [-0.08, -0.16] and g["met"] is True
    # Without network rows there is nothing to compare: not measured, not failed.
    none = goal_checks([r for r in ROWS if r["tier"] != "network"])
    assert none[0]["pairs"] == 0 and none[0]["met"] is None


def test_the_aberration_is_added_to_the_twins_own() -> None:
    twin = TrueBench(zernike_rad=(0.1,))
    out = aberrated(twin, (0.5, -0.3, 0.4))
    assert out.zernike_rad == pytest.approx((0.6, -0.3, 0.4))
    assert out.fill_factor == twin.fill_factor and twin.zernike_rad == (0.1,)
    assert aberrated(TrueBench(), (0.5,)).zernike_rad == (0.5,)


def test_the_unknown_aberration_is_a_setting_and_the_record_says_which() -> None:
    assert _zernike("0.5,-0.3,0.4") == (0.5, -0.3, 0.4) and _zernike("none") == ()
    assert aberrated(TrueBench(), _zernike("none")).zernike_rad == TrueBench().zernike_rad
    with pytest.raises(ValueError, match=r"--unknown-zernike 'coma': give radians"):
        _zernike("coma")
    with pytest.raises(ValueError, match=r"--unknown-zernike '0.5,nan': each within"):
        _zernike("0.5,nan")
    assert not any("aberration" in line for line in leaves_out(()))
    assert "coma and astigmatism (Noll 5-7) +0.5, -0.3 rad" in " ".join(leaves_out((0.5, -0.3)))


def test_seeded_views_lie_inside_the_model_envelope_and_repeat_with_the_seed() -> None:
    env = PoseEnvelope(distance=(0.6, 0.8), azimuth_deg=(-30.0, 40.0),
                       elevation_deg=(10.0, 30.0))
    info = SimpleNamespace(pose_envelope=env)
    views = seeded_views(np.random.default_rng(3), 20, None, info, (288, 512))  # type: ignore[arg-type]
    again = seeded_views(np.random.default_rng(3), 20, None, info, (288, 512))  # type: ignore[arg-type]
    assert views == again and len(set(views)) == 20
    for v in views:
        o = v.camera
        assert -30 + 7 <= o.azimuth_deg <= 40 - 7  # ENVELOPE_INSET of the 70-degree span
        assert 10 + 2 <= o.elevation_deg <= 30 - 2
        assert 0.62 - 1e-12 <= o.radius <= 0.78 + 1e-12
    assert ENVELOPE_INSET == 0.1
