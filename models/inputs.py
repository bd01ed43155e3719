"""What the network sees: sRGB alone (`rgb`) or sRGB plus the view's mapped depth (`rgbd`).

Why a depth channel: from sRGB alone a small U-Net has to guess each pixel's depth from local
appearance, and the depth decides the phase curvature the hologram needs. Measured on the donut
scene (README, "RGB or RGB-D"), sRGB-only networks kept drifting their focus toward the reference
plane. The renderer computes the depth anyway, at no extra cost per frame.

The depth channel is the hologram depth `z_h = a + b / d` (the scene's mapping, docs/physics.md)
scaled so the volume spans [-1, 1]: `(z_h - centre) / half_depth`, clipped to
[-DEPTH_CLIP, DEPTH_CLIP]; background (coverage below ALPHA_CONTENT) is 0, the reference plane's
depth.

One formula, three places, all here:

- `depth_channel(mapped_depth(...))`: float64, step by step; training's path (`HoloData`).
- `network_input` (NumPy, float32, in place): the definition of the frame's input. The CPU frame
  worker uses it; it agrees with training's float64 path to about 1e-6.
- `network_input_torch`: the same float32 arithmetic in torch, on the tensors' device (the
  device frame path, `nhfd.pipeline.frame`). Bit for bit `network_input`
  (tests/models/test_inputs_torch.py, at the full 1920 x 1080 panel). It is not used on the CPU
  path: at 1920 x 1080 NumPy took 11.5 ms against torch's 14-16 ms on one thread and up to
  120 ms on two threads of a loaded 2-core machine.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

INPUTS = ("rgb", "rgbd")
# Pixels with less coverage than this are background (no mapped depth).
ALPHA_CONTENT = 0.5
# Scene content mapped outside the volume (views beyond the pose envelope) stays bounded.
DEPTH_CLIP = 2.0


def input_channels(inputs: str) -> int:
    """Channels of the network input for `inputs` ("rgb": 3, "rgbd": 4)."""
    if inputs not in INPUTS:
        raise ValueError(f"inputs = {inputs!r}: must be one of {', '.join(INPUTS)}")
    return 3 + (inputs == "rgbd")


def mapped_depth(depth: np.ndarray, alpha: np.ndarray, a_m: float, b_m: float) -> np.ndarray:
    """Hologram depth `z_h` (m, float32) of a render's depth `[H, W]` (scene units, > 0 on
    content); NaN where coverage is below ALPHA_CONTENT or the depth is not positive."""
    d = np.asarray(depth, np.float64)
    content = (np.asarray(alpha) >= ALPHA_CONTENT) & (d > 0) & np.isfinite(d)
    zh = np.full(d.shape, np.nan, np.float32)
    zh[content] = a_m + b_m / d[content]
    return zh


def _centre_half(volume_m: Sequence[float]) -> tuple[float, float]:
    """Centre and half-depth (m) of the volume [near, far]; refuses an empty or inverted one."""
    lo, hi = float(volume_m[0]), float(volume_m[1])
    if not hi > lo:
        raise ValueError(f"volume_m = {list(volume_m)}: the far end must lie beyond the near end")
    return (lo + hi) / 2, (hi - lo) / 2


def depth_channel(zh_m: np.ndarray, volume_m: Sequence[float]) -> np.ndarray:
    """The network's depth channel `[..., H, W]` float32 from mapped depth (NaN = background)."""
    centre, half = _centre_half(volume_m)
    x = (np.asarray(zh_m, np.float64) - centre) / half
    return np.clip(np.nan_to_num(x, nan=0.0), -DEPTH_CLIP, DEPTH_CLIP).astype(np.float32)


def _depth_coefficients(depth: object, alpha: object, mapping: dict | None,
                        volume_m: Sequence[float] | None) -> tuple[np.float32, np.float32]:
    """The depth channel's `(b / half, (a - centre) / half)`, each rounded once to float32, so
    the channel is `clip(scale / d + offset, -DEPTH_CLIP, DEPTH_CLIP)`; refuses an "rgbd" call
    without what it needs."""
    if depth is None or alpha is None or mapping is None or volume_m is None:
        raise ValueError("an rgbd model needs the render's depth and alpha, the scene mapping "
                         "and the volume")  # fmt: skip
    centre, half = _centre_half(volume_m)
    a_m, b_m = float(mapping["a_m"]), float(mapping["b_m"])
    return np.float32(b_m / half), np.float32((a_m - centre) / half)


