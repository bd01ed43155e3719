"""From a scene and a pose to the complex field on the reference plane, one colour at a time.

`ColourInverter` turns one colour's rendered views (sRGB channel, depth, alpha) into that colour's
field; `scene_hologram` renders the views with `nhfd.scene.lightfield.iter_views` (one view in
memory at a time) and returns the `[3, H, W]` complex64 field (R, G, B); `band_limit` filters it
by the Fourier aperture, as the targets and the focus test need.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from nhfd.holo.istft import InverseSTFT
from nhfd.holo.phase import PhaseMode, hologram_depth, view_phase, view_spectrum
from nhfd.holo.sampling import ColourSampling
from nhfd.optics import Aperture, apply_aperture
from nhfd.scene import gsplat_backend
from nhfd.scene.cameras import Camera
from nhfd.scene.gaussians import Gaussians
from nhfd.scene.lightfield import DepthMapping, LightField, iter_views, view_camera
from nhfd.scene.raster import RasterSettings

DEFAULT_RASTER = RasterSettings()


class ColourInverter:
    """One colour's inverse STFT fed view by view.

    Args:
        shape_hw: (H, W) of the views, pixels.
        sampling: the colour's `ColourSampling` (W, bins, slopes, wavelength).
        mapping: the scene's depth mapping (used by the depth-aware phase).
        colour: channel index (0 R, 1 G, 2 B) taken from each view's rgb, and part of the random
            phase's seed key.
        phase: "depth" (default), "zero" or "random"; seed: the random phase's base seed.
        skip: optional bool [Ky, Kx], True for views to leave out (e.g. outside a non-square
            aperture, see `sampling.inside_aperture`, inverted).
        device: where the field accumulates (default the CPU; a CUDA device for GPU builds).
    """

    def __init__(
        self,
        shape_hw: tuple[int, int],
        sampling: ColourSampling,
        mapping: DepthMapping,
        colour: int,
        *,
        phase: PhaseMode = "depth",
        seed: int = 0,
        skip: np.ndarray | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        self.sampling, self.mapping, self.colour = sampling, mapping, int(colour)
        self.phase, self.seed, self.skip = phase, int(seed), skip
        self.shape_hw = (int(shape_hw[0]), int(shape_hw[1]))
        self._istft = InverseSTFT(self.shape_hw, sampling.window, sampling.k, sampling.k,
                                  device=device)  # fmt: skip

    def add_view(
        self,
        iy: int,
        ix: int,
        rgb: np.ndarray | torch.Tensor,
        depth: np.ndarray | torch.Tensor,
        alpha: np.ndarray | torch.Tensor,
        z_h_m: torch.Tensor | None = None,
    ) -> None:
        """Add view (iy, ix): `rgb` [3, H, W] sRGB (or [H, W], this colour's channel), `depth` and
        `alpha` [H, W] (camera z in scene units, 0 where nothing was drawn). `z_h_m`: the view's
        hologram depth if the caller already has it (colours sharing a view share it)."""
        if self.skip is not None and self.skip[iy, ix]:
            return
        channel = rgb[self.colour] if rgb.ndim == 3 else rgb
        tau = self.sampling.tau
        z_h = None
        if self.phase == "depth":
            z_h = z_h_m if z_h_m is not None else hologram_depth(depth, self.mapping)
        phi = view_phase(
            self.phase, self.shape_hw, wavelength_m=self.sampling.wavelength_m,
            tau_x=float(tau[ix]), tau_y=float(tau[iy]), z_h_m=z_h, seed=self.seed,
            key=(self.colour, iy, ix),
        )  # fmt: skip
        if phi is not None and isinstance(channel, torch.Tensor):
            phi = phi.to(channel.device)  # the random phase is drawn on the CPU
        self._istft.add(iy, ix, view_spectrum(channel, phi))

    def result(self) -> torch.Tensor:
        """The colour's reference-plane field, [H, W] complex64."""
        return self._istft.result()


@dataclass
class Hologram:
    """`field` [C, H, W] complex64 on the reference plane (not yet band-limited), and where the
    time went: `render_s` (views), `invert_s` (inverse STFT), `n_views` rendered."""

    field: torch.Tensor
    render_s: float
    invert_s: float
    n_views: int


def _view_groups(sampling: Sequence[ColourSampling], shared_views: bool) -> list[list[int]]:
    """Colours that can use the same rendered views: identical slopes, or all with shared_views."""
    if shared_views:
        return [list(range(len(sampling)))]
    groups: list[list[int]] = []
    for c, s in enumerate(sampling):
        for grp in groups:
            if np.array_equal(sampling[grp[0]].tau, s.tau):
                grp.append(c)
                break
        else:
            groups.append([c])
    return groups


def _bin_index(ref: ColourSampling, own: ColourSampling) -> dict[int, int]:
    """Index of each of `ref`'s bins in `own`'s bins (bins `own` lacks are left out)."""
    pos = {int(k): i for i, k in enumerate(own.k)}
    return {i: pos[int(k)] for i, k in enumerate(ref.k) if int(k) in pos}


def scene_hologram(
    g: Gaussians,
    cam: Camera,
    mapping: DepthMapping,
    pitch_m: float,
    sampling: Sequence[ColourSampling],
    *,
    phase: PhaseMode = "depth",
    seed: int = 0,
    shared_views: bool = False,
    settings: RasterSettings = DEFAULT_RASTER,
    progress: Callable[[int, int], None] | None = None,
    device: str = "cpu",
    batch_views: int = 16,
) -> Hologram:
    """Render each colour's light field view by view and invert it: `[C, H, W]` complex64.

    Colours with identical slopes share renders. With `shared_views`, every colour uses the views
    rendered with the longest wavelength's slopes (with `colour_sampling(..., shared=True)` the
    others' own slopes differ from them by the rounding of W, a few percent; docs/physics.md,
    "Light field sampling (per wavelength)").

    `device` "cpu" renders with the CPU rasteriser and inverts on the CPU (the field is a CPU
    tensor); "cuda" or "cuda:N" renders with gsplat, `batch_views` views per call, and inverts on
    that GPU (the field stays there)."""
    shape = (int(cam.height_px), int(cam.width_px))
    on_gpu = str(device) != "cpu"
    if on_gpu:
        gsplat_backend.require("a CUDA hologram")
    inverters = [
        ColourInverter(shape, s, mapping, c, phase=phase, seed=seed,
                       device=device if on_gpu else None)
        for c, s in enumerate(sampling)
    ]  # fmt: skip
    groups = _view_groups(sampling, shared_views)
    total = sum(max(sampling[c].n_views for c in grp) for grp in groups)
    done, render_s, invert_s = 0, 0.0, 0.0
    for grp in groups:
        ref = max(grp, key=lambda c: sampling[c].wavelength_m)
        tau = sampling[ref].tau
        # With shared views a colour uses the reference's views whose bin k it has (the same k
        # gives nearly the same slope, since W is proportional to lambda).
        maps = [(c, _bin_index(sampling[ref], sampling[c])) for c in grp]
        views = iter(_gpu_views(g, cam, mapping, pitch_m, tau, settings, device, batch_views)
                     if on_gpu else iter_views(g, cam, mapping, pitch_m, tau, tau, settings))
        while True:
            t0 = time.perf_counter()
            item = next(views, None)
            t1 = time.perf_counter()
            if item is None:
                break
            iy, ix, view = item
            render_s += t1 - t0
            # One hologram depth per view, whichever colours use it (the mapping is the scene's).
            z_h = hologram_depth(view.depth, mapping) if phase == "depth" else None
            for c, index in maps:
                if iy in index and ix in index:
                    inverters[c].add_view(index[iy], index[ix], view.rgb, view.depth, view.alpha,
                                          z_h_m=z_h)
            invert_s += time.perf_counter() - t1
            done += 1
            if progress is not None:
                progress(done, total)
    t0 = time.perf_counter()
    field = torch.stack([inv.result() for inv in inverters])
    invert_s += time.perf_counter() - t0
    return Hologram(field, render_s, invert_s, total)


def _gpu_views(g: Gaussians, cam: Camera, mapping: DepthMapping, pitch_m: float,
               tau: np.ndarray, settings: RasterSettings, device: str, batch: int):  # fmt: skip
    """`iter_views`'s `(iy, ix, view)` rendered by gsplat, `batch` views per call: each view is
    `view_camera`'s moved camera (the CPU path shifts the prepared means instead: the same
    view). A view's rgb, depth and alpha are tensors on `device`."""
    scene = gsplat_backend.GsplatScene(g, device)
    index = [(iy, ix) for iy in range(len(tau)) for ix in range(len(tau))]
    cams = [view_camera(cam, mapping, pitch_m, float(tau[ix]), float(tau[iy]))[1]
            for iy, ix in index]  # fmt: skip
    for start, views in gsplat_backend.iter_views_gsplat(
        scene, cams, eps2d_px2=settings.eps2d_px2, antialias=settings.antialias, batch=batch
    ):
        for j in range(views.rgb.shape[0]):
            iy, ix = index[start + j]
            yield iy, ix, gsplat_backend.TorchViews(views.rgb[j], views.alpha[j], views.depth[j])


def hologram_from_light_field(
    lf: LightField,
    sampling: ColourSampling,
    mapping: DepthMapping,
    colour: int,
    *,
    phase: PhaseMode = "depth",
    seed: int = 0,
) -> torch.Tensor:
    """One colour's field [H, W] complex64 from an in-memory `LightField` rendered with
    `sampling`'s directions (`lf.rgb[..., colour, :, :]` is used)."""
    if not np.array_equal(lf.k_x, sampling.k) or not np.array_equal(lf.k_y, sampling.k):
        raise ValueError("the light field's bins differ from the sampling's")
    inv = ColourInverter(
        tuple(lf.depth.shape[-2:]), sampling, mapping, colour, phase=phase, seed=seed
    )
    for iy in range(lf.rgb.shape[0]):
        for ix in range(lf.rgb.shape[1]):
            inv.add_view(iy, ix, lf.rgb[iy, ix], lf.depth[iy, ix], lf.alpha[iy, ix])
    return inv.result()


def band_limit(
    field: torch.Tensor, aperture: Aperture, *, pad_px: int | None = None
) -> torch.Tensor:
    """Filter `[..., C, H, W]` by the Fourier aperture on a zero-padded grid, then crop back.

    The aperture is a convolution with a slowly decaying kernel; without padding, light near one
    edge would wrap to the other. `pad_px` per side defaults to half the larger image side."""
    h, w = field.shape[-2:]
    pad = max(h, w) // 2 if pad_px is None else int(pad_px)
    if pad < 0:
        raise ValueError(f"pad_px must be >= 0, got {pad_px}")
    padded = torch.nn.functional.pad(field, (pad, pad, pad, pad)) if pad else field
    out = apply_aperture(padded, aperture)
    return out[..., pad : pad + h, pad : pad + w] if pad else out
