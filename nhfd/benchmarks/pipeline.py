"""`nhfd bench pipeline`: view-change-to-SLM latency, split into render, inference, propagation,
coding and output, through the daemon's own frame worker (a spawned process with 2 threads).

For each model given (the shipped 512 x 288 one by default; add a 1024 x 576 model with another
--model), the views move along an orbit inside the model's pose envelope, one request at a time:
the clock runs from sending the view to the worker until the full panel frame has been shown on a
simulated SLM (the daemon's path, IPC included). The first views warm the caches (numba, kernels)
and are not counted. The frame cache is off: every view is computed.
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


def measure(config: Any, model: Path, scene: Path, views: int, warmup: int) -> dict[str, Any]:
    meta = OnnxModel(model).metadata
    no_cache = {"daemon": {"frame_cache_frames": 0}}
    cfg = Config.model_validate(_overlay(config.model_dump(), no_cache))
    wh, ww = frame_window_hw(cfg, meta)
    if wh > cfg.slm.height_px or ww > cfg.slm.width_px:
        raise ValueError(f"{model}: trained at {ww} x {wh}, larger than the {cfg.slm.width_px} x "
                         f"{cfg.slm.height_px} panel; set daemon.frame_size_px to at most "
                         f"[{cfg.slm.width_px}, {cfg.slm.height_px}]")
    host = _Host(cfg)
    link = FrameLink(host)
    try:
        _load(link, scene, model)
        env = meta.get("pose_envelope") or {}
        az = env.get("azimuth_deg") or [-20.0, 20.0]
        el = env.get("elevation_deg") or [20.0, 20.0]
        dist = env.get("distance") or [2.0, 2.0]
        rows = []
        for i, a in enumerate(np.linspace(az[0], az[1], warmup + views)):
            seq = host.views.submit({"kind": "orbit", "azimuth_deg": float(a),
                                     "elevation_deg": 0.5 * (el[0] + el[1]),
                                     "radius": 0.5 * (dist[0] + dist[1]), "refocus_mm": 0.0})
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
    finally:
        link.close()
    h, w = (int(v) for v in meta["train_size_hw"])
    size = list(cfg.daemon.frame_size_px) or [w, h]
    summary = {k: {"median_ms": float(np.median([r[k] for r in rows])),
                   "p90_ms": float(np.percentile([r[k] for r in rows], 90))}
               for k in (*STAGES, "total")}
    after = float(np.median([r["total"] - r["render"] for r in rows]))
    return {"model": str(model), "profile": meta.get("profile"), "size_wh": size,
            "views": len(rows), "stages": summary, "after_render_median_ms": after,
            "ipc_and_wait_median_ms": float(np.median(
                [r["total"] - sum(r[k] for k in STAGES) for r in rows])),
            "rows": rows}


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
    results = []
    for model in models:
        r = measure(config, model, Path(args.scene), args.views, args.warmup)
        results.append(r)
        s = r["stages"]
        print(f"{model} ({r['profile']}, {r['size_wh'][0]} x {r['size_wh'][1]}), "
              f"{r['views']} views, worker threads {config.daemon.worker_threads}:")
        print(f"  {'stage':<12} {'median ms':>10} {'p90 ms':>8}")
        for k in (*STAGES, "total"):
            print(f"  {k:<12} {s[k]['median_ms']:>10.1f} {s[k]['p90_ms']:>8.1f}")
        print(f"  after rendering: {r['after_render_median_ms']:.1f} ms (goal <= 100 ms); "
              f"IPC and waiting: {r['ipc_and_wait_median_ms']:.1f} ms")
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"nhfd_version": __version__, "cpus": os.cpu_count(),
                               "results": results}, indent=1))
    print(f"wrote {out}")
    return 0
