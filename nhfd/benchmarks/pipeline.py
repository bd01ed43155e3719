"""`nhfd bench pipeline`: view-change-to-SLM latency, split into render, inference, propagation,
coding and output, through the daemon's own frame worker (a spawned process with 2 threads).

For each model given (the shipped 512 x 288 one by default; add a 1024 x 576 model with another
--model), the views move along an orbit inside the model's pose envelope, one request at a time:
the clock runs from sending the view to the worker until the full panel frame has been shown on a
simulated SLM (the daemon's path, IPC included). The first views warm the caches (numba, kernels)
and are not counted. The frame cache is off: every view is computed.

--transport shm,pickle measures both ways frames cross from the worker in one run (shared-memory
slots, the default, or the arrays pickled through the pipe), and --int8 never,auto the float model
and the int8 sibling the daemon would serve (`daemon.frames.int8`); each combination in its own
worker, all given the same views in turn (a loaded machine loads them alike). --device cpu,cuda adds
the device the same way (each result records the device its worker computed on, and the GPU's name),
and --frame-size-px W H, repeated, measures each window size in turn. The panel's refresh
pacing is off here (slm.refresh_hz at its maximum): the figure is the pipeline's, not the
panel's.

--quality network,sgd compares new views arriving while the previous one is refined: each
measured view follows the same pose asked for at the variant's tier (`set_view`'s quality),
shown and then left to rest a seeded random time in --rest-ms MIN,MAX (the same draws for every
variant) while the worker refines it, so the measured view (open loop) arrives at a random point
of a refinement step. The sgd row is then the time from a new view to its frame while a
refinement ran, the network row the same with nothing running (issue 34: at most one frame
period apart). Each variant's refinement ends with its measured view, so none runs while
another variant is measured. A refinement begins with the view's light-field inversion (2 to 3
s at 512 x 288 on 2 cores) and only then steps: rests longer than that put the new view in a
step; each row records the iterations the worker had reported (`refine.swap_every`).

--side-by-side measures the --model files the same way, one worker each given the same views in
turn, instead of one after another (each in turn, on a machine whose load drifts, gave a tuned
model 0.84 to 1.16 times its source's median in two runs); each result then also gives its median
over the first model's (`median_vs_first`). The models' frame windows must be the same.

After the results, one markdown table (one row per result, also written as <json stem>.md beside
the JSON) under a line naming the machine: the form the README quotes.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, NamedTuple

import numpy as np
import onnxruntime as ort
import torch

from nhfd import __version__
from nhfd.benchmarks.machine import describe
from nhfd.calibration import CalibrationStore
from nhfd.config import (
    DEVICES,
    FRAME_TRANSPORTS,
    INFERENCES,
    INT8_MODES,
    REFRESH_HZ_MAX,
    Config,
    FramesSettings,
    SLMSettings,
    _overlay,
    load_config,
)
from nhfd.daemon.frame_link import WORKER_MODULE, FrameEvents, FrameLink
from nhfd.daemon.panel import Panel
from nhfd.daemon.views import ViewSlot
from nhfd.drivers.slm import SimulatedSLM
from nhfd.model_info import ModelInfo
from nhfd.models.export import OnnxModel
from nhfd.pipeline.device import check_cuda_frames, gpu_name, resolve_device
from nhfd.pipeline.settings import frame_window_hw
from nhfd.views import QUALITY_TIERS, Orbit, View

# The stages status reports, in order: the frame pipeline's four (`nhfd.pipeline.frame`), then
# the daemon's output (the region pasted into the panel and shown).
STAGES = ("render", "inference", "propagation", "coding", "output")
DEFAULT_MODEL = "models/nhf-donut-512.onnx"
# The rests' seed (--rest-ms): fixed, so every variant and every run rests alike.
REST_SEED = 20261127


class Variant(NamedTuple):
    """One worker's settings in a side-by-side run (None: the configuration's)."""

    transport: str | None = None  # daemon.frames.transport
    int8: str | None = None  # daemon.frames.int8
    device: str | None = None  # daemon.frames.device
    inference: str | None = None  # daemon.frames.inference
    cuda_graphs: bool | None = None  # daemon.frames.cuda_graphs
    quality: str | None = None  # the tier each view asks for (None: network)
    model: str | None = None  # the model file this worker serves (None: the measured model)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("pipeline", help="view-change-to-SLM latency per stage",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", action="append", default=None,
                   help="exported model (repeatable; default models/nhf-donut-512.onnx)")
    p.add_argument("--scene", default="models/scenes/donut.ply")
    p.add_argument("--config", help="configuration file (default: the search order)")
    p.add_argument("--views", type=int, default=12, help="views measured per model")
    p.add_argument("--warmup", type=int, default=3, help="views not counted")
    p.add_argument("--json", default="out/bench/pipeline.json", help="JSON results file")
    p.add_argument("--device", help="comma list of devices to compare, each auto, cpu, cuda or "
                   "cuda:N (default: daemon.frames.device)")
    p.add_argument("--frame-size-px", type=int, nargs=2, metavar=("W", "H"), action="append",
                   help="hologram window (daemon.frames.size_px), repeatable: each size measured "
                        "in turn (default: the configuration's)")
    p.add_argument("--transport", default="shm",
                   help=f"comma list of frame transports to compare: {', '.join(FRAME_TRANSPORTS)} "
                        "(default shm)")
    p.add_argument("--int8", default=None,
                   help="comma list of daemon.frames.int8 settings to compare: "
                        f"{', '.join(INT8_MODES)} (default: the configuration's)")
    p.add_argument("--inference", default=None,
                   help=f"comma list of what runs the network, to compare: "
                        f"{', '.join(INFERENCES)} (daemon.frames.inference; default: the "
                        "configuration's)")
    p.add_argument("--cuda-graphs", default=None,
                   help="comma list of on, off: daemon.frames.cuda_graphs to compare on a CUDA "
                        "device (default: the configuration's)")
    p.add_argument("--quality", default=None,
                   help=f"comma list of tiers the views ask for, to compare: "
                        f"{', '.join(QUALITY_TIERS)} (default network)")
    p.add_argument("--side-by-side", action="store_true",
                   help="measure the --model files side by side, one worker each, given the "
                        "same views in turn, instead of one after another: their medians "
                        "compare on a loaded machine (a tuned model against its source); "
                        "each row also gives its median over the first model's")
    p.add_argument("--rest-ms", default="0,400", metavar="MIN,MAX",
                   help="with --quality: each view rests a seeded random time in this range "
                        "while it is refined (ms, 0 to 60000; default 0,400)")
    p.set_defaults(handler=run)


class _Host:
    """The slice of the daemon a FrameLink needs: the view slot, the panel on a simulated SLM,
    the error list its events feed (`frame_link`).

    `config`: the whole configuration, handed to the daemon's `Panel` and `FrameLink` (which
    take it whole: the worker runs under all of it); the simulated SLM is `[slm]`'s size."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.views = ViewSlot()
        self.slm = SimulatedSLM(config.slm.width_px, config.slm.height_px).open()
        self.errors: list[str] = []
        self.calibration = CalibrationStore.of(config)
        self.panel = Panel(config, SimpleNamespace(slm=self.slm, errors={"slm": None}),
                           self.calibration)

    def error(self, source: str, message: str) -> None:
        self.errors.append(f"{source}: {message}")

    def frame_link(self, worker_module: str = WORKER_MODULE) -> FrameLink:
        """A frame link on this host: shown views marked applied, errors, a crash (no lasers
        here to switch off) and a lost SLM output all into `errors`."""
        return FrameLink(self.config, self.calibration, self.views, lambda: self.panel, FrameEvents(
            shown=self.views.mark_applied, error=self.error,
            crashed=lambda message: self.error("frame worker", message),
            slm_lost=lambda detail: self.error("slm", detail)), worker_module)


