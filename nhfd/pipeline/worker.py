"""The frame worker: the spawned process that renders, runs the network and codes frames.

Why a process: rendering (numba), inference (onnxruntime) and propagation (torch) hold the CPU
for tens of milliseconds at a time; in the daemon's own process they would delay the control
loop that feeds the laser guardian's heartbeat. The daemon (`nhfd.daemon.frame_link`) spawns it
by this module's name, with the thread counts in the environment before anything here imports
torch, numba or onnxruntime (a fresh interpreter: no pools exist yet).

Protocol: typed messages over one duplex `multiprocessing` pipe (`nhfd.worker_messages`, the
table in docs/frames.md), matched by type; a message of any other type is answered with
`MessageRefused` naming it.

  daemon -> worker   FrameRequest(seq, view, slot)   LoadModel(req_id, path)
                     LoadScene(req_id, path)         CancelFrame(seq)
                     CaptureAnswer(req_id, reply)    RefineSlotFree(slot)   Stop()
  worker -> daemon   WorkerReady(pid)
                     Loaded(req_id, ModelLoaded | SceneLoaded)   LoadFailed(req_id, error)
                     FrameDone(seq, message, subframes)   FrameFailed(seq, error)
                     BetterFrame(seq, frame)         RefineFailed(seq, error)
                     FrameCancelled(seq)             CaptureAsked(seq, req_id, request)
                     MessageRefused(kind, error)

A view whose `quality` is above "network" is refined after its network frame is sent
(`Refiner`, a thread): each better frame comes as a `BetterFrame` (a `RefinedFrame`) until the
refinement stops or any message from the daemon but a `CaptureAnswer` or a `RefineSlotFree`
cancels it (`CancelFrame` does only that: a newer view waits for a scene's exact frame no
longer). A better frame's K subframes go into one of the daemon's refine slots (shared
memory), which the daemon gives back with `RefineSlotFree` once it shows newer ones; so what
crosses the pipe is small whatever K. A `citl` view's steps ask the daemon's bench for captures
(`nhfd.pipeline.citl.RemoteCapture`: a `CaptureAsked`, answered by a `CaptureAnswer`). With no
model loaded, such a view's first frame is its exact frame (the scene's own hologram, seconds
later), or `FrameCancelled` when a load or a newer view came first.

The view is an `nhfd.views.View` and a frame's message an `nhfd.frame_message.FrameMessage`:
L0 values both processes import, read by name.

Frames cross in shared memory (`daemon.frames.transport = "shm"`): the daemon creates the slots
(`multiprocessing.shared_memory`, each sized for the whole panel, so any region fits), names
them to the worker at spawn, and names the slot each frame request may write; the worker owns
that slot until its reply, the daemon from then until it has copied the frame out. The message
then says where the arrays are (`slot`, `grey_shape`, `rgb_shape`) and carries no array. With
slot None (`"pickle"`) the arrays travel in the message, pickled, as before.

Everything the daemon learns of the model crosses the pipe as data: what `status` reports of
it as a `ModelLoaded` (the model's own `ModelInfo` and the facts of its serving), why it was
refused (`ModelUnfit`, `ModelMismatch`) as a `LoadFailed`'s text; the daemon never imports the
model code. The worker drains its pipe before each frame and computes only the newest view
(latest wins); loads are applied in order, and a failed load leaves the previous model or scene
in use.
"""

from __future__ import annotations

import functools
import os
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import replace
from multiprocessing import shared_memory
from pathlib import Path
from typing import Any

import numba
import numpy as np
import onnxruntime as ort
import torch

from nhfd.calibration import Calibration, CalibrationStore, other_bench
from nhfd.config import Config, DaemonSettings
from nhfd.dataset.build import sha256_file
from nhfd.frame_message import CaptureReply, FrameMessage, RefinedFrame, StageTimes
from nhfd.models.export import (
    check_providers,
    load_model,
    probe_model,
    read_model_metadata,
)
from nhfd.models.metadata import expected_from_config, parse_model_info
from nhfd.models.quantise import HELDOUT_KEY, INT8_MAX_LOSS_DB, int8_sibling, int8_within_loss
from nhfd.models.sizes import window_check
from nhfd.models.torch_model import TorchModel
from nhfd.scene.io import read_scene
from nhfd.views import View
from nhfd.worker_messages import (
    TO_WORKER,
    BetterFrame,
    CancelFrame,
    CaptureAnswer,
    FrameCancelled,
    FrameDone,
    FrameFailed,
    FrameRequest,
    FromWorker,
    Loaded,
    LoadFailed,
    LoadModel,
    LoadScene,
    MessageRefused,
    ModelLoaded,
    RefineFailed,
    RefineSlotFree,
    SceneLoaded,
    Stop,
    WorkerReady,
    refusal,
)

