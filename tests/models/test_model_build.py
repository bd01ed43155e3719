"""`nhfd model build`: the whole chain on a tiny recipe, its resume, its refusals, its report."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import struct
from pathlib import Path
from types import SimpleNamespace

import pytest

from nhfd.calibration import Calibration, fingerprint
from nhfd.cli import cmd_model
from nhfd.cli.main import main
from nhfd.config import Config
from nhfd.demos.serve import check_model_and_scene
from nhfd.drivers.simcamera import TrueBench
from nhfd.models import build as mb
from nhfd.models.build import STAGES, Recipe, run_build
from nhfd.models.sizes import read_metadata
from nhfd.models.train import TrainOptions
from nhfd.pipeline import tune as tune_module
from nhfd.scene.io import load_scene
from tests.calib.twin_stack import truth_calibration

SCENE = Path(__file__).parents[1] / "data" / "formats" / "donut-crop.ply"
# The bench a build is made for: the default configuration's [optics] and [slm].
BENCH = (Config().optics, Config().slm)


def tiny_recipe(**kw) -> Recipe:
    train = TrainOptions(width=8, depth=2, unshuffle=1, inputs="rgbd", steps=40,
                         crop_width_px=32, crop_height_px=32, checkpoint_every=10, val_views=1,
                         progress=False, threads=1)  # fmt: skip
    base = dict(name="tiny", views=8, width_px=48, height_px=32, fov_x_deg=40.0,
                azimuth_deg=(-20.0, 20.0), elevation_deg=(10.0, 30.0), radius_scale=(0.9, 1.1),
                phase="depth", seed=0, eval_views=0, sheet_views=2, int8=True, train=train)
    base.update(kw)
    return Recipe(**base)


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def _fingerprints(out: Path) -> dict[str, tuple[int, str]]:
    files = [p for p in out.rglob("*") if p.is_file() and p.name != mb.STATE]
    return {str(p.relative_to(out)): (p.stat().st_mtime_ns,
                                      hashlib.sha256(p.read_bytes()).hexdigest())
            for p in files}  # fmt: skip


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A build interrupted by a failure in training, then rerun to the end."""
    out = tmp_path_factory.mktemp("build") / "donut"
    logs: list[str] = []
    real_train = mb.train

    def failing_train(*a, **k):
        raise RuntimeError("injected failure in training")

    mb.train = failing_train
    try:
        with pytest.raises(RuntimeError, match="injected failure"):
            run_build(SCENE, out, tiny_recipe(), *BENCH, workers=1, log=logs.append,
                      progress=False)  # fmt: skip
    finally:
        mb.train = real_train
    state = json.loads((out / mb.STATE).read_text())
    after_failure = {s: e.get("done") for s, e in state["stages"].items()}
    shards = {p.name: p.stat().st_mtime_ns for p in (out / "dataset").glob("view_*.npz")}
    logs.clear()
    res = run_build(SCENE, out, tiny_recipe(), *BENCH, workers=1, log=logs.append,
                    progress=False)  # fmt: skip
    return out, res, after_failure, shards, list(logs)


def test_a_failure_in_training_keeps_the_dataset_and_the_rerun_continues_from_train(built):
    out, res, after_failure, shards, logs = built
    assert after_failure == {"scene": True, "reduce": True, "dataset": True, "train": False}
    assert res.skipped == ["scene", "reduce", "dataset"]
    assert res.ran == ["train", "export", "eval", "report"]
    assert any(line == "[3/7] dataset: skipped (done, inputs unchanged)" for line in logs)
    # the dataset's shards were not rewritten by the rerun
    assert {p.name: p.stat().st_mtime_ns for p in (out / "dataset").glob("view_*.npz")} == shards
    assert len(shards) == 8