def _load(link: Any, scene: Path, model: Path) -> None:
    """Load the scene and the model through the worker, as the daemon does; a refused file is a
    ValueError with the worker's message (the one a daemon's load job fails with)."""
    failed: list[BaseException] = []

    def loads() -> None:
        try:
            link.load_scene(str(scene.resolve()))
            link.load_model(str(model.resolve()))
        except Exception as exc:  # re-raised on the stepping thread, not printed here
            failed.append(exc)

    thread = threading.Thread(target=loads)
    thread.start()
    while thread.is_alive():  # loads wait for the control loop (here: this thread) to answer
        link.step()
        time.sleep(0.01)
    if failed:
        raise ValueError(str(failed[0])) from None


def measure(config: Config, model: Path, scene: Path, views: int, warmup: int, *,
            transport: str | None = None, int8: str | None = None,
            device: str | None = None) -> dict[str, Any]:
    """One model under one transport, int8 setting and device (`measure_side_by_side` of one).
    `config`: as `measure_side_by_side`'s."""
    return measure_side_by_side(config, model, scene, views, warmup,
                                [Variant(transport, int8, device)])[0]


def measure_side_by_side(config: Config, model: Path, scene: Path, views: int, warmup: int,
                         variants: list[tuple[str | None, ...]],
                         rest_ms: tuple[float, float] = (0.0, 0.0)) -> list[dict[str, Any]]:
    """`model` under each `Variant` (transport, daemon.frames.int8[, daemon.frames.device]; None:
    the configuration's) of `variants`, each in its own worker, all started first and then given the
    same views in turn, one frame at a time (the order rotating per view): on a loaded machine
    the variants see the same load and their medians compare. A variant with a `quality` is
    shown each view at that tier first, then rests a seeded random time in `rest_ms` (one
    draw per view, the same for every variant; the link stepped as the daemon's loop does, so
    refined frames are shown), and the view asked again open loop is the one measured.

    `config`: the whole configuration, because each worker runs under all of it (the frame
    pipeline joins `[daemon]`, `[slm]`, `[optics]`, `[coding]` and `[calibration]`), with the
    variant's `[daemon.frames]` settings and `[slm]` refresh on top (`_variant_config`)."""
    variants = [Variant(*v) for v in variants]
    configs = [_variant_config(config, v) for v in variants]
    files = [Path(v.model) if v.model else model for v in variants]
    infos = {f: OnnxModel(f).info for f in {model, *files}}  # each file read once
    info = infos[model]
    rests_s = np.random.default_rng(REST_SEED).uniform(rest_ms[0] * 1e-3, rest_ms[1] * 1e-3,
                                                        warmup + views)
    # before any worker starts: each window fits the panel, and (side by side) they agree
    windows = {f: _window_that_fits(cfg.daemon.frames, cfg.slm, f, infos[f])
               for cfg, f in zip(configs, files, strict=True)}
    if len(set(windows.values())) > 1:
        raise ValueError("--side-by-side: the models' frame windows differ ("
                         + ", ".join(f"{f}: {w} x {h}" for f, (h, w) in windows.items())
                         + "): the same views must make the same frames' work; set "
                           "--frame-size-px W H")
    runs = []
    try:
        for cfg in configs:
            host = _Host(cfg)
            link = host.frame_link()
            runs.append((cfg, host, link, []))
            link.ensure_started()  # the workers' imports overlap; loads follow one by one
        for (_cfg, _host, link, _rows), f in zip(runs, files, strict=True):
            _load(link, scene, f)
        for i, view in enumerate(_orbit(info, warmup + views)):
            for k in range(len(runs)):
                _cfg, host, link, rows = runs[(i + k) % len(runs)]
                quality = variants[(i + k) % len(runs)].quality
                refined = 0
                if quality:  # the view at its tier, refined while it rests; then a new view
                    _show(host, link, view.with_quality(quality))
                    _rest(link, host, float(rests_s[i]))
                    report = link.refinement.report if link.refinement is not None else {}
                    refined = int(report.get("iterations") or 0)
                total_ms = _show(host, link, view)
                if i >= warmup:
                    t = link.timings or {}
                    rows.append({**{s: t[f"{s}_ms"] for s in STAGES}, "total": total_ms,
                                 "azimuth_deg": view.camera.azimuth_deg,  # type: ignore[union-attr]
                                 "refined_iterations": refined})
        reports = [link.model.to_json() if link.model else {}
                   for _cfg, _host, link, _rows in runs]
    finally:
        for _cfg, _host, link, _rows in runs:
            link.close()
    return [{**_result(f, infos[f], cfg.daemon.frames, rows, report),
             "quality": v.quality or "network", "rest_ms": list(rest_ms)}
            for (cfg, _host, _link, rows), report, v, f in zip(runs, reports, variants, files,
                                                               strict=True)]


