"""Mixed precision in training: the autocast choice, a float32 loss inside any autocast region,
and bf16 steps on the CPU. The fp16 + GradScaler path needs CUDA and skips here."""

from __future__ import annotations

import math

import pytest
import torch

import nhfd.models.loss as loss_module
from nhfd.config import load_config
from nhfd.models.data import HoloData
from nhfd.models.loss import FocalStackLoss, Optics, uniform_planes
from nhfd.models.net import build_net, predict, to_field
from nhfd.models.train import (
    AMP_MODES,
    CHECKPOINT,
    TrainOptions,
    amp_dtype,
    autocast_context,
    float32_loss,
    grad_scaler,
    train,
)

from .conftest import tiny_options

CPU = torch.device("cpu")
CUDA = torch.device("cuda")  # a device name only: nothing here runs on it


def test_autocast_dtype_per_mode_and_device():
    assert amp_dtype("auto", CPU) is None  # the CPU trains in float32 unless told otherwise
    assert amp_dtype("off", CPU) is None
    assert amp_dtype("off", CUDA) is None
    assert amp_dtype("bf16", CPU) is torch.bfloat16
    assert amp_dtype("bf16", CUDA) is torch.bfloat16
    assert amp_dtype("fp16", CUDA) is torch.float16
    with pytest.raises(ValueError, match=r"amp = 'fp16' on cpu: needs CUDA"):
        amp_dtype("fp16", CPU)
    with pytest.raises(ValueError, match=r"amp = 'half': must be one of auto, off, bf16, fp16"):
        amp_dtype("half", CPU)
    with pytest.raises(ValueError, match=r"amp = 'fp32': must be one of auto, off, bf16, fp16"):
        tiny_options(amp="fp32")
    assert AMP_MODES == ("auto", "off", "bf16", "fp16")


def test_amp_is_a_configuration_key_with_auto_default():
    config = load_config(None).config
    assert config.model.train.amp == "auto"
    assert TrainOptions().amp == "auto"
    assert TrainOptions.from_config(config.model).amp == "auto"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_auto_picks_bf16_where_supported_and_scales_fp16():
    want = torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    assert amp_dtype("auto", CUDA) is want
    assert grad_scaler(torch.float16, CUDA).is_enabled()
    assert not grad_scaler(torch.bfloat16, CUDA).is_enabled()


def test_no_gradient_scaler_without_fp16():
    assert not grad_scaler(None, CPU).is_enabled()
    assert not grad_scaler(torch.bfloat16, CPU).is_enabled()


def test_the_loss_stays_float32_inside_a_bf16_autocast_region(tiny_data, monkeypatch):
    """Under CPU bf16 autocast the network's outputs are bf16 (autocast is on), yet the loss's
    field, its propagation (FFTs) and the result are float32 / complex64, and equal the loss of
    the same outputs computed outside any autocast region."""
    data = HoloData(tiny_data)
    s = data.splits["train"]
    optics = Optics.from_manifest(data.manifest)
    loss_fn = FocalStackLoss(optics)
    planes = uniform_planes(optics.volume_m, 3)
    net = build_net(tiny_options().spec, seed=0)
    seen: list[tuple[torch.dtype, torch.dtype]] = []
    real = loss_module.propagate

    def spy(field, *a, **kw):
        out = real(field, *a, **kw)
        seen.append((field.dtype, out.dtype))
        return out

    monkeypatch.setattr(loss_module, "propagate", spy)
    x, target = s.rgb[:1], s.field[:1]
    with autocast_context(torch.bfloat16, CPU):
        amp, phase = predict(net, x)
        assert amp.dtype == torch.bfloat16  # autocast really is on for the network
        out = float32_loss(loss_fn, amp, phase, target, planes, [1], (True,) * 4)
    assert out["loss"].dtype == torch.float32
    assert seen and all(d == (torch.complex64, torch.complex64) for d in seen), seen
    seen.clear()
    ref = loss_fn(to_field(amp.float(), phase.float(), 1.0), target, planes, [1], (True,) * 4)
    value = float(out["loss"].detach())
    assert value == pytest.approx(float(ref["loss"].detach()), rel=1e-6)
    assert math.isfinite(value)


def test_bf16_training_on_the_cpu_gives_finite_falling_loss(tiny_data, tmp_path):
    data = HoloData(tiny_data)
    quiet = {"log": lambda _m: None, "data": data}
    res = train(tiny_data, tmp_path / "bf16", tiny_options(steps=4, amp="bf16"), **quiet)
    assert res.step == 4 and math.isfinite(res.last_loss)
    ckpt = torch.load(tmp_path / "bf16" / CHECKPOINT, weights_only=False)
    assert ckpt["options"]["amp"] == "bf16"
    assert ckpt["grad_scaler"] is None  # bf16 needs no scaler
    for t in ckpt["model"].values():
        assert t.dtype == torch.float32  # the weights stay float32; only activations are bf16
    # amp may change on resume (rounding, not the computation): bf16 -> off continues.
    more = train(tiny_data, tmp_path / "bf16", tiny_options(steps=6, amp="off"), **quiet)
    assert more.resumed_from == 4 and more.step == 6 and math.isfinite(more.last_loss)


def test_auto_on_the_cpu_trains_exactly_as_float32(tiny_data, tmp_path):
    """"auto" and "off" on the CPU are the same float32 run, bit for bit."""
    data = HoloData(tiny_data)
    quiet = {"log": lambda _m: None, "data": data}
    train(tiny_data, tmp_path / "a", tiny_options(steps=2, amp="auto"), **quiet)
    train(tiny_data, tmp_path / "b", tiny_options(steps=2, amp="off"), **quiet)
    a = torch.load(tmp_path / "a" / CHECKPOINT, weights_only=False)["model"]
    b = torch.load(tmp_path / "b" / CHECKPOINT, weights_only=False)["model"]
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("amp", ["fp16", "bf16", "auto"])
def test_cuda_amp_training_is_finite_and_keeps_its_scaler(tiny_data, tmp_path, amp):
    """A few CUDA steps in each mode: finite loss, float32 weights, and for fp16 the gradient
    scaler's state in the checkpoint (a resumed run continues with its scale)."""
    if amp == "bf16" and not torch.cuda.is_bf16_supported():
        pytest.skip("this GPU has no bf16")
    data = HoloData(tiny_data)
    quiet = {"log": lambda _m: None, "data": data}
    res = train(tiny_data, tmp_path / amp, tiny_options(steps=4, amp=amp, device="cuda"), **quiet)
    assert res.step == 4 and math.isfinite(res.last_loss)
    ckpt = torch.load(tmp_path / amp / CHECKPOINT, weights_only=False)
    fp16 = amp_dtype(amp, CUDA) is torch.float16
    assert (ckpt["grad_scaler"] is not None) == fp16
    if fp16:
        assert ckpt["grad_scaler"]["scale"] > 0
    assert all(t.dtype == torch.float32 for t in ckpt["model"].values())
    more = train(tiny_data, tmp_path / amp, tiny_options(steps=6, amp=amp, device="cuda"),
                 **quiet)  # fmt: skip
    assert more.resumed_from == 4 and math.isfinite(more.last_loss)
