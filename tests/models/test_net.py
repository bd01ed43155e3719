"""The network's shapes and conventions."""

from __future__ import annotations

import pytest
import torch

from nhfd.models.net import NetSpec, build_net, pad_to_multiple, predict


@pytest.mark.parametrize("spec", [NetSpec(8, 2, 1), NetSpec(8, 1, 2), NetSpec(4, 3, 4),
                                  NetSpec(8, 2, 2, growth=1, skip="add"),
                                  NetSpec(8, 2, 2, single_conv_levels=2)])  # fmt: skip
def test_any_size_in_gives_the_same_size_out(spec):
    net = build_net(spec, seed=0).eval()
    rgb = torch.rand(3, 37, 53)
    with torch.no_grad():
        amp, phase = predict(net, rgb)
        amp_b, _ = predict(net, rgb[None].repeat(2, 1, 1, 1))
    assert amp.shape == phase.shape == (3, 37, 53)
    assert amp_b.shape == (2, 3, 37, 53)
    assert (amp > 0).all()  # softplus: amplitude is positive
    assert spec.multiple == spec.unshuffle * 2**spec.depth


def test_padding_is_outside_the_graph_and_cropped_back():
    spec = NetSpec(8, 2, 2)
    x, hw = pad_to_multiple(torch.rand(1, 3, 37, 53), spec.multiple)
    assert hw == (37, 53) and x.shape[-2:] == (40, 56)
    assert (x[..., 37:, :] == 0).all() and (x[..., :, 53:] == 0).all()  # black, as rendered
    net = build_net(spec, seed=0).eval()
    with pytest.raises(RuntimeError):
        net(torch.rand(1, 3, 37, 53))  # the graph itself needs multiples of the stride


def test_seeded_build_is_reproducible_and_leaves_the_global_rng_alone():
    state = torch.random.get_rng_state()
    a, b = build_net(NetSpec(8, 2, 1), seed=3), build_net(NetSpec(8, 2, 1), seed=3)
    assert torch.equal(torch.random.get_rng_state(), state)
    for pa, pb in zip(a.parameters(), b.parameters(), strict=True):
        assert torch.equal(pa, pb)


@pytest.mark.parametrize("name,rgb", [
    ("black", torch.zeros(1, 3, 32, 48)),
    ("white", torch.ones(1, 3, 32, 48)),
    ("saturated", torch.full((1, 3, 32, 48), 4.0)),
    ("negative", torch.full((1, 3, 32, 48), -1.0)),
    ("float16", torch.rand(1, 3, 32, 48).half()),
])  # fmt: skip
def test_extreme_inputs_give_finite_outputs(name, rgb):
    net = build_net(NetSpec(8, 2, 2), seed=0).eval()
    with torch.no_grad():
        amp, phase = predict(net, rgb)
    assert amp.dtype == torch.float32
    assert torch.isfinite(amp).all() and torch.isfinite(phase).all(), name


def test_bad_specs_are_refused_by_name():
    with pytest.raises(ValueError, match="unshuffle = 3"):
        NetSpec(8, 2, 3)
    with pytest.raises(ValueError, match="depth = 9"):
        NetSpec(8, 9, 1)
    with pytest.raises(ValueError, match=r"growth = 3: must be in \[1, 2\]"):
        NetSpec(8, 2, 1, growth=3)
    with pytest.raises(ValueError, match="growth = nan"):
        NetSpec(8, 2, 1, growth=float("nan"))
    with pytest.raises(ValueError, match="skip = 'sum': must be one of concat, add"):
        NetSpec(8, 2, 1, skip="sum")
    with pytest.raises(ValueError, match=r"single_conv_levels = 4: must be in 0\.\.3 \(depth "):
        NetSpec(8, 2, 1, single_conv_levels=4)
    with pytest.raises(ValueError, match=r"deep_width = -8: must be in 0\.\.512 channels"):
        NetSpec(8, 2, 1, deep_width=-8)


def test_growth_sets_the_channels_of_each_level():
    assert NetSpec(16, 3, 2).widths == [16, 32, 64, 128]  # the classic U-Net doubles
    assert NetSpec(16, 3, 2, growth=1).widths == [16, 16, 16, 16]
    assert NetSpec(16, 3, 2, growth=1.5).widths == [16, 24, 36, 54]
    # deep_width sets the second level; the growth applies from there
    assert NetSpec(16, 3, 2, growth=1, deep_width=8).widths == [16, 8, 8, 8]
    assert NetSpec(16, 3, 2, deep_width=8).widths == [16, 8, 16, 32]
    net = build_net(NetSpec(16, 3, 2, growth=1))
    assert [m[0].out_channels for m in net.down] == [16, 16, 16]
    assert net.head.in_channels == 16 and net.head.out_channels == 6 * 2 * 2
    # a run saved before growth and skip existed was a doubling, concatenating U-Net
    old = {"width": 16, "depth": 3, "unshuffle": 2, "inputs": "rgbd"}
    assert NetSpec(**old).widths == [16, 32, 64, 128] and NetSpec(**old).skip == "concat"


def test_summed_skips_halve_the_decoders_first_convolution():
    cat = build_net(NetSpec(16, 2, 2, growth=1), seed=0)
    add = build_net(NetSpec(16, 2, 2, growth=1, skip="add"), seed=0)
    assert [d[0].in_channels for d in cat.dec] == [32, 32]
    assert [d[0].in_channels for d in add.dec] == [16, 16]
    # the sum is what the decoder sees: the upsampled features plus the skip, not either alone
    x = torch.rand(1, 3 * 2 * 2, 8, 8)  # unshuffled sRGB
    seen = {}
    add.dec[0].register_forward_pre_hook(lambda _m, a: seen.setdefault("in", a[0]))
    with torch.no_grad():
        add.trunk(x)
        skip0 = add.inc(x)
        skip1 = add.down[0](skip0)
        up0 = add.up[0](add.dec[1](add.up[1](add.down[1](skip1)) + skip1))
    assert torch.allclose(seen["in"], up0 + skip0, atol=1e-6)


def test_single_conv_levels_thin_the_first_levels_blocks():
    def convs(block):
        return sum(isinstance(m, torch.nn.Conv2d) for m in block)

    def per_level(net):
        """(encoder, decoder) 3 x 3 convolutions per block at each level, first to deepest."""
        enc = [convs(net.inc)] + [convs(d[2]) for d in net.down]
        return enc, [convs(d) for d in net.dec]

    def spec(n):
        return NetSpec(16, 3, 2, growth=1, skip="add", single_conv_levels=n)

    assert per_level(build_net(spec(0))) == ([2, 2, 2, 2], [2, 2, 2])  # the classic U-Net
    assert per_level(build_net(spec(1))) == ([1, 2, 2, 2], [1, 2, 2])
    assert per_level(build_net(spec(2))) == ([1, 1, 2, 2], [1, 1, 2])
    assert per_level(build_net(spec(4))) == ([1, 1, 1, 1], [1, 1, 1])
    # the stride-2 convolutions and the widths are untouched
    assert [d[0].stride for d in build_net(spec(2)).down] == [(2, 2)] * 3
    # a run saved before the key existed had two convolutions everywhere
    old = {"width": 16, "depth": 3, "unshuffle": 2, "inputs": "rgbd"}
    assert NetSpec(**old).single_conv_levels == 0 and NetSpec(**old).deep_width == 0