def test_the_build_writes_the_model_the_report_and_the_contact_sheet(built):
    out, res, *_ = built
    report = json.loads((out / "report.json").read_text())
    assert report == res.report
    f = report["heldout"]["float"]
    for key in ("model_psnr_db", "hologram_2d_psnr_db", "black_psnr_db", "model_ssim",
                "margin_over_2d_db", "focus_bins_passed", "focus_bins", "psnr_vs_angle"):
        assert key in f, key
    assert f["views"] == 2  # one interpolation and one extrapolation view of 8 poses
    assert f["model_psnr_db"] > f["black_psnr_db"] + 1  # even 40 steps beat black
    assert report["checks"]["beats_black"] is True
    assert f["angle_reference"].startswith("the poses the model was trained on")
    # held-out views lie off the training poses
    assert all(angle > 0 for angle, _ in f["psnr_vs_angle"])
    # The scene the dataset rendered is the reduction, which the report states and counts.
    red = report["reduce"]
    assert red["reduced"] is True and red["n_gaussians_in"] == 2108
    assert red["n_kept"] == red["gaussians"] == len(load_scene(out / "scene.ply"))
    assert red["n_kept"] + red["n_culled_frustum"] + red["n_culled_contribution"] == 2108
    assert red["max_grey_change"] <= red["grey_levels"] == 1.0
    # the colours share the longest wavelength's 9 x 9 views (the dataset renders 81 per pose)
    assert red["envelope"]["poses"] == 8 and red["envelope"]["views_per_pose"] == 81
    assert [v["n_views"] for v in report["dataset"]["light_field_views"]] == [81, 49, 36]
    m = report["dataset"]["depth_mapping"]
    assert m["z_max_m"] == pytest.approx(3e-3) and m["d_near"] < m["d_far"]
    assert (out / "model.onnx").stat().st_size > 1000
    q = report["heldout"]["int8"]
    assert q["kept"] == (q["loss_vs_float_db"] <= mb.INT8_MAX_LOSS_DB)
    assert (out / "model-int8.onnx").exists() == q["kept"]
    # the daemon serves int8 by the figures inside the file, measured against this float model
    from nhfd.dataset.build import sha256_file
    from nhfd.models.quantise import HELDOUT_KEY
    from nhfd.models.sizes import read_metadata

    record = read_metadata(out / "candidates" / "model-int8.onnx")[HELDOUT_KEY]
    assert record["loss_vs_float_db"] == pytest.approx(q["loss_vs_float_db"], abs=1e-9)
    assert record["float_sha256"] == sha256_file(out / "model.onnx")
    h = report["heldout"]["fp16"]
    assert h["kept"] == (h["loss_vs_float_db"] <= mb.INT8_MAX_LOSS_DB)
    assert (out / "model-fp16.onnx").exists() == h["kept"]
    assert set(report["stages"]) == set(STAGES)
    assert all(s["seconds"] > 0 for s in report["stages"].values())
    assert report["stages"]["train"]["peak_rss_mb"] > 50  # torch alone is more
    sheet = report["contact_sheet"]
    assert _png_size(out / "contact_sheet.png") == tuple(sheet["size_px"])
    from nhfd.models.contact_sheet import sheet_size_px

    assert tuple(sheet["size_px"]) == sheet_size_px(2, (32, 48))
    for v in sheet["views"]:
        assert v["near_focus_mm"] > v["far_focus_mm"]  # near content has the larger z_h


def test_the_demo_serves_the_model_with_the_scene_file_it_was_built_from(built, tmp_path):
    """The dataset rendered the reduced scene.ply, whose hash is the model's scene_sha256; the
    model also records its source file's, so `nhfd demo --scene SOURCE` takes it, and a file of
    neither is refused."""
    out, *_ = built
    model = out / "model.onnx"
    meta = check_model_and_scene(model, SCENE, Config())
    assert meta["source_scene_sha256"] == hashlib.sha256(SCENE.read_bytes()).hexdigest()
    assert meta["scene_sha256"] == hashlib.sha256((out / "scene.ply").read_bytes()).hexdigest()
    check_model_and_scene(model, out / "scene.ply", Config())
    other = tmp_path / "other.ply"
    other.write_bytes(SCENE.read_bytes() + b"\n")
    with pytest.raises(ValueError, match="trained on another scene than"):
        check_model_and_scene(model, other, Config())