from .citl import RemoteCapture
from .device import frame_device, inference_backend
from .encoder import Encoder
from .frame import compute_frame, preview_levels
from .refine import Cancelled, Prepared, Refined, prepare, refine_view
from .settings import frame_settings, frame_window_hw
from .view import Scene, envelope_warnings, scene_frame

# Encoders kept per refocus depth: a refocus sweep must not grow kernels without bound.
MAX_ENCODERS = 8
# The test inference's input: mid-grey sRGB everywhere and, for an rgbd model, the reference
# plane's depth (0): a frame the daemon could send, so a model that fails it fails real frames.
TEST_GREY = 0.5
# How long a better frame waits for a free refine slot (s): the daemon gives one back within a
# control-loop step of showing the next; an intermediate frame that finds none is skipped (its
# report still goes), the final one waits longer.
BETTER_WAIT_S = 0.05
FINAL_WAIT_S = 2.0
# The setting a model's load memory is bounded by (`open_model`), named in its refusals.
MEMORY_SETTING = "daemon.paths.model_memory_mb"


def _set_threads(threads: int) -> None:
    """The libraries' pools at `threads` (their environment, OMP_NUM_THREADS, NUMBA_NUM_THREADS
    and the rest, was set by the process's creator before they loaded)."""
    torch.set_num_threads(threads)
    torch.set_num_interop_threads(1)
    numba.set_num_threads(threads)


@functools.cache
def worker_device(value: str, inference: str = "auto") -> tuple[torch.device, str]:
    """`frame_device` for this process, resolved once per value (its torch and onnxruntime do
    not change while it runs); an invalid value raises every time it is asked."""
    return frame_device(value, ort.get_available_providers(), inference=inference)


def worker_inference(daemon: DaemonSettings) -> tuple[str, str]:
    """`inference_backend` for the configured device and `daemon.frames.inference`: ("onnxruntime" |
    "torch", why)."""
    device, _ = worker_device(daemon.frames.device, daemon.frames.inference)
    return inference_backend(daemon.frames.inference, device, ort.get_available_providers())


def open_model(path: str, config: Config, threads: int) -> Any:
    """The model at `path` checked against the configured optics, on the configured device:
    an `OnnxModel` on the configured providers, with `threads` intra-op threads in pools that
    do not spin (`nhfd.models.export.session_options`), or a `TorchModel` where
    `worker_inference` says torch.

    Before this process creates a session, the file is read within `daemon.paths.model_memory_mb`
    (a regular file no larger, no external data), its metadata checked field by field, and its
    session created and test-run on the frame window in a child process limited to that memory
    (`nhfd.models.export.probe_model`): a model that needs more is refused (`ModelOverBudget`)
    without this process allocating it. `load_memory_mb` on the model: what the child's session
    and run took.

    `config`: the whole configuration, because a model is served under three sections: `[daemon]`
    (providers, device, inference, memory, frame window), `[slm]` (the panel the window fits)
    and `[optics]` with `[slm]`'s pitch (the optics the model must have been trained for)."""
    # Checked here too, so the error names the setting to change. No silent fallback: a bench
    # configured for CUDA that quietly ran on the CPU would be 10x slower with nothing but a
    # warning to say why; the load fails instead and the previous model keeps running.
    d = config.daemon
    providers = check_providers(list(d.frames.onnx_providers), ort.get_available_providers(),
                                "daemon.frames.onnx_providers")
    # A CUDA device torch lacks, or one named without its frame path installed: ValueError.
    device, _ = worker_device(d.frames.device, d.frames.inference)
    memory_mb = int(d.paths.model_memory_mb)
    meta, input_name = read_model_metadata(path, max_bytes=memory_mb << 20,
                                           setting=MEMORY_SETTING)
    info = parse_model_info(meta, path, input_name)
    window_hw = frame_window_hw(d.frames, config.slm, info)
    torch_inference = worker_inference(d)[0] == "torch"
    m = info.input_multiple
    shape, want = trial_input(4 if input_name == "rgbd" else 3, m, window_hw)
    shapes = [shape]
    if torch_inference:  # TorchModel's own check runs the file's graph at 2 x 3 strides
        shapes.append((1, shape[1], 2 * m, 3 * m))
    probe = probe_model(path, memory_mb, shapes, threads=threads, fill=TEST_GREY,
                        setting=MEMORY_SETTING)
    if probe["run_error"]:  # not memory (that is refused in probe_model): the model is unfit
        raise ModelUnfit(f"{path}: a test inference on a {want} input failed: "
                         f"{probe['run_error']}")
    if torch_inference:
        model = TorchModel(path, expected=expected_from_config(config.optics, config.slm),
                           device=device)
    elif device.type == "cuda":  # providers chosen for the GPU, engines built for the frames' size
        model = load_model(path, config, threads=threads, providers=tuple(providers),
                           device=device, input_hw=window_hw,
                           engine_cache_dir=d.frames.engine_cache_dir or None)
    else:  # validates; raises ModelMismatch etc.
        model = load_model(path, config, threads=threads, providers=tuple(providers))
    # reported in status (ModelLoaded.load_memory_mb): what to compare
    # daemon.paths.model_memory_mb with
    model.load_memory_mb = round(probe["peak_mb"], 1)
    return model


