"""Template: a camera backend. The base class validates settings, linearises with the response
curve, flags saturation, averages bursts and subtracts the dark frame."""

from __future__ import annotations

import numpy as np

from nhfd.drivers.camera import Camera, CameraSettings, ResponseCurve


class MyCamera(Camera):
    """A camera backend to fill in: open, set exposure and gain with auto modes off, grab one raw
    frame."""

    def __init__(self, settings: CameraSettings, response: ResponseCurve | None = None) -> None:
        super().__init__(settings, response=response)
        # Import the vendor library here, not at module level, and raise CameraUnavailable
        # with the pip/apt command when it is missing.

    def _do_open(self) -> None:
        raise NotImplementedError  # find the camera (by serial number, not index) and open it

    def _do_close(self) -> None:
        raise NotImplementedError

    def _apply_exposure(self, exposure_s: float) -> float:
        # Turn auto exposure OFF, set it, and return the value the camera reads back.
        raise NotImplementedError

    def _apply_gain(self, gain_db: float) -> float:
        # Turn auto gain OFF, set it, and return the value read back.
        raise NotImplementedError

    def _grab(self) -> np.ndarray:
        # One raw frame as integers at settings.bit_depth: [H, W] (mono) or [H, W, 3] in R, G, B
        # order (not BGR). Prefer raw or mono formats; no auto white balance, no sharpening.
        raise NotImplementedError
