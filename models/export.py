"""ONNX export of a trained run, its check against torch, and the runtime loader.

The exported graph is `nhfd.models.serving.ServingNet`: the network's function written with
operators onnxruntime runs fast, checked against `NHFNet.forward`. It takes `rgb` `[B, 3, H, W]`
(or `rgbd` `[B, 4, H, W]` for a network that also sees the mapped depth, `nhfd.models.inputs`)
with H and W dynamic multiples of the network's stride (`input_multiple` in the metadata) and
returns `amplitude` and `phase`. `OnnxModel` pads any input to that multiple outside the graph
and crops back, and refuses a model trained for optics other than the configured ones.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import stat
import subprocess
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nhfd.config import Config, device_choice
from nhfd.dataset.build import sha256_file
from nhfd.model_info import ModelInfo
from nhfd.models.inputs import seeded_input
from nhfd.models.metadata import (
    METADATA_KEY,
    NotAModel,
    build_metadata,
    check_metadata,
    expected_from_config,
    parse_metadata,
    parse_model_info,
    training_poses,
)
from nhfd.models.serving import ServingNet
from nhfd.models.sizes import check_and_record, sizes_to_check
from nhfd.models.train import load_run

MIN_OPSET = 18
# What the exported graph is written as (`nhfd.models.serving`); caches of exports compare it.
GRAPH_FORM = "serving-2"
# Sizes (in strides) the export is checked at, besides the example it was traced with.
CHECK_SIZES_STRIDES = ((3, 5), (5, 4))


@dataclass
class ExportResult:
    """An exported model: its path, the largest torch-onnxruntime difference (NaN unchecked),
    the input sizes `(H, W)` px it was compared at, and its metadata."""

    path: Path
    max_abs_diff: float
    checked_sizes: list[tuple[int, int]]
    metadata: dict


def export_onnx(
    run_dir: str | Path, out_path: str | Path, *, opset: int = MIN_OPSET, check: bool = True,
    source_scene: str | Path | None = None, check_sizes_hw: list[tuple[int, int]] | None = None,
) -> ExportResult:
    """Export a run's network to ONNX with its metadata; check it with onnxruntime against torch
    (max abs difference over amplitude and phase, at sizes other than the traced one).
    `source_scene`: the file the dataset's scene was reduced from (`nhfd model build`), recorded
    as `source_scene_sha256` so that the original file serves the model too. `check_sizes_hw`:
    the input sizes recorded as `checked_sizes` besides the training window
    (`nhfd.models.sizes.default_sizes_hw` unless given)."""
    import onnx

    if opset < MIN_OPSET:
        raise ValueError(f"--opset {opset}: must be {MIN_OPSET} or newer")
    net, info = load_run(run_dir)
    m = net.spec.multiple
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    name = net.spec.inputs
    example = torch.rand(1, net.spec.channels, 2 * m, 3 * m)
    hd, wd = torch.export.Dim("h_strides", min=1, max=8192 // m), torch.export.Dim(
        "w_strides", min=1, max=8192 // m
    )
    dynamic = ({0: torch.export.Dim("batch", min=1, max=64), 2: m * hd, 3: m * wd},)
    tmp = out_path.with_name(out_path.name + ".tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's deprecation chatter, not ours
        torch.onnx.export(
            ServingNet(net).eval(), (example,), str(tmp), input_names=[name],
            output_names=["amplitude", "phase"], opset_version=opset, dynamo=True,
            dynamic_shapes=dynamic, external_data=False, verbose=False,
        )  # fmt: skip
    model = onnx.load(str(tmp))
    meta = build_metadata(info, opset=opset, train_poses=run_training_poses(info))
    if source_scene is not None:
        meta["source_scene_sha256"] = sha256_file(Path(source_scene))
    del model.metadata_props[:]
    props = ((METADATA_KEY, json.dumps(meta)), ("nhfd_version", str(meta["nhfd_version"])))
    for key, value in props:
        prop = model.metadata_props.add()
        prop.key, prop.value = key, value
    model.producer_name = "nhfd"
    onnx.checker.check_model(model)
    onnx.save(model, str(tmp))
    tmp.replace(out_path)
    diff, sizes = (float("nan"), [])
    if check:
        diff, sizes = compare_with_torch(net, out_path)
        meta = check_and_record(out_path, sizes_to_check(meta, check_sizes_hw),
                                lambda hw: compare_with_torch(net, out_path, [hw])[0])
    return ExportResult(out_path, diff, sizes, meta)


def run_training_poses(run_info: dict) -> dict | None:
    """The training poses of a run (`training_poses`), read from the dataset it was trained on
    when that folder still holds the same manifest; None otherwise."""
    ds = run_info.get("dataset") or {}
    path = Path(str(ds.get("data_dir", ""))) / "manifest.json"
    if not ds.get("data_dir") or not path.is_file():
        return None
    manifest = json.loads(path.read_text())
    if manifest.get("key") != ds.get("manifest_key"):
        return None
    return training_poses(manifest)


def compare_with_torch(net, onnx_path: str | Path, sizes_hw: list[tuple[int, int]] | None = None
                       ) -> tuple[float, list[tuple[int, int]]]:  # fmt: skip
    """Max abs difference between torch and onnxruntime outputs on random inputs, at
    `sizes_hw` (default: CHECK_SIZES_STRIDES)."""

    model = OnnxModel(onnx_path)
    m = net.spec.multiple
    worst, sizes = 0.0, []
    for h, w in sizes_hw or [(hs * m, ws * m) for hs, ws in CHECK_SIZES_STRIDES]:
        x = seeded_input(net.spec.channels, (h, w), seed=0)
        with torch.no_grad():
            ta, tp = net(torch.from_numpy(x))
        oa, op = model.run_raw(x)
        # NaN anywhere is a failed check: max() would drop it, np.max keeps it
        d = float(np.max([np.abs(ta.numpy() - oa).max(), np.abs(tp.numpy() - op).max()]))
        worst = max(worst, d if np.isfinite(d) else float("inf"))
        sizes.append((h, w))
    return worst, sizes


# Where a model runs unless told otherwise (the daemon takes `daemon.frames.onnx_providers`).
CPU_ONLY = ("CPUExecutionProvider",)
TENSORRT, CUDA = "TensorrtExecutionProvider", "CUDAExecutionProvider"
# The providers that run a graph on a CUDA device, in the order a CUDA device prefers them:
# TensorRT's engines first, the CUDA provider as the fallback (nodes TensorRT does not take, or
# no TensorRT libraries: onnxruntime then runs the whole graph on the CUDA provider).
GPU_PROVIDERS = (TENSORRT, CUDA)
# A provider with its options, as onnxruntime takes them.
Provider = str | tuple[str, dict[str, Any]]


def provider_name(p: Provider) -> str:
    """The execution provider's name, with or without its options."""
    return p if isinstance(p, str) else p[0]


