"""`nhfd bench tradeoff`'s pieces: which layer int8 keeps in float, reuse of finished runs, and
the Pareto front."""

from __future__ import annotations

import json
from pathlib import Path

import onnx
import pytest
import torch

from nhfd.benchmarks.tradeoff import (
    fastest_within,
    finished_run,
    interleaved_ms,
    pareto,
    run,
    variants,
)
from nhfd.models.export import export_onnx
from nhfd.models.quantise import output_nodes
from nhfd.models.train import CHECKPOINT, train
from tests.models.conftest import tiny_options


@pytest.fixture(scope="module")
def int8_pair(tiny_data, tiny_run, tmp_path_factory) -> tuple[Path, Path]:
    """The tiny run's float export and its int8 sibling (quantised once for this module: each
    took 15 s)."""
    from nhfd.models.data import HoloData
    from nhfd.models.net import NetSpec
    from nhfd.models.quantise import quantise_int8

    out = tmp_path_factory.mktemp("int8")
    src = export_onnx(tiny_run, out / "m.onnx").path
    spec = NetSpec(**json.loads((tiny_run / "run.json").read_text())["net"])
    dst = quantise_int8(src, out / "m-int8.onnx", HoloData(tiny_data), spec.multiple,
                        spec.inputs)  # fmt: skip
    return src, dst


def test_int8_keeps_the_layers_that_write_the_outputs_in_float(int8_pair):
    model = onnx.load(str(int8_pair[0]))
    heads, tail = output_nodes(model)
    by_name = {n.name: n for n in model.graph.node}
    assert len(heads) == 2 and {by_name[h].op_type for h in heads} == {"ConvTranspose"}
    # they are the last convolutions: nothing but elementwise ops between them and the outputs
    convs = [n.name for n in model.graph.node if n.op_type in ("Conv", "ConvTranspose")]
    assert set(convs[-2:]) == set(heads)
    assert {by_name[t].op_type for t in tail} >= {"Exp", "Log", "Max"}  # softplus's passes


def test_int8_leaves_the_head_and_the_softplus_in_float(int8_pair):
    q = onnx.load(str(int8_pair[1]))
    producer = {out: n for n in q.graph.node for out in n.output}
    # every path from the outputs back to the head: float nodes only, no (de)quantisation
    todo, seen = [o.name for o in q.graph.output], set()
    while todo:
        node = producer.get(todo.pop())
        if node is None or node.name in seen or node.op_type in ("Conv", "ConvTranspose"):
            continue
        seen.add(node.name)
        assert node.op_type not in ("QuantizeLinear", "DequantizeLinear"), node.name
        todo.extend(node.input)
    assert len(seen) >= 5  # softplus's passes were walked
    assert any(n.op_type == "QuantizeLinear" for n in q.graph.node)  # the trunk is int8


def test_a_finished_run_is_reused_and_another_network_or_recipe_is_refused(tiny_data, tmp_path):
    run = tmp_path / "run"
    opts = tiny_options(steps=3)
    assert finished_run(run, opts, "k") is None
    train(tiny_data, run, tiny_options(steps=2), log=lambda _m: None)
    assert finished_run(run, opts, "k") is None  # short of the budget: train on
    train(tiny_data, run, opts, log=lambda _m: None)
    key = torch.load(run / CHECKPOINT, weights_only=False)["manifest_key"]
    step, ms, note = finished_run(run, opts, key)
    assert step == 3 and ms > 0 and note == ""
    _, _, note = finished_run(run, opts, "another-build")
    assert "another build of the dataset" in note and key[:12] in note
    with pytest.raises(ValueError, match=r"trained otherwise than this variant \(width: 8 -> 4\)"):
        finished_run(run, tiny_options(steps=3, width=4), key)
    # another recipe is another variant too: a run at another learning rate is not reused
    with pytest.raises(ValueError, match=r"learning_rate: 0\.001 -> 0\.002"):
        finished_run(run, tiny_options(steps=3, learning_rate=0.002), key)
    # the profile is only a name: the same network and recipe under another default profile
    # (a grid variant carries the default's name) is the same variant
    assert finished_run(run, tiny_options(steps=3, profile="accurate"), key)[0] == 3
    assert json.loads((run / "run.json").read_text())["options"]["device"] == "cpu"