def network_input(
    rgb: np.ndarray, inputs: str, *, depth: np.ndarray | None = None,
    alpha: np.ndarray | None = None, mapping: dict | None = None,
    volume_m: Sequence[float] | None = None,
) -> np.ndarray:  # fmt: skip
    """The network input `[C, H, W]` float32 for one render (C = 3 for "rgb", 4 for "rgbd"):
    `rgb` `[3, H, W]` sRGB in [0, 1], and for "rgbd" the render's `depth` `[H, W]` (scene
    units, > 0 on content) and `alpha` `[H, W]` (coverage in [0, 1]), the scene `mapping`
    ({"a_m", "b_m"} in metres, from the model's metadata) and the model's `volume_m`
    ([near, far] hologram depths in metres).

    The depth channel, in float32: `clip((b / half) / d + (a - centre) / half, -DEPTH_CLIP,
    DEPTH_CLIP)`, 0 where the coverage is below ALPHA_CONTENT or the depth is not a positive
    finite number. The reference for `network_input_torch` (the same, bit for bit)."""
    rgb = np.asarray(rgb, np.float32)
    if input_channels(inputs) == 3:
        return rgb
    scale, offset = _depth_coefficients(depth, alpha, mapping, volume_m)
    out = np.empty((4, *rgb.shape[-2:]), np.float32)
    out[:3] = rgb
    # depth_channel(mapped_depth(...)) in float32 and in place: (a + b / d - centre) / half. It
    # agrees with that float64 path (training's) to about 1e-6 and takes about 5 ms per
    # 1024 x 576 frame instead of 25: the daemon builds one per frame.
    d = np.asarray(depth, np.float32)
    ch = out[3]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        np.divide(scale, d, out=ch)
    ch += offset
    np.clip(ch, -DEPTH_CLIP, DEPTH_CLIP, out=ch)
    content = (np.asarray(alpha) >= ALPHA_CONTENT) & (d > 0) & np.isfinite(d)
    np.copyto(ch, 0.0, where=~content)
    return out


def network_input_torch(
    rgb: torch.Tensor, inputs: str, *, depth: torch.Tensor | None = None,
    alpha: torch.Tensor | None = None, mapping: dict | None = None,
    volume_m: Sequence[float] | None = None,
) -> torch.Tensor:  # fmt: skip
    """`network_input` in torch on the tensors' device (the device frame path): `[C, H, W]`
    float32 from `rgb` `[3, H, W]`, `depth` and `alpha` `[H, W]` (units as there). The same
    float32 operations in the same order (the two coefficients rounded to float32 once, as
    0-d tensors: a Python scalar divided by a tensor would be a reciprocal and a product), so
    the result is `network_input`'s bit for bit."""
    rgb = rgb.to(torch.float32)
    if input_channels(inputs) == 3:
        return rgb
    scale, offset = _depth_coefficients(depth, alpha, mapping, volume_m)
    d = depth.to(torch.float32)
    ch = torch.tensor(scale, device=d.device) / d
    ch = (ch + torch.tensor(offset, device=d.device)).clamp(-DEPTH_CLIP, DEPTH_CLIP)
    content = (alpha >= ALPHA_CONTENT) & (d > 0) & torch.isfinite(d)
    ch = torch.where(content, ch, torch.zeros_like(ch))
    return torch.cat([rgb, ch[None]])


def seeded_input(channels: int, hw: tuple[int, int], seed: int, batch: int = 1) -> np.ndarray:
    """A seeded `[batch, channels, H, W]` float32 input as the daemon sends them, for checking
    one graph against another: sRGB in [0, 1] and, for an rgbd model, the mapped depth spanning
    the volume, [-1, 1]."""
    x = np.random.default_rng(seed).random((batch, channels, *hw), dtype=np.float32)
    if channels == 4:
        x[:, 3] = 2 * x[:, 3] - 1
    return x
