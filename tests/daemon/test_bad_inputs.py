"""Bad input never replaces good state: a model that cannot take the daemon's frames, (and, in
the other tests of this file) a calibration for another bench and a scene of random data are
refused by name, and what was running keeps running."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

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
                           scene=str(short_dir / "scenes" / "cloud.ply"),
                           model=str(short_dir / "models" / "tiny.onnx"))
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

    from nhfd.daemon.worker import ModelUnfit, check_inference

    check_inference(load_model(tiny["model"]), WINDOW_HW, "tiny.onnx")  # a working model passes
    for kind, refusal in REFUSALS.items():
        path = bad_model(tiny["model"], tmp_path / f"{kind}.onnx", kind)
        with pytest.raises(ModelUnfit) as info:
            check_inference(load_model(path), WINDOW_HW, str(path))
        assert str(info.value).startswith(f"{path}: ") and refusal in str(info.value)
    # a frame size the fixed graph does take is not refused for its shape
    check_inference(load_model(tmp_path / "fixed.onnx"), (8, 8), "fixed.onnx")


def _bench_config(tmp_path: Path, **daemon: object) -> Path:
    import json

    from .test_frames import SMALL

    lines = [f"[{section}]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in values.items())
             for section, values in ({**SMALL, "daemon": daemon} if daemon else SMALL).items()]
    path = tmp_path / "nhfd.toml"
    path.write_text("\n".join(lines))
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
    from nhfd.bench.pipeline import check_frame_size
    from nhfd.cli.main import main

    config = _bench_config(tmp_path, frame_size_px=[4096, 2160])
    config.write_text(config.read_text().replace("width_px = 192", "width_px = 1920")
                      .replace("height_px = 128", "height_px = 1080"))
    rc = main(["bench", "pipeline", "--model", str(tiny["model"]), "--config", str(config),
               "--json", str(tmp_path / "out.json")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert "daemon.frame_size_px" in err and "1920" in err and "1080" in err
    # the bench's own rule (config validation may refuse the file first)
    def panel(w: int, h: int) -> SimpleNamespace:
        return SimpleNamespace(daemon=SimpleNamespace(frame_size_px=[w, h]),
                               slm=SimpleNamespace(width_px=1920, height_px=1080))

    with pytest.raises(ValueError, match=r"daemon.frame_size_px = \[4096, 2160\]: does not fit "
                                         r"the 1920 x 1080 panel"):
        check_frame_size(panel(4096, 2160))
    check_frame_size(panel(1920, 1080))
