"""`nhfd bench quality`'s figures: the per-tier means, the paired goal checks (met or not, and
a goal with nothing to compare reported as such), the twin's aberration added after its
calibration, the seeded views inside the model's pose envelope, the twin's TOML and its
refusals, and the tuned tier's row from a tiny run."""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from nhfd.benchmarks import quality as Q
from nhfd.benchmarks.quality import (
    ENVELOPE_INSET,
    _zernike,
    aberrated,
    goal_checks,
    leaves_out,
    paired,
    register,
    seeded_views,
    summarise,
    table,
)
from nhfd.calib.learn import LearnPlan
from nhfd.calib.sim import sim_panel_hw
from nhfd.calibration import Calibration, fingerprint
from nhfd.drivers.simcamera import TrueBench
from nhfd.model_info import PoseEnvelope, recorded_scenes
from nhfd.models.sizes import read_metadata
from tests.calib.twin_stack import truth_calibration


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


# -- the twin's TOML (`TrueBench.from_toml`) ----------------------------------------------------

def _toml(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "twin.toml"
    path.write_text(text)
    return path


def test_a_twin_toml_sets_its_fields_and_starts_from_a_randomised_twin(tmp_path) -> None:
    twin = TrueBench.from_toml(_toml(tmp_path, 'randomised_seed = 7\nfill_factor = 0.9\n'
                                     'zernike_rad = [0.2, -0.1]\nmirror_x = true\n'
                                     'aperture_shape = "circle"\noversample = 3\n'))
    assert twin == TrueBench.randomised(7, fill_factor=0.9, zernike_rad=(0.2, -0.1),
                                        mirror_x=True, aperture_shape="circle", oversample=3)
    plain = TrueBench.from_toml(_toml(tmp_path, "crosstalk_sigma_m = 2e-6\n"
                                      "source_offset_m = [1e-4, -2e-4]\n"))
    assert plain == TrueBench(crosstalk_sigma_m=2e-6, source_offset_m=(1e-4, -2e-4))


@pytest.mark.parametrize(("text", "message"), [
    ("fill_factr = 0.9", r"unknown key\(s\) fill_factr; allowed: randomised_seed, "),
    ("fill_factor = 1.5", r"fill_factor = 1\.5: must be a number in 0\.01\.\.1"),
    ("fill_factor = nan", r"fill_factor = nan: must be a number in 0\.01\.\.1"),
    ("fill_factor = 'high'", r"fill_factor = 'high': must be a number"),
    ("oversample = 2.5", r"oversample = 2\.5: must be a whole number in 1\.\.8"),
    ("zero_order_fraction = -0.1", r"zero_order_fraction = -0\.1: must be a number in 0\.\.0\.99"),
    ("zernike_rad = [0.1, 11.0]", r"zernike_rad = 11\.0: must be a number in -10\.\.10"),
    ("shift_m = [1e-5]", r"shift_m = \[1e-05\]: must be a list of 2 values"),
    ("mirror_x = 1", r"mirror_x = 1: must be true or false"),
    ("aperture_shape = 'hexagon'", r"aperture_shape = 'hexagon': must be one of square, circle"),
    ("phase_sign = 0", r"phase_sign = 0: must be \+1 or -1"),
    ("colour_matrix = [[1, 0], [0, 1]]", r"colour_matrix = .*: must be a list of 3 values"),
    ("fill_factor = ", r"not TOML"),
])
def test_a_twin_toml_is_refused_naming_the_key_and_its_range(tmp_path, text, message) -> None:
    path = _toml(tmp_path, text + "\n")
    with pytest.raises(ValueError, match=message) as err:
        TrueBench.from_toml(path)
    assert str(path) in str(err.value)


# -- the tuned tier -----------------------------------------------------------------------------

def _bench_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    return parser.parse_args(["quality", *argv])


def test_the_tuned_tier_scores_the_model_tuned_through_the_runs_calibration(
        tmp_path, monkeypatch) -> None:
    """A tiny run (64 x 48, one seeded view, 2 tuning steps on 1 view) on a twin read from
    --twin: the tuned rows are the tuned models' frames captured at K = 1 and at K = 4 (a model
    of four heads, its four subframes), tuned through the run's calibration on training poses
    (the shipped model records none: the envelope's grid), never the scored view. The
    calibration is the twin's truth here (the subject is the row; the fit costs minutes at this
    panel and has its own tests)."""
    monkeypatch.setattr(Q, "twin_calibration", lambda _folder, twin, panel_hw, **_kw:
                        truth_calibration(twin, twin.roi_for_panel(panel_hw)))
    twin_file = _toml(tmp_path, "randomised_seed = 7\nfill_factor = 0.9\n")
    out = tmp_path / "quality.json"
    args = _bench_args("--size", "64x48", "--views", "1", "--tiers", "network,tuned",
                       "--subframes", "1,4", "--other-scene", "none", "--tune-steps", "2",
                       "--tune-views", "1", "--tune-ssim-weight", "0.05",
                       "--unknown-zernike", "none", "--twin",
                       str(twin_file), "--out", str(out), "--plot", "")
    assert Q.run(args) == 0
    result = json.loads(out.read_text())
    assert result["twin"]["file"] == str(twin_file) and result["twin"]["seed"] is None
    assert result["twin"]["fields"]["fill_factor"] == 0.9
    rows = {(r["tier"], r["k"]): r for r in result["rows"]}
    assert set(rows) == {("network", 1), ("tuned", 1), ("tuned", 4)}
    k4_record = result["tuned"]["donut K=4"]
    assert k4_record["tuned_for"]["subframes"] == 4 == k4_record["settings"]["subframes"]
    assert Path(k4_record["dir"]) != Path(result["tuned"]["donut"]["dir"])
    assert rows["tuned", 4]["model_psnr_db"] != rows["tuned", 1]["model_psnr_db"]
    tuned, network = rows["tuned", 1], rows["network", 1]
    assert tuned["tune_steps"] == 2 and tuned["tune_s"] > 0 and tuned["tune_steps_s"] > 0
    for key in ("psnr_db", "ssim", "speckle", "model_psnr_db", "seconds"):
        assert math.isfinite(tuned[key]), key
    assert tuned["model_psnr_db"] != network["model_psnr_db"]  # another model's frame
    record = result["tuned"]["donut"]
    twin = TrueBench.from_toml(twin_file)
    cal = truth_calibration(twin, twin.roi_for_panel(sim_panel_hw((48, 64))))
    assert record["tuned_for"]["calibration_sha256"] == fingerprint(cal)
    assert record["steps"] == 2 and len(record["views"]) == 1
    assert record["settings"]["ssim_weight"] == 0.05 == record["tuned_for"]["ssim_weight"]
    scored = [{k: v for k, v in view.items() if k not in ("scene", "view", "planes_m")}
              for view in result["views"]]
    assert len(scored) == 1 and scored[0]["kind"] == "orbit"
    assert not any(v in scored for v in record["views"])
    assert Path(record["dir"], "model.onnx").is_file()
    goals = {g["goal"]: g for g in result["goals"]}
    assert goals[f"tuned (K=1) captured PSNR on the model's scene >= {Q.GOAL_TUNED_K1_DB:g} "
                 "dB"]["diffs"] == [round(tuned["psnr_db"], 3)]
    k4 = goals[f"tuned (K=4) captured PSNR >= {Q.GOAL_TUNED_K4_DB:g} dB"]
    assert k4["diffs"] == [round(rows["tuned", 4]["psnr_db"], 3)]


def test_a_second_scene_with_its_model_is_tuned_and_judged_over_its_exact_frame(
        tmp_path, monkeypatch) -> None:
    """--other-model gives the second scene the model tiers: its tuned model is tuned on that
    scene, in its own folder, and the goal over the exact frame is judged on that scene's
    pairs only. (The second scene is the donut's file under another name with the same model:
    the subject is the run's bookkeeping.)"""
    monkeypatch.setattr(Q, "twin_calibration", lambda _folder, twin, panel_hw, **_kw:
                        truth_calibration(twin, twin.roi_for_panel(panel_hw)))
    other = tmp_path / "ring.ply"
    other.write_bytes(Q.DONUT.read_bytes())
    out = tmp_path / "quality.json"
    assert Q.run(_bench_args("--size", "64x48", "--views", "1", "--tiers", "exact,tuned",
                             "--subframes", "1", "--other-scene", str(other), "--other-model",
                             str(Q.DONUT_MODEL), "--tune-steps", "1", "--tune-views", "1",
                             "--unknown-zernike", "none", "--out", str(out),
                             "--plot", "")) == 0
    result = json.loads(out.read_text())
    rows = {(r["scene"], r["tier"]): r for r in result["rows"]}
    assert set(rows) == {(s, t) for s in ("donut", "ring") for t in ("exact", "tuned")}
    assert Path(result["tuned"]["ring"]["dir"]).parent.name == "quality-tune-ring"
    assert result["tuned"]["ring"]["dir"] != result["tuned"]["donut"]["dir"]
    goal = {g["goal"]: g for g in result["goals"]}[
        f"tuned (K=1) over the exact frame on another scene >= +{Q.GOAL_TUNED_OVER_EXACT_DB:g} "
        "dB captured"]
    assert goal["diffs"] == [round(rows["ring", "tuned"]["psnr_db"]
                                   - rows["ring", "exact"]["psnr_db"], 3)]


@pytest.mark.parametrize(("argv", "message"), [
    (("--other-scene", "none", "--other-model", "m.onnx"),
     "--other-model m.onnx: needs --other-scene (its scene), not 'none'"),
    (("--other-scene", "no-such.ply"), "--other-scene no-such.ply: not found"),
    (("--other-model", "no-such.onnx"), "--other-model no-such.onnx: not found"),
])
def test_a_second_scene_or_model_that_cannot_run_is_refused_before_the_calibration(
        tmp_path, monkeypatch, argv, message) -> None:
    def calibrate(*_a, **_kw):
        raise AssertionError("calibrated before the files were checked")

    monkeypatch.setattr(Q, "twin_calibration", calibrate)
    monkeypatch.chdir(tmp_path)
    with pytest.raises((ValueError, FileNotFoundError)) as info:
        Q.run(_bench_args(*argv, "--out", str(tmp_path / "q.json"), "--plot", ""))
    assert str(info.value) == message
    assert not (tmp_path / "q.json").exists()


@pytest.mark.parametrize(("model_flag", "scene_flag"), [("--model", "--scene"),
                                                      ("--other-model", "--other-scene")])
def test_a_model_built_from_another_scene_is_refused_naming_both_before_the_calibration(
        tmp_path, monkeypatch, model_flag, scene_flag) -> None:
    """A model measured on a scene its metadata does not record would score a scene it never
    saw (the network tiers have no other check): refused with both files and both hashes."""
    def calibrate(*_a, **_kw):
        raise AssertionError("calibrated before the files were checked")

    monkeypatch.setattr(Q, "twin_calibration", calibrate)
    other = tmp_path / "other.ply"
    other.write_bytes(Q.DONUT.read_bytes() + b"\n")  # one byte more: another file
    argv = [model_flag, str(Q.DONUT_MODEL), scene_flag, str(other)]
    if model_flag == "--other-model":
        argv += ["--scene", str(Q.DONUT)]
    with pytest.raises(ValueError) as info:
        Q.run(_bench_args(*argv, "--out", str(tmp_path / "q.json"), "--plot", ""))
    recorded = recorded_scenes(read_metadata(Q.DONUT_MODEL))
    assert str(info.value) == (
        f"{model_flag} {Q.DONUT_MODEL}: built from another scene than {scene_flag} {other} "
        f"(SHA-256 {recorded[0][:12]}... in the model's metadata, "
        f"{Q.sha256_file(other)[:12]}... for the file)")
    assert not (tmp_path / "q.json").exists()


def test_the_tuned_goals_are_checked_on_the_rows() -> None:
    rows = [*ROWS, _row("donut", 0, "tuned", 1, 27.5, 0.2, 0.6),
            _row("donut", 1, "tuned", 1, 26.9, 0.2, 0.7)]
    for r in rows:
        if r["tier"] == "tuned":
            r["tune_steps_s"] = 600.0
    goals = {g["goal"]: g for g in goal_checks(rows)}
    g = goals["tuned (K=1) captured PSNR on the model's scene >= 27 dB"]
    assert g["diffs"] == [27.5, 26.9] and g["mean_diff"] == pytest.approx(27.2) and g["met"]
    g = goals["tuned (K=1) over sgd (K=1) >= 0 dB captured"]
    assert g["diffs"] == [3.0, 3.9] and g["met"] is True
    g = goals["tuned (K=1) SSIM >= the network's (paired)"]
    assert g["met"] is True  # the rows' SSIM is PSNR / 40
    ratio = next(v for k, v in goals.items() if k.startswith("tuned frame time"))
    assert ratio["diffs"] == [1.2, 1.0] and ratio["met"] is True
    assert next(v for k, v in goals.items() if k.startswith("`model tune` steps"))["met"]
    assert goals["tuned (K=1) over the exact frame on another scene >= +2.5 dB "
                 "captured"]["met"] is None  # the guitar has no model here


def test_the_learned_tiers_refine_and_tune_through_a_bench_learned_in_the_run(
        tmp_path, monkeypatch) -> None:
    """A tiny run (64 x 48, one seeded view): the bench is learned on top of the run's
    calibration from the twin's captures, into a folder beside it that a rerun reuses; sgd and
    the tuned model run through it beside the parametric ones, the capture and fit seconds in
    the record. The plan is shrunk (the subject is the rows; `nhfd calib learn` has its own
    tests)."""
    made: list[Calibration] = []  # the run's parametric calibration

    def calibrated(_folder, twin, panel_hw, **_kw) -> Calibration:
        made.append(truth_calibration(twin, twin.roi_for_panel(panel_hw)))
        return made[-1]

    monkeypatch.setattr(Q, "twin_calibration", calibrated)
    plan = partial(LearnPlan, random_patterns=1, structured_patterns=2, held_out_patterns=1,
                   planes_m=(-2e-4, 0.0, 2e-4), held_out_plane=1, batch=2)
    monkeypatch.setattr(Q, "LearnPlan", plan)
    out = tmp_path / "quality.json"
    common = ("--size", "64x48", "--views", "1", "--subframes", "1", "--other-scene", "none",
              "--unknown-zernike", "none", "--iterations", "3", "--learn-patterns", "1",
              "--learn-steps", "3", "--calibration-dir", str(tmp_path / "cal"), "--plot", "")
    assert Q.run(_bench_args(*common, "--tiers", "sgd,sgd-learned,tuned-learned",
                             "--tune-steps", "2", "--tune-views", "1", "--out", str(out))) == 0
    result = json.loads(out.read_text())
    rows = {(r["tier"], r["k"]): r for r in result["rows"]}
    assert set(rows) == {("sgd", 1), ("sgd-learned", 1), ("tuned-learned", 1)}
    rec = result["learned"]
    assert not rec["reused"] and rec["steps"] == 3
    assert rec["captures"] == 4 * 3 * 3  # (1 sgd + 1 random + 2 structured) x 3 planes x RGB
    assert rec["capture_s"] > 0 and rec["fit_s"] > 0
    assert Path(rec["dir"]).parent == tmp_path / "cal"
    parametric = Calibration.load(made[0].save(tmp_path / "parametric.toml"))  # as a file has it
    learned = Calibration.load(Path(rec["dir"]) / "calibration.toml")
    assert learned.learned_sha256  # on top of the run's fit, stamped when its file was written
    assert replace(learned, learned_file="", learned_sha256="", created="", source="") == \
        replace(parametric, created="", source="")
    tuned_for = result["tuned_learned"]["donut"]["tuned_for"]
    assert tuned_for["calibration_sha256"] == fingerprint(learned) != fingerprint(parametric)
    # The learned bench's own estimate of the frames, not the parametric one's.
    assert rows["sgd-learned", 1]["model_psnr_db"] != rows["sgd", 1]["model_psnr_db"]
    for row in rows.values():
        assert math.isfinite(row["psnr_db"]) and math.isfinite(row["model_psnr_db"])
    goals = {g["goal"]: g for g in result["goals"]}
    g = goals["sgd-learned (K=1) over sgd (K=1) >= 0 dB captured"]
    assert g["diffs"] == [round(rows["sgd-learned", 1]["psnr_db"] - rows["sgd", 1]["psnr_db"],
                                3)]
    # A rerun with the same bench, calibration and plan reuses the learned bench.
    again = tmp_path / "again.json"
    assert Q.run(_bench_args(*common, "--tiers", "sgd-learned", "--out", str(again))) == 0
    rec2 = json.loads(again.read_text())["learned"]
    assert rec2["reused"] and rec2["dir"] == rec["dir"] and rec2["fit_s"] == rec["fit_s"]


def test_the_learned_goals_are_checked_on_the_rows() -> None:
    rows = [*ROWS, _row("donut", 0, "sgd-learned", 1, 30.0, 0.2),
            _row("donut", 1, "sgd-learned", 1, 22.0, 0.2),
            _row("donut", 0, "tuned", 1, 25.0, 0.2), _row("donut", 0, "tuned-learned", 1, 29.5,
                                                         0.2)]
    goals = {g["goal"]: g for g in goal_checks(rows)}
    g = goals[f"sgd-learned (K=1) captured PSNR on the model's scene >= "
              f"{Q.GOAL_SGD_LEARNED_K1_DB:g} dB"]
    assert g["diffs"] == [30.0, 22.0] and g["met"] is False  # mean 26.0
    g = goals["sgd-learned (K=1) over sgd (K=1) >= 0 dB captured"]
    assert g["diffs"] == [5.5, -1.0] and g["mean_diff"] == pytest.approx(2.25) and g["met"]
    g = goals["tuned-learned (K=1) over tuned (K=1) >= 0 dB captured"]
    assert g["diffs"] == [4.5] and g["met"] is True
    assert goals[f"tuned-learned (K=1) captured PSNR on the model's scene >= "
                 f"{Q.GOAL_TUNED_LEARNED_K1_DB:g} dB"]["met"] is True


def _record(cpu: str, rows: list[dict], views: list[dict]) -> dict:
    return {"machine": {"cpu": cpu, "cores": 2}, "size": "64x48", "window_hw": [48, 64],
            "twin": {"seed": 7}, "views": views, "rows": rows}


def test_replotted_runs_merge_their_rows_the_first_run_winning_a_row_both_measured() -> None:
    donut = [{"scene": "donut", "view": 0, "azimuth_deg": 13.8}]
    a = _record("A", [_row("donut", 0, "network", 1, 24.0, 0.3),
                      _row("donut", 0, "tuned", 4, 26.0, 0.2)], donut)
    b = _record("A", [_row("donut", 0, "network", 1, 99.0, 0.3),
                      _row("donut", 0, "tuned-learned", 4, 27.0, 0.1),
                      _row("ring", 0, "exact", 1, 30.0, 0.3)],
                [*donut, {"scene": "ring", "view": 0, "azimuth_deg": 50.0}])
    rows = Q.merged_rows([("a.json", a), ("b.json", b)])
    assert [(r["scene"], r["tier"], r["k"], r["psnr_db"]) for r in rows] == [
        ("donut", "network", 1, 24.0), ("donut", "tuned", 4, 26.0),
        ("donut", "tuned-learned", 4, 27.0), ("ring", "exact", 1, 30.0)]


@pytest.mark.parametrize(("change", "message"), [
    ({"machine": {"cpu": "B", "cores": 2}}, "--replot b.json: another machine than a.json's"),
    ({"twin": {"seed": 8}}, "--replot b.json: another twin than a.json's"),
    ({"views": [{"scene": "donut", "view": 0, "azimuth_deg": 40.0}]},
     "--replot b.json: other donut views than a.json's"),
])
def test_replotted_runs_of_another_machine_twin_or_views_are_refused_naming_them(
        change, message) -> None:
    a = _record("A", [_row("donut", 0, "network", 1, 24.0, 0.3)],
                [{"scene": "donut", "view": 0, "azimuth_deg": 13.8}])
    with pytest.raises(ValueError) as info:
        Q.merged_rows([("a.json", a), ("b.json", {**a, **change})])
    assert str(info.value).startswith(message)


def test_replot_writes_the_merged_figure_and_refuses_no_figure_or_a_bad_file(tmp_path) -> None:
    a = _record("A", [_row("donut", 0, "network", 1, 24.0, 0.3)],
                [{"scene": "donut", "view": 0, "azimuth_deg": 13.8}])
    (tmp_path / "a.json").write_text(json.dumps(a))
    (tmp_path / "bad.json").write_text("{")
    (tmp_path / "norows.json").write_text(json.dumps({k: v for k, v in a.items() if k != "rows"}))
    (tmp_path / "badrow.json").write_text(json.dumps({**a, "rows": [{"scene": "donut"}]}))
    figure = tmp_path / "f.png"
    with pytest.raises(ValueError, match=r"^--replot: needs --plot"):
        Q.run(_bench_args("--replot", str(tmp_path / "a.json"), "--plot", ""))
    with pytest.raises(ValueError, match=r"bad.json: not a bench quality JSON"):
        Q.replot(f"{tmp_path / 'a.json'},{tmp_path / 'bad.json'}", str(figure))
    with pytest.raises(ValueError, match=r"norows.json: not a bench quality JSON \(no rows\)$"):
        Q.replot(str(tmp_path / "norows.json"), str(figure))
    with pytest.raises(ValueError, match=r"badrow.json: not a bench quality JSON \(no k, "):
        Q.replot(str(tmp_path / "badrow.json"), str(figure))
    with pytest.raises(FileNotFoundError, match=r"--replot .*nope.json: not found"):
        Q.replot(str(tmp_path / "nope.json"), str(figure))
    assert not figure.exists()
    assert Q.run(_bench_args("--replot", str(tmp_path / "a.json"), "--plot", str(figure))) == 0
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