def check_providers(wanted: Sequence[Provider], available: list[str],
                    setting: str = "providers") -> list[Provider]:  # fmt: skip
    """`wanted` execution providers, in order, or a ValueError naming `setting`, the missing
    ones, and what this onnxruntime has."""
    wanted = list(wanted)
    missing = [provider_name(p) for p in wanted if provider_name(p) not in available]
    if missing:
        raise ValueError(f"{setting}: {', '.join(missing)} not available in this onnxruntime; "
                         f"available: {', '.join(available)}")
    return wanted


def default_engine_cache_dir(environ: dict[str, str] | None = None) -> Path:
    """Where TensorRT engines go when `daemon.frames.engine_cache_dir` is "": $XDG_CACHE_HOME/nhfd/
    tensorrt, else ~/.cache/nhfd/tensorrt."""
    env = os.environ if environ is None else environ
    base = env.get("XDG_CACHE_HOME") or str(Path(env.get("HOME") or Path.home()) / ".cache")
    return Path(base) / "nhfd" / "tensorrt"


def engine_cache_key(model_sha256: str, input_shape: Sequence[int] | None, gpu_name: str
                     ) -> str:
    """The folder name of one TensorRT engine: an engine is built for one graph (the model
    file's SHA-256), one input shape (the profile it was optimised for; None: "dynamic", the
    shapes onnxruntime meets) and one GPU model, and a cached one is reused only when all three
    match."""
    sha = str(model_sha256).lower()
    if not re.fullmatch(r"[0-9a-f]{64}", sha):
        raise ValueError(f"model_sha256 = {model_sha256!r}: expected 64 hex digits")
    shape = "dynamic"
    if input_shape is not None:
        dims = [int(v) for v in input_shape]
        if len(dims) != 4 or min(dims) < 1:
            raise ValueError(f"input_shape = {list(input_shape)}: expected [B, C, H, W], each "
                             ">= 1")
        shape = "x".join(map(str, dims))
    gpu = re.sub(r"[^a-z0-9]+", "-", str(gpu_name).lower()).strip("-")
    if not gpu:
        raise ValueError(f"gpu_name = {gpu_name!r}: expected the GPU's name")
    return f"{sha[:16]}-{shape}-{gpu}"


