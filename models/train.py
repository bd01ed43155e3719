"""Training: seeded, resumable, validated every epoch, logged as CSV and a PNG of the curves.

A run folder holds `run.json` (the options, the network, the dataset it was trained on),
`checkpoint.pt` (weights, optimiser, step, every RNG state and the data order; written
atomically every `checkpoint_every` steps and at the end), `train_log.csv`, `val_log.csv` and
`curves.png`. Running the same command again continues from the checkpoint's step with the same
data order: every random draw of a step comes from (seed, step) and the order of an epoch from
(seed, epoch), so an interrupted run ends with the same weights as an uninterrupted one.

Under `torchrun` (WORLD_SIZE > 1) the same loop runs as DistributedDataParallel: every process
draws the step's whole batch and crops from (seed, step) as one process would, keeps its own
contiguous share (batch / WORLD_SIZE views), and DDP averages the gradients (gloo on the CPU,
nccl on GPUs), so a step's update is one process's on the whole batch up to float summation
order. The L2 term is a mean over the batch, so that holds exactly; the SSIM term's scale and the
field term's normalisation are taken over each process's share, which changes the loss slightly
(within the run-to-run spread). Rank 0 alone writes the run folder and validates.
"""

from __future__ import annotations

import csv
import ctypes
import json
import math
import os
import random
import sys
import time
import typing
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.profiler import record_function

from nhfd import __version__
from nhfd.config import (
    LEARNING_RATE_RULE,
    ModelSettings,
    TrainSettings,
    device_choice,
    learning_rate_ok,
)
from nhfd.models.data import (
    HoloData,
    batch_views,
    centre_crop,
    centre_crop_edges,
    random_crop,
    step_rng,
)
from nhfd.models.loss import FocalStackLoss, Optics, choose_planes, uniform_planes
from nhfd.models.metadata import manifest_sha256
from nhfd.models.net import NetSpec, build_net, parameter_count, predict, to_field

CHECKPOINT = "checkpoint.pt"
RUN_JSON = "run.json"
TRAIN_LOG = "train_log.csv"
VAL_LOG = "val_log.csv"
CURVES = "curves.png"
TRAIN_COLUMNS = ("step", "epoch", "loss", "l2", "perceptual", "lr", "planes", "seconds")
VAL_COLUMNS = ("step", "epoch", "split", "views", "loss", "l2", "psnr_db")
# The learning rate decays along a cosine to this fraction of its start over the budget.
LR_FLOOR = 0.05
# Options that may change when a run is resumed (they do not change what a step computes).
# The device changes float rounding, not the computation, so a run may move between them.
# So does mixed precision (`amp`): it changes the forward pass's rounding, not what it computes.
RESUMABLE_CHANGES = ("steps", "checkpoint_every", "val_views", "threads", "device", "progress",
                     "amp")  # fmt: skip
# `[model.train] amp`'s values, as the configuration declares them.
AMP_MODES: tuple[str, ...] = typing.get_args(TrainSettings.model_fields["amp"].annotation)


def check_amp(amp: str) -> str:
    """`amp` if it is one of AMP_MODES, else ValueError naming it and the allowed values."""
    if amp not in AMP_MODES:
        raise ValueError(f"amp = {amp!r}: must be one of {', '.join(AMP_MODES)}")
    return amp


def amp_dtype(amp: str, device: torch.device) -> torch.dtype | None:
    """The autocast dtype of the network's forward pass for `[model.train] amp`, or None (full
    float32). "auto": on CUDA bf16 where the GPU supports it, else fp16; off on the CPU (bf16
    autocast there is slower than float32 on most CPUs). "bf16" runs on the CPU or CUDA; "fp16"
    needs CUDA (a gradient scaler keeps its small gradients)."""
    check_amp(amp)
    if amp == "off" or (amp == "auto" and device.type != "cuda"):
        return None
    if amp == "auto":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    if amp == "fp16" and device.type != "cuda":
        raise ValueError(f"amp = 'fp16' on {device}: needs CUDA (on the CPU use bf16 or off)")
    return torch.bfloat16 if amp == "bf16" else torch.float16


