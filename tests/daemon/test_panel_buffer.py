"""The daemon's output stage: the panel is the zero pattern with the coded region pasted in,
shown on the SLM without a transposing copy, in every colour mode."""

from __future__ import annotations

import numpy as np

from nhfd.calibration import CalibrationStore
from nhfd.daemon.colour import panel_for_mode
from nhfd.daemon.frame_link import FrameWorker, PanelBuffer
from nhfd.drivers.slm import SimulatedSLM, to_rgb
from nhfd.frame_message import FrameMessage, StageTimes, is_interleaved
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.settings import zero_pattern
from nhfd.pipeline.worker import FrameSlots
from tests.daemon.test_frames import small_config
from tests.pipeline.test_encoder import SETTINGS


def test_panel_is_the_zero_pattern_with_the_region_and_the_slm_keeps_its_own_copy():
    enc = Encoder(SETTINGS)
    r = enc.region
    grey = np.random.default_rng(0).integers(0, 256, (3, r.height, r.width), dtype=np.uint8)
    want = zero_pattern(SETTINGS).copy()
    want[:, r.rows, r.cols] = grey
    buffer = PanelBuffer(enc.zero)
    panel = buffer.frame(r.top, r.left, grey)
    assert panel.shape == (3, 128, 192) and np.array_equal(panel, want)
    assert np.shares_memory(to_rgb(panel, 128, 192), panel)  # no transposing copy
    again = buffer.frame(r.top, r.left, grey)  # a fresh frame each time, the buffer unchanged
    assert np.array_equal(again, want) and not np.shares_memory(again, panel)
    for mode, colour in (("hw-sync", "red"), ("single", "blue")):
        frame = panel_for_mode(buffer.frame(r.top, r.left, grey), mode, colour)
        expect = np.broadcast_to(want[2], want.shape) if mode == "single" else want
        assert np.array_equal(frame, expect)
        assert np.shares_memory(to_rgb(frame, 128, 192), frame)
        slm = SimulatedSLM(192, 128).open()
        slm.show(frame)
        frame[:] = 7  # the caller's array changes later: what the SLM keeps does not
        assert np.array_equal(slm.last_frame, expect) and np.array_equal(slm.frames[-1], expect)


def test_a_region_in_the_slms_layout_crosses_the_slot_and_pastes_as_the_planar_one():
    """A device frame's grey region is the `[3, h, w]` view of an `[h, w, 3]` array: it is
    written to its shared-memory slot in that layout (`grey_hwc`), read back as the same view,
    and pasted row by row into the same panel as its channel-first copy."""
    enc = Encoder(SETTINGS)
    r = enc.region
    rng = np.random.default_rng(11)
    hwc = rng.integers(0, 256, (r.height, r.width, 3), dtype=np.uint8)
    grey = hwc.transpose(2, 0, 1)
    planar = np.ascontiguousarray(grey)
    assert is_interleaved(grey) and not is_interleaved(planar)
    preview = rng.integers(0, 256, (3, 20, 30), dtype=np.uint8)
    message = FrameMessage.of_arrays(r, grey, preview, StageTimes())
    assert message.grey_hwc and not FrameMessage.of_arrays(r, planar, None, StageTimes()).grey_hwc
    config = small_config()
    worker = FrameWorker(config, CalibrationStore.of(config))
    slots = worker._make_slots()
    try:
        written = FrameSlots(slots["names"], slots["bytes"]).write(0, message)
        assert written.grey is None and written.grey_hwc
        raw = np.ndarray(hwc.size, np.uint8, buffer=worker.shms[0].buf)
        assert raw.tobytes() == hwc.tobytes()  # the slot holds the interleaved bytes
        got, got_preview = worker.arrays(written)
        assert is_interleaved(got) and np.array_equal(got, planar)
        assert np.array_equal(got_preview, preview)
        buffer = PanelBuffer(enc.zero)
        assert np.array_equal(buffer.frame(r.top, r.left, got),
                              buffer.frame(r.top, r.left, planar))
        del got, got_preview, raw
    finally:
        worker._unlink()
