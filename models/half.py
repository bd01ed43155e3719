"""fp16 export: an exported float model rewritten to store its weights and compute in float16,
with float32 inputs and outputs (`nhfd export --fp16`).

A small converter of its own rather than `onnxconverter-common`'s (1.16): asked to keep the
softplus in float32 (`node_block_list`), that one declares the amplitude output float16 in spite
of `keep_io_types`. Here each node computes either in float16 or in float32:

- float16: the operators in `FP16_OPS` (convolutions, ReLU, sums, concatenation, the shape
  plumbing) outside the output tail;
- float32: everything else, and the elementwise passes between the output convolutions and the
  graph's outputs (`nhfd.models.quantise.output_nodes`, the softplus): its `exp(min(a, 80))`
  overflows float16 (largest finite value 65504, `exp(11.1)`) and would turn every amplitude above
  about 11 into inf.

A Cast is inserted wherever a tensor crosses between the two (graph inputs and outputs
included), so the graph is correct whatever operators it holds; weights used only by float16
nodes are stored as float16 (saturated at +-65504), the rest stay float32. The nhfd metadata is
carried over with `precision: "fp16"`.

onnxruntime's CPU provider runs the result, but not in float16: it computes float16 operators
that have no CPU kernel in float32 and drops the casts between them, so on the CPU only the
weights' rounding shows (a float16 `1 + exp(30)` comes out finite there). `emulate_fp16` runs a
model with onnx's reference evaluator instead, which computes every float16 operator in float16
(numpy: each result rounded to float16, a convolution's sums accumulated in float32 by its
matrix product, as a GPU's fp16 kernels do), and `evaluate_emulated` is `nhfd eval`'s measure
under it: what a GPU would give, from a machine without one (about 15 s per 512 x 288 view on 2
cores).
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np

from nhfd.models import evaluate as ev
from nhfd.models.export import OnnxModel
from nhfd.models.inputs import seeded_input
from nhfd.models.metadata import METADATA_KEY, NotAModel, parse_metadata
from nhfd.models.quantise import output_nodes
from nhfd.models.sizes import recheck_derived

# Operators safe to compute in float16 for this network: no exponentials or reductions, so no
# intermediate leaves float16's range unless the float32 model's activations already near it.
FP16_OPS = frozenset({
    "Conv", "ConvTranspose", "Relu", "LeakyRelu", "Add", "Sub", "Mul", "Concat", "Slice",
    "Expand", "Reshape", "Transpose", "Identity", "Split", "MaxPool", "AveragePool",
    "DepthToSpace", "SpaceToDepth", "Pad", "Shape", "Max", "Min",
})  # fmt: skip
FP16_MAX = float(np.finfo(np.float16).max)  # 65504
# The fp16 file's own record of `compare_fp16` against its float model (float16 emulated).
CHECK_KEY = "fp16_vs_float"
PRECISION = "fp16"


def convert_fp16(src: str | Path, dst: str | Path, *, keep_float: tuple[str, ...] = (),
                 check: bool = True) -> Path:  # fmt: skip
    """Write `src` (an `nhfd export` model, float32) to `dst` as float16 weights and compute with
    float32 inputs and outputs; `keep_float`: more node names to keep in float32. Refuses a file
    that is not an nhfd model, or one already converted. `check`: refuse (and remove) a result
    that gives inf or NaN computed in float16 on a random input or the extreme ones
    (`compare_fp16`)."""
    import onnx

    src, dst = Path(src), Path(dst)
    if not src.is_file():
        raise FileNotFoundError(f"{src}: no such model file")
    if src.resolve() == dst.resolve():
        raise ValueError(f"{dst}: the fp16 model must not overwrite its source {src}")
    try:
        model = onnx.load(str(src))
    except Exception as exc:  # protobuf's DecodeError and friends: not an ONNX file
        raise NotAModel(f"{src}: not a readable ONNX model ({type(exc).__name__})") from None
    meta = parse_metadata({p.key: p.value for p in model.metadata_props}, str(src))
    if meta.get("precision", "fp32") != "fp32":
        raise ValueError(f"{src}: precision {meta['precision']!r}; convert the float32 model")
    half = to_fp16(model, keep_float=keep_float)
    # the float model's size checks are not this model's: checked again once it is written
    checked = meta.pop("checked_sizes", None) or []
    for prop in half.metadata_props:
        if prop.key == METADATA_KEY:
            prop.value = json.dumps({**meta, "precision": PRECISION})
    onnx.checker.check_model(half)
    # types line up everywhere (a Cast missing at a boundary fails here, not in a session)
    onnx.shape_inference.infer_shapes(half, check_type=True, strict_mode=True)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(dst.name + ".tmp")
    onnx.save(half, str(tmp))
    if check:
        d = compare_fp16(src, tmp, emulate=True)
        if not d["finite"]:
            tmp.unlink()
            raise ValueError(f"{src}: its fp16 conversion gives inf or NaN (float16's range is "
                             f"+-{FP16_MAX:g}); not written to {dst}")  # fmt: skip
        # the comparison travels with the file (`nhfd export --fp16` prints it from there)
        for prop in half.metadata_props:
            if prop.key == METADATA_KEY:
                prop.value = json.dumps({**meta, "precision": PRECISION, CHECK_KEY: d})
        onnx.save(half, str(tmp))
    tmp.replace(dst)
    recheck_derived(src, dst, checked)
    return dst


def to_fp16(model, *, keep_float: tuple[str, ...] = ()):
    """The float16 rewrite of an in-memory float32 `onnx.ModelProto` (see the module's text)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    FLOAT, HALF = TensorProto.FLOAT, TensorProto.FLOAT16
    model = onnx.shape_inference.infer_shapes(model)
    g = model.graph
    if any(a.type == onnx.AttributeProto.GRAPH for n in g.node for a in n.attribute):
        raise ValueError("a graph with subgraphs (If, Loop, Scan): not supported by the fp16 "
                         "converter")  # fmt: skip
    # element type of every tensor the graph names
    elem = {v.name: v.type.tensor_type.elem_type
            for v in (*g.input, *g.value_info, *g.output)}  # fmt: skip
    elem.update({t.name: t.data_type for t in g.initializer})
    _heads, tail = output_nodes(model)
    fp32_nodes = set(tail) | set(keep_float)
    # copies, one Python object per node: their ids below stay valid, and they outlive g.node
    graph_nodes = [copy.deepcopy(n) for n in g.node]
    node_half = {id(n): n.op_type in FP16_OPS and n.name not in fp32_nodes for n in graph_nodes}
    # the type each float tensor has after the rewrite
    have: dict[str, int] = {}
    for n in graph_nodes:
        for out in n.output:
            if elem.get(out) == FLOAT:
                have[out] = HALF if node_half[id(n)] else FLOAT
    for v in g.input:
        if elem.get(v.name) == FLOAT:
            have[v.name] = FLOAT
    # weights: float16 when every reader computes in float16
    readers: dict[str, list] = {}
    for n in graph_nodes:
        for name in n.input:
            readers.setdefault(name, []).append(n)
    inits = []
    for t in g.initializer:
        if t.data_type == FLOAT and readers.get(t.name) and all(
                node_half[id(n)] for n in readers[t.name]):  # fmt: skip
            w = np.clip(numpy_helper.to_array(t), -FP16_MAX, FP16_MAX).astype(np.float16)
            inits.append(numpy_helper.from_array(w, t.name))
            have[t.name] = HALF
        else:
            inits.append(t)
            if t.data_type == FLOAT:
                have[t.name] = FLOAT
    # float16 nodes' float16 attributes: none in FP16_OPS carries a float tensor attribute
    nodes, casts = [], {}

    def cast(name: str, to: int) -> str:
        key = (name, to)
        if key not in casts:
            casts[key] = f"{name}__to_{'fp16' if to == HALF else 'fp32'}"
            nodes.append(helper.make_node("Cast", [name], [casts[key]], to=to,
                                          name=f"cast_{casts[key]}"))  # fmt: skip
        return casts[key]

    for n in graph_nodes:
        want = HALF if node_half[id(n)] else FLOAT
        if n.op_type != "Shape":  # Shape reads any element type
            for i, name in enumerate(n.input):
                if name in have and have[name] != want:
                    n.input[i] = cast(name, want)
        nodes.append(n)
    # graph outputs stay float32: a float16 producer writes a renamed tensor, cast back
    for out in g.output:
        if have.get(out.name) == HALF:
            inner = out.name + "__fp16"
            for n in nodes:
                n.output[:] = [inner if o == out.name else o for o in n.output]
                n.input[:] = [inner if i == out.name else i for i in n.input]
            nodes.append(helper.make_node("Cast", [inner], [out.name], to=FLOAT,
                                          name=f"cast_{out.name}_fp32"))  # fmt: skip
    del g.node[:]
    g.node.extend(nodes)
    del g.initializer[:]
    g.initializer.extend(inits)
    del g.value_info[:]  # the old types are stale; onnxruntime infers them again
    return model


def half_initializer_bytes(path: str | Path) -> dict[str, int]:
    """Bytes of a model's weights by element type (`"float32"`, `"float16"`, ...)."""
    import onnx
    from onnx import numpy_helper

    out: dict[str, int] = {}
    for t in onnx.load(str(path)).graph.initializer:
        a = numpy_helper.to_array(t)
        out[str(a.dtype)] = out.get(str(a.dtype), 0) + a.nbytes
    return out


def emulate_fp16(model: OnnxModel) -> OnnxModel:
    """`model` run by onnx's reference evaluator (float16 operators in float16; see the module's
    text) instead of onnxruntime: same `run_raw` and `__call__`, much slower."""
    from onnx.reference import ReferenceEvaluator

    # run(output_names, feeds) as onnxruntime's session
    model.session = ReferenceEvaluator(str(model.path))
    return model


class _EmulatedModel(OnnxModel):
    def __init__(self, path, **kw) -> None:
        super().__init__(path, **kw)
        emulate_fp16(self)


def evaluate_emulated(half_path: str | Path, data_dir: str | Path, **kw) -> dict:
    """`nhfd.models.evaluate.evaluate` of an fp16 model computed in float16 throughout
    (`emulate_fp16`); keywords as `evaluate`'s."""
    import warnings

    saved = ev.OnnxModel
    ev.OnnxModel = _EmulatedModel  # the one model this call loads
    try:
        with warnings.catch_warnings():
            # numpy's float16 cast overflow warning: the result is checked for inf below
            warnings.simplefilter("ignore", RuntimeWarning)
            result = ev.evaluate(half_path, data_dir, **kw)
    finally:
        ev.OnnxModel = saved
    if not np.isfinite(result["summary"]["all"]["model_psnr_db"]):
        raise ValueError(f"{half_path}: inf or NaN in float16 (emulated)")
    return result


def compare_fp16(float_path: str | Path, half_path: str | Path, *, seed: int = 0,
                 size_strides: tuple[int, int] = (3, 5), emulate: bool = False
                 ) -> dict[str, float]:  # fmt: skip
    """Max abs difference of amplitude and phase between the float and the fp16 model on one
    seeded random input (`size_strides` x the input multiple), and whether every output of the
    fp16 model is finite there and on the extreme inputs (all zero, all one, depth at either end
    of the volume). `emulate`: the fp16 model computed in float16 (`emulate_fp16`)."""
    import warnings

    f, h = OnnxModel(float_path), OnnxModel(half_path)
    if emulate:
        emulate_fp16(h)
    m = h.multiple
    shape = (1, h.channels, size_strides[0] * m, size_strides[1] * m)
    x = seeded_input(h.channels, shape[2:], seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy's overflow: checked below
        (fa, fp), (ha, hp) = f.run_raw(x), h.run_raw(x)
        finite = bool(np.isfinite(ha).all() and np.isfinite(hp).all())
        for rgb, depth in ((0.0, -1.0), (1.0, 1.0), (1.0, -1.0), (0.0, 1.0)):
            y = np.full(shape, rgb, np.float32)
            if h.channels == 4:
                y[:, 3] = depth
            finite = finite and all(bool(np.isfinite(o).all()) for o in h.run_raw(y))
    return {"amplitude_max_abs_diff": float(np.abs(fa - ha).max()),
            "phase_max_abs_diff": float(np.abs(fp - hp).max()),
            "amplitude_max": float(np.abs(fa).max()), "finite": finite}