class ModelUnfit(ValueError):
    """A model whose graph cannot take the daemon's frames, or whose test inference gives
    outputs of another shape or non-finite values; the message names the file and what differs."""


def trial_input(channels: int, multiple: int, window_hw: tuple[int, int]
               ) -> tuple[tuple[int, int, int, int], str]:
    """The test inference's input shape for a `window_hw` frame window, padded to `multiple`
    as frames are ([1, C, H, W]), and how refusals describe it."""
    h, w = window_hw
    ph, pw = h + (-h) % multiple, w + (-w) % multiple
    name = "rgbd" if channels == 4 else "rgb"
    return (1, channels, ph, pw), (f"[B, {channels}, {ph}, {pw}] ({name}, a {h} x {w} frame "
                                   f"window padded to multiples of {multiple})")


def check_inference(model: Any, window_hw: tuple[int, int], path: str) -> None:
    """Run `model` once on a frame of `window_hw` (padded to its input multiple, as frames are)
    and refuse it, with `ModelUnfit`, unless it takes that input and returns finite amplitude
    and phase of [1, colours x subframes, H, W]. Before the swap: a model that passes the
    metadata check but cannot serve frames must not replace a working one."""
    c, m = model.channels, model.multiple
    (_, _, ph, pw), want = trial_input(c, m, window_hw)
    declared = list(model.input_shape)
    if len(declared) != 4:
        raise ModelUnfit(f"{path}: input shape: expected {want}, found {declared}")
    for what, expected, found in zip(("channels", "height", "width"), (c, ph, pw),
                                     declared[1:], strict=True):
        if isinstance(found, int) and found != expected:
            raise ModelUnfit(f"{path}: input {what}: expected {expected}, found {found} "
                             f"(input shape: expected {want}, found {declared})")
    x = np.full((1, c, ph, pw), TEST_GREY, np.float32)
    if c == 4:
        x[:, 3] = 0.0
    try:
        outputs = model.run_raw(x)
    except Exception as exc:  # onnxruntime's own types: the first line says what
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:300]
        raise ModelUnfit(f"{path}: a test inference on a {want} input failed: {first}") from None
    # K subframes of three colours (`ModelInfo.subframes`, its metadata's word)
    colours = model.info.colours * model.info.subframes
    for name, out in zip(("amplitude", "phase"), outputs, strict=True):
        if list(out.shape) != [1, colours, ph, pw]:
            raise ModelUnfit(f"{path}: output {name} shape: expected [1, {colours}, {ph}, {pw}], "
                             f"found {list(out.shape)} ({model.info.subframes} subframes of "
                             f"{model.info.colours} colours)")
        bad = int(out.size - np.count_nonzero(np.isfinite(out)))
        if bad:
            raise ModelUnfit(f"{path}: output {name}: expected finite values, found {bad} of "
                             f"{out.size} not finite (test inference on a mid-grey frame)")


def cpu_path(daemon: DaemonSettings) -> bool:
    """Whether the frames' inference runs in onnxruntime on the CPU: its CPU provider first, no
    CUDA device asked for (`daemon.frames.device`, where this nhfd has it), and not in torch."""
    if worker_device(daemon.frames.device, daemon.frames.inference)[0].type != "cpu":
        return False
    if worker_inference(daemon)[0] != "onnxruntime":
        return False
    return daemon.frames.onnx_providers[0] == "CPUExecutionProvider"


