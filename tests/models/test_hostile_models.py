"""Hostile model files (issue 32, items 8 and 9): metadata the frame path cannot use is refused
at load naming the field and its range; files that are not regular, too large or that point
outside themselves are refused before onnx reads them; a session that needs more memory than
its budget is refused by the memory probe, in a child process, without the caller allocating it.

Each hostile file is the shipped model with its metadata or graph edited here (small files)."""

from __future__ import annotations

import json
import math
import re
import resource
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from nhfd.models import export
from nhfd.models.export import (
    ModelOverBudget,
    OnnxModel,
    probe_model,
    read_model_file,
    read_model_metadata,
)
from nhfd.models.metadata import (
    INPUT_MULTIPLE_MAX,
    METADATA_KEY,
    InvalidMetadata,
    NotAModel,
)

SHIPPED = Path(__file__).resolve().parents[2] / "models" / "nhf-donut-512.onnx"
# The shipped model's training window padded to its multiple: the probe's input.
SHIPPED_INPUT = (1, 4, 288, 512)


@pytest.fixture(scope="module")
def shipped() -> Path:
    if not SHIPPED.exists():
        pytest.skip(f"no shipped model at {SHIPPED}")
    return SHIPPED


def hostile_copy(src: Path, dst: Path, *, meta: Callable[[dict], Any] | None = None,
                 graph: Callable[[onnx.ModelProto], Any] | None = None) -> Path:
    """`src` saved as `dst` with its nhfd metadata edited in place by `meta` and its model by
    `graph`."""
    model = onnx.load(str(src))
    if meta is not None:
        for prop in model.metadata_props:
            if prop.key == METADATA_KEY:
                value = json.loads(prop.value)
                meta(value)
                prop.value = json.dumps(value)  # NaN and Infinity written as Python writes them
    if graph is not None:
        graph(model)
    onnx.save(model, str(dst))
    return dst


def setting(path: str, value: Any) -> Callable[[dict], None]:
    """A metadata edit: the field at the dotted `path` set to `value`."""
    def edit(meta: dict) -> None:
        *parents, last = path.split(".")
        for key in parents:
            meta = meta[key]
        meta[last] = value
    return edit


def with_huge_tensor(shape_hw: tuple[int, int], at: str) -> Callable[[onnx.ModelProto], None]:
    """A graph edit: a ConstantOfShape of `shape_hw` float32 whose minimum (0) is added to the
    amplitude, so the outputs are unchanged and nothing prunes it. `at` "session": through a
    Cast, a chain onnxruntime's constant folding computes when the session is created (measured:
    2.1 GB resident for a 1 GiB tensor); "run": straight into a reduction, which onnxruntime
    leaves to the first run (4.5 GB for the [32768, 32768] of the issue)."""
    def edit(model: onnx.ModelProto) -> None:
        g = model.graph
        for node in g.node:
            node.output[:] = ["amplitude_raw" if o == "amplitude" else o for o in node.output]
        g.initializer.append(numpy_helper.from_array(np.array(shape_hw, np.int64), "huge_shape"))
        zero = helper.make_tensor("zero", TensorProto.FLOAT, [1], [0.0])
        nodes = [helper.make_node("ConstantOfShape", ["huge_shape"], ["huge"], value=zero)]
        if at == "session":
            nodes.append(helper.make_node("Cast", ["huge"], ["huge_cast"], to=TensorProto.FLOAT))
        nodes += [helper.make_node("ReduceMin", [nodes[-1].output[0]], ["huge_min"], keepdims=0),
                  helper.make_node("Add", ["amplitude_raw", "huge_min"], ["amplitude"])]
        g.node.extend(nodes)
    return edit


