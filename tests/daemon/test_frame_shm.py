"""Frames cross from the real frame worker in shared memory: what the daemon shows is, byte for
byte, `compute_frame`'s grey in the blank panel; the pipe carries only a small message; the
region changing size (a refocus) needs no new slot; the daemon's stop leaves /dev/shm clean."""

from __future__ import annotations

import dataclasses
import pickle
import time
from typing import Any

import numpy as np
import torch

from nhfd.benchmarks.pipeline import _Host, _load
from nhfd.calibration import CalibrationStore
from nhfd.daemon.frame_link import REFINE_SLOTS, SLOTS, PanelBuffer
from nhfd.models.export import load_model
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.frame import compute_frame
from nhfd.pipeline.settings import frame_settings
from nhfd.pipeline.view import Scene, scene_frame
from nhfd.scene.io import read_scene
from nhfd.worker_messages import FrameDone

from .test_frames import FRONT_VIEW, small_config


def arrays_in(obj: Any) -> list[str]:
    """Every numpy array (or bytes-like blob) anywhere in a message, by path."""
    if isinstance(obj, np.ndarray | bytes | bytearray | memoryview):
        return [type(obj).__name__]
    if isinstance(obj, dict):
        return [f"{k}.{p}" for k, v in obj.items() for p in arrays_in(v)]
    if dataclasses.is_dataclass(obj):  # a FrameMessage, its Region and StageTimes
        return [f"{f.name}.{p}" for f in dataclasses.fields(obj)
                for p in arrays_in(getattr(obj, f.name))]
    if isinstance(obj, list | tuple):
        return [f"{i}.{p}" for i, v in enumerate(obj) for p in arrays_in(v)]
    return []


def _spied_link(config: Any) -> tuple[Any, Any, list[Any]]:
    """A host's frame link whose worker's messages are also kept, in order, in the list."""
    host = _Host(config)
    link = host.frame_link()
    received: list[Any] = []
    receive = link.worker.receive

    def spy() -> list[Any]:
        msgs = receive()
        received.extend(msgs)
        return msgs

    link.worker.receive = spy
    return host, link, received


def test_frames_shown_through_shared_memory_are_compute_frames_grey(tiny, our_segments):
    config = small_config(daemon={"frames": {"cache_frames": 0}})
    host, link, received = _spied_link(config)
    model = load_model(tiny["model"], config)
    load = read_scene(str(tiny["scene"]))
    scene = Scene(load.gaussians, scene_frame(load.gaussians, str(tiny["scene"])))
    shapes = []
    try:
        _load(link, tiny["scene"], tiny["model"])
        assert len(our_segments()) == SLOTS + REFINE_SLOTS
        for refocus_mm in (0.0, 3.0):  # a refocus widens the coded region
            view = FRONT_VIEW.with_refocus(refocus_mm)
            seq = host.views.submit(view)
            deadline = time.monotonic() + 30
            while link.shown_seq < seq:
                link.step()
                assert not host.errors, host.errors
                assert time.monotonic() < deadline, "no frame"
                time.sleep(0.002)
            msg = next(m for m in received if isinstance(m, FrameDone) and m.seq == seq)
            # The pipe message says where the frame is; the arrays are not in it.
            assert arrays_in(msg) == []
            assert len(pickle.dumps(msg)) < 2000
            message = msg.message
            assert message.slot in range(SLOTS) and message.grey is None

            settings = frame_settings(config, model.info, CalibrationStore.of(config).active(),
                                      refocus_m=refocus_mm * 1e-3)
            expected = compute_frame(view, scene, model, Encoder(settings))
            r = expected.region
            assert message.grey_shape == expected.grey.shape == (3, r.height, r.width)
            assert message.region == r  # the worker's region, by name
            panel = PanelBuffer(host.panel.blank_frame()).frame(r.top, r.left, expected.grey)
            shown = host.slm.last_frame
            assert shown.tobytes() == panel.tobytes()  # byte-identical, blank around it
            assert np.array_equal(link.last_rgb, (np.clip(expected.rgb, 0, 1) * 255 + 0.5
                                                  ).astype(np.uint8))
            shapes.append(message.grey_shape)
        assert shapes[0] != shapes[1]
        assert len(our_segments()) == SLOTS + REFINE_SLOTS  # the same served both sizes
    finally:
        link.close()
    assert our_segments() == []


def test_the_pickle_transport_still_carries_the_arrays_in_the_message(tiny, our_segments):
    """`daemon.frames.transport = "pickle"` (kept for `nhfd bench pipeline --transport`): no
    segments, the grey in the message."""
    config = small_config(daemon={"frames": {"cache_frames": 0, "transport": "pickle"}})
    host = _Host(config)
    link = host.frame_link()
    received: list[Any] = []
    receive = link.worker.receive
    link.worker.receive = lambda: (msgs := receive(), received.extend(msgs))[0]
    try:
        _load(link, tiny["scene"], tiny["model"])
        assert our_segments() == []
        seq = host.views.submit(FRONT_VIEW)
        deadline = time.monotonic() + 30
        while link.shown_seq < seq:
            link.step()
            assert time.monotonic() < deadline, "no frame"
            time.sleep(0.002)
        msg = next(m for m in received if isinstance(m, FrameDone))
        assert arrays_in(msg) == ["message.grey.ndarray", "message.rgb.ndarray"]
        assert msg.message.slot is None
        r = msg.message.region
        shown = host.slm.last_frame[:, r.rows, r.cols]
        assert np.array_equal(shown, msg.message.grey)
    finally:
        link.close()


