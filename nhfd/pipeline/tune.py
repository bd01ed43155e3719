"""A scene's model tuned through one bench's model: `nhfd model tune` (docs/tune.md).

The network's frame is open loop: trained against the exact field, it never sees the double-phase
coding, the panel's grey levels or the calibrated bench. Tuning trains the exported network
further (HoloNet's way, Peng et al. 2020: through the camera-calibrated propagation model, that
model frozen) on the same objective `sgd` refines a frame with: the focal stack the calibrated
bench model (`BenchForward`) sees of the frame, against the view's exact target at its content
planes (`stack_loss`), plus a structural term (`box_ssim`).

What carries the gradient from the network's output to the loss, `DifferentiableCoding`, is the
frame path written differentiably:

    network amplitude, phase  -> the reference-plane field (x the model's amplitude scale)
    propagation by -z0        the encoder's own kernels (its region, its aperture, per colour
                              depth and the relay's pre-compensated pupil), as plain FFTs
    double-phase coding       the coder's formula (`nhfd.optics.dpac`) with the gain map
    grey levels               the frame path's own coder (`Encoder.code`) decides them; the
                              panel's phase for them passes the coded phase's gradient straight
                              through (as `refine.quantise` does)
    BenchForward              frozen

The frame path itself is unchanged: a tuned model is an ordinary model file (the same graph and
metadata, new weights, and a `tuned_for` record).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.fft as fft

from nhfd.calibration import Calibration, bench_record, check_bench, fingerprint
from nhfd.config import Config
from nhfd.dataset.build import sha256_file
from nhfd.model_info import SUBFRAMES_RANGE, ModelInfo, recorded_scenes
from nhfd.models.inputs import network_input
from nhfd.models.loss import box_ssim
from nhfd.models.metadata import METADATA_KEY, expected_from_config, parse_metadata
from nhfd.models.sizes import check_and_record
from nhfd.models.torch_model import FOLDED, TorchModel
from nhfd.optics import colour_gains
from nhfd.optics.dpac import AMPLITUDE_CEILING, checkerboard, empty_below, wrap_phase
from nhfd.scene.cameras import look_at
from nhfd.views import Orbit, Pose, View

from .encoder import Encoder, reference_field
from .frame import subframe_fields
from .refine import Prepared, grey_phase, prepare, psnr_db, stack_loss
from .view import Scene

# The ranges `TuneSettings` allows (the CLI's options name them).
STEPS_RANGE = (1, 1_000_000)
VIEWS_RANGE = (1, 1024)
SECONDS_RANGE = (1.0, 30 * 86400.0)
LEARNING_RATE_RANGE = (1e-7, 1e-2)
SSIM_WEIGHT_RANGE = (0.0, 1.0)
PLANES_RANGE = (1, 8)
CHECKPOINT_EVERY_RANGE = (1, 100_000)
WINDOW_RANGE_PX = (16, 4096)
# A one-frame model widened to K subframes starts with K copies of its head, the phase weights of
# subframes 2..K moved by this much of their rms (seeded): identical heads would get identical
# gradients and stay one frame shown K times. Measured at 64 x 48 (K = 4, 6 views, 120 steps,
# 2 held-out views through the bench model): 0.05 -> 22.96 dB, 0.3 -> 24.07, 1.0 -> 23.85 (its
# start 16.4 dB), against 22.43 for K = 1.
SUBFRAME_JITTER = 0.3
SUBFRAME_JITTER_RANGE = (0.0, 2.0)
# The gradient's norm is clipped to this: one view's step never throws the network far.
GRAD_CLIP = 1.0
CHECKPOINT = "checkpoint.pt"
TUNED = "model.onnx"
REPORT = "tune.json"


class TuneError(ValueError):
    """Tuning refused (bad input: nothing written) or stopped (a non-finite loss: the last good
    checkpoint kept); the message names the setting or the checkpoint."""


def _range(name: str, value: float, lo: float, hi: float, unit: str = "") -> None:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and \
        math.isfinite(value) and lo <= value <= hi
    if not ok:
        shown = [str(v) if isinstance(v, int) else f"{v:g}" for v in (lo, hi)]
        raise TuneError(f"{name} = {value!r}: must be in {shown[0]}..{shown[1]}{unit}")


@dataclass(frozen=True)
class TuneSettings:
    """How a model is tuned: `steps` (one training view each) and at most `seconds` in all
    (resumes included), `views` training views, the `window_hw` (h, w px) frame window, Adam's
    `learning_rate`, the structural term's weight `ssim_weight` (the loss is `stack_loss` +
    ssim_weight x (1 - SSIM)), `planes` content planes per view (as `refine.planes`), a
    checkpoint every `checkpoint_every` steps, the `seed` of the views' order (and of the
    subframe heads' jitter), `device`, and `subframes` K: the frames one inference emits, tuned
    jointly on their mean intensity (a one-frame model is widened to K heads, the copies'
    phase weights moved apart by `subframe_jitter` of their rms).
    ValueError (`TuneError`) naming the setting and its range."""

    steps: int = 200
    seconds: float = 3600.0
    views: int = 8
    window_hw: tuple[int, int] = (144, 256)
    learning_rate: float = 1e-4
    ssim_weight: float = 0.02
    planes: int = 3
    checkpoint_every: int = 20
    seed: int = 0
    device: str = "cpu"
    subframes: int = 1
    subframe_jitter: float = SUBFRAME_JITTER

    def __post_init__(self) -> None:
        _range("steps (--steps)", self.steps, *STEPS_RANGE)
        if not isinstance(self.steps, int):
            raise TuneError(f"steps (--steps) = {self.steps!r}: must be a whole number")
        _range("seconds (--seconds)", self.seconds, *SECONDS_RANGE, " s")
        _range("views (--views)", self.views, *VIEWS_RANGE)
        if len(self.window_hw) != 2:
            raise TuneError(f"size (--size) = {self.window_hw!r}: expected W x H")
        for n, v in zip(("height", "width"), self.window_hw, strict=True):
            _range(f"size (--size) {n}", v, *WINDOW_RANGE_PX, " px")
        _range("learning_rate", self.learning_rate, *LEARNING_RATE_RANGE)
        _range("ssim_weight (--ssim-weight)", self.ssim_weight, *SSIM_WEIGHT_RANGE)
        _range("planes", self.planes, *PLANES_RANGE)
        _range("checkpoint_every", self.checkpoint_every, *CHECKPOINT_EVERY_RANGE)
        _range("subframes (--subframes)", self.subframes, *SUBFRAMES_RANGE)
        if not isinstance(self.subframes, int):
            raise TuneError(f"subframes (--subframes) = {self.subframes!r}: must be a whole "
                            "number")
        _range("subframe_jitter (--subframe-jitter)", self.subframe_jitter,
               *SUBFRAME_JITTER_RANGE)
        if self.device != "cpu" and not str(self.device).startswith("cuda"):
            raise TuneError(f"device (--device) = {self.device!r}: must be cpu or cuda[:N]")

    def key(self) -> dict[str, Any]:
        """What a checkpoint must have been made with to be resumed (not the budget)."""
        d = dataclasses.asdict(self)
        for k in ("steps", "seconds", "checkpoint_every", "device"):
            d.pop(k)
        if self.subframes == 1:  # no heads to move apart
            d.pop("subframe_jitter")
        d["window_hw"] = list(self.window_hw)
        return d


# -- the differentiable frame path ---------------------------------------------------------------

class DifferentiableCoding:
    """The frame path from the reference-plane field to the SLM phase, differentiable: the
    encoder's propagation (its kernels, as plain FFTs on its padded grids), double-phase coding
    with its gain map and amplitude scale, and its coder's grey levels, whose panel phase passes
    the coded phase's gradient straight through. On the encoder's device."""

    def __init__(self, encoder: Encoder) -> None:
        self.encoder = encoder
        s, r = encoder.settings, encoder.region
        self.groups = []
        for g in encoder.groups():
            n = g.colours.stop - g.colours.start
            hp, wp = g.padded_hw
            kernel = torch.zeros((n, hp, wp), dtype=torch.complex64, device=encoder.device)
            cols = torch.tensor([i for a, b in g.col_runs for i in range(a, b)],
                                dtype=torch.long, device=encoder.device)
            for (a, b), k in zip(g.row_runs, g.kernels, strict=True):
                block = torch.zeros((n, b - a, wp), dtype=torch.complex64, device=encoder.device)
                block[..., cols] = k.transpose(-1, -2)
                kernel[:, a:b] = block
            self.groups.append((g.colours, kernel, g.offset))
        self.region_hw = (r.height, r.width)
        gain = encoder.amplitude_gain_map()
        self.gain = None if gain is None else gain.to(encoder.device)
        self.scale = float(s.amplitude_scale)
        self.empty = empty_below(s.zero_below)
        self.parity = checkerboard(self.region_hw, encoder.device)

    def to_slm(self, reference: torch.Tensor) -> torch.Tensor:
        """Window field `[C, h, w]` -> SLM-plane region field `[C, Hr, Wr]` (`Encoder.to_slm`'s
        field, to float32 rounding), differentiable."""
        hr, wr = self.region_hw
        h, w = reference.shape[-2:]
        out = []
        for colours, kernel, (r0, c0) in self.groups:
            n, hp, wp = kernel.shape
            padded = torch.zeros((n, hp, wp), dtype=torch.complex64, device=kernel.device)
            padded[:, r0 : r0 + h, c0 : c0 + w] = reference[colours].to(torch.complex64)
            out.append(fft.ifft2(fft.fft2(padded) * kernel)[:, :hr, :wr])
        return torch.cat(out, dim=0)

    def coded_phase(self, slm: torch.Tensor) -> torch.Tensor:
        """The double-phase code `[C, Hr, Wr]` (rad, before the curves) of an SLM-plane field,
        `nhfd.optics.dpac`'s formula with the gain map, differentiable (empty pixels carry no
        gradient)."""
        u = slm if self.gain is None else slm * self.gain
        amp = (u.abs() / self.scale).clamp(0.0, AMPLITUDE_CEILING)
        mean = torch.angle(u.sum(dim=(-2, -1), keepdim=True))
        empty = (amp < self.empty).detach()
        amp = torch.where(empty, torch.zeros_like(amp), amp)
        safe = torch.where(empty, torch.ones_like(u), u)  # no angle of 0 in the graph
        phi = torch.where(empty, torch.zeros_like(amp), torch.angle(safe) - mean)
        return wrap_phase(phi + torch.acos(amp) * self.parity)

    def __call__(self, reference: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
        """(the phase the panel shows `[C, Hr, Wr]`, its value the grey levels' and its gradient
        the coded phase's; the grey levels `[C, Hr, Wr]` uint8). The field coded is the frame
        path's (`Encoder.to_slm`, whose gradient is `to_slm`'s here: the same linear map to
        float32 rounding) and its grey levels the frame coder's (`Encoder.code`), so they are
        the frame's own."""
        slm = self.to_slm(reference)
        with torch.no_grad():  # the frame path's own field: its grey levels, bit for bit
            exact = self.encoder.to_slm(reference)
        slm = slm + (exact - slm).detach()
        theta = self.coded_phase(slm)
        grey, _ = self.encoder.code(slm.detach())
        shown = grey_phase(grey, self.encoder)
        return theta + (shown - theta).detach(), grey


