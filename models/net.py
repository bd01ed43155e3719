"""The NHF network: a small U-Net from one sRGB view to the complex reference-plane hologram.

Conventions (the exported ONNX graph has the same ones):
- input `[B, C, H, W]`: the renderer's sRGB in [0, 1] composited on black, and for `inputs =
  "rgbd"` a fourth channel, the mapped depth (`nhfd.models.inputs`); sRGB normalisation happens
  inside the graph, so callers feed what the renderer gives them;
- outputs `amplitude` and `phase`, each `[B, 3, H, W]` (R, G, B): amplitude through softplus, in
  units of the dataset's amplitude scale; phase unconstrained (used only through cos/sin, so no
  wrapping in the graph: double-phase coding wraps);
- H and W must be multiples of `multiple = unshuffle * 2**depth`. `pad_to_multiple` /
  `predict` pad outside the graph and crop back, so any size works (an exported U-Net fails at
  1080 rows otherwise).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from nhfd.config import DEPTH_MAX, GROWTH_RANGE, SKIPS, WIDTH_MAX
from nhfd.models.inputs import input_channels

# sRGB renders of splat scenes on black are dark on average; centring them is enough.
INPUT_MEAN = 0.5
INPUT_STD = 0.25


@dataclass(frozen=True)
class NetSpec:
    """The network's shape: base width, depth (levels below the first), unshuffle factor,
    inputs, the width's growth per level (2: each level doubles the channels, the classic
    U-Net; 1: every level keeps the base width), and how the decoder joins each skip ("concat":
    side by side, the classic U-Net; "add": summed, half the arithmetic of the decoder's first
    convolution at each level), how many levels, from the first, have one 3 x 3 convolution
    per block instead of two (0, the classic U-Net), and the channels of the second level when
    they are not `width * growth` (`deep_width`; 0: they are; the growth applies below it)."""

    width: int = 16
    depth: int = 3
    unshuffle: int = 2
    inputs: str = "rgb"
    growth: float = GROWTH_RANGE[1]
    skip: str = SKIPS[0]
    single_conv_levels: int = 0
    deep_width: int = 0

    def __post_init__(self) -> None:
        input_channels(self.inputs)  # validates
        if not 1 <= self.width <= WIDTH_MAX:
            raise ValueError(f"width = {self.width}: must be in 1..{WIDTH_MAX} channels")
        if not 0 <= self.depth <= DEPTH_MAX:
            raise ValueError(f"depth = {self.depth}: must be in 0..{DEPTH_MAX} levels")
        if self.unshuffle not in (1, 2, 4, 8):
            raise ValueError(f"unshuffle = {self.unshuffle}: must be 1, 2, 4 or 8")
        lo, hi = GROWTH_RANGE
        if not lo <= self.growth <= hi:
            raise ValueError(f"growth = {self.growth}: must be in [{lo:g}, {hi:g}] (width factor "
                             "per level)")  # fmt: skip
        if self.skip not in SKIPS:
            raise ValueError(f"skip = {self.skip!r}: must be one of {', '.join(SKIPS)}")
        if not 0 <= self.single_conv_levels <= self.depth + 1:
            raise ValueError(f"single_conv_levels = {self.single_conv_levels}: must be in "
                             f"0..{self.depth + 1} (depth + 1 levels)")  # fmt: skip
        if not 0 <= self.deep_width <= WIDTH_MAX:
            raise ValueError(f"deep_width = {self.deep_width}: must be in 0..{WIDTH_MAX} channels "
                             "(0: width * growth)")  # fmt: skip

    @property
    def channels(self) -> int:
        """Input channels: 3 (sRGB) or 4 (sRGB + mapped depth)."""
        return input_channels(self.inputs)

    @property
    def widths(self) -> list[int]:
        """Channels at each level, the first (after unshuffle) to the deepest."""
        if not self.deep_width:
            return [max(1, round(self.width * self.growth**i)) for i in range(self.depth + 1)]
        return [self.width] + [max(1, round(self.deep_width * self.growth**i))
                               for i in range(self.depth)]  # fmt: skip

    @property
    def multiple(self) -> int:
        """Input H and W must be multiples of this (the network's total stride)."""
        return self.unshuffle * 2**self.depth

    def to_json(self) -> dict:
        """The spec's fields as a dict (checkpoints and the ONNX metadata record it)."""
        return asdict(self)


def _block(c_in: int, c_out: int, convs: int = 2) -> nn.Sequential:
    """`convs` 3 x 3 convolutions, each followed by a ReLU (module indices 0, 2, ... as the
    two-convolution block always had, so saved networks load)."""
    layers: list[nn.Module] = []
    for i in range(convs):
        layers += [nn.Conv2d(c_in if i == 0 else c_out, c_out, 3, padding=1), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class NHFNet(nn.Module):
    """U-Net: pixel-unshuffle, `depth` stride-2 levels with skips, pixel-shuffle back."""

    def __init__(self, spec: NetSpec) -> None:
        super().__init__()
        self.spec = spec
        f, widths = spec.unshuffle, spec.widths

        def convs(level: int) -> int:
            return 1 if level < spec.single_conv_levels else 2

        self.inc = _block(spec.channels * f * f, widths[0], convs(0))
        # Strided convolutions downsample: cheaper than pooling + conv, and export cleanly.
        self.down = nn.ModuleList(
            nn.Sequential(nn.Conv2d(widths[i], widths[i + 1], 3, stride=2, padding=1),
                          nn.ReLU(inplace=True),
                          _block(widths[i + 1], widths[i + 1], convs(i + 1)))
            for i in range(spec.depth)
        )  # fmt: skip
        self.up = nn.ModuleList(
            nn.ConvTranspose2d(widths[i + 1], widths[i], 2, stride=2) for i in range(spec.depth)
        )
        joined = 2 if spec.skip == "concat" else 1  # channels into each decoder, per width
        self.dec = nn.ModuleList(
            _block(joined * widths[i], widths[i], convs(i)) for i in range(spec.depth)
        )
        self.head = nn.Conv2d(widths[0], 6 * f * f, 1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`x` `[B, C, H, W]` (sRGB, then depth for rgbd; H, W multiples of `spec.multiple`) ->
        (amplitude, phase)."""
        # float16 (or float64) input is computed in float32: the weights are float32.
        x = x.float()
        rgb = (x[:, :3] - INPUT_MEAN) / INPUT_STD
        x = torch.cat([rgb, x[:, 3:]], dim=1) if x.shape[1] > 3 else rgb
        f = self.spec.unshuffle
        if f > 1:
            x = F.pixel_unshuffle(x, f)
        x = self.head(self.trunk(x))
        if f > 1:
            x = F.pixel_shuffle(x, f)
        return F.softplus(x[:, :3]), x[:, 3:]

    def trunk(self, x: torch.Tensor) -> torch.Tensor:
        """The U-Net between the unshuffled, normalised input `[B, C f f, H/f, W/f]` and the
        head: features `[B, width, H/f, W/f]` (shared with `nhfd.models.serving.ServingNet`)."""
        x = self.inc(x)
        skips = [x]
        for down in self.down:
            x = down(x)
            skips.append(x)
        skips.pop()
        for i in reversed(range(self.spec.depth)):
            up = self.up[i](x)
            x = self.dec[i](torch.cat([up, skips[i]], dim=1) if self.spec.skip == "concat"
                            else up + skips[i])  # fmt: skip
        return x


def build_net(spec: NetSpec, seed: int | None = None) -> NHFNet:
    """A freshly initialised network (seeded from `seed` when given, without touching the global
    RNG's later draws: its state is saved and restored)."""
    if seed is None:
        return NHFNet(spec)
    state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        return NHFNet(spec)
    finally:
        torch.random.set_rng_state(state)


def parameter_count(net: nn.Module) -> int:
    """The number of scalar parameters of `net`."""
    return sum(p.numel() for p in net.parameters())


def pad_amounts(h: int, w: int, multiple: int) -> tuple[int, int]:
    """Rows and columns to add (bottom, right) to reach multiples of `multiple`."""
    return (-h) % multiple, (-w) % multiple


def pad_to_multiple(rgb: torch.Tensor, multiple: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """Pad `[..., H, W]` at the bottom and right with black (the renderer's background) to
    multiples of `multiple`; returns the padded tensor and the original (H, W) to crop back to."""
    h, w = rgb.shape[-2:]
    ph, pw = pad_amounts(h, w, multiple)
    if ph or pw:
        rgb = F.pad(rgb, (0, pw, 0, ph))
    return rgb, (h, w)


def predict(net: NHFNet, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Amplitude and phase for network inputs of any size (`[C, H, W]` or `[B, C, H, W]`,
    `nhfd.models.inputs`)."""
    c = net.spec.channels
    if x.dim() not in (3, 4) or x.shape[-3] != c:
        raise ValueError(f"input {tuple(x.shape)}: expected [{c}, H, W] or [B, {c}, H, W] "
                         f"({net.spec.inputs})")  # fmt: skip
    single = x.dim() == 3
    x = x[None] if single else x
    x, (h, w) = pad_to_multiple(x.float(), net.spec.multiple)
    amp, phase = net(x)
    amp, phase = amp[..., :h, :w], phase[..., :h, :w]
    return (amp[0], phase[0]) if single else (amp, phase)


def to_field(amplitude: torch.Tensor, phase: torch.Tensor, amplitude_scale: float) -> torch.Tensor:
    """Complex field (the dataset's units) from the network's outputs."""
    return torch.polar(amplitude * amplitude_scale, phase)
