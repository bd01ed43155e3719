"""`nhfd bench refine`: milliseconds per `sgd` iteration, per device, at the panel's size.

The workload (issue 34's GPU figure): the configured panel, optics and coding with a window of
`--size` (default 1920 x 1080, the whole panel), a calibrated relay's pupil (Zernike terms, see
PUPIL_ZERNIKE_RAD) and `--planes` planes across the volume, fitted to a seeded band-limited
field (noise through the aperture under a smooth envelope: every target fills the band). Each
device starts from the same double-phase frame and runs `--iterations` steps of `refine`:
phase -> grey levels (straight-through) -> `BenchForward` (pupil, angular spectrum to each plane
for each colour) -> the loss -> backward -> Adam. "ms / iteration" is the median gap between
iterations after the first (which builds the kernels and FFT plans); "forward" is one
`BenchForward` call without autograd, the floor of an iteration. The baseline is the CPU,
measured in the same run; each other device's row says how far its last loss lies from the
CPU's (the same steps in float32 on other kernels), so a speed never comes without its error.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import statistics
import time
from pathlib import Path

import torch

from nhfd.benchmarks.machine import describe
from nhfd.cli.args import parse_wxh
from nhfd.config import RefineSettings, load_config
from nhfd.holo import band_limit
from nhfd.pipeline.device import resolve_device
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.refine import (
    BenchForward,
    configured_info,
    grey_phase,
    refine,
    target_from_field,
)
from nhfd.pipeline.settings import frame_settings

# The relay's pupil a calibration fits (Noll 5..11, rad at the middle colour): the bench's
# aberrations cost an extra padded FFT pair per colour per step, so the workload carries them.
PUPIL_ZERNIKE_RAD = (0.3, -0.2, 0.15, -0.1, 0.05, 0.0, 0.1)
SEED = 20261127


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("refine", help="ms per sgd iteration per device at the panel's size",
                       description=__doc__)
    p.add_argument("--size", default="1920x1080", metavar="WxH",
                   help="the window refined (default 1920x1080, the whole panel)")
    p.add_argument("--devices", default="auto", metavar="cpu,cuda[:N]",
                   help="comma list; auto (default): cpu, and cuda where torch sees one")
    p.add_argument("--iterations", type=int, default=6,
                   help="sgd iterations per device (default 6; >= 3)")
    p.add_argument("--planes", type=int, default=3, help="planes fitted (default 3)")
    p.add_argument("--subframes", type=int, default=1, help="K subframes (default 1)")
    p.add_argument("--out", default="out/bench/refine.json", help="JSON file to write")
    p.set_defaults(handler=run)


def devices(text: str) -> list[torch.device]:
    """The devices `--devices` names, the CPU first (the baseline)."""
    if text.strip().lower() == "auto":
        names = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    else:
        names = [n for n in (t.strip() for t in text.split(",")) if n]
    out = [resolve_device(n, "--devices") for n in names]
    if torch.device("cpu") not in out:
        out.insert(0, torch.device("cpu"))
    return list(dict.fromkeys(out))


def workload(window_hw: tuple[int, int], n_planes: int, device: torch.device
             ) -> tuple[Encoder, torch.Tensor, tuple[float, ...]]:
    """The encoder (configured optics with the pupil, amplitude scale fitted to the field),
    the seeded reference field `[3, h, w]` and the planes (metres)."""
    config = load_config().config
    slm = config.slm
    h, w = window_hw
    if not (1 <= h <= slm.height_px and 1 <= w <= slm.width_px):
        raise ValueError(f"--size {w}x{h}: must fit the {slm.width_px} x {slm.height_px} panel")
    info = configured_info(config.optics, slm, window_hw)
    s = dataclasses.replace(frame_settings(config, info, None), window_hw=(h, w),
                            zernike_rad=PUPIL_ZERNIKE_RAD)
    g = torch.Generator().manual_seed(SEED)
    noise = torch.polar(torch.rand((3, h, w), generator=g),
                        2 * math.pi * torch.rand((3, h, w), generator=g))
    yy = torch.linspace(-1, 1, h)[:, None]
    xx = torch.linspace(-1, 1, w)[None, :]
    envelope = torch.exp(-(xx**2 + yy**2) / 0.5)
    reference = band_limit(noise * envelope, s.aperture).to(torch.complex64)
    enc = Encoder(s, device=device)
    peak = float(enc.to_slm(reference).abs().max())
    enc = Encoder(dataclasses.replace(s, amplitude_scale=1.01 * peak), device=device)
    lo, hi = info.volume_m
    planes = tuple(lo + (hi - lo) * (i + 0.5) / n_planes for i in range(n_planes))
    return enc, reference, planes


def measure(device: torch.device, window_hw: tuple[int, int], args: argparse.Namespace
            ) -> dict[str, object]:
    """One device's row."""
    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    enc, reference, planes = workload(window_hw, args.planes, device)
    with torch.no_grad():
        grey, _ = enc.code(enc.to_slm(reference))
    target = target_from_field(reference, planes, enc)
    model = BenchForward(enc, planes)
    settings = RefineSettings(iterations=args.iterations, tolerance=0.0, seconds=3600.0,
                              subframes=args.subframes)
    t0 = time.perf_counter()
    out = refine(grey, target, model, settings)
    sync()
    total_s = time.perf_counter() - t0
    times = [t for _, t, _ in out.history]
    gaps = [b - a for a, b in itertools.pairwise(times[1:])]
    phase = grey_phase(grey, enc)[None].repeat(args.subframes, 1, 1, 1)
    forward = []
    with torch.no_grad():
        for _ in range(3):
            sync()
            t = time.perf_counter()
            model(phase)
            sync()
            forward.append(time.perf_counter() - t)
    r = enc.region
    return {
        "device": str(device),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "window_hw": list(window_hw), "region_hw": [r.height, r.width],
        "planes": len(planes), "subframes": args.subframes, "iterations": len(out.history),
        "ms_per_iteration": 1e3 * statistics.median(gaps),
        "forward_ms": 1e3 * statistics.median(forward),
        "first_iteration_s": times[1] if len(times) > 1 else total_s, "total_s": total_s,
        "start_psnr_db": out.report.start_psnr_db, "psnr_db": out.report.psnr_db,
        "loss": out.report.loss,
    }