def _variant_config(config: Config, v: Variant) -> Config:
    """The configuration one worker runs under: the variant's settings, no frame cache (every
    view computed) and no refresh pacing (the bench times the pipeline, not the panel)."""
    frames: dict[str, Any] = {"cache_frames": 0}  # [daemon.frames]
    if v.transport is not None:
        frames["transport"] = v.transport
    if v.int8 is not None:
        frames["int8"] = v.int8
    if v.device is not None:
        frames["device"] = v.device
    if v.inference is not None:
        frames["inference"] = v.inference
    if v.cuda_graphs is not None:
        frames["cuda_graphs"] = v.cuda_graphs
    overlay = {"daemon": {"frames": frames}, "slm": {"refresh_hz": REFRESH_HZ_MAX}}
    return Config.model_validate(_overlay(config.model_dump(), overlay))


def _window_that_fits(frames: FramesSettings, slm: SLMSettings, model: Path, info: ModelInfo
                      ) -> tuple[int, int]:
    """The frame window (h, w) a worker for `model` would run, or a ValueError naming the model
    when it is larger than the panel, before a worker starts for it (the configuration checked
    daemon.frames.size_px; `frame_window_hw` checks the model's training size that stands in
    for an empty one)."""
    try:
        return frame_window_hw(frames, slm, info)
    except ValueError as exc:
        raise ValueError(f"{model}: {exc}") from None