def autocast_context(dtype: torch.dtype | None, device: torch.device) -> AbstractContextManager:
    """The forward pass's autocast region (a no-op context for float32)."""
    if dtype is None:
        return nullcontext()
    return torch.autocast(device.type, dtype=dtype)


def grad_scaler(dtype: torch.dtype | None, device: torch.device) -> torch.amp.GradScaler:
    """A gradient scaler, enabled only for fp16 (bf16 has float32's range)."""
    return torch.amp.GradScaler(device.type, enabled=dtype == torch.float16)


def float32_loss(
    loss_fn: FocalStackLoss,
    amp: torch.Tensor,
    phase: torch.Tensor,
    target: torch.Tensor,
    planes: Sequence[float],
    perceptual_planes: Sequence[int],
    edges: Sequence[bool],
) -> dict[str, torch.Tensor]:
    """The focal-stack loss in float32 whatever autocast region it is called from: the network's
    (possibly half-precision) outputs are cast up and autocast is switched off, so the field,
    the FFTs and the propagation are complex64 (torch's half FFTs need power-of-two sizes, and
    half would lose the loss's dynamic range)."""
    with torch.autocast(target.device.type, enabled=False):
        field = to_field(amp.float(), phase.float(), 1.0)
        return loss_fn(field, target.to(torch.complex64), planes, perceptual_planes, edges)


def training_device(name: str, *, check_available: bool = False) -> torch.device:
    """`cpu`, `cuda`, `cuda:N` or `auto` (CUDA when torch sees a device, else the CPU) as a torch
    device; with `check_available`, refuse a CUDA device this machine does not have
    (`device_choice`'s messages)."""
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    chosen = device_choice(name, "device", cuda_count=count if check_available else None)
    if chosen == "auto":  # the name alone was checked; "auto" still has to pick
        chosen = device_choice(chosen, "device", cuda_count=count)
    return torch.device(chosen)


# The defaults of nhfd.toml's [model] section, held once in nhfd.config.
_MODEL = ModelSettings()
_NET = _MODEL.profiles[_MODEL.profile]
_TRAIN = _MODEL.train


