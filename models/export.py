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
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nhfd.dataset.build import sha256_file
from nhfd.models.metadata import (
    METADATA_KEY,
    NotAModel,
    build_metadata,
    check_metadata,
    expected_from_config,
    parse_metadata,
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
    (`nhfd.models.sizes.DEFAULT_SIZES_HW` unless given)."""
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
    rng = np.random.default_rng(0)
    worst, sizes = 0.0, []
    for h, w in sizes_hw or [(hs * m, ws * m) for hs, ws in CHECK_SIZES_STRIDES]:
        x = rng.random((1, net.spec.channels, h, w), dtype=np.float32)
        with torch.no_grad():
            ta, tp = net(torch.from_numpy(x))
        oa, op = model.run_raw(x)
        # NaN anywhere is a failed check: max() would drop it, np.max keeps it
        d = float(np.max([np.abs(ta.numpy() - oa).max(), np.abs(tp.numpy() - op).max()]))
        worst = max(worst, d if np.isfinite(d) else float("inf"))
        sizes.append((h, w))
    return worst, sizes


# Where a model runs unless told otherwise (the daemon takes `daemon.onnx_providers`).
CPU_ONLY = ("CPUExecutionProvider",)


def check_providers(wanted: list[str], available: list[str], setting: str = "providers"
                    ) -> list[str]:  # fmt: skip
    """`wanted` execution providers, in order, or a ValueError naming `setting`, the missing
    ones, and what this onnxruntime has."""
    missing = [p for p in wanted if p not in available]
    if missing:
        raise ValueError(f"{setting}: {', '.join(missing)} not available in this onnxruntime; "
                         f"available: {', '.join(available)}")
    return wanted


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
    """

    def __init__(self, path: str | Path, *, expected: dict | None = None, threads: int = 0,
                 source: str | None = None, providers: tuple[str, ...] = CPU_ONLY
                 ) -> None:  # fmt: skip
        import onnxruntime as ort

        self.path = Path(path)
        name = source or str(self.path)
        if not self.path.is_file():
            raise FileNotFoundError(f"{name}: no such model file")
        # before the session: its errors below are reported as an unreadable file
        check_providers(list(providers), ort.get_available_providers())
        try:
            self.session = ort.InferenceSession(
                str(self.path), sess_options=session_options(threads), providers=list(providers)
            )
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise NotAModel(f"{name}: not a readable ONNX model ({first[:200]})") from None
        props = dict(self.session.get_modelmeta().custom_metadata_map)
        self.metadata = parse_metadata(props, name)
        inputs = [i.name for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        if inputs not in (["rgb"], ["rgbd"]) or outputs != ["amplitude", "phase"]:
            raise NotAModel(f"{name}: inputs {inputs} / outputs {outputs} are not rgb or rgbd -> "
                            "amplitude, phase")  # fmt: skip
        if expected is not None:
            check_metadata(self.metadata, expected, name)
        # "rgb" (sRGB) or "rgbd" (sRGB + mapped depth): build inputs with
        # nhfd.models.inputs.network_input(..., self.inputs, ...).
        self.inputs: str = inputs[0]
        self.channels = 3 + (self.inputs == "rgbd")
        self.multiple = int(self.metadata["input_multiple"])
        self.amplitude_scale = float(self.metadata["amplitude_scale"])

    def run_raw(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The graph as is: `[B, C, H, W]` float32 with H, W multiples of `multiple`."""
        amp, phase = self.session.run(["amplitude", "phase"], {self.inputs: x})
        return amp, phase

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


def load_model(path: str | Path, config=None, *, threads: int = 0,
               providers: tuple[str, ...] = CPU_ONLY) -> OnnxModel:
    """Load an exported model; with a `nhfd.config.Config`, refuse one trained for other optics."""
    expected = expected_from_config(config) if config is not None else None
    return OnnxModel(path, expected=expected, threads=threads, providers=providers)