def _orbit(info: ModelInfo, n: int) -> list[View]:
    """`n` views along the azimuth of the model's pose envelope, at its middle elevation and
    distance (a range the envelope lacks: azimuth [-20, 20] deg, elevation 20 deg, distance 2
    scene units)."""
    env = info.pose_envelope
    az = (env and env.azimuth_deg) or (-20.0, 20.0)
    el = (env and env.elevation_deg) or (20.0, 20.0)
    dist = (env and env.distance) or (2.0, 2.0)
    return [View(Orbit(float(a), 0.5 * (el[0] + el[1]), 0.5 * (dist[0] + dist[1])), 0.0)
            for a in np.linspace(az[0], az[1], n)]


def _show(host: _Host, link: Any, view: View) -> float:
    """Milliseconds from sending `view` to its frame shown on the simulated SLM."""
    seq = host.views.submit(view)
    t0 = time.perf_counter()
    while link.shown_seq < seq:
        link.step()
        if host.errors:
            raise RuntimeError(host.errors[-1])
        time.sleep(0.0005)
    return (time.perf_counter() - t0) * 1e3


def _rest(link: Any, host: _Host, seconds: float) -> None:
    """Step the link for `seconds` as the daemon's loop would (refined frames are shown)."""
    deadline = time.perf_counter() + seconds
    while time.perf_counter() < deadline:
        link.step()
        if host.errors:
            raise RuntimeError(host.errors[-1])
        time.sleep(0.001)


def _result(model: Path, model_info: ModelInfo, frames: FramesSettings,
            rows: list[dict[str, float]], info: dict[str, Any]) -> dict[str, Any]:
    """One worker's figures, with what it served and the device it computed on (its model
    status: `device`, `device_reason`); `frames`: the `[daemon.frames]` it ran under."""
    h, w = model_info.train_size_hw
    summary = {k: {"median_ms": float(np.median([r[k] for r in rows])),
                   "p90_ms": float(np.percentile([r[k] for r in rows], 90)),
                   "p99_ms": float(np.percentile([r[k] for r in rows], 99))}
               for k in (*STAGES, "total")}
    device = info.get("device")
    return {"model": str(model), "profile": model_info.profile,
            "size_wh": list(frames.size_px) or [w, h],
            "transport": frames.transport, "int8": frames.int8,
            "worker_threads": frames.worker_threads,
            "device_setting": frames.device, "device": device, "cuda_graphs": frames.cuda_graphs,
            "device_reason": info.get("device_reason"), "gpu": _gpu(device),
            "onnx_providers": info.get("providers"), "inference": info.get("inference"),
            "inference_reason": info.get("inference_reason"),
            "served": info.get("served", str(model)), "variant": info.get("variant"),
            "variant_reason": info.get("variant_reason"),
            "views": len(rows), "stages": summary,
            "after_render_median_ms": float(np.median([r["total"] - r["render"] for r in rows])),
            "ipc_and_wait_median_ms": float(np.median(
                [r["total"] - sum(r[k] for k in STAGES) for r in rows])),
            "rows": rows}