# -- the loss ----------------------------------------------------------------------------------

def tune_loss(seen: torch.Tensor, p: Prepared, ssim_weight: float, window_px: int
              ) -> tuple[torch.Tensor, float, float]:
    """The tuning loss of the intensities `seen` `[D, C, h, w]` the bench model gives for a
    view's frame: `stack_loss` (sgd's objective) + ssim_weight x (1 - SSIM), the SSIM over each
    plane and colour inside the loss's window, after the same gain per colour, in units of the
    target's scale. Returns (loss, the MSE, the SSIM)."""
    target = p.target.to(seen.device)
    mse = stack_loss(seen, target)
    m = target.mask
    rows, cols = torch.nonzero(m.any(1)).flatten(), torch.nonzero(m.any(0)).flatten()
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    gains = colour_gains(seen.detach(), target.intensity, m).to(seen.dtype)
    x = (seen * gains[:, None, None] / target.scale)[..., r0:r1, c0:c1].flatten(0, 1)
    y = (target.intensity / target.scale)[..., r0:r1, c0:c1].flatten(0, 1)
    window = min(window_px, r1 - r0, c1 - c0)
    ssim = box_ssim(x, y, window)
    return mse + ssim_weight * (1 - ssim), float(mse.detach()), float(ssim.detach())