def test_a_k_subframe_models_frames_take_turns_on_the_panel(tiny, our_segments, tmp_path):
    """A model of K = 3 subframes (the tiny model's head widened, its copies moved apart):
    one frame request brings all K, in a refine slot (the pipe carries no array), and the panel
    shows the K distinct frames `compute_frame` gives, in turn, one per refresh, and nothing
    else."""
    from nhfd.models.torch_model import TorchModel
    from nhfd.pipeline.tune import write_tuned_model

    k = 3
    widened = TorchModel(tiny["model"]).module.with_subframes(k, jitter=0.0, seed=4)
    with torch.no_grad():  # subframes 1 and 2: other amplitudes (this small network's
        # features hardly vary across the view, and a phase offset is no other frame)
        widened.amplitude.weight[:, 3:6] *= 1.5
        widened.amplitude.weight[:, 6:9] *= 0.5
    path = write_tuned_model(tiny["model"], widened, tmp_path / "k3.onnx", {"steps": 0},
                             check_sizes=False)
    # (written as a tuned file is: served under no calibration only with the override)
    config = small_config(daemon={"frames": {"cache_frames": 0, "allow_other_bench": True}})
    host, link, received = _spied_link(config)
    model = load_model(path, config)
    load = read_scene(str(tiny["scene"]))
    scene = Scene(load.gaussians, scene_frame(load.gaussians, str(tiny["scene"])))
    settings = frame_settings(config, model.info, CalibrationStore.of(config).active())
    expected = compute_frame(FRONT_VIEW, scene, model, Encoder(settings))
    assert expected.subframes is not None and expected.subframes.shape[0] == k
    r = expected.region
    buffer = PanelBuffer(host.panel.blank_frame())
    panels = [buffer.frame(r.top, r.left, g).tobytes() for g in expected.subframes]
    assert len(set(panels)) == k
    try:
        _load(link, tiny["scene"], path)
        seq = host.views.submit(FRONT_VIEW)
        seen: list[bytes] = []
        deadline = time.monotonic() + 30
        while len(seen) < 2 * k + 1:
            link.step()
            assert not host.errors, host.errors
            assert time.monotonic() < deadline, f"{len(seen)} frames shown"
            if link.shown_seq == seq:
                frame = host.slm.last_frame.tobytes()
                if not seen or frame != seen[-1]:
                    seen.append(frame)
            time.sleep(0.002)
        msg = next(m for m in received if isinstance(m, FrameDone) and m.seq == seq)
        assert arrays_in(msg) == [] and msg.subframes.slot in range(REFINE_SLOTS)
        assert msg.subframes.grey_shape == expected.subframes.shape
        # the frame's own first, then subframes 1, 2, 0, 1, ... one per refresh
        assert seen == [panels[i % k] for i in range(len(seen))]
        assert link.subframes_shown == k  # what a capture's exposure is checked against
    finally:
        link.close()
    assert our_segments() == []


def test_a_k_subframe_frame_never_waits_for_a_refine_slot():
    """The worker's frame path writes a frame's K subframes into a free refine slot; when the
    daemon still holds every slot it sends them pickled in the message instead of waiting (the
    slots come back through the pipe the same thread reads)."""
    from multiprocessing import shared_memory

    from nhfd.frame_message import FrameMessage, Region, StageTimes
    from nhfd.pipeline.worker import FrameSlots, network_subframes

    region = Region(4, 6, 4, 6, 0, 0)
    grey = np.random.default_rng(5).integers(0, 256, (3, 3, 4, 6), np.uint8)
    message = FrameMessage.of_arrays(region, grey[0], None, StageTimes(render_s=0.002))
    shm = shared_memory.SharedMemory(create=True, size=grey.nbytes)
    try:
        slots = FrameSlots([], 0, [shm.name], grey.nbytes)
        first = network_subframes(message, grey, slots)
        assert first.slot == 0 and first.grey is None and first.grey_shape == grey.shape
        assert np.array_equal(np.ndarray(grey.shape, np.uint8, buffer=shm.buf), grey)
        assert first.report["tier"] == "network" and first.report["seconds"] == 0.002
        second = network_subframes(message, grey[::-1].copy(), slots)  # slot 0 still held
        assert second.slot is None and np.array_equal(second.grey, grey[::-1])
        slots.close()
    finally:
        shm.close()
        shm.unlink()