def _gpu(device: str | None) -> str | None:
    """The GPU's name for a CUDA device the worker reported, None for the CPU."""
    if not device or not device.startswith("cuda") or not torch.cuda.is_available():
        return None
    return gpu_name(torch.device(device))


def run(args: argparse.Namespace) -> int:
    # load_config applies the cross-field rules: a frame larger than the panel is a
    # ConfigError (exit 2) before any worker starts.
    config = load_config(args.config).config
    # Every choice is checked here, before any worker starts: a clean error, not a late one.
    devices = _devices(args.device) if getattr(args, "device", None) else [None]
    transports = _choices("--transport", args.transport, FRAME_TRANSPORTS)
    int8s = _choices("--int8", args.int8, INT8_MODES) if args.int8 else [None]
    inferences = (_choices("--inference", args.inference, INFERENCES)
                  if getattr(args, "inference", None) else [None])
    configs = _size_configs(config, args.frame_size_px)
    models = [Path(m) for m in (args.model or [DEFAULT_MODEL])]
    missing = [m for m in models if not m.is_file()]
    if missing:
        raise FileNotFoundError(f"{missing[0]}: no such model (see `nhfd demo` for how to build "
                                "the default one)")
    graphs = ([{"on": True, "off": False}[g] for g in _choices(
        "--cuda-graphs", args.cuda_graphs, ("on", "off"))]
        if getattr(args, "cuda_graphs", None) else [None])
    qualities = (_choices("--quality", args.quality, QUALITY_TIERS)
                 if getattr(args, "quality", None) else [None])
    rest_ms = _rest_range(getattr(args, "rest_ms", "0,0"))
    variants = [Variant(t, q, d, n, g, tier) for d in devices for n in inferences for q in int8s
                for t in transports for g in graphs for tier in qualities]
    results = []
    side_by_side = getattr(args, "side_by_side", False)
    for cfg in configs:  # each size in turn, its variants side by side
        # --side-by-side: every model's workers in one run; else each model in turn
        for group in ([models] if side_by_side else [[m] for m in models]):
            these = [v._replace(model=str(m)) for m in group for v in variants]
            measured = measure_side_by_side(cfg, group[0], Path(args.scene), args.views,
                                            args.warmup, these, rest_ms)
            if side_by_side:
                against_first(measured, len(variants))
            for r in measured:
                results.append(r)
                _print(r, cfg.daemon.frames)
    machine = _machine(results)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"nhfd_version": __version__, "cpus": os.cpu_count(),
                               "command": _command(args), "machine": machine,
                               "results": results}, indent=1))
    table = _markdown(results, machine, _command(args))
    md = out.with_suffix(".md")
    md.write_text(table)
    print()
    print(table, end="")
    print(f"wrote {out} and {md}")
    return 0


def against_first(results: list[dict[str, Any]], per_model: int) -> None:
    """Add to each result of a side-by-side run (`per_model` variants per model, in the
    models' order) its median view-to-panel time over the first model's for the same variant:
    `median_vs_first` (1 for the first model's own)."""
    for i, r in enumerate(results):
        first = results[i % per_model]["stages"]["total"]["median_ms"]
        r["median_vs_first"] = r["stages"]["total"]["median_ms"] / first