def execution_providers(device: str, available: list[str], configured: Sequence[str], *,
                        setting: str = "daemon.frames.onnx_providers", device_setting: str =
                        "daemon.frames.device", engine_cache_dir: str | Path | None = None,
                        model_sha256: str = "", input_name: str = "rgb",
                        input_shape: Sequence[int] | None = None, gpu_name: str = "",
                        tensorrt_fp16: bool = False) -> list[Provider]:
    """The providers, with their options, a session for `device` ("cpu", "cuda" or "cuda:N")
    is created with. Pure: what onnxruntime has (`available`) and the configured list are given.

    CPU: the configured list as it is, each one checked (today's behaviour). CUDA: the GPU
    providers of the configured list, in its order (checked); when it names none (the default,
    ["CPUExecutionProvider"]), TensorRT where this onnxruntime has it, then CUDA, which must be
    there (a ValueError names `device_setting` and what onnxruntime has); the CPU provider last.
    Each GPU provider gets the device index; TensorRT also an engine cache of its own,
    `engine_cache_dir` / `engine_cache_key(model_sha256, input_shape, gpu_name)`, a timing
    cache shared by that GPU's engines, and with `input_shape` a profile of exactly that shape
    (an engine optimised for the frames it serves)."""
    # A resolved device ("auto" picked already); the name only: what torch sees is not asked.
    dev = device_choice(device, device_setting, cuda_count=None, allowed=("cpu", "cuda", "cuda:N"))
    if dev == "cpu":
        return check_providers(list(configured), available, setting)
    index = int(dev.partition(":")[2])
    wanted = [p for p in configured if p in GPU_PROVIDERS]
    if wanted:
        check_providers(wanted, available, setting)
    else:
        if CUDA not in available:
            raise ValueError(f"{device_setting} = {device!r}: this onnxruntime has no "
                             f"{CUDA} (available: {', '.join(available)}); install "
                             "onnxruntime-gpu, or set it to \"cpu\"")
        wanted = [p for p in GPU_PROVIDERS if p in available]
    out: list[Provider] = []
    for name in wanted:
        options: dict[str, Any] = {"device_id": index}
        if name == TENSORRT:
            root = Path(engine_cache_dir) if engine_cache_dir else default_engine_cache_dir()
            shape = list(input_shape) if input_shape is not None else None
            key = engine_cache_key(model_sha256, shape, gpu_name)
            options.update({
                "trt_engine_cache_enable": True,
                "trt_engine_cache_path": str(root / key),
                "trt_timing_cache_enable": True,
                "trt_timing_cache_path": str(root),
                "trt_fp16_enable": bool(tensorrt_fp16),
            })
            if shape is not None:
                profile = f"{input_name}:{'x'.join(str(int(v)) for v in shape)}"
                options.update({"trt_profile_min_shapes": profile,
                                "trt_profile_opt_shapes": profile,
                                "trt_profile_max_shapes": profile})
        out.append((name, options))
    out.append("CPUExecutionProvider")
    return out