@dataclass(frozen=True)
class TrainOptions:
    """Everything a training run depends on besides the dataset (see nhfd.toml [model.train]).
    The defaults are the configuration's: the default profile's network and training recipe."""

    width: int = _NET.width
    depth: int = _NET.depth
    unshuffle: int = _NET.unshuffle
    inputs: str = _NET.inputs
    growth: float = _NET.growth
    skip: str = _NET.skip
    single_conv_levels: int = _NET.single_conv_levels
    deep_width: int = _NET.deep_width
    profile: str = _MODEL.profile
    steps: int = _TRAIN.steps
    batch: int = _TRAIN.batch
    crop_width_px: int = _TRAIN.crop_width_px
    crop_height_px: int = _TRAIN.crop_height_px
    learning_rate: float = _TRAIN.learning_rate
    seed: int = _TRAIN.seed
    plane_mode: str = _TRAIN.plane_mode
    planes_from_depth: int = _TRAIN.planes_from_depth
    planes_random: int = _TRAIN.planes_random
    plane_step_mm: float = _TRAIN.plane_step_mm
    perceptual: str = _TRAIN.perceptual
    perceptual_weight: float = _TRAIN.perceptual_weight
    perceptual_planes: int = _TRAIN.perceptual_planes
    field_weight: float = _TRAIN.field_weight
    ssim_window_px: int = _TRAIN.ssim_window_px
    vgg_weights: str = _TRAIN.vgg_weights
    checkpoint_every: int = _TRAIN.checkpoint_every
    val_views: int = _TRAIN.val_views
    threads: int = _TRAIN.threads
    amp: str = _TRAIN.amp
    device: str = "cpu"
    progress: bool = True

    def __post_init__(self) -> None:
        _ = self.spec  # NetSpec validates the network's shape
        training_device(self.device)  # validates the name; availability is checked at start
        check_amp(self.amp)
        checks = {
            "steps": (self.steps >= 1, "must be at least 1"),
            "batch": (self.batch >= 1, "must be at least 1"),
            "crop_width_px": (self.crop_width_px >= 1, "must be at least 1"),
            "crop_height_px": (self.crop_height_px >= 1, "must be at least 1"),
            "learning_rate": (learning_rate_ok(self.learning_rate), LEARNING_RATE_RULE),
            "planes_from_depth": (self.planes_from_depth >= 0, "must be 0 or more"),
            "planes_random": (self.planes_random >= 0, "must be 0 or more"),
            "plane_step_mm": (self.plane_step_mm > 0, "must be > 0"),
            "field_weight": (math.isfinite(self.field_weight) and self.field_weight >= 0,
                             "must be a finite number >= 0"),
            "checkpoint_every": (self.checkpoint_every >= 1, "must be at least 1"),
            "val_views": (self.val_views >= 1, "must be at least 1"),
        }
        for name, (ok, allowed) in checks.items():
            if not ok:
                raise ValueError(f"{name} = {getattr(self, name)!r}: {allowed}")
        if self.planes_from_depth + self.planes_random < 1:
            raise ValueError("planes_from_depth + planes_random must be at least 1")
        if self.plane_mode not in ("depth", "uniform"):
            raise ValueError(f"plane_mode = {self.plane_mode!r}: must be depth or uniform")
        if self.perceptual not in ("ssim", "vgg", "none"):
            raise ValueError(f"perceptual = {self.perceptual!r}: must be ssim, vgg or none")

    @property
    def spec(self) -> NetSpec:
        """The network these options train."""
        return NetSpec(self.width, self.depth, self.unshuffle, self.inputs, self.growth,
                       self.skip, self.single_conv_levels, self.deep_width)  # fmt: skip

    @property
    def crop_hw(self) -> tuple[int, int]:
        """The training crop `(H, W)`, px."""
        return self.crop_height_px, self.crop_width_px

    @staticmethod
    def from_config(model: ModelSettings, profile: str | None = None,
                    **overrides) -> TrainOptions:
        """Options from a configuration's `[model]` section: the network of `[model.profiles]`
        `profile` (default `[model].profile`) and `[model.train]`, with `overrides` (None
        values ignored) on top."""
        m = model
        name = profile or m.profile
        if name not in m.profiles:
            raise ValueError(
                f"--profile {name!r}: not one of the configured profiles "
                f"{', '.join(sorted(m.profiles))}"
            )
        p = m.profiles[name]
        base = {f.name: getattr(m.train, f.name) for f in fields(TrainOptions)
                if hasattr(m.train, f.name)}  # fmt: skip
        base.update(width=p.width, depth=p.depth, unshuffle=p.unshuffle, inputs=p.inputs,
                    growth=p.growth, skip=p.skip, single_conv_levels=p.single_conv_levels,
                    deep_width=p.deep_width, profile=name)
        base.update({k: v for k, v in overrides.items() if v is not None})
        return TrainOptions(**base)


@dataclass(frozen=True)
class Distributed:
    """This process's place in a torchrun job."""

    rank: int
    world_size: int
    local_rank: int
    backend: str
    started_group: bool  # this process initialised the group (and destroys it at the end)

    @property
    def is_main(self) -> bool:
        """Whether this is rank 0 (the process that logs, validates and saves)."""
        return self.rank == 0