def test_the_fp16_model_is_converted_again_only_after_a_new_export(tmp_path, monkeypatch):
    """The conversion (and its slow emulated check) runs when the fp16 file is missing or the
    float model was just exported again, not on a call that only measures latency."""
    import nhfd.benchmarks.tradeoff as tradeoff

    made = []

    def convert(src, dst):
        made.append((src, dst))
        dst.write_bytes(b"fp16 of " + src.read_bytes())
        return dst

    monkeypatch.setattr(tradeoff, "convert_fp16", convert)
    f = tmp_path / "w8.onnx"
    f.write_bytes(b"float")
    half = tmp_path / "w8-fp16.onnx"
    assert tradeoff.fp16_model(f, exported_now=False) == half and made == [(f, half)]
    assert tradeoff.fp16_model(f, exported_now=False) == half and len(made) == 1  # kept
    f.write_bytes(b"float, exported again")
    assert tradeoff.fp16_model(f, exported_now=True) == half and len(made) == 2
    assert half.read_bytes() == b"fp16 of float, exported again"


def test_pareto_front_keeps_only_undominated_points():
    points = [(10.0, 20.0), (20.0, 25.0), (15.0, 19.0), (30.0, 25.0), (5.0, 18.0)]
    assert pareto(points) == [4, 0, 1]  # in order of latency


def test_the_fastest_variant_within_the_gap_of_the_best():
    rows = [{"name": n, "onnxruntime_ms": ms, "psnr_db": db}
            for n, ms, db in [("a", 300, 28.6), ("b", 88, 26.9), ("c", 40, 26.5), ("d", 35, 23.5)]]
    best, near = fastest_within(rows, 2.0)
    assert best["name"] == "a" and near["name"] == "b"  # c is 2.1 dB short of a: not within
    assert fastest_within(rows, 1.0)[1]["name"] == "a"


def test_models_are_timed_taking_turns_so_a_busy_spell_hits_all_alike():
    import time

    calls = []
    ms = interleaved_ms({"slow": lambda: (calls.append("slow"), time.sleep(0.02)),
                         "quick": lambda: calls.append("quick")}, 3)  # fmt: skip
    assert calls == ["slow", "quick"] * 4  # a warm-up, then three rounds
    assert ms["slow"] >= 20 > ms["quick"]


def test_the_pause_before_each_timed_call_is_not_counted():
    import time

    ends, starts = [], []
    ms = interleaved_ms({"a": lambda: (starts.append(time.perf_counter()), time.sleep(0.01),
                                       ends.append(time.perf_counter())),
                         "b": lambda: None}, 3, settle_s=0.05)  # fmt: skip
    assert 10 <= ms["a"] < 40  # a 10 ms call; the 50 ms pause before it is not in the figure
    # every timed call of "a" began at least the pause after the previous "a" ended
    assert all(s - e >= 0.05 for e, s in zip(ends[:-1], starts[1:], strict=True))


def test_the_grid_adds_variants_named_by_shape_and_growth():
    from nhfd.config import Config

    todo = variants(Config().model, "balanced", [8, 16], [], [], [1, 2], ["concat"])
    names = [t[0] for t in todo]
    # balanced (16/3/2, doubling) is not repeated by the grid; constant width gets "-g1"
    assert names == ["balanced", "w8-d3-u2-g1", "w8-d3-u2", "w16-d3-u2-g1"]
    assert todo[1][2:] == (8, 3, 2, 1.0, "concat")


def test_summed_skips_are_a_grid_axis_named_add():
    from nhfd.config import Config

    todo = variants(Config().model, "none", [16], [], [], [1], ["concat", "add"])
    assert [t[0] for t in todo] == ["w16-d3-u2-g1", "w16-d3-u2-g1-add"]
    assert todo[1][2:] == (16, 3, 2, 1.0, "add")


def test_profiles_that_differ_in_single_conv_levels_or_deep_width_are_distinct_variants():
    from nhfd.config import Config, ModelProfile

    config = Config()
    fast = config.model.profiles["fast"]
    config.model.profiles["lean"] = ModelProfile(**{**fast.model_dump(), "single_conv_levels": 2})
    config.model.profiles["thin"] = ModelProfile(**{**fast.model_dump(), "deep_width": 8})
    todo = variants(config.model, "fast,lean,thin", [16], [], [], [1], ["add"])
    # the grid point has fast's shape (the grid keeps the default profile's blocks), so it is
    # fast and is not repeated; lean and thin have the same grid key but other networks
    assert [t[0] for t in todo] == ["fast", "lean", "thin"]


