"""`nhfd bench pipeline`: view-change-to-SLM latency, split into render, inference, propagation,
coding and output, through the daemon's own frame worker (a spawned process with 2 threads).

For each model given (the shipped 512 x 288 one by default; add a 1024 x 576 model with another
--model), the views move along an orbit inside the model's pose envelope, one request at a time:
the clock runs from sending the view to the worker until the full panel frame has been shown on a
simulated SLM (the daemon's path, IPC included). The first views warm the caches (numba, kernels)
and are not counted. The frame cache is off: every view is computed.

--transport shm,pickle measures both ways frames cross from the worker in one run (shared-memory
slots, the default, or the arrays pickled through the pipe), and --int8 never,auto the float model
and the int8 sibling the daemon would serve (`daemon.int8`); each combination in its own worker,
all given the same views in turn (a loaded machine loads them alike). The panel's refresh
pacing is off here (slm.refresh_hz at its maximum): the figure is the pipeline's, not the
panel's.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from nhfd import __version__
from nhfd.config import Config, _overlay, load_config
from nhfd.daemon.frame_link import FrameLink
from nhfd.daemon.panel import Panel
from nhfd.daemon.views import ViewSlot
from nhfd.drivers.slm import SimulatedSLM
from nhfd.models.export import OnnxModel
from nhfd.pipeline.device import resolve_device
from nhfd.pipeline.settings import frame_window_hw

# The stages status reports, in order: the frame pipeline's four (`nhfd.pipeline.frame`), then
# the daemon's output (the region pasted into the panel and shown).
STAGES = ("render", "inference", "propagation", "coding", "output")


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
    p.add_argument("--device", help="where frames are computed: auto, cpu, cuda or cuda:N "
                   "(default: daemon.device)")
    p.add_argument("--frame-size-px", type=int, nargs=2, metavar=("W", "H"),
                   help="hologram window (daemon.frame_size_px; default: the configuration's)")
    p.add_argument("--transport", default="shm",
                   help="comma list of frame transports to compare: shm, pickle (default shm)")
    p.add_argument("--int8", default=None,
                   help="comma list of daemon.int8 settings to compare: auto, never, always "
                        "(default: the configuration's)")
    p.set_defaults(handler=run)


class _Host:
    """The slice of the daemon a FrameLink needs (`FrameHost`): views, the panel on a simulated
    SLM, the error list."""

    def __init__(self, config: Any) -> None:
        self.config = config
        self.views = ViewSlot()
        self.slm = SimulatedSLM(config.slm.width_px, config.slm.height_px).open()
        self.errors: list[str] = []
        self.bench = self  # where a lost SLM is noted
        self.panel = Panel(config, SimpleNamespace(slm=self.slm, errors={"slm": None}))
        self.laser = None  # no lasers here (FrameLink switches them off if the worker dies)

    def note_slm_lost(self, detail: str) -> None:
        self._error("slm", detail)

    def _error(self, source: str, message: str) -> None:
        self.errors.append(f"{source}: {message}")


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


def measure(config: Any, model: Path, scene: Path, views: int, warmup: int, *,
            transport: str | None = None, int8: str | None = None) -> dict[str, Any]:
    """One model under one transport and int8 setting (`measure_side_by_side` of one)."""
    return measure_side_by_side(config, model, scene, views, warmup, [(transport, int8)])[0]


def measure_side_by_side(config: Any, model: Path, scene: Path, views: int, warmup: int,
                         variants: list[tuple[str | None, str | None]]) -> list[dict[str, Any]]:
    """`model` under each (transport, daemon.int8) of `variants` (None: the configuration's),
    each in its own worker, all started first and then given the same views in turn, one frame
    at a time (the order rotating per view): on a loaded machine the variants see the same load
    and their medians compare."""
    meta = OnnxModel(model).metadata
    runs = []
    try:
        for transport, int8 in variants:
            daemon: dict[str, Any] = {"frame_cache_frames": 0}
            if transport is not None:
                daemon["frame_transport"] = transport
            if int8 is not None:
                daemon["int8"] = int8
            # No refresh pacing: the bench times the pipeline, not the panel.
            overlay = {"daemon": daemon, "slm": {"refresh_hz": 1000.0}}
            cfg = Config.model_validate(_overlay(config.model_dump(), overlay))
            wh, ww = frame_window_hw(cfg, meta)
            if wh > cfg.slm.height_px or ww > cfg.slm.width_px:
                raise ValueError(f"{model}: trained at {ww} x {wh}, larger than the "
                                 f"{cfg.slm.width_px} x {cfg.slm.height_px} panel; set "
                                 f"daemon.frame_size_px to at most [{cfg.slm.width_px}, "
                                 f"{cfg.slm.height_px}]")
            host = _Host(cfg)
            link = FrameLink(host)
            runs.append((cfg, host, link, []))
            _load(link, scene, model)
        env = meta.get("pose_envelope") or {}
        az = env.get("azimuth_deg") or [-20.0, 20.0]
        el = env.get("elevation_deg") or [20.0, 20.0]
        dist = env.get("distance") or [2.0, 2.0]
        for i, a in enumerate(np.linspace(az[0], az[1], warmup + views)):
            view = {"kind": "orbit", "azimuth_deg": float(a),
                    "elevation_deg": 0.5 * (el[0] + el[1]),
                    "radius": 0.5 * (dist[0] + dist[1]), "refocus_mm": 0.0}
            for k in range(len(runs)):
                _cfg, host, link, rows = runs[(i + k) % len(runs)]
                seq = host.views.submit(view)
                t0 = time.perf_counter()
                while link.shown_seq < seq:
                    link.step()
                    if host.errors:
                        raise RuntimeError(host.errors[-1])
                    time.sleep(0.0005)
                total_ms = (time.perf_counter() - t0) * 1e3
                if i >= warmup:
                    t = link.timings or {}
                    rows.append({**{k: t[f"{k}_ms"] for k in STAGES}, "total": total_ms})
        infos = [dict(link.model_info or {}) for _cfg, _host, link, _rows in runs]
    finally:
        for _cfg, _host, link, _rows in runs:
            link.close()
    h, w = (int(v) for v in meta["train_size_hw"])
    out = []
    for (cfg, _host, _link, rows), info in zip(runs, infos, strict=True):
        size = list(cfg.daemon.frame_size_px) or [w, h]
        summary = {k: {"median_ms": float(np.median([r[k] for r in rows])),
                       "p90_ms": float(np.percentile([r[k] for r in rows], 90)),
                       "p99_ms": float(np.percentile([r[k] for r in rows], 99))}
                   for k in (*STAGES, "total")}
        after = float(np.median([r["total"] - r["render"] for r in rows]))
        out.append({"model": str(model), "profile": meta.get("profile"), "size_wh": size,
                    "transport": cfg.daemon.frame_transport, "int8": cfg.daemon.int8,
                    "served": info.get("served", str(model)), "variant": info.get("variant"),
                    "variant_reason": info.get("variant_reason"),
                    "views": len(rows), "stages": summary, "after_render_median_ms": after,
                    "ipc_and_wait_median_ms": float(np.median(
                        [r["total"] - sum(r[k] for k in STAGES) for r in rows])),
                    "rows": rows})
    return out


def run(args: argparse.Namespace) -> int:
    # load_config applies the cross-field rules: a frame larger than the panel is a
    # ConfigError (exit 2) before any worker starts.
    config = load_config(args.config).config
    if getattr(args, "device", None):  # checked here: a clean error before any worker starts
        resolve_device(args.device, "--device")
        config = Config.model_validate(_overlay(config.model_dump(),
                                                {"daemon": {"device": args.device}}))
    models = [Path(m) for m in (args.model or ["models/nhf-donut-512.onnx"])]
    missing = [m for m in models if not m.is_file()]
    if missing:
        raise FileNotFoundError(f"{missing[0]}: no such model (see `nhfd demo` for how to build "
                                "the default one)")
    if args.frame_size_px:
        config = Config.model_validate(_overlay(
            config.model_dump(), {"daemon": {"frame_size_px": list(args.frame_size_px)}}))
    transports = _choices("--transport", args.transport, ("shm", "pickle"))
    int8s = _choices("--int8", args.int8, ("auto", "never", "always")) if args.int8 else [None]
    results = []
    for model in models:
        variants = [(t, q) for q in int8s for t in transports]
        for r in measure_side_by_side(config, model, Path(args.scene), args.views, args.warmup,
                                      variants):
            results.append(r)
            _print(r, config)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"nhfd_version": __version__, "cpus": os.cpu_count(),
                               "results": results}, indent=1))
    print(f"wrote {out}")
    return 0


def _choices(flag: str, text: str, allowed: tuple[str, ...]) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in items if t not in allowed]
    if bad or not items:
        raise ValueError(f"{flag} {text!r}: give a comma list of {', '.join(allowed)}")
    return items


def _print(r: dict[str, Any], config: Any) -> None:
    s = r["stages"]
    print(f"{r['model']} ({r['profile']}, {r['size_wh'][0]} x {r['size_wh'][1]}), "
          f"{r['views']} views, worker threads {config.daemon.worker_threads}, frames by "
          f"{r['transport']}, serving {r['variant']} {r['served']} "
          f"(daemon.int8 = {r['int8']}: {r['variant_reason']}):")
    print(f"  {'stage':<12} {'median ms':>10} {'p90 ms':>8} {'p99 ms':>8}")
    for k in (*STAGES, "total"):
        print(f"  {k:<12} {s[k]['median_ms']:>10.1f} {s[k]['p90_ms']:>8.1f} "
              f"{s[k]['p99_ms']:>8.1f}")
    print(f"  after rendering: {r['after_render_median_ms']:.1f} ms (goal <= 100 ms); "
          f"IPC and waiting: {r['ipc_and_wait_median_ms']:.1f} ms")