def choose_variant(path: str, daemon: DaemonSettings, int8_metadata: dict[str, Any] | None
                   ) -> tuple[str, str]:
    """("int8" | "float", why) for the float model at `path` whose int8 sibling has the nhfd
    metadata `int8_metadata` (None: no sibling). `daemon.frames.int8`: "never", "always" (whenever
    the sibling exists), "auto": the sibling's own metadata must record a held-out loss against
    this very float file (its SHA-256) within INT8_MAX_LOSS_DB (`int8_within_loss`)."""
    mode = daemon.frames.int8
    sibling = int8_sibling(path).name
    if mode == "never":
        return "float", "daemon.frames.int8 = \"never\""
    if not cpu_path(daemon):
        return "float", (f"int8 serves only on the CPU path (daemon.frames.onnx_providers = "
                         f"{list(daemon.frames.onnx_providers)}, daemon.frames.device = "
                         f"{daemon.frames.device!r}, daemon.frames.inference = "
                         f"{daemon.frames.inference!r})")
    if int8_metadata is None:
        return "float", f"no int8 model beside it ({sibling})"
    if mode == "always":
        return "int8", f"daemon.frames.int8 = \"always\" ({sibling})"
    record = int8_metadata.get(HELDOUT_KEY)
    if not isinstance(record, dict) or "loss_vs_float_db" not in record:
        return "float", (f"{sibling} records no held-out loss against the float model (`nhfd "
                         "model build` and `nhfd export --int8 --data` record it)")
    if record.get("float_sha256") != sha256_file(Path(path)):
        return "float", (f"{sibling}'s held-out loss was measured against another float model "
                         "(SHA-256 differs): rebuild it")
    loss = float(record["loss_vs_float_db"])
    if not int8_within_loss(loss):
        return "float", (f"{sibling} loses {loss:.2f} dB of held-out PSNR, more than "
                         f"{INT8_MAX_LOSS_DB} dB")
    return "int8", (f"{sibling} loses {loss:.2f} dB of held-out PSNR (within "
                    f"{INT8_MAX_LOSS_DB} dB, {record.get('views')} views)")


class FrameSlots:
    """The daemon's shared-memory slots, attached by name. Each holds a frame's grey `[3, h, w]`
    uint8 (`[h, w, 3]` where the message says `grey_hwc`) and then its render's RGB
    `[3, h', w']` uint8, back to back."""

    def __init__(self, names: Sequence[str], slot_bytes: int, refine_names: Sequence[str] = (),
                 refine_bytes: int = 0) -> None:
        self.slot_bytes = int(slot_bytes)
        self.refine_bytes = int(refine_bytes)
        # Attaching registers the name with the resource tracker again: the daemon's own
        # tracker (a spawned child shares it), which already holds it, so this process's exit
        # unlinks nothing; the daemon unlinks its slots when it closes the worker.
        self.shms = [shared_memory.SharedMemory(name=name) for name in names]
        self.refine_shms = [shared_memory.SharedMemory(name=name) for name in refine_names]
        # The refine slots this worker may write: all at first; the daemon gives each back
        # (`RefineSlotFree`) once it no longer shows what is in it.
        self.free_refine: queue.SimpleQueue[int] = queue.SimpleQueue()
        for i in range(len(self.refine_shms)):
            self.free_refine.put(i)

    def write_refined(self, frame: RefinedFrame, wait_s: float) -> RefinedFrame:
        """`frame` with its subframes `[K, 3, h, w]` copied into a free refine slot, which it
        then names; waits up to `wait_s` for one, and without one (the daemon still shows both)
        returns its report alone: the next better frame goes instead."""
        grey = frame.grey
        assert grey is not None
        if grey.nbytes > self.refine_bytes:
            raise ValueError(f"refined subframes {list(grey.shape)} ({grey.nbytes} bytes) do not "
                             f"fit a {self.refine_bytes}-byte refine slot (refine.subframes x "
                             "the panel)")
        try:
            slot = self.free_refine.get(timeout=wait_s) if wait_s > 0 else \
                self.free_refine.get_nowait()
        except queue.Empty:
            return replace(frame, grey=None)
        np.ndarray(grey.shape, np.uint8, buffer=self.refine_shms[slot].buf)[...] = grey
        return frame.in_slot(slot)

    def write(self, slot: int, message: FrameMessage) -> FrameMessage:
        """The message with its arrays (grey `[3, h, w]`, the preview `[3, H, W]` or None,
        uint8) copied into `slot`, which it then names instead of carrying them."""
        grey, rgb = message.grey, message.rgb
        assert grey is not None  # a computed frame holds its grey region
        need = grey.nbytes + (rgb.nbytes if rgb is not None else 0)
        if need > self.slot_bytes:
            raise ValueError(f"frame of {need} bytes (grey {list(grey.shape)}, rgb "
                             f"{None if rgb is None else list(rgb.shape)}) does not fit a "
                             f"{self.slot_bytes}-byte slot (the panel's size)")
        buf = self.shms[slot].buf
        if message.grey_hwc:  # the SLM's layout, as the device frame computed it
            c, h, w = grey.shape
            np.ndarray((h, w, c), np.uint8, buffer=buf)[...] = grey.transpose(1, 2, 0)
        else:
            np.ndarray(grey.shape, np.uint8, buffer=buf)[...] = grey
        if rgb is not None:
            np.ndarray(rgb.shape, np.uint8, buffer=buf, offset=grey.nbytes)[...] = rgb
        return message.in_slot(slot)

    def close(self) -> None:
        """Detach from every slot (the daemon unlinks them)."""
        for shm in (*self.shms, *self.refine_shms):
            shm.close()