def test_a_run_saved_before_single_conv_levels_and_deep_width_read_as_the_classic_u_net():
    from dataclasses import asdict, replace

    from nhfd.models.train import changed_options

    opts = tiny_options(steps=3)
    saved = {k: v for k, v in asdict(opts).items()
             if k not in ("single_conv_levels", "deep_width")}  # fmt: skip
    assert opts.single_conv_levels == 0 and opts.deep_width == 0
    assert changed_options({"options": saved}, opts) == ""
    assert changed_options({"options": saved}, replace(opts, single_conv_levels=1)) == (
        "single_conv_levels: 0 -> 1")
    assert changed_options({"options": saved}, replace(opts, deep_width=4)) == "deep_width: 0 -> 4"


@pytest.mark.parametrize("flag,value,message", [
    ("growths", "0.5", "--growths '0.5': each must be in [1, 2]"),
    ("growths", "x", "--growths 'x': give comma-separated numbers"),
    ("widths", "0", "--widths '0': values must be positive"),
    ("skips", "add,sum", "--skips 'add,sum': each must be one of concat, add"),
    ("lr", 0.0, "--lr 0: must be in (0, 1]"),
    ("lr", float("nan"), "--lr nan: must be in (0, 1]"),
])  # fmt: skip
def test_bad_grids_are_named(flag, value, message, tmp_path):
    import argparse

    args = argparse.Namespace(size="1024x576", crop=None, widths="", depths="", unshuffles="",
                              growths="", skips="", lr=None, steps=1, threads=1, repeats=1,
                              eval_views=1, data=str(tmp_path), config=None)  # fmt: skip
    setattr(args, flag, value)
    with pytest.raises(ValueError) as err:
        run(args)
    assert message in str(err.value)


def test_the_bench_end_to_end_on_a_tiny_dataset(tiny_data, tmp_path, capsys):
    from nhfd.cli.main import main

    out = tmp_path / "bench"
    argv = ["bench", "tradeoff", "--data", str(tiny_data), "--profiles", "none", "--widths", "4",
            "--depths", "1", "--growths", "2", "--skips", "concat,add", "--steps", "2",
            "--crop", "32x32",
            "--size", "64x48", "--threads", "1", "--repeats", "2", "--eval-views", "1",
            "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    report = json.loads((out / "tradeoff.json").read_text())
    rows = {r["name"]: r for r in report["rows"]}
    assert set(rows) == {"w4-d1-u2", "w4-d1-u2-add"}
    assert rows["w4-d1-u2-add"]["skip"] == "add" and report["budget_steps"] == 2
    assert rows["w4-d1-u2-add"]["parameters"] < rows["w4-d1-u2"]["parameters"]
    for r in rows.values():
        assert r["steps"] == 2 and r["onnxruntime_ms"] > 0 and r["torch_ms"] > 0
        assert r["torch_over_onnxruntime"] == pytest.approx(r["torch_ms"] / r["onnxruntime_ms"])
    assert report["fastest_within_db"]["name"] in rows
    assert (out / "tradeoff.png").is_file()


def test_int8_checks_its_own_sizes_not_the_float_models(int8_pair):
    """The float model's checked_sizes were measured against torch; the int8 graph is another
    model, so it gets the same sizes checked on itself (full run against tiles)."""
    from nhfd.models.sizes import read_metadata

    src, dst = int8_pair
    float_sizes = read_metadata(src)["checked_sizes"]
    int8_sizes = read_metadata(dst)["checked_sizes"]
    assert [e["hw"] for e in int8_sizes] == [e["hw"] for e in float_sizes]
    assert all("torch" in e["against"] for e in float_sizes)
    assert all("torch" not in e["against"] and "tile" in e["against"] for e in int8_sizes)
    # with the float model's receptive margin the int8 graph agrees with itself on tiles
    assert all(e["ok"] for e in int8_sizes), int8_sizes
