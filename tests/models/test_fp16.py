"""The fp16 export (`nhfd.models.half`, `nhfd export --fp16`): float32 at the graph's edges,
float16 weights, the softplus kept in float32, the metadata carried over, and the same held-out
quality as the float model."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest

from nhfd.cli.main import main
from nhfd.models.data import HoloData
from nhfd.models.export import OnnxModel, export_onnx, load_model
from nhfd.models.half import (
    CHECK_KEY,
    FP16_MAX,
    compare_fp16,
    convert_fp16,
    emulate_fp16,
    evaluate_emulated,
    half_initializer_bytes,
)
from nhfd.models.metadata import (
    NotAModel,
    check_metadata,
    checked_size_entry,
    expected_from_manifest,
)

FLOAT, HALF = onnx.TensorProto.FLOAT, onnx.TensorProto.FLOAT16
# Tolerance of the fp16 model's outputs against the float model's on one seeded random input,
# relative to the float output's largest magnitude: float16 rounds to 2^-11 (4.9e-4) relative,
# and about 20 layers of sums compound it (measured: 4e-4 amplitude, 6e-4 phase on the
# shipped model).
REL_TOL = 5e-3


@pytest.fixture(scope="module")
def pair(tiny_run, tmp_path_factory):
    """The tiny run's float export and its fp16 conversion (through the CLI)."""
    d = tmp_path_factory.mktemp("fp16")
    f = export_onnx(tiny_run, d / "m.onnx", check=False).path
    assert main(["export", str(f), "--fp16", str(d / "m-fp16.onnx")]) == 0
    return f, d / "m-fp16.onnx"


@pytest.fixture(scope="module")
def shipped_pair(tmp_path_factory):
    from nhfd.demos.serve import DEFAULT_MODEL

    if not DEFAULT_MODEL.exists():
        pytest.skip(f"no shipped model at {DEFAULT_MODEL}")
    return DEFAULT_MODEL, convert_fp16(DEFAULT_MODEL, tmp_path_factory.mktemp("sh") / "h.onnx")


def test_edges_are_float32_and_the_weights_float16(pair):
    f, h = pair
    g = onnx.load(str(h)).graph
    assert [v.type.tensor_type.elem_type for v in (*g.input, *g.output)] == [FLOAT] * 3
    before, after = half_initializer_bytes(f), half_initializer_bytes(h)
    # every float32 weight is now float16, except the few scalars the float32 softplus reads
    assert after.get("float32", 0) <= 16
    assert after["float16"] == pytest.approx(before["float32"] / 2, abs=16)
    # the file shrinks by half its weights (the metadata and the graph stay as they were)
    assert f.stat().st_size - h.stat().st_size >= 0.45 * before["float32"]


def _scaled_amplitude_head(src, dst, factor: float):
    """`src` with the amplitude head's weights times `factor`."""
    from nhfd.models.quantise import output_nodes

    model = onnx.load(str(src))
    heads, _tail = output_nodes(model)
    # the head that feeds the softplus (the phase head writes `phase` itself)
    amp_head = next(n for n in model.graph.node if n.name in heads and "phase" not in n.output)
    for t in model.graph.initializer:
        if t.name == amp_head.input[1]:
            w = onnx.numpy_helper.to_array(t) * factor
            t.CopyFrom(onnx.numpy_helper.from_array(w.astype(np.float32), t.name))
    onnx.save(model, str(dst))
    return dst


def test_a_model_beyond_float16s_range_is_refused(pair, tmp_path):
    huge = _scaled_amplitude_head(pair[0], tmp_path / "huge.onnx", 1e6)
    assert np.abs(OnnxModel(huge).run_raw(np.ones((1, 3, 64, 64), np.float32))[0]).max() > 7e4
    with pytest.raises(ValueError, match=r"gives inf or NaN .* not written to"):
        convert_fp16(huge, tmp_path / "huge-fp16.onnx")
    assert not (tmp_path / "huge-fp16.onnx").exists()
    assert not list(tmp_path.glob("*.tmp"))


def test_the_softplus_computes_in_float32(pair, tmp_path):
    """Amplitudes whose softplus input is far above float16's exp limit (exp(11.1) = 65504)
    come out finite and right when every float16 operator computes in float16 (emulated: the CPU
    provider computes them in float32); a float16 `1 + exp(a)` would make them inf."""
    # the amplitude head scaled so its outputs reach tens (still well inside float16's range)
    loud = _scaled_amplitude_head(pair[0], tmp_path / "loud.onnx", 200.0)
    h = convert_fp16(loud, tmp_path / "loud-fp16.onnx", check=False)
    x = np.random.default_rng(5).random((1, 3, 64, 64), dtype=np.float32)
    fa, _ = OnnxModel(loud).run_raw(x)
    ha, _ = emulate_fp16(OnnxModel(h)).run_raw(x)
    assert fa.max() > 20  # beyond float16's exp, inside its range
    assert np.isfinite(ha).all()
    assert np.abs(ha - fa).max() <= REL_TOL * np.abs(fa).max()


