"""The daemon's output stage: the panel is the zero pattern with the coded region pasted in,
shown on the SLM without a transposing copy, in every colour mode."""

from __future__ import annotations

import numpy as np

from nhfd.daemon.colour import panel_for_mode
from nhfd.daemon.frame_link import PanelBuffer
from nhfd.drivers.slm import SimulatedSLM, to_rgb
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.settings import zero_pattern
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
