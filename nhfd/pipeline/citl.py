"""The camera in the loop (`citl`, issue 34), the frame pipeline's half: captures -> the
window's grid, and `RemoteCapture`, the `nhfd.pipeline.refine.Capture` a frame worker uses.

The camera belongs to the daemon and the optimisation to the frame worker. Each citl step the
worker sends a `CaptureAsked(seq, req_id, CaptureRequest)` (the step's subframes and the
planes' depths); the daemon's bench shows them, captures each plane with each colour's diode
alone on (`nhfd.daemon.citl`) and answers `CaptureAnswer(req_id, CaptureReply)` with the raw
camera images, which are mapped here onto the SLM's grid through the calibration's geometry
(`captured_window`, also what the offline `nhfd.calib.citl.CameraLoop` uses).
"""

from __future__ import annotations

import itertools
import queue
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np

from nhfd.calibration import Calibration
from nhfd.frame_message import CaptureReply, CaptureRequest
from nhfd.optics.camera_grid import Geometry, calibrated_geometry, to_slm_grid
from nhfd.worker_messages import CaptureAsked

from .encoder import Encoder
from .refine import Cancelled, CaptureStopped

# More than this fraction of the window saturated: the exposure is too long to fit intensities.
MAX_SATURATED = 0.02
# Less than this fraction of the window inside the camera's image: its region of interest does
# not hold the panel's image.
MIN_SEEN = 0.5
# The longest a step's captures may take on the bench (planes x colours x subframes captures,
# stage moves and settling) before the worker stops waiting.
CAPTURE_TIMEOUT_S = 300.0
# How often a worker waiting for captures looks for a cancel.
POLL_S = 0.05


def captured_window(images: np.ndarray, saturated: np.ndarray, geometry: Geometry,
                    encoder: Encoder) -> tuple[np.ndarray, np.ndarray]:
    """Camera images `[P, C, Hc, Wc]` (linear) and their saturation `[P, C, Hc, Wc]` -> the
    intensities on the encoder's window `[P, C, h, w]` float64 and where they count `[h, w]`
    (inside every image, away from the panel's edge, saturated nowhere). CaptureStopped when
    less than MIN_SEEN of the window is seen or more than MAX_SATURATED of it saturated."""
    s, r = encoder.settings, encoder.region
    h, w = s.window_hw
    top, left = r.top + r.window_top, r.left + r.window_left
    p, c = images.shape[:2]
    out = np.zeros((p, c, h, w), np.float64)
    seen = np.ones((h, w), bool)
    sat_any = np.zeros((h, w), bool)
    for i in range(p):
        for k in range(c):
            vals, ok = to_slm_grid(images[i, k], geometry, s.panel_hw, s.pitch_m)
            sat, _ = to_slm_grid(saturated[i, k].astype(np.float64), geometry, s.panel_hw,
                                 s.pitch_m)
            out[i, k] = vals[top : top + h, left : left + w]
            seen &= ok[top : top + h, left : left + w]
            sat_any |= sat[top : top + h, left : left + w] > 0
    if seen.mean() < MIN_SEEN:
        raise CaptureStopped(f"the camera sees {100 * seen.mean():.0f}% of the window: its "
                             "region of interest must hold the panel's image, as in the "
                             "calibration's capture")
    if (sat_any & seen).sum() > MAX_SATURATED * seen.sum():
        raise CaptureStopped(f"{100 * (sat_any & seen).sum() / seen.sum():.1f}% of the window "
                             "saturated: shorten devices.camera_settings.exposure_s")
    return out, seen & ~sat_any


class RemoteCapture:
    """A `Capture` served by the daemon's bench through the worker's pipe (see the module's
    docstring), for view `seq` refined with `encoder` under `calibration` (its geometry maps
    the images; its focus mapping moves the stage, in the daemon). `camera_pitch_m`: the bench
    camera's pixel pitch, where the calibration did not record it.

    `send` puts a message on the pipe; the worker's loop hands each `CaptureAnswer`'s req_id and
    reply to `deliver`. A call waits for its own reply, polling `stop` (then `Cancelled`); an error
    reply, or none within `timeout_s`, is `CaptureStopped` with the daemon's reason."""

    _ids = itertools.count(1)

    def __init__(self, send: Callable[[CaptureAsked], None], seq: int, encoder: Encoder,
                 calibration: Calibration, stop: threading.Event, *, camera_pitch_m: float,
                 frames: int = 0,
                 timeout_s: float = CAPTURE_TIMEOUT_S) -> None:
        self.send, self.seq, self.encoder, self.stop = send, seq, encoder, stop
        self.geometry = calibrated_geometry(calibration, camera_pitch_m)
        self.frames, self.timeout_s = int(frames), float(timeout_s)
        self.replies: queue.SimpleQueue[tuple[int, CaptureReply]] = queue.SimpleQueue()
        self.requests = 0

    def deliver(self, req_id: int, reply: CaptureReply) -> None:
        """A reply from the daemon (any thread)."""
        self.replies.put((req_id, reply))

    def __call__(self, grey: np.ndarray, planes_m: Sequence[float]
                 ) -> tuple[np.ndarray, np.ndarray]:
        """The bench's captures of the K subframes `grey` at `planes_m` (metres from the
        reference plane, as `Target.planes_m`), on the window: `captured_window`'s."""
        s = self.encoder.settings
        req_id = next(self._ids)
        z_m = tuple(s.z0_m + s.refocus_m + float(dz) for dz in planes_m)
        self.send(CaptureAsked(self.seq, req_id,
                               CaptureRequest(self.encoder.region, np.asarray(grey, np.uint8),
                                              z_m, self.frames)))
        self.requests += 1
        deadline = time.monotonic() + self.timeout_s
        while True:
            if self.stop.is_set():
                raise Cancelled
            if time.monotonic() > deadline:
                raise CaptureStopped(f"no captures from the daemon's bench within "
                                     f"{self.timeout_s:g} s")
            try:
                got_id, reply = self.replies.get(timeout=POLL_S)
            except queue.Empty:
                continue
            if got_id == req_id:  # an older request's late reply is dropped
                break
        if reply.error:
            raise CaptureStopped(reply.error)
        assert reply.images is not None and reply.saturated is not None
        return captured_window(reply.images, reply.saturated, self.geometry, self.encoder)