def test_outputs_match_the_float_model_and_stay_finite_at_extremes(pair, shipped_pair):
    for f, h in (pair, shipped_pair):
        d = compare_fp16(f, h, seed=7, emulate=True)
        assert d["finite"], (f, d)
        assert d["amplitude_max_abs_diff"] <= REL_TOL * d["amplitude_max"], (f, d)
        assert d["phase_max_abs_diff"] <= REL_TOL * max(np.pi, d["amplitude_max"]), (f, d)
    # the shipped model sees depth: all black at the near end, all white at the far end, at the
    # trained size, as onnxruntime serves it
    model = OnnxModel(shipped_pair[1])
    assert model.inputs == "rgbd"
    for rgb, depth in ((0.0, -1.0), (1.0, 1.0)):
        x = np.full((4, 288, 512), rgb, np.float32)
        x[3] = depth
        amp, phase = model(x)
        assert np.isfinite(amp).all() and np.isfinite(phase).all()
        assert np.abs(amp).max() < FP16_MAX


def test_metadata_survives_and_the_model_loads(pair, shipped_pair, tiny_data):
    from nhfd.config import Config

    f, h = pair
    mf, mh = OnnxModel(f).metadata, OnnxModel(h).metadata
    check = mh.pop(CHECK_KEY)  # the conversion's own comparison, recorded in the file
    assert mh == {**mf, "precision": "fp16"}
    assert check == compare_fp16(f, h, emulate=True)
    manifest = json.loads((tiny_data / "manifest.json").read_text())
    check_metadata(mh, expected_from_manifest(manifest), str(h))
    # the shipped model's fp16 copy is accepted for the default optics, as the daemon loads it
    model = load_model(shipped_pair[1], Config())
    assert model.metadata["precision"] == "fp16" and model.multiple == 16


def test_heldout_psnr_within_0_2_db(pair, tiny_data, tmp_path):
    """As `nhfd eval` serves it (onnxruntime, CPU) and computed in float16 throughout."""
    from nhfd.models.evaluate import evaluate

    quiet = {"log": lambda _m: None}
    f, h = (evaluate(p, tiny_data, out_dir=tmp_path / p.stem, **quiet) for p in pair)
    e = evaluate_emulated(pair[1], tiny_data, out_dir=tmp_path / "emulated", **quiet)
    psnr = [r["summary"]["all"]["model_psnr_db"] for r in (f, h, e)]
    assert abs(psnr[1] - psnr[0]) <= 0.2 and abs(psnr[2] - psnr[0]) <= 0.2, psnr
    assert h["model"]["source"] == str(pair[1])


@pytest.mark.parametrize("argv,message", [
    (["export", "{tmp}/none.onnx", "--fp16", "{tmp}/h.onnx"], "{tmp}/none.onnx: no such .onnx"),
    (["export", "{f}", "--fp16", "{tmp}/h.txt"], "--fp16 {tmp}/h.txt: the fp16 model's file name"),
    (["export", "{f}", "--fp16", "{f}"], "must not overwrite its source"),
    (["export", "{h}", "--fp16", "{tmp}/hh.onnx"], "{h}: precision 'fp16', not fp32"),
    (["export", "{f}"], "an .onnx source needs --fp16 OUT_FP16"),
    (["export", "{f}", "-o", "{tmp}/x.onnx", "--fp16", "{tmp}/h.onnx"], "is already exported"),
    (["export", "{tmp}/junk.onnx", "--fp16", "{tmp}/h.onnx"], "not a readable ONNX model"),
    (["export", "{tmp}", "--fp16", "{tmp}/h.onnx"], "exporting a run folder needs -o OUT.onnx"),
])  # fmt: skip
def test_bad_paths_are_named(argv, message, pair, tmp_path, capsys):
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    fill = {"tmp": str(tmp_path), "f": str(pair[0]), "h": str(pair[1])}
    assert main([a.format(**fill) for a in argv]) == 2
    err = capsys.readouterr().err
    assert message.format(**fill) in err, err
    assert not (tmp_path / "h.onnx").exists()


def test_only_a_float32_source_is_converted(pair, tiny_data, tmp_path, capsys):
    """`nhfd export X.onnx --fp16/--int8` refuses an fp16 or an int8 source before writing
    anything: quantising an fp16 file, or converting an int8 one again (its metadata reads fp32,
    carried over from its float model), would make a model nothing checked."""
    import shutil

    from nhfd.models.quantise import HELDOUT_KEY, quantise_int8, record_heldout_loss

    f, h = pair
    # an int8 file as `nhfd export --int8 --int8-eval-views 0` leaves it: known by its operators
    q = quantise_int8(f, tmp_path / "q.onnx", HoloData(tiny_data), OnnxModel(f).multiple,
                      OnnxModel(f).inputs, n_calib=1)  # fmt: skip
    assert HELDOUT_KEY not in OnnxModel(q).metadata
    assert OnnxModel(q).metadata.get("precision", "fp32") == "fp32"
    # one known only by its held-out record (a float graph under an int8 file's metadata)
    r = shutil.copyfile(f, tmp_path / "r.onnx")
    record_heldout_loss(r, f, float_psnr_db=20.0, int8_psnr_db=19.9, views=2)
    out = {"--fp16": tmp_path / "out-fp16.onnx", "--int8": tmp_path / "out-int8.onnx"}
    for source, why in ((h, "precision 'fp16', not fp32"),
                        (q, "an int8 model (DequantizeLinear, QuantizeLinear)"),
                        (r, f"an int8 model (metadata {HELDOUT_KEY})")):  # fmt: skip
        for flag, dst in out.items():
            argv = ["export", str(source), flag, str(dst), "--data", str(tiny_data)]
            assert main(argv) == 2
            err = capsys.readouterr().err
            assert f"{source}: {why}; give the float32 model to convert" in err, err
            assert not dst.exists()


