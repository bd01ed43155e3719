"""Cameras: a base class that returns linear float32 images, and the real backends.

The base class holds what every camera needs for measurement (docs/design.md, "The hardware":
Camera): explicit exposure and gain with auto modes off, the camera's response curve applied
inverse so that values are *linear* in irradiance, saturation flagged rather than hidden, burst
averaging, and a stored dark frame subtracted from later captures. A backend only opens the
device, sets exposure and gain and returns one raw frame.

Values are fractions of full scale: 1.0 is the linear value of the highest raw level (a saturated
pixel). Mono captures are `[H, W]`, colour captures channel-first `[3, H, W]` in R, G, B order
(docs/physics.md's convention, "Units and names").

Backends here: `OpenCVCamera` (any V4L2/UVC camera through OpenCV's `VideoCapture`) and
`GenICamCamera` (USB3 Vision / GigE Vision through `harvesters` and the vendor's GenTL producer
`.cti`). Both import their library only when constructed, so this module needs neither, and it
imports no torch: the simulated camera lives in `nhfd.drivers.simcamera`.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.device_settings import COLOURS, CameraSettings

from .device import Device
from .errors import DeviceError

log = logging.getLogger(__name__)


class CameraUnavailable(DeviceError):
    """The camera's backend library or device is missing; the message says what to install/do."""


class CameraTimeout(DeviceError):
    """No frame arrived within exposure + frame_timeout_s (a hung camera, a pulled cable)."""


class ResponseCurve:
    """The camera's response: `linear[level]` is the linear signal (fraction of full scale) that
    produces raw level `level`. Non-decreasing; `linear[-1]` is 1 (the top level = saturation)."""

    def __init__(self, linear: Any) -> None:
        table = np.asarray(linear, dtype=np.float64).reshape(-1)
        if table.size < 2 or not np.isfinite(table).all():
            raise ValueError("response curve needs >= 2 finite values")
        if np.any(np.diff(table) < 0):
            raise ValueError("response curve must not decrease with raw level")
        if table[0] < 0 or not math.isclose(table[-1], 1.0, rel_tol=1e-9):
            raise ValueError("response curve must start >= 0 and end at 1 (full scale)")
        self.linear = table
        self.linear.setflags(write=False)

    @classmethod
    def gamma(cls, gamma: float, bit_depth: int) -> ResponseCurve:
        """raw / max = linear ** (1 / gamma), so linear = (raw / max) ** gamma."""
        if not (math.isfinite(gamma) and gamma > 0):
            raise ValueError(f"response gamma = {gamma!r}: must be > 0")
        levels = 2**bit_depth
        return cls((np.arange(levels) / (levels - 1)) ** gamma)

    @property
    def max_level(self) -> int:
        """The top raw level (saturation): the table's length less one."""
        return self.linear.size - 1

    def to_linear(self, raw: np.ndarray) -> np.ndarray:
        """Raw integer levels -> linear float32 (the inverse of the camera's response)."""
        return self.linear.astype(np.float32)[raw]

    def to_raw(self, linear: np.ndarray) -> np.ndarray:
        """Linear signal -> raw level (float, unrounded): the camera's forward response, for a
        simulator. Values above full scale map to the top level."""
        levels = np.arange(self.linear.size, dtype=np.float64)
        return np.interp(np.asarray(linear, np.float64), self.linear, levels)


