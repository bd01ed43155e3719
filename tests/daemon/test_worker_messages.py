"""The frame worker's pipe as typed messages (`nhfd.worker_messages`): each message crosses a
real `multiprocessing` pipe equal to itself; each refuses a bad field naming it; docs/frames.md's
table lists every class with its exact fields and nothing else; and a message of another type
is refused by name on either side, the worker answering `MessageRefused`, the daemon's control
loop noting an error and going on."""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from nhfd.frame_message import (
    REFINE_KEYS,
    CaptureReply,
    CaptureRequest,
    FrameMessage,
    RefinedFrame,
    Region,
    StageTimes,
)
from nhfd.model_info import CheckedSize, DepthMapping, ModelInfo, PoseEnvelope
from nhfd.views import Orbit, Pose, View
from nhfd.worker_messages import (
    FROM_WORKER,
    LOADED,
    TO_WORKER,
    BetterFrame,
    CancelFrame,
    CaptureAnswer,
    CaptureAsked,
    FrameCancelled,
    FrameDone,
    FrameFailed,
    FrameRequest,
    Loaded,
    LoadFailed,
    LoadModel,
    LoadScene,
    MessageRefused,
    ModelLoaded,
    RefineFailed,
    RefineSlotFree,
    SceneLoaded,
    Stop,
    WorkerReady,
)

from .fake_loads import fake_scene
from .test_frame_link_state import make_link

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "frames.md"
DONUT = REPO / "models" / "scenes" / "donut.ply"
REGION = Region(2, 4, 3, 5, 1, 1)
INFO = ModelInfo(
    inputs="rgbd", wavelengths_m=(660e-9, 520e-9, 450e-9), pitch_m=8e-6, aperture_shape="square",
    cutoff_per_px=(0.5, 0.45, 0.4), z0_m=0.006, volume_m=(-0.003, 0.003), amplitude_scale=2.9,
    train_size_hw=(288, 512), input_multiple=16, fx_px=703.4, fy_px=703.4,
    mapping=DepthMapping(-0.0167, 0.0106, 0.54, 0.77),
    pose_envelope=PoseEnvelope(distance=(0.6, 0.75), azimuth_deg=(-29.6, 41.7),
                               elevation_deg=(10.1, 30.0), position_min=(0.4, -0.3, 0.1),
                               position_max=(0.7, 0.5, 0.4), n=130),
    checked_sizes=(CheckedSize((288, 512), 1e-6, True, "torch"),
                   CheckedSize((576, 1024), 2e-6, True, "torch")),
    profile="fast", parameters=42968, train_steps=10000, scene_sha256="ab" * 32,
    precision="float32")
MODEL = ModelLoaded(
    path="/m/model.onnx", info=INFO, served="/m/model-int8.onnx", variant="int8",
    variant_reason="model-int8.onnx loses 0.30 dB", providers=("CPUExecutionProvider",),
    inference="onnxruntime", inference_reason="auto", device="cpu", device_reason="auto",
    window_hw=(288, 512), checked_sizes_hw=((288, 512), (576, 1024)),
    checked_sizes_recorded=True, loaded_s=1764650000.5, load_memory_mb=24.3,
    size_warning="a warning")