class _WorkerState:
    """The frame worker's model, scene, encoders and frame cache.

    `config`: the whole configuration, handed on to `open_model` and `frame_settings`, which
    join several sections; its `[daemon]` section sets the threads, the frame cache, the model's
    variant and the scene's size limit. `calibration`: the calibration frames are coded with
    (default: `config`'s file, read here)."""

    def __init__(self, config: Config, calibration: CalibrationStore | None = None) -> None:
        self.config = config
        self.calibration = calibration or CalibrationStore.of(config)
        self.threads = int(config.daemon.frames.worker_threads)
        self.model: Any = None
        self.model_id = 0
        self.scene: Scene | None = None
        self.scene_id = 0
        self.encoders: dict[float, Encoder] = {}  # refocus_m -> Encoder (each its own kernels)
        # (view, model id, scene id) -> the frame with its arrays: a view is a frozen value, so
        # it keys the cache itself (equal views, equal keys)
        # each frame's message and, from a model of K > 1 subframes, all K `[K, 3, h, w]`
        self.cache: OrderedDict[tuple[View, int, int], tuple[FrameMessage, np.ndarray | None]] \
            = OrderedDict()
        self.cache_size = int(config.daemon.frames.cache_frames)

    def load_model(self, path: str) -> ModelLoaded:
        """The float model at `path`, or its int8 sibling where `choose_variant` says so (an
        int8 model that fails to load or to infer falls back to the float one, saying why):
        what the daemon reports of it (the served model's `ModelInfo` and how it serves)."""
        daemon = self.config.daemon
        model = open_model(path, self.config, self.threads)
        window_hw = frame_window_hw(daemon.frames, self.config.slm, model.info)
        allow = daemon.frames.allow_unchecked_sizes
        # UncheckedSize names the size, the checked ones and daemon.frames.allow_unchecked_sizes
        warning = window_check(model.info, window_hw, path, allow=allow)
        check_inference(model, window_hw, path)
        tuned_for = model.metadata.get("tuned_for") or None
        other = other_bench(tuned_for, self.calibration.active())
        if other and not daemon.frames.allow_other_bench:
            raise ModelUnfit(f"{path}: {other}. Load a model tuned for this calibration (nhfd "
                             "model tune), or set daemon.frames.allow_other_bench = true to "
                             "serve it anyway")
        served, variant, why = model, "float", ""
        sibling = int8_sibling(path)
        if Path(path).stem.endswith("-int8") or HELDOUT_KEY in model.metadata:
            variant, why = "int8", "the model given is an int8 model"
        elif daemon.frames.int8 != "never" and sibling.is_file() and cpu_path(daemon):
            try:
                q = open_model(str(sibling), self.config, self.threads)
                variant, why = choose_variant(path, daemon, q.metadata)
                if variant == "int8":
                    window_check(q.info, window_hw, str(sibling), allow=allow)
                    check_inference(q, window_hw, str(sibling))
                    served = q
            except Exception as exc:  # the float model serves; status says why
                variant, why = "float", f"{sibling.name} refused: {type(exc).__name__}: {exc}"
        else:
            variant, why = choose_variant(path, daemon, None)
        self.model, self.model_id = served, self.model_id + 1
        self.encoders.clear()
        # recorded False: an older export, only its training window counts as checked
        checked, recorded = served.info.checked_sizes_hw()
        device, device_why = worker_device(daemon.frames.device, daemon.frames.inference)
        inference, inference_why = worker_inference(daemon)
        return ModelLoaded(
            path=path, info=served.info, served=str(sibling) if variant == "int8" else path,
            variant=variant, variant_reason=why, providers=tuple(served.providers),
            inference=inference, inference_reason=inference_why, device=str(device),
            device_reason=device_why, window_hw=window_hw, checked_sizes_hw=tuple(checked),
            checked_sizes_recorded=recorded, loaded_s=time.time(),
            # the memory its session and test run took in the load's probe (open_model)
            load_memory_mb=getattr(served, "load_memory_mb", None), size_warning=warning or "",
            tuned_for=dict(tuned_for) if tuned_for else None,
            bench_warning=f"{other}: served because daemon.frames.allow_other_bench = true"
            if other else "")

    def load_scene(self, path: str) -> SceneLoaded:
        """The scene file at `path`, read within `daemon.paths.max_gaussians`: its counts,
        centre and up axis."""
        load = read_scene(path, self.config.daemon.paths.max_gaussians)
        frame = scene_frame(load.gaussians, path)
        self.scene = Scene(load.gaussians, frame)
        self.scene_id += 1
        self.encoders.clear()
        return SceneLoaded(path=path, **load.counts(), center=frame.center, up=frame.up)

    def encoder(self, refocus_m: float) -> Encoder:
        if refocus_m not in self.encoders:
            if len(self.encoders) >= MAX_ENCODERS:
                self.encoders.clear()
            settings = frame_settings(self.config, self.model.info,
                                      self.calibration.active(), refocus_m=refocus_m)
            self.encoders[refocus_m] = Encoder(settings, device=self.model.device,
                                               cuda_graphs=self.config.daemon.frames.cuda_graphs)
        return self.encoders[refocus_m]

    def frame(self, view: View) -> tuple[FrameMessage, np.ndarray | None]:
        """The frame for `view`, holding its arrays (computed, or from the frame cache), and
        from a model of K > 1 subframes all K `[K, 3, h, w]` uint8 (None for one)."""
        if self.model is None:
            raise RuntimeError("no model loaded (load_model, or daemon.frames.model)")
        if self.scene is None:
            raise RuntimeError("no scene loaded (load_scene, or daemon.paths.scene)")
        view = view.with_quality("network")  # the tiers above refine this frame (`Refiner`)
        key = (view, self.model_id, self.scene_id)
        if key in self.cache:
            self.cache.move_to_end(key)
            cached, subframes = self.cache[key]
            return cached.from_cache(), subframes
        frame = compute_frame(view, self.scene, self.model, self.encoder(view.refocus_m))
        message = FrameMessage.of_arrays(
            frame.region, frame.grey, frame.preview, StageTimes.from_seconds(frame.timings_s),
            frame.clipped_fraction,
            envelope_warnings(view, self.scene.frame, self.model.info.pose_envelope))
        if self.cache_size:
            self.cache[key] = (message, frame.subframes)
            while len(self.cache) > self.cache_size:
                self.cache.popitem(last=False)
        return message, frame.subframes