def test_a_rerun_skips_every_stage_and_touches_no_file(built):
    out, *_ = built
    before = _fingerprints(out)
    logs: list[str] = []
    res = run_build(SCENE, out, tiny_recipe(), *BENCH, workers=1, log=logs.append,
                    progress=False)  # fmt: skip
    assert res.ran == [] and res.skipped == list(STAGES)
    assert [line.split(": ", 1)[1] for line in logs] == \
        ["skipped (done, inputs unchanged)"] * len(STAGES)
    assert _fingerprints(out) == before


LATE_STAGES = ("train", "export", "eval", "report")


@pytest.fixture
def early_build(tmp_path, monkeypatch):
    """A build whose stages after the dataset are stand-ins (fast: what they return is all the
    tests below read), built once; returns (OUT, a rerun function, the run's log)."""
    for stage in LATE_STAGES:
        monkeypatch.setitem(mb.STAGE_FUNCS, stage, lambda ctx: {"sheet": None, "outputs": []})
    monkeypatch.setattr(mb, "build_report", lambda ctx, sheet: {"stand-in": True})
    out, logs = tmp_path / "early", []

    def rerun():
        logs.clear()
        return run_build(SCENE, out, tiny_recipe(views=6), *BENCH, workers=1,
                         log=logs.append, progress=False)  # fmt: skip

    rerun()
    return out, rerun, logs


def test_a_shard_changed_after_the_build_is_rebuilt_on_resume(early_build):
    """A finished dataset counts as done only while its shards hash as they did (issue 32):
    the changed shard is rebuilt, the intact ones kept, and the stages after it run again."""
    out, rerun, logs = early_build
    state = json.loads((out / mb.STATE).read_text())
    entry = state["stages"]["dataset"]
    shards = sorted(p.name for p in (out / "dataset").glob("view_*.npz"))
    assert len(shards) == 6
    assert set(entry["output_sha256"]) == {"dataset/manifest.json",
                                           *(f"dataset/{n}" for n in shards)}
    victim = out / "dataset" / shards[3]
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte, the zip still opens
    victim.write_bytes(bytes(data))
    assert mb.changed_outputs(out, entry) == [f"dataset/{shards[3]}"]
    assert all(mb.changed_outputs(out, state["stages"][s]) == [] for s in STAGES if s != "dataset")
    kept = {n: (out / "dataset" / n).stat().st_mtime_ns for n in shards if n != shards[3]}
    res = rerun()
    assert res.skipped == ["scene", "reduce"] and res.ran == list(STAGES[2:])
    assert f"[3/7] dataset: 1 output(s) changed since it finished (dataset/{shards[3]}); " \
           "rebuilding them" in logs
    assert {n: (out / "dataset" / n).stat().st_mtime_ns for n in kept} == kept
    after = json.loads((out / mb.STATE).read_text())["stages"]["dataset"]
    assert mb.changed_outputs(out, after) == []
    assert after["output_sha256"][f"dataset/{shards[3]}"] == mb.sha256_file(victim)
    assert rerun().ran == []  # and now it is done again


def test_a_killed_attempts_time_counts_towards_its_stage(early_build):
    """An attempt killed outright (nothing of it ran its except) left its time in `attempt`,
    written while it ran; the resumed stage's seconds include it and the failed attempts'."""
    out, rerun, _ = early_build
    state = json.loads((out / mb.STATE).read_text())
    report = state["stages"]["report"]
    state["stages"]["report"] = {"key": report["key"], "done": False, "started": 0.0,
                                 "partial": {"seconds": 5.0, "cpu_s": 1.0},
                                 "attempt": {"seconds": 30.0, "cpu_s": 4.0}}
    (out / mb.STATE).write_text(json.dumps(state))
    assert rerun().ran == ["report"]
    done = json.loads((out / mb.STATE).read_text())["stages"]["report"]
    assert done["done"] and "attempt" not in done
    assert 35.0 <= done["seconds"] < 35.0 + 60 and done["cpu_s"] >= 5.0