def _grey(*shape: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


REPORT = {"tier": "sgd", "iterations": 10, "seconds": 0.5, "loss": 0.1, "psnr_db": 31.0,
          "start_psnr_db": 28.0, "stop": ""}
assert set(REPORT) == set(REFINE_KEYS)
REPLY = CaptureReply(np.linspace(0, 1, 2 * 3 * 4 * 5, dtype=np.float32).reshape(2, 3, 4, 5),
                     np.zeros((2, 3, 4, 5), bool))
# One of every message (and of every value a load's answer carries), as each side sends it.
SAMPLES: list[Any] = [
    FrameRequest(3, View(Orbit(10.0, 5.0, 2.0), 1.5, "sgd"), 0),
    FrameRequest(4, View(Pose((0.1, 0.2, -2.0), (1.0, 0.0, 0.0, 0.0))), None),
    LoadModel(1, "/m/model.onnx"),
    LoadScene(2, "/s/donut.ply"),
    CancelFrame(4),
    CaptureAnswer(5, REPLY),
    CaptureAnswer(6, CaptureReply(error="the lasers are disarmed")),
    RefineSlotFree(1),
    Stop(),
    WorkerReady(4321),
    Loaded(1, MODEL),
    Loaded(2, SceneLoaded("/s/donut.ply", 45624, 45624, 0, "", (0.005, 0.017, 0.054), "+z")),
    LoadFailed(7, "ModelMismatch: pitch_m differs"),
    FrameDone(3, FrameMessage(REGION, (3, 3, 5), (3, 8, 9), StageTimes(0.1, 0.02, 0.03, 0.004),
                              (0.0, 0.01, 0.02), ("outside the azimuths",), slot=0,
                              ready_s=12.5)),
    FrameDone(3, FrameMessage.of_arrays(REGION, _grey(3, 3, 5), _grey(3, 8, 9, seed=1),
                                        StageTimes(render_s=0.1))),
    FrameFailed(3, "RuntimeError: no model loaded"),
    FrameCancelled(8),
    BetterFrame(3, RefinedFrame(REGION, None, REPORT, slot=1, grey_shape=(2, 3, 3, 5))),
    BetterFrame(3, RefinedFrame(REGION, _grey(2, 3, 3, 5), REPORT)),
    RefineFailed(3, "ValueError: quality = 'citl' needs a calibration"),
    CaptureAsked(3, 9, CaptureRequest(REGION, _grey(2, 3, 3, 5), (0.006, 0.0065), 2)),
    MessageRefused("tuple", "tuple: not a message the frame worker takes (...)"),
    MODEL,
    fake_scene("/s/cloud.ply"),
]
# Those whose fields compare by value (the frame messages and captures compare by identity:
# they may hold arrays), so `==` holds across the pipe too.
BY_VALUE = (FrameRequest, LoadModel, LoadScene, CancelFrame, RefineSlotFree, Stop, WorkerReady,
            Loaded, LoadFailed, FrameFailed, FrameCancelled, RefineFailed, MessageRefused,
            ModelLoaded, SceneLoaded)


def same(a: Any, b: Any) -> bool:
    """Equal values, arrays compared by dtype, shape and content, dataclasses field by field."""
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    if dataclasses.is_dataclass(a):
        return all(same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    return a == b


def test_every_message_crosses_a_real_pipe_equal_to_itself():
    assert {type(m) for m in SAMPLES} == {*TO_WORKER, *FROM_WORKER, *LOADED}
    here, there = mp.Pipe(duplex=True)
    try:
        for msg in SAMPLES:
            here.send(msg)
            got = there.recv()
            assert same(got, msg), msg
            if isinstance(msg, BY_VALUE):
                assert got == msg
            there.send(got)  # and back the other way
            assert same(here.recv(), msg)
    finally:
        here.close()
        there.close()


def test_messages_are_frozen_slotted_values():
    for cls in (*TO_WORKER, *FROM_WORKER, *LOADED):
        params = cls.__dataclass_params__
        assert params.frozen and hasattr(cls, "__slots__"), cls.__name__
    with pytest.raises(dataclasses.FrozenInstanceError):
        SAMPLES[0].seq = 5
    assert not hasattr(Stop(), "__dict__")


def test_a_message_refuses_a_bad_field_naming_it():
    view = View(Orbit(0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match=r"frame request seq = -1: expected an integer >= 0"):
        FrameRequest(-1, view, 0)
    with pytest.raises(ValueError, match=r"frame request view: expected View, found dict"):
        FrameRequest(1, {"kind": "orbit"}, 0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"frame request slot = 'a': expected an integer >= 0 "
                                         r"or None"):
        FrameRequest(1, view, "a")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"frame done message: expected FrameMessage, found "
                                         r"tuple"):
        FrameDone(1, ("frame", 1))  # type: ignore[arg-type]
    # The old protocol's report (a dict) is no load result.
    with pytest.raises(ValueError, match=r"loaded result: expected ModelLoaded or SceneLoaded, "
                                         r"found dict"):
        Loaded(1, {"path": "m.onnx"})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"model loaded info: expected ModelInfo, found dict"):
        dataclasses.replace(MODEL, info={"profile": "fast"})
    with pytest.raises(ValueError, match=r"model loaded variant = 'fp16': expected one of "
                                         r"float, int8"):
        dataclasses.replace(MODEL, variant="fp16")
    with pytest.raises(ValueError, match=r"model loaded window_hw = \[0, 512\]"):
        dataclasses.replace(MODEL, window_hw=(0, 512))
    with pytest.raises(ValueError, match=r"scene loaded center = \[0.0, 1.0\]"):
        SceneLoaded("s.ply", 1, 1, 0, "", (0.0, 1.0), "+z")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"capture asked request: expected CaptureRequest"):
        CaptureAsked(1, 2, REPLY)  # type: ignore[arg-type]


def test_the_model_reports_itself_as_status_always_showed_it():
    """`status`'s "model": the path, the metadata's fields, then how it serves; the size warning
    only where there is one."""
    out = MODEL.to_json()
    assert list(out) == [
        "path", "profile", "train_size_hw", "fx", "amplitude_scale", "z0_m", "volume_m",
        "mapping", "pose_envelope", "parameters", "train_steps", "scene_sha256", "subframes",
        "providers",
        "loaded_s", "load_memory_mb", "inference", "inference_reason", "variant",
        "variant_reason", "served", "window_hw", "checked_sizes_hw", "checked_sizes_recorded",
        "device", "device_reason", "size_warning", "tuned_for"]
    assert out == {"path": "/m/model.onnx", **INFO.status_json(),
                   "providers": ["CPUExecutionProvider"], "loaded_s": 1764650000.5,
                   "load_memory_mb": 24.3, "inference": "onnxruntime",
                   "inference_reason": "auto", "variant": "int8",
                   "variant_reason": "model-int8.onnx loses 0.30 dB",
                   "served": "/m/model-int8.onnx", "window_hw": [288, 512],
                   "checked_sizes_hw": [[288, 512], [576, 1024]],
                   "checked_sizes_recorded": True, "device": "cpu", "device_reason": "auto",
                   "size_warning": "a warning", "tuned_for": None}
    assert "size_warning" not in dataclasses.replace(MODEL, size_warning="").to_json()
    assert SAMPLES[11].result.to_json() == {
        "path": "/s/donut.ply", "gaussians": 45624, "declared": 45624, "dropped": 0,
        "dropped_reason": "", "center": (0.005, 0.017, 0.054), "up": "+z"}


