"""gsplat's renders predicted on the CPU: nhfd's own kernels with gsplat's one different constant.

gsplat and nhfd's CPU rasteriser share their semantics except the alpha cap (gsplat 0.999, nhfd
0.99; docs/gpu.md). This recompiles nhfd's numba kernels with gsplat's cap and feeds them the
adapter's inputs (`nhfd.scene.gsplat_backend.gaussian_inputs`, opacities clamped to 0.99), which
predicts gsplat's images up to float32 rounding and depth-sort ties (CUDA is not run):

    .venv/bin/python docs/gsplat_emulation.py scenes        # the shared scenes vs the CPU
    .venv/bin/python docs/gsplat_emulation.py scenes --raw  # opacities passed unclamped
    .venv/bin/python docs/gsplat_emulation.py tests         # the CUDA-only tests, emulated

`scenes` prints, per shared scene at 512 x 288 from its suggested camera, the RGB PSNR, the
largest relative depth error where alpha > 0.5 and the largest alpha difference.
"""

from __future__ import annotations

import argparse
import inspect
import math
import sys
import types
from pathlib import Path

import numpy as np
import torch

from nhfd.scene import _kernels, gsplat_backend, raster
from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import Gaussians

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO.parent / "shared" / "data" / "scenes"
NAMES = ("donut.ply", "guitar.compressed.ply", "tiny-sh.compressed.ply")


def gsplat_kernels() -> types.ModuleType:
    """nhfd's kernels compiled afresh with gsplat's alpha cap."""
    src = inspect.getsource(_kernels)
    if "ALPHA_MAX = 0.99\n" not in src:
        raise RuntimeError("nhfd's alpha cap is no longer 0.99: update this emulation")
    src = src.replace("ALPHA_MAX = 0.99\n", f"ALPHA_MAX = {gsplat_backend.GSPLAT_ALPHA_MAX}\n")
    mod = types.ModuleType("gsplat_emulated_kernels")
    exec(compile(src.replace("cache=True", "cache=False"), mod.__name__, "exec"), mod.__dict__)
    return mod


GK = gsplat_kernels()


def emulated(g: Gaussians, cam: Camera, eps2d_px2: float = 0.3, antialias: bool = False,
             clamp: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(rgb, alpha, depth) as gsplat would draw them from the adapter's inputs."""
    inputs = gsplat_backend.gaussian_inputs(g)
    op = inputs["opacities"] if clamp else g.opacities
    g2 = Gaussians(inputs["means"], inputs["quats"], inputs["scales"], op, inputs["colors"])
    prep = raster.prepare(g2, cam)
    w, h, tile = int(cam.width_px), int(cam.height_px), 16
    rgb = np.zeros((3, h, w), np.float32)
    alpha = np.zeros((h, w), np.float32)
    depth = np.zeros((h, w), np.float32)
    if prep.order.shape[0] == 0:
        return rgb, alpha, depth
    k = gsplat_backend.intrinsics_matrix(cam)
    rec, counts = GK.project_view(
        prep.pc, prep.cov, prep.opacities, prep.sh, prep.order, np.zeros(2), cam.R,
        float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), w, h, float(cam.near),
        float(cam.far), float(eps2d_px2), bool(antialias), tile,
    )  # fmt: skip
    offsets = np.zeros(counts.shape[0] + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    n_tiles = ((w + tile - 1) // tile) * ((h + tile - 1) // tile)
    tiles = GK.fill_tile_ids(rec, counts, offsets, tile, w, h)
    starts, gauss = GK.sort_by_tile(tiles, counts, offsets, n_tiles)
    GK.composite(rec, starts, gauss, tile, w, h, rgb, alpha, depth)
    return rgb, alpha, gsplat_backend.expected_depth(depth, alpha)


class EmulatedScene:
    """Stands in for `gsplat_backend.GsplatScene` (CPU tensors)."""

    def __init__(self, g: Gaussians, device: str = "cuda") -> None:
        self.g = g

    def render(self, cams, eps2d_px2: float = 0.3, antialias: bool = False):
        gsplat_backend.check_same_size(cams)
        out = [emulated(self.g, c, eps2d_px2, antialias) for c in cams]
        return gsplat_backend.TorchViews(
            *(torch.from_numpy(np.stack([o[i] for o in out])) for i in range(3))
        )


def scenes(clamp: bool) -> None:
    from nhfd.scene.io import load_scene
    from nhfd.scene.suggest import detect_up_axis, format_hint, suggest_camera

    for name in NAMES:
        path = SCENES / name
        g = load_scene(path)
        up, _ = detect_up_axis(g, format_hint(path))
        cam = suggest_camera(g, 512, 288, up)
        cpu = raster.render(g, cam)
        rgb, alpha, depth = emulated(g, cam, clamp=clamp)
        mse = float(np.mean((cpu.rgb.astype(np.float64) - rgb) ** 2))
        psnr = math.inf if mse == 0 else 10 * math.log10(1 / mse)
        sel = (cpu.alpha > 0.5) & (alpha > 0.5)
        rel = np.abs(cpu.depth[sel].astype(np.float64) - depth[sel]) / cpu.depth[sel]
        print(f"{name} ({len(g)} splats): RGB {psnr:.1f} dB, depth max rel {rel.max():.1e} "
              f"(p99 {np.quantile(rel, 0.99):.1e}), max |alpha diff| "
              f"{np.abs(cpu.alpha - alpha).max():.4f}", flush=True)  # fmt: skip


def tests() -> int:
    import pytest

    gsplat_backend.available = lambda: True
    gsplat_backend.render_gsplat = emulated
    gsplat_backend.GsplatScene = EmulatedScene
    return pytest.main(["-q", "-p", "no:cacheprovider", "-k", "cuda",
                        str(REPO / "tests" / "scene" / "test_gsplat_conventions.py")])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=("scenes", "tests"))
    p.add_argument("--raw", action="store_true", help="pass opacities unclamped (scenes)")
    args = p.parse_args()
    if args.what == "tests":
        return tests()
    scenes(clamp=not args.raw)
    return 0


if __name__ == "__main__":
    sys.exit(main())
