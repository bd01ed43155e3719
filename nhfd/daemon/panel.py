"""The panel: what the SLM shows, and the one place in the daemon that changes it.

Four things take turns on the panel:
  a view frame          the frame worker's newest frame, the blank around its coded region,
                        in the colour mode (`show_view`);
  the blank             the zero-amplitude pattern: at start and close, on `blank`, when the SLM's
                        output comes back, after a crashed frame worker (`blank`);
  a calibration pattern `show_pattern`, until the next set_view or blank (`resume`);
  a capture sequence    capture mode's one colour at a time (`hold` + `show_colour`, `resume`).
While a calibration pattern or a capture sequence owns the panel it is `held`: view frames are
still computed and reported, but they do not reach the SLM.

The blank is `nhfd.spec.zero_pattern` through the curves frames are coded with: the active
calibration's measured curves and sign, else the configured ones. So the blank, the panel around
every view frame and the coder's zero are one pattern (tests/daemon/test_zero_pattern.py).

Two readings of the same state: `current`, what the daemon puts up (status "display"), and
`showing`, what the SLM was last sent (status "devices.slm.showing").
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import Any, Protocol

import numpy as np

from nhfd import spec
from nhfd.calibration import Calibration, CalibrationStore, panel_coding
from nhfd.config import Config

from .colour import panel_for_mode

log = logging.getLogger("nhfd.daemon.panel")


class PanelDevices(Protocol):
    """What the panel uses of the bench: its SLM (None when there is none) and why there is
    none (`errors["slm"]`)."""

    slm: Any
    errors: dict[str, str | None]


def coding_calibration(calibration: CalibrationStore) -> Calibration | None:
    """The calibration frames are coded with, or None. One that cannot be loaded (the daemon
    refuses to start on one, so this is a file gone bad since) counts as none here: the panel
    must still be blanked."""
    try:
        return calibration.active()
    except ValueError as exc:
        log.warning("blank pattern from the configured phase curves: %s", exc)
        return None


def blank_pattern(config: Config, cal: Calibration | None) -> np.ndarray:
    """The blank of the whole panel ([3, H, W] uint8) under `cal` (None: the configured
    curves); see `nhfd.spec.zero_pattern`."""
    s = config.slm
    return spec.zero_pattern((s.height_px, s.width_px), *panel_coding(config.slm, cal))


class Panel:
    """What the SLM shows, and the one way to change it (see the module's docstring)."""

    def __init__(self, config: Config, devices: PanelDevices,
                 calibration: CalibrationStore) -> None:
        """`config`: the panel's size and curves (`[slm]`) and the colour mode
        (`[daemon.frames]`). `devices`: the SLM it drives and why there is none (the bench).
        `calibration`: the active calibration, whose curves code the blank."""
        self.config = config
        self.calibration = calibration
        self.devices = devices
        self.current = "blank"  # status "display"
        self.showing = "nothing"  # what the SLM was last sent
        self.pattern: str | None = None  # the calibration pattern up, until set_view or blank
        self._capturing = False  # a capture sequence owns the panel (`hold`)
        self._blank: np.ndarray | None = None
        self._blank_calibration: Calibration | None = None  # the one `_blank` was coded with

    @property
    def held(self) -> bool:
        """View frames do not reach the SLM: a calibration pattern or a capture sequence owns
        the panel."""
        return self._capturing or self.pattern is not None

    @property
    def vsync_detail(self) -> str:
        """How the SLM paces frames to its refresh, when it says (the framebuffer's
        FBIO_WAITFORVSYNC, or why not); "" otherwise."""
        return str(getattr(self.devices.slm, "vsync_detail", "") or "")

    def blank_frame(self) -> np.ndarray:
        """The blank of the coding in use, rebuilt when a calibration is swapped in: shown by
        `blank`, and the panel around every view frame."""
        # Called for every frame: the active calibration is one object per file version, so
        # its identity says whether the pattern must be rebuilt (no curves built per frame).
        cal = coding_calibration(self.calibration)
        if self._blank is None or cal is not self._blank_calibration:
            self._blank, self._blank_calibration = blank_pattern(self.config, cal), cal
        return self._blank

    def _slm(self) -> Any:
        slm = self.devices.slm
        if slm is None:
            raise RuntimeError(self.devices.errors["slm"] or "no SLM configured")
        return slm

    def blank(self) -> None:
        """The blank on the panel; it ends a calibration pattern."""
        self._slm().show(self.blank_frame())
        self.current = self.showing = "blank"
        self.pattern = None

    def show_view(self, frame: np.ndarray, seq: int) -> np.ndarray:
        """View `seq`'s full-panel frame ([3, H, W] uint8) in the colour mode; it reaches the
        SLM unless the panel is held. Returns the frame as shown (what `resume` shows again);
        raises what the SLM raises. FrameLink's one way onto the panel."""
        c = self.config.daemon.frames
        frame = panel_for_mode(frame, c.colour_mode, c.single_colour)
        if self.devices.slm is not None and not self.held:
            self.devices.slm.show(frame)
            self.showing = f"view {seq}"
        if self.pattern is None:  # the pattern stays what the daemon shows until it ends
            self.current = f"view {seq}"
        return frame

    def show_pattern(self, frame: np.ndarray, name: str) -> None:
        """A calibration frame ([3, H, W] uint8, the panel's size) in the colour mode, instead
        of the view until the next set_view or blank."""
        c = self.config.daemon.frames
        self._slm().show(panel_for_mode(frame, c.colour_mode, c.single_colour))
        self.showing = f"pattern {name}"
        self.current = f"calibration pattern {name}"
        self.pattern = name

    @contextlib.contextmanager
    def hold(self) -> Iterator[None]:
        """A capture sequence owns the panel meanwhile: a view arriving cannot replace the
        colour's pattern under the camera."""
        self._capturing = True
        try:
            yield
        finally:
            self._capturing = False

    def show_colour(self, frame: np.ndarray, colour: str) -> None:
        """Capture mode: `colour`'s pattern of `frame` in every channel, settled."""
        self._slm().show(panel_for_mode(frame, "single", colour), wait_settled=True)
        self.showing = f"capture: {colour} pattern"

    def resume(self, last_view: np.ndarray | None, seq: int) -> None:
        """After a calibration pattern or a capture sequence: the last view frame again (view
        `seq`), or the blank when there is none."""
        self.pattern = None
        if last_view is not None and self.devices.slm is not None:
            self.devices.slm.show(last_view)
            self.current = self.showing = f"view {seq}"
        else:
            self.blank()

    def output_lost(self) -> None:
        """The SLM's output is gone: the panel shows nothing the daemon computed."""
        self.current = "nothing (SLM output lost)"
        self.showing = "nothing (output lost)"
