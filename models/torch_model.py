"""A model file served by torch instead of onnxruntime: `TorchModel` (`daemon.frames.inference`).

Why: a GPU workstation has a CUDA torch (every other stage of a frame needs it) but often not
onnxruntime-gpu, whose wheels are built for one CUDA and cuDNN major version each, and a bench
PC without internet may have no way to install it at all. Without it, onnxruntime has no CUDA
provider and the network would be the one stage of a GPU frame left on the CPU. An nhfd model
file is `nhfd.models.serving.ServingNet(NHFNet(spec))` exported: its initialisers carry that
module's parameter names and its metadata the spec (`"net"`), so the module is rebuilt from the
file. The rebuild is trusted only after it agrees with the file's own graph: at load,
onnxruntime (its CPU provider, always installed) and the rebuilt module run one seeded input, and
a file whose graph computes something else (edited, or written by another exporter) is refused,
never served wrong.

What it serves: float32 files, and fp16 files (`nhfd export --fp16`) computed in float32 with
their float16 weights (exact in float32): within 1e-3 of onnxruntime's own run of the shipped
model's fp16 file, which rounds some operators to float16. int8 files are refused: their integer
arithmetic is onnxruntime's.

`TorchModel` has `OnnxModel`'s serving interface (`metadata`, `info`, `inputs`, `channels`,
`multiple`, `amplitude_scale`, `colours`, `subframes`, `device`, `input_shape`, `providers`,
`run_raw`, `run_on`, `__call__`), so the frame path does not ask which one it has.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from nhfd.config import device_choice
from nhfd.models.export import OnnxModel, run_padded
from nhfd.models.inputs import seeded_input
from nhfd.models.metadata import NotAModel
from nhfd.models.net import NetSpec, build_net
from nhfd.models.quantise import QUANTISED_OPS
from nhfd.models.serving import ServingNet

# What `providers` reports for a TorchModel (status shows it where onnxruntime's list would be).
TORCH_PROVIDER = "torch"
# The rebuild's check against the file's graph: largest absolute difference allowed on amplitude
# and phase. The export's own check (torch against onnxruntime) measures about 1e-6 on these
# networks; a real difference (a weight, an operator, an activation) is orders above it. An
# fp16 file computes in float16 where onnxruntime has float16 kernels (float16 rounds at 2^-11
# relative): the shipped model's fp16 file differs from its float32 rebuild by 5.4e-4.
REBUILD_TOL = {"fp32": 1e-4, "fp16": 1e-2}
# Parameters the exported graph does not hold: ServingNet folds the head into its output
# transposed convolutions (`amplitude`, `phase`), so the head's own are unused.
FOLDED = frozenset({"net.head.weight", "net.head.bias"})


class TorchModel:
    """The network of the model file at `path`, rebuilt as a torch module on `device`.

    `run_on` launches only device work (no host synchronisation), so the device frame path may
    capture it in a CUDA graph (`graphable`; `nhfd.pipeline.device.CudaGraphs`).

    `expected` (optics keys, `nhfd.models.metadata.expected_from_config`): refuse a model
    trained for other optics, as `OnnxModel` does. ValueError (`NotAModel`) for a file that is
    not an nhfd model, an int8 one, or one whose graph the rebuild does not reproduce."""

    graphable = True

    def __init__(self, path: str | Path, *, expected: dict | None = None,
                 device: str | torch.device = "cpu", source: str | None = None) -> None:
        import onnx
        from onnx import numpy_helper

        self.path = Path(path)
        # "cuda" as "cuda:0": tensors always carry an index, and run_on compares devices
        self.device = torch.device(device_choice(str(device), "device", cuda_count=None,
                                                 allowed=("cpu", "cuda", "cuda:N")))
        name = source or str(self.path)
        # onnxruntime reads the file first: its checks (not a model, not an nhfd model, wrong
        # inputs or outputs) and its messages are the ones OnnxModel gives.
        reference = OnnxModel(self.path, expected=expected, source=name)
        self.metadata, self.info = reference.metadata, reference.info
        self.inputs, self.channels = reference.inputs, reference.channels
        self.multiple, self.colours = reference.multiple, reference.colours
        self.amplitude_scale = reference.amplitude_scale
        graph = onnx.load(str(self.path)).graph
        quantised = sorted({n.op_type for n in graph.node} & QUANTISED_OPS)
        if quantised:
            raise NotAModel(f"{name}: an int8 model ({', '.join(quantised)}): it serves with "
                            "onnxruntime on the CPU, not with daemon.frames.inference = \"torch\"")
        weights = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
        self.subframes = self.info.subframes
        self.module = _rebuild(self.metadata, weights, name, self.subframes)
        worst = _compare(self.module, reference, self.channels, self.multiple)
        tol = REBUILD_TOL["fp16" if self.info.precision == "fp16" else "fp32"]
        if not worst <= tol:  # NaN fails too
            raise NotAModel(f"{name}: rebuilt as a torch module, it differs from the file's own "
                            f"graph by {worst:.3g} (at most {tol:g} allowed): serve it with "
                            "daemon.frames.inference = \"onnxruntime\"")
        self.module = self.module.to(self.device)
        self.input_shape: list[Any] = ["batch", self.channels, "height", "width"]
        self.providers = [TORCH_PROVIDER]

    def run_on(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Amplitude and phase for `x` `[C, H, W]` or `[B, C, H, W]` on this model's device, any
        size (`nhfd.models.export.run_padded`, as `OnnxModel.run_on`)."""
        return run_padded(self, x, self._run_module)

    def _run_module(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if x.device != self.device:
            raise ValueError(f"input on {x.device}: this model runs on {self.device}")
        # float32 convolutions in float32, not cuDNN's default TF32 (10-bit mantissa): TF32 put
        # the outputs 5e-4 (amplitude, relative) and 1.4e-3 rad (phase) from onnxruntime's on an
        # H200 and saved 0.35 ms of 3.0 at 1920 x 1080 (scripts/gpu_probe.py net, docs/gpu.md).
        with torch.no_grad(), torch.backends.cudnn.flags(
                enabled=torch.backends.cudnn.enabled, benchmark=torch.backends.cudnn.benchmark,
                deterministic=torch.backends.cudnn.deterministic, allow_tf32=False):
            return self.module(x.to(torch.float32))

    def run_raw(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The graph as is on NumPy arrays: `[B, C, H, W]` float32, H and W multiples of
        `multiple`."""
        h, w = x.shape[-2:]
        if h % self.multiple or w % self.multiple:
            raise ValueError(f"{self.inputs} input {tuple(x.shape)}: H and W must be multiples "
                             f"of {self.multiple}")
        return self(x)

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`OnnxModel.__call__`: NumPy `[C, H, W]` or `[B, C, H, W]` in, NumPy out."""
        t = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).to(self.device)
        amp, phase = self.run_on(t)
        return amp.cpu().numpy(), phase.cpu().numpy()


def _rebuild(metadata: dict, weights: dict[str, np.ndarray], name: str, subframes: int = 1
             ) -> ServingNet:
    """`ServingNet(NHFNet(spec), subframes)` with the file's weights (float16 ones promoted,
    exactly)."""
    spec_json = metadata.get("net")
    if not isinstance(spec_json, dict):
        raise NotAModel(f"{name}: its metadata has no network spec (\"net\"): exported by an "
                        "older nhfd; serve it with daemon.frames.inference = \"onnxruntime\"")
    try:
        spec = NetSpec(**spec_json)
    except (TypeError, ValueError) as exc:
        raise NotAModel(f"{name}: its network spec {spec_json} is not one nhfd builds: "
                        f"{exc}") from None
    module = ServingNet(build_net(spec, seed=0), subframes=subframes)
    state = module.state_dict()
    missing = sorted(k for k in state if k not in weights and k not in FOLDED)
    if missing:
        raise NotAModel(f"{name}: the graph lacks {len(missing)} of the spec's parameters "
                        f"({', '.join(missing[:3])}{', ...' if len(missing) > 3 else ''})")
    loaded = {}
    for key, value in state.items():
        if key in FOLDED:
            loaded[key] = value
            continue
        w = weights[key]
        if tuple(w.shape) != tuple(value.shape):
            raise NotAModel(f"{name}: parameter {key} is {list(w.shape)} in the file, "
                            f"{list(value.shape)} in the spec {spec_json}")
        loaded[key] = torch.from_numpy(np.array(w, dtype=np.float32))  # a writable copy
    module.load_state_dict(loaded)
    return module.eval()


def _compare(module: ServingNet, reference: OnnxModel, channels: int, multiple: int) -> float:
    """Largest absolute difference, amplitude and phase, between the module and the file's graph
    (onnxruntime) on one seeded input of 2 x 3 strides: sRGB in [0, 1] and, for rgbd, depths
    across the network's clipped range."""
    x = seeded_input(channels, (2 * multiple, 3 * multiple), seed=2023)
    with torch.no_grad():
        ta, tp = module(torch.from_numpy(x))
    oa, op = reference.run_raw(x)
    d = max(float(np.max(np.abs(ta.numpy() - oa))), float(np.max(np.abs(tp.numpy() - op))))
    return d if np.isfinite(d) else float("inf")
