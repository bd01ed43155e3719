"""The NHF network's function, rewritten with operators onnxruntime's CPU provider runs fast.

`nhfd export` exports `ServingNet(net)`, not `net`: the same function (to float32 rounding; the
export check measures it against `NHFNet.forward`) with the same inputs and outputs. What
changes is how the full-resolution ends of the graph are written. Measured with onnxruntime 1.32
on 2 cores at 1024 x 576 for the tensors of the earlier fast profile (16/3/4, unshuffle 4), one
operator per graph:

- sRGB normalisation plus pixel-unshuffle exported as Sub, Div, Split, Concat and a 6-D
  Transpose: about 13 ms. Here it is one stride-`f` convolution with one-hot weights that also
  scale and shift the sRGB channels: about 5 ms. `4 x - 2` rounds exactly as `(x - 0.5) / 0.25`
  does, since scaling by a power of two commutes with rounding.
- the 1 x 1 head convolution plus DepthToSpace (pixel-shuffle): about 17 ms. Here it is a
  ConvTranspose with kernel and stride `f` per output (amplitude, phase), which is the same
  linear map; the head's per-position bias rides on a constant-one input channel.
- Softplus exported as Softplus, Greater and Where: about 18 ms (onnxruntime's Softplus kernel
  is not vectorised). Here it is `max(a, log(1 + exp(min(a, 80))))`: five elementwise passes
  over the full-resolution amplitude. The earlier `relu(a) + log(1 + exp(-|a|))` took seven:
  the fastest profile's whole graph ran 1.9 ms faster with five (43.0 against 45.0 ms, 25
  rounds in turns). Amplitudes below about 1e-7 (in amplitude-scale units) come out as 0
  instead of their tiny positive value.
"""

from __future__ import annotations

import torch
from torch import nn

from nhfd.models.net import INPUT_MEAN, INPUT_STD, NHFNet


def _unshuffle_weights(channels: int, f: int) -> tuple[torch.Tensor, torch.Tensor]:
    """One-hot `[C f f, C, f, f]` weights and `[C f f]` bias: pixel-unshuffle's channel order
    (`c f^2 + i f + j`), with the sRGB channels normalised on the way."""
    weight = torch.zeros(channels * f * f, channels, f, f)
    bias = torch.zeros(channels * f * f)
    for c in range(channels):
        scale, shift = (1 / INPUT_STD, -INPUT_MEAN / INPUT_STD) if c < 3 else (1.0, 0.0)
        for i in range(f):
            for j in range(f):
                weight[c * f * f + i * f + j, c, i, j] = scale
                bias[c * f * f + i * f + j] = shift
    return weight, bias


# exp(80) is finite in float32 (its limit is about exp(88.7)); above 17, softplus(a) = a anyway.
_EXP_LIMIT = 80.0


def softplus_exportable(a: torch.Tensor) -> torch.Tensor:
    """softplus without the threshold branch: exact to float32 rounding (`log(1 + e^a)` rounds
    to `a` above about 17, and the max returns `a` above `_EXP_LIMIT`); exp never overflows."""
    return torch.maximum(a, torch.log(1 + torch.exp(torch.clamp(a, max=_EXP_LIMIT))))


class ServingNet(nn.Module):
    """`net`'s function with export-friendly ends around `net.trunk`.

    `subframes` K: the heads emit K frames per inference, amplitude and phase `[B, 3 K, H, W]`
    (subframe k in channels 3k..3k+2), each head `net.head`'s to begin with (`with_subframes`
    makes them differ, so tuning can take them apart)."""

    def __init__(self, net: NHFNet, subframes: int = 1) -> None:
        super().__init__()
        self.net = net
        self.subframes = int(subframes)
        f, c = net.spec.unshuffle, net.spec.channels
        self.unshuffle = nn.Conv2d(c, c * f * f, f, stride=f)
        weight, bias = _unshuffle_weights(c, f)
        with torch.no_grad():
            self.unshuffle.weight.copy_(weight)
            self.unshuffle.bias.copy_(bias)
        # head: [6 f f, w0, 1, 1] -> ConvTranspose [w0 + 1, 6, f, f]; output channel k of the
        # head is (colour-or-phase o, row i, column j) with k = o f^2 + i f + j (pixel-shuffle).
        head_w = net.head.weight.detach()[:, :, 0, 0]
        w0 = head_w.shape[1]
        stacked = torch.cat([head_w, net.head.bias.detach()[:, None]], dim=1)
        stacked = stacked.T.reshape(w0 + 1, 6, f, f)
        k = self.subframes
        self.amplitude = nn.ConvTranspose2d(w0 + 1, 3 * k, f, stride=f, bias=False)
        self.phase = nn.ConvTranspose2d(w0 + 1, 3 * k, f, stride=f, bias=False)
        with torch.no_grad():
            self.amplitude.weight.copy_(stacked[:, :3].repeat(1, k, 1, 1))
            self.phase.weight.copy_(stacked[:, 3:].repeat(1, k, 1, 1))

    def with_subframes(self, k: int, jitter: float, seed: int) -> ServingNet:
        """This network with K heads (it must have one): each the present head, and the phase
        weights of subframes 1..K-1 moved by seeded noise of `jitter` x their rms, so that
        tuning on the subframes' mean intensity takes them apart (identical heads get identical
        gradients and stay one frame shown K times). Subframe 0 is the present head exactly."""
        if self.subframes != 1:
            raise ValueError(f"subframes = {self.subframes}: only a one-frame network is "
                             "widened to K subframes")
        out = ServingNet(self.net, subframes=k)  # the same trunk (shared, not copied)
        with torch.no_grad():
            out.unshuffle.weight.copy_(self.unshuffle.weight)
            out.unshuffle.bias.copy_(self.unshuffle.bias)
            out.amplitude.weight.copy_(self.amplitude.weight.repeat(1, k, 1, 1))
            out.phase.weight.copy_(self.phase.weight.repeat(1, k, 1, 1))
            if k > 1 and jitter > 0:
                w = self.phase.weight
                g = torch.Generator().manual_seed(int(seed))
                noise = torch.randn((w.shape[0], 3 * (k - 1), *w.shape[2:]), generator=g)
                out.phase.weight[:, 3:] += noise * (jitter * w.pow(2).mean().sqrt())
        return out

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Same contract as `NHFNet.forward`; with K subframes the outputs have 3 K channels."""
        x = self.net.trunk(self.unshuffle(x.float()))
        x = torch.cat([x, torch.ones_like(x[:, :1])], dim=1)
        return softplus_exportable(self.amplitude(x)), self.phase(x)
