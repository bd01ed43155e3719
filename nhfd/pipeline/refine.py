"""Frames better than the network's: the `exact`, `sgd` and `citl` tiers (docs/refine.md).

  exact   a view's hologram without a network: the light-field inversion the dataset build uses
          (`nhfd.holo.scene_hologram`), double-phase coded as a network frame is. Seconds on a
          CPU; also the target every refinement is fitted to.
  sgd     the SLM's phase optimised with Adam through the calibrated bench model
          (`BenchForward`): the phase curves and their grey levels (a straight-through
          estimator), each colour's focus, the illumination and the relay's pupil, fitted to the
          target's focal stack at the planes where the view's content lies, started from a
          double-phase frame.
  citl    the same loop with the bench's camera in it (Peng et al. 2020, camera-in-the-loop),
          started from `sgd`'s frame: each step's frame is shown and captured at those planes (a
          `Capture`; `nhfd.calib.citl.CameraLoop` over the devices), and the captured
          intensities replace the model's in the loss while the model's gradients steer.

Time multiplexing: K subframes are optimised jointly on their mean intensity (the eye, or one
camera exposure spanning K flips, sees the mean). `refine` stops on its budget (iterations,
seconds) or on convergence, is cancelled between steps (a new view), and stops on a non-finite
or diverging loss keeping the best frame so far: nothing worse than the start is ever returned.

Shapes: the frame's region (`Encoder.region`, the window plus the propagation's reach) is
`[C, Hr, Wr]`; the window `[C, h, w]`; K subframes lead, D planes follow them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
import torch

from nhfd.calibration import Calibration
from nhfd.config import Config, OpticsSettings, RefineSettings, SLMSettings
from nhfd.holo import (
    band_limit,
    colour_sampling,
    hologram_depth,
    scene_depth_range,
    scene_hologram,
)
from nhfd.model_info import DepthMapping as InfoMapping
from nhfd.model_info import ModelInfo
from nhfd.models.learned_bench import LearnedBench, LearnedOptics, learned_of
from nhfd.optics import (
    Aperture,
    colour_gains,
    focal_stack,
    grey_to_phase,
    phase_to_grey,
    propagate,
)
from nhfd.optics.pupil import apply_pupil, pupil_scales, pupil_transfer
from nhfd.scene.lightfield import DepthMapping
from nhfd.scene.raster import Render
from nhfd.views import QUALITY_TIERS, View

from .encoder import Encoder
from .frame import render_view
from .settings import FrameSettings, frame_settings
from .view import SCENE_FOV_X_DEG, Scene, render_camera

# Pixels along the window's edge left out of the loss: the window's edge diffracts, and the
# target (the window alone, propagated) and the bench (the whole region) differ there.
EDGE_PX = 6
# A content pixel: the render's alpha above this.
CONTENT_ALPHA = 0.5
# Planes closer than this (m) count as one.
PLANE_MERGE_M = 20e-6
# The loss this many times the starting loss: the optimisation is diverging.
DIVERGE_FACTOR = 4.0
# A step whose loss is this many times the best so far overshot: `refine` goes back to the best
# phase and halves the step (measured on the donut at 512 x 288: without it one such step at
# iteration 15 left the best at 29.4 dB, "converged").
BACKTRACK_FACTOR = 1.5
# The subframes after the first start from the first with a seeded phase jitter of this
# amplitude (rad): different starts decorrelate their speckle.
SUBFRAME_JITTER_RAD = 0.5 * math.pi


class Cancelled(Exception):
    """Refinement was cancelled (a new view): the caller keeps what it showed."""


class CaptureStopped(RuntimeError):
    """The bench cannot capture for `citl` (lasers disarmed, no camera, a device fault); the
    message says why and what to do."""


class Capture(Protocol):
    """The bench's camera as `citl` needs it: the K subframes `grey` `[K, C, Hr, Wr]` uint8
    (the frame's region) shown in turn during each exposure, captured at `planes_m` (metres
    from the reference plane) -> the intensities `[D, C, h, w]` on the window's SLM pixel grid
    (any units: a gain per colour is fitted) and the pixels the camera saw `[h, w]` bool.
    Raises `CaptureStopped` when it cannot."""

    def __call__(self, grey: np.ndarray, planes_m: Sequence[float]
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Show `grey`, capture at `planes_m`: (intensities `[D, C, h, w]`, seen `[h, w]`)."""
        ...


