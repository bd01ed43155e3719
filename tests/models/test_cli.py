"""`nhfd train|eval|export` from the command line: a round trip, and errors naming bad values."""

from __future__ import annotations

import json

import pytest

from nhfd.cli.main import main


def test_train_export_eval_round_trip(tiny_data, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["train", "--data", str(tiny_data), "--out", str(run), "--profile", "fast",
            "--width", "8", "--depth", "1", "--single-conv-levels", "2", "--steps", "2",
            "--crop", "48x48", "--no-progress",
            "--val-views", "1", "--threads", "1"]  # fmt: skip
    assert main(args) == 0
    assert "step 2" in capsys.readouterr().out
    info = json.loads((run / "run.json").read_text())
    assert info["net"] == {"width": 8, "depth": 1, "unshuffle": 2, "inputs": "rgbd",
                           "growth": 1.0, "skip": "add",
                           "single_conv_levels": 2, "deep_width": 0}  # fast's, but overridden
    assert "box-window SSIM" in info["loss"]  # the log says which perceptual term ran
    onnx_path = tmp_path / "m.onnx"
    int8_path = tmp_path / "m-int8.onnx"
    assert main(["export", str(run), "-o", str(onnx_path), "--int8", str(int8_path),
                 "--data", str(tiny_data)]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "max abs difference" in out and "recorded in the file" in out
    _int8_is_quantised_and_close(onnx_path, int8_path)
    # the held-out loss inside the int8 file is what `nhfd eval` measures of the two models
    from nhfd.dataset.build import sha256_file
    from nhfd.models.evaluate import evaluate
    from nhfd.models.export import OnnxModel
    from nhfd.models.quantise import HELDOUT_KEY

    record = OnnxModel(int8_path).metadata[HELDOUT_KEY]
    psnr = {p: evaluate(p, tiny_data, log=lambda _l: None)["summary"]["all"]["model_psnr_db"]
            for p in (onnx_path, int8_path)}
    assert record["float_sha256"] == sha256_file(onnx_path)
    assert record["loss_vs_float_db"] == pytest.approx(psnr[onnx_path] - psnr[int8_path],
                                                       abs=1e-9)
    assert main(["eval", str(onnx_path), "--data", str(tiny_data), "--out",
                 str(tmp_path / "ev")]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "model dB" in out and "2D dB" in out and "black dB" in out
    result = json.loads((tmp_path / "ev" / "eval.json").read_text())
    assert {"interp", "extrap", "all"} <= set(result["summary"])
    assert result["views"][0]["focus"] and (tmp_path / "ev" / "eval.png").exists()


def _int8_is_quantised_and_close(float_path, int8_path):
    import numpy as np
    import onnx

    from nhfd.models.export import OnnxModel
    from nhfd.models.quantise import output_nodes

    graph = onnx.load(str(int8_path)).graph
    ops = [n.op_type for n in graph.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    floats = {i.name for i in graph.initializer if i.data_type == onnx.TensorProto.FLOAT}
    for name in output_nodes(onnx.load(str(int8_path)))[0]:  # the output layers keep float weights
        node = next(n for n in graph.node if n.name == name)
        assert node.input[1] in floats
    f, q = OnnxModel(float_path), OnnxModel(int8_path)
    # the same metadata, except the sizes: the int8 graph's are checked on itself (tiles)
    q_meta, f_meta = dict(q.metadata), dict(f.metadata)
    q_sizes, f_sizes = q_meta.pop("checked_sizes"), f_meta.pop("checked_sizes")
    q_meta.pop("int8_heldout")  # its held-out loss, checked by the caller
    assert q_meta == f_meta and q.inputs == f.inputs == "rgbd"
    assert [e["hw"] for e in q_sizes] == [e["hw"] for e in f_sizes]
    assert all(e["ok"] and "tiles" in e["against"] for e in q_sizes)
    x = np.random.default_rng(0).random((4, 48, 48), dtype=np.float32)
    for a, b in zip(f(x), q(x), strict=True):  # amplitude, phase
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.9


@pytest.mark.parametrize("argv,message", [
    (["train", "--data", "{data}", "--out", "{tmp}/r", "--profile", "huge"],
     "--profile 'huge': not one of the configured profiles accurate, balanced, fast, fastest"),
    (["train", "--data", "{data}", "--out", "{tmp}/r", "--crop", "512"],
     "--crop '512' is not of the form WxH"),
    (["train", "--data", "{data}", "--out", "{tmp}/r", "--steps", "0"],
     "--steps 0: must be positive"),
    (["train", "--data", "{data}", "--out", "{tmp}/r", "--unshuffle", "3"],
     "--unshuffle 3: must be 1, 2, 4 or 8"),
    (["train", "--data", "{data}", "--out", "{tmp}/r", "--growth", "0.5"],
     "--growth 0.5: must be in [1, 2]"),
    (["train", "--data", "{tmp}/nowhere", "--out", "{tmp}/r"], "--data {tmp}/nowhere: no such"),
    (["export", "{tmp}", "-o", "{tmp}/m.onnx", "--opset", "17"], "--opset 17: must be 18"),
    (["export", "{tmp}", "-o", "{tmp}/m.onnx"], "not a training run"),
    (["export", "{tmp}", "-o", "{tmp}/m.onnx", "--int8", "{tmp}/q.onnx"], "--int8 needs --data"),
    (["export", "{tmp}", "-o", "{tmp}/m.onnx", "--int8", "{tmp}/q.onnx", "--data", "{data}",
      "--int8-eval-views", "-1"], "--int8-eval-views -1: must be 0 (not measured) or a positive"),
    (["train", "--data", "{data}", "--out", "{tmp}/r", "--device", "tpu"],
     "device = 'tpu': must be one of auto, cpu, cuda, cuda:N (N: a CUDA device index)"),
    (["eval", "{tmp}/none.onnx", "--data", "{data}"], "no such run folder or .onnx"),
    (["eval", "{tmp}", "--data", "{data}", "--splits", "test"], "--splits 'test'"),
])  # fmt: skip
def test_bad_values_are_named(argv, message, tiny_data, tmp_path, capsys):
    fill = {"data": str(tiny_data), "tmp": str(tmp_path)}
    argv = [a.format(**fill) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message.format(**fill) in err, err
    assert len(err.strip().splitlines()) == 1


def test_the_int8_keep_rule_is_finite_and_within_the_limit():
    """One rule keeps (`nhfd model build`), reports (`nhfd export --int8`) and serves (the frame
    worker's `choose_variant`) a reduced-precision model."""
    from nhfd.models.quantise import INT8_MAX_LOSS_DB, int8_within_loss

    assert INT8_MAX_LOSS_DB == 0.5
    kept = [0.0, -0.3, 0.5, 0.49]
    dropped = [0.5001, 3.0, float("nan"), float("inf"), float("-inf")]
    assert [int8_within_loss(x) for x in kept + dropped] == [True] * 4 + [False] * 5
