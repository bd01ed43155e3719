"""`nhfd calib learn`: learn what the parametric bench model leaves out, from captures
(docs/learned_bench.md).

1. **Patterns** on the frame's region of the panel (`training_patterns`): partly converged
   `sgd` frames of varied content (spots at the planes, smooth images), each refined a few
   steps through the parametric model; random grey levels; structured frames (gratings,
   blocks).
2. **Captures** through the bench's `Camera`, in this process (`CameraLoop`, citl's loop) or
   through a running daemon (`DaemonCameraLoop`, its `capture_stack` job): never arming, never
   setting a power, every diode off on every way out. Each pattern at `LearnPlan.planes_m` per
   colour, with the calibration's focus mapping and geometry, onto the window's SLM grid. The
   plan (count, settle time, expected duration on a real bench) is printed first; the captures
   are kept pattern by pattern, and a stopped run resumes where it stopped.
3. **The fit**: a `LearnedBench` around the calibration's `BenchForward`, by Adam on the
   captures of the training patterns at the training planes; held-out patterns and a held-out
   plane score it, parametric against learned, PSNR per colour.
4. **The files**: the weights (safetensors) beside the calibration and the calibration
   referencing them, each written atomically, the weights first; the captures and the plan
   beside them, so that `fidelity` (drawn by `nhfd calib report`) scores the fit again, per
   colour and plane, from the files alone.

Only the captures and the fitted calibration are read: nothing of the simulated bench.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nhfd.calibration import Calibration, parametric_fingerprint
from nhfd.config import MAX_PLANES, Config, RefineSettings
from nhfd.dataset.build import write_json_atomic
from nhfd.models.learned_bench import LearnedBench, LearnedOptics, save_learned
from nhfd.optics import propagate
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.refine import (
    BenchForward,
    grey_phase,
    learned_bench_for,
    refine,
    target_from_field,
    window_mask,
)
from nhfd.pipeline.settings import FrameSettings, with_calibration

from .citl import CameraLoop

WEIGHTS_NAME = "learned.safetensors"
CAPTURES_NAME = "captures.npz"
# The capture set while it is taken, pattern by pattern: what a rerun resumes from.
PARTIAL_NAME = "captures.partial.npz"
RECORD_NAME = "learn.json"
# Each colour's images above this percentile of its training captures count as 1 in the loss.
SCALE_PERCENTILE = 99.5
# The double-phase content's SLM amplitude peak (of the encoder's amplitude scale): nothing clips.
CONTENT_PEAK = 0.9
# The unmodulated light's coarse map steps this many times `LearnPlan.learning_rate` (its
# constant at the rate itself): at the full rate, on a twin without unmodulated light, the map
# fitted the training patterns' other residuals and cost 1.8 dB in green on held-out patterns.
MAP_LR_FACTOR = 0.1
# The CNNs' residuals step this many times `LearnPlan.learning_rate` (physics first: at the
# full rate the SLM-plane and target-plane CNNs overfitted 7 patterns on the test twin).
NET_LR_FACTOR = 0.3


@dataclass(frozen=True)
class LearnPlan:
    """What `learn` captures and fits. Counts are patterns; `planes_m` are metres from the
    reference plane (z0 + refocus), `held_out_plane` an index into them; times in seconds:
    `settle_s` the panel's settling after each pattern shown, `stage_move_s` one stage move,
    `laser_switch_s` one diode switched on and off, `exposure_s` one capture (for the printed
    estimate of a real bench; the twin's own time is measured)."""

    window_hw: tuple[int, int] = (64, 64)
    planes_m: tuple[float, ...] = (-0.6e-3, -0.2e-3, 0.2e-3, 0.6e-3)
    held_out_plane: int = 2
    sgd_patterns: int = 12
    sgd_iterations: tuple[int, ...] = (2, 5, 10)
    random_patterns: int = 4
    structured_patterns: int = 8
    held_out_patterns: int = 6
    steps: int = 150
    batch: int = 4
    learning_rate: float = 0.01
    seed: int = 0
    settle_s: float = 0.1
    stage_move_s: float = 0.5
    laser_switch_s: float = 0.02
    exposure_s: float = 0.005

    def __post_init__(self) -> None:
        checks: list[tuple[str, Any, bool, str]] = [
            ("window_hw", self.window_hw, len(self.window_hw) == 2
             and all(isinstance(n, int) and 16 <= n <= 4096 for n in self.window_hw),
             "2 integers in [16, 4096] px"),
            ("planes_m", self.planes_m, 2 <= len(self.planes_m) <= MAX_PLANES
             and all(math.isfinite(z) and abs(z) <= 0.05 for z in self.planes_m),
             f"2 to {MAX_PLANES} planes, |z| <= 0.05 m"),
            ("held_out_plane", self.held_out_plane,
             0 <= self.held_out_plane < len(self.planes_m), f"0 <= i < {len(self.planes_m)}"),
            ("sgd_patterns", self.sgd_patterns, 0 <= self.sgd_patterns <= 10_000, "[0, 10000]"),
            ("sgd_iterations", self.sgd_iterations, len(self.sgd_iterations) >= 1
             and all(0 <= n <= 1000 for n in self.sgd_iterations), "values in [0, 1000]"),
            ("random_patterns", self.random_patterns, 0 <= self.random_patterns <= 10_000,
             "[0, 10000]"),
            ("structured_patterns", self.structured_patterns,
             0 <= self.structured_patterns <= 10_000, "[0, 10000]"),
            ("held_out_patterns", self.held_out_patterns,
             1 <= self.held_out_patterns <= self.patterns - 2,
             f"[1, {self.patterns - 2}] (2 patterns at least left to train)"),
            ("steps", self.steps, 0 <= self.steps <= 1_000_000, "[0, 1000000]"),
            ("batch", self.batch, 1 <= self.batch <= 256, "[1, 256]"),
            ("learning_rate", self.learning_rate, 0 < self.learning_rate <= 1, "(0, 1]"),
        ]
        for name in ("settle_s", "stage_move_s", "laser_switch_s", "exposure_s"):
            v = getattr(self, name)
            checks.append((name, v, math.isfinite(v) and 0 <= v <= 60, "[0, 60] s"))
        for name, value, ok, allowed in checks:
            if not ok:
                raise ValueError(f"{name} = {value!r}: must be {allowed}")

    @property
    def patterns(self) -> int:
        """Patterns shown in all."""
        return self.sgd_patterns + self.random_patterns + self.structured_patterns

    @property
    def captures(self) -> int:
        """Camera captures in all: each pattern at each plane in each colour."""
        return self.patterns * len(self.planes_m) * 3

    def bench_seconds(self) -> float:
        """The expected capture time on a real bench: per pattern and plane a stage move, per
        colour the pattern shown and settled, the diode switched, one exposure."""
        per_colour = self.settle_s + self.laser_switch_s + self.exposure_s
        return self.patterns * len(self.planes_m) * (self.stage_move_s + 3 * per_colour)

    def describe(self) -> str:
        """The capture plan, as printed before anything is captured."""
        d = len(self.planes_m)
        planes = ", ".join(f"{z * 1e3:+.2f}" for z in self.planes_m)
        return (f"capture plan: {self.patterns} patterns ({self.sgd_patterns} sgd, "
                f"{self.random_patterns} random, {self.structured_patterns} structured; "
                f"{self.held_out_patterns} held out) x {d} planes ({planes} mm; plane "
                f"{self.held_out_plane} held out) x 3 colours = {self.captures} captures; "
                f"settle {self.settle_s * 1e3:.0f} ms per pattern shown, stage move "
                f"{self.stage_move_s:.2f} s, exposure {self.exposure_s * 1e3:.1f} ms: about "
                f"{self.bench_seconds() / 60:.1f} min on a real bench")


# The plan's fields that make the patterns and what is captured of them (the rest are the fit's,
# the split's and the printed estimate's): a partial capture resumes only under the same.
CAPTURE_FIELDS = ("window_hw", "planes_m", "sgd_patterns", "sgd_iterations", "random_patterns",
                  "structured_patterns", "seed")


@dataclass(frozen=True)
class Captured:
    """The training set: the patterns `grey` `[N, C, Hr, Wr]` uint8 (the region), what they
    are (`kinds`), the captures `images` `[N, D, C, h, w]` float32 on the window's SLM grid
    (any units), the pixels every capture saw `valid` `[h, w]` bool, and the capture's
    seconds."""

    grey: np.ndarray
    kinds: tuple[str, ...]
    images: np.ndarray
    valid: np.ndarray
    seconds: float


@dataclass(frozen=True)
class LearnResult:
    """What `learn` measured and wrote: held-out PSNR (dB) per colour, parametric and learned,
    on the held-out patterns at the training planes and on every pattern at the held-out plane;
    the training loss before and after; the files; the seconds of capture and fit."""

    held_out_patterns_db: dict[str, tuple[float, float, float]]
    held_out_plane_db: dict[str, tuple[float, float, float]]
    train_loss: tuple[float, float]
    weights: Path | None
    calibration: Path | None
    capture_s: float
    fit_s: float

    def lines(self) -> list[str]:
        """The held-out figures, one line each, as `nhfd calib learn` prints them."""
        out = []
        for what, table in (("held-out patterns", self.held_out_patterns_db),
                            ("held-out plane", self.held_out_plane_db)):
            p, q = table["parametric"], table["learned"]
            out.append(f"{what}: PSNR R/G/B parametric {p[0]:.2f} / {p[1]:.2f} / {p[2]:.2f} dB, "
                       f"learned {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} dB")
        return out


def learn_settings(config: Config, calibration: Calibration, window_hw: tuple[int, int],
                   panel_hw: tuple[int, int]) -> FrameSettings:
    """The frame settings captures are coded and modelled with: the configured optics and
    coding, the calibration's curves, sign, focus offsets, source and pupil, the window on the
    `panel_hw` panel, an amplitude scale of 1 (the content is scaled to it)."""
    o = config.optics
    base = FrameSettings(
        panel_hw=tuple(panel_hw), window_hw=tuple(window_hw), pitch_m=calibration.pitch_m,
        wavelengths_m=calibration.wavelengths_m, z0_m=o.z0_mm * 1e-3,
        aperture_shape=o.aperture.shape, cutoff_per_px=tuple(o.aperture.cutoff_per_px),
        amplitude_scale=1.0, zero_below=float(config.coding.zero_below),
        phase_stroke_rad=tuple(float(v) for v in config.slm.phase_stroke_rad),
        grey_invert=bool(config.slm.grey_invert), padding=o.padding)
    return with_calibration(base, calibration)


def content_field(rng: np.random.Generator, kind: int, window_hw: tuple[int, int],
             planes_m: Sequence[float], s: FrameSettings) -> torch.Tensor:
    """A reference-plane field `[C, h, w]` complex64 of varied content: spots at the planes
    (kind 0) or a smooth random image at one plane (kind 1), each colour its own brightness."""
    h, w = window_hw
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64) - (h - 1) / 2,
                            torch.arange(w, dtype=torch.float64) - (w - 1) / 2, indexing="ij")
    out = torch.zeros(3, h, w, dtype=torch.complex128)
    colours = torch.from_numpy(rng.uniform(0.3, 1.0, 3))[:, None, None]
    if kind == 0:
        for z in planes_m:
            img = torch.zeros(h, w, dtype=torch.float64)
            for x, y in rng.uniform(-0.35, 0.35, (4, 2)) * np.array([w, h]):
                img += torch.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.5**2))
            u = (img * colours).to(torch.complex128)
            out += propagate(u, -z, s.pitch_m, s.wavelengths_m, padding="auto")
    else:
        z = float(rng.choice(np.asarray(planes_m)))
        noise = torch.from_numpy(rng.standard_normal((1, 1, h // 8 + 1, w // 8 + 1)))
        img = torch.nn.functional.interpolate(noise, size=(h, w), mode="bicubic",
                                              align_corners=False)[0, 0]
        img = (img - img.min()) / (img.max() - img.min() + 1e-12)
        u = (img.sqrt() * colours).to(torch.complex128)
        out = propagate(u, -z, s.pitch_m, s.wavelengths_m, padding="auto")
    return out.to(torch.complex64)


def _structured(rng: np.random.Generator, hw: tuple[int, int]) -> np.ndarray:
    """A structured frame `[3, Hr, Wr]` uint8: a grating of random period and direction, or
    random blocks, each colour its own."""
    hr, wr = hw
    out = np.empty((3, hr, wr), np.uint8)
    yy, xx = np.mgrid[0:hr, 0:wr]
    for c in range(3):
        if rng.random() < 0.5:
            period = rng.uniform(2.0, 16.0)
            a = rng.uniform(0, np.pi)
            t = (np.cos(a) * xx + np.sin(a) * yy) / period + rng.uniform()
            out[c] = np.round(127.5 + 127.5 * np.sin(2 * np.pi * t)).astype(np.uint8)
        else:
            b = int(rng.integers(2, 17))
            blocks = rng.integers(0, 256, (hr // b + 1, wr // b + 1))
            out[c] = np.kron(blocks, np.ones((b, b)))[:hr, :wr].astype(np.uint8)
    return out


def training_patterns(encoder: Encoder, plan: LearnPlan, *,
                      say: Callable[[str], None] = print) -> tuple[np.ndarray, tuple[str, ...]]:
    """The plan's patterns `[N, C, Hr, Wr]` uint8 on the encoder's region and their kinds
    ("sgd-N": content refined N steps through the parametric model from its double-phase
    frame; "random"; "structured"), seeded by `plan.seed`."""
    rng = np.random.default_rng(plan.seed)
    s, r = encoder.settings, encoder.region
    greys: list[np.ndarray] = []
    kinds: list[str] = []
    model = BenchForward(encoder, plan.planes_m)
    for i in range(plan.sgd_patterns):
        ref = content_field(rng, i % 2, s.window_hw, plan.planes_m, s)
        with torch.no_grad():
            peak = float(encoder.to_slm(ref).abs().max())
        ref = ref * (CONTENT_PEAK * s.amplitude_scale / max(peak, 1e-12))
        with torch.no_grad():
            start, _ = encoder.code(encoder.to_slm(ref))
        n = plan.sgd_iterations[i % len(plan.sgd_iterations)]
        grey = start[None]
        if n:
            target = target_from_field(ref, plan.planes_m, encoder)
            grey = refine(start, target, model, RefineSettings(iterations=n, tolerance=0.0),
                          seed=plan.seed + i).grey
        greys.append(np.asarray(grey[0], np.uint8))
        kinds.append(f"sgd-{n}")
    for _ in range(plan.random_patterns):
        greys.append(rng.integers(0, 256, (3, r.height, r.width), dtype=np.uint8))
        kinds.append("random")
    for _ in range(plan.structured_patterns):
        greys.append(_structured(rng, (r.height, r.width)))
        kinds.append("structured")
    say(f"patterns: {len(greys)} on the {r.width} x {r.height} region")
    return np.stack(greys), tuple(kinds)


CaptureFor = Callable[[Encoder], Any]  # the encoder -> a `Capture` with a `captures` count


def camera_loop(devices: Any, calibration: Calibration) -> CaptureFor:
    """The captures through the bench's devices in this process (`CameraLoop`: never arms, never
    sets a power, every diode off on every way out), for `learn`."""
    return lambda encoder: CameraLoop(devices, calibration, encoder)


def resume_key(plan: LearnPlan, settings: FrameSettings, calibration: Calibration) -> str:
    """What a partial capture must have been taken with to be resumed: the plan's fields that
    make the patterns and captures (not the fit's), the frame settings, the parametric fit."""
    made = {k: v for k, v in dataclasses.asdict(plan).items() if k in CAPTURE_FIELDS}
    text = json.dumps({"plan": made, "settings": dataclasses.asdict(settings),
                       "calibration": parametric_fingerprint(calibration)},
                      sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def capture_set(loop: Any, plan: LearnPlan, grey: np.ndarray, kinds: Sequence[str], *,
                say: Callable[[str], None] = print, partial: Path | None = None,
                key: str = "") -> Captured:
    """Each pattern of `grey` `[N, C, Hr, Wr]` captured at the plan's planes in each colour
    through `loop` (a `Capture`: `CameraLoop`, `DaemonCameraLoop`; `CaptureStopped` when it
    cannot capture). With `partial`, what is captured is saved there after each pattern
    (atomically, with `key`), and a partial set saved with the same `key` is taken up where it
    stopped; one saved with another key is refused, not overwritten."""
    done = load_partial(partial, key, grey, kinds) if partial is not None else None
    images = [] if done is None else list(done.images)
    valid = None if done is None else done.valid.copy()
    seconds0 = 0.0 if done is None else done.seconds
    if done is not None:
        say(f"resuming: {len(images)} of {len(grey)} patterns captured ({partial})")
    t0 = time.perf_counter()
    for i in range(len(images), len(grey)):
        im, ok = loop(grey[i][None], plan.planes_m)
        images.append(np.asarray(im, np.float32))
        valid = np.asarray(ok, bool).copy() if valid is None else valid & np.asarray(ok, bool)
        seconds = seconds0 + time.perf_counter() - t0
        if partial is not None:
            save_captured(Captured(grey, tuple(kinds), np.stack(images), valid, seconds),
                          partial, key=key)
        if (i + 1) % 8 == 0 or i + 1 == len(grey):
            say(f"captured {i + 1} / {len(grey)} patterns ({loop.captures} captures, "
                f"{seconds:.1f} s)")
    return Captured(grey, tuple(kinds), np.stack(images), valid,
                    seconds0 + time.perf_counter() - t0)


def load_partial(path: Path, key: str, grey: np.ndarray | None = None,
                 kinds: Sequence[str] | None = None) -> Captured | None:
    """The partial capture set at `path` when it was saved with `key` (None when there is none);
    ValueError naming the file when it was saved with another plan, settings or calibration,
    or (given `grey`, `kinds`) holds other patterns."""
    path = Path(path)
    if not path.is_file():
        return None
    data = load_captured(path, partial=True)
    with np.load(path, allow_pickle=False) as z:
        saved = str(z["key"]) if "key" in z.files else ""
    other = saved != key or (grey is not None and not np.array_equal(data.grey, grey)) or (
        kinds is not None and tuple(data.kinds) != tuple(kinds))
    if other:
        raise ValueError(f"{path}: {len(data.images)} patterns captured with another plan, "
                         "frame settings or calibration: run again with the same options to "
                         "resume, or remove the file to start over")
    return data


def _colour_gain(seen: torch.Tensor, captured: torch.Tensor, mask: torch.Tensor, c: int
                 ) -> tuple[float, torch.Tensor, torch.Tensor]:
    """Colour `c`'s least-squares gain of `seen` onto `captured` (`[N, D, C, h, w]`) over every
    image inside `mask`, and the two masked pixel vectors (float64)."""
    x = seen[:, :, c][..., mask].double().flatten()
    y = captured[:, :, c][..., mask].double().flatten()
    return float(x @ y) / max(float(x @ x), 1e-300), x, y


def psnr_per_colour(seen: torch.Tensor, captured: torch.Tensor, mask: torch.Tensor
                    ) -> tuple[float, float, float]:
    """PSNR (dB) per colour of predictions `seen` against captures `captured` (both
    `[N, D, C, h, w]`) inside `mask` `[h, w]`: one least-squares gain per colour over all
    images (the exposure and each laser's power are fixed over a capture set, their product
    free), the error in units of the colour's captured 99.5th percentile."""
    out = []
    for c in range(seen.shape[2]):
        gain, x, y = _colour_gain(seen, captured, mask, c)
        peak = float(torch.quantile(y[:16_000_000], SCALE_PERCENTILE / 100))
        mse = float(((gain * x - y) ** 2).mean()) / max(peak, 1e-300) ** 2
        out.append(min(120.0, -10 * math.log10(max(mse, 1e-12))))
    return tuple(out)  # type: ignore[return-value]


def _loss(seen: torch.Tensor, captured: torch.Tensor, mask: torch.Tensor,
          scales: torch.Tensor) -> torch.Tensor:
    """The fit's loss: per colour the mean squared error after the least-squares gain over the
    batch (detached), in units of the colour's scale, averaged over the colours."""
    total = seen.new_zeros(())
    for c in range(seen.shape[2]):
        x, y = seen[:, :, c][..., mask], captured[:, :, c][..., mask]
        xd = x.detach()
        gain = (xd * y).sum() / (xd * xd).sum().clamp(min=1e-30)
        total = total + ((gain * x - y) / scales[c]).square().mean()
    return total / seen.shape[2]


def _predict(model: BenchForward, phase: torch.Tensor, chunk: int = 8) -> torch.Tensor:
    with torch.no_grad():
        return torch.cat([model(phase[i : i + chunk]) for i in range(0, len(phase), chunk)])


def split_patterns(plan: LearnPlan, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The held-out and the training patterns' indices (each sorted) of `n` patterns: a seeded
    draw of `plan.held_out_patterns`, the same for the fit and for `fidelity`."""
    order = np.random.default_rng(plan.seed + 1).permutation(n)
    return np.sort(order[: plan.held_out_patterns]), np.sort(order[plan.held_out_patterns :])


def fit_learned(encoder: Encoder, plan: LearnPlan, data: Captured, *,
                say: Callable[[str], None] = print
                ) -> tuple[LearnedBench, dict[str, Any]]:
    """The learned bench fitted to the training patterns' captures at the training planes, and
    its scores (`LearnResult`'s fields, as a dict) against the parametric model's."""
    torch.manual_seed(plan.seed)
    s = encoder.settings
    d = len(plan.planes_m)
    held, train = split_patterns(plan, len(data.grey))
    planes_train = [i for i in range(d) if i != plan.held_out_plane]
    mask = window_mask(s.window_hw) & torch.as_tensor(data.valid)
    if int(mask.sum()) < 64:
        raise ValueError(f"only {int(mask.sum())} window pixels seen by every capture: the "
                         "camera's region must hold the panel's image")
    images = torch.from_numpy(data.images)  # [N, D, C, h, w]
    phase = grey_phase(data.grey, encoder).float()  # [N, C, Hr, Wr]
    optics = LearnedOptics(tuple(s.wavelengths_m), s.pitch_m, tuple(s.panel_hw))  # type: ignore[arg-type]
    learned = LearnedBench(optics)
    fwd_train = BenchForward(encoder, [plan.planes_m[i] for i in planes_train], learned)
    cap_train = images[train][:, planes_train]
    scales = torch.stack([torch.quantile(cap_train[:, :, c][..., mask].flatten()[:16_000_000],
                                         SCALE_PERCENTILE / 100) for c in range(3)])
    nets = [p for n, p in learned.named_parameters() if not n.startswith("unmodulated")]
    opt = torch.optim.Adam([
        {"params": [learned.unmodulated], "lr": plan.learning_rate},
        {"params": [learned.unmodulated_map], "lr": MAP_LR_FACTOR * plan.learning_rate},
        {"params": nets, "lr": NET_LR_FACTOR * plan.learning_rate}])
    # The step decays to a tenth along a cosine: the last steps settle, not oscillate.
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda k: 0.1 + 0.45 * (1 + math.cos(math.pi * k / max(1, plan.steps))))
    rng = np.random.default_rng(plan.seed + 2)
    t0 = time.perf_counter()
    with torch.no_grad():
        first = float(_loss(_predict(fwd_train, phase[train]), cap_train, mask, scales))
    for step in range(plan.steps):
        pick = rng.choice(len(train), size=min(plan.batch, len(train)), replace=False)
        seen = fwd_train(phase[train[pick]])
        loss = _loss(seen, cap_train[pick], mask, scales)
        value = float(loss.detach())
        if not math.isfinite(value):
            raise ValueError(f"the learned bench's loss is not finite at step {step}: lower "
                             f"learning_rate = {plan.learning_rate}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if (step + 1) % 50 == 0 or step + 1 == plan.steps:
            say(f"  step {step + 1} / {plan.steps}: loss {value:.4g} "
                f"({time.perf_counter() - t0:.1f} s)")
    learned.requires_grad_(False)
    learned.eval()
    with torch.no_grad():
        last = float(_loss(_predict(fwd_train, phase[train]), cap_train, mask, scales))
    parametric = _predict(BenchForward(encoder, plan.planes_m), phase)
    fitted = _predict(BenchForward(encoder, plan.planes_m, learned), phase)
    keep = planes_train
    hp = plan.held_out_plane
    scores = {
        "held_out_patterns_db": {
            "parametric": psnr_per_colour(parametric[held][:, keep], images[held][:, keep], mask),
            "learned": psnr_per_colour(fitted[held][:, keep], images[held][:, keep], mask)},
        "held_out_plane_db": {
            "parametric": psnr_per_colour(parametric[:, hp : hp + 1], images[:, hp : hp + 1],
                                          mask),
            "learned": psnr_per_colour(fitted[:, hp : hp + 1], images[:, hp : hp + 1], mask)},
        "train_loss": (first, last),
        "fit_s": time.perf_counter() - t0,
    }
    return learned, scores


def write_learned(learned: LearnedBench, calibration: Calibration, out_dir: Path | str,
                  scores: dict[str, Any], plan: LearnPlan, *,
                  calibration_name: str = "calibration.toml") -> tuple[Path, Path]:
    """The weights (`WEIGHTS_NAME`, safetensors) and the calibration referencing them into
    `out_dir`, each atomically, the weights first (a calibration never names a missing file).
    The weights' metadata records the parametric fit they belong to and the held-out scores."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    weights = out / WEIGHTS_NAME
    # The calibration as its file will read back (the creation time set, the parts a file
    # leaves out left out): the weights record the fingerprint of that.
    probe = out / f".{calibration_name}.probe"
    try:
        bare = dataclasses.replace(calibration, learned_file="", learned_sha256="")
        calibration = dataclasses.replace(Calibration.load(bare.save(probe)), source="")
    finally:
        probe.unlink(missing_ok=True)
    extra = {"parametric_sha256": parametric_fingerprint(calibration),
             "held_out_patterns_db": scores["held_out_patterns_db"],
             "held_out_plane_db": scores["held_out_plane_db"],
             "plan": dataclasses.asdict(plan)}
    sha = save_learned(learned, weights, extra)
    updated = dataclasses.replace(calibration, learned_file=weights.name, learned_sha256=sha)
    path = updated.save(out / calibration_name)
    return weights, path


def learn(capture_for: CaptureFor, calibration: Calibration, config: Config, plan: LearnPlan,
          out_dir: Path | str | None, *, panel_hw: tuple[int, int],
          say: Callable[[str], None] = print) -> LearnResult:
    """The whole step (the module's docstring): the plan printed, patterns, captures through
    `capture_for(encoder)` (`camera_loop(devices, calibration)` in this process, a
    `DaemonCameraLoop` through `nhfd serve`; a person armed the lasers and set the powers), the
    fit, the files into `out_dir` (None: none written) and the held-out figures
    (`LearnResult.lines()`, for the caller to print).

    With `out_dir`, the captures are kept pattern by pattern in `PARTIAL_NAME` there: a run
    stopped (disarmed lasers, a cancel, a failed fit) is resumed by the same command, its
    patterns taken from the file, and only what is missing captured; the file goes once the
    weights, the calibration and the whole capture set are written."""
    if calibration.learned_file:
        calibration = dataclasses.replace(calibration, learned_file="", learned_sha256="")
    say(plan.describe())
    encoder = Encoder(learn_settings(config, calibration, plan.window_hw, panel_hw))
    partial = Path(out_dir) / PARTIAL_NAME if out_dir is not None else None
    key = resume_key(plan, encoder.settings, calibration)
    resumed = load_partial(partial, key) if partial is not None else None
    if resumed is not None:
        grey, kinds = resumed.grey, resumed.kinds
    else:
        grey, kinds = training_patterns(encoder, plan, say=say)
    if partial is not None:
        partial.parent.mkdir(parents=True, exist_ok=True)
    data = capture_set(capture_for(encoder), plan, grey, kinds, say=say, partial=partial,
                       key=key)
    say(f"fitting the learned bench ({plan.steps} steps, batch {plan.batch})")
    learned, scores = fit_learned(encoder, plan, data, say=say)
    weights = cal_path = None
    if out_dir is not None:
        weights, cal_path = write_learned(learned, calibration, out_dir, scores, plan)
    result = LearnResult(scores["held_out_patterns_db"], scores["held_out_plane_db"],
                         scores["train_loss"], weights, cal_path, data.seconds, scores["fit_s"])
    if out_dir is not None:
        save_captured(data, Path(out_dir) / CAPTURES_NAME, key=key)
        write_json_atomic(Path(out_dir) / RECORD_NAME, {
            "held_out_patterns_db": result.held_out_patterns_db,
            "held_out_plane_db": result.held_out_plane_db, "train_loss": result.train_loss,
            "capture_s": round(result.capture_s, 2), "fit_s": round(result.fit_s, 2),
            "plan": dataclasses.asdict(plan), "settings": dataclasses.asdict(encoder.settings),
            "captures": CAPTURES_NAME})
        assert partial is not None
        partial.unlink(missing_ok=True)
    return result


def save_captured(data: Captured, path: Path | str, *, key: str = "") -> Path:
    """The training set into `path` (uncompressed npz, atomically): the patterns, their kinds,
    the captures (of the first patterns only, in a partial set), the pixels every capture saw,
    and the `resume_key` it was taken with."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp.npz")
    np.savez(tmp, grey=data.grey, kinds=np.asarray(data.kinds), images=data.images,
             valid=data.valid, seconds=np.float64(data.seconds), key=np.asarray(key))
    tmp.replace(path)
    return path


def load_captured(path: Path | str, *, partial: bool = False) -> Captured:
    """A training set `save_captured` wrote, checked (ValueError naming the file and the
    problem): uint8 patterns `[N, C, Hr, Wr]`, float32 captures `[N, D, C, h, w]` (`partial`:
    of the first 1 to N patterns), finite, a bool `[h, w]` mask, one kind per pattern; no
    pickled objects."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            grey, kinds, images = z["grey"], z["kinds"], z["images"]
            valid, seconds = z["valid"], float(z["seconds"])
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"{path}: not a capture set of nhfd calib learn ({exc})") from None
    problems = []
    if grey.dtype != np.uint8 or grey.ndim != 4 or grey.shape[1] != 3:
        problems.append(f"patterns {grey.dtype} {grey.shape}: must be uint8 [N, 3, H, W]")
    n = images.shape[0] if images.ndim == 5 else -1
    count_ok = 1 <= n <= len(grey) if partial else n == len(grey)
    if images.dtype != np.float32 or not count_ok or images.shape[2] != 3:
        problems.append(f"captures {images.dtype} {images.shape}: must be float32 "
                        f"[{'1..' if partial else ''}{len(grey)}, D, 3, h, w]")
    elif not np.isfinite(images).all():
        problems.append("captures hold NaN or Inf")
    if valid.dtype != bool or valid.shape != images.shape[-2:]:
        problems.append(f"mask {valid.dtype} {valid.shape}: must be bool {images.shape[-2:]}")
    if kinds.shape != (len(grey),):
        problems.append(f"{kinds.shape[0] if kinds.ndim else 0} kinds for {len(grey)} patterns")
    if problems:
        raise ValueError(f"{path}: " + "; ".join(problems))
    return Captured(grey, tuple(str(k) for k in kinds), images, valid, seconds)


def _tuples(value: Any) -> Any:
    """JSON's lists back into the tuples the settings' dataclasses hold."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


@dataclass(frozen=True)
class Fidelity:
    """A learned bench scored again from its folder (`fidelity`): the captures `captured`
    `[N, D, C, h, w]` and what each model predicts of them, each prediction times its
    least-squares gain per colour over every image (`parametric`, `learned`, the same shape);
    the pixels scored `mask` `[h, w]`; the held-out patterns `held`; and per plane the PSNR
    per colour of each model (`per_plane`: the held-out patterns at a training plane, every
    pattern at the held-out plane, as `LearnResult` scores them)."""

    plan: LearnPlan
    captured: np.ndarray
    parametric: np.ndarray
    learned: np.ndarray
    mask: np.ndarray
    held: np.ndarray
    per_plane: tuple[dict[str, Any], ...]

    def to_json(self) -> dict[str, Any]:
        """The scores (no images)."""
        return {"planes_m": list(self.plan.planes_m), "held_out_plane": self.plan.held_out_plane,
                "held_out_patterns": [int(i) for i in self.held], "per_plane": list(self.per_plane)}


def _gained(pred: torch.Tensor, captured: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    """`pred` times each colour's gain onto `captured` (`_colour_gain`), as the PSNR scores it."""
    out = pred.double().clone()
    for c in range(pred.shape[2]):
        out[:, :, c] *= _colour_gain(pred, captured, mask, c)[0]
    return out.float().numpy()


def fidelity(out_dir: Path | str) -> Fidelity:
    """The learned bench in `out_dir` (what `learn` wrote: the calibration referencing the
    weights, the captures, the record) scored again, parametric against learned. ValueError
    naming the file when one is missing, refused (the weights' checks) or not `learn`'s."""
    out = Path(out_dir)
    record_path = out / RECORD_NAME
    if not record_path.is_file():
        raise ValueError(f"{out}: no {RECORD_NAME}: not a folder nhfd calib learn wrote")
    record = json.loads(record_path.read_text())
    if "settings" not in record:
        raise ValueError(f"{record_path}: written before the captures were kept: run nhfd calib "
                         "learn again")
    plan = LearnPlan(**{k: _tuples(v) for k, v in record["plan"].items()})
    settings = FrameSettings(**{k: _tuples(v) for k, v in record["settings"].items()})
    cal = Calibration.load(out / "calibration.toml")
    learned, why = learned_bench_for(cal, settings)
    if learned is None:
        raise ValueError(f"{out / 'calibration.toml'}: {why or 'references no learned bench'}")
    data = load_captured(out / record.get("captures", CAPTURES_NAME))
    encoder = Encoder(settings)
    mask = window_mask(settings.window_hw) & torch.as_tensor(data.valid)
    images = torch.from_numpy(data.images)
    phase = grey_phase(data.grey, encoder).float()
    preds = {"parametric": _predict(BenchForward(encoder, plan.planes_m), phase),
             "learned": _predict(BenchForward(encoder, plan.planes_m, learned), phase)}
    held, _train = split_patterns(plan, len(data.grey))
    rows = []
    for i, z in enumerate(plan.planes_m):
        every = i == plan.held_out_plane
        idx = np.arange(len(data.grey)) if every else held
        rows.append({"plane_m": z, "held_out": every,
                     "scored": "every pattern" if every else "held-out patterns",
                     **{name: psnr_per_colour(p[idx][:, i : i + 1], images[idx][:, i : i + 1],
                                              mask) for name, p in preds.items()}})
    return Fidelity(plan, data.images, _gained(preds["parametric"], images, mask),
                    _gained(preds["learned"], images, mask), mask.numpy(), held, tuple(rows))