def test_the_attempt_clock_records_while_the_stage_runs_and_clears_at_the_end():
    import time

    seen: list = []
    with mb.AttemptClock(seen.append, every_s=0.02):
        time.sleep(0.2)
    assert seen[-1] is None and len(seen) >= 3
    running = [s["seconds"] for s in seen[:-1]]
    assert running == sorted(running) and 0 < running[0] < running[-1] <= 0.25
    assert mb.carried_time({"partial": {"seconds": 2.0}, "attempt": {"seconds": 3.0,
                                                                      "cpu_s": 1.0}}) == \
        {"seconds": 5.0, "cpu_s": 1.0}
    assert mb.carried_time(None) == {"seconds": 0.0, "cpu_s": 0.0}


def test_another_recipe_or_scene_is_refused_without_force(built, tmp_path):
    out, *_ = built
    before = _fingerprints(out)
    with pytest.raises(ValueError, match=rf"{out} holds a build of .* with profile 'tiny', not "
                       r"of .* with profile 'other'; use another --out, or --force"):
        run_build(SCENE, out, tiny_recipe(name="other"), *BENCH, progress=False,
                  log=lambda _m: None)  # fmt: skip
    with pytest.raises(ValueError, match=r"the train stage was built with other settings.*"
                       r"--force to redo it"):
        run_build(SCENE, out, mb.recipe_with(tiny_recipe(), steps=41), *BENCH,
                  progress=False, log=lambda _m: None)  # fmt: skip
    assert _fingerprints(out) == before
    stray = tmp_path / "stray"
    stray.mkdir()
    (stray / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"holds files that are not a model build.*--force"):
        run_build(SCENE, stray, tiny_recipe(), *BENCH, progress=False, log=lambda _m: None)


def test_recipes_come_from_the_configuration():
    config = Config()
    default = Recipe.from_config(config.model)
    assert default.name == "default" and default.views == 130
    assert (default.width_px, default.height_px) == (512, 288)
    # the default recipe trains as `nhfd train` does by default (the shipped model's recipe)
    assert default.train == TrainOptions.from_config(config.model)
    quick = Recipe.from_config(config.model, "quick")
    assert quick.train.steps < default.train.steps and quick.views < default.views
    with pytest.raises(ValueError, match=r"--profile 'huge': not one of the recipes default, "
                       r"quick"):
        Recipe.from_config(config.model, "huge")


@pytest.mark.parametrize("toml,message", [
    ('[model.build]\nprofile = "nope"', "build.profile = 'nope': not one of the recipes "
     "default, quick"),
    ('[model.build.profiles.quick]\nnetwork = "huge"',
     "build.profiles.quick.network = 'huge': not one of the profiles accurate, balanced"),
    ("[model.build.profiles.quick]\nelevation_deg = [10.0, 95.0]",
     r"elevation_deg = \[10.0, 95.0\]: must lie in \[-89, 89\]"),
    ("[model.build.profiles.quick]\nviews = 2", r"model.build.profiles.quick.views.*2"),
])  # fmt: skip
def test_bad_recipes_are_refused_naming_the_key(tmp_path, toml, message):
    from nhfd.config import load_config

    path = tmp_path / "nhfd.toml"
    path.write_text(toml + "\n")
    with pytest.raises(ValueError, match=message):
        load_config(path)


def test_a_recipe_of_ones_own_takes_the_default_recipe_for_what_it_leaves_out(tmp_path):
    from nhfd.config import load_config

    path = tmp_path / "nhfd.toml"
    path.write_text("[model.build.profiles.mine]\nsteps = 200\n")
    mine = Recipe.from_config(load_config(path).config.model, "mine")
    assert mine.train.steps == 200 and mine.views == 130 and mine.train.profile == "fast"


