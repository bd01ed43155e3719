"""Measurements `scripts/gpu_check.sh` takes on a GPU beside nhfd's own benches (issue 35).

    python scripts/gpu_probe.py env               what the machine has (JSON)
    python scripts/gpu_probe.py gsplat            gsplat imports, says whence, renders on CUDA
    python scripts/gpu_probe.py net  [--views N]  the network in torch, one variant per row
    python scripts/gpu_probe.py frame [--views N] one device frame's stages and top kernels
    python scripts/gpu_probe.py train RUN         steps per second from RUN/train_log.csv
    python scripts/gpu_probe.py trainprof DATA [--views N]  N training steps under the profiler

Each prints a human summary and writes one JSON object to `--json` (default stdout only). The
`net` variants are the knobs issue 35 names before any is built into the frame path: TF32,
cudnn.benchmark, float16 and bfloat16 weights, channels-last, a CUDA graph. Each row says how
far its outputs are from float32 (TF32 off) on one seeded input, so a speed is never quoted
without the error it costs. Not part of the package: a tool for the GPU check, like the
Makefile.
"""

from __future__ import annotations

import argparse
import copy
import csv
import json
import math
import os
import platform
import sys
import time
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "models" / "nhf-donut-512.onnx"
SCENE = REPO / "models" / "scenes" / "donut.ply"
SIZES_WH = ((1024, 576), (1920, 1080))


def _dump(obj: dict[str, Any], path: str | None) -> None:
    text = json.dumps(obj, indent=1, default=str)
    if path:
        Path(path).write_text(text)
    print(text if not path else f"wrote {path}")


def cmd_env(args: argparse.Namespace) -> dict[str, Any]:
    import onnxruntime as ort

    info: dict[str, Any] = {
        "python": sys.version.split()[0], "platform": platform.platform(),
        "cpus": os.cpu_count(), "torch": torch.__version__, "torch_cuda": torch.version.cuda,
        "cudnn": torch.backends.cudnn.version() if torch.backends.cudnn.is_available() else None,
        "onnxruntime": ort.__version__, "onnx_providers": ort.get_available_providers(),
        "numpy": np.__version__, "cuda_available": torch.cuda.is_available(),
    }
    try:
        import numba

        info["numba"] = numba.__version__
    except ImportError as exc:
        info["numba"] = f"absent: {exc}"
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info |= {"gpu": p.name, "capability": f"{p.major}.{p.minor}",
                 "gpu_memory_gib": round(p.total_memory / 2**30, 1),
                 "multiprocessors": p.multi_processor_count,
                 "bf16": torch.cuda.is_bf16_supported()}
    return info


def cmd_gsplat(args: argparse.Namespace) -> dict[str, Any]:
    """Import gsplat's CUDA extension (the carried build or a JIT compile, timed) and render
    one splat on the GPU, checked against the CPU rasteriser."""
    t0 = time.perf_counter()
    import gsplat
    from gsplat.cuda import _backend

    import_s = time.perf_counter() - t0
    if _backend._C is None:
        raise RuntimeError("gsplat imported without its CUDA extension")
    whence = "prebuilt gsplat.csrc" if _backend._C.__name__ == "gsplat.csrc" else "JIT build"
    from nhfd.scene.cameras import Camera, intrinsics_from_fov, look_at
    from nhfd.scene.gaussians import make_gaussians
    from nhfd.scene.raster import render

    rng = np.random.default_rng(5)
    g = make_gaussians(rng.uniform(-0.5, 0.5, (200, 3)), rng.normal(size=(200, 4)),
                       np.full((200, 3), 0.05), rng.uniform(0.2, 0.9, 200),
                       rng.normal(0, 0.3, (200, 1, 3)))
    r, t = look_at(np.array([0.0, 0.0, -3.0]), np.zeros(3), "+y")
    fx, fy, cx, cy = intrinsics_from_fov(128, 96, 50.0)
    cam = Camera(r, t, fx, fy, cx, cy, 128, 96, near=0.05)
    t1 = time.perf_counter()
    gpu = render(g, cam, backend="gsplat")
    first_render_s = time.perf_counter() - t1
    cpu = render(g, cam, backend="cpu")
    mse = float(np.mean((gpu.rgb.astype(np.float64) - cpu.rgb) ** 2))
    psnr = math.inf if mse == 0 else 10 * math.log10(1 / mse)
    out = {"gsplat": gsplat.__version__, "extension": whence, "extension_file":
           getattr(_backend._C, "__file__", None), "import_s": round(import_s, 2),
           "first_render_s": round(first_render_s, 3), "rgb_psnr_vs_cpu_db": round(psnr, 1)}
    print(f"gsplat {gsplat.__version__}: {whence}, imported in {import_s:.1f} s; one render "
          f"against the CPU rasteriser: {psnr:.1f} dB")
    return out