def distributed_from_env(device: torch.device) -> Distributed | None:
    """Join the torchrun job the environment describes (WORLD_SIZE > 1): gloo on the CPU, nccl
    on CUDA; None when this is the only process."""
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world <= 1:
        return None
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", str(rank)))
    backend = "nccl" if device.type == "cuda" else "gloo"
    started = False
    if not dist.is_initialized():
        dist.init_process_group(backend=backend)
        started = True
    return Distributed(dist.get_rank(), dist.get_world_size(), local, backend, started)


@dataclass
class TrainResult:
    """A finished run: its folder, the last step, the last loss, seconds per step of this call
    and the step it resumed from (0: a fresh run)."""

    run_dir: Path
    step: int
    last_loss: float
    seconds_per_step: float
    resumed_from: int


def tune_malloc() -> str:
    """Raise glibc's mmap and trim thresholds: large FFT buffers otherwise go back to the kernel
    after every step and come back as page faults (820 -> 271 ms per step measured here)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return "malloc: not glibc, left as is"
    m_trim, m_top_pad, m_mmap = -1, -2, -3
    ok = [
        libc.mallopt(m_mmap, 32 * 2**20),  # glibc's largest allowed mmap threshold
        libc.mallopt(m_trim, 2**30),
        libc.mallopt(m_top_pad, 256 * 2**20),
    ]
    return "malloc: thresholds raised" if all(ok) else f"malloc: mallopt returned {ok}"


def _rng_states() -> dict:
    return {
        "torch": torch.random.get_rng_state(),
        "numpy": np.random.get_state(),  # noqa: NPY002 (the legacy global, in case a caller uses it)
        "python": random.getstate(),
    }


def _set_rng_states(states: dict) -> None:
    torch.random.set_rng_state(states["torch"])
    np.random.set_state(states["numpy"])  # noqa: NPY002
    random.setstate(states["python"])


def _atomic_save(obj: object, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def lr_at(step: int, options: TrainOptions) -> float:
    """The learning rate at `step`: a cosine from `learning_rate` down to `LR_FLOOR` of it at
    the last step."""
    t = min(1.0, step / max(1, options.steps))
    return options.learning_rate * (LR_FLOOR + (1 - LR_FLOOR) * 0.5 * (1 + math.cos(math.pi * t)))


def _truncate_csv(path: Path, columns: tuple[str, ...], max_step: int) -> None:
    """Keep the header and the rows up to `max_step` (rows written after the last checkpoint
    are repeated by the resumed run)."""
    if not path.exists():
        with open(path, "w", newline="") as f:
            csv.writer(f).writerow(columns)
        return
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(columns))
        w.writeheader()
        for r in rows:
            if int(r["step"]) <= max_step:
                w.writerow(r)


def _append(path: Path, columns: tuple[str, ...], row: dict) -> None:
    with open(path, "a", newline="") as f:
        csv.DictWriter(f, fieldnames=list(columns)).writerow(row)


def plot_curves(run_dir: Path) -> Path:
    """Plot the run's training loss and L2, and its validation loss and PSNR (dB), against step
    into its curves PNG; returns the PNG's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(run_dir / TRAIN_LOG, newline="") as f:
        train = list(csv.DictReader(f))
    with open(run_dir / VAL_LOG, newline="") as f:
        val = list(csv.DictReader(f))
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    if train:
        steps = [int(r["step"]) for r in train]
        ax[0].semilogy(steps, [max(float(r["loss"]), 1e-12) for r in train], lw=0.6, label="loss")
        ax[0].semilogy(steps, [max(float(r["l2"]), 1e-12) for r in train], lw=0.6, label="L2")
    for split in sorted({r["split"] for r in val}):
        rows = [r for r in val if r["split"] == split]
        s = [int(r["step"]) for r in rows]
        ax[0].semilogy(s, [max(float(r["loss"]), 1e-12) for r in rows], "o-", label=f"{split}")
        ax[1].plot(s, [float(r["psnr_db"]) for r in rows], "o-", label=split)
    ax[0].set_xlabel("step")
    ax[0].set_title("focal-stack loss")
    ax[0].legend()
    ax[1].set_xlabel("step")
    ax[1].set_title("validation PSNR of the loss's planes (dB)")
    if val:
        ax[1].legend()
    fig.tight_layout()
    out = run_dir / CURVES
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def _optics_summary(data: HoloData) -> dict:
    """What the exported model's metadata needs from the dataset (kept in run.json)."""
    m = data.manifest
    return {
        "data_dir": str(data.dir.resolve()),
        "manifest_key": m.get("key"),
        "settings": m["settings"],
        "mapping": m["mapping"],
        "amplitude_scale": data.amplitude_scale,
        "camera": data.camera,
        "envelope": m.get("envelope"),
        "scene": m.get("scene"),
        "splits": {k: len(v) for k, v in m["splits"].items()},
        "manifest_sha256": manifest_sha256(data.dir),
    }


