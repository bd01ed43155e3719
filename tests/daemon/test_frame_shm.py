"""Frames cross from the real frame worker in shared memory: what the daemon shows is, byte for
byte, `compute_frame`'s grey in the blank panel; the pipe carries only a small message; the
region changing size (a refocus) needs no new slot; the daemon's stop leaves /dev/shm clean."""

from __future__ import annotations

import dataclasses
import pickle
import time
from typing import Any

import numpy as np

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


def test_frames_shown_through_shared_memory_are_compute_frames_grey(tiny, our_segments):
    config = small_config(daemon={"frames": {"cache_frames": 0}})
    host = _Host(config)
    link = host.frame_link()
    received: list[Any] = []
    receive = link.worker.receive

    def spy() -> list[Any]:
        msgs = receive()
        received.extend(msgs)
        return msgs

    link.worker.receive = spy
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