# --- the network in torch ----------------------------------------------------------------------


def _times_ms(fn, iters: int, dev: torch.device) -> list[float]:
    """Milliseconds per call: CUDA events on a GPU (the host is not waited for between the
    two), the wall clock elsewhere."""
    out = []
    for _ in range(iters):
        if dev.type != "cuda":
            t0 = time.perf_counter()
            fn()
            out.append((time.perf_counter() - t0) * 1e3)
            continue
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn()
        b.record()
        b.synchronize()
        out.append(a.elapsed_time(b))
    return out


def _padded(h: int, w: int, m: int) -> tuple[int, int]:
    return -(-h // m) * m, -(-w // m) * m


def cmd_net(args: argparse.Namespace) -> dict[str, Any]:
    from nhfd.models.torch_model import TorchModel

    dev = torch.device(args.device)
    base = TorchModel(MODEL, device=dev)
    module = base.module.eval()
    rows = []
    for w, h in args.sizes:
        ph, pw = _padded(h, w, base.multiple)
        x32 = torch.rand(1, base.channels, ph, pw, generator=torch.Generator().manual_seed(11)
                         ).to(dev)
        torch.backends.cudnn.allow_tf32 = False
        torch.backends.cudnn.benchmark = False
        with torch.no_grad():
            ref_a, ref_p = (t.float() for t in module(x32))

        def variant(name: str, net: torch.nn.Module, x: torch.Tensor, *, tf32: bool,
                    bench: bool, autocast: torch.dtype | None = None, graph: bool = False,
                    w: int = w, h: int = h, ref_a: torch.Tensor = ref_a,
                    ref_p: torch.Tensor = ref_p) -> None:
            torch.backends.cudnn.allow_tf32 = tf32
            torch.backends.cudnn.benchmark = bench

            def run() -> tuple[torch.Tensor, torch.Tensor]:
                with torch.no_grad(), torch.autocast(dev.type, dtype=autocast or torch.float16,
                                                      enabled=autocast is not None):
                    return net(x)

            if graph and dev.type != "cuda":
                return
            try:
                for _ in range(5):
                    run()
                if dev.type == "cuda":
                    torch.cuda.synchronize()
                call = run
                if graph:
                    g = torch.cuda.CUDAGraph()
                    s = torch.cuda.Stream()
                    s.wait_stream(torch.cuda.current_stream())
                    with torch.cuda.stream(s):
                        run()
                    torch.cuda.current_stream().wait_stream(s)
                    with torch.cuda.graph(g):
                        static = run()

                    def call() -> tuple[torch.Tensor, torch.Tensor]:
                        g.replay()
                        return static
                ms = _times_ms(call, args.views, dev)
                a, p = (t.float() for t in call())
                err_a = float((a - ref_a).abs().max() / ref_a.abs().max())
                dp = torch.remainder(p - ref_p + math.pi, 2 * math.pi) - math.pi
                err_p = float(dp.abs().max())
                row = {"size_wh": [w, h], "variant": name, "median_ms": float(np.median(ms)),
                       "p99_ms": float(np.percentile(ms, 99)), "amp_rel_err": err_a,
                       "phase_err_rad": err_p, "finite": bool(torch.isfinite(a).all()
                                                              and torch.isfinite(p).all())}
            except Exception as exc:  # a variant that fails is a finding, not the end
                row = {"size_wh": [w, h], "variant": name, "error": f"{type(exc).__name__}: {exc}"}
            rows.append(row)
            print(json.dumps(row))

        # Whole-module .half() does not run: ServingNet builds float32 constants inside
        # (rehearsed on the CPU), so float16 is measured as autocast.
        cl = copy.deepcopy(module).to(memory_format=torch.channels_last)
        xcl = x32.contiguous(memory_format=torch.channels_last)
        f16, b16 = torch.float16, torch.bfloat16
        variant("fp32, TF32 off", module, x32, tf32=False, bench=False)
        variant("fp32, TF32 (torch default)", module, x32, tf32=True, bench=False)
        variant("fp32, TF32, cudnn.benchmark", module, x32, tf32=True, bench=True)
        variant("fp32 channels-last, TF32, benchmark", cl, xcl, tf32=True, bench=True)
        variant("fp32, TF32, benchmark, CUDA graph", module, x32, tf32=True, bench=True,
                graph=True)
        variant("bf16 autocast, benchmark", module, x32, tf32=True, bench=True, autocast=b16)
        variant("fp16 autocast, benchmark", module, x32, tf32=True, bench=True, autocast=f16)
        variant("fp16 autocast channels-last, benchmark", cl, xcl, tf32=True, bench=True,
                autocast=f16)
        variant("fp16 autocast channels-last, benchmark, CUDA graph", cl, xcl, tf32=True,
                bench=True, autocast=f16, graph=True)
        variant("bf16 autocast channels-last, benchmark, CUDA graph", cl, xcl, tf32=True,
                bench=True, autocast=b16, graph=True)
    torch.backends.cudnn.allow_tf32 = True
    torch.backends.cudnn.benchmark = False
    return {"model": MODEL.name, "channels": base.channels, "multiple": base.multiple,
            "device": _device_name(dev), "iters": args.views, "rows": rows}


def _device_name(dev: torch.device) -> str:
    return torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor()


# --- one device frame, profiled ----------------------------------------------------------------


def _frame_parts(w: int, h: int, device: str) -> dict[str, Any]:
    from nhfd.calibration import active_calibration
    from nhfd.config import Config, _overlay, default_text
    from nhfd.pipeline.encoder import Encoder
    from nhfd.pipeline.settings import frame_settings
    from nhfd.pipeline.view import Scene, scene_frame
    from nhfd.pipeline.worker import open_model
    from nhfd.scene.io import read_scene
    from nhfd.views import Orbit, View

    config = Config.model_validate(_overlay(tomllib.loads(default_text()), {
        "daemon": {"frames": {"size_px": [w, h], "device": device}}}))
    model = open_model(str(MODEL), config, 2)
    load = read_scene(SCENE)
    scene = Scene(load.gaussians, scene_frame(load.gaussians, str(SCENE)))
    env = model.info.pose_envelope
    view = View(Orbit(float(np.mean(env.azimuth_deg)), float(np.mean(env.elevation_deg)),
                      float(np.mean(env.distance))), refocus_mm=0.0)
    settings = frame_settings(config, model.info, active_calibration(config))
    return {"model": model, "scene": scene, "view": view,
            "encoder": Encoder(settings, device=device),
            "graphed": Encoder(settings, device=device, cuda_graphs=True)}


def _panel_paste_ms(grey_hwc: np.ndarray, zero: np.ndarray, iters: int = 30) -> dict[str, float]:
    """The daemon's output stage on this host: the region pasted into the panel from the
    SLM's [h, w, 3] layout (a device frame's) and from a channel-first copy (the CPU path's)."""
    from nhfd.daemon.frame_link import PanelBuffer

    buffer = PanelBuffer(zero)
    grey = grey_hwc.transpose(2, 0, 1)
    planar = np.ascontiguousarray(grey)
    out = {}
    for name, g in (("interleaved", grey), ("planar", planar)):
        times = []
        for _ in range(iters):
            t0 = time.perf_counter()
            buffer.frame(0, 0, g)
            times.append((time.perf_counter() - t0) * 1e3)
        out[f"paste_{name}_median_ms"] = float(np.median(times))
    return out


def cmd_frame(args: argparse.Namespace) -> dict[str, Any]:
    from torch.profiler import ProfilerActivity, profile

    from nhfd.pipeline.frame import compute_frame

    dev = torch.device(args.device)
    out: dict[str, Any] = {"device": _device_name(dev), "sizes": []}
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    for w, h in args.sizes:
        p = _frame_parts(w, h, args.device)
        entry: dict[str, Any] = {"size_wh": [w, h], "frames": args.views}
        # Eager and graphed in turns, frame by frame: the same card, the same load.
        walls: dict[str, list[float]] = {"eager": [], "graphs": []}
        stages: dict[str, dict[str, list[float]]] = {"eager": {}, "graphs": {}}
        for _ in range(5):
            for enc in (p["encoder"], p["graphed"]):
                f = compute_frame(p["view"], p["scene"], p["model"], enc)
        for _ in range(args.views):
            for name, enc in (("eager", p["encoder"]), ("graphs", p["graphed"])):
                t0 = time.perf_counter()
                f = compute_frame(p["view"], p["scene"], p["model"], enc)
                walls[name].append((time.perf_counter() - t0) * 1e3)
                for k, v in f.timings_s.items():
                    stages[name].setdefault(k, []).append(v * 1e3)
        for name in walls:
            entry[name] = {"wall_median_ms": float(np.median(walls[name])),
                           "wall_p99_ms": float(np.percentile(walls[name], 99)),
                           "stage_median_ms": {k: float(np.median(v))
                                               for k, v in stages[name].items()}}
            print(f"{w} x {h} on {args.device}, {name}: compute_frame wall median "
                  f"{entry[name]['wall_median_ms']:.2f} ms, p99 "
                  f"{entry[name]['wall_p99_ms']:.2f}; stages "
                  + ", ".join(f"{k} {v:.2f}" for k, v in entry[name]["stage_median_ms"].items()))
        entry["graph_failures"] = dict(p["graphed"].graphs.failed)
        entry.update(_panel_paste_ms(f.grey.transpose(1, 2, 0), p["encoder"].zero))
        print(f"  output paste: interleaved {entry['paste_interleaved_median_ms']:.2f} ms, "
              f"planar {entry['paste_planar_median_ms']:.2f} ms; graph failures: "
              f"{entry['graph_failures'] or 'none'}")
        with profile(activities=activities) as prof:
            for _ in range(5):
                compute_frame(p["view"], p["scene"], p["model"], p["graphed"])
        entry["profile_top_kernels_5_graphed_frames"] = prof.key_averages().table(
            sort_by="cuda_time_total" if dev.type == "cuda" else "cpu_time_total", row_limit=25,
            max_name_column_width=60)
        print(entry["profile_top_kernels_5_graphed_frames"])
        out["sizes"].append(entry)
    return out


def cmd_train(args: argparse.Namespace) -> dict[str, Any]:
    with open(Path(args.run) / "train_log.csv") as f:
        rows = list(csv.DictReader(f))
    secs = [float(r["seconds"]) for r in rows]
    steady = secs[min(10, len(secs) // 2):]  # the first steps build cuDNN plans and caches
    run = json.loads((Path(args.run) / "run.json").read_text())
    out = {"steps": len(secs), "median_step_s": float(np.median(steady)),
           "steps_per_s": 1.0 / float(np.median(steady)), "first_step_s": secs[0],
           "run": {k: run.get(k) for k in ("device", "amp", "batch", "crop", "net", "options")
                   if k in run}}
    print(f"{len(secs)} steps: median {out['median_step_s'] * 1e3:.1f} ms per step "
          f"({out['steps_per_s']:.1f} steps/s) after the first {min(10, len(secs) // 2)}")
    return out


def cmd_trainprof(args: argparse.Namespace) -> dict[str, Any]:
    """`--views` training steps of the default recipe on DATA under torch.profiler: the wall
    time in each named part of a step (`train.crop`, `.forward`, `.loss`, `.backward_step`,
    `.log`, whose read of the loss waits for the device, `.validate`, `.checkpoint`), the
    device's busy time, and the top kernels: whether a step is bound by the GPU or by the
    host's launches and copies (what a graphed or compiled step would remove)."""
    import tempfile

    from torch.profiler import ProfilerActivity, profile

    from nhfd.config import load_config
    from nhfd.models.train import TrainOptions, train

    dev = torch.device(args.device)
    options = TrainOptions.from_config(load_config().config.model, device=str(dev),
                                       steps=args.views, checkpoint_every=10**6)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with tempfile.TemporaryDirectory() as run:
        train(args.run, run, replace(options, steps=10), log=lambda _m: None)  # warm-up
        t0 = time.perf_counter()
        with profile(activities=activities) as prof:
            result = train(args.run, run, options, log=lambda _m: None)
        wall_s = time.perf_counter() - t0
    events = prof.key_averages()
    parts = {e.key: {"calls": e.count, "cpu_ms": e.cpu_time_total / 1e3,
                     "device_ms": getattr(e, "device_time_total", 0.0) / 1e3}
             for e in events if e.key.startswith("train.")}
    kernels = [e for e in events if getattr(e, "self_device_time_total", 0.0) > 0]
    busy_ms = sum(e.self_device_time_total for e in kernels) / 1e3
    steps = args.views - 10
    out = {"device": _device_name(dev), "steps_profiled": steps, "wall_s": wall_s,
           "wall_ms_per_step": 1e3 * wall_s / steps, "device_busy_ms_per_step": busy_ms / steps,
           "parts_ms_per_step": {k: {kk: (v / steps if kk != "calls" else v)
                                     for kk, v in d.items()} for k, d in parts.items()},
           "seconds_per_step_reported": result.seconds_per_step,
           "options": {k: getattr(options, k) for k in ("amp", "batch", "crop_width_px",
                                                        "crop_height_px", "steps")
                       if hasattr(options, k)},
           "top": events.table(sort_by="self_cuda_time_total" if dev.type == "cuda"
                               else "self_cpu_time_total", row_limit=25,
                               max_name_column_width=60)}
    print(f"{steps} steps on {out['device']}: {out['wall_ms_per_step']:.1f} ms a step under the "
          f"profiler, the device busy {out['device_busy_ms_per_step']:.1f} ms of it")
    for k, d in out["parts_ms_per_step"].items():
        print(f"  {k}: {d['cpu_ms']:.2f} ms host, {d['device_ms']:.2f} ms device per step "
              f"({d['calls']} calls)")
    print(out["top"])
    return out


def _size(text: str) -> tuple[int, int]:
    w, h = (int(v) for v in text.lower().split("x"))
    return w, h


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("env", "gsplat", "net", "frame", "train", "trainprof"))
    ap.add_argument("run", nargs="?", help="train: the run folder; trainprof: a dataset")
    ap.add_argument("--views", type=int, default=50, help="timed repetitions")
    ap.add_argument("--json", help="write the result here")
    ap.add_argument("--device", default="cuda:0",
                    help="net, frame, trainprof: where (cpu to rehearse)")
    ap.add_argument("--sizes", type=_size, nargs="+", default=list(SIZES_WH),
                    help="net, frame: frame sizes WxH (default 1024x576 1920x1080)")
    args = ap.parse_args(argv)
    result = {"env": cmd_env, "gsplat": cmd_gsplat, "net": cmd_net, "frame": cmd_frame,
              "train": cmd_train, "trainprof": cmd_trainprof}[args.what](args)
    _dump(result, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