def _rest_range(text: str) -> tuple[float, float]:
    """--rest-ms MIN,MAX in ms (0 <= MIN <= MAX <= 60000), or a ValueError naming it."""
    try:
        lo, hi = (float(v) for v in str(text).split(","))
    except ValueError:
        raise ValueError(f"--rest-ms {text!r}: give MIN,MAX in ms, e.g. 3000,4000") from None
    if not 0 <= lo <= hi <= 60_000:
        raise ValueError(f"--rest-ms {text!r}: need 0 <= MIN <= MAX <= 60000 ms")
    return lo, hi


def _devices(text: str) -> list[str]:
    """--device's comma list, each item a device torch sees (`resolve_device`) and, for an
    explicit CUDA device, one whose frame path is installed (gsplat, onnxruntime's CUDA
    provider); "auto" is kept as it is, for the worker to choose as the daemon does."""
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise ValueError(f"--device {text!r}: give a comma list of {', '.join(DEVICES)}")
    for item in items:
        device = resolve_device(item, "--device")
        if item.lower() != "auto":
            check_cuda_frames(item, device, ort.get_available_providers(), "--device")
    return [item.lower() for item in items]  # daemon.frames.device's spelling


def _size_configs(config: Config, sizes: list[list[int]] | None) -> list[Config]:
    """One configuration per --frame-size-px W H (validated: a window larger than the panel is
    refused here), or the configuration as it is."""
    if not sizes:
        return [config]
    return [Config.model_validate(_overlay(config.model_dump(),
                                           {"daemon": {"frames": {"size_px": list(size)}}}))
            for size in sizes]


def _choices(flag: str, text: str, allowed: tuple[str, ...]) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in items if t not in allowed]
    if bad or not items:
        raise ValueError(f"{flag} {text!r}: give a comma list of {', '.join(allowed)}")
    return items


def _machine(results: list[dict[str, Any]]) -> dict[str, Any]:
    """The machine the figures are from: CPU model and cores (`describe`), torch and
    onnxruntime with its providers, and, where torch sees CUDA, each CUDA device used by name."""
    info: dict[str, Any] = {**describe(), "onnxruntime": ort.__version__,
                            "onnx_providers_available": ort.get_available_providers()}
    if torch.cuda.is_available():
        info["cuda_devices"] = {r["device"]: r["gpu"] for r in results if r["gpu"]}
    return info


def _command(args: argparse.Namespace) -> str:
    """The command line that gives these figures again (the README quotes it with them)."""
    words = ["nhfd", "bench", "pipeline"]
    for model in args.model or []:
        words += ["--model", model]
    if args.config:
        words += ["--config", args.config]
    if getattr(args, "device", None):
        words += ["--device", args.device]
    for w, h in args.frame_size_px or []:
        words += ["--frame-size-px", str(w), str(h)]
    if args.transport != "shm":
        words += ["--transport", args.transport]
    if args.int8:
        words += ["--int8", args.int8]
    if getattr(args, "inference", None):
        words += ["--inference", args.inference]
    if getattr(args, "quality", None):
        words += ["--quality", args.quality, "--rest-ms", args.rest_ms]
    if getattr(args, "side_by_side", False):
        words += ["--side-by-side"]
    words += ["--views", str(args.views), "--warmup", str(args.warmup), "--json", args.json]
    return shlex.join(words)


def _device_label(r: dict[str, Any]) -> str:
    """The device computed on: "cpu", "cuda:0 (NVIDIA H100 80GB HBM3)"; "auto"'s choice says
    so ("cpu (auto)"), else a cpu,auto run's two rows would read alike."""
    graphs = None
    if str(r.get("device", "")).startswith("cuda") and "cuda_graphs" in r:
        graphs = "CUDA graphs" if r["cuda_graphs"] else "no graphs"
    notes = [n for n in (r.get("gpu"), "auto" if r.get("device_setting") == "auto" else None,
                         graphs) if n]
    return f"{r['device']} ({', '.join(notes)})" if notes else str(r["device"])


def _ms(value: float) -> str:
    """Milliseconds for the table: two decimals below 10 ms (GPU stages), one above."""
    return f"{value:.2f}" if abs(value) < 10 else f"{value:.1f}"


