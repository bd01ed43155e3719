"""Bad input never replaces good state: a model that cannot take the daemon's frames, (and, in
the other tests of this file) a calibration for another bench and a scene of random data are
refused by name, and what was running keeps running."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from .conftest import Running, wait_until

# The tiny model's frames: a 64 x 96 window (its training size), 3 colours.
WINDOW_HW = (64, 96)


def bad_model(tiny_model: Path, out: Path, kind: str) -> Path:
    """A small graph with the tiny model's metadata (so the optics check passes) that cannot
    serve frames: "channels" takes 4 input channels where rgb gives 3, "fixed" takes only an
    8 x 8 input, "nan" returns NaN amplitudes."""
    import onnx
    from onnx import TensorProto, helper

    shape: list = {"channels": ["B", 4, "H", "W"], "fixed": [1, 3, 8, 8]}.get(kind, ["B", 3, "H",
                                                                                     "W"])
    nodes, inits = [], []
    if kind == "channels":
        inits = [helper.make_tensor(n, TensorProto.INT64, [1], [v])
                 for n, v in (("s0", 0), ("s1", 3), ("ax", 1))]
        nodes.append(helper.make_node("Slice", ["rgb", "s0", "s1", "ax"], ["x"]))
    else:
        nodes.append(helper.make_node("Identity", ["rgb"], ["x"]))
    if kind == "nan":
        inits.append(helper.make_tensor("nan", TensorProto.FLOAT, [], [float("nan")]))
        nodes.append(helper.make_node("Mul", ["x", "nan"], ["amplitude"]))
    else:
        nodes.append(helper.make_node("Identity", ["x"], ["amplitude"]))
    nodes.append(helper.make_node("Identity", ["x"], ["phase"]))
    out_shape = ["B", 3, "H", "W"] if kind != "fixed" else [1, 3, 8, 8]
    graph = helper.make_graph(
        nodes, kind, [helper.make_tensor_value_info("rgb", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, out_shape)
         for n in ("amplitude", "phase")], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for prop in onnx.load(str(tiny_model)).metadata_props:
        model.metadata_props.add(key=prop.key, value=prop.value)
    onnx.save(model, str(out))
    return out


# What each bad model's refusal says: the mismatch, expected against found.
REFUSALS = {
    "channels": "input channels: expected 3, found 4",
    "fixed": "input height: expected 64, found 8",
    "nan": "output amplitude: expected finite values, found 18432 of 18432 not finite",
}


def test_a_model_that_cannot_take_the_frames_is_refused_and_the_old_one_keeps_running(
        short_dir, mecom_twin, tiny):
    from .test_faults import light
    from .test_frames import daemon_config, wait_for_frames

    config = daemon_config(short_dir, mecom_twin, tiny,
                           paths={"scene": str(short_dir / "scenes" / "cloud.ply")},
                           frames={"model": str(short_dir / "models" / "tiny.onnx")})
    r = Running(config, short_dir)
    try:
        c = r.client()
        before = wait_for_frames(c)["model"]
        light(c, mecom_twin, "green")
        for kind, refusal in REFUSALS.items():
            path = bad_model(tiny["model"], short_dir / "models" / f"bad-{kind}.onnx", kind)
            job = c.call("load_model", path=str(path))["job"]
            wait_until(lambda job=job: c.call("job", id=job)["state"] in ("failed", "done"), 20,
                       f"the {kind} model's load")
            state = c.call("job", id=job)
            assert state["state"] == "failed", (kind, state)
            assert str(path) in state["error"] and refusal in state["error"], state["error"]
            assert c.status()["model"] == before  # the old model, loaded at the same time
        seq = c.call("set_view", pose={"position": [0.0, 0.05, -2.0],
                                       "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]})["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq, 20, "a frame after them")
        assert not [e for e in c.status()["errors"] if e["source"] == "frame worker"]
        assert mecom_twin.emitting()["green"] == 5.0  # the light path kept its frames
    finally:
        r.stop()


def test_check_inference_passes_the_good_model_and_names_each_mismatch(tiny, tmp_path):
    from nhfd.models.export import load_model
    from nhfd.pipeline.worker import ModelUnfit, check_inference

    check_inference(load_model(tiny["model"]), WINDOW_HW, "tiny.onnx")  # a working model passes
    for kind, refusal in REFUSALS.items():
        path = bad_model(tiny["model"], tmp_path / f"{kind}.onnx", kind)
        with pytest.raises(ModelUnfit) as info:
            check_inference(load_model(path), WINDOW_HW, str(path))
        assert str(info.value).startswith(f"{path}: ") and refusal in str(info.value)
    # a frame size the fixed graph does take is not refused for its shape
    check_inference(load_model(tmp_path / "fixed.onnx"), (8, 8), "fixed.onnx")


def _bench_config(tmp_path: Path, **daemon: object) -> Path:
    """SMALL with `daemon`'s sections (e.g. frames={"size_px": ...}) as a TOML file."""
    from nhfd.config import toml_text

    from .test_frames import SMALL

    path = tmp_path / "nhfd.toml"
    path.write_text(toml_text({**SMALL, "daemon": daemon} if daemon else SMALL))
    return path


