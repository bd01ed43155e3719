"""Where frames are computed: `daemon.frames.device` -> a torch device, and the one host copy a CUDA
frame makes (issue 23).

`resolve_device("auto" | "cpu" | "cuda" | "cuda:N")`: "auto" is the first CUDA device when
torch sees one, else the CPU; a CUDA device torch does not see is a ValueError, never a silent
fall back to the CPU (a bench configured for the GPU that quietly ran 20x slower would say
nothing of why). On CUDA every stage of a frame runs on the GPU and only the uint8 panel region
(and the uint8 preview of the rendered view) crosses to the host: `HostCopy` copies it
asynchronously into pinned memory and waits for that copy alone. `inference_backend` says
what runs the network there (`daemon.frames.inference`: onnxruntime, or torch where onnxruntime has
no CUDA provider).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from nhfd.config import device_choice
from nhfd.models.export import CUDA
from nhfd.scene import gsplat_backend

SETTING = "daemon.frames.device"
log = logging.getLogger(__name__)


def resolve_device(value: str | torch.device, setting: str = SETTING, *,
                   cuda_count: int | None = None) -> torch.device:
    """The torch device `value` names; `cuda_count` (tests) stands in for what torch sees.

    A ValueError (`nhfd.config.device_choice`'s) names `setting`, the value, and the allowed
    values or the CUDA devices torch sees."""
    if isinstance(value, torch.device):
        value = str(value)
    count = _cuda_count() if cuda_count is None else int(cuda_count)
    return torch.device(device_choice(value, setting, cuda_count=count))


INFERENCE_SETTING = "daemon.frames.inference"


def inference_backend(inference: str, device: torch.device, onnx_providers: list[str],
                      setting: str = SETTING) -> tuple[str, str]:
    """("onnxruntime" | "torch", why): what runs the network on `device` for
    `daemon.frames.inference` = `inference`, given the providers this onnxruntime has.

    "auto" is onnxruntime (on the CPU, 2.4x faster than torch for these networks) except on a CUDA
    device whose onnxruntime has no CUDA provider (the CPU build beside a CUDA torch, or a bench
    that cannot install onnxruntime-gpu): torch there, so the network runs on the GPU with the
    other stages. "onnxruntime" on such a device is refused, naming both settings and the fix."""
    if inference == "torch":
        return "torch", f'{INFERENCE_SETTING} = "torch": the network in torch on {device}'
    if device.type != "cuda" or CUDA in onnx_providers:
        return "onnxruntime", f'{INFERENCE_SETTING} = "{inference}": onnxruntime on {device}'
    missing = (f"this onnxruntime has no {CUDA} (available: "
               f"{', '.join(onnx_providers)})")
    if inference == "onnxruntime":
        raise ValueError(f'{setting} = {device} with {INFERENCE_SETTING} = "onnxruntime": '
                         f"{missing}; install onnxruntime-gpu in place of onnxruntime, or set "
                         f'{INFERENCE_SETTING} to "auto" or "torch"')
    return "torch", f'{INFERENCE_SETTING} = "auto": {missing}, so the network runs in torch on ' \
                    f"{device}"


def check_cuda_frames(value: str, device: torch.device, onnx_providers: list[str],
                      setting: str = SETTING, inference: str = "auto") -> None:
    """Refuse, before a model loads, a CUDA device whose frames could not be computed: gsplat
    absent (every frame would fail to render), or `inference` = "onnxruntime" with an
    onnxruntime without its CUDA provider (`inference_backend`). The message names `setting`,
    its value (and what "auto" chose) and the fix."""
    if device.type != "cuda":
        return
    chose = f" (chose {device}: torch sees a GPU)" if str(value).strip() == "auto" else ""
    if not gsplat_backend.available():
        raise ValueError(f"{setting} = {value!r}{chose}: CUDA frames render with gsplat, which "
                         "does not import here; pip install 'nhfd[gpu]', or set it to \"cpu\"")
    inference_backend(inference, device, onnx_providers, setting)


def frame_device(value: str, onnx_providers: list[str], setting: str = SETTING,
                 inference: str = "auto") -> tuple[torch.device, str]:
    """The device frames are computed on, and why. "auto" takes the GPU only where its frame
    path is installed (gsplat; and onnxruntime's CUDA provider where `inference` is
    "onnxruntime"): otherwise it keeps serving frames on the CPU, and the reason says what is
    missing. A device named explicitly ("cuda", "cuda:N") that cannot run frames is refused
    (`check_cuda_frames`): never a silent fall back."""
    device = resolve_device(value, setting)
    if device.type != "cuda":
        return device, f"{setting} = {value!r}: the CPU"
    try:
        check_cuda_frames(value, device, onnx_providers, setting, inference)
    except ValueError as e:
        if str(value).strip().lower() != "auto":
            raise
        return torch.device("cpu"), f"{e}; computing frames on the CPU"
    return device, f"{setting} = {value!r}: {device}"


def _cuda_count() -> int:
    return torch.cuda.device_count() if torch.cuda.is_available() else 0


def gpu_name(device: torch.device) -> str:
    """The GPU's name as the driver gives it ("NVIDIA H100 80GB HBM3"): part of the TensorRT
    engine cache's key (an engine is built for one GPU model)."""
    return torch.cuda.get_device_name(device)


class HostCopy:
    """Device tensors -> host NumPy arrays through pinned memory, copied asynchronously on the
    device's current stream: `start` queues the copies, `wait` waits for those copies only (a
    CUDA event), not for the whole device.

    Each copy's pinned tensor comes from torch's caching host allocator: a block is reused only
    once nothing refers to it, so the arrays returned stay valid while a caller keeps them (the
    worker's frame cache does), and a steady stream of frames allocates nothing new. On the CPU
    the tensors' own memory is returned (no copy)."""

    def __init__(self, device: torch.device | str) -> None:
        self.device = torch.device(device)

    def start(self, *tensors: torch.Tensor | None) -> tuple[list[torch.Tensor | None], Any]:
        """Queue the copies of `tensors` (None passes through) into pinned host tensors; the
        result is the host tensors and the event that marks them done (None on the CPU)."""
        if self.device.type != "cuda":
            return [None if t is None else t.detach() for t in tensors], None
        hosts: list[torch.Tensor | None] = []
        for t in tensors:
            if t is None:
                hosts.append(None)
                continue
            host = torch.empty(t.shape, dtype=t.dtype, pin_memory=True)
            host.copy_(t.detach(), non_blocking=True)
            hosts.append(host)
        done = torch.cuda.Event()
        done.record(torch.cuda.current_stream(self.device))
        return hosts, done

    def wait(self, started: tuple[list[torch.Tensor | None], Any]) -> list[np.ndarray | None]:
        """Wait for the copies `start` queued and return them as NumPy arrays (shapes and
        dtypes of the device tensors)."""
        hosts, done = started
        if done is not None:
            done.synchronize()
        return [None if h is None else h.numpy() for h in hosts]

    def fetch(self, *tensors: torch.Tensor | None) -> list[np.ndarray | None]:
        """`start` then `wait`: the tensors as host NumPy arrays."""
        return self.wait(self.start(*tensors))


class WallMark:
    """A reading of the host's clock with the part of `torch.cuda.Event`'s interface that
    `StageClock` uses, so that the CPU and CUDA clocks share one code path."""

    def __init__(self) -> None:
        self.t_s = time.perf_counter()

    def synchronize(self) -> None:
        """Nothing to wait for: the reading was taken when the mark was made."""

    def elapsed_time(self, end: WallMark) -> float:
        """Milliseconds from this mark to `end` (torch.cuda.Event's unit)."""
        return (end.t_s - self.t_s) * 1e3


class StageClock:
    """Seconds per stage: each `stage(name)` ends the stage that began at the previous one.

    On the CPU, wall-clock marks. On CUDA, events recorded on the device's stream (no
    synchronisation between stages: the frame is queued as fast as the host can); `seconds`
    reads them after the last one has completed. Both go through the same marks: N stages are
    N + 1 marks, each stage the span between two neighbours."""

    def __init__(self, device: torch.device | None = None) -> None:
        dev = torch.device(device) if device is not None else torch.device("cpu")
        self._new_mark = (lambda: _cuda_mark(dev)) if dev.type == "cuda" else WallMark
        self._names: list[str] = []
        self._marks = [self._new_mark()]

    def stage(self, name: str) -> None:
        """End the current stage as `name` and begin the next one."""
        self._names.append(name)
        self._marks.append(self._new_mark())

    @property
    def seconds(self) -> dict[str, float]:
        """Each stage's duration in seconds, by name, in order (waits for the last mark); a
        stage named more than once (each of K subframes) sums its turns."""
        self._marks[-1].synchronize()
        out: dict[str, float] = {}
        for n, a, b in zip(self._names, self._marks[:-1], self._marks[1:], strict=True):
            out[n] = out.get(n, 0.0) + 1e-3 * a.elapsed_time(b)
        return out


def _cuda_mark(device: torch.device) -> Any:
    e = torch.cuda.Event(enable_timing=True)
    e.record(torch.cuda.current_stream(device))
    return e


# Eager runs of a stage before its capture: cuDNN's algorithm choice, cuFFT's plans, the
# encoder's kernels and scratch buffers and the caching allocator's blocks all settle on the
# first runs, and none of them may happen inside a capture.
GRAPH_WARMUP_RUNS = 3
GRAPHS_SETTING = "daemon.frames.cuda_graphs"


class CudaGraphs:
    """Frame stages replayed as CUDA graphs (`daemon.frames.cuda_graphs`), one per stage and input
    shape: after `GRAPH_WARMUP_RUNS` eager runs on a side stream, the stage's kernels are
    captured once, and each later frame copies its inputs into the graph's own and replays the
    whole stage with one launch. A 1920 x 1080 frame launches a few hundred small kernels; on an
    H200 the host's launches, not the GPU, bounded it (10.1 ms of wall time for 5.3 ms of GPU
    work, docs/gpu.md).

    `run(name, fn, *inputs)`: `fn`'s tensors for `inputs` (tensors on the device). A captured
    stage's outputs are the graph's own memory: valid until that stage runs again (the frame
    path copies them to the host before its next frame). On the CPU, when disabled, or for a
    stage whose capture failed (named in `failed`, logged once, then run eagerly), `fn` runs as
    it is. `fn` must not synchronise with the host nor copy from pageable host memory."""

    def __init__(self, device: torch.device | str, enabled: bool = True) -> None:
        self.device = torch.device(device)
        self.enabled = bool(enabled) and self.device.type == "cuda"
        self.failed: dict[str, str] = {}  # stage -> why its capture failed
        self._graphs: dict[tuple, _Graph] = {}

    def run(self, name: str, fn: Callable[..., Any], *inputs: torch.Tensor) -> Any:
        """`fn(*inputs)`, from a replayed graph where one is (or can be) captured."""
        if not self.enabled or name in self.failed:
            return fn(*inputs)
        key = (name, *((tuple(t.shape), t.dtype, tuple(t.stride())) for t in inputs))
        graph = self._graphs.get(key)
        if graph is None:
            try:
                graph = _Graph(fn, inputs, self.device)
            except Exception as exc:  # any capture failure: run eagerly
                self.failed[name] = f"{type(exc).__name__}: {exc}"
                log.warning("%s: stage %r runs without a CUDA graph: %s", GRAPHS_SETTING, name,
                            self.failed[name])
                torch.cuda.synchronize(self.device)
                return fn(*inputs)
            self._graphs[key] = graph
        return graph.replay(inputs)


class _Graph:
    """One captured stage: its static inputs, the graph and its static outputs."""

    def __init__(self, fn: Callable[..., Any], inputs: tuple[torch.Tensor, ...],
                 device: torch.device) -> None:
        self.inputs = tuple(t.detach().clone() for t in inputs)
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(GRAPH_WARMUP_RUNS):
                fn(*self.inputs)
        torch.cuda.current_stream(device).wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.outputs = fn(*self.inputs)

    def replay(self, inputs: tuple[torch.Tensor, ...]) -> Any:
        for static, t in zip(self.inputs, inputs, strict=True):
            static.copy_(t)
        self.graph.replay()
        return self.outputs