TABLE_COLUMNS = ("model", "size", "device", "network in", "transport", "int8 (served)",
                 "views ask", "median ms",
                 "p99 ms", *(f"{k} ms" for k in STAGES))


def _markdown(results: list[dict[str, Any]], machine: dict[str, Any], command: str) -> str:
    """The README-ready figures: the machine, the command, one table row per result (the total
    median and p99, view to panel, then each stage's median)."""
    gpus = "; ".join(f"{d}: {n}" for d, n in (machine.get("cuda_devices") or {}).items())
    # the CPU path's threads are the worker's (daemon.frames.worker_threads), not the machine's
    # cores
    threads = sorted({r["worker_threads"] for r in results})
    lines = [f"Machine: {machine['cpu']}, {machine['cores']} cores; torch "
             f"{machine.get('torch', 'absent')}, onnxruntime {machine['onnxruntime']} "
             f"({', '.join(machine['onnx_providers_available'])})"
             + (f"; {gpus}" if gpus else "") + f"; frame worker threads "
             f"{', '.join(map(str, threads))} (daemon.frames.worker_threads); nhfd {__version__}.",
             f"Command: `{command}`", "",
             "| " + " | ".join(TABLE_COLUMNS) + " |",
             "|" + "---|" * 7 + "---:|" * (len(TABLE_COLUMNS) - 7)]
    names = _model_names([r["model"] for r in results])
    for r in results:
        s = r["stages"]
        cells = [names[r["model"]], f"{r['size_wh'][0]} x {r['size_wh'][1]}",
                 _device_label(r), str(r["inference"]), r["transport"],
                 f"{r['int8']}: {r['variant']}", r.get("quality", "network"),
                 _ms(s["total"]["median_ms"]), _ms(s["total"]["p99_ms"]),
                 *(_ms(s[k]["median_ms"]) for k in STAGES)]
        lines.append("| " + " | ".join(cells) + " |")
    ratios = [r for r in results if "median_vs_first" in r]
    if ratios:
        lines += ["", f"Side by side, each median over {names[ratios[0]['model']]}'s: "
                  + ", ".join(f"{names[r['model']]} {r['median_vs_first']:.2f}x"
                              for r in ratios[1:] if r["model"] != ratios[0]["model"]) + "."]
    return "\n".join(lines) + "\n"


def _model_names(paths: list[str]) -> dict[str, str]:
    """Each model file's name in the table: its file name, or its folder and name where two
    files share a name (tuned models are all model.onnx)."""
    names = {p: Path(p).name for p in paths}
    shared = {n for n in names.values() if sum(v == n for v in names.values()) > 1}
    return {p: (f"{Path(p).parent.name}/{n}" if n in shared else n) for p, n in names.items()}


def _print(r: dict[str, Any], frames: FramesSettings) -> None:
    """One result `r` as the command prints it; `frames`: the `[daemon.frames]` it ran
    under."""
    s = r["stages"]
    print(f"{r['model']} ({r['profile']}, {r['size_wh'][0]} x {r['size_wh'][1]}), "
          f"device {_device_label(r)}, {r['views']} views, worker threads "
          f"{frames.worker_threads}, frames by {r['transport']}, serving {r['variant']} "
          f"{r['served']} (daemon.frames.int8 = {r['int8']}: {r['variant_reason']}):")
    if r["device_setting"] != r["device"]:  # "auto", or a fall back: say why
        print(f"  device: {r['device_reason']}")
    print(f"  network: {r['inference_reason']}")
    print(f"  {'stage':<12} {'median ms':>10} {'p90 ms':>8} {'p99 ms':>8}")
    for k in (*STAGES, "total"):
        print(f"  {k:<12} {_ms(s[k]['median_ms']):>10} {_ms(s[k]['p90_ms']):>8} "
              f"{_ms(s[k]['p99_ms']):>8}")
    print(f"  after rendering: {r['after_render_median_ms']:.1f} ms (goal <= 100 ms); "
          f"IPC and waiting: {r['ipc_and_wait_median_ms']:.1f} ms")
    if "median_vs_first" in r:
        print(f"  median over the first model's, side by side: {r['median_vs_first']:.2f}x")