# -- the views -----------------------------------------------------------------------------------

def _quaternion_wxyz(m: np.ndarray) -> tuple[float, float, float, float]:
    """The unit quaternion (w, x, y, z) of a rotation matrix (w >= 0)."""
    m = np.asarray(m, np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2 * math.sqrt(1 + t)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (m[j, i] + m[i, j]) / s
        v[k] = (m[k, i] + m[i, k]) / s
        q = ((m[k, j] - m[j, k]) / s, *v)
    qa = np.asarray(q) / np.linalg.norm(q)
    qa = -qa if qa[0] < 0 else qa
    return tuple(float(v) for v in qa)  # type: ignore[return-value]


def pose_view(r_wc: np.ndarray, t_wc: np.ndarray) -> View:
    """The `View` of a world-to-camera pose `(R, t)` (OpenCV axes)."""
    r = np.asarray(r_wc, np.float64)
    position = -r.T @ np.asarray(t_wc, np.float64)
    return View(Pose(tuple(float(v) for v in position), _quaternion_wxyz(r.T)))


def training_poses_of(metadata: dict[str, Any], scene: Scene, dataset: Path | None
                      ) -> list[View]:
    """The dataset's training poses as views: the training split of `dataset`/manifest.json
    (which must be the model's dataset), else the model's recorded `train_poses` (positions,
    looking at the recorded centre, the scene's up). Never the held-out splits."""
    if dataset is not None:
        path = Path(dataset) / "manifest.json"
        if not path.is_file():
            raise TuneError(f"--dataset {dataset}: no manifest.json there")
        want = metadata.get("dataset_manifest_sha256")
        if want and sha256_file(path) != want:
            raise TuneError(f"--dataset {dataset}: its manifest is not the one the model was "
                            f"trained on (dataset_manifest_sha256 {want[:12]}...)")
        manifest = json.loads(path.read_text())
        poses = manifest.get("poses") or []
        train = (manifest.get("splits") or {}).get("train") or []
        if not train:
            raise TuneError(f"--dataset {dataset}: its manifest has no training split")
        return [pose_view(poses[i]["R"], poses[i]["t"]) for i in train]
    recorded = metadata.get("train_poses")
    if not recorded or not recorded.get("positions"):
        raise TuneError("the model records no training poses (train_poses): give its dataset "
                        "with --dataset DIR (nhfd dataset build)")
    centre = np.asarray(recorded["center"], np.float64)
    return [pose_view(*look_at(np.asarray(p, np.float64), centre, scene.frame.up))
            for p in recorded["positions"]]


# Stand-in training poses for a model that records none and whose dataset is not given (the
# shipped donut's): grids of fractions of its pose envelope's azimuth, elevation and distance,
# the smallest that has the views asked for. The distance is in them because 6 poses at the mid
# distance alone over-fitted them: at 512 x 288 a nearer seeded view lost 1.0 dB captured to the
# tuning (`nhfd bench quality`, whose scored views are drawn at random inside the envelope:
# never one of these). 24 of the 27 tuned through the learned bench gained 1.0 dB captured over
# 8 of the 12 (docs/tune.md).
ENVELOPE_GRIDS = (
    tuple((f, g, h) for f in (0.2, 0.5, 0.8) for g in (0.3, 0.7) for h in (0.25, 0.75)),
    tuple((f, g, h) for f in (0.15, 0.5, 0.85) for g in (0.15, 0.5, 0.85)
          for h in (0.15, 0.5, 0.85)),
)


def tuning_poses(metadata: dict[str, Any], scene: Scene, info: ModelInfo,
                 dataset: Path | None, dataset_flag: str = "--dataset", views: int = 1
                 ) -> tuple[list[View], str]:
    """The poses tuning chooses `views` views from, and where they come from: the training split
    of `dataset` (the model's), else the model's recorded training poses, else, for a model that
    records none, the smallest of `ENVELOPE_GRIDS` over its pose envelope with at least
    `views` poses. TuneError naming `dataset_flag` when the model has neither poses nor an
    envelope, or asks for more views than the largest grid has."""
    if dataset is not None or (metadata.get("train_poses") or {}).get("positions"):
        poses = training_poses_of(metadata, scene, dataset)
        return poses, (f"the training split of {dataset_flag}" if dataset is not None
                       else "the model's recorded training poses")
    env = info.pose_envelope
    if env is None or not (env.azimuth_deg and env.elevation_deg and env.distance):
        raise TuneError(f"the model records no training poses (train_poses) and no pose "
                        f"envelope: give its dataset with {dataset_flag} DIR (nhfd dataset "
                        "build)")
    grid = next((g for g in ENVELOPE_GRIDS if len(g) >= views), None)
    if grid is None:
        raise TuneError(f"views = {views}: a model that records no training poses tunes on at "
                        f"most {len(ENVELOPE_GRIDS[-1])} poses of a grid over its pose "
                        f"envelope; give its dataset with {dataset_flag} DIR for more")
    (a0, a1), (e0, e1), (d0, d1) = env.azimuth_deg, env.elevation_deg, env.distance
    return ([View(Orbit(a0 + (a1 - a0) * f, e0 + (e1 - e0) * g, d0 + (d1 - d0) * h))
             for f, g, h in grid],
            "a grid over the model's pose envelope (the model records no training poses)")


def choose_views(poses: Sequence[View], n: int) -> list[View]:
    """`n` of the training poses, evenly spread over their order (refused when there are
    fewer)."""
    if n > len(poses):
        raise TuneError(f"views (--views) = {n}: must be in 1..{len(poses)} (the training "
                        "poses of the model's dataset)")
    idx = sorted({round(float(v)) for v in np.linspace(0, len(poses) - 1, n)})
    return [poses[i] for i in idx]


@dataclass
class TuneView:
    """A training view ready to tune on: the network's input `[1, C, H, W]` (padded to the
    network's multiple), the window (h, w), the prepared view (target, bench model, encoder)
    and the differentiable coding over its encoder; the SSIM's box window (px: training's
    structural term's, `[model.train] ssim_window_px`)."""

    view: View
    x: torch.Tensor
    hw: tuple[int, int]
    prepared: Prepared
    coding: DifferentiableCoding
    ssim_window_px: int


def prepare_views(views: Sequence[View], scene: Scene, model: TorchModel, config: Config,
                  calibration: Calibration, settings: TuneSettings,
                  panel_hw: tuple[int, int] | None = None,
                  say: Callable[[str], None] = print) -> list[TuneView]:
    """Each view prepared as `refine` prepares one (`prepare`: its exact target at its content
    planes, the calibrated encoder and bench model), with the network's input. `TuneError`
    when the calibration's learned bench is refused (before anything is written)."""
    out = []
    m = model.multiple
    for i, view in enumerate(views):
        t0 = time.perf_counter()
        p = prepare(config, view, scene, info=model.info, calibration=calibration,
                    window_hw=settings.window_hw, panel_hw=panel_hw, planes=settings.planes,
                    device=settings.device)
        if p.bench_refusal:  # tuned through the parametric model, recorded as the learned one
            raise TuneError(f"--calibration: its learned bench is refused ({p.bench_refusal}): "
                            "re-learn it (nhfd calib learn), or set refine.bench_model = "
                            '"parametric" to tune through the parametric model')
        r = p.render  # the view as prepare rendered it, not rendered again
        x = network_input(r.rgb, model.inputs, depth=r.depth, alpha=r.alpha,
                          mapping=model.info.mapping_dict, volume_m=model.info.volume_m)
        t = torch.from_numpy(np.ascontiguousarray(x))[None].to(settings.device)
        h, w = t.shape[-2:]
        t = torch.nn.functional.pad(t, (0, (-w) % m, 0, (-h) % m))
        out.append(TuneView(view, t, (h, w), p, DifferentiableCoding(p.encoder),
                            config.model.train.ssim_window_px))
        say(f"view {i + 1}/{len(views)} prepared ({len(p.target.planes_m)} planes) in "
            f"{time.perf_counter() - t0:.1f} s")
    return out


def view_loss(net: torch.nn.Module, v: TuneView, amplitude_scale: float, ssim_weight: float
              ) -> tuple[torch.Tensor, float, float]:
    """One view's tuning loss through the network, the differentiable coding and the bench
    model: (loss, MSE, SSIM). A network of K subframes is scored on their mean intensity."""
    amp, phase = net(v.x)
    h, w = v.hw
    shown = [v.coding(reference_field(a, p, amplitude_scale))[0]
             for a, p in subframe_fields(amp[0, :, :h, :w], phase[0, :, :h, :w])]
    seen = v.prepared.model(torch.stack(shown)).mean(0)
    return tune_loss(seen, v.prepared, ssim_weight, v.ssim_window_px)


def bench_scores(net: torch.nn.Module, views: Sequence[TuneView], amplitude_scale: float
                 ) -> list[tuple[float, float]]:
    """Each view's frame scored by its bench model against its exact target: (PSNR in dB, the
    figure `refine` reports for a frame; the loss's SSIM)."""
    out = []
    with torch.no_grad():
        for v in views:
            _, mse, ssim = view_loss(net, v, amplitude_scale, 0.0)
            out.append((round(psnr_db(mse), 3), round(ssim, 4)))
    return out


def _mean(scores: Sequence[Sequence[float]]) -> tuple[float, float]:
    return (round(float(np.mean([s[0] for s in scores])), 3),
            round(float(np.mean([s[1] for s in scores])), 4))


# -- the run -----------------------------------------------------------------------------------

@dataclass
class TuneResult:
    """A finished tuning: the tuned model's path, the steps run (in all), the seconds (in all),
    the training views' bench-model scores (PSNR dB, SSIM) before and after, and the
    `tuned_for` record."""

    path: Path
    steps: int
    seconds: float
    before: list[tuple[float, float]]
    after: list[tuple[float, float]]
    tuned_for: dict[str, Any]


def _atomic_save(obj: object, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _view_order(seed: int, step: int, n: int) -> int:
    """The view of `step`: each pass over the views in a seeded order (resumable: a function
    of the step alone)."""
    epoch, i = divmod(step, n)
    return int(np.random.default_rng([seed, epoch]).permutation(n)[i])


def trainable(module: torch.nn.Module) -> list[torch.nn.Parameter]:
    """The tuned parameters of a `ServingNet`: all but its fixed input normalisation and the
    head its output convolutions fold (not in the exported graph)."""
    out = []
    for name, p in module.named_parameters():
        keep = not name.startswith("unshuffle.") and name not in FOLDED
        p.requires_grad_(keep)
        if keep:
            out.append(p)
    return out


def _fmt_s(s: float) -> str:
    return f"{s / 60:.1f} min" if s >= 120 else f"{s:.0f} s"


def tune_model(model_path: str | Path, scene: Scene, scene_path: str | Path,
               calibration: Calibration, out: str | Path, settings: TuneSettings, *,
               config: Config | None = None, dataset: str | Path | None = None,
               panel_hw: tuple[int, int] | None = None, check_sizes: bool = True,
               stop_after: int | None = None, poses: Sequence[View] | None = None,
               say: Callable[[str], None] = print) -> TuneResult | None:
    """Tune the exported model at `model_path` for `scene` through `calibration`'s bench model
    into `out`/model.onnx (module docstring). Refusals (`TuneError`, nothing written): settings
    out of range, a model without the scene's metadata (its scene hash, depth mapping and
    training poses) or made for another scene, a calibration for other optics
    (`check_bench`), more views than training poses. Resumes from `out`/checkpoint.pt when it
    was made with the same model, scene, calibration and settings (the step budget aside). A
    non-finite loss stops with `TuneError` naming the last good checkpoint. `stop_after`: stop
    (without writing the model) after that many steps in all, as an interruption would (tests);
    then returns None. `check_sizes`: check the tuned file at its original model's
    `checked_sizes` (the ONNX-only tile check) and record them. `poses`: the training poses
    to choose the views from; default `tuning_poses`: the dataset's, the model's recorded ones,
    or a grid over its pose envelope."""
    config = config or Config()
    model_path, out = Path(model_path), Path(out)
    # Everything that can be refused is, before anything is written.
    try:
        model = TorchModel(model_path, expected=expected_from_config(config.optics, config.slm),
                           device=settings.device)
    except ValueError as exc:
        raise TuneError(str(exc)) from None
    meta = model.metadata
    scene_sha = sha256_file(Path(scene_path))
    recorded = recorded_scenes(meta)
    if not recorded:
        raise TuneError(f"{model_path}: its metadata records no scene (scene_sha256): tune a "
                        "model `nhfd model build` made")
    if scene_sha not in recorded:
        raise TuneError(f"--scene {scene_path}: not the scene {model_path} was built from "
                        f"(scene_sha256 {recorded[0][:12]}...)")
    if model.info.mapping is None:
        raise TuneError(f"{model_path}: its metadata has no depth mapping (mapping): the "
                        "exact target needs it")
    try:
        check_bench(calibration, tuple(model.info.wavelengths_m), model.info.pitch_m)
    except ValueError as exc:
        raise TuneError(f"--calibration: {exc}") from None
    if model.subframes not in (1, settings.subframes):
        raise TuneError(f"subframes (--subframes) = {settings.subframes}: {model_path} emits "
                        f"{model.subframes} subframes; tune it at --subframes "
                        f"{model.subframes}, or tune its one-frame source")
    if poses is None:
        poses, poses_from = tuning_poses(meta, scene, model.info,
                                         None if dataset is None else Path(dataset),
                                         views=settings.views)
        say(f"tuning views: {settings.views} of {len(poses)} poses, {poses_from}")
    views = choose_views(poses, settings.views)
    model_sha = sha256_file(model_path)
    cal_sha = fingerprint(calibration)
    key = {"model_sha256": model_sha, "scene_sha256": scene_sha, "calibration_sha256": cal_sha,
           "settings": settings.key(), "panel_hw": list(panel_hw or ()),
           "views": [v.to_json() for v in views]}
    ckpt_path = out / CHECKPOINT
    ckpt = None
    if ckpt_path.is_file():
        ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        if ckpt.get("key") != key:
            changed = sorted(k for k in key if ckpt.get("key", {}).get(k) != key[k])
            raise TuneError(f"--out {out}: its checkpoint was made with another "
                            f"{', '.join(changed)}: choose another folder or remove {ckpt_path}")

    net = model.module
    if settings.subframes != model.subframes:
        net = net.with_subframes(settings.subframes, settings.subframe_jitter, settings.seed)
    net = net.train()
    params = trainable(net)
    opt = torch.optim.Adam(params, lr=settings.learning_rate)
    tv = prepare_views(views, scene, model, config, calibration, settings, panel_hw, say)
    scale = model.amplitude_scale
    out.mkdir(parents=True, exist_ok=True)
    if ckpt is None:
        before = bench_scores(net, tv, scale)
        step, elapsed, history = 0, 0.0, []
        ckpt = {"key": key, "step": 0, "seconds": 0.0, "state": net.state_dict(),
                "optimizer": opt.state_dict(), "history": [], "before": before}
        _atomic_save(ckpt, ckpt_path)  # the start is the first good checkpoint
        say(f"untuned: {_mean(before)[0]:.2f} dB, SSIM {_mean(before)[1]:.3f} through the "
            f"bench model on {len(tv)} views")
    else:
        net.load_state_dict(ckpt["state"])
        opt.load_state_dict(ckpt["optimizer"])
        step, elapsed, history = ckpt["step"], ckpt["seconds"], list(ckpt["history"])
        before = ckpt["before"]
        say(f"resumed from {ckpt_path} at step {step}")
    good = step

    def save() -> None:
        nonlocal good
        _atomic_save({"key": key, "step": step, "seconds": elapsed, "state": net.state_dict(),
                      "optimizer": opt.state_dict(), "history": history,
                      "before": before}, ckpt_path)
        good = step

    t_start, run_steps = time.perf_counter(), 0
    last_say = -math.inf
    while step < settings.steps and elapsed < settings.seconds:
        if stop_after is not None and step >= stop_after:
            save()
            return None
        t0 = time.perf_counter()
        i = _view_order(settings.seed, step, len(tv))
        loss, mse, ssim = view_loss(net, tv[i], scale, settings.ssim_weight)
        value = float(loss.detach())
        if not math.isfinite(value):
            raise TuneError(f"non-finite loss at step {step} (view {i}): stopped; the last "
                            f"good checkpoint is {ckpt_path} (step {good})")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, GRAD_CLIP)
        opt.step()
        if not all(bool(torch.isfinite(p).all()) for p in params):
            raise TuneError(f"non-finite weights after step {step} (view {i}): stopped; the "
                            f"last good checkpoint is {ckpt_path} (step {good})")
        step += 1
        run_steps += 1
        dt = time.perf_counter() - t0
        elapsed += dt
        history.append((step, round(elapsed, 3), value, mse, ssim))
        if step % settings.checkpoint_every == 0:
            save()
        now = time.perf_counter()
        if now - last_say >= 5.0 or step == settings.steps:
            last_say = now
            per = (now - t_start) / run_steps
            left = min((settings.steps - step) * per, max(settings.seconds - elapsed, 0.0))
            say(f"step {step}/{settings.steps} view {i}: {psnr_db(mse):.2f} dB, SSIM "
                f"{ssim:.3f}; {_fmt_s(elapsed)} in, about {_fmt_s(left)} left")
    save()
    if step < settings.steps:
        say(f"stopped at step {step} of {settings.steps}: the time budget (--seconds "
            f"{settings.seconds:g}) is spent")
    net.eval()
    after = bench_scores(net, tv, scale)
    tuned_for = {
        **bench_record(calibration, _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")),
        "source_model_sha256": model_sha, "steps": step, "seconds": round(elapsed, 1),
        "views": len(tv), "window_hw": list(settings.window_hw),
        "subframes": settings.subframes,
        "ssim_weight": settings.ssim_weight, "learning_rate": settings.learning_rate,
        "train_views_bench": {"psnr_db_before": _mean(before)[0],
                              "psnr_db_after": _mean(after)[0],
                              "ssim_before": _mean(before)[1], "ssim_after": _mean(after)[1]},
    }
    path = write_tuned_model(model_path, net, out / TUNED, tuned_for, check_sizes=check_sizes)
    (out / REPORT).write_text(json.dumps({"tuned_for": tuned_for, "before": before,
                                          "after": after}, indent=2) + "\n")
    say(f"tuned: {_mean(before)[0]:.2f} -> {_mean(after)[0]:.2f} dB, SSIM {_mean(before)[1]:.3f} "
        f"-> {_mean(after)[1]:.3f} through the bench model on the {len(tv)} training views; "
        f"{path}")
    return TuneResult(path, step, elapsed, list(before), after, tuned_for)


def write_tuned_model(source: str | Path, module: torch.nn.Module, path: str | Path,
                      tuned_for: dict[str, Any], *, check_sizes: bool = True) -> Path:
    """The model file `source` with `module`'s weights (a `ServingNet` rebuilt from it: the
    initialisers carry its parameter names; each keeps its file's dtype) and its metadata plus
    `tuned_for`, written atomically to `path`, then loaded back as `TorchModel` does (its graph
    must compute the module's function). Its `checked_sizes` are checked again on the new
    weights (`check_sizes`) or left out."""
    import onnx
    from onnx import numpy_helper

    source, path = Path(source), Path(path)
    model = onnx.load(str(source))
    k = int(getattr(module, "subframes", 1))
    if k > 1:  # K heads: the head weights' shapes and the outputs' channels change
        _widen_outputs(model, k)
    state = {n: v.detach().cpu() for n, v in module.state_dict().items()}
    for init in model.graph.initializer:
        if init.name in state and init.name not in FOLDED:
            dtype = numpy_helper.to_array(init).dtype
            init.CopyFrom(numpy_helper.from_array(state[init.name].numpy().astype(dtype),
                                                  init.name))
    meta = parse_metadata({p.key: p.value for p in model.metadata_props}, str(source))
    checked = meta.pop("checked_sizes", [])
    meta["tuned_for"] = tuned_for
    if k > 1:
        meta["subframes"] = k
    for prop in model.metadata_props:
        if prop.key == METADATA_KEY:
            prop.value = json.dumps(meta)
    onnx.checker.check_model(model)
    tmp = path.with_name(path.name + ".tmp")
    onnx.save(model, str(tmp))
    TorchModel(tmp)  # its graph is the module's function, or NotAModel
    os.replace(tmp, path)
    if check_sizes and checked:
        check_and_record(path, [tuple(e["hw"]) for e in checked])
    return path


def _widen_outputs(model: Any, k: int) -> None:
    """An exported `ServingNet` graph as one of K subframes: its outputs (amplitude, phase)
    declared with 3 K channels, and the shapes inferred for its inner values dropped (the heads'
    weights, written next, carry the new ones; onnxruntime infers the rest again)."""
    for out in model.graph.output:
        dim = out.type.tensor_type.shape.dim[1]
        dim.Clear()
        dim.dim_value = 3 * k
    del model.graph.value_info[:]