def test_cli_refuses_a_bad_device_and_a_bad_profile(tmp_path, capsys):
    from nhfd.cli.main import main

    assert main(["model", "build", str(SCENE), "--out", str(tmp_path / "o"), "--device",
                 "tpu"]) == 2  # fmt: skip
    assert "--device = 'tpu': must be one of auto, cpu, cuda, cuda:N" in capsys.readouterr().err
    assert main(["model", "build", str(SCENE), "--out", str(tmp_path / "o"), "--profile",
                 "huge"]) == 2  # fmt: skip
    assert "--profile 'huge'" in capsys.readouterr().err
    import torch

    if not torch.cuda.is_available():  # refused before any stage runs, not after the dataset
        assert main(["model", "build", str(SCENE), "--out", str(tmp_path / "o"), "--device",
                     "cuda"]) == 2  # fmt: skip
        err = capsys.readouterr().err
        assert "--device = 'cuda': torch " in err and "sees 0 CUDA devices" in err
    assert not os.path.exists(tmp_path / "o")


def test_serve_tells_a_load_that_timed_out_from_one_that_failed():
    """A load still running when --serve stops waiting is not blamed on the daemon's folders."""
    from nhfd.cli.cmd_model import _load
    from nhfd.daemon.client import Client

    class Scripted(Client):  # the real wait_job over scripted job states (no daemon)
        def __init__(self, state: str, error: str | None = None) -> None:
            self.state, self.error = state, error

        def call(self, method, **params):
            if method == "load_model":
                return {"job": 3}
            return {"id": 3, "state": self.state, "error": self.error}

    m = Path("/models/m.onnx")
    _load(Scripted("done"), "load_model", m, 0.1)
    with pytest.raises(RuntimeError) as e:
        _load(Scripted("running"), "load_model", m, 0.1)
    assert str(e.value) == ("load_model /models/m.onnx: job 3 still running after 0.1 s "
                            "(`nhfctl job 3` follows it)")
    with pytest.raises(RuntimeError) as e:
        _load(Scripted("failed", "path = 'm.onnx' resolves outside"), "load_model", m, 0.1)
    assert str(e.value).startswith("load_model /models/m.onnx: path = 'm.onnx' resolves outside "
                                   "(the daemon reads files only inside daemon.paths.scene_dirs")


def test_serve_loads_the_scene_and_the_model_into_a_running_daemon(built, tmp_path_factory):
    import argparse
    import contextlib
    import shutil
    import tempfile

    from nhfd.cli.cmd_model import serve
    from tests.daemon.conftest import Running, bench_config

    out, *_ = built
    root = Path(tempfile.mkdtemp(prefix="nhfd-mb-", dir="/tmp"))  # a short socket path
    config = bench_config(root, None)
    running = Running(config, root)
    try:
        # no --socket: the configured daemon's, as nhfctl finds it
        args = argparse.Namespace(model_dir=None, scene_dir=None, socket=None)
        # relative folders are the daemon's (its base_dir is root): serve from there
        cwd = os.getcwd()
        os.chdir(root)
        try:
            serve(config, SCENE, out, "nhf-donut-crop-tiny.onnx", args)
        finally:
            os.chdir(cwd)
        status = running.client().status()
        assert Path(status["scene"]["path"]) == root / "scenes" / SCENE.name
        assert status["scene"]["gaussians"] == 2108
        assert Path(status["model"]["path"]).name == "nhf-donut-crop-tiny.onnx"
        assert (root / "models" / "nhf-donut-crop-tiny.onnx").read_bytes() == \
            (out / "model.onnx").read_bytes()
        # a kept int8 model goes beside it, and the CPU serves it by the figures it records
        int8 = root / "models" / "nhf-donut-crop-tiny-int8.onnx"
        assert int8.exists() == (out / "model-int8.onnx").exists()
        assert status["model"]["variant"] == ("int8" if int8.exists() else "float")
        view = status["view"]["requested"]
        assert view["kind"] == "orbit" and view["azimuth_deg"] == 0.0  # middle of [-20, 20]
        assert view["elevation_deg"] == 20.0
    finally:
        with contextlib.suppress(Exception):
            running.stop()
        shutil.rmtree(root, ignore_errors=True)