@dataclass(frozen=True)
class Capture:
    """One capture: `image` linear float32 ([H, W] or [3, H, W], fractions of full scale),
    `saturated` (bool, same shape: at the top raw level in any frame of the burst)."""

    image: np.ndarray
    saturated: np.ndarray
    exposure_s: float
    gain_db: float
    frames: int
    dark_subtracted: bool

    @property
    def saturated_fraction(self) -> float:
        """The fraction of pixels saturated in any frame of the burst (0 for an empty image)."""
        return float(self.saturated.mean()) if self.saturated.size else 0.0

    @property
    def any_saturated(self) -> bool:
        """Whether any pixel saturated in any frame of the burst."""
        return bool(self.saturated.any())

    def of_colour(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """The image and saturation `[H, W]` a colour `c` (0 R, 1 G, 2 B) lights: a mono
        camera's whole frame, a colour camera's own channel (channel-first)."""
        if self.image.ndim == 2:
            return self.image, self.saturated
        return self.image[c], self.saturated[c]


def colour_planes(n_planes: int, n_subframes: int, *, at_plane: Callable[[int], None],
                  before_colour: Callable[[str], None], show: Callable[[int, str], None],
                  light: Callable[[str, bool], None], capture: Callable[[], Capture]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The captures of camera-in-the-loop and the capture-mode tiers, one sequence for the
    daemon's job and the offline loop: for each plane (`at_plane(i)`: the focus there), each
    colour in COLOURS: `before_colour(name)` (raises to stop: the lasers disarmed, the view
    changed), subframe 0 shown as that colour's pattern (`show(k, name)`, settled), the diode
    switched on (`light(name, True)`), each of the `n_subframes` shown and captured in turn,
    and the diode off again on every way out. Returns the subframes' mean image `[P, C, H, W]`
    float32 (one exposure spanning K flips) and where any saturated `[P, C, H, W]` bool."""
    images: list[list[np.ndarray]] = []
    saturated: list[list[np.ndarray]] = []
    for i in range(n_planes):
        at_plane(i)
        images.append([])
        saturated.append([])
        for c, name in enumerate(COLOURS):
            before_colour(name)
            show(0, name)  # the pattern is up before the light
            light(name, True)
            try:
                shots = []
                for k in range(n_subframes):
                    if k:
                        show(k, name)
                    shots.append(capture().of_colour(c))
            finally:
                light(name, False)
            images[-1].append(np.mean([np.asarray(im, np.float32) for im, _ in shots], axis=0))
            saturated[-1].append(np.any([np.asarray(m, bool) for _, m in shots], axis=0))
    return np.asarray(images, np.float32), np.asarray(saturated, bool)


class Camera(Device, ABC):
    """A camera that returns linear float32 images.

    Use it as a context manager (or call open/close). Exposure and gain are applied on open and
    whenever set; changing either drops the stored dark frame, which belongs to one setting.
    A backend implements `_do_open`, `_do_close`, `_apply_exposure`, `_apply_gain` and
    `_grab` (one raw frame, integers, [H, W] or [H, W, 3] R, G, B).
    """

    def __init__(
        self, settings: CameraSettings | None = None, *, response: ResponseCurve | None = None
    ) -> None:
        self.settings = settings or CameraSettings()
        self.response = response or ResponseCurve.gamma(
            self.settings.response_gamma, self.settings.bit_depth
        )
        self._exposure_s = self.settings.exposure_s
        self._gain_db = self.settings.gain_db
        self._dark: np.ndarray | None = None
        self._is_open = False
        # The trigger input's wire from the SLM's flip output, or the exposure-active output's
        # wire to the host (drivers/trigger.py), if wired.
        self.trigger: Any = None

    # -- lifecycle ---------------------------------------------------------------------------

    def open(self) -> Camera:
        """Open the backend and apply the exposure and gain with auto modes off (closed again if
        that fails); a no-op when open."""
        if not self._is_open:
            self._do_open()
            self._is_open = True
            try:
                # Explicit values on every open: a camera may come up in auto modes or with the
                # last user's settings.
                self.set_exposure(self._exposure_s)
                self.set_gain(self._gain_db)
            except BaseException:
                self.close()
                raise
        return self

    def close(self) -> None:
        """Close the backend; a no-op when closed."""
        if self._is_open:
            self._is_open = False
            self._do_close()

    @property
    def is_open(self) -> bool:
        """Whether the camera is open."""
        return self._is_open

    # -- settings ----------------------------------------------------------------------------

    @property
    def exposure_s(self) -> float:
        """The exposure in use (s), as the camera read it back."""
        return self._exposure_s

    @property
    def gain_db(self) -> float:
        """The gain in use (dB), as the camera read it back."""
        return self._gain_db

    def set_exposure(self, exposure_s: float) -> float:
        """Set the exposure (s); returns the value the camera actually uses."""
        low, high = self._exposure_limits_s()
        if not (math.isfinite(exposure_s) and low <= exposure_s <= high):
            raise ValueError(f"{self.name}: exposure_s = {exposure_s!r}: must be in "
                             f"[{low:g}, {high:g}]")
        actual = self._apply_exposure(exposure_s) if self._is_open else exposure_s
        if actual != self._exposure_s:
            self._dark = None
        self._exposure_s = actual
        return actual

    def set_gain(self, gain_db: float) -> float:
        """Set the gain (dB); returns the value the camera actually uses."""
        if not (math.isfinite(gain_db) and 0 <= gain_db <= 48):
            raise ValueError(f"{self.name}: gain_db = {gain_db!r}: must be in [0, 48]")
        actual = self._apply_gain(gain_db) if self._is_open else gain_db
        if actual != self._gain_db:
            self._dark = None
        self._gain_db = actual
        return actual

    # -- capture -----------------------------------------------------------------------------

    @property
    def dark_frame(self) -> np.ndarray | None:
        """The stored dark frame (linear) for the current exposure and gain, or None."""
        return self._dark

    def capture_dark(self, frames: int | None = None) -> np.ndarray:
        """Capture and store the dark frame. The caller makes it dark (lasers off, shutter
        closed): the camera cannot tell."""
        cap = self.capture(frames, subtract_dark=False)
        self._dark = cap.image
        return cap.image

    def clear_dark(self) -> None:
        """Drop the stored dark frame."""
        self._dark = None

    def capture(self, frames: int | None = None, *, subtract_dark: bool = True) -> Capture:
        """Average a burst of `frames` (default: settings.burst_frames) linearised frames and
        subtract the stored dark frame when there is one and `subtract_dark` is set."""
        if not self._is_open:
            raise DeviceError(f"{self.name}: not open")
        n = self.settings.burst_frames if frames is None else int(frames)
        if n < 1:
            raise ValueError(f"frames = {frames!r}: must be >= 1")
        total: np.ndarray | None = None
        saturated: np.ndarray | None = None
        if self.trigger is not None and self.trigger.flip_triggers_exposure:
            # Armed: the burst's first exposure starts on the flip of the frame last written
            # (plus the trigger delay); TriggerTimeout when the edge never comes.
            self.trigger.wait_exposure_start()
        for _ in range(n):
            raw = self._checked(self._grab())
            # Linearise each frame before averaging: the mean of gamma-encoded values is biased.
            lin = self.response.to_linear(raw)
            top = raw >= self.response.max_level
            total = lin.astype(np.float64) if total is None else total + lin
            saturated = top if saturated is None else saturated | top
        assert total is not None and saturated is not None
        image = (total / n).astype(np.float32)
        dark = subtract_dark and self._dark is not None
        if dark:
            image = image - self._dark
        return Capture(image, saturated, self._exposure_s, self._gain_db, n, dark)

    def _checked(self, raw: np.ndarray) -> np.ndarray:
        """Validate a backend's raw frame and put it channel-first for colour."""
        a = np.asarray(raw)
        if not np.issubdtype(a.dtype, np.integer):
            raise DeviceError(f"{self.name}: raw frame dtype {a.dtype}: expected integers")
        mono = self.settings.channels == "mono"
        if (a.ndim != 2) if mono else (a.ndim != 3 or a.shape[2] != 3):
            want = "[H, W]" if mono else "[H, W, 3]"
            raise DeviceError(f"{self.name}: raw frame shape {a.shape}: expected {want}")
        if a.size and (a.min() < 0 or a.max() > self.response.max_level):
            raise DeviceError(f"{self.name}: raw levels [{a.min()}, {a.max()}] exceed "
                              f"{self.response.max_level} (check bit_depth)")
        return a if mono else np.ascontiguousarray(a.transpose(2, 0, 1))

    # -- backend hooks -----------------------------------------------------------------------

    def _exposure_limits_s(self) -> tuple[float, float]:
        return (1e-6, 60.0)

    @abstractmethod
    def _do_open(self) -> None: ...

    @abstractmethod
    def _do_close(self) -> None: ...

    @abstractmethod
    def _apply_exposure(self, exposure_s: float) -> float:
        """Turn auto exposure off, set the exposure, return the value read back."""

    @abstractmethod
    def _apply_gain(self, gain_db: float) -> float:
        """Turn auto gain off, set the gain, return the value read back."""

    @abstractmethod
    def _grab(self) -> np.ndarray:
        """One raw frame: integers, [H, W] (mono) or [H, W, 3] (R, G, B)."""


# ------------------------------------------------------------------------------ OpenCV / V4L2

# V4L2 exposure_time_absolute counts 100 us units; OpenCV's V4L2 backend passes them through.
V4L2_EXPOSURE_UNIT_S = 1e-4
# CAP_PROP_AUTO_EXPOSURE value for manual mode with OpenCV's V4L2 backend (V4L2_EXPOSURE_MANUAL).
V4L2_AUTO_EXPOSURE_MANUAL = 1


class OpenCVCamera(Camera):
    """Any V4L2/UVC camera through OpenCV's VideoCapture (opencv-contrib-python-headless)."""

    def __init__(
        self, settings: CameraSettings | None = None, *, response: ResponseCurve | None = None
    ) -> None:
        super().__init__(settings, response=response)
        try:
            import cv2
        except ImportError:
            raise CameraUnavailable(
                "OpenCVCamera needs OpenCV, a dependency of nhfd: pip install "
                "opencv-contrib-python-headless"
            ) from None
        self._cv2 = cv2
        self._cap: Any = None

    def _do_open(self) -> None:
        cv2 = self._cv2
        dev = self.settings.device
        source: int | str = int(dev) if dev.isdigit() else dev
        cap = cv2.VideoCapture(source, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise CameraUnavailable(f"{self.name}: cannot open {dev!r} (V4L2)")
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        # Keep raw 8-bit values where the driver allows; colour frames still arrive as BGR.
        cap.set(cv2.CAP_PROP_AUTO_WB, 0)
        self._cap = cap

    def _do_close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def _apply_exposure(self, exposure_s: float) -> float:
        cv2 = self._cv2
        self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_AUTO_EXPOSURE_MANUAL)
        self._cap.set(cv2.CAP_PROP_EXPOSURE, exposure_s / V4L2_EXPOSURE_UNIT_S)
        got = self._cap.get(cv2.CAP_PROP_EXPOSURE)
        return float(got) * V4L2_EXPOSURE_UNIT_S if got > 0 else exposure_s

    def _apply_gain(self, gain_db: float) -> float:
        cv2 = self._cv2
        self._cap.set(cv2.CAP_PROP_GAIN, gain_db)
        got = self._cap.get(cv2.CAP_PROP_GAIN)
        return float(got) if got >= 0 else gain_db

    def _grab(self) -> np.ndarray:
        # Frames queued before a settings change would be stale: drop a few.
        for _ in range(self.settings.discard_frames):
            self._cap.grab()
        ok, frame = self._cap.read()
        if not ok or frame is None:
            raise DeviceError(f"{self.name}: no frame from {self.settings.device!r}")
        if frame.ndim == 3:
            rgb = frame[..., ::-1]  # OpenCV delivers BGR
            return rgb.mean(axis=2).round().astype(frame.dtype) \
                if self.settings.channels == "mono" else rgb
        return frame


# ------------------------------------------------------------------------- GenICam / harvesters


class GenICamCamera(Camera):
    """A USB3 Vision / GigE Vision camera through `harvesters` and the vendor's GenTL `.cti`."""

    def __init__(
        self, settings: CameraSettings | None = None, *, response: ResponseCurve | None = None
    ) -> None:
        super().__init__(settings, response=response)
        cti = self.settings.cti_path
        if not cti:
            raise CameraUnavailable("GenICamCamera needs cti_path: the vendor's GenTL producer "
                                    "(.cti file, e.g. from FLIR's Spinnaker SDK)")
        if not Path(cti).is_file():
            raise CameraUnavailable(f"GenICamCamera: cti_path {cti!r} is not a file")
        try:
            from harvesters.core import Harvester
        except ImportError:
            raise CameraUnavailable("GenICamCamera needs harvesters: pip install harvesters") \
                from None
        self._harvester_cls = Harvester
        self._h: Any = None
        self._ia: Any = None

    def _do_open(self) -> None:
        h = self._harvester_cls()
        h.add_file(self.settings.cti_path)
        h.update()
        if not h.device_info_list:
            h.reset()
            raise CameraUnavailable(f"{self.name}: no GenICam device through "
                                    f"{self.settings.cti_path}")
        serial = self.settings.serial_number
        self._h = h
        try:
            self._ia = h.create({"serial_number": serial} if serial else 0)
            nodes = self._ia.remote_device.node_map
            if self.settings.pixel_format:
                nodes.PixelFormat.value = self.settings.pixel_format
            self._ia.start()
        except BaseException:
            self._do_close()
            raise

    def _do_close(self) -> None:
        if self._ia is not None:
            try:
                self._ia.stop()
            finally:
                self._ia.destroy()
                self._ia = None
        if self._h is not None:
            self._h.reset()
            self._h = None

    def _apply_exposure(self, exposure_s: float) -> float:
        nodes = self._ia.remote_device.node_map
        nodes.ExposureAuto.value = "Off"
        nodes.ExposureTime.value = exposure_s * 1e6  # GenICam SFNC: microseconds
        return float(nodes.ExposureTime.value) * 1e-6

    def _apply_gain(self, gain_db: float) -> float:
        nodes = self._ia.remote_device.node_map
        nodes.GainAuto.value = "Off"
        nodes.Gain.value = gain_db  # SFNC: dB
        return float(nodes.Gain.value)

    def _grab(self) -> np.ndarray:
        timeout = self._exposure_s + self.settings.frame_timeout_s
        with self._ia.fetch(timeout=timeout) as buffer:
            comp = buffer.payload.components[0]
            per_pixel = int(comp.num_components_per_pixel)
            shape = (comp.height, comp.width) if per_pixel == 1 else \
                (comp.height, comp.width, per_pixel)
            # Copy: the buffer goes back to the producer's queue when the block ends.
            return np.array(comp.data.reshape(shape), copy=True)
