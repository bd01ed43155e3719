"""`TorchModel` (`daemon.frames.inference = "torch"`): a model file's network rebuilt as a torch
module gives what onnxruntime gives for the same file, at the training window and the full panel,
and a file whose graph it would not reproduce is refused at load."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
import torch
from onnx import helper, numpy_helper

from nhfd.models.export import OnnxModel, export_onnx
from nhfd.models.half import convert_fp16
from nhfd.models.metadata import METADATA_KEY, ModelMismatch, NotAModel
from nhfd.models.torch_model import TORCH_PROVIDER, TorchModel

# torch against onnxruntime on the same float32 weights: the export's own check measures about
# 1e-6 on these networks (float32 sums in another order); a wrong weight or operator is >1e-2.
TOL = 1e-5


@pytest.fixture(scope="module")
def shipped():
    from nhfd.demos.serve import DEFAULT_MODEL

    if not DEFAULT_MODEL.exists():
        pytest.skip(f"no shipped model at {DEFAULT_MODEL}")
    return DEFAULT_MODEL


def _inputs(channels: int, hw: tuple[int, int], seed: int, batch: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.random((batch, channels, *hw), dtype=np.float32)
    if channels == 4:  # mapped depth spans [-1, 1] over the volume
        x[:, 3] = 2 * x[:, 3] - 1
    return x


def _worst(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    return max(float(np.abs(x - y).max()) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("hw", [(288, 512), (1080, 1920), (100, 150)],
                         ids=["training-window", "full-panel", "not-a-multiple"])
def test_the_rebuilt_network_gives_onnxruntimes_outputs(shipped, hw):
    torch_model, ort_model = TorchModel(shipped), OnnxModel(shipped)
    x = _inputs(torch_model.channels, hw, seed=7)[0]
    got, want = torch_model(x), ort_model(x)
    assert got[0].shape == want[0].shape == (3, *hw)
    assert _worst(got, want) <= TOL
    assert np.isfinite(got[0]).all() and np.isfinite(got[1]).all()


def test_it_serves_as_onnx_model_does(shipped):
    m, ref = TorchModel(shipped), OnnxModel(shipped)
    for key in ("inputs", "channels", "multiple", "colours", "amplitude_scale", "metadata"):
        assert getattr(m, key) == getattr(ref, key), key
    assert m.providers == [TORCH_PROVIDER]
    assert m.input_shape[1] == m.channels == 4
    # run_on keeps tensors on the device, any batch and size, cropped back
    x = torch.from_numpy(_inputs(4, (40, 70), seed=3, batch=2))
    amp, phase = m.run_on(x)
    assert amp.shape == phase.shape == (2, 3, 40, 70) and isinstance(amp, torch.Tensor)
    assert _worst((amp.numpy(), phase.numpy()), ref(x.numpy())) <= TOL
    with pytest.raises(ValueError, match=r"rgbd input \(2, 3, 40, 70\): expected \[4, H, W\]"):
        m.run_on(x[:, :3])
    with pytest.raises(ValueError, match="must be multiples of 16"):
        m.run_raw(x.numpy())


def test_an_fp16_file_serves_from_its_float16_weights(shipped, tmp_path):
    half = convert_fp16(shipped, tmp_path / "h.onnx")
    m = TorchModel(half)
    x = _inputs(4, (288, 512), seed=11)[0]
    # computed in float32 from the file's float16 weights: within float16 rounding of the
    # file's own onnxruntime run (which rounds some operators to float16), and of the float
    # model (the weights' rounding alone)
    assert _worst(m(x), OnnxModel(half)(x)) <= 5e-3
    assert _worst(m(x), OnnxModel(shipped)(x)) <= 5e-3


def _edited(src, dst, edit) -> str:
    model = onnx.load(str(src))
    edit(model)
    onnx.save(model, str(dst))
    return str(dst)


def _double_the_phase(model) -> None:
    """Append `phase = 2 * phase`: a graph computing something the spec's network does not."""
    g = model.graph
    for node in g.node:
        node.output[:] = ["phase_raw" if o == "phase" else o for o in node.output]
    g.initializer.append(numpy_helper.from_array(np.array(2.0, np.float32), "two"))
    g.node.append(helper.make_node("Mul", ["phase_raw", "two"], ["phase"]))


def _quantise_the_phase(model) -> None:
    """Pass the phase through QuantizeLinear / DequantizeLinear, as an int8 export does."""
    g = model.graph
    for node in g.node:
        node.output[:] = ["phase_raw" if o == "phase" else o for o in node.output]
    g.initializer.extend([numpy_helper.from_array(np.array(0.05, np.float32), "q_scale"),
                          numpy_helper.from_array(np.array(0, np.int8), "q_zero")])
    g.node.extend([helper.make_node("QuantizeLinear", ["phase_raw", "q_scale", "q_zero"], ["q"]),
                   helper.make_node("DequantizeLinear", ["q", "q_scale", "q_zero"], ["phase"])])