def test_bench_pipeline_with_a_bad_model_exits_2_with_the_refusal(tiny, tmp_path, capsys):
    from nhfd.cli.main import main

    path = bad_model(tiny["model"], tmp_path / "bad-channels.onnx", "channels")
    rc = main(["bench", "pipeline", "--model", str(path), "--scene", str(tiny["scene"]),
               "--config", str(_bench_config(tmp_path)), "--views", "1", "--warmup", "0",
               "--json", str(tmp_path / "out.json")])
    err = capsys.readouterr().err
    assert rc == 2
    assert f"{path}: input channels: expected 3, found 4" in err
    assert "Traceback" not in err
    assert not (tmp_path / "out.json").exists()


def test_bench_pipeline_refuses_a_frame_size_larger_than_the_panel(tiny, tmp_path, capsys):
    from nhfd.cli.main import main

    config = _bench_config(tmp_path, frames={"size_px": [4096, 2160]})
    config.write_text(config.read_text().replace("width_px = 192", "width_px = 1920")
                      .replace("height_px = 128", "height_px = 1080"))
    rc = main(["bench", "pipeline", "--model", str(tiny["model"]), "--config", str(config),
               "--json", str(tmp_path / "out.json")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert "daemon.frames.size_px" in err and "1920" in err and "1080" in err


def write_calibration(path: Path, *, stage_at_slm_mm: float = 5.0,
                      wavelengths_m: tuple[float, float, float] = (6.6e-7, 5.2e-7, 4.5e-7),
                      pitch_m: float = 8e-6) -> Path:
    """A calibration file with nominal curves whose focus mapping is stage_mm =
    stage_at_slm_mm + z (mm from the SLM), written atomically as a lab's fit would be."""
    from nhfd.calibration import Calibration

    table = tuple(float(v) for v in 2 * np.pi * np.arange(256) / 256)
    cal = Calibration(
        wavelengths_m=wavelengths_m, pitch_m=pitch_m, phase_sign=1,
        phase_tables_rad=(table,) * 3, phase_table_std_rad=(0.0,) * 3, stage_scale=1.0,
        stage_scale_std=0.0, stage_at_slm_mm=stage_at_slm_mm, stage_at_slm_std_mm=0.0,
        z_offset_m=(0.0, 0.0, 0.0), z_offset_std_m=(0.0, 0.0, 0.0), magnification=1.0,
        magnification_std=0.0, rotation_deg=0.0, rotation_std_deg=0.0, mirror_x=False,
        shift_px=(0.0, 0.0), intensity=(1.0, 1.0, 1.0), intensity_std=(0.0, 0.0, 0.0))
    return cal.save(path)


def _with_calibration(config: Any, path: Path) -> Any:
    from nhfd.config import Config, _overlay

    user = {"calibration": {"file": str(path)}}
    return Config.model_validate(_overlay(config.model_dump(), user))


def test_a_hot_swapped_calibration_for_another_bench_is_refused_and_the_old_one_kept(
        short_dir, mecom_twin):
    from nhfd.calibration import CalibrationStore
    from nhfd.daemon.protocol import INVALID_FILE, RpcError

    from .conftest import bench_config

    path = write_calibration(short_dir / "calibration.toml", stage_at_slm_mm=5.0)
    r = Running(_with_calibration(bench_config(short_dir, mecom_twin), path), short_dir)
    try:
        c = r.client()
        # z0 = 6 mm plus 1 mm from the SLM: the stage at 5 + 7 = 12 mm
        assert c.call("focus", z_mm=1.0)["stage_mm"] == pytest.approx(12.0)
        write_calibration(short_dir / "infrared.tmp", stage_at_slm_mm=2.0,
                          wavelengths_m=(1.064e-6, 5.2e-7, 4.5e-7)).replace(path)
        assert c.call("focus", z_mm=1.0)["stage_mm"] == pytest.approx(12.0)  # the old one
        refusal = (f"calibration file {path}: bench.wavelengths_m[0] = 1.064e-06 m, expected "
                   "6.6e-07 m (from optics.wavelengths_nm[0]) within 0.5%: fitted for another "
                   "bench; keeping " + str(path))
        status = c.status()
        assert status["calibration"]["loaded"] is True
        assert status["calibration"]["refused"].startswith(refusal)
        assert status["calibration"]["stage_at_slm_mm"] == 5.0
        c.status()  # asked again: still one error for that file version
        errors = [e["message"] for e in c.status()["errors"] if e["source"] == "calibration"]
        assert len(errors) == 1 and errors[0].startswith(refusal)

        (short_dir / "corrupt.tmp").write_bytes(b"\x00\xff garbage")
        (short_dir / "corrupt.tmp").replace(path)
        assert c.call("focus", z_mm=1.0)["stage_mm"] == pytest.approx(12.0)
        assert "corrupt" in c.status()["calibration"]["refused"]

        write_calibration(short_dir / "good.tmp", stage_at_slm_mm=3.0).replace(path)
        assert c.call("focus", z_mm=1.0)["stage_mm"] == pytest.approx(10.0)  # a good swap applies
        assert c.status()["calibration"]["refused"] is None

        # No accepted version to keep (a store that never loaded the file, as a fresh process
        # has): the file's code
        (short_dir / "corrupt.tmp").write_bytes(b"\x00\xff garbage")
        (short_dir / "corrupt.tmp").replace(path)
        r.daemon.rpc.calibration = CalibrationStore.of(r.daemon.config)
        with pytest.raises(RpcError) as info:
            c.call("focus", z_mm=1.0)
        assert info.value.code == INVALID_FILE.code
        assert info.value.message.startswith(f"calibration file {path}: corrupt")
        assert info.value.data == {"field": "calibration.file"}
    finally:
        r.stop()


def test_the_daemon_refuses_to_start_on_a_calibration_for_another_pitch(short_dir, mecom_twin):
    from nhfd.calibration import CalibrationFileError
    from nhfd.daemon.service import Daemon

    from .conftest import bench_config

    path = write_calibration(short_dir / "other-panel.toml", pitch_m=3.74e-6)
    config = _with_calibration(bench_config(short_dir, mecom_twin), path)
    with pytest.raises(CalibrationFileError) as info:
        Daemon(config, base_dir=short_dir, env={}, handle_signals=False).start()
    assert str(info.value) == (f"calibration file {path}: bench.pitch_m = 3.74e-06 m, expected "
                               "8e-06 m (from slm.pitch_um) within 0.1%: fitted for another bench")
    assert mecom_twin.emitting() == {"red": 0.0, "green": 0.0, "blue": 0.0}


def test_a_scene_of_random_data_is_refused_and_dropped_counts_reach_status(
        short_dir, mecom_twin, tiny):
    from nhfd.scene.io import load_scene, save_ply
    from tests.scene.test_io import random_data_ply

    from .test_frames import daemon_config, wait_for_frames

    scenes = short_dir / "scenes"
    config = daemon_config(short_dir, mecom_twin, tiny, paths={"scene": str(scenes / "cloud.ply")},
                           frames={"model": str(short_dir / "models" / "tiny.onnx")})
    r = Running(config, short_dir)
    try:
        c = r.client()
        before = wait_for_frames(c)["scene"]
        assert (before["gaussians"], before["declared"], before["dropped"]) == (300, 300, 0)
        path = random_data_ply(scenes / "random.ply")
        job = c.call("load_scene", path=str(path))["job"]
        wait_until(lambda: c.call("job", id=job)["state"] in ("failed", "done"), 20, "the load")
        state = c.call("job", id=job)
        assert state["state"] == "failed", state
        assert state["error"].startswith(f"SceneFileError: {path}: not a plausible scene: ")
        assert c.status()["scene"] == before  # the old scene keeps rendering

        g = load_scene(tiny["scene"])  # the cloud with 3 splats made non-finite
        means = g.means.copy()
        means[[5, 50, 150]] = np.nan
        save_ply(scenes / "holes.ply", type(g)(means, g.quats, g.scales, g.opacities, g.sh))
        job = c.call("load_scene", path=str(scenes / "holes.ply"))["job"]
        wait_until(lambda: c.call("job", id=job)["state"] in ("failed", "done"), 20, "the load")
        state = c.call("job", id=job)
        assert state["state"] == "done", state
        counts = {"gaussians": 297, "declared": 300, "dropped": 3}
        assert {k: state["result"][k] for k in counts} == counts
        assert {k: c.status()["scene"][k] for k in counts} == counts
        assert "dropped 3 of 300 Gaussians" in c.status()["scene"]["dropped_reason"]
    finally:
        r.stop()


def test_the_frame_worker_keeps_the_daemons_calibration_when_the_file_is_swapped_first(
        short_dir, mecom_twin, tiny):
    """The worker reads the calibration at its first frame: a file refused by then keeps the
    calibration the daemon accepted at start there too, and frames are shown."""
    from .test_frames import daemon_config, wait_for_frames

    path = write_calibration(short_dir / "calibration.toml")
    config = _with_calibration(daemon_config(
        short_dir, mecom_twin, tiny, paths={"scene": str(short_dir / "scenes" / "cloud.ply")},
        frames={"model": str(short_dir / "models" / "tiny.onnx")}), path)
    r = Running(config, short_dir)
    try:
        c = r.client()
        wait_for_frames(c)  # worker, model and scene ready; no view yet, so no frame computed
        write_calibration(short_dir / "other.tmp", pitch_m=3.74e-6).replace(path)
        seq = c.call("set_view", pose={"position": [0.0, 0.05, -2.0],
                                       "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]})["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq
                   or any(e["source"] == "frame worker" for e in c.status()["errors"]),
                   30, "the frame or its error")
        status = c.status()
        assert [e["message"] for e in status["errors"] if e["source"] == "frame worker"] == []
        assert status["view"]["applied_seq"] == seq
        assert "bench.pitch_m = 3.74e-06 m" in status["calibration"]["refused"]
    finally:
        r.stop()