def _never() -> bool:
    return False


@dataclass(frozen=True)
class Target:
    """What a refined frame is fitted to: `intensity` `[D, C, h, w]` float32, the focal stack of
    the view's reference field through the aperture at `planes_m` (metres from the reference
    plane), compared inside `mask` `[h, w]` bool; `scale` is its 99.5th percentile there (the
    loss is in units of it, so -10 log10(loss) is the PSNR `nhfd.optics.stack_quality` gives)."""

    planes_m: tuple[float, ...]
    intensity: torch.Tensor
    mask: torch.Tensor
    scale: float

    def __post_init__(self) -> None:
        d = len(self.planes_m)
        if self.intensity.dim() != 4 or self.intensity.shape[0] != d:
            raise ValueError(f"target intensity {tuple(self.intensity.shape)}: expected "
                             f"[D, C, h, w] with D = {d} planes")
        if self.mask.shape != self.intensity.shape[-2:] or not bool(self.mask.any()):
            raise ValueError(f"target mask {tuple(self.mask.shape)}: expected a non-empty "
                             f"[h, w] = {list(self.intensity.shape[-2:])}")
        if not torch.isfinite(self.intensity).all() or not self.scale > 0:
            raise ValueError("target intensity: expected finite values with a positive peak")

    def to(self, device: torch.device | str) -> Target:
        """This target with its intensity and mask on `device`."""
        return Target(self.planes_m, self.intensity.to(device), self.mask.to(device), self.scale)