def test_a_foreign_onnx_file_is_refused(tmp_path):
    from onnx import helper

    g = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "g",
                          [helper.make_tensor_value_info("x", FLOAT, [1])],
                          [helper.make_tensor_value_info("y", FLOAT, [1])])  # fmt: skip
    onnx.save(helper.make_model(g), str(tmp_path / "relu.onnx"))
    with pytest.raises(NotAModel, match="without nhfd metadata"):
        convert_fp16(tmp_path / "relu.onnx", tmp_path / "h.onnx")


def test_the_tradeoff_table_says_when_the_gpu_column_is_not_measured(capsys):
    import onnxruntime as ort
    import torch

    from nhfd.benchmarks.tradeoff import gpu_unavailable, print_table

    cuda = torch.cuda.is_available() and "CUDAExecutionProvider" in ort.get_available_providers()
    assert (gpu_unavailable() is None) == cuda
    row = {"name": "w8", "parameters": 10, "onnxruntime_ms": 3.0, "torch_ms": 4.0,
           "torch_over_onnxruntime": 4 / 3, "psnr_db": 20.0, "ssim": 0.5, "psnr_2d_db": 15.0,
           "focus_bins_passed": "1/1", "pareto": True}  # fmt: skip
    print_table([{**row, "gpu_fp16_ms": None}, {**row, "name": "w16", "gpu_fp16_ms": 0.731}])
    lines = capsys.readouterr().out.splitlines()
    assert "gpu fp16 ms" in lines[0]
    assert "not measured" in lines[1] and "0.73" in lines[2] and "not measured" not in lines[2]


def test_the_fp16_model_on_cuda_matches_the_float_model(pair):
    """On a GPU the fp16 file runs where `daemon.frames.inference = "auto"` runs it: onnxruntime's
    CUDA provider (float16 kernels) where the installed onnxruntime has one, else torch (float32
    arithmetic on the float16 weights, `nhfd.models.torch_model`). Either way its outputs are
    the float model's on the CPU."""
    import onnxruntime as ort
    import torch

    from nhfd.models.torch_model import TorchModel

    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    f, h = pair
    x = np.random.default_rng(3).random((1, 3, 64, 96), dtype=np.float32)
    fa, fp = OnnxModel(f).run_raw(x)
    if "CUDAExecutionProvider" in ort.get_available_providers():
        ga, gp = OnnxModel(h, providers=("CUDAExecutionProvider", "CPUExecutionProvider")
                           ).run_raw(x)  # fmt: skip
    else:
        ga, gp = TorchModel(h, device="cuda:0").run_raw(x)
    assert np.abs(ga - fa).max() <= REL_TOL * np.abs(fa).max()
    assert np.abs(gp - fp).max() <= REL_TOL * max(np.pi, np.abs(fa).max())


def test_export_of_a_run_writes_both_models(tiny_run, tmp_path, capsys):
    f, h = tmp_path / "m.onnx", tmp_path / "m-fp16.onnx"
    assert main(["export", str(tiny_run), "-o", str(f), "--fp16", str(h), "--no-check"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["fp16_path"] == str(h) and report["fp16_vs_float"]["finite"] is True
    assert OnnxModel(f).metadata.get("precision", "fp32") == "fp32"
    assert OnnxModel(h).metadata["precision"] == "fp16"


def test_the_float_models_size_checks_are_checked_again_on_the_fp16_graph(shipped_pair,
                                                                          tmp_path):
    """The fp16 file carries none of the float model's checks (as an int8 file): each size is
    checked on its own graph (the full run against tiles)."""
    import shutil

    from nhfd.models.sizes import record_checked_sizes

    f = shutil.copyfile(shipped_pair[0], tmp_path / "f.onnx")
    record_checked_sizes(f, [checked_size_entry((576, 1024), 0.0, "the torch network of its run")])
    h = convert_fp16(f, tmp_path / "h.onnx")
    entries = {tuple(e["hw"]): e for e in OnnxModel(h).metadata["checked_sizes"]}
    assert set(entries) == {tuple(e["hw"]) for e in OnnxModel(f).metadata["checked_sizes"]}
    assert entries[(576, 1024)]["against"].startswith("the same graph on overlapping")
    assert all(e["ok"] for e in entries.values())