def _with_spec(**changes):
    def edit(model) -> None:
        for prop in model.metadata_props:
            if prop.key == METADATA_KEY:
                meta = json.loads(prop.value)
                if changes:
                    meta["net"].update(changes)
                else:
                    del meta["net"]
                prop.value = json.dumps(meta)
    return edit


def test_a_graph_the_rebuild_does_not_reproduce_is_refused(shipped, tmp_path):
    path = _edited(shipped, tmp_path / "doubled.onnx", _double_the_phase)
    assert OnnxModel(path)  # a valid model file: onnxruntime would serve it
    with pytest.raises(NotAModel) as e:
        TorchModel(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}: rebuilt as a torch module, it differs from the file's own "
                          "graph by ")
    assert 'daemon.frames.inference = "onnxruntime"' in msg
    # the difference named is the real one: phases are O(1) rad, doubling them moves them a lot
    assert float(msg.split("graph by ")[1].split()[0]) > 0.1


def test_int8_older_and_mismatched_files_are_refused_saying_why(shipped, tmp_path):
    q = _edited(shipped, tmp_path / "q.onnx", _quantise_the_phase)
    with pytest.raises(NotAModel, match=r"q\.onnx: an int8 model \(DequantizeLinear, "
                                        r"QuantizeLinear\): it serves with onnxruntime"):
        TorchModel(q)
    old = _edited(shipped, tmp_path / "old.onnx", _with_spec())
    with pytest.raises(NotAModel, match=r'old\.onnx: its metadata has no network spec \("net"\)'):
        TorchModel(old)
    wide = _edited(shipped, tmp_path / "wide.onnx", _with_spec(width=24))
    with pytest.raises(NotAModel, match=r"wide\.onnx: parameter net\.inc\.0\.weight is "
                                        r"\[16, 16, 3, 3\] in the file, \[24, 16, 3, 3\]"):
        TorchModel(wide)
    bad = _edited(shipped, tmp_path / "bad.onnx", _with_spec(width=0))
    with pytest.raises(NotAModel, match=r"bad\.onnx: its network spec .* width = 0: must be"):
        TorchModel(bad)


def test_optics_are_checked_as_onnx_models_are(shipped):
    meta = OnnxModel(shipped).metadata
    expected = {"z0_m": meta["z0_m"] * 2}
    with pytest.raises(ModelMismatch, match="z0_m"):
        TorchModel(shipped, expected=expected)


def test_another_spec_rebuilds_too(tiny_data, tmp_path):
    """A network unlike the shipped one: rgb input, no unshuffle, concatenated skips, widths
    doubling per level, one single-convolution level."""
    from nhfd.models.train import train

    from .conftest import tiny_options

    run = tmp_path / "run"
    train(tiny_data, run, tiny_options(skip="concat", growth=2.0, single_conv_levels=1),
          log=lambda _m: None)
    path = export_onnx(run, tmp_path / "t.onnx", check=False).path
    m, ref = TorchModel(path), OnnxModel(path)
    spec = m.metadata["net"]
    assert (spec["unshuffle"], spec["skip"], spec["growth"], spec["single_conv_levels"],
            m.inputs) == (1, "concat", 2.0, 1, "rgb")
    x = _inputs(3, (64, 96), seed=5)[0]
    assert _worst(m(x), ref(x)) <= TOL


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_on_a_gpu_the_outputs_stay_on_it_and_match(shipped):
    """On CUDA the convolutions run in float32 (TorchModel turns cuDNN's default TF32 off: with
    it an H200 gave 5e-4 relative), so the full panel's outputs are onnxruntime's on the CPU
    to float32 rounding of the sums, relative to the outputs' largest magnitude."""
    m = TorchModel(shipped, device="cuda:0")
    x = _inputs(4, (1080, 1920), seed=13)
    amp, phase = m.run_on(torch.from_numpy(x).to("cuda:0"))
    assert amp.device.type == phase.device.type == "cuda"
    want = OnnxModel(shipped)(x)
    for got, ref in zip((amp.cpu().numpy(), phase.cpu().numpy()), want, strict=True):
        assert np.abs(got - ref).max() <= 1e-4 * np.abs(ref).max()


def test_a_device_name_is_checked_as_everywhere(shipped):
    with pytest.raises(ValueError, match=r"^device = 'gpu': must be one of cpu, cuda, cuda:N "
                                         r"\(N: a CUDA device index\)$"):
        TorchModel(shipped, device="gpu")
    assert TorchModel(shipped, device=" CPU ").device == torch.device("cpu")