def window_mask(window_hw: tuple[int, int], edge_px: int = EDGE_PX) -> torch.Tensor:
    """The window's pixels `[h, w]` bool, less `edge_px` along each edge."""
    h, w = window_hw
    mask = torch.zeros((h, w), dtype=torch.bool)
    e = min(edge_px, (h - 1) // 2, (w - 1) // 2)
    mask[e : h - e, e : w - e] = True
    return mask


def target_from_field(reference: torch.Tensor, planes_m: Sequence[float], encoder: Encoder,
                      mask: torch.Tensor | None = None) -> Target:
    """The `Target` of a reference-plane field `[C, h, w]` (the window, in the dataset's
    units: an `exact_reference`, or a network's field) at `planes_m`."""
    s = encoder.settings
    if reference.dim() != 3 or tuple(reference.shape[-2:]) != tuple(s.window_hw):
        raise ValueError(f"reference field {tuple(reference.shape)}: expected [C, h, w] = "
                         f"[{len(s.wavelengths_m)}, {s.window_hw[0]}, {s.window_hw[1]}]")
    with torch.no_grad():
        stack = focal_stack(reference.detach().cpu().to(torch.complex64), list(planes_m),
                            s.pitch_m, s.wavelengths_m, s.aperture, padding=s.padding)
    mask = window_mask(s.window_hw) if mask is None else mask
    scale = torch.quantile(stack[..., mask].flatten().double()[:16_000_000], 0.995).item()
    return Target(tuple(float(z) for z in planes_m), stack.float(), mask, scale)


def content_planes(z_h_m: np.ndarray | torch.Tensor, alpha: np.ndarray | torch.Tensor, n: int,
                   volume_m: tuple[float, float]) -> tuple[float, ...]:
    """`n` planes where a view's content lies: quantiles (1/2n, 3/2n, ...) of its hologram
    depth `z_h_m` `[h, w]` (metres from the reference plane) over the pixels with alpha above
    CONTENT_ALPHA, clipped to the volume; planes closer than PLANE_MERGE_M merge. A view with
    no content gets the reference plane."""
    z = torch.as_tensor(z_h_m, dtype=torch.float64).flatten()
    a = torch.as_tensor(alpha, dtype=torch.float64).flatten()
    z = z[(a > CONTENT_ALPHA) & torch.isfinite(z)]
    if not z.numel():
        return (0.0,)
    q = torch.tensor([(2 * i + 1) / (2 * n) for i in range(n)], dtype=torch.float64)
    planes: list[float] = []
    for v in torch.quantile(z, q).tolist():
        v = min(max(v, volume_m[0]), volume_m[1])
        if not planes or v - planes[-1] > PLANE_MERGE_M:
            planes.append(round(v, 9))
    return tuple(planes)


def exact_reference(view: View, scene: Scene, info: ModelInfo, window_hw: tuple[int, int], *,
                    progress: Callable[[int, int], None] | None = None) -> torch.Tensor:
    """The view's reference-plane field `[C, h, w]` complex64 without a network: its light field
    rendered through the model's camera and inverted (`nhfd.holo.scene_hologram`, the depth-aware
    phase, colours sharing views, as the dataset build does), band-limited by the aperture; in
    the dataset's units, so the encoder codes it as it codes a network's field. `progress(done,
    total)` is called after each view (it may raise `Cancelled`)."""
    if info.mapping is None:
        raise ValueError("exact: the model records no depth mapping (mapping.a_m, b_m): "
                         "rebuild it with `nhfd model build`")
    aperture = Aperture(info.aperture_shape, tuple(info.cutoff_per_px))  # type: ignore[arg-type]
    sampling = colour_sampling(info.wavelengths_m, info.pitch_m, info.volume_m, aperture,
                               shared=True)
    mapping = DepthMapping(info.mapping.a_m, info.mapping.b_m)
    holo = scene_hologram(scene.gaussians, render_camera(view, scene.frame, info, window_hw),
                          mapping, info.pitch_m, sampling, phase="depth", shared_views=True,
                          progress=progress)
    return band_limit(holo.field, aperture).to(torch.complex64)


def configured_info(optics: OpticsSettings, slm: SLMSettings, window_hw: tuple[int, int], *,
                    fov_x_deg: float = SCENE_FOV_X_DEG) -> ModelInfo:
    """What the frame path needs of a model, from the configuration alone: the configured
    optics (`[optics]`, `[slm]`'s pitch), a `fov_x_deg` camera across the `window_hw` window, an
    amplitude scale of 1 and no depth mapping (`scene_info` adds a view's own)."""
    h, w = window_hw
    fx = 0.5 * w / math.tan(math.radians(fov_x_deg) / 2)
    return ModelInfo(inputs="rgb", wavelengths_m=tuple(v * 1e-9 for v in optics.wavelengths_nm),
                     pitch_m=slm.pitch_m, aperture_shape=optics.aperture.shape,  # type: ignore[arg-type]
                     cutoff_per_px=tuple(optics.aperture.cutoff_per_px), z0_m=optics.z0_mm * 1e-3,
                     volume_m=(optics.volume_mm[0] * 1e-3, optics.volume_mm[1] * 1e-3),
                     amplitude_scale=1.0, train_size_hw=(h, w), input_multiple=1, fx_px=fx,
                     fy_px=fx)


def amplitude_scale_of(reference: torch.Tensor, encoder: Encoder) -> float:
    """The amplitude scale a dataset of this one field would have: the 99.5th percentile of
    its SLM-plane amplitude over content pixels (above 1% of the peak), as `nhfd dataset
    build` pools it over its shards."""
    with torch.no_grad():
        amp = encoder.to_slm(reference).abs().flatten().double().cpu()
    peak = float(amp.max())
    if not peak > 0:
        raise ValueError("the view's field is dark: nothing of the scene is in view")
    return float(torch.quantile(amp[amp > 0.01 * peak][:16_000_000], 0.995))


def quantise(theta: torch.Tensor, encoder: Encoder) -> tuple[torch.Tensor, torch.Tensor]:
    """Phase `[..., C, H, W]` (rad) -> (the phase the panel shows for the nearest grey levels,
    which passes `theta`'s gradient straight through; those grey levels, uint8)."""
    s = encoder.settings
    with torch.no_grad():
        grey = phase_to_grey(theta.detach(), encoder.curves, sign=s.phase_sign,
                             invert=s.grey_invert)
        shown = grey_to_phase(grey, encoder.curves, sign=s.phase_sign, invert=s.grey_invert)
    return theta + (shown.to(theta.dtype) - theta).detach(), grey


def grey_phase(grey: np.ndarray | torch.Tensor, encoder: Encoder) -> torch.Tensor:
    """Grey levels `[..., C, H, W]` -> the phase the panel shows (rad, float32), on the
    encoder's device."""
    s = encoder.settings
    return grey_to_phase(torch.as_tensor(np.asarray(grey)).to(encoder.device), encoder.curves,
                         sign=s.phase_sign, invert=s.grey_invert)


class BenchForward:
    """The calibrated bench as refinement sees it: the SLM phase on the frame's region
    `[K, C, Hr, Wr]` (rad) -> the intensity `[K, D, C, h, w]` on the window at each of
    `planes_m`. Each colour: the illumination's amplitude (`Encoder.source_amplitude`), the
    relay's pupil (the calibration's Zernike terms), the aperture and the angular spectrum to
    z0 + refocus + the colour's focus offset + the plane's depth. What it leaves out (the
    pixels' fill factor, gaps and crosstalk, unmodulated light, the camera's colour and
    response) is what `citl`'s captures bring in. It runs on the encoder's device, as does
    `refine` with it.

    `learned`: a learned bench (`nhfd.models.learned_bench`, docs/learned_bench.md) applied
    around this model: its field leaving the panel replaces the unit-amplitude one, and its
    target-plane network follows each colour's intensity. None: the parametric model alone."""

    def __init__(self, encoder: Encoder, planes_m: Sequence[float],
                 learned: LearnedBench | None = None) -> None:
        s, r = encoder.settings, encoder.region
        self.encoder = encoder
        self.device = encoder.device
        self.planes_m = tuple(float(z) for z in planes_m)
        source = encoder.source_amplitude()  # [C, Hr, Wr] float64 or None
        self.source = None if source is None else source.float().to(self.device)
        # Each colour's pupil transfer, kept: the same every step.
        self._pupils: dict[int, torch.Tensor] = {}
        self.window = (slice(r.window_top, r.window_top + s.window_hw[0]),
                       slice(r.window_left, r.window_left + s.window_hw[1]))
        self.cutoffs = s.aperture.cutoffs(len(s.wavelengths_m))
        self.pupil_scales = pupil_scales(s.zernike_wavelength_m, s.wavelengths_m)
        # SLM -> each plane: the reverse of the encoder's propagation, plus the plane's depth.
        self.z_m = [[-zc + dz for dz in self.planes_m] for zc in s.colour_propagation_z_m]
        self.learned = None if learned is None else learned.to(self.device)
        self.box = (r.top, r.left, r.height, r.width)  # the region on the panel

    def __call__(self, phase: torch.Tensor, cancelled: Callable[[], bool] = _never
                 ) -> torch.Tensor:
        """The intensity `[K, D, C, h, w]` of the phase `[K, C, Hr, Wr]` (differentiable);
        `cancelled()` is polled before each colour and after its pupil (raising `Cancelled`),
        and between each colour's stages when the result's gradient is taken: a new view need
        not wait for a whole backward pass (2 of the 3 parts of a step)."""
        s = self.encoder.settings

        def poll(grad: torch.Tensor) -> torch.Tensor:
            if cancelled():
                raise Cancelled  # out of `backward()`: the step is dropped
            return grad

        hooks = phase.requires_grad and torch.is_grad_enabled() and cancelled is not _never
        out = []
        for c, lam in enumerate(s.wavelengths_m):
            if cancelled():
                raise Cancelled
            if self.learned is None:
                u = torch.polar(torch.ones_like(phase[:, c]), phase[:, c])  # [K, Hr, Wr]
            else:
                u = self.learned.slm_field(phase[:, c], c, self.box)
            if hooks:
                u.register_hook(poll)
            if self.source is not None:
                u = u * self.source[c]
            if s.zernike_rad:
                scale = self.pupil_scales[c]
                if c not in self._pupils:
                    self._pupils[c] = pupil_transfer(u.shape[-2:], self.cutoffs[c],
                                                     s.zernike_rad, scale, self.device)
                u = apply_pupil(u, self.cutoffs[c], s.zernike_rad, scale, self._pupils[c])
                if cancelled():  # the pupil's padded FFT pair costs as much as propagating
                    raise Cancelled
                if hooks:
                    u.register_hook(poll)
            v = propagate(u[:, None], self.z_m[c], s.pitch_m, [lam],
                          aperture=Aperture(s.aperture_shape, (self.cutoffs[c],)),  # type: ignore[arg-type]
                          padding=s.padding, cache=self.encoder.cache)  # [K, D, 1, Hr, Wr]
            intensity = v[..., 0, self.window[0], self.window[1]].abs().square()
            if self.learned is not None:
                intensity = self.learned.intensity(intensity, c)
            if hooks:
                intensity.register_hook(poll)
            out.append(intensity)
        return torch.stack(out, dim=2)


def stack_loss(seen: torch.Tensor, target: Target, mask: torch.Tensor | None = None
               ) -> torch.Tensor:
    """Mean squared error of intensities `seen` `[D, C, h, w]` against the target inside the
    mask, after the least-squares gain per colour (`nhfd.optics.colour_gains`: a camera's
    exposure and each laser's power are free), in units of the target's scale squared."""
    m = target.mask if mask is None else mask
    gains = colour_gains(seen.detach(), target.intensity, m).to(seen.dtype)
    diff = (seen * gains[:, None, None] - target.intensity) / target.scale
    return diff[..., m].square().mean()


def psnr_db(loss: float) -> float:
    """The PSNR (dB) a `stack_loss` stands for (120 dB at most)."""
    return min(120.0, -10 * math.log10(max(loss, 1e-12)))


@dataclass
class RefineReport:
    """Where a refinement stands: its tier, iterations and seconds so far, the best loss and
    the PSNR it stands for (the model's for `sgd`, the camera's for `citl`), the start's, and
    why it stopped ("" while it runs): "iterations", "seconds", "converged", "cancelled", or a
    sentence for a non-finite or diverging loss or a capture that stopped."""

    tier: str
    iterations: int = 0
    seconds: float = 0.0
    loss: float = math.inf
    psnr_db: float = 0.0
    start_psnr_db: float = 0.0
    stop: str = ""

    def to_json(self) -> dict[str, object]:
        """What `status` and `nhfd refine`'s report show."""
        return {"tier": self.tier, "iterations": self.iterations,
                "seconds": round(self.seconds, 3), "loss": self.loss,
                "psnr_db": round(self.psnr_db, 2), "start_psnr_db": round(self.start_psnr_db, 2),
                "stop": self.stop}


@dataclass
class Refined:
    """A refinement's best frame, `grey` `[K, C, Hr, Wr]` uint8 (K subframes of the region),
    its report, and the loss history `[(iteration, seconds, loss)]`."""

    grey: np.ndarray
    report: RefineReport
    history: list[tuple[int, float, float]] = field(default_factory=list)


def check_tier(tier: str) -> str:
    """`tier` if it is one of QUALITY_TIERS, else a ValueError naming them."""
    if tier not in QUALITY_TIERS:
        raise ValueError(f"quality = {tier!r}: must be one of {', '.join(QUALITY_TIERS)}")
    return tier


def refine(start: np.ndarray, target: Target, model: BenchForward, settings: RefineSettings,
           *, capture: Capture | None = None, cancelled: Callable[[], bool] = _never,
           on_better: Callable[[Refined], None] | None = None, seed: int = 0,
           clock: Callable[[], float] = time.monotonic,
           progress: Callable[[int, float, float], None] | None = None) -> Refined:
    """Optimise the SLM pattern from `start` (grey `[C, Hr, Wr]` or `[K, C, Hr, Wr]` uint8: a
    double-phase frame) for `target` through `model`, with the camera in the loop when
    `capture` is given (`citl`; else `sgd`), `settings.subframes` subframes.

    Stops at `settings.iterations` or `settings.seconds`, when the best loss fell by less than
    `settings.tolerance` of itself over `settings.patience` iterations, when `cancelled()`, on a
    non-finite loss or phase, on a loss DIVERGE_FACTOR times the start's, or when the capture
    stops (`CaptureStopped`). A step that overshoots (loss BACKTRACK_FACTOR times the best)
    goes back to the best phase with half the step. Returns the best frame seen (the start if
    nothing was better).
    `on_better(refined)` is called every `settings.swap_every` iterations when the best
    improved (progressive display). `progress(iteration, seconds, loss)` is called after each
    iteration's loss (the history's entry: iteration from 0, seconds since the start)."""
    tier = "citl" if capture is not None else "sgd"
    t0 = clock()
    grey0 = np.asarray(start, np.uint8)
    grey0 = grey0[None] if grey0.ndim == 3 else grey0
    k = settings.subframes
    device = model.encoder.device  # the model runs where its encoder does
    target = target.to(device)
    theta0 = grey_phase(grey0, model.encoder).float()
    if theta0.shape[0] < k:  # subframes after the first: the first with a seeded jitter
        g = torch.Generator().manual_seed(seed)  # on the CPU: the same jitter on every device
        extra = theta0[:1].repeat(k - theta0.shape[0], 1, 1, 1)
        jitter = 2 * torch.rand(extra.shape, generator=g) - 1
        extra = extra + SUBFRAME_JITTER_RAD * jitter.to(device)
        theta0 = torch.cat([theta0, extra])
    theta = theta0[:k].clone().requires_grad_(True)
    # The camera's loss is noisy: citl takes smaller steps (refine.citl_learning_rate_rad).
    lr = settings.citl_learning_rate_rad if capture is not None else settings.learning_rate_rad
    opt = torch.optim.Adam([theta], lr=lr)
    best_theta = theta.detach().clone()
    report = RefineReport(tier)
    best = Refined(grey0[:k].copy() if grey0.shape[0] >= k else
                   quantise(theta.detach(), model.encoder)[1].cpu().numpy(), report)
    start_loss = math.inf
    last_swap = 0
    it = 0
    while True:
        if cancelled():
            report.stop = "cancelled"
            break
        try:
            shown, grey = quantise(theta, model.encoder)
            seen = model(shown, cancelled).mean(dim=0)  # [D, C, h, w]: the eye's mean
            mask = target.mask
            if capture is not None:
                captured, valid = capture(grey.cpu().numpy(), target.planes_m)
                cap = torch.as_tensor(np.asarray(captured), dtype=seen.dtype, device=device)
                mask = target.mask & torch.as_tensor(np.asarray(valid, bool), device=device)
                if cap.shape != seen.shape or not bool(mask.any()):
                    raise CaptureStopped(f"the capture gave {tuple(cap.shape)} over "
                                         f"{int(mask.sum())} valid pixels: expected "
                                         f"{tuple(seen.shape)} over the window")
                cap = cap * colour_gains(cap, seen.detach(), mask).to(seen.dtype)[:, None, None]
                seen = seen + (cap - seen).detach()  # the camera's values, the model's gradient
            loss = stack_loss(seen, target, mask)
        except Cancelled:
            report.stop = "cancelled"
            break
        except CaptureStopped as exc:
            report.stop = f"capture stopped: {exc}"
            break
        value = float(loss.detach())
        now = clock() - t0
        if not math.isfinite(value) or not bool(torch.isfinite(theta).all()):
            report.stop = (f"non-finite loss at iteration {it}: kept the frame of loss "
                           f"{report.loss:.3g}")
            break
        if it == 0:
            start_loss = value
            report.start_psnr_db = psnr_db(value)
        best.history.append((it, now, value))
        if progress is not None:
            progress(it, now, value)
        if value < report.loss:
            report.loss, report.psnr_db = value, psnr_db(value)
            best.grey = grey.cpu().numpy()
            best_theta = theta.detach().clone()
        report.iterations, report.seconds = it + 1, now
        if value > DIVERGE_FACTOR * start_loss:
            report.stop = (f"diverged at iteration {it}: loss {value:.3g} against {start_loss:.3g} "
                           f"at the start (refine.learning_rate_rad too large?)")
            break
        if on_better is not None and it - last_swap >= settings.swap_every and \
                report.loss < start_loss:
            last_swap = it
            on_better(best)
        if it + 1 >= settings.iterations:
            report.stop = "iterations"
            break
        if now >= settings.seconds:
            report.stop = "seconds"
            break
        p = settings.patience
        if settings.tolerance > 0 and len(best.history) > p:
            before = min(h[2] for h in best.history[:-p])
            if before - report.loss < settings.tolerance * report.loss:
                report.stop = "converged"
                break
        if value > BACKTRACK_FACTOR * report.loss:
            # A step overshot (many pixels crossed grey levels at once, or Adam's moments went
            # stale): back to the best phase with half the step and fresh moments.
            lr *= 0.5
            with torch.no_grad():
                theta.copy_(best_theta)
            opt = torch.optim.Adam([theta], lr=lr)
        else:
            opt.zero_grad(set_to_none=True)
            try:
                loss.backward()
            except Cancelled:  # mid-step: the phase is as it was, the best frame kept
                report.stop = "cancelled"
                break
            opt.step()
        it += 1
    report.seconds = clock() - t0
    return best


@dataclass
class Prepared:
    """A view ready to refine, what every tier of it shares: the model's info (or, for a scene
    without a model, `configured_info` with the view's own depth mapping and amplitude scale),
    the encoder, the view's exact reference field `[C, h, w]`, the target at its content
    planes, the bench model at those planes, the exact frame `[C, Hr, Wr]` uint8 and its
    clipped fractions, the view's render (sRGB `[3, h, w]`, the preview; depth and alpha) and
    the seconds all that took."""

    view: View
    info: ModelInfo
    encoder: Encoder
    reference: torch.Tensor
    target: Target
    model: BenchForward
    exact_grey: np.ndarray
    clipped: tuple[float, ...]
    render: Render
    seconds: float
    # Why the calibration's learned bench is not in use although asked for (a refused weights
    # file: the parametric model refines), or "".
    bench_refusal: str = ""

    @property
    def rgb(self) -> np.ndarray:
        """The view's sRGB render `[3, h, w]` (the preview)."""
        return self.render.rgb


def prepare(config: Config, view: View, scene: Scene, *, info: ModelInfo | None = None,
            calibration: Calibration | None = None, window_hw: tuple[int, int] | None = None,
            panel_hw: tuple[int, int] | None = None, planes: int | None = None,
            device: torch.device | str = "cpu", cancelled: Callable[[], bool] = _never
            ) -> Prepared:
    """The one preparation of a view for refinement (`nhfd refine`, the frame worker, `nhfd
    bench quality`): the view rendered once (its content planes, and without a model its depth
    mapping and its preview), its light field inverted (`exact_reference`), the encoder, the
    target at `planes` (default `refine.planes`) content planes, the bench model there and the
    exact frame.

    `info`: the model's; None, a scene without one: `configured_info` on `window_hw` (then
    required) with the view's robust near and far depths mapped onto the volume
    (`nhfd.holo.scene_depth_range`) and the amplitude scale a dataset of this one field would
    have (`amplitude_scale_of`). `config`: the whole configuration (frame settings join [slm],
    [coding], [optics], [daemon]); `window_hw` and `panel_hw` replace its window and panel
    when given. `device`: where the encoder and the bench model run. `cancelled()` is polled
    between the stages and the light field's elemental views (`Cancelled`). The bench model is
    the calibration's learned bench when it has one and `refine.bench_model` is "learned"
    (a refused weights file: the parametric model, the reason in `bench_refusal`)."""
    t0 = time.perf_counter()

    def poll(_done: int = 0, _total: int = 0) -> None:
        if cancelled():
            raise Cancelled

    own = info is None
    if own:
        if window_hw is None:
            raise ValueError("a scene without a model needs the frame window (window_hw)")
        info = configured_info(config.optics, config.slm, window_hw)
    assert info is not None
    s = frame_settings(config, info, calibration, refocus_m=view.refocus_m)
    if window_hw is not None:
        s = replace(s, window_hw=tuple(window_hw))
    if panel_hw is not None:
        s = replace(s, panel_hw=tuple(panel_hw))
    (h, w), (ph, pw) = s.window_hw, s.panel_hw
    if h > ph or w > pw:
        raise ValueError(f"the window {w} x {h} does not fit the panel {pw} x {ph} "
                         "(slm.width_px x height_px)")
    r = render_view(view, scene, info, s.window_hw)  # the view, rendered once
    poll()
    if own:
        d = scene_depth_range([r.depth], [r.alpha])
        mapping = DepthMapping.from_range(d["d_near"], d["d_far"], *info.volume_m)
        info = replace(info, mapping=InfoMapping(mapping.a_m, mapping.b_m, d["d_near"],
                                                 d["d_far"]))
    reference = exact_reference(view, scene, info, s.window_hw, progress=poll)
    encoder = Encoder(s, device=device)
    if own:
        scale = amplitude_scale_of(reference, encoder)
        info = replace(info, amplitude_scale=scale)
        encoder = Encoder(replace(s, amplitude_scale=scale), device=device)
    n = config.refine.planes if planes is None else planes
    at = ((0.0,) if info.mapping is None else
          content_planes(hologram_depth(r.depth, info.mapping), r.alpha, n, info.volume_m))
    target = target_from_field(reference, at, encoder)
    with torch.no_grad():
        exact_grey, clipped = encoder.code(encoder.to_slm(reference))
    poll()
    learned, refusal = (learned_bench_for(calibration, s, device)
                        if config.refine.bench_model == "learned" else (None, None))
    return Prepared(view, info, encoder, reference, target,
                    BenchForward(encoder, at, learned), exact_grey, tuple(clipped), r,
                    time.perf_counter() - t0, refusal or "")


def learned_bench_for(calibration: Calibration | None, settings: FrameSettings,
                      device: torch.device | str = "cpu"
                      ) -> tuple[LearnedBench | None, str | None]:
    """The learned bench `calibration` references, checked for the optics of `settings` (its
    wavelengths, pitch and panel): `nhfd.models.learned_bench.learned_of`'s (model, refusal)."""
    optics = LearnedOptics(tuple(settings.wavelengths_m), settings.pitch_m,  # type: ignore[arg-type]
                           tuple(settings.panel_hw))  # type: ignore[arg-type]
    return learned_of(calibration, optics, device=device)


def model_loss(p: Prepared, grey: np.ndarray) -> float:
    """The bench model's loss of a frame `[C, Hr, Wr]` or `[K, C, Hr, Wr]` against the target."""
    g = np.asarray(grey)
    g = g[None] if g.ndim == 3 else g
    with torch.no_grad():
        seen = p.model(grey_phase(g, p.encoder)).mean(0)
        return float(stack_loss(seen, p.target.to(p.model.device)))


def exact_frame(p: Prepared) -> Refined:
    """The exact tier: the reference's double-phase frame, scored by the bench model."""
    loss = model_loss(p, p.exact_grey)
    report = RefineReport("exact", 0, p.seconds, loss, psnr_db(loss), psnr_db(loss), "exact")
    return Refined(p.exact_grey[None], report)


def sgd_frame(p: Prepared, settings: RefineSettings, *, start: np.ndarray | None = None,
              cancelled: Callable[[], bool] = _never,
              on_better: Callable[[Refined], None] | None = None, seed: int = 0,
              progress: Callable[[int, float, float], None] | None = None) -> Refined:
    """The sgd tier from `start` (the network's frame `[C, Hr, Wr]`) or the exact frame."""
    first = p.exact_grey if start is None else start
    return refine(first, p.target, p.model, settings, cancelled=cancelled, on_better=on_better,
                  seed=seed, progress=progress)


def citl_frame(p: Prepared, sgd: Refined, settings: RefineSettings, capture: Capture, *,
               cancelled: Callable[[], bool] = _never,
               on_better: Callable[[Refined], None] | None = None, seed: int = 0,
               progress: Callable[[int, float, float], None] | None = None) -> Refined:
    """The citl tier: the camera's loop from sgd's frame (each step D x C x K captures)."""
    return refine(sgd.grey, p.target, p.model, settings, capture=capture, cancelled=cancelled,
                  on_better=on_better, seed=seed, progress=progress)


def refine_view(p: Prepared, tier: str, settings: RefineSettings, *,
                start: np.ndarray | None = None, capture: Capture | None = None,
                cancelled: Callable[[], bool] = _never,
                on_better: Callable[[Refined], None] | None = None, seed: int = 0,
                progress: Callable[[int, float, float], None] | None = None) -> Refined:
    """A prepared view's frame at `tier` ("exact", "sgd" or "citl"; `check_tier`): "exact"
    codes the exact field, "sgd" refines from `start` (the network's frame, `[C, Hr, Wr]`
    uint8) or the exact frame, "citl" then goes on with the camera in the loop (`capture`).
    `cancelled()` is polled every step; `progress` is `refine`'s (sgd's steps, then citl's,
    each counting from 0)."""
    check_tier(tier)
    if tier == "network":
        raise ValueError("quality = 'network': the network's frame is `compute_frame`'s")
    if tier == "citl" and capture is None:
        raise ValueError("quality = 'citl' needs the bench's camera and a calibration "
                         "(devices.camera and calibration.file)")
    if tier == "exact":
        return exact_frame(p)
    sgd = sgd_frame(p, settings, start=start, cancelled=cancelled, on_better=on_better,
                    seed=seed, progress=progress)
    if tier == "sgd" or sgd.report.stop == "cancelled":
        return sgd
    assert capture is not None
    return citl_frame(p, sgd, settings, capture, cancelled=cancelled, on_better=on_better,
                      seed=seed, progress=progress)
