"""The frame worker's load path against hostile model files (issue 32, items 8 and 9): a model
whose metadata the frame path cannot use, or whose session needs more than
daemon.paths.model_memory_mb, is refused, the refusal names the field or the budget, and the model
already serving stays (the same object, the same model id), loaded and answering."""

from __future__ import annotations

import math
import multiprocessing
import re
import resource
from pathlib import Path

import pytest

from nhfd.config import Config
from nhfd.models.export import ModelOverBudget
from nhfd.models.metadata import InvalidMetadata
from nhfd.pipeline.worker import _serve, _WorkerState, check_inference
from nhfd.worker_messages import Loaded, LoadFailed, LoadModel, ModelLoaded, Stop, WorkerReady
from tests.models.test_hostile_models import SHIPPED, hostile_copy, setting, with_huge_tensor

# The shipped model's training window (checked), and a budget far above what its session takes
# (24 MB measured) and far below the hostile tensors here (512 MiB).
FRAME = [512, 288]
BUDGET_MB = 256


@pytest.fixture(scope="module")
def shipped() -> Path:
    if not SHIPPED.exists():
        pytest.skip(f"no shipped model at {SHIPPED}")
    return SHIPPED


def serving(shipped: Path) -> _WorkerState:
    """A worker state serving the shipped model under a BUDGET_MB model budget."""
    state = _WorkerState(Config.model_validate(
        {"daemon": {"paths": {"model_memory_mb": BUDGET_MB}, "frames": {"size_px": FRAME}}}))
    info = state.load_model(str(shipped))
    # what the load's probe measured travels to status, below the budget
    assert 0 < info.load_memory_mb < BUDGET_MB
    assert info.to_json()["load_memory_mb"] == info.load_memory_mb
    return state


def assert_still_serving(state: _WorkerState, model: object, shipped: Path) -> None:
    assert state.model is model and state.model_id == 1
    assert state.model.path == shipped
    check_inference(state.model, (FRAME[1], FRAME[0]), str(shipped))  # and it still answers


@pytest.mark.parametrize(("field", "value"), [
    ("amplitude_scale", math.nan), ("amplitude_scale", -1e30), ("mapping", math.nan),
    ("fx", math.nan), ("fx", 0), ("input_multiple", -16), ("input_multiple", 0),
    ("mapping.a_m", math.nan),
])
def test_a_model_with_unusable_metadata_never_replaces_the_serving_one(shipped, tmp_path,
                                                                       field, value):
    state = serving(shipped)
    model = state.model
    path = hostile_copy(shipped, tmp_path / "bad.onnx", meta=setting(field, value))
    # Today: NaN or negative scales, a NaN mapping, a zero fx passed and replaced the model
    # (every later frame failed); input_multiple 0 raised ZeroDivisionError.
    with pytest.raises(InvalidMetadata, match=rf"bad\.onnx: metadata {re.escape(field)}"):
        state.load_model(str(path))
    assert_still_serving(state, model, shipped)


@pytest.mark.parametrize("at", ["session", "run"])
def test_a_model_that_needs_more_than_the_budget_is_refused_without_allocating_it(
        shipped, tmp_path, at):
    state = serving(shipped)
    model = state.model
    path = hostile_copy(shipped, tmp_path / f"huge-{at}.onnx",
                        graph=with_huge_tensor((8192, 16384), at))
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ModelOverBudget, match=rf"huge-{at}\.onnx: its test inference needs "
                                              rf"more memory than daemon\.paths\.model_memory_mb = "
                                              rf"{BUDGET_MB} MB allows"):
        state.load_model(str(path))
    # Today this process folded or ran the 512 MiB tensor (1 GB resident at the fold): here it
    # never held it.
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before < 128 * 1024
    assert_still_serving(state, model, shipped)


def test_the_worker_replies_with_each_refusal_and_keeps_the_model(shipped, tmp_path):
    """Through the worker's message loop, as the daemon's `load_model` reaches it."""
    state = _WorkerState(Config.model_validate(
        {"daemon": {"paths": {"model_memory_mb": BUDGET_MB}, "frames": {"size_px": FRAME}}}))
    nan_scale = hostile_copy(shipped, tmp_path / "nan.onnx",
                             meta=setting("amplitude_scale", math.nan))
    huge = hostile_copy(shipped, tmp_path / "huge.onnx", graph=with_huge_tensor((8192, 16384),
                                                                                 "session"))
    daemon_end, worker_end = multiprocessing.Pipe()
    for i, path in enumerate((shipped, nan_scale, huge), 1):
        daemon_end.send(LoadModel(i, str(path)))
    daemon_end.send(Stop())
    _serve(worker_end, state, None)  # handles the batch in order, returns at Stop
    assert isinstance(daemon_end.recv(), WorkerReady)
    replies = {r.req_id: r for r in (daemon_end.recv() for _ in range(3))}
    assert isinstance(replies[1], Loaded) and isinstance(replies[1].result, ModelLoaded)
    assert replies[1].result.path == str(shipped)
    assert replies[1].result.info == state.model.info  # the ModelInfo itself crossed
    assert isinstance(replies[2], LoadFailed)
    assert replies[2].error.startswith("InvalidMetadata: ")
    assert "nan.onnx: metadata amplitude_scale = nan: expected a finite number" in replies[2].error
    assert isinstance(replies[3], LoadFailed) and replies[3].error.startswith("ModelOverBudget: ")
    assert f"daemon.paths.model_memory_mb = {BUDGET_MB} MB" in replies[3].error
    assert state.model_id == 1 and str(state.model.path) == str(shipped)
