"""Static int8 quantisation of an exported model (onnxruntime, QDQ, per channel).

The layers that write the outputs stay in float32: amplitude and phase feed a propagation and
double-phase coding that amplify their errors. Calibrated on the first training views of a
dataset. On 2 cores at 1024 x 576 it took the earlier fast profile (16/3/4) from 35.5 to 26.3 ms
for 0.16 dB of held-out PSNR (`nhfd bench tradeoff --int8`); it helps less, or not at all, where
convolutions are a smaller share of the time.

`record_heldout_loss` writes what `nhfd eval` measured of an int8 model and its float model into
the int8 file's own metadata (`nhfd model build` does, at its eval stage): the daemon serves the
int8 sibling by that record (`daemon.frames.int8`, docs/frames.md).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from nhfd.dataset.build import sha256_file
from nhfd.models.metadata import METADATA_KEY
from nhfd.models.net import pad_amounts
from nhfd.models.sizes import recheck_derived

if TYPE_CHECKING:
    from nhfd.models.data import HoloData

# An int8 model is served (and `nhfd model build` keeps it) only if its held-out PSNR is within
# this of its float model's (issue 24).
INT8_MAX_LOSS_DB = 0.5
# The key of the held-out record in an int8 model's nhfd metadata (`record_heldout_loss`).
HELDOUT_KEY = "int8_heldout"


# Operators of a quantised graph (what tells an int8 file from a float one: it carries its float
# model's metadata): its arithmetic is integer, which no float rebuild reproduces.
QUANTISED_OPS = frozenset({"QuantizeLinear", "DequantizeLinear", "QLinearConv", "ConvInteger",
                           "MatMulInteger", "DynamicQuantizeLinear", "QLinearAdd"})


def int8_sibling(path: str | Path) -> Path:
    """Where the int8 model of a float model lies: `<stem>-int8.onnx` beside it (`nhfd model
    build` writes model.onnx and model-int8.onnx)."""
    p = Path(path)
    return p.with_name(f"{p.stem}-int8{p.suffix}")


def int8_within_loss(loss_db: float) -> bool:
    """Whether a reduced-precision model that loses `loss_db` of held-out PSNR against its float
    model is kept and served: finite and at most INT8_MAX_LOSS_DB (NaN or inf is not)."""
    return math.isfinite(loss_db) and loss_db <= INT8_MAX_LOSS_DB


def output_nodes(model) -> tuple[list[str], list[str]]:
    """Names of the convolutions that produce the graph's outputs (the network's last layer),
    and of every node between them and the outputs (softplus's elementwise passes): walk back
    from each output through non-convolution nodes."""
    producer = {out: node for node in model.graph.node for out in node.output}
    heads, tail, todo, seen = [], [], [o.name for o in model.graph.output], set()
    while todo:
        node = producer.get(todo.pop())
        if node is None or node.name in seen:
            continue
        seen.add(node.name)
        if node.op_type in ("Conv", "ConvTranspose"):
            heads.append(node.name)
        else:
            tail.append(node.name)
            todo.extend(node.input)
    return heads, tail


def quantise_int8(src: Path, dst: Path, data: HoloData, multiple: int, inputs: str = "rgb",
                  n_calib: int = 8) -> Path:
    """Static int8 (QDQ, per channel), the head (the last layer) and the elementwise passes
    after it kept in float32, calibrated on training views; the nhfd metadata is carried
    over."""
    import numpy as np
    import onnx
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    model = onnx.load(str(src))
    split = data.splits["train"]
    Path(dst).parent.mkdir(parents=True, exist_ok=True)

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.items = []
            for j in range(min(n_calib, len(split))):
                x = split.inputs(inputs, slice(j, j + 1)).numpy()
                ph, pw = pad_amounts(*x.shape[-2:], multiple)
                x = np.pad(x, ((0, 0), (0, 0), (0, ph), (0, pw)))
                self.items.append({inputs: np.ascontiguousarray(x, np.float32)})
            self.it = iter(self.items)

        def get_next(self):
            return next(self.it, None)

    # The head and everything after it stay float: quantising the softplus's Min and Max (which
    # onnxruntime's QDQ quantiser takes) cost fastest 4.3 dB of held-out PSNR.
    heads, tail = output_nodes(model)
    quantize_static(str(src), str(dst), Reader(), quant_format=QuantFormat.QDQ,
                    per_channel=True, activation_type=QuantType.QUInt8,
                    weight_type=QuantType.QInt8, nodes_to_exclude=heads + tail)  # fmt: skip
    q = onnx.load(str(dst))
    del q.metadata_props[:]
    checked: list = []
    for prop in model.metadata_props:
        copy = q.metadata_props.add()
        copy.CopyFrom(prop)
        if prop.key == METADATA_KEY:  # the float model's size checks are not this model's
            meta = json.loads(prop.value)
            checked = meta.pop("checked_sizes", None) or []
            copy.value = json.dumps(meta)
    onnx.save(q, str(dst))
    recheck_derived(src, dst, checked)
    return dst


def record_heldout_loss(int8_path: str | Path, float_path: str | Path, *, float_psnr_db: float,
                        int8_psnr_db: float, views: int) -> dict[str, Any]:
    """Write into the int8 model's own nhfd metadata what `nhfd eval` measured of it and of its
    float model on the held-out views: the figure travels with the file, so whoever serves it
    (the daemon's frame worker) need not trust a separate report. The float model's SHA-256
    ties the record to the float file it was measured against. Returns the record."""
    import onnx

    record = {"float_psnr_db": float(float_psnr_db), "int8_psnr_db": float(int8_psnr_db),
              "loss_vs_float_db": float(float_psnr_db) - float(int8_psnr_db),
              "views": int(views), "float_sha256": sha256_file(Path(float_path)),
              "max_loss_db": INT8_MAX_LOSS_DB}  # fmt: skip
    model = onnx.load(str(int8_path))
    for prop in model.metadata_props:
        if prop.key == METADATA_KEY:
            meta = json.loads(prop.value)
            meta[HELDOUT_KEY] = record
            prop.value = json.dumps(meta)
            break
    else:
        raise ValueError(f"{int8_path}: no nhfd metadata to record the held-out loss in")
    tmp = Path(int8_path).with_name(Path(int8_path).name + ".rec.tmp")
    onnx.save(model, str(tmp))
    os.replace(tmp, int8_path)
    return record