# -- the table in docs/frames.md ----------------------------------------------------------------


def _section(text: str, title: str) -> str:
    start = text.index(f"## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start:] if end < 0 else text[start:end]


def _rows(section: str, header: str) -> list[list[str]]:
    """The rows of the table whose header line is `header`, as cells."""
    lines = section.splitlines()
    at = lines.index(header)
    rows = []
    for line in lines[at + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


def _names(cell: str) -> list[str]:
    return re.findall(r"`([^`]+)`", cell)


def test_the_protocol_table_lists_every_message_with_its_exact_fields():
    section = _section(DOC.read_text(), "The worker's pipe")
    rows = _rows(section, "| message | direction | fields | meaning |")
    documented = [(_names(m)[0], d, _names(f)) for m, d, f, meaning in rows if meaning]
    assert len(documented) == len(rows)  # every row says what the message means
    expected = ([(c.__name__, "daemon → worker", [f.name for f in dataclasses.fields(c)])
                 for c in TO_WORKER]
                + [(c.__name__, "worker → daemon", [f.name for f in dataclasses.fields(c)])
                   for c in FROM_WORKER])
    assert documented == expected
    values = _rows(section, "| value | fields | meaning |")
    assert [(_names(v)[0], _names(f)) for v, f, _ in values] == [
        (c.__name__, [f.name for f in dataclasses.fields(c)]) for c in LOADED]


# -- a message of another type, refused by name on each side ----------------------------------


def test_the_worker_refuses_a_message_it_does_not_take_by_name_and_goes_on():
    from nhfd.config import Config
    from nhfd.pipeline.worker import _serve, _WorkerState

    state = _WorkerState(Config.model_validate({}))
    daemon_end, worker_end = mp.Pipe()
    try:
        daemon_end.send(("model", 1, "old.onnx"))  # the old protocol's tuple
        daemon_end.send(WorkerReady(1))  # a worker's message sent back to it
        daemon_end.send(CaptureAnswer(3, REPLY))  # for no citl step: dropped, no reply
        daemon_end.send(LoadScene(2, str(DONUT)))
        daemon_end.send(Stop())
        _serve(worker_end, state, None)  # returns at Stop
        replies = []
        while daemon_end.poll(0):
            replies.append(daemon_end.recv())
    finally:
        daemon_end.close()
        worker_end.close()
    assert isinstance(replies[0], WorkerReady)
    refused = replies[1:3]
    assert [type(r) for r in refused] == [MessageRefused, MessageRefused]
    assert [r.kind for r in refused] == ["tuple", "WorkerReady"]
    assert refused[0].error == ("tuple: not a message the frame worker takes (FrameRequest, "
                                "LoadModel, LoadScene, CancelFrame, CaptureAnswer, "
                                "RefineSlotFree, Stop)")
    # and it goes on: the load after them is served
    assert len(replies) == 4 and isinstance(replies[3], Loaded) and replies[3].req_id == 2
    assert isinstance(replies[3].result, SceneLoaded) and replies[3].result.gaussians > 0


def test_the_frame_link_notes_a_message_it_does_not_take_and_goes_on(short_dir):
    owner, link = make_link(short_dir)
    here, there = mp.Pipe(duplex=True)
    link.worker.conn = here
    link.worker.process = SimpleNamespace(is_alive=lambda: True, exitcode=None, pid=1)
    link.state = link.state.RUNNING
    try:
        there.send(("frame", 7, "a message of the old protocol"))
        there.send(Stop())  # a daemon's message coming back
        there.send(MessageRefused("tuple", "tuple: not a message the frame worker takes (...)"))
        there.send(FrameFailed(8, "RuntimeError: no model loaded"))  # the loop goes on
        link.step()
        assert link.state == link.state.RUNNING and owner.crashes == []
        assert [source for source, _ in owner.errors] == ["frame worker"] * 4
        messages = [m for _, m in owner.errors]
        assert messages[0] == ("tuple: not a message the frame link takes (WorkerReady, Loaded, "
                               "LoadFailed, FrameDone, FrameFailed, FrameCancelled, "
                               "BetterFrame, RefineFailed, CaptureAsked, MessageRefused)")
        assert messages[1].startswith("Stop: not a message the frame link takes (")
        assert messages[2] == "refused tuple: not a message the frame worker takes (...)"
        assert messages[3] == "view 8: RuntimeError: no model loaded"
    finally:
        link.state, link.worker.process = link.state.IDLE, None
        here.close()
        there.close()