def read_model_file(path: str | Path, *, max_bytes: int | None = None,
                    setting: str = "max_bytes") -> Any:
    """The ONNX model at `path` (onnx's `ModelProto`), parsed without a session. Refused
    (`NotAModel`, or `ModelOverBudget` naming `setting`) unless it is a regular file of at most
    `max_bytes` (None: any size) that keeps every tensor inside itself: an nhfd export never
    uses external data (`external_data=False`), and a reference to another file could name any
    file at any length (/dev/zero). The size is read from the open file, and no more than
    `max_bytes` + 1 bytes are read, so a file swapped or grown meanwhile is refused too."""
    import onnx

    name = str(path)
    try:
        # O_NONBLOCK: a FIFO put where a model was expected must not block the open
        fd = os.open(name, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise FileNotFoundError(f"{name}: no such model file") from None
    except OSError as exc:
        raise NotAModel(f"{name}: cannot be opened ({exc.strerror})") from None
    with os.fdopen(fd, "rb") as f:
        info = os.fstat(f.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise NotAModel(f"{name}: not a regular file (a model is read only from one)")
        if max_bytes is not None and info.st_size > max_bytes:
            raise ModelOverBudget(f"{name}: {info.st_size / 2**20:.1f} MB, more than {setting} "
                                  f"= {max_bytes / 2**20:g} MB (its weights alone would not fit)")
        data = f.read() if max_bytes is None else f.read(max_bytes + 1)
    if max_bytes is not None and len(data) > max_bytes:
        raise ModelOverBudget(f"{name}: grew past {setting} = {max_bytes / 2**20:g} MB while "
                              "being read")
    try:
        model = onnx.load_model_from_string(data)
    except Exception as exc:  # onnx's own types for a file that is not a model
        raise NotAModel(f"{name}: not a readable ONNX model ({str(exc)[:200]})") from None
    outside = _external_tensor(model)
    if outside is not None:
        raise NotAModel(f"{name}: tensor {outside[:80]!r} is stored outside the model file "
                        "(external data); nhfd models keep their weights inside it")
    return model


def _external_tensor(model: Any) -> str | None:
    """The name of the first tensor of `model` stored as external data (initialisers, sparse
    ones, node attributes, subgraphs and functions included), or None."""
    from onnx import AttributeProto, TensorProto

    def external(t: Any) -> bool:
        return t.data_location == TensorProto.EXTERNAL or len(t.external_data) > 0

    graphs, nodes = [model.graph], [n for fn in model.functions for n in fn.node]
    while graphs or nodes:
        if graphs:
            g = graphs.pop()
            tensors = [*g.initializer, *(t for s in g.sparse_initializer
                                         for t in (s.values, s.indices))]
            for t in tensors:
                if external(t):
                    return t.name or "(unnamed)"
            nodes.extend(g.node)
            continue
        for a in nodes.pop().attribute:
            attr_tensors = [*([a.t] if a.type == AttributeProto.TENSOR else []), *a.tensors]
            if a.type == AttributeProto.SPARSE_TENSOR:
                attr_tensors += [a.sparse_tensor.values, a.sparse_tensor.indices]
            for t in attr_tensors:
                if external(t):
                    return t.name or a.name
            graphs.extend([*([a.g] if a.type == AttributeProto.GRAPH else []), *a.graphs])
    return None


def read_model_metadata(path: str | Path, *, max_bytes: int | None = None,
                        setting: str = "max_bytes") -> tuple[dict, str]:
    """A model file's metadata (checked, `nhfd.models.metadata.validate_metadata`) and its
    input's name ("rgb" or "rgbd"), read with onnx (no session; `read_model_file`'s bounds):
    what a GPU session's options, and the memory probe's input, depend on before a session
    exists."""
    model = read_model_file(path, max_bytes=max_bytes, setting=setting)
    name = str(path)
    props = {p.key: p.value for p in model.metadata_props}
    initialisers = {i.name for i in model.graph.initializer}
    inputs = [i.name for i in model.graph.input if i.name not in initialisers]
    return parse_metadata(props, name, inputs[0] if len(inputs) == 1 else None), \
        (inputs[0] if inputs else "")


class ModelOverBudget(ValueError):
    """A model whose file, first session or test inference needs more memory than the budget
    it may take at load (`probe_model`), or more time than the probe allows; the message names
    the budget."""


# The memory probe. A model's first session can allocate far more than its file holds:
# onnxruntime folds constant subgraphs when it creates a session (a 250 KB file with a
# ConstantOfShape of [32768, 32768] took 4.9 GB there, issue 32), and a first run allocates every
# intermediate at the input's size. `probe_model` creates the session and runs it once in a child
# process: a fresh interpreter that imports NumPy and onnxruntime only (not nhfd, not torch: a
# small address space, 0.2 s to start), whose address space is then limited (RLIMIT_AS) to what
# it has plus the budget. An allocation past it fails in that child (onnxruntime reports
# "Failed to allocate memory"; constant folding that cannot allocate is skipped and fails at the
# run instead), never in the caller; the caller opens the model only once the child has shown
# its session and first run fit. The child runs on onnxruntime's CPU provider, whatever serves
# the model afterwards: RLIMIT_AS cannot bound a CUDA process (the driver reserves address
# space by the tens of GB), and the CPU session folds the same constants and allocates the same
# intermediates (in host memory) that a GPU session would (in device memory).
PROBE_SCRIPT = r"""
import json, resource, sys
spec = json.loads(sys.argv[1])

def status_kb(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return 0

import numpy as np
import onnxruntime as ort

out = {"stage": "session", "skipped": []}
rss_kb = status_kb("VmRSS")
hard = resource.getrlimit(resource.RLIMIT_AS)[1]
limit = status_kb("VmSize") * 1024 + spec["budget_bytes"]
unlimited = resource.RLIM_INFINITY
resource.setrlimit(resource.RLIMIT_AS, (limit if hard == unlimited else min(limit, hard), hard))
cpu_hard = resource.getrlimit(resource.RLIMIT_CPU)[1]
cpu = spec["cpu_s"] if cpu_hard == unlimited else min(spec["cpu_s"], cpu_hard)
resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu_hard))
try:
    opts = ort.SessionOptions()
    opts.log_severity_level = 4
    if spec["threads"]:
        opts.intra_op_num_threads = spec["threads"]
        opts.inter_op_num_threads = 1
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
    session = ort.InferenceSession(spec["path"], sess_options=opts,
                                   providers=["CPUExecutionProvider"])
    out["stage"] = "run"
    inputs = session.get_inputs()
    for shape in spec["shapes"]:
        declared = list(inputs[0].shape) if len(inputs) == 1 else []
        if len(declared) != 4 or any(isinstance(d, int) and d != s
                                     for d, s in zip(declared[1:], shape[1:])):
            out["skipped"].append(shape)
            continue
        x = np.full(shape, spec["fill"], np.float32)
        if shape[1] == 4:
            x[:, 3] = 0.0
        session.run(None, {inputs[0].name: x})
    out["stage"] = "done"
except BaseException as exc:
    out["error"] = type(exc).__name__ + ": " + str(exc)[:600]
# VmHWM: the peak of this program's own memory (ru_maxrss would count the parent's, forked)
out["peak_mb"] = (status_kb("VmHWM") - rss_kb) / 1024
print("\n" + json.dumps(out), flush=True)
"""
# Wall-clock seconds the probe may take: a CPU session and one run at up to the whole panel
# (1920 x 1080) take under 2 s for the shipped profiles on 2 cores; a graph that computes for
# minutes would hold the frame worker as long.
PROBE_TIMEOUT_S = 120.0
# How onnxruntime, the C++ runtime and Python word a failed allocation.
MEMORY_FAILURES = ("Failed to allocate memory", "bad_alloc", "bad allocation",
                   "Cannot allocate memory", "out of memory", "MemoryError")


def probe_model(path: str | Path, memory_mb: int, input_shapes: Sequence[Sequence[int]], *,
                threads: int = 0, fill: float = 0.5, timeout_s: float = PROBE_TIMEOUT_S,
                setting: str = "memory_mb", source: str | None = None) -> dict[str, Any]:
    """Create `path`'s onnxruntime session and run it once per input shape (`[1, C, H, W]`,
    float32 `fill`, an rgbd model's depth 0) in a child process whose address space may grow by
    at most `memory_mb` MB (see PROBE_SCRIPT's comment), with `threads` intra-op threads as
    `session_options` sets them. Returns {"peak_mb": the child's peak resident memory above its
    start (MB), "run_error": the first run's error when it failed otherwise than for memory,
    else None, "skipped": shapes the graph's declared input cannot take (not run)}.

    Refused, naming `setting` = `memory_mb`: a session or run that failed for memory, a child
    that ended by a signal, or one that ran past `timeout_s` (`ModelOverBudget`); a session that
    failed otherwise is `NotAModel` (the file is not one onnxruntime reads)."""
    name = source or str(path)
    budget = f"{setting} = {memory_mb} MB"
    spec = {"path": str(path), "budget_bytes": int(memory_mb) << 20, "threads": int(threads),
            "fill": float(fill), "shapes": [[int(v) for v in s] for s in input_shapes],
            # CPU seconds, every thread's: a bound even on a child whose parent died
            "cpu_s": math.ceil(timeout_s) * max(1, threads or os.cpu_count() or 1) + 5}
    # One malloc arena: glibc reserves 64 MB of address space per thread's arena, which would
    # count against the budget without being used.
    env = dict(os.environ, MALLOC_ARENA_MAX="1")
    try:
        done = subprocess.run([sys.executable, "-I", "-c", PROBE_SCRIPT, json.dumps(spec)],
                              capture_output=True, text=True, timeout=timeout_s, env=env,
                              stdin=subprocess.DEVNULL, check=False)
    except subprocess.TimeoutExpired:  # run() has killed it
        raise ModelOverBudget(f"{name}: loading and test-running it took more than "
                              f"{timeout_s:g} s (refused; the memory probe under {budget} "
                              "was stopped)") from None
    lines = done.stdout.strip().splitlines()
    try:
        out = json.loads(lines[-1]) if lines else None
    except json.JSONDecodeError:
        out = None
    if not isinstance(out, dict):
        how = (f"signal {signal.Signals(-done.returncode).name}" if done.returncode < 0
               else f"exit status {done.returncode}")
        tail = (done.stderr.strip().splitlines() or [""])[-1][:200]
        raise ModelOverBudget(f"{name}: its session, created in a child process limited to "
                              f"{budget}, ended with {how} before it could report (a session "
                              "that needs more memory than that can end so)"
                              + (f": {tail}" if tail else ""))
    error = str(out.get("error") or "")
    first = (error.strip().splitlines() or [""])[0][:300]
    failure = next((m for m in MEMORY_FAILURES if m in error), None)
    if failure:
        what = "session" if out["stage"] == "session" else "test inference"
        # onnxruntime's message buries the operator and the size in source paths: keep those
        node = re.search(r"running (\w+) node", error)
        said = error[error.index(failure):].splitlines()[0][:120]
        raise ModelOverBudget(f"{name}: its {what} needs more memory than {budget} allows "
                              f"(refused: {node.group(1) + ' node: ' if node else ''}{said})")
    if error and out["stage"] == "session":
        raise NotAModel(f"{name}: not a readable ONNX model ({first[:200]})")
    return {"peak_mb": float(out.get("peak_mb") or 0.0), "run_error": first or None,
            "skipped": out.get("skipped") or []}


def session_options(threads: int = 0) -> Any:
    """onnxruntime session options. `threads` > 0 (serving, latency benches): that many intra-op
    threads, one inter-op thread, and pools that sleep instead of spinning between runs. A
    spinning pool keeps the cores busy for a while after each run: it slowed the daemon's
    following torch FFT from 20 to 31 ms on 2 cores (issue 7), and a second model timed right
    after the first from about 55 to 105 ms (two 2-thread models taking turns). `threads` = 0:
    onnxruntime's defaults (offline evaluation)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    if threads:
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return opts


class OnnxModel:
    """An exported NHF network under onnxruntime, with its metadata.

    `expected` (optics keys, see `nhfd.models.metadata.expected_from_config`) makes loading refuse
    a model trained for other optics, with a message that says what differs.

    `device` ("cpu", "cuda:N" or a torch device): where `run_on` takes its input and leaves its
    outputs. On CUDA the session's providers come from `execution_providers` (`providers` is
    then the configured list it chooses from), TensorRT's engines cached under
    `engine_cache_dir` for `input_hw` (the frame window, padded here to the input multiple),
    and `run_on` binds device memory (I/O binding: no host round trip). `__call__` and `run_raw`
    take and return NumPy arrays on any device.
    """

    def __init__(self, path: str | Path, *, expected: dict | None = None, threads: int = 0,
                 source: str | None = None, providers: tuple[str, ...] = CPU_ONLY,
                 device: str | torch.device = "cpu", input_hw: tuple[int, int] | None = None,
                 engine_cache_dir: str | Path | None = None,
                 device_setting: str = "device") -> None:  # fmt: skip
        import onnxruntime as ort

        self.path = Path(path)
        # "cuda" as "cuda:0": tensors always carry an index, and run_on compares devices
        self.device = torch.device(device_choice(str(device), device_setting, cuda_count=None,
                                                 allowed=("cpu", "cuda", "cuda:N")))
        name = source or str(self.path)
        if not self.path.is_file():
            raise FileNotFoundError(f"{name}: no such model file")
        available = ort.get_available_providers()
        # before the session: its errors below are reported as an unreadable file
        if self.device.type == "cuda":
            chosen = self._gpu_providers(list(providers), available, input_hw, engine_cache_dir,
                                         device_setting)
        else:
            chosen = check_providers(list(providers), available)
        try:
            self.session = ort.InferenceSession(
                str(self.path), sess_options=session_options(threads), providers=chosen
            )
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise NotAModel(f"{name}: not a readable ONNX model ({first[:200]})") from None
        props = dict(self.session.get_modelmeta().custom_metadata_map)
        inputs = [i.name for i in self.session.get_inputs()]
        # checked field by field: a value the frame path cannot use is refused here, by name
        self.metadata = parse_metadata(props, name, inputs[0] if len(inputs) == 1 else None)
        outputs = [o.name for o in self.session.get_outputs()]
        if inputs not in (["rgb"], ["rgbd"]) or outputs != ["amplitude", "phase"]:
            raise NotAModel(f"{name}: inputs {inputs} / outputs {outputs} are not rgb or rgbd -> "
                            "amplitude, phase")  # fmt: skip
        if expected is not None:
            check_metadata(self.metadata, expected, name)
        # "rgb" (sRGB) or "rgbd" (sRGB + mapped depth): build inputs with
        # nhfd.models.inputs.network_input(..., self.inputs, ...).
        self.inputs: str = inputs[0]
        # The metadata typed, parsed once: what the frame path reads (by name, never by key).
        self.info: ModelInfo = parse_model_info(self.metadata, name, self.inputs)
        # The graph's declared input shape (ints, or names for dynamic axes) and the providers
        # running it: what the frame worker checks and reports (TorchModel has both too).
        self.input_shape: list[Any] = list(self.session.get_inputs()[0].shape)
        self.providers: list[str] = list(self.session.get_providers())
        self.channels = self.info.channels
        self.multiple = self.info.input_multiple
        self.amplitude_scale = self.info.amplitude_scale
        self.colours = self.info.colours
        # frames per inference: the outputs are [B, 3 K, H, W] (`ServingNet(subframes=K)`)
        self.subframes = self.info.subframes

    def _gpu_providers(self, configured: list[str], available: list[str],
                       input_hw: tuple[int, int] | None, engine_cache_dir: str | Path | None,
                       device_setting: str) -> list[Provider]:
        """`execution_providers` for this file on this CUDA device (its hash, its padded input
        shape, the GPU's name)."""
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        device = device_choice(f"cuda:{self.device.index or 0}", device_setting, cuda_count=count)
        shape = None
        name = "rgb"
        if input_hw is not None:
            meta, name = read_model_metadata(self.path)
            m = parse_model_info(meta, str(self.path), name).input_multiple
            h, w = (int(v) for v in input_hw)
            shape = (1, 3 + (name == "rgbd"), h + (-h) % m, w + (-w) % m)
        return execution_providers(
            device, available, configured, device_setting=device_setting,
            engine_cache_dir=engine_cache_dir, model_sha256=sha256_file(self.path),
            input_name=name, input_shape=shape,
            gpu_name=torch.cuda.get_device_name(self.device.index or 0))

    def run_raw(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The graph as is: `[B, C, H, W]` float32 with H, W multiples of `multiple`."""
        amp, phase = self.session.run(["amplitude", "phase"], {self.inputs: x})
        return amp, phase

    def run_bound(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The graph on a tensor `[B, C, H, W]` float32 (H, W multiples of `multiple`) on this
        model's device, its outputs written to fresh tensors there: onnxruntime's I/O binding,
        so on CUDA nothing crosses to the host. The caller's queued work on `x` finishes first
        (torch's stream is synchronised: onnxruntime runs on a stream of its own), and the
        outputs are complete when this returns."""
        if x.device != self.device:
            raise ValueError(f"input on {x.device}: this model runs on {self.device}")
        if x.dim() != 4 or x.shape[1] != self.channels:
            raise ValueError(f"{self.inputs} input {tuple(x.shape)}: expected [B, "
                             f"{self.channels}, H, W]")
        x = x.detach().to(torch.float32).contiguous()
        b, _c, h, w = x.shape
        amp = torch.empty((b, self.colours * self.subframes, h, w), dtype=torch.float32,
                          device=x.device)
        phase = torch.empty_like(amp)
        kind = "cuda" if x.device.type == "cuda" else "cpu"
        index = (x.device.index or 0) if kind == "cuda" else 0
        binding = self.session.io_binding()
        binding.bind_input(self.inputs, kind, index, np.float32, list(x.shape), x.data_ptr())
        for out_name, out in (("amplitude", amp), ("phase", phase)):
            binding.bind_output(out_name, kind, index, np.float32, list(out.shape),
                                out.data_ptr())
        if kind == "cuda":
            torch.cuda.current_stream(x.device).synchronize()
        self.session.run_with_iobinding(binding)
        binding.synchronize_outputs()
        return amp, phase

    def run_on(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`__call__` on tensors on this model's device (`run_padded` around `run_bound`):
        amplitude and phase tensors on the same device."""
        return run_padded(self, x, self.run_bound)

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Amplitude (amplitude-scale units) and phase for inputs `[C, H, W]` or `[B, C, H, W]`
        of any size (`nhfd.models.inputs.network_input`): padded with black (and the reference
        plane's depth) to the multiple outside the graph and cropped back."""
        x = np.asarray(x, dtype=np.float32)
        given = x.shape
        single = x.ndim == 3
        if single:
            x = x[None]
        c = self.channels
        if x.ndim != 4 or x.shape[1] != c:
            raise ValueError(f"{self.inputs} input {given}: expected [{c}, H, W] or "
                             f"[B, {c}, H, W]")  # fmt: skip
        h, w = x.shape[-2:]
        ph, pw = (-h) % self.multiple, (-w) % self.multiple
        if ph or pw:
            x = np.pad(x, ((0, 0), (0, 0), (0, ph), (0, pw)))
        amp, phase = self.run_raw(np.ascontiguousarray(x))
        amp, phase = amp[..., :h, :w], phase[..., :h, :w]
        return (amp[0], phase[0]) if single else (amp, phase)


def run_padded(model: Any, x: torch.Tensor,
               run: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """`run` (`[B, C, H, W]` with H, W multiples of `model.multiple` -> amplitude, phase) on
    `x` `[C, H, W]` or `[B, C, H, W]` of any size: padded with zeros to the multiple (as
    `OnnxModel.__call__`'s black and reference-plane depth) and cropped back. `model`: its
    `channels`, `inputs` and `multiple` (an `OnnxModel` or a `TorchModel`)."""
    given = tuple(x.shape)
    single = x.dim() == 3
    if single:
        x = x[None]
    if x.dim() != 4 or x.shape[1] != model.channels:
        raise ValueError(f"{model.inputs} input {given}: expected [{model.channels}, H, W] or "
                         f"[B, {model.channels}, H, W]")
    h, w = x.shape[-2:]
    ph, pw = (-h) % model.multiple, (-w) % model.multiple
    if ph or pw:
        x = torch.nn.functional.pad(x, (0, pw, 0, ph))
    amp, phase = run(x)
    amp, phase = amp[..., :h, :w], phase[..., :h, :w]
    return (amp[0], phase[0]) if single else (amp, phase)


def load_model(path: str | Path, config: Config | None = None, *, threads: int = 0,
               providers: tuple[str, ...] = CPU_ONLY, device: str | torch.device = "cpu",
               input_hw: tuple[int, int] | None = None,
               engine_cache_dir: str | Path | None = None) -> OnnxModel:
    """Load an exported model; with a configuration, refuse one trained for other optics.
    `device`, `input_hw`, `engine_cache_dir`: `OnnxModel`'s (a CUDA device's errors name
    daemon.frames.device when a config is given).

    `config`: the whole configuration the model is to serve under (None: no check), because the
    optics it must match span two sections, `[optics]` and `[slm]`'s pitch
    (`expected_from_config`), and its device is `daemon.frames.device`."""
    expected = expected_from_config(config.optics, config.slm) if config is not None else None
    return OnnxModel(path, expected=expected, threads=threads, providers=providers,
                     device=device, input_hw=input_hw, engine_cache_dir=engine_cache_dir,
                     device_setting="daemon.frames.device" if config is not None else "device")
