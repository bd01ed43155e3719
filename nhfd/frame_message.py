"""A computed frame as it crosses the pipe from the frame worker to the daemon (layer L0).

The worker (`nhfd.pipeline.worker`) sends a `FrameDone(seq, FrameMessage)` (the pipe's messages
are `nhfd.worker_messages`'); the daemon's frame link (`nhfd.daemon.frame_link`) reads it by
name: where the coded region goes on the panel
(`Region`), where its arrays are (a shared-memory slot and their shapes, or the arrays
themselves with the pickled transport), the stage times (`StageTimes`), the clipped fractions,
the pose warnings, whether it came from the frame cache, and when it was whole in its slot.
A refinement's better frames come as `RefinedFrame`s; the camera in the loop asks the daemon's
bench for captures with a `CaptureRequest` and gets a `CaptureReply`. Both processes import this
module (NumPy and the standard library only), so the message's form
is defined once: no positional lists, no keys to agree on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

# What a view's first frame can be: the network's, or the exact one of a scene with no model.
FRAME_TIERS = ("network", "exact")
# The frame pipeline's stages, in order (`nhfd.pipeline.frame.compute_frame`); the daemon adds
# "output" (the region pasted into the panel and shown).
STAGES = ("render", "inference", "propagation", "coding")


def _count(name: str, value: Any) -> int:
    if not (isinstance(value, int | np.integer) and not isinstance(value, bool) and value >= 0):
        raise ValueError(f"region {name} = {value!r}: expected an integer >= 0 (px)")
    return int(value)


@dataclass(frozen=True)
class Region:
    """The part of the panel a frame changes (px): the window plus the kernel's reach, with an
    even top-left corner so its checkerboard lines up with the zero pattern's; and where the
    window sits inside it."""

    top: int
    left: int
    height: int
    width: int
    window_top: int
    window_left: int

    def __post_init__(self) -> None:
        for name in ("top", "left", "height", "width", "window_top", "window_left"):
            object.__setattr__(self, name, _count(name, getattr(self, name)))

    @property
    def rows(self) -> slice:
        """The region's panel rows."""
        return slice(self.top, self.top + self.height)

    @property
    def cols(self) -> slice:
        """The region's panel columns."""
        return slice(self.left, self.left + self.width)


@dataclass(frozen=True)
class StageTimes:
    """Seconds each stage of a frame took in the worker (0 for a frame from its cache)."""

    render_s: float = 0.0
    inference_s: float = 0.0
    propagation_s: float = 0.0
    coding_s: float = 0.0

    def __post_init__(self) -> None:
        for stage in STAGES:
            v = getattr(self, f"{stage}_s")
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"stage time {stage}_s = {v!r}: expected a finite number "
                                 ">= 0 (s)")

    @classmethod
    def from_seconds(cls, seconds: dict[str, float]) -> StageTimes:
        """From the pipeline's clock (`{stage: seconds}`, `nhfd.pipeline.device.StageClock`);
        ValueError naming a stage it does not know."""
        unknown = sorted(set(seconds) - set(STAGES))
        if unknown:
            raise ValueError(f"stage times {unknown}: expected stages among {', '.join(STAGES)}")
        return cls(**{f"{k}_s": float(v) for k, v in seconds.items()})

    def seconds(self) -> dict[str, float]:
        """{stage: seconds} in the pipeline's order."""
        return {stage: getattr(self, f"{stage}_s") for stage in STAGES}


