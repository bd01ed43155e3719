"""The network input's two implementations, one formula (`nhfd.models.inputs`): the torch one
(`network_input_torch`, the device frame path) is the NumPy one (`network_input`, the CPU path
and the reference) bit for bit, at the full 1920 x 1080 panel and at the edges of its domain
(depth 0, negative, subnormal, huge, NaN, +-Inf; coverage at ALPHA_CONTENT and a float32 step
below it, NaN; depths mapped far past the volume, clipped), on the CPU and on CUDA when torch
sees a GPU."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nhfd.models.inputs import ALPHA_CONTENT, DEPTH_CLIP, network_input, network_input_torch

PANEL_HW = (1080, 1920)
# The donut build's mapping (a_m, b_m) and a volume of +-3 mm, off centre by 0.5 mm.
MAPPING = {"a_m": -0.016656, "b_m": 0.010565}
VOLUME_M = [-0.0025, 0.0035]
CUDA = pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                     reason="needs CUDA"))


def panel_render(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sRGB `[3, 1080, 1920]`, depth and alpha `[1080, 1920]` float32: depths spanning the
    volume and beyond it (clipped), with the first rows holding every edge case."""
    rng = np.random.default_rng(seed)
    rgb = rng.random((3, *PANEL_HW), dtype=np.float32)
    # z_h = a + b / d from -7.9 to +9.8 mm: the volume and beyond it at both ends.
    depth = rng.uniform(0.4, 1.2, PANEL_HW).astype(np.float32)
    alpha = rng.random(PANEL_HW, dtype=np.float32)
    f32 = np.float32
    edges = np.array([0.0, -0.0, -1.0, np.nan, np.inf, -np.inf, 1e-30, 1e30, 1e-45, 3e38,
                      np.finfo(np.float32).tiny, np.nextafter(f32(0), f32(1))], np.float32)
    depth[0, : len(edges)] = edges
    depth[1, : len(edges)] = edges
    alpha[1, : len(edges)] = 1.0
    alpha[2, :4] = [ALPHA_CONTENT, np.nextafter(f32(ALPHA_CONTENT), f32(0)), np.nan, -np.inf]
    return rgb, depth, alpha


def bits(x: np.ndarray) -> np.ndarray:
    """The float32 values' bit patterns (so -0.0 differs from 0.0 and NaN from anything)."""
    return np.ascontiguousarray(x, np.float32).view(np.uint32)


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_the_torch_input_is_the_numpy_one_bit_for_bit_on_the_full_panel(device):
    rgb, depth, alpha = panel_render(5)
    want = network_input(rgb, "rgbd", depth=depth, alpha=alpha, mapping=MAPPING,
                         volume_m=VOLUME_M)
    got = network_input_torch(torch.from_numpy(rgb).to(device), "rgbd",
                              depth=torch.from_numpy(depth).to(device),
                              alpha=torch.from_numpy(alpha).to(device), mapping=MAPPING,
                              volume_m=VOLUME_M)
    assert got.dtype == torch.float32 and got.device.type == device
    assert got.shape == want.shape == (4, *PANEL_HW)
    np.testing.assert_array_equal(bits(got.cpu().numpy()), bits(want))
    # The facts both share: finite, clipped, 0 off content, the coverage edge inclusive.
    ch = want[3]
    assert np.isfinite(want).all() and np.abs(ch).max() == DEPTH_CLIP
    assert (ch[0, :12][[0, 1, 2, 3, 4, 5]] == 0).all()  # not a positive finite depth
    assert ch[2, 0] != 0 and ch[2, 1] == 0 and ch[2, 2] == 0 and ch[2, 3] == 0
    assert (ch == DEPTH_CLIP).mean() > 0.01 and (ch == -DEPTH_CLIP).mean() > 0.01
    assert ((np.abs(ch) < DEPTH_CLIP) & (ch != 0)).mean() > 0.2


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_the_two_take_any_real_dtype_and_refuse_alike(device):
    rgb, depth, alpha = (x[..., :64, :96] for x in panel_render(6))
    # float64 and float16 inputs are taken to float32 first, by both (3e38 is Inf in float16).
    for dtype in (np.float64, np.float16):
        with np.errstate(over="ignore"):
            rgb_d, depth_d, alpha_d = rgb.astype(dtype), depth.astype(dtype), alpha.astype(dtype)
        want = network_input(rgb_d, "rgbd", depth=depth_d, alpha=alpha_d, mapping=MAPPING,
                             volume_m=VOLUME_M)
        got = network_input_torch(torch.from_numpy(rgb_d).to(device), "rgbd",
                                  depth=torch.from_numpy(depth_d).to(device),
                                  alpha=torch.from_numpy(alpha_d).to(device),
                                  mapping=MAPPING, volume_m=VOLUME_M)
        np.testing.assert_array_equal(bits(got.cpu().numpy()), bits(want))
    # "rgb": the colours alone, as float32.
    assert np.array_equal(bits(network_input_torch(torch.from_numpy(rgb), "rgb").numpy()),
                          bits(network_input(rgb, "rgb")))
    t = torch.from_numpy(rgb)
    for kw, message in [({}, "rgbd model needs the render's depth"),
                        ({"depth": torch.from_numpy(depth), "alpha": torch.from_numpy(alpha),
                          "mapping": MAPPING, "volume_m": VOLUME_M[::-1]},
                         r"volume_m = \[0.0035, -0.0025\]: the far end")]:
        with pytest.raises(ValueError, match=message):
            network_input_torch(t, "rgbd", **kw)
        np_kw = {k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in kw.items()}
        with pytest.raises(ValueError, match=message):
            network_input(rgb, "rgbd", **np_kw)
    with pytest.raises(ValueError, match=r"inputs = 'rgba'"):
        network_input_torch(t, "rgba")
