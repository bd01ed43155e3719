"""The CUDA path: gsplat's rasteriser behind the same `Render` result (optional extra `gpu`).

gsplat (checked against 1.5.3's source: rendering.py, cuda/_wrapper.py,
ProjectionEWA3DGSFused.cu, RasterizeToPixels3DGSFwd.cu, Utils.cuh, SphericalHarmonicsCUDA.cu)
implements the CPU renderer's semantics; each convention is converted here by one pure function
(numpy, no CUDA) that tests/scene/test_gsplat_conventions.py pins:

- pixel centres: both put pixel (i, j)'s centre at (j + 0.5, i + 0.5) (gsplat's
  `px = j + 0.5f`), so K takes cx, cy unshifted (`PIXEL_CENTRE_SHIFT_PX` = 0; `intrinsics_matrix`).
- pose: both world-to-camera, OpenCV axes (`view_matrix`: nhfd's `[R | t]` as a 4 x 4).
- near / far: both cull a centre whose camera z lies outside [near, far]; passed as they are.
- quaternions: both w x y z (gsplat normalises them itself; nhfd's are unit already).
- scales and opacities: `gsplat.rasterization` takes activated values, like `Gaussians`
  (exp and sigmoid are a trainer's business): no log, no logit (`gaussian_inputs`). Opacities
  are clamped to nhfd's alpha cap (`gsplat_opacities`, below).
- SH: both [N, K, 3] basis-major, K = (degree + 1)^2, the same real basis and signs; the
  permutation is the identity and `sh_degree` follows from K (`sh_to_gsplat`). Colour is
  `max(SH + 0.5, 0)` in both (gsplat's `clamp_min(colors + 0.5, 0)`), no upper clamp.
- depth: nhfd's is the expected depth `sum(w z) / alpha`, 0 where alpha = 0; gsplat's "ED"
  is `sum(w z) / max(alpha, 1e-10)`: the same, made explicit by `expected_depth`
  (`accumulated_to_expected` for its "D").
- eps2d and antialias: both add eps2d px^2 to the 2-D covariance's diagonal; "antialiased"
  scales opacity by `sqrt(det / det_dilated)` like nhfd's `antialias` (`rasterize_mode`).
- splat extent: both opacity-aware (gsplat: `min(3.33, sqrt(2 ln(255 op)))` sigma, rounded up
  to whole pixels), so both reach alpha = 1/255; per-pixel alpha below 1/255 is skipped in both,
  and a pixel stops before the splat that takes its transmittance to 1e-4 in both.

The alpha cap is the one convention no input converts exactly: nhfd draws
`min(0.99, op exp(-q))` (INRIA's cap), gsplat `min(0.999, op exp(-q))` (a constant in its
kernel). Passed as they are, a splat of opacity 1 leaves a transmittance of 0.001 behind its
core instead of 0.01, and with the shared stop rule (a pixel stops before the splat that would
take it below 1e-4) a whole opaque splat can drop out: alpha off by 0.07 on the donut (CPU
emulation). So the adapter passes `min(op, 0.99)`: gsplat's cap never binds, the core's alpha
and transmittance are nhfd's, and splats of opacity up to 0.99 render identically. Outside its
core a splat above 0.99 draws `0.99 / op` of nhfd's alpha, at most `0.99 (1 - 0.99 / op)` less
(0.0099 for op = 1; `opacity_clamp_error`), and its faintest edge (op e^-q within 1% above
1/255) is drawn by nhfd only. Emulated on the CPU (nhfd's compositor recompiled
with gsplat's cap, 512 x 288, docs/gpu.md) this leaves the shared scenes at RGB 82 / 94 / 65 dB
(donut, guitar, tiny-sh) and depth within 4e-4 / 2e-5 / 1.4e-3 relative where alpha > 0.5; with
opacities at most 0.99 everything agrees to float rounding.

It is used only when CUDA is available and gsplat imports; `raster.render(..., backend="auto")`
falls back to the CPU otherwise.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from nhfd.scene._kernels import ALPHA_MAX
from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import Gaussians

# gsplat's constants (RasterizeToPixels3DGSFwd.cu, Common.h) beside nhfd's (_kernels.py).
GSPLAT_ALPHA_MAX = 0.999
GSPLAT_ALPHA_MIN = 1.0 / 255.0
GSPLAT_T_MIN = 1e-4
# gsplat's pixel (i, j) is centred at (j + 0.5, i + 0.5) in its K's coordinates, as nhfd's
# (cameras.py): the principal point is passed unshifted.
PIXEL_CENTRE_SHIFT_PX = 0.0
# gsplat's "ED" divides the accumulated depth by alpha clamped to this.
GSPLAT_ED_ALPHA_FLOOR = 1e-10


def available() -> bool:
    """True when torch sees a CUDA device and gsplat imports."""
    try:
        import torch

        if not torch.cuda.is_available():
            return False
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def require(what: str = "backend 'gsplat'") -> None:
    """Raise RuntimeError naming what is missing unless CUDA and gsplat are both there."""
    if not available():
        raise RuntimeError(
            f"{what} needs a CUDA device and the gsplat package "
            "(pip install 'nhfd[gpu]'); use backend='cpu' or 'auto'"
        )


# ----------------------------------------------------------------- pure conversions (no CUDA)


def view_matrix(cam: Camera) -> np.ndarray:
    """gsplat's `viewmats` row: world-to-camera 4 x 4, float32 (nhfd's `[R | t]`, OpenCV axes)."""
    view = np.eye(4)
    view[:3, :3], view[:3, 3] = cam.R, cam.t
    return view.astype(np.float32)


def intrinsics_matrix(cam: Camera) -> np.ndarray:
    """gsplat's `Ks` row, float32: `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]` with the principal
    point moved by `PIXEL_CENTRE_SHIFT_PX` (0: both put pixel centres at j + 0.5)."""
    return np.array(
        [[cam.fx, 0.0, cam.cx + PIXEL_CENTRE_SHIFT_PX],
         [0.0, cam.fy, cam.cy + PIXEL_CENTRE_SHIFT_PX],
         [0.0, 0.0, 1.0]],
        np.float32,
    )  # fmt: skip


def sh_to_gsplat(sh: np.ndarray) -> tuple[np.ndarray, int]:
    """nhfd's `[N, K, 3]` SH (basis-major, `sh[:, 0]` the DC term) as gsplat's `colors`
    `[N, K, 3]` and its `sh_degree`: the same layout and basis, so the permutation is the
    identity (INRIA PLY's channel-major `f_rest` is reordered by nhfd's loader, not here)."""
    sh = np.asarray(sh, np.float32)
    k = sh.shape[1] if sh.ndim == 3 else -1
    degree = {1: 0, 4: 1, 9: 2, 16: 3}.get(k)
    if sh.ndim != 3 or sh.shape[2] != 3 or degree is None:
        raise ValueError(f"SH must be [N, K, 3] with K in (1, 4, 9, 16), got {sh.shape}")
    return np.ascontiguousarray(sh), degree


def gsplat_opacities(opacities: np.ndarray) -> np.ndarray:
    """Activated opacities for gsplat, clamped to nhfd's alpha cap (0.99) so that gsplat's
    higher cap (0.999) never binds: see the module docstring. float32."""
    return np.minimum(np.asarray(opacities, np.float32), np.float32(ALPHA_MAX))


def opacity_clamp_error(opacity: float) -> float:
    """The largest alpha difference between nhfd (`min(0.99, op e^-q)`) and gsplat given the
    clamped opacity (`0.99 e^-q`) over all q >= 0: 0 up to 0.99, else `0.99 (1 - 0.99 / op)`."""
    op = float(opacity)
    return 0.0 if op <= ALPHA_MAX else ALPHA_MAX * (1.0 - ALPHA_MAX / op)


def gaussian_inputs(g: Gaussians) -> dict[str, np.ndarray | int]:
    """gsplat.rasterization's per-Gaussian arguments from a `Gaussians`: `means`, `quats`
    (w x y z, as nhfd's), `scales` (activated standard deviations: no log), `opacities`
    (activated: no logit; clamped by `gsplat_opacities`), `colors` (SH, `sh_to_gsplat`) and
    `sh_degree`."""
    colors, degree = sh_to_gsplat(g.sh)
    return {
        "means": np.ascontiguousarray(g.means, np.float32),
        "quats": np.ascontiguousarray(g.quats, np.float32),
        "scales": np.ascontiguousarray(g.scales, np.float32),
        "opacities": np.ascontiguousarray(gsplat_opacities(g.opacities)),
        "colors": colors,
        "sh_degree": degree,
    }


def rasterize_mode(antialias: bool) -> str:
    """gsplat's `rasterize_mode` for nhfd's `RasterSettings.antialias`."""
    return "antialiased" if antialias else "classic"


def expected_depth(depth_channel, alpha):
    """nhfd's depth from gsplat's "ED" channel (`sum(w z) / max(alpha, 1e-10)`): the same
    expected depth where anything was drawn, exactly 0 where alpha is 0 (gsplat's 0 / 1e-10 is 0
    too; this makes it explicit). Works on numpy arrays and torch tensors."""
    if isinstance(depth_channel, np.ndarray):
        return np.where(alpha > 0, depth_channel, 0.0).astype(np.float32)
    return depth_channel.where(alpha > 0, depth_channel.new_zeros(()))


def accumulated_to_expected(accumulated, alpha):
    """gsplat's "D" (accumulated `sum(w z)`) to nhfd's expected depth: divided by alpha, 0 where
    alpha is 0 (what "ED" does inside gsplat)."""
    if isinstance(accumulated, np.ndarray):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(alpha > 0, accumulated / np.maximum(alpha, GSPLAT_ED_ALPHA_FLOOR),
                            0.0).astype(np.float32)  # fmt: skip
    return expected_depth(accumulated / alpha.clamp(min=GSPLAT_ED_ALPHA_FLOOR), alpha)


def check_same_size(cams: Sequence[Camera]) -> tuple[int, int]:
    """One batched gsplat call renders one image size: (W, H) of all `cams`, or ValueError."""
    if not cams:
        raise ValueError("no cameras to render")
    sizes = {(int(c.width_px), int(c.height_px)) for c in cams}
    if len(sizes) != 1:
        raise ValueError(f"a batch of views must share one size, got {sorted(sizes)}")
    planes = {(float(c.near), float(c.far)) for c in cams}
    if len(planes) != 1:
        raise ValueError(f"a batch of views must share near and far, got {sorted(planes)}")
    return next(iter(sizes))


# ----------------------------------------------------------------- CUDA rendering


@dataclass
class TorchViews:
    """Views rendered on the GPU: `rgb` [C, 3, H, W], `alpha` and `depth` [C, H, W], float32
    torch tensors on the render's device."""

    rgb: object
    alpha: object
    depth: object


class GsplatScene:
    """A scene's tensors on one CUDA device, uploaded once and rendered many times."""

    def __init__(self, g: Gaussians, device: str = "cuda") -> None:
        require()
        import torch

        self.device = torch.device(device)
        inputs = gaussian_inputs(g)
        self.sh_degree = int(inputs.pop("sh_degree"))
        self.tensors = {k: torch.from_numpy(v).to(self.device) for k, v in inputs.items()}
        self.n = len(g)

    def render(self, cams: Sequence[Camera], eps2d_px2: float = 0.3,
               antialias: bool = False) -> TorchViews:  # fmt: skip
        """Render every camera in one gsplat call (one size, one near/far)."""
        import gsplat
        import torch

        w, h = check_same_size(cams)
        c = len(cams)
        if self.n == 0:
            z = torch.zeros
            return TorchViews(z((c, 3, h, w), device=self.device),
                              z((c, h, w), device=self.device), z((c, h, w), device=self.device))
        viewmats = torch.from_numpy(np.stack([view_matrix(k) for k in cams])).to(self.device)
        ks = torch.from_numpy(np.stack([intrinsics_matrix(k) for k in cams])).to(self.device)
        t = self.tensors
        colors, alphas, _ = gsplat.rasterization(
            t["means"], t["quats"], t["scales"], t["opacities"], t["colors"], viewmats, ks,
            w, h, near_plane=float(cams[0].near), far_plane=float(cams[0].far),
            sh_degree=self.sh_degree, render_mode="RGB+ED", eps2d=float(eps2d_px2),
            rasterize_mode=rasterize_mode(antialias),
        )  # fmt: skip
        colors = colors.float()
        alpha = alphas[..., 0].float()
        rgb = colors[..., :3].permute(0, 3, 1, 2).contiguous()
        depth = expected_depth(colors[..., 3], alpha)
        return TorchViews(rgb, alpha, depth)


def render_gsplat(g: Gaussians, cam: Camera, eps2d_px2: float, antialias: bool,
                  device: str = "cuda"):
    """Render one view with gsplat on `device` (a scene rendered many times: `GsplatScene`);
    returns numpy rgb, alpha, depth."""
    require()
    views = GsplatScene(g, device).render([cam], eps2d_px2, antialias)
    return (views.rgb[0].cpu().numpy(), views.alpha[0].cpu().numpy(),
            views.depth[0].cpu().numpy())  # fmt: skip


def iter_views_gsplat(
    scene: GsplatScene,
    cams: Sequence[Camera],
    *,
    eps2d_px2: float = 0.3,
    antialias: bool = False,
    batch: int = 16,
) -> Iterator[tuple[int, TorchViews]]:
    """Yield `(first index, views)` for `cams` rendered `batch` at a time on the GPU."""
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    for start in range(0, len(cams), batch):
        yield start, scene.render(cams[start : start + batch], eps2d_px2, antialias)
