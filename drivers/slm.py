"""SLM output: a base class that validates and quantises frames, and the simulated SLM.

`show(frame)` takes grey levels shaped [H, W] (the same pattern in all three colour channels, the
usual phase frame) or [3, H, W] / [1, H, W] (R, G, B patterns, one per channel), as uint8 or any
array of values in [0, 255] (floats are rounded to the nearest level; anything outside, NaN, or a
wrong shape is refused before the panel changes). The base class checks the output's health
before writing (a framebuffer write does not fail on an unplugged cable), keeps the last frame,
and knows when the liquid crystal has settled.

A backend implements `_write(rgb)` with rgb a C-contiguous uint8 array [H, W, 3] in R, G, B
order, plus `_health()` and optionally `_before_write()` (a wait for the vertical blank) and the
`Device` hooks `_do_open()` / `_do_close()`.
"""

from __future__ import annotations

import logging
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.device_settings import SLMOutputSettings

from .device import Device
from .errors import DeviceError

log = logging.getLogger(__name__)

# 8-bit panels. The same fact is nhfd.optics.dpac.GREY_LEVELS; it is not imported from there
# because that would pull torch into every SLM backend (framebuffer, window).
GREY_LEVELS = 256


class SLMOutputLost(DeviceError):
    """The SLM's output is gone (cable unplugged, output disabled): nothing reaches the panel."""


@dataclass(frozen=True)
class SLMHealth:
    """Whether the output reaches the panel, and why not (or what it is)."""

    ok: bool
    detail: str


def to_rgb(frame: Any, height_px: int, width_px: int) -> np.ndarray:
    """Validate and quantise a grey frame -> uint8 [H, W, 3] (R, G, B), C-contiguous."""
    a = np.asarray(frame)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or a.shape[0] not in (1, 3) or a.shape[1:] != (height_px, width_px):
        raise ValueError(
            f"SLM frame shape {np.shape(frame)}: expected [{height_px}, {width_px}] or "
            f"[1 or 3, {height_px}, {width_px}]"
        )
    if a.dtype == np.uint8:
        grey = a
    elif np.issubdtype(a.dtype, np.integer) or a.dtype == np.bool_:
        if a.size and (a.min() < 0 or a.max() > GREY_LEVELS - 1):
            raise ValueError(f"SLM grey levels span [{a.min()}, {a.max()}]: must be in [0, 255]")
        grey = a.astype(np.uint8)
    elif np.issubdtype(a.dtype, np.floating):
        if not np.isfinite(a).all():
            raise ValueError("SLM frame contains NaN or Inf")
        rounded = np.rint(a)
        if a.size and (rounded.min() < 0 or rounded.max() > GREY_LEVELS - 1):
            raise ValueError(
                f"SLM grey levels span [{a.min():g}, {a.max():g}]: must round into [0, 255]"
            )
        grey = rounded.astype(np.uint8)
    else:
        raise ValueError(f"SLM frame dtype {a.dtype}: expected integers or floats")
    return np.ascontiguousarray(np.broadcast_to(grey, (3, height_px, width_px)).transpose(1, 2, 0))


