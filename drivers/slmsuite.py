"""Vendor SLMs and cameras through slmsuite (HOLOEYE, Meadowlark, Santec, Hamamatsu, Thorlabs,
Texas Instruments SLMs; Basler, FLIR, Allied Vision, Thorlabs and other cameras).

`[devices] slm = "slmsuite"` / `camera = "slmsuite"` with `[devices.slmsuite] slm_class` /
`camera_class` = "module:Class" and their keyword arguments (`slm_kwargs`, `camera_kwargs`).
slmsuite is imported only when one of these backends opens (`pip install nhfd[slmsuite]`).

SLM: nhfd's grey frame goes to the slmsuite SLM as integer data, which slmsuite's `set_phase`
passes to the hardware (`_set_phase_hw(display)`) as it is: slmsuite's own phase-to-grey
conversion, LUT and wavefront correction are bypassed, so nhfd's calibrated curves stay the only
ones. A monochrome slmsuite SLM shows one channel of nhfd's [H, W, 3] frame (`channel`). On open
the device's size and pitch are checked against `[slm]` and its bit depth must be 8 (nhfd codes
256 grey levels). nhfd's `settle_ms` is the settle time; slmsuite's is not slept.

Camera: raw frames from slmsuite's `get_image` (no slmsuite averaging or HDR: nhfd's base class
averages bursts, linearises with the response curve, subtracts the dark frame and flags pixels at
the device's top level, 2**bitdepth - 1, as saturated). Exposure is seconds on both sides. Gain:
slmsuite has no common gain call; a camera with a numeric `gain` attribute (slmsuite's simulated
camera: a factor on the counts) gets 10**(gain_db / 20) times its configured gain, any other
accepts only 0 dB. A camera class whose constructor takes `slm` (slmsuite's simulated camera,
which images the simulated SLM's far field) gets the slmsuite SLM of the `slmsuite` SLM backend.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from nhfd.device_settings import COLOURS, CameraSettings, SLMOutputSettings, SlmsuiteSettings

from .camera import Camera, ResponseCurve
from .errors import DeviceError
from .slm import GREY_LEVELS, SLM, SLMHealth

log = logging.getLogger(__name__)

class SlmsuiteUnavailable(DeviceError):
    """slmsuite, or the configured class, cannot be loaded; the message says what to install."""


# Relative tolerance of the pitch cross-check (a vendor's pitch is given to a few digits).
PITCH_REL_TOL = 1e-3


def load_class(spec: str, kind: str) -> type:
    """"module:Class" -> the class; SlmsuiteUnavailable saying what is missing."""
    module_name, _, name = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise SlmsuiteUnavailable(
            f"devices.slmsuite.{kind}_class = {spec!r}: cannot import {module_name} ({exc}); "
            "pip install 'nhfd[slmsuite]' (and the vendor's SDK for real hardware)") from None
    cls = getattr(module, name, None)
    if not isinstance(cls, type):
        raise SlmsuiteUnavailable(f"devices.slmsuite.{kind}_class = {spec!r}: {module_name} "
                                  f"has no class {name}")
    return cls


def _class_name(spec: str, given: Any) -> str:
    return spec.partition(":")[2] if given is None else type(given).__name__


def _kwargs(raw: dict[str, Any]) -> dict[str, Any]:
    # TOML arrays arrive as lists; slmsuite takes tuples for (width, height) and pitches.
    return {k: tuple(v) if isinstance(v, list) else v for k, v in raw.items()}


class SlmsuiteSLM(SLM):
    """Any slmsuite SLM, shown nhfd's grey levels unchanged. `device` (tests) is an slmsuite SLM
    made by the caller: it is used instead of `suite.slm_class` and not closed here."""

    def __init__(self, width_px: int, height_px: int, settings: SLMOutputSettings | None = None,
                 suite: SlmsuiteSettings | None = None, *, pitch_um: float | None = None,
                 device: Any = None, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(width_px, height_px, settings, clock=clock)
        self.suite = suite or SlmsuiteSettings()
        self.pitch_um = pitch_um
        self._given = device
        self.device: Any = None  # the slmsuite SLM while open
        self._channel = COLOURS.index(self.suite.channel)

    @property
    def name(self) -> str:
        """"SlmsuiteSLM(<slmsuite class>)", for messages."""
        return f"SlmsuiteSLM({_class_name(self.suite.slm_class, self._given)})"

    def _do_open(self) -> None:
        device = self._given
        if device is None:
            cls = load_class(self.suite.slm_class, "slm")
            device = cls(**_kwargs(self.suite.slm_kwargs))
        try:
            self._check(device)
        except BaseException:
            if self._given is None:
                device.close()
            raise
        self.device = device

    def _check(self, device: Any) -> None:
        h, w = (int(v) for v in device.shape)
        if (h, w) != (self.height_px, self.width_px):
            raise ValueError(
                f"{self.name}: the slmsuite SLM is {w} x {h} px but [slm] width_px x height_px "
                f"is {self.width_px} x {self.height_px}: make them agree")
        if self.pitch_um is not None:
            pitch = [float(v) for v in np.ravel(device.pitch_um)]
            if any(not math.isclose(p, self.pitch_um, rel_tol=PITCH_REL_TOL) for p in pitch):
                raise ValueError(
                    f"{self.name}: the slmsuite SLM's pitch_um is {pitch} but [slm] pitch_um is "
                    f"{self.pitch_um:g}: make them agree")
        if int(device.bitdepth) != 8:
            raise ValueError(f"{self.name}: the slmsuite SLM has bitdepth {device.bitdepth}: "
                             f"nhfd codes {GREY_LEVELS} grey levels (bitdepth 8)")

    def _do_close(self) -> None:
        device, self.device = self.device, None
        if device is not None and device is not self._given:
            device.close()

    def _write(self, rgb: np.ndarray) -> None:
        grey = np.ascontiguousarray(rgb[..., self._channel])
        # Integer data of the display's dtype: slmsuite hands it to _set_phase_hw unchanged (no
        # phase-to-grey, no LUT, no wavefront correction); nhfd owns the settle time.
        self.device.set_phase(grey, settle=False)

    def _health(self) -> SLMHealth:
        if self.device is None:
            return SLMHealth(False, "not open")
        # slmsuite has no common output check: a written frame is all it reports.
        return SLMHealth(True, f"slmsuite {type(self.device).__name__} (output not checked)")


class SlmsuiteCamera(Camera):
    """Any slmsuite camera, returning nhfd's linear captures. `slm` is the `SlmsuiteSLM` a
    simulated slmsuite camera images; `device` (tests) an slmsuite camera made by the caller."""

    def __init__(self, settings: CameraSettings | None = None,
                 suite: SlmsuiteSettings | None = None, *, slm: SlmsuiteSLM | None = None,
                 device: Any = None, response: ResponseCurve | None = None) -> None:
        super().__init__(settings, response=response)
        if self.settings.channels != "mono":
            raise ValueError(f"camera_settings.channels = {self.settings.channels!r}: slmsuite "
                             "cameras deliver one channel; use 'mono'")
        self.suite = suite or SlmsuiteSettings()
        self._slm = slm
        self._given = device
        self._own_response = response is not None
        self._base_gain: float | None = None  # a simulated camera's configured gain factor
        self.device: Any = None

    @property
    def name(self) -> str:
        """"SlmsuiteCamera(<slmsuite class>)", for messages."""
        return f"SlmsuiteCamera({_class_name(self.suite.camera_class, self._given)})"

    def _do_open(self) -> None:
        device = self._given
        if device is None:
            cls = load_class(self.suite.camera_class, "camera")
            kwargs = _kwargs(self.suite.camera_kwargs)
            if "slm" in inspect.signature(cls).parameters and "slm" not in kwargs:
                if self._slm is None or self._slm.device is None:
                    raise DeviceError(
                        f"{self.suite.camera_class} images an slmsuite SLM: set devices.slm = "
                        "'slmsuite' (opened before the camera)")
                kwargs["slm"] = self._slm.device
            device = cls(**kwargs)
        self.device = device
        bitdepth = int(device.bitdepth)
        if not self._own_response and self.response.max_level != 2**bitdepth - 1:
            # The device's ADC depth decides what a saturated pixel is.
            self.response = ResponseCurve.gamma(self.settings.response_gamma, bitdepth)
        gain = getattr(device, "gain", None)
        self._base_gain = float(gain) if isinstance(gain, int | float) else None

    def _do_close(self) -> None:
        device, self.device = self.device, None
        if device is not None and device is not self._given:
            device.close()

    def _exposure_limits_s(self) -> tuple[float, float]:
        bounds = getattr(self.device, "exposure_bounds_s", None)
        if bounds is not None:
            return float(bounds[0]), float(bounds[1])
        return super()._exposure_limits_s()

    def _apply_exposure(self, exposure_s: float) -> float:
        return float(self.device.set_exposure(exposure_s))

    def _apply_gain(self, gain_db: float) -> float:
        if self._base_gain is None:
            if gain_db != 0:
                raise ValueError(f"{self.name}: gain_db = {gain_db!r}: this slmsuite camera has "
                                 "no gain control nhfd knows; must be 0")
            return 0.0
        self.device.gain = self._base_gain * 10 ** (gain_db / 20)
        return 20 * math.log10(self.device.gain / self._base_gain)

    def _grab(self) -> np.ndarray:
        try:
            # slmsuite adds the exposure to timeout_s, as camera_settings.frame_timeout_s means.
            raw = self.device.get_image(timeout_s=self.settings.frame_timeout_s,
                                        averaging=False, hdr=False)
        except Exception as exc:
            raise DeviceError(f"{self.name}: get_image failed: {type(exc).__name__}: {exc}") \
                from exc
        return np.asarray(raw)