# (field, value, what the refusal says is allowed): the cases first, then every other
# field the frame path, status or the size checks read.
NAN, INF = math.nan, math.inf
CASES = [
    ("amplitude_scale", NAN, "a finite number in [1e-12, 1e+12]"),
    ("amplitude_scale", -1e30, "a finite number in [1e-12, 1e+12]"),
    ("amplitude_scale", 0, "a finite number in [1e-12, 1e+12]"),
    ("amplitude_scale", "2.9", "a finite number in [1e-12, 1e+12]"),
    ("mapping", NAN, "an object with a_m and b_m"),
    ("mapping.a_m", NAN, "a finite number (m)"),
    ("mapping.b_m", None, "a finite number (m)"),
    ("fx", NAN, "a finite number > 0 (px)"),
    ("fx", 0, "a finite number > 0 (px)"),
    ("fx", -703.0, "a finite number > 0 (px)"),
    ("fy", INF, "a finite number > 0 (px)"),
    ("fov_x_deg", 270.0, "a finite number in (0, 180) (deg)"),
    ("input_multiple", -16, f"a power of two in 1..{INPUT_MULTIPLE_MAX}"),
    ("input_multiple", 0, f"a power of two in 1..{INPUT_MULTIPLE_MAX}"),
    ("input_multiple", 12, f"a power of two in 1..{INPUT_MULTIPLE_MAX}"),
    ("input_multiple", 16.0, f"a power of two in 1..{INPUT_MULTIPLE_MAX}"),
    ("input_multiple", 32, "net.unshuffle x 2^net.depth = 16"),
    ("subframes", 0, "an integer in 1..8 (frames one inference emits)"),
    ("subframes", 9, "an integer in 1..8 (frames one inference emits)"),
    ("subframes", 2.5, "an integer in 1..8 (frames one inference emits)"),
    ("volume_m", [0.003, -0.003], "[near, far] in metres from the reference plane with near < "
                                  "far"),
    ("volume_m", [-0.007, 0.003], "a near end in front of the SLM (z0_m + near > 0"),
    ("volume_m", [-0.003], "a list of 2 numbers (m)"),
    ("wavelengths_m", [6.6e-7, NAN, 4.5e-7], "a finite number in [2e-07, 2e-06] (m)"),
    ("wavelengths_m", [6.6e-7, 5.2e-7], "a list of 3 numbers (m)"),
    ("wavelengths_m", [6.6e-7, 5.2e-7, 4.5e-3], "a finite number in [2e-07, 2e-06] (m)"),
    ("z0_m", NAN, "a finite number in (0, 1] (m)"),
    ("z0_m", -0.006, "a finite number in (0, 1] (m)"),
    ("pitch_m", 0, "a finite number in (0, 0.001) (m)"),
    ("pitch_m", NAN, "a finite number in (0, 0.001) (m)"),
    ("cutoff_per_px", [0.25, 0.25, 0.9], "a finite number in (0, 0.5] (cycles/px)"),
    ("aperture_shape", "hexagon", "one of square, circle, diamond"),
    ("train_size_hw", [0, 512], "an integer in 1..32768 (px)"),
    ("train_size_hw", [288.5, 512], "an integer in 1..32768 (px)"),
    ("train_size_hw", [288], "[height, width], integers in 1..32768 px"),
    ("pose_envelope.distance", [0.75, 0.61], "[low, high] with low <= high (scene units)"),
    ("pose_envelope.distance", [NAN, 0.75], "a finite number >= 0 (scene units)"),
    ("pose_envelope.azimuth_deg", "wide", "a list of 2 numbers (deg)"),
    ("pose_envelope.position_min", [0.5, -0.3], "a list of 3 numbers (scene units)"),
    ("checked_sizes", [{"hw": [288, 512], "max_abs_diff": NAN, "ok": True, "against": "x"}],
     "a finite number in [0, 0.001] (ok is true)"),
    ("checked_sizes", [{"hw": [-288, 512], "max_abs_diff": 0.0, "ok": True, "against": "x"}],
     "an integer in 1..32768 (px)"),
    ("format_version", "1", "an integer in 1..1"),
    ("train_steps", 1e4, "an integer or null"),
    ("profile", ["fast"], "a string or null"),
]


@pytest.mark.parametrize(("field", "value", "allowed"), CASES,
                         ids=[f"{c[0]}={c[1]!r}" for c in CASES])
def test_metadata_out_of_range_is_refused_at_load_naming_the_field(shipped, tmp_path, field,
                                                                   value, allowed):
    path = hostile_copy(shipped, tmp_path / "m.onnx", meta=setting(field, value))
    # No configuration given (as `nhfd eval` opens a model): today's load accepted every one
    # of these, and the optics ones were refused only when compared with a configuration.
    with pytest.raises(InvalidMetadata) as refused:
        OnnxModel(path)
    message = str(refused.value)
    name = field.split(".")[0] if field in ("checked_sizes",) else field
    assert message.startswith(f"{path}: metadata {name}"), message
    assert f": expected {allowed}" in message
    # the onnx reader (no session: what a GPU session's options come from) refuses it too
    with pytest.raises(InvalidMetadata, match=re.escape(f"metadata {name}")):
        read_model_metadata(path)


def test_a_non_finite_number_anywhere_in_the_metadata_is_refused_by_its_path(shipped, tmp_path):
    path = hostile_copy(shipped, tmp_path / "m.onnx",
                        meta=setting("mapping.measured.d_max", INF))
    with pytest.raises(InvalidMetadata, match=r"metadata mapping\.measured\.d_max = inf: "
                                              r"expected a finite number \(no NaN or infinity"):
        OnnxModel(path)
    # except where exports write one: a size check that failed records NaN, with ok false
    failed = {"hw": [64, 64], "max_abs_diff": NAN, "ok": False, "against": "torch"}
    path = hostile_copy(shipped, tmp_path / "failed.onnx",
                        meta=lambda m: m["checked_sizes"].append(failed))
    assert math.isnan(OnnxModel(path).metadata["checked_sizes"][-1]["max_abs_diff"])
    assert OnnxModel(shipped).metadata["input_multiple"] == 16  # and the shipped model passes


