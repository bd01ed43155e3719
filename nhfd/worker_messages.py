"""The frame worker's pipe as typed messages (layer L0): every message the daemon's frame link
(`nhfd.daemon.frame_link`) and the frame worker (`nhfd.pipeline.worker`) send each other over
their duplex `multiprocessing` pipe is one of the frozen dataclasses here, matched by its type
on the other side (`match msg: case FrameDone(seq=seq, message=message): ...`), never by a
string tag or a position. A message of another type is refused by name: the worker answers
`MessageRefused`, the daemon notes an error in `status` and keeps serving.

  daemon -> worker   `TO_WORKER`: FrameRequest, LoadModel, LoadScene, CancelFrame,
                     CaptureAnswer, RefineSlotFree, Stop
  worker -> daemon   `FROM_WORKER`: WorkerReady, Loaded, LoadFailed, FrameDone, FrameFailed,
                     FrameCancelled, BetterFrame, RefineFailed, CaptureAsked, MessageRefused

A load's answer carries what the worker loaded as a value: `ModelLoaded` (the model's own
`nhfd.model_info.ModelInfo` and the facts of its serving: the file served, the variant and why,
what runs the network, the device, the frame window and the sizes it was checked at) or
`SceneLoaded` (its counts, centre and up axis). The daemon keeps them as they are and turns
them into JSON once, at the edge (`ModelLoaded.to_json`: `status`'s "model").

docs/frames.md ("The worker's pipe") has the protocol in one table; tests/daemon/
test_worker_messages.py holds that table to these classes. NumPy and the standard library only:
both processes import this module, so the protocol is defined once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from nhfd.calibration import BENCH_RECORD_KEYS
from nhfd.frame_message import CaptureReply, CaptureRequest, FrameMessage, RefinedFrame
from nhfd.model_info import ModelInfo
from nhfd.views import View

# The model variants a load may serve (`nhfd.pipeline.worker.choose_variant`).
VARIANTS = ("float", "int8")



def _index(owner: str, name: str, value: Any, *, optional: bool = False) -> None:
    """ValueError naming `owner.name` unless `value` is an integer >= 0 (or None, `optional`)."""
    if optional and value is None:
        return
    if not (isinstance(value, int | np.integer) and not isinstance(value, bool) and value >= 0):
        raise ValueError(f"{owner} {name} = {value!r}: expected an integer >= 0"
                         + (" or None" if optional else ""))


def _typed(owner: str, name: str, value: Any, expected: type | tuple[type, ...]) -> None:
    """ValueError naming `owner.name` unless `value` is an `expected`."""
    if not isinstance(value, expected):
        names = (expected,) if isinstance(expected, type) else expected
        raise ValueError(f"{owner} {name}: expected {' or '.join(t.__name__ for t in names)}, "
                         f"found {type(value).__name__}")


def _hw(owner: str, name: str, value: Any) -> tuple[int, int]:
    """`value` as (height, width) px, or ValueError naming `owner.name`."""
    dims = tuple(value)
    if len(dims) != 2 or not all(isinstance(d, int | np.integer) and not isinstance(d, bool)
                                 and d >= 1 for d in dims):
        raise ValueError(f"{owner} {name} = {list(dims)}: expected [height, width], integers "
                         ">= 1 px")
    return int(dims[0]), int(dims[1])


# -- what a load's answer carries ---------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ModelLoaded:
    """A model the worker serves now, as it reports it: the daemon keeps it (`FrameLink.model`)
    and `status`'s "model" is its `to_json()`.

    path                    the model file the load asked for (the float model)
    info                    the served model's metadata (`ModelInfo`, checked at its load)
    served                  the file serving frames: `path`, or its int8 sibling
    variant, variant_reason "float" or "int8", and why (`daemon.frames.int8`, the recorded loss)
    providers               onnxruntime's providers in order, or ("torch",)
    inference, inference_reason  what runs the network ("onnxruntime" | "torch"), and why
    device, device_reason   the torch device frames are computed on ("cpu", "cuda:0"), and why
    window_hw               the frame window (h, w px)
    checked_sizes_hw        the graph input sizes (h, w) its size checks passed at
    checked_sizes_recorded  False: an older export, only its training window counts as checked
    loaded_s                when it was loaded (time.time(), s)
    load_memory_mb          what its session and test run took in the load's probe (MB), or
                            None where not measured
    size_warning            why the frame window is not a checked size, where allowed ("": it is)
    tuned_for               the bench a tuned model was tuned for (its metadata's record:
                            calibration label, fingerprint, date), or None: not tuned
    bench_warning           why it serves on another bench (`daemon.frames.allow_other_bench`)
    """

    path: str
    info: ModelInfo
    served: str
    variant: str
    variant_reason: str
    providers: tuple[str, ...]
    inference: str
    inference_reason: str
    device: str
    device_reason: str
    window_hw: tuple[int, int]
    checked_sizes_hw: tuple[tuple[int, int], ...]
    checked_sizes_recorded: bool
    loaded_s: float
    load_memory_mb: float | None = None
    size_warning: str = ""
    tuned_for: dict[str, Any] | None = None
    bench_warning: str = ""

    def __post_init__(self) -> None:
        _typed("model loaded", "info", self.info, ModelInfo)
        if self.variant not in VARIANTS:
            raise ValueError(f"model loaded variant = {self.variant!r}: expected one of "
                             f"{', '.join(VARIANTS)}")
        object.__setattr__(self, "providers", tuple(str(p) for p in self.providers))
        object.__setattr__(self, "window_hw", _hw("model loaded", "window_hw", self.window_hw))
        object.__setattr__(self, "checked_sizes_hw", tuple(
            _hw("model loaded", "checked_sizes_hw", hw) for hw in self.checked_sizes_hw))

    def to_json(self) -> dict[str, Any]:
        """What `status` reports of the model (its "model" object): the path, the metadata's
        fields (`ModelInfo.status_json`), then how it serves."""
        out: dict[str, Any] = {
            "path": self.path, **self.info.status_json(), "providers": list(self.providers),
            "loaded_s": self.loaded_s, "load_memory_mb": self.load_memory_mb,
            "inference": self.inference, "inference_reason": self.inference_reason,
            "variant": self.variant, "variant_reason": self.variant_reason,
            "served": self.served, "window_hw": list(self.window_hw),
            "checked_sizes_hw": [list(hw) for hw in self.checked_sizes_hw],
            "checked_sizes_recorded": self.checked_sizes_recorded, "device": self.device,
            "device_reason": self.device_reason}
        if self.size_warning:
            out["size_warning"] = self.size_warning
        out["tuned_for"] = (None if not self.tuned_for else
                            {k: self.tuned_for.get(k) for k in BENCH_RECORD_KEYS})
        if self.bench_warning:
            out["bench_warning"] = self.bench_warning
        return out


@dataclass(frozen=True, slots=True)
class SceneLoaded:
    """A scene the worker renders now: the file, its Gaussians (those kept, those the file
    declared, those dropped and why), and the frame orbit views are about (its centre in scene
    units, its up axis, e.g. "+z")."""

    path: str
    gaussians: int
    declared: int
    dropped: int
    dropped_reason: str
    center: tuple[float, float, float]
    up: str

    def __post_init__(self) -> None:
        for name in ("gaussians", "declared", "dropped"):
            _index("scene loaded", name, getattr(self, name))
        center = tuple(float(v) for v in self.center)
        if len(center) != 3:
            raise ValueError(f"scene loaded center = {list(center)}: expected [x, y, z]")
        object.__setattr__(self, "center", center)

    def to_json(self) -> dict[str, Any]:
        """A load job's result and `status`'s "scene" (with the daemon's `loaded_s`)."""
        return {"path": self.path, "gaussians": self.gaussians, "declared": self.declared,
                "dropped": self.dropped, "dropped_reason": self.dropped_reason,
                "center": self.center, "up": self.up}


# -- daemon -> worker ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FrameRequest:
    """Compute view `seq`'s frame into shared-memory frame slot `slot` (None: the pickled
    transport, the arrays in the answer). The worker owns the slot until it answers."""

    seq: int
    view: View
    slot: int | None = None

    def __post_init__(self) -> None:
        _index("frame request", "seq", self.seq)
        _typed("frame request", "view", self.view, View)
        _index("frame request", "slot", self.slot, optional=True)


@dataclass(frozen=True, slots=True)
class LoadModel:
    """Load the model file at `path` (checked against the configured optics, test-run); answered
    by `Loaded` (a `ModelLoaded`) or `LoadFailed`, with the same `req_id`."""

    req_id: int
    path: str

    def __post_init__(self) -> None:
        _index("load model", "req_id", self.req_id)


@dataclass(frozen=True, slots=True)
class LoadScene:
    """Load the scene file at `path`; answered by `Loaded` (a `SceneLoaded`) or `LoadFailed`."""

    req_id: int
    path: str

    def __post_init__(self) -> None:
        _index("load scene", "req_id", self.req_id)


@dataclass(frozen=True, slots=True)
class CancelFrame:
    """Stop the refinement or the exact frame of view `seq` (a newer view waits): nothing
    else."""

    seq: int

    def __post_init__(self) -> None:
        _index("cancel frame", "seq", self.seq)


@dataclass(frozen=True, slots=True)
class CaptureAnswer:
    """The bench's captures for the citl step that sent `CaptureAsked` `req_id` (or why there
    are none). Unlike other messages, it does not cancel the refinement."""

    req_id: int
    reply: CaptureReply

    def __post_init__(self) -> None:
        _index("capture answer", "req_id", self.req_id)
        _typed("capture answer", "reply", self.reply, CaptureReply)


@dataclass(frozen=True, slots=True)
class RefineSlotFree:
    """Refine slot `slot` is the worker's again (the daemon shows newer subframes). Does not
    cancel the refinement."""

    slot: int

    def __post_init__(self) -> None:
        _index("refine slot free", "slot", self.slot)


@dataclass(frozen=True, slots=True)
class Stop:
    """End the worker (it returns from its loop; the daemon then unlinks the slots)."""


# -- worker -> daemon ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class WorkerReady:
    """The worker process `pid` has imported its libraries and takes messages."""

    pid: int

    def __post_init__(self) -> None:
        _index("worker ready", "pid", self.pid)


@dataclass(frozen=True, slots=True)
class Loaded:
    """Load `req_id` succeeded: the worker serves `result` now (a `ModelLoaded` for a
    `LoadModel`, a `SceneLoaded` for a `LoadScene`)."""

    req_id: int
    result: ModelLoaded | SceneLoaded

    def __post_init__(self) -> None:
        _index("loaded", "req_id", self.req_id)
        _typed("loaded", "result", self.result, (ModelLoaded, SceneLoaded))


@dataclass(frozen=True, slots=True)
class LoadFailed:
    """Load `req_id` was refused, `error` saying why ("ModelMismatch: ..."); the model or scene
    before it stays in use."""

    req_id: int
    error: str

    def __post_init__(self) -> None:
        _index("load failed", "req_id", self.req_id)


@dataclass(frozen=True, slots=True)
class FrameDone:
    """View `seq`'s frame: `message` says where its region goes, where its arrays are (the
    slot the request named, or in the message) and how it was computed. A model of K > 1
    subframes sends all K as `subframes` (a `RefinedFrame` of tier "network", in a refine slot
    or pickled), its first the message's own; None for one frame."""

    seq: int
    message: FrameMessage
    subframes: RefinedFrame | None = None

    def __post_init__(self) -> None:
        _index("frame done", "seq", self.seq)
        _typed("frame done", "message", self.message, FrameMessage)
        if self.subframes is not None:
            _typed("frame done", "subframes", self.subframes, RefinedFrame)


@dataclass(frozen=True, slots=True)
class FrameFailed:
    """View `seq` could not be computed, `error` saying why (its slot is the daemon's again)."""

    seq: int
    error: str

    def __post_init__(self) -> None:
        _index("frame failed", "seq", self.seq)


@dataclass(frozen=True, slots=True)
class FrameCancelled:
    """View `seq`'s exact frame (a scene with no model) was cancelled before it was done (a load
    or a newer view came first); its slot is the daemon's again."""

    seq: int

    def __post_init__(self) -> None:
        _index("frame cancelled", "seq", self.seq)


@dataclass(frozen=True, slots=True)
class BetterFrame:
    """A refinement's better frame for view `seq`, already shown (`RefinedFrame`: its K
    subframes in a refine slot or in the message, or its report alone)."""

    seq: int
    frame: RefinedFrame

    def __post_init__(self) -> None:
        _index("better frame", "seq", self.seq)
        _typed("better frame", "frame", self.frame, RefinedFrame)


@dataclass(frozen=True, slots=True)
class RefineFailed:
    """View `seq`'s refinement failed, `error` saying why; the frame shown stays."""

    seq: int
    error: str

    def __post_init__(self) -> None:
        _index("refine failed", "seq", self.seq)


@dataclass(frozen=True, slots=True)
class CaptureAsked:
    """A citl step of view `seq` asks the daemon's bench for captures (`request`); it waits for
    the `CaptureAnswer` with the same `req_id`."""

    seq: int
    req_id: int
    request: CaptureRequest

    def __post_init__(self) -> None:
        _index("capture asked", "seq", self.seq)
        _index("capture asked", "req_id", self.req_id)
        _typed("capture asked", "request", self.request, CaptureRequest)


@dataclass(frozen=True, slots=True)
class MessageRefused:
    """The worker got a message it does not take, of type `kind` (its class name), and did
    nothing with it; `error` says what it takes."""

    kind: str
    error: str


# The messages each way, in the order docs/frames.md lists them.
TO_WORKER = (FrameRequest, LoadModel, LoadScene, CancelFrame, CaptureAnswer, RefineSlotFree, Stop)
FROM_WORKER = (WorkerReady, Loaded, LoadFailed, FrameDone, FrameFailed, FrameCancelled,
               BetterFrame, RefineFailed, CaptureAsked, MessageRefused)
# What a load's answer carries (`Loaded.result`).
LOADED = (ModelLoaded, SceneLoaded)

ToWorker = (FrameRequest | LoadModel | LoadScene | CancelFrame | CaptureAnswer | RefineSlotFree
            | Stop)
FromWorker = (WorkerReady | Loaded | LoadFailed | FrameDone | FrameFailed | FrameCancelled
              | BetterFrame | RefineFailed | CaptureAsked | MessageRefused)


def refusal(msg: Any, who: str, takes: tuple[type, ...]) -> str:
    """Why `msg` is refused by `who` ("the frame worker", "the frame link"), which takes only
    the messages `takes`: its type named, then what is taken."""
    return (f"{type(msg).__name__}: not a message {who} takes "
            f"({', '.join(t.__name__ for t in takes)})")
