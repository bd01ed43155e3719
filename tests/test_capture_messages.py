"""The citl capture messages (`nhfd.frame_message.CaptureRequest`, `CaptureReply`): what crosses
the worker's pipe is checked where it is made, each bad field named."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from nhfd.frame_message import CaptureReply, CaptureRequest, Region

REGION = Region(0, 0, 8, 12, 2, 2)


def _grey(*shape: int) -> np.ndarray:
    return np.zeros(shape, np.uint8)


def test_a_request_keeps_its_subframes_and_depths_and_crosses_a_pipe():
    request = CaptureRequest(REGION, _grey(2, 3, 8, 12), [np.float32(1e-3), 2e-3], np.int64(3))
    assert request.z_m == (pytest.approx(1e-3), 2e-3) and request.frames == 3
    assert isinstance(request.frames, int)
    again = pickle.loads(pickle.dumps(request))
    assert again.region == REGION and again.grey.shape == (2, 3, 8, 12)


@pytest.mark.parametrize(("grey", "z_m", "frames", "named"), [
    (_grey(3, 8, 12), (1e-3,), 0, r"capture grey uint8 \[3, 8, 12\]: expected uint8 \[K >= 1"),
    (_grey(1, 3, 8, 10), (1e-3,), 0, r"expected uint8 \[K >= 1, C, 8, 12\]"),
    (np.zeros((1, 3, 8, 12)), (1e-3,), 0, r"capture grey float64"),
    (_grey(1, 3, 8, 12), (), 0, r"capture z_m = \[\]: expected one or more finite depths"),
    (_grey(1, 3, 8, 12), (float("nan"),), 0, r"capture z_m = \[nan\]"),
    (_grey(1, 3, 8, 12), (1e-3,), -1, r"capture frames = -1: expected an integer >= 0"),
    (_grey(1, 3, 8, 12), (1e-3,), True, r"capture frames = True"),
])
def test_a_bad_request_names_its_field(grey, z_m, frames, named):
    with pytest.raises(ValueError, match=named):
        CaptureRequest(REGION, grey, z_m, frames)


def test_a_reply_is_images_with_their_saturation_or_an_error():
    images = np.ones((2, 3, 5, 7), np.float32)
    ok = CaptureReply(images, np.zeros(images.shape, bool))
    assert ok.error == "" and ok.images is images
    assert CaptureReply(error="the lasers are not armed").images is None
    with pytest.raises(ValueError, match=r"images \[2, 3, 5, 7\], saturated \[2, 3, 5\]"):
        CaptureReply(images, np.zeros((2, 3, 5), bool))
    with pytest.raises(ValueError, match="saturated bool"):
        CaptureReply(images, np.zeros(images.shape, np.uint8))
    with pytest.raises(ValueError, match="not finite"):
        bad = images.copy()
        bad[0, 0, 0, 0] = np.inf
        CaptureReply(bad, np.zeros(images.shape, bool))
    with pytest.raises(ValueError, match="or an error"):
        CaptureReply()