@dataclass(frozen=True, eq=False)
class FrameMessage:
    """One frame, as the worker reports it.

    region            where the grey region goes on the panel
    grey_shape        the coded region's shape `[3, h, w]` (uint8 grey levels; h, w = the
                      region's height and width)
    rgb_shape         the view's preview `[3, H, W]` uint8, or None (none sent)
    timings           the worker's stage times
    clipped_fraction  per colour, the fraction of pixels whose amplitude double-phase coding
                      clipped
    warnings          why the view lies outside the model's pose envelope (empty: inside)
    cached            whether it came from the worker's frame cache
    slot              the shared-memory slot holding the arrays, or None: `grey` and `rgb` are
                      in the message (the pickled transport), or not yet written (`in_slot`)
    ready_s           when the frame was whole in its slot (CLOCK_MONOTONIC, shared by both
                      processes), set just before sending
    grey_hwc          the slot holds the grey region as `[h, w, 3]` (the SLM's interleaved
                      layout, which a device frame computes) instead of `[3, h, w]`
    tier              what the frame is: "network" (the model's), or "exact" (a scene served
                      without a model: the view's own hologram, its first frame)
    """

    region: Region
    grey_shape: tuple[int, int, int]
    rgb_shape: tuple[int, int, int] | None
    timings: StageTimes
    clipped_fraction: tuple[float, ...] = ()
    warnings: tuple[str, ...] = ()
    cached: bool = False
    slot: int | None = None
    ready_s: float | None = None
    grey: np.ndarray | None = None
    rgb: np.ndarray | None = None
    grey_hwc: bool = False
    tier: str = "network"

    def __post_init__(self) -> None:
        if not isinstance(self.region, Region):
            raise ValueError(f"frame region = {self.region!r}: expected a Region")
        if self.tier not in FRAME_TIERS:
            raise ValueError(f"frame tier = {self.tier!r}: expected one of "
                             f"{', '.join(FRAME_TIERS)}")
        if not isinstance(self.timings, StageTimes):
            raise ValueError(f"frame timings = {self.timings!r}: expected StageTimes")
        object.__setattr__(self, "grey_shape", _shape("grey_shape", self.grey_shape))
        r = self.region
        if self.grey_shape[1:] != (r.height, r.width):
            raise ValueError(f"frame grey_shape = {list(self.grey_shape)}: expected [C, "
                             f"{r.height}, {r.width}] (the region's height and width)")
        if self.rgb_shape is not None:
            object.__setattr__(self, "rgb_shape", _shape("rgb_shape", self.rgb_shape))
        object.__setattr__(self, "clipped_fraction",
                           tuple(float(f) for f in self.clipped_fraction))
        object.__setattr__(self, "warnings", tuple(str(w) for w in self.warnings))
        if self.slot is not None and not (isinstance(self.slot, int) and self.slot >= 0):
            raise ValueError(f"frame slot = {self.slot!r}: expected a slot index >= 0 or None")

    @classmethod
    def of_arrays(cls, region: Region, grey: np.ndarray, rgb: np.ndarray | None,
                  timings: StageTimes, clipped_fraction: tuple[float, ...] = (),
                  warnings: tuple[str, ...] | list[str] = ()) -> FrameMessage:
        """A frame holding its arrays (grey `[3, h, w]` uint8, the preview `[3, H, W]` uint8 or
        None), the shapes taken from them; a grey region that is a view of an `[h, w, 3]` array
        (`is_interleaved`) crosses in that layout."""
        return cls(region, tuple(grey.shape), None if rgb is None else tuple(rgb.shape),
                   timings, tuple(clipped_fraction), tuple(warnings), grey=grey, rgb=rgb,
                   grey_hwc=is_interleaved(grey))

    def in_slot(self, slot: int) -> FrameMessage:
        """This frame with its arrays written to shared-memory `slot` (by the caller): the
        message then carries their shapes only."""
        return replace(self, slot=slot, grey=None, rgb=None)

    def ready(self, ready_s: float) -> FrameMessage:
        """This frame, whole in its slot at `ready_s` (CLOCK_MONOTONIC, s)."""
        return replace(self, ready_s=ready_s)

    def from_cache(self) -> FrameMessage:
        """This frame served again from the worker's cache: no stage ran."""
        return replace(self, cached=True, timings=StageTimes())


def is_interleaved(grey: np.ndarray) -> bool:
    """Whether `grey` `[C, h, w]` is the channel-first view of a C-contiguous `[h, w, C]` array
    (the SLM's layout): then it is copied as `grey.transpose(1, 2, 0)`, row by row."""
    return (grey.ndim == 3 and grey.shape[0] > 1 and not grey.flags.c_contiguous
            and grey.transpose(1, 2, 0).flags.c_contiguous)


def _shape(name: str, shape: Any) -> tuple[int, int, int]:
    dims = tuple(shape)
    if len(dims) != 3 or not all(isinstance(d, int | np.integer) and d >= 0 for d in dims):
        raise ValueError(f"frame {name} = {list(dims)}: expected [3, h, w], integers >= 0")
    return tuple(int(d) for d in dims)  # type: ignore[return-value]


# What a refinement report carries (`nhfd.pipeline.refine.RefineReport.to_json`), the keys
# `status.frames.refine` shows.
REFINE_KEYS = ("tier", "iterations", "seconds", "loss", "psnr_db", "start_psnr_db", "stop")


