"""`nhfd demo --model --scene`: the user's model and scene reach the daemon's configuration, and a
pair that does not belong together, or a missing file, is refused before anything starts."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from nhfd.cli.main import main
from nhfd.config import load_config
from nhfd.demos import serve as demo
from nhfd.scene.gaussians import make_gaussians
from nhfd.scene.io import save_ply

pytestmark = pytest.mark.skipif(not demo.DEFAULT_MODEL.is_file(),
                                reason=f"no shipped model at {demo.DEFAULT_MODEL}")


@pytest.fixture
def captured(monkeypatch):
    """What `nhfd demo` hands the demo (the daemon demo itself is not run)."""
    calls: list[dict] = []

    def fake_run(out, *, config, model, scene, **_):
        calls.append({"out": out, "config": config, "model": model, "scene": scene})
        return {"stages_ms_median": {}, "runtime_s": 0.0}

    monkeypatch.setattr(demo, "run", fake_run)
    return calls


def other_scene(path):
    g = make_gaussians(means=[[0.0, 0.0, 0.0]], quats=[[1.0, 0, 0, 0]], scales=[[0.1] * 3],
                       opacities=[0.9], sh=np.ones((1, 1, 3)))
    save_ply(path, g)
    return path


def test_defaults_are_the_shipped_model_and_donut(tmp_path, captured):
    assert main(["demo", "--out", str(tmp_path / "out")]) == 0
    assert (captured[0]["model"], captured[0]["scene"]) == (demo.DEFAULT_MODEL, demo.DEFAULT_SCENE)


def test_the_flags_reach_the_daemon_configuration(tmp_path, captured):
    scene = tmp_path / "mine" / "donut-copy.ply"  # the model's scene, under another name
    scene.parent.mkdir()
    shutil.copy(demo.DEFAULT_SCENE, scene)
    model = tmp_path / "models" / "mine.onnx"
    model.parent.mkdir()
    shutil.copy(demo.DEFAULT_MODEL, model)
    assert main(["demo", "--model", str(model), "--scene", str(scene), "--out",
                 str(tmp_path / "out")]) == 0
    call = captured[0]
    assert (call["model"], call["scene"]) == (model, scene)
    cfg, _, info = demo.demo_config(call["config"], model=call["model"], scene=call["scene"],
                                    runtime=tmp_path / "rt", captures=tmp_path / "cap")
    assert cfg.daemon.frames.model == str(model.resolve())
    assert cfg.daemon.paths.scene == str(scene.resolve())
    assert str(scene.parent.resolve()) in cfg.daemon.paths.scene_dirs
    assert str(model.parent.resolve()) in cfg.daemon.paths.model_dirs
    assert info.train_size_hw == (288, 512)


def test_a_model_trained_on_another_scene_is_refused_naming_both(tmp_path, captured, capsys):
    scene = other_scene(tmp_path / "guitar-like.ply")
    with pytest.raises(ValueError, match="trained on another scene") as err:
        demo.check_model_and_scene(demo.DEFAULT_MODEL, scene, load_config(None).config)
    assert str(demo.DEFAULT_MODEL) in str(err.value) and str(scene) in str(err.value)
    assert main(["demo", "--scene", str(scene), "--out", str(tmp_path / "out")]) == 2
    msg = capsys.readouterr().err
    assert str(scene) in msg and str(demo.DEFAULT_MODEL) in msg
    assert not captured and not (tmp_path / "out").exists()


def test_a_model_for_another_panel_is_refused_naming_both_sizes(tmp_path, captured):
    toml = tmp_path / "small-panel.toml"
    toml.write_text("[slm]\nwidth_px = 1280\nheight_px = 720\n")
    config = load_config(str(toml)).config
    with pytest.raises(ValueError, match=r"1920x1080 panel, the configured SLM .* is 1280x720"
                       ) as err:  # fmt: skip
        demo.check_model_and_scene(demo.DEFAULT_MODEL, demo.DEFAULT_SCENE, config)
    assert str(demo.DEFAULT_MODEL) in str(err.value)


def test_missing_files_are_named_and_nothing_starts(tmp_path, captured, capsys):
    absent = tmp_path / "absent.ply"
    assert main(["demo", "--scene", str(absent), "--out", str(tmp_path / "out")]) == 3
    assert f"the scene {absent} is not there" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError, match="nhfd dataset build"):
        demo.check_model_and_scene(tmp_path / "absent.onnx", demo.DEFAULT_SCENE,
                                   load_config(None).config)
    assert not captured and not (tmp_path / "out").exists()