class Refiner:
    """Progressive refinement (issue 34) in a thread of the worker: once a view's network frame
    is sent, a view asking for a higher tier (`View.quality`) is refined while no newer message
    waits, and each better frame goes to the daemon as a `BetterFrame` (a `RefinedFrame`); a
    failure goes as a `RefineFailed`. `cancel` (any message from the daemon but a capture
    answer or a refine slot given back: a new view, a load, stop) stops it between steps and
    waits for the thread, which polls between each colour's propagation: the new view's frame
    starts within one of them."""

    def __init__(self, send: Callable[[FromWorker], None], config: Config,
                 calibration: CalibrationStore, slots: FrameSlots | None = None) -> None:
        """`calibration`: the worker's (the bench model, citl's camera mapping). `slots`: the
        daemon's shared memory, whose refine slots carry the better frames (None: they are
        pickled through the pipe)."""
        self.send = send
        self.config = config
        self.calibration = calibration
        self.slots = slots
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._capture: RemoteCapture | None = None  # citl's, while a citl view is refined

    def deliver(self, req_id: int, reply: CaptureReply) -> None:
        """The daemon's captures for the citl step waiting on them (dropped when none waits:
        the refinement that asked was cancelled)."""
        capture = self._capture
        if capture is not None:
            capture.deliver(req_id, reply)

    def start(self, seq: int, view: View, state: _WorkerState, network: np.ndarray) -> None:
        """Refine view `seq` from its network frame's grey region `network` `[3, h, w]`."""
        self.cancel()
        if view.quality == "network":
            return
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(seq, view, state.model, state.scene, network, self._stop),
            name=f"refine-{seq}", daemon=True)
        self._thread.start()

    def start_without_model(self, seq: int, view: View, state: _WorkerState,
                            first: Callable[[FrameMessage], None]) -> None:
        """View `seq` of a scene with no model loaded (its `quality` above "network"): the exact
        frame (`scene_info`: the configured optics, the view's own depth mapping) is its first
        frame, handed to `first`, then refined at the view's tier. Seconds on a CPU."""
        self.cancel()
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run_without_model, args=(seq, view, state.scene, first, self._stop),
            name=f"exact-{seq}", daemon=True)
        self._thread.start()

    def cancel(self) -> None:
        """Stop the refinement running (if any) and wait for its thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _run(self, seq: int, view: View, model: Any, scene: Any, network: np.ndarray,
             stop: threading.Event) -> None:
        try:
            # Its own encoder (the worker's keeps scratch buffers for the frames it computes),
            # with the frames' settings: the refined frame's region is the network frame's.
            p = prepare(self.config, view, scene, info=model.info,
                        calibration=self.calibration.active(), device=model.device,
                        cancelled=stop.is_set)
            self._refine(seq, view, p, network, stop)
        except Cancelled:  # a newer message stopped it (in the inversion or a step): no error
            pass
        except Exception as exc:  # reported to the daemon; the frame shown stays
            self.send(RefineFailed(seq, f"{type(exc).__name__}: {exc}"))

    def _refine(self, seq: int, view: View, p: Prepared, start: np.ndarray,
                stop: threading.Event) -> None:
        """Refine prepared view `seq` from the grey region `start` at its tier, sending each
        better frame as a `BetterFrame` and the best one when it stops (unless a newer message
        cancelled it)."""
        enc = p.encoder

        def better(refined: Refined, wait_s: float = BETTER_WAIT_S) -> None:
            frame = RefinedFrame(enc.region, refined.grey, refined.report.to_json())
            # Into a refine slot (a copy), or pickled now, under the send lock: either way the
            # refinement's own array never crosses.
            if self.slots is not None:
                frame = self.slots.write_refined(frame, wait_s)
            self.send(BetterFrame(seq, frame))

        capture = self._remote_capture(seq, view, enc, stop)
        refined = refine_view(p, view.quality, self.config.refine, start=start, capture=capture,
                              cancelled=stop.is_set, on_better=better)
        if refined.report.stop != "cancelled":
            better(refined, FINAL_WAIT_S)

    def _remote_capture(self, seq: int, view: View, enc: Encoder, stop: threading.Event
                        ) -> RemoteCapture | None:
        """citl's captures, from the daemon's bench (None for the other tiers). The calibration
        maps the camera onto the SLM and the focus onto the stage: without one, a ValueError
        naming it."""
        if view.quality != "citl":
            return None
        cal = self.calibration.active()
        if cal is None:
            raise ValueError("quality = 'citl' needs a calibration (calibration.file): it maps "
                             "the camera onto the SLM and the focus onto the stage")
        camera_pitch_m = self.config.devices.camera_settings.pixel_pitch_um * 1e-6
        self._capture = RemoteCapture(self.send, seq, enc, cal, stop, camera_pitch_m=camera_pitch_m)
        return self._capture

    def _run_without_model(self, seq: int, view: View, scene: Any,
                           first: Callable[[FrameMessage], None], stop: threading.Event) -> None:
        try:
            t0 = time.perf_counter()
            config = self.config
            window_hw = (config.optics.hologram_height_px, config.optics.hologram_width_px)
            if config.daemon.frames.size_px:
                window_hw = (config.daemon.frames.size_px[1], config.daemon.frames.size_px[0])
            # A newer view cancels it between its stages and between the light field's
            # elemental views (`stop`), so the newer view's exact frame starts at once.
            p = prepare(config, view, scene, window_hw=window_hw,
                        calibration=self.calibration.active(), cancelled=stop.is_set)
            first(replace(FrameMessage.of_arrays(
                p.encoder.region, p.exact_grey, preview_levels(p.rgb),
                StageTimes(render_s=time.perf_counter() - t0), p.clipped), tier="exact"))
            if view.quality == "exact" or stop.is_set():
                return
            self._refine(seq, view, p, p.exact_grey, stop)
        except Cancelled:
            self.send(FrameCancelled(seq))
        except Exception as exc:
            self.send(FrameFailed(seq, f"{type(exc).__name__}: {exc}"))


def worker_main(conn: Any, config_data: dict[str, Any],
                calibration: Calibration | None = None,
                slots: dict[str, Any] | None = None) -> None:
    """Entry point of the spawned process. `calibration`: the daemon's accepted one (kept when
    the file on disk is refused, as in the daemon). `slots`: the daemon's shared-memory slots
    ({"names": [...], "bytes": n}; None: frames are pickled through the pipe)."""
    config = Config.model_validate(config_data)
    _set_threads(int(config.daemon.frames.worker_threads))
    state = _WorkerState(config, CalibrationStore.of(config, accepted=calibration))
    shm = (FrameSlots(slots["names"], slots["bytes"], slots.get("refine_names", ()),
                      slots.get("refine_bytes", 0)) if slots else None)
    try:
        _serve(conn, state, shm)
    finally:
        if shm is not None:
            shm.close()


def _serve(conn: Any, state: _WorkerState, shm: FrameSlots | None) -> None:
    lock = threading.Lock()

    def send(msg: FromWorker) -> None:  # the refinement thread sends too
        with lock:
            conn.send(msg)

    refiner = Refiner(send, state.config, state.calibration, shm)
    try:
        _serve_loop(conn, send, state, shm, refiner)
    finally:
        refiner.cancel()


def _serve_loop(conn: Any, send: Callable[[FromWorker], None], state: _WorkerState,
                shm: FrameSlots | None, refiner: Refiner) -> None:
    send(WorkerReady(os.getpid()))
    while True:
        try:
            msgs = [conn.recv()]
            while conn.poll(0):
                msgs.append(conn.recv())
        except (EOFError, OSError):
            return  # the daemon is gone: nothing to show frames to
        # The bench's captures go to the citl step waiting for them, and refine slots given
        # back return to the pool; any other message the worker takes means the view being
        # refined is no longer alone. One it does not take is refused by name, and changes
        # nothing.
        commands: list[FrameRequest | LoadModel | LoadScene | CancelFrame | Stop] = []
        for msg in msgs:
            match msg:
                case CaptureAnswer(req_id=req_id, reply=reply):
                    refiner.deliver(req_id, reply)
                case RefineSlotFree(slot=slot):
                    if shm is not None:
                        shm.free_refine.put(int(slot))
                case FrameRequest() | LoadModel() | LoadScene() | CancelFrame() | Stop():
                    commands.append(msg)
                case _:
                    send(MessageRefused(type(msg).__name__,
                                        refusal(msg, "the frame worker", TO_WORKER)))
        if not commands:
            continue
        refiner.cancel()
        latest: FrameRequest | None = None
        for msg in commands:
            match msg:
                case Stop():
                    return
                case CancelFrame():  # the refinement (or an exact frame) only: done above
                    continue
                case FrameRequest():
                    latest = msg  # latest wins: an older view that was overtaken is never computed
                case LoadModel(req_id=req_id, path=path):
                    _load(send, req_id, state.load_model, path)
                case LoadScene(req_id=req_id, path=path):
                    _load(send, req_id, state.load_scene, path)
        if latest is not None:
            _frame(send, state, shm, refiner, latest)


def _load(send: Callable[[FromWorker], None], req_id: int,
          load: Callable[[str], ModelLoaded | SceneLoaded], path: str) -> None:
    """Load `path`, answering `Loaded` or, with the reason, `LoadFailed` (the old model or scene
    stays)."""
    try:
        result = load(path)
    except Exception as exc:  # reported to the daemon; the old model/scene stays
        send(LoadFailed(req_id, f"{type(exc).__name__}: {exc}"))
        return
    send(Loaded(req_id, result))


def _frame(send: Callable[[FromWorker], None], state: _WorkerState, shm: FrameSlots | None,
           refiner: Refiner, request: FrameRequest) -> None:
    """The frame `request` asks for, into its slot, answered `FrameDone` (or `FrameFailed`);
    then its refinement, when the view asks for a tier above the network's."""
    seq, view, slot = request.seq, request.view, request.slot
    if state.model is None and state.scene is not None and view.quality != "network":

        def first(message: FrameMessage) -> None:
            if slot is not None and shm is not None:
                message = shm.write(slot, message)
            send(FrameDone(seq, message.ready(time.monotonic())))

        refiner.start_without_model(seq, view, state, first)
        return
    try:
        message, subframes = state.frame(view)
        network = message.grey
        if slot is not None and shm is not None:
            message = shm.write(slot, message)
        cycle = None if subframes is None else network_subframes(message, subframes, shm)
        # When the frame was whole in its slot (CLOCK_MONOTONIC, shared by both processes):
        # the daemon's "late" counts from here.
        send(FrameDone(seq, message.ready(time.monotonic()), cycle))
    except Exception as exc:
        send(FrameFailed(seq, f"{type(exc).__name__}: {exc}"))
        return
    if network is not None:
        refiner.start(seq, view, state, network)


def network_subframes(message: FrameMessage, subframes: np.ndarray, shm: FrameSlots | None
                      ) -> RefinedFrame:
    """A network frame's K subframes `[K, 3, h, w]` as the daemon cycles them (a `RefinedFrame`
    of tier "network"): in a free refine slot, or pickled in the message when none is free (a
    frame never waits for one: the daemon gives slots back through the pipe this thread
    reads)."""
    seconds = round(sum(message.timings.seconds().values()), 6)
    report = {"tier": "network", "iterations": 0, "seconds": seconds,
              "loss": None, "psnr_db": None, "start_psnr_db": None, "stop": "subframes"}
    frame = RefinedFrame(message.region, np.ascontiguousarray(subframes), report)
    if shm is None:
        return frame
    written = shm.write_refined(frame, 0.0)
    return written if written.slot is not None else frame