def validate_views(
    net: torch.nn.Module, data: HoloData, loss_fn: FocalStackLoss, options: TrainOptions,
    split: str,
) -> dict | None:  # fmt: skip
    """Mean loss and PSNR of the loss's intensity L2 over centre crops of a held-out split, on
    fixed uniform planes (comparable between epochs)."""
    if split not in data.splits:
        return None
    s = data.splits[split]
    n = min(len(s), options.val_views)
    planes = uniform_planes(data_volume(data), options.planes_from_depth + options.planes_random)
    k = list(range(min(options.perceptual_planes, len(planes))))
    losses, l2s, psnrs = [], [], []
    net.eval()
    device = next(net.parameters()).device
    with torch.no_grad():
        for v in range(n):
            x = centre_crop(s.inputs(options.inputs, slice(v, v + 1)), options.crop_hw)
            target = centre_crop(s.field[v : v + 1], options.crop_hw)
            x, target = x.to(device), target.to(device)
            edges = centre_crop_edges(tuple(s.rgb.shape[-2:]), options.crop_hw)
            amp, phase = predict(net, x)
            out = loss_fn(to_field(amp, phase, 1.0), target, planes, k, edges)
            peak = float(loss_fn.stack(target, planes, edges).max())
            losses.append(float(out["loss"]))
            l2s.append(float(out["l2"]))
            psnrs.append(10 * math.log10(max(peak, 1e-30) ** 2 / max(float(out["l2"]), 1e-30)))
    net.train()
    return {"split": split, "views": n, "loss": float(np.mean(losses)), "l2": float(np.mean(l2s)),
            "psnr_db": float(np.mean(psnrs))}  # fmt: skip


def data_volume(data: HoloData) -> tuple[float, float]:
    """The dataset's hologram volume `(z_min, z_max)` about the reference plane, m."""
    v = data.manifest["settings"]["volume_m"]
    return float(v[0]), float(v[1])


def train(
    data_dir: str | Path,
    run_dir: str | Path,
    options: TrainOptions,
    *,
    force: bool = False,
    log: Callable[[str], None] | None = None,
    data: HoloData | None = None,
    stop_at: int | None = None,
) -> TrainResult:
    """Train (or continue training) a network on a dataset folder into `run_dir`.

    `stop_at` stops (with a checkpoint) at that step as an interruption would; the learning-rate
    schedule follows `options.steps`, so raising the budget on resume changes the remaining
    steps' rates."""
    say = log or (lambda msg: print(msg, file=sys.stderr))
    device = training_device(options.device, check_available=True)
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world > 1 and options.batch % world:
        raise ValueError(
            f"batch = {options.batch}: must be a multiple of WORLD_SIZE = {world} (each "
            "process takes an equal share of a step's views)"
        )
    ddp = distributed_from_env(device)
    if ddp is not None:
        try:
            return _train(data_dir, run_dir, options, force=force, say=say, data=data,
                          stop_at=stop_at, ddp=ddp)  # fmt: skip
        finally:
            if ddp.started_group:
                dist.destroy_process_group()
    return _train(data_dir, run_dir, options, force=force, say=say, data=data, stop_at=stop_at,
                  ddp=None)  # fmt: skip