def test_metadata_json_past_the_decoders_limits_is_not_a_model(shipped, tmp_path):
    # json's decoder recurses per level: today a RecursionError escaped the loader
    text = json.dumps({"x": 1}).replace("1", "[" * 100_000 + "]" * 100_000)

    def nest(model: onnx.ModelProto) -> None:
        for prop in model.metadata_props:
            if prop.key == METADATA_KEY:
                prop.value = prop.value[:-1] + ', "deep": ' + text + "}"
    path = hostile_copy(shipped, tmp_path / "deep.onnx", graph=nest)
    with pytest.raises(NotAModel, match="nhfd metadata is nested too deeply to read"):
        OnnxModel(path)
    # and an integer longer than Python converts (4300 digits) raised a bare ValueError
    path = hostile_copy(shipped, tmp_path / "long.onnx", graph=lambda m: setattr(
        m.metadata_props[0], "value", m.metadata_props[0].value[:-1] + ', "n": ' + "9" * 5000
        + "}"))
    with pytest.raises(NotAModel, match="nhfd metadata is not valid JSON"):
        OnnxModel(path)


def test_only_regular_files_within_the_budget_and_without_external_data_are_read(shipped,
                                                                                 tmp_path):
    link = tmp_path / "null.onnx"
    link.symlink_to("/dev/null")
    with pytest.raises(NotAModel, match=r"null\.onnx: not a regular file"):
        read_model_metadata(link)
    size = shipped.stat().st_size
    with pytest.raises(ModelOverBudget, match=rf"{size / 2**20:.1f} MB, more than "
                                              r"daemon\.paths\.model_memory_mb = 0\.125 MB"):
        read_model_file(shipped, max_bytes=2**20 // 8, setting="daemon.paths.model_memory_mb")
    assert read_model_file(shipped, max_bytes=size).graph.input[0].name == "rgbd"

    def outside(model: onnx.ModelProto) -> None:
        t = model.graph.initializer[0]
        t.ClearField("raw_data")
        t.data_location = TensorProto.EXTERNAL
        t.external_data.add(key="location", value="/dev/zero")
        t.external_data.add(key="length", value=str(1 << 40))
    path = hostile_copy(shipped, tmp_path / "ext.onnx", graph=outside)
    name = onnx.load(str(shipped)).graph.initializer[0].name
    with pytest.raises(NotAModel, match=rf"tensor '{re.escape(name)}' is stored outside the "
                                        "model file"):
        read_model_metadata(path)


def test_the_probe_measures_the_shipped_model_within_a_small_budget(shipped):
    probe = probe_model(shipped, 64, [SHIPPED_INPUT], threads=1,
                        setting="daemon.paths.model_memory_mb")
    assert probe["run_error"] is None and probe["skipped"] == []
    # a session and a 288 x 512 run of the 43k-parameter network: tens of MB, not more
    assert 0 < probe["peak_mb"] < 64
    # a shape the graph's declared input cannot take is left to the load's own check
    assert probe_model(shipped, 64, [(1, 3, 288, 512)])["skipped"] == [[1, 3, 288, 512]]


@pytest.mark.parametrize("at", ["session", "run"])
def test_the_probe_refuses_a_graph_that_allocates_past_the_budget_without_the_caller(
        shipped, tmp_path, at):
    # 512 MiB of float32 (the was 4 GiB): past a 256 MB budget
    path = hostile_copy(shipped, tmp_path / f"huge-{at}.onnx",
                        graph=with_huge_tensor((8192, 16384), at))
    assert path.stat().st_size < 300_000  # a small file
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ModelOverBudget) as refused:
        probe_model(path, 256, [SHIPPED_INPUT], setting="daemon.paths.model_memory_mb")
    message = str(refused.value)
    assert "needs more memory than daemon.paths.model_memory_mb = 256 MB allows" in message
    assert "ConstantOfShape node: Failed to allocate memory" in message
    assert str(8192 * 16384 * 4) in message  # the size that was asked for
    # this process never held it (its own peak grew by far less than the 512 MiB)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before < 128 * 1024


def test_a_probe_that_dies_is_a_refusal_naming_the_budget(shipped, monkeypatch):
    # What a C++ runtime that aborts on a failed allocation looks like from here.
    monkeypatch.setattr(export, "PROBE_SCRIPT", "import os, signal\n"
                                                "os.kill(os.getpid(), signal.SIGKILL)\n")
    with pytest.raises(ModelOverBudget, match=r"limited to daemon\.paths\.model_memory_mb = 64 MB, "
                                              r"ended with signal SIGKILL"):
        probe_model(shipped, 64, [SHIPPED_INPUT], setting="daemon.paths.model_memory_mb")


def test_a_graph_onnxruntime_cannot_open_is_not_a_model_in_the_probe(shipped, tmp_path):
    def broken(model: onnx.ModelProto) -> None:
        model.graph.node[0].input[0] = "nowhere"
    path = hostile_copy(shipped, tmp_path / "broken.onnx", graph=broken)
    with pytest.raises(NotAModel, match=r"broken\.onnx: not a readable ONNX model"):
        probe_model(path, 256, [SHIPPED_INPUT])