class SLM(Device, ABC):
    """A phase SLM of width_px x height_px driven with 8-bit grey levels per colour channel."""

    # What `status` says of the backend's vertical-blank synchronisation ("": the backend does
    # not say; the framebuffer asks its driver for FBIO_WAITFORVSYNC at open).
    vsync_detail: str = ""

    def __init__(
        self,
        width_px: int,
        height_px: int,
        settings: SLMOutputSettings | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if width_px < 1 or height_px < 1:
            raise ValueError(f"SLM geometry {width_px} x {height_px}: must be positive")
        self.width_px = width_px
        self.height_px = height_px
        self.settings = settings or SLMOutputSettings()
        self._clock = clock
        self._last: np.ndarray | None = None
        # The panel's own copies of frames built in the [H, W, 3] layout, reused in turn: a
        # fresh 6 MB array per frame costs ~500 page faults (13 ms of CPU on this project's VM)
        # where a copy into memory already touched costs 0.3 ms.
        self._own: list[np.ndarray] = []
        self._own_next = 0
        self._shown_at = -float("inf")
        self._is_open = False
        # The frame-flip output's wire to the camera (drivers/trigger.py), when one is wired.
        self.trigger: Any = None

    @property
    def shape(self) -> tuple[int, int]:
        """(height_px, width_px)."""
        return self.height_px, self.width_px

    @property
    def settle_s(self) -> float:
        """Seconds from a write until a capture means anything: `settle_ms`, or 0 where the flip
        output triggers the camera's exposure."""
        # With the flip output wired to the camera, the camera's exposure waits on the flip's
        # edge (plus its trigger delay): the host sleeps no settle time.
        # (The camera's exposure-active line, "camera_exposure", says nothing of the panel: the
        # settle time stays.)
        if self.trigger is not None and self.trigger.flip_triggers_exposure:
            return 0.0
        return self.settings.settle_ms / 1000

    def open(self) -> SLM:
        """Open the backend; a no-op when open."""
        if not self._is_open:
            self._do_open()
            self._is_open = True
        return self

    def close(self) -> None:
        """Close the backend; a no-op when closed."""
        if self._is_open:
            self._is_open = False
            self._do_close()

    def show(self, frame: Any, *, wait_settled: bool = False) -> float:
        """Show a grey frame; returns the clock time at which the liquid crystal has settled."""
        if not self._is_open:
            raise DeviceError(f"{self.name}: not open")
        rgb = to_rgb(frame, self.height_px, self.width_px)
        if np.may_share_memory(rgb, frame):
            # A frame built in the [H, W, 3] layout (its [3, H, W] view) needs no transposing
            # copy; the panel still keeps a frame of its own (a plain copy, ~0.3 ms at 1080p).
            rgb = self._own_copy(rgb)
        health = self.health()
        if not health.ok:
            raise SLMOutputLost(f"{self.name}: output lost: {health.detail}")
        # Before the written stamp and the exposure gate: the vertical blank waited for here
        # is the old frame's (a flip stamped as the new frame's would start a flip-triggered
        # exposure on the old one), and the camera's exposure is not held off while it waits.
        self._before_write()
        if self.trigger is not None and self.trigger.exposure_gates_write:
            # The camera's exposure-active line: no frame changes while the sensor integrates
            # (TriggerTimeout when the line stays high).
            with self.trigger.frame_write():
                self.trigger.written(self._clock())
                self._write(rgb)
        else:
            if self.trigger is not None:
                # Before the write: a flip the write causes is later than this.
                self.trigger.written(self._clock())
            self._write(rgb)
        self._last = rgb
        self._shown_at = self._clock()
        if wait_settled:
            self.wait_settled()
        return self._shown_at + self.settle_s

    def _own_copy(self, rgb: np.ndarray) -> np.ndarray:
        """`rgb` copied into the next of `frames_kept() + 1` arrays of the panel's own, reused in
        turn: none of them is still kept (by `_last`, or a backend's history) when it is
        written again."""
        if len(self._own) < self.frames_kept() + 1:
            self._own.append(rgb.copy())
            return self._own[-1]
        out = self._own[self._own_next]
        self._own_next = (self._own_next + 1) % len(self._own)
        np.copyto(out, rgb)
        return out

    def frames_kept(self) -> int:
        """How many of the frames it was shown this SLM keeps a reference to (the last; a
        backend with a history says more)."""
        return 1

    def blank(self) -> float:
        """Show grey 0 everywhere; returns the clock time (s) at which the liquid crystal has
        settled."""
        return self.show(np.zeros(self.shape, np.uint8))

    def attach_trigger(self, line: Any) -> None:
        """Wire the frame-flip output to a camera's trigger input, or the camera's
        exposure-active output to the host (a `TriggerLine`)."""
        self.trigger = line

    def wait_settled(self) -> None:
        """Sleep until the last frame has settled (`settle_s` after it was shown)."""
        remaining = self._shown_at + self.settle_s - self._clock()
        if remaining > 0:
            time.sleep(remaining)

    @property
    def settled(self) -> bool:
        """Whether the last frame has settled."""
        return self._clock() >= self._shown_at + self.settle_s

    @property
    def last_frame(self) -> np.ndarray | None:
        """The last frame shown, [3, H, W] uint8 (R, G, B), or None."""
        return None if self._last is None else self._last.transpose(2, 0, 1).copy()

    def health(self) -> SLMHealth:
        """The backend's health (`_health`): whether frames reach the panel."""
        return self._health()

    # -- backend hooks -------------------------------------------------------------------------

    def _before_write(self) -> None:
        """Called by `show` just before the frame is stamped written and `_write` runs: where a
        backend waits for the vertical blank. Nothing by default."""

    @abstractmethod
    def _write(self, rgb: np.ndarray) -> None:
        """Put uint8 [H, W, 3] R, G, B pixels on the panel."""

    @abstractmethod
    def _health(self) -> SLMHealth: ...


class SimulatedSLM(SLM):
    """Keeps recent frames in memory; optionally writes each as PNG (settings.png_dir)."""

    def __init__(self, width_px: int, height_px: int, settings: SLMOutputSettings | None = None,
                 *, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(width_px, height_px, settings, clock=clock)
        self.frames: deque[np.ndarray] = deque(maxlen=self.settings.history_frames)
        # The clock at each recent write: how often frames reached the panel (pacing tests).
        self.written_s: deque[float] = deque(maxlen=self.settings.history_frames)
        self.count = 0
        self._plugged = True
        # (written, flipped, frame [H, W, 3]) of recent frames: the panel shows each from its
        # flip on (flip_latency_ms after the write); the simulated camera images `panel_frame()`.
        self._flips: deque[tuple[float, float, np.ndarray]] = deque(
            maxlen=self.settings.history_frames)
        self._never_flips = False

    def unplug(self) -> None:
        """Test hook: the output reads lost (`show` raises SLMOutputLost) until `replug`."""
        self._plugged = False

    def replug(self) -> None:
        """Test hook: the output is back."""
        self._plugged = True

    def never_flip(self, stuck: bool = True) -> None:
        """Test-only: frames are written but the panel never flips to them (no flip edge)."""
        self._never_flips = stuck

    def frames_kept(self) -> int:
        """Its history of recent frames (`history_frames`), each kept by reference."""
        return int(self.settings.history_frames)

    def panel_frame(self) -> np.ndarray:
        """What the panel shows now, uint8 [H, W, 3]: a copy of the last frame whose flip has
        come (grey 0, [H, W], before the first); a copy, since the panel's own arrays are
        reused once `history_frames` newer frames have come."""
        now = self._clock()
        for _, flip_s, rgb in reversed(self._flips):
            if flip_s <= now:
                return rgb.copy()
        return np.zeros(self.shape, np.uint8)

    def _write(self, rgb: np.ndarray) -> None:
        # `show` hands each backend a frame of its own: kept as is, seen as [3, H, W].
        self.frames.append(rgb.transpose(2, 0, 1))
        self.written_s.append(self._clock())
        self.count += 1
        if self.settings.png_dir:
            # matplotlib.image.imsave is what plt.imsave calls; importing it directly picks no
            # GUI backend, which a daemon must not do.
            from matplotlib import image

            out = Path(self.settings.png_dir)
            out.mkdir(parents=True, exist_ok=True)
            image.imsave(out / f"slm_{self.count:06d}.png", rgb)
        if not self._never_flips:
            now = self._clock()
            flip_s = now + self.settings.flip_latency_ms / 1000
            self._flips.append((now, flip_s, rgb))
            if self.trigger is not None:
                self.trigger.edge(flip_s)

    def attach_trigger(self, line: Any) -> None:
        """Wire `line` as `SLM.attach_trigger` does, and replay the frame already up's write and
        flip on it."""
        super().attach_trigger(line)
        if self._flips:  # the frame already up (the daemon's blank) has flipped: say so
            written_s, flip_s, _ = self._flips[-1]
            line.written(written_s)
            line.edge(flip_s)

    def _health(self) -> SLMHealth:
        return SLMHealth(True, "simulated") if self._plugged else SLMHealth(False, "unplugged")