def test_a_gpu_build_builds_its_dataset_on_that_gpu_or_says_why_not(monkeypatch):
    """`nhfd model build --device cuda`: the dataset is rendered and inverted on the training GPU
    in one process (where gsplat renders); without gsplat the CPU's workers build it and the
    log says why; a CPU build keeps its workers."""
    logged: list[str] = []

    def ctx(device: str) -> SimpleNamespace:
        return SimpleNamespace(recipe=SimpleNamespace(train=SimpleNamespace(device=device)),
                               workers=6, log=logged.append)

    monkeypatch.setattr(mb, "check_device", lambda device: device)
    assert mb._dataset_device(ctx("cuda:1")) == ("cuda:1", 1)
    assert mb._dataset_device(ctx("cpu")) == ("cpu", 6)
    assert logged == []

    def no_gsplat(device: str) -> str:
        raise ValueError(f"--device {device}: needs the gsplat package (pip install 'nhfd[gpu]')")

    monkeypatch.setattr(mb, "check_device", no_gsplat)
    assert mb._dataset_device(ctx("cuda:0")) == ("cpu", 6)
    assert logged == ["dataset on the CPU: --device cuda:0: needs the gsplat package "
                      "(pip install 'nhfd[gpu]')"]


def test_build_with_a_calibration_tunes_the_model_as_its_last_stage(built, tmp_path,
                                                                     monkeypatch, capsys):
    """`nhfd model build --calibration FILE` on a finished build (a copy of the tiny one, its
    recipe given to the CLI): every build stage is skipped, then the model is tuned through that
    calibration (2 steps, 1 view, the build's window) into OUT/tuned/model.onnx, whose
    `tuned_for` names it, and its checked sizes are checked again; OUT/model.onnx is not
    changed. The size check itself is recorded, not run (2.5 min for the tiny model's 3 sizes
    on a loaded 2-core machine; `nhfd model tune`'s own test runs it)."""
    out = tmp_path / "donut"
    shutil.copytree(built[0], out)
    before = (out / "model.onnx").read_bytes()
    monkeypatch.setattr(cmd_model.Recipe, "from_config",
                        classmethod(lambda _cls, *_a, **_k: tiny_recipe()))
    checked: list[tuple[Path, list]] = []
    monkeypatch.setattr(tune_module, "check_and_record",
                        lambda path, sizes: checked.append((Path(path), list(sizes))))
    cal = truth_calibration(TrueBench())
    path = cal.save(tmp_path / "calibration.toml")
    rc = main(["model", "build", str(SCENE), "--out", str(out), "--no-progress",
               "--calibration", str(path), "--tune-steps", "2", "--tune-views", "1",
               "--tune-size", "48x32"])
    printed = capsys.readouterr().out
    assert rc == 0, printed
    assert "ran nothing" in printed and "tuned for" in printed
    record = read_metadata(out / cmd_model.TUNED_DIR / "model.onnx")["tuned_for"]
    loaded = Calibration.load(path)
    assert record["calibration_sha256"] == fingerprint(loaded)
    assert record["calibration"] == loaded.label and record["steps"] == 2
    assert record["window_hw"] == [32, 48]
    assert (out / "model.onnx").read_bytes() == before
    want = [tuple(e["hw"]) for e in read_metadata(out / "model.onnx")["checked_sizes"]]
    assert want and checked == [(out / cmd_model.TUNED_DIR / "model.onnx", want)]


def test_build_refuses_a_bad_calibration_before_anything_is_written(tmp_path, capsys):
    out = tmp_path / "o"
    other = truth_calibration(TrueBench(wavelengths_m=(640e-9, 532e-9, 450e-9)))
    bad = other.save(tmp_path / "other.toml")
    assert main(["model", "build", str(SCENE), "--out", str(out), "--calibration",
                 str(bad)]) == 2
    assert "--calibration " in capsys.readouterr().err
    assert main(["model", "build", str(SCENE), "--out", str(out), "--calibration",
                 str(tmp_path / "missing.toml")]) == 2
    capsys.readouterr()
    good = truth_calibration(TrueBench()).save(tmp_path / "good.toml")
    assert main(["model", "build", str(SCENE), "--out", str(out), "--calibration", str(good),
                 "--tune-steps", "0"]) == 2
    assert "steps (--steps) = 0: must be in 1..1000000" in capsys.readouterr().err
    assert not out.exists()