def _train(
    data_dir: str | Path,
    run_dir: str | Path,
    options: TrainOptions,
    *,
    force: bool,
    say: Callable[[str], None],
    data: HoloData | None,
    stop_at: int | None,
    ddp: Distributed | None,
) -> TrainResult:
    main = ddp is None or ddp.is_main
    world = 1 if ddp is None else ddp.world_size
    if not main:
        say = lambda _msg: None  # noqa: E731 (rank 0 speaks for the job)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    say(tune_malloc())
    if options.threads:
        torch.set_num_threads(options.threads)
    data = data or HoloData(data_dir, max_views={"interp": options.val_views,
                                                 "extrap": options.val_views})  # fmt: skip
    train_split = data.splits["train"]
    optics = Optics.from_manifest(data.manifest)
    loss_fn = FocalStackLoss(
        optics, perceptual=options.perceptual, perceptual_weight=options.perceptual_weight,
        ssim_window_px=options.ssim_window_px, vgg_weights=options.vgg_weights or None,
        field_weight=options.field_weight,
    )  # fmt: skip
    device = training_device(options.device, check_available=True)
    if ddp is not None and device.type == "cuda":
        device = torch.device("cuda", ddp.local_rank)  # one GPU per process
        torch.cuda.set_device(device)
    net = build_net(options.spec, seed=options.seed).to(device)
    if loss_fn.vgg is not None:
        loss_fn.vgg.to(device)
    opt = torch.optim.Adam(net.parameters(), lr=options.learning_rate)
    half = amp_dtype(options.amp, device)
    scaler = grad_scaler(half, device)
    ckpt_path = run_dir / CHECKPOINT
    step = 0
    if ckpt_path.exists() and not force:
        ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        _check_resumable(ckpt, options, data, ckpt_path)
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        if scaler.is_enabled() and ckpt.get("grad_scaler"):
            scaler.load_state_dict(ckpt["grad_scaler"])
        _set_rng_states(ckpt["rng"])
        step = int(ckpt["step"])
        say(f"resuming {run_dir} at step {step} of {options.steps}")
    elif force and main:
        ckpt_path.unlink(missing_ok=True)
        for name in (TRAIN_LOG, VAL_LOG):
            (run_dir / name).unlink(missing_ok=True)
    resumed_from = step
    if main:
        _truncate_csv(run_dir / TRAIN_LOG, TRAIN_COLUMNS, step)
        _truncate_csv(run_dir / VAL_LOG, VAL_COLUMNS, step)
    model: torch.nn.Module = net
    if ddp is not None:
        # Built after the checkpoint is loaded; DDP also broadcasts rank 0's weights.
        model = DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda"
                                        else None)  # fmt: skip
        model.spec = net.spec  # predict() reads the network's spec
    share = slice(0, options.batch) if ddp is None else slice(
        ddp.rank * options.batch // world, (ddp.rank + 1) * options.batch // world)
    n_train = len(train_split)
    per_epoch = -(-n_train // options.batch)
    run_info = {
        "options": asdict(options),
        "net": options.spec.to_json(),
        "parameters": parameter_count(net),
        "loss": loss_fn.describe(),
        "dataset": _optics_summary(data),
        "steps_per_epoch": per_epoch,
        "nhfd_version": __version__,
    }
    if ddp is not None:
        run_info["distributed"] = {"world_size": world, "backend": ddp.backend}
    if main:
        (run_dir / RUN_JSON).write_text(json.dumps(run_info, indent=1, default=str))
    say(f"network {options.spec.to_json()} ({run_info['parameters']} parameters, input multiple "
        f"{options.spec.multiple}); {n_train} training views, {per_epoch} steps per epoch; "
        f"crops {options.crop_width_px}x{options.crop_height_px}")  # fmt: skip
    say(f"loss: {loss_fn.describe()}; planes: {options.plane_mode}; forward pass in "
        f"{str(half).removeprefix('torch.') if half else 'float32'}, loss in float32")
    fixed = uniform_planes(data_volume(data), options.planes_from_depth + options.planes_random)
    bar = None
    if options.progress and main:
        from tqdm import tqdm

        bar = tqdm(total=options.steps, initial=step, unit="step", desc="train", file=sys.stderr)
    net.train()
    last_loss = float("nan")
    t_start, steps_done = time.perf_counter(), 0

    def checkpoint() -> None:
        if not main:
            return
        _atomic_save({
            "step": step, "model": net.state_dict(), "optimizer": opt.state_dict(),
            "rng": _rng_states(),
            "grad_scaler": scaler.state_dict() if scaler.is_enabled() else None,
            "data_order": {"seed": options.seed, "epoch": step // per_epoch,
                           "position": step % per_epoch, "batch": options.batch,
                           "n_train": n_train},
            "options": asdict(options), "net": options.spec.to_json(),
            "manifest_key": data.manifest.get("key"), "nhfd_version": __version__,
        }, ckpt_path)  # fmt: skip

    try:
        end = options.steps if stop_at is None else min(options.steps, stop_at)
        while step < end:
            t0 = time.perf_counter()
            # The step's parts are named for torch.profiler (`scripts/gpu_probe.py trainprof`);
            # with no profiler running a name costs about a microsecond.
            with record_function("train.crop"):
                rng = step_rng(options.seed, step)
                views = batch_views(options.seed, step, options.batch, n_train)
                x, target, zh, edges = random_crop(train_split, views, options.crop_hw, rng,
                                                   options.inputs)
                # Every process draws the whole batch (the same crops and planes as one process);
                # each trains on its share.
                x, target = x[share].to(device), target[share].to(device)
                if options.plane_mode == "uniform":
                    planes = fixed
                else:
                    planes = choose_planes(zh, data_volume(data), options.planes_from_depth,
                                           options.planes_random, rng, options.plane_step_mm * 1e-3)
                k = min(options.perceptual_planes, len(planes))
                perc = sorted(rng.choice(len(planes), size=k, replace=False).tolist()) if k else []
                lr = lr_at(step, options)
                for g in opt.param_groups:
                    g["lr"] = lr
            with record_function("train.forward"):
                with autocast_context(half, device):
                    amp, phase = predict(model, x)
            with record_function("train.loss"):
                out = float32_loss(loss_fn, amp, phase, target, planes, perc, edges)
            with record_function("train.backward_step"):
                opt.zero_grad(set_to_none=True)
                # Without fp16 the scaler is disabled: backward() and opt.step() as they were.
                scaler.scale(out["loss"]).backward()
                scaler.step(opt)
                scaler.update()
            step += 1
            steps_done += 1
            with record_function("train.log"):  # reading the loss waits for the device
                terms = torch.stack([out[k].detach().float() for k in ("loss", "l2", "perceptual")])
                if ddp is not None:
                    dist.all_reduce(terms)  # the job's mean, as one process would log it
                    terms = terms / world
                last_loss, l2_val, perc_val = (float(v) for v in terms.cpu())
                if not math.isfinite(last_loss):
                    raise FloatingPointError(f"step {step}: loss is {last_loss}; lower the rate")
                if main:
                    _append(run_dir / TRAIN_LOG, TRAIN_COLUMNS, {
                        "step": step, "epoch": (step - 1) // per_epoch, "loss": f"{last_loss:.6g}",
                        "l2": f"{l2_val:.6g}", "perceptual": f"{perc_val:.6g}",
                        "lr": f"{lr:.4g}", "planes": " ".join(f"{z * 1e3:.2f}" for z in planes),
                        "seconds": f"{time.perf_counter() - t0:.4f}",
                    })  # fmt: skip
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(loss=f"{last_loss:.4g}")
            if main and (step % per_epoch == 0 or step == options.steps):
                for split in ("interp", "extrap"):
                    with record_function("train.validate"):
                        res = validate_views(net, data, loss_fn, options, split)
                    if res:
                        _append(run_dir / VAL_LOG, VAL_COLUMNS, {
                            "step": step, "epoch": (step - 1) // per_epoch, **{
                                k2: (f"{v:.6g}" if isinstance(v, float) else v)
                                for k2, v in res.items()}})  # fmt: skip
            if step % options.checkpoint_every == 0 or step == end:
                with record_function("train.checkpoint"):
                    checkpoint()
    except KeyboardInterrupt:
        checkpoint()
        say(f"interrupted: checkpoint at step {step}; run the same command to continue")
        raise
    finally:
        if bar is not None:
            bar.close()
    if steps_done == 0 and not ckpt_path.exists():
        checkpoint()
    elapsed = time.perf_counter() - t_start
    if main:
        try:
            plot_curves(run_dir)
        except Exception as exc:  # a plot is a convenience; a finished run must not fail over it
            say(f"curves.png not written: {exc}")
    if ddp is not None:
        dist.barrier()  # no process leaves before rank 0 has written the final checkpoint
    return TrainResult(run_dir, step, last_loss, elapsed / max(1, steps_done), resumed_from)


def changed_options(ckpt: dict, options: TrainOptions, ignore: frozenset[str] = frozenset()
                    ) -> str:  # fmt: skip
    """The options (other than `RESUMABLE_CHANGES` and `ignore`) a checkpoint was trained with
    that differ from `options`, as "name: saved -> now, ..." ("" when none)."""
    # A run saved before an option existed was trained with that option's default then; for
    # the network's shape that is the classic U-Net its checkpoint's network loads as (doubling,
    # concatenating, two convolutions per block), whatever the default profile's are now.
    classic = {k: getattr(NetSpec(), k)
               for k in ("growth", "skip", "single_conv_levels", "deep_width")}  # fmt: skip
    saved = {f.name: f.default for f in fields(TrainOptions)} | classic | ckpt.get("options", {})
    now = asdict(options)
    diff = [k for k in now
            if k not in RESUMABLE_CHANGES and k not in ignore and saved.get(k) != now[k]]
    return ", ".join(f"{k}: {saved.get(k)!r} -> {now[k]!r}" for k in diff)


def _check_resumable(ckpt: dict, options: TrainOptions, data: HoloData, path: Path) -> None:
    pairs = changed_options(ckpt, options)
    if pairs:
        raise ValueError(
            f"{path} was trained with other options ({pairs}); use another --out, or --force "
            "to start over"
        )
    if ckpt.get("manifest_key") != data.manifest.get("key"):
        raise ValueError(
            f"{path} was trained on another dataset (manifest key "
            f"{str(ckpt.get('manifest_key'))[:12]} != {str(data.manifest.get('key'))[:12]}); "
            "use another --out, or --force to start over"
        )


def load_run(run_dir: str | Path) -> tuple[torch.nn.Module, dict]:
    """The trained network (eval mode) and run.json of a run folder."""
    run_dir = Path(run_dir)
    info_path, ckpt_path = run_dir / RUN_JSON, run_dir / CHECKPOINT
    if not info_path.exists() or not ckpt_path.exists():
        raise FileNotFoundError(f"{run_dir}: not a training run (needs {RUN_JSON} and "
                                f"{CHECKPOINT}; see `nhfd train`)")  # fmt: skip
    info = json.loads(info_path.read_text())
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    net = build_net(NetSpec(**ckpt["net"]))
    net.load_state_dict(ckpt["model"])
    info["step"] = int(ckpt["step"])
    return net.eval(), info


def with_overrides(options: TrainOptions, **kw) -> TrainOptions:
    """`options` with the fields in `kw` replaced, None values ignored."""
    return replace(options, **{k: v for k, v in kw.items() if v is not None})
