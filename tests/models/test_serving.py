"""The exported form of the network: the same function, without the operators that made
onnxruntime slow at full resolution."""

from __future__ import annotations

import onnx
import pytest
import torch
import torch.nn.functional as F

from nhfd.models.export import export_onnx
from nhfd.models.net import NetSpec, build_net
from nhfd.models.serving import ServingNet, softplus_exportable
from tests.models.conftest import tiny_options


def _perturbed(spec: NetSpec) -> torch.nn.Module:
    """A seeded network with its weights moved off their initial values, so the head's
    per-position biases differ (zero biases would hide a wrong bias layout)."""
    net = build_net(spec, seed=1).eval()
    g = torch.Generator().manual_seed(2)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g))
    return net


@pytest.mark.parametrize("spec", [NetSpec(8, 2, 1), NetSpec(8, 1, 2, "rgbd"),
                                  NetSpec(4, 2, 4), NetSpec(4, 1, 4, "rgbd"),
                                  NetSpec(8, 2, 2, "rgbd", growth=1, skip="add"),
                                  NetSpec(8, 2, 2, "rgbd", growth=1, skip="add",
                                          single_conv_levels=2, deep_width=4)])  # fmt: skip
def test_serving_form_computes_the_networks_function(spec):
    net = _perturbed(spec)
    m = spec.multiple
    x = torch.rand(2, spec.channels, 3 * m, 5 * m)
    x[:, 3:] = 4 * x[:, 3:] - 2  # depth spans [-2, 2]
    with torch.no_grad():
        a0, p0 = net(x)
        a1, p1 = ServingNet(net)(x)
    assert a1.shape == a0.shape and p1.shape == p0.shape
    assert (a0 - a1).abs().max() < 1e-5
    assert (p0 - p1).abs().max() < 1e-5
    # each output pixel sits where pixel-shuffle puts it: swapping two positions would show
    assert not torch.allclose(a0[..., 0, 0], a0[..., 0, 1])


def test_exportable_softplus_matches_softplus_over_the_whole_range():
    a = torch.linspace(-120, 120, 240001)
    err = (softplus_exportable(a) - F.softplus(a)).abs()
    assert (err / F.softplus(a).clamp(min=1.0)).max() < 3e-7  # a few float32 ulps
    assert torch.isfinite(softplus_exportable(torch.tensor([-1e30, 1e30, -3e38]))).all()


def test_export_has_no_full_resolution_shuffles_or_softplus(tiny_data, tmp_path):
    from nhfd.models.train import train

    run = tmp_path / "run"
    train(tiny_data, run, tiny_options(unshuffle=2, steps=1), log=lambda _m: None)
    result = export_onnx(run, tmp_path / "m.onnx")
    ops = {n.op_type for n in onnx.load(str(result.path)).graph.node}
    assert not ops & {"Softplus", "DepthToSpace", "SpaceToDepth", "Transpose", "Where"}, ops
    assert result.max_abs_diff < 1e-4