def run(args: argparse.Namespace) -> int:
    w, h = parse_wxh(args.size, "--size")
    if args.iterations < 3:
        raise ValueError(f"--iterations {args.iterations}: must be >= 3 (the first builds "
                         f"kernels; the median gap needs two after it)")
    if not 1 <= args.planes <= 16 or not 1 <= args.subframes <= 16:
        raise ValueError(f"--planes {args.planes}, --subframes {args.subframes}: each 1..16")
    machine = describe()
    print(f"refine at {w} x {h}, {args.planes} planes, K = {args.subframes}; {machine}")
    rows = []
    for device in devices(args.devices):
        row = measure(device, (h, w), args)
        if rows:
            row["psnr_db_minus_cpu"] = row["psnr_db"] - rows[0]["psnr_db"]  # type: ignore[operator]
            row["speedup_vs_cpu"] = rows[0]["ms_per_iteration"] / row["ms_per_iteration"]  # type: ignore[operator]
        rows.append(row)
        print(f"  {row['device']}{' (' + str(row['gpu']) + ')' if row['gpu'] else ''}: region "
              f"{row['region_hw'][0]} x {row['region_hw'][1]}: "  # type: ignore[index]
              f"{row['ms_per_iteration']:.1f} ms / iteration (forward {row['forward_ms']:.1f} "
              f"ms; first {row['first_iteration_s']:.2f} s); PSNR {row['start_psnr_db']:.2f} -> "
              f"{row['psnr_db']:.2f} dB in {row['iterations']} iterations"
              + (f"; {row['speedup_vs_cpu']:.1f}x the CPU, PSNR {row['psnr_db_minus_cpu']:+.3f} "
                 f"dB from it" if "speedup_vs_cpu" in row else ""), flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"size": [w, h], "rows": rows, "machine": machine}, indent=2))
    print(f"wrote {out}")
    return 0