@dataclass(frozen=True, eq=False)
class RefinedFrame:
    """A better frame for a view already shown (the progressive mode of issue 34), as the worker
    reports it while the view rests.

    region      where the subframes go on the panel (the network frame's region)
    grey        the K subframes `[K, 3, h, w]` uint8, shown in turn one per refresh, when they
                travel in the message (the pickled transport); None when they are in a
                shared-memory refine slot (`slot`) or when only the report changed (a
                refinement that stopped without a better frame)
    report      the refinement so far: `REFINE_KEYS` (tier, iterations, seconds, loss, the
                estimated PSNR in dB and the start's, why it stopped or "" while it runs)
    slot        the refine slot holding the subframes `[K, 3, h, w]` uint8 (channel-first,
                contiguous), or None; the daemon gives it back once it shows newer ones
    grey_shape  the subframes' shape `[K, 3, h, w]` when they are in `slot`
    A better frame comes every `refine.swap_every` iterations at most. In a slot, what crosses
    the pipe is a few hundred bytes whatever K and the panel: the daemon's control loop then
    pastes one subframe per refresh straight from the slot.
    """

    region: Region
    grey: np.ndarray | None
    report: dict[str, Any]
    slot: int | None = None
    grey_shape: tuple[int, int, int, int] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.region, Region):
            raise ValueError(f"refined region = {self.region!r}: expected a Region")
        g = self.grey
        hw = (self.region.height, self.region.width)
        if g is not None and (g.dtype != np.uint8 or g.ndim != 4 or g.shape[2:] != hw):
            raise ValueError(f"refined grey {g.dtype} {list(g.shape)}: expected uint8 [K, C, "
                             f"{self.region.height}, {self.region.width}]")
        if self.slot is not None:
            shape = tuple(self.grey_shape or ())
            if (g is not None or not (isinstance(self.slot, int) and self.slot >= 0)
                    or len(shape) != 4 or shape[2:] != hw or min(shape) < 1):
                raise ValueError(f"refined slot {self.slot!r} with grey_shape {list(shape)}: "
                                 f"expected a slot index >= 0, [K, C, {hw[0]}, {hw[1]}] and no "
                                 "grey in the message")
            object.__setattr__(self, "grey_shape", tuple(int(d) for d in shape))
        missing = [k for k in REFINE_KEYS if k not in self.report]
        if missing:
            raise ValueError(f"refined report: missing {', '.join(missing)}")

    @property
    def subframes(self) -> int:
        """K: how many subframes it carries (0: a report only)."""
        if self.grey is not None:
            return int(self.grey.shape[0])
        return self.grey_shape[0] if self.slot is not None and self.grey_shape else 0

    def in_slot(self, slot: int) -> RefinedFrame:
        """This frame with its subframes written to refine slot `slot` (by the caller)."""
        assert self.grey is not None
        return replace(self, grey=None, slot=slot, grey_shape=tuple(self.grey.shape))


@dataclass(frozen=True, eq=False)
class CaptureRequest:
    """The camera in the loop (`citl`, issue 34) asking the daemon's bench for one step's
    captures: the worker sends a `CaptureAsked(seq, req_id, CaptureRequest)` and waits for the
    `CaptureAnswer(req_id, CaptureReply)` (`nhfd.worker_messages`).

    region   where the subframes go on the panel
    grey     the K subframes `[K, 3, h, w]` uint8, each shown in turn during a colour's capture
    z_m      the planes to capture, as depths from the SLM (m; what `Calibration.stage_mm_for`
             takes): the stage moves to each in turn
    frames   camera frames averaged per capture (`devices.camera_settings`' burst when 0)
    """

    region: Region
    grey: np.ndarray
    z_m: tuple[float, ...]
    frames: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.region, Region):
            raise ValueError(f"capture region = {self.region!r}: expected a Region")
        g = self.grey
        if (not isinstance(g, np.ndarray) or g.dtype != np.uint8 or g.ndim != 4
                or g.shape[0] < 1 or g.shape[2:] != (self.region.height, self.region.width)):
            raise ValueError(f"capture grey {getattr(g, 'dtype', type(g).__name__)} "
                             f"{list(getattr(g, 'shape', ()))}: expected uint8 [K >= 1, C, "
                             f"{self.region.height}, {self.region.width}]")
        z = tuple(float(v) for v in self.z_m)
        if not z or not all(math.isfinite(v) for v in z):
            raise ValueError(f"capture z_m = {list(self.z_m)}: expected one or more finite "
                             "depths (m)")
        object.__setattr__(self, "z_m", z)
        f = self.frames
        if not (isinstance(f, int | np.integer) and not isinstance(f, bool) and f >= 0):
            raise ValueError(f"capture frames = {f!r}: expected an integer >= 0")
        object.__setattr__(self, "frames", int(f))


@dataclass(frozen=True, eq=False)
class CaptureReply:
    """The daemon's answer to a `CaptureRequest`: the camera's linear images `[P, C, Hc, Wc]`
    (float32, per plane and colour, the K subframes' mean, dark subtracted) and where any
    subframe saturated (bool, the same shape); or `error`, why the bench did not capture (the
    lasers disarmed, a device missing or failing, the request overtaken)."""

    images: np.ndarray | None = None
    saturated: np.ndarray | None = None
    error: str = ""

    def __post_init__(self) -> None:
        if self.error:
            return
        im, sat = self.images, self.saturated
        if (not isinstance(im, np.ndarray) or im.ndim != 4 or not isinstance(sat, np.ndarray)
                or sat.shape != im.shape or sat.dtype != np.bool_):
            raise ValueError(f"capture reply images {list(getattr(im, 'shape', ()))}, saturated "
                             f"{list(getattr(sat, 'shape', ()))}: expected [P, C, H, W] each "
                             "(saturated bool), or an error")
        if not np.isfinite(im).all():
            raise ValueError("capture reply images: not finite")
