"""The CUDA path: gsplat's rasteriser behind the same `Render` result (optional extra `gpu`).

gsplat implements the same semantics as the CPU renderer (EWA with the tan-FOV clamp, eps2d
dilation, classic or antialiased mode, alpha threshold 1/255, cap 0.99, transmittance 1e-4,
expected depth), so results agree up to float rounding. It is used only when CUDA is available
and gsplat imports; `raster.render(..., backend="auto")` falls back to the CPU otherwise.
"""

from __future__ import annotations

import numpy as np

from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import Gaussians


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


def render_gsplat(g: Gaussians, cam: Camera, eps2d_px2: float, antialias: bool):
    """Render one view with gsplat on the first CUDA device; returns numpy rgb, alpha, depth."""
    if not available():
        raise RuntimeError(
            "backend 'gsplat' needs a CUDA device and the gsplat package "
            "(pip install 'nhfd[gpu]'); use backend='cpu' or 'auto'"
        )
    import gsplat
    import torch

    dev = torch.device("cuda")

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(dev)

    view = np.eye(4)
    view[:3, :3], view[:3, 3] = cam.R, cam.t
    k = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    colors, alphas, _ = gsplat.rasterization(
        t(g.means), t(g.quats), t(g.scales), t(g.opacities), t(g.sh),
        t(view[None].astype(np.float32)), t(k[None].astype(np.float32)),
        int(cam.width_px), int(cam.height_px),
        near_plane=float(cam.near), far_plane=float(cam.far), sh_degree=g.sh_degree,
        render_mode="RGB+ED", eps2d=float(eps2d_px2),
        rasterize_mode="antialiased" if antialias else "classic",
    )  # fmt: skip
    out = colors[0].permute(2, 0, 1).float().cpu().numpy()
    alpha = alphas[0, :, :, 0].float().cpu().numpy()
    return out[:3].copy(), alpha, np.where(alpha > 0, out[3], 0.0).astype(np.float32)
