"""The frame path's CPU kernels compiled before the first frame (`nhfd warmup`, which `make demo`
and `make test` run once after installing).

The renderer's and the double-phase coder's numba kernels compile on their first call (about
25 s on a 2-core machine, the first frame after an install) and are cached on disk
(`cache=True`: beside the package's sources, or in `$NUMBA_CACHE_DIR`). `warm_frame_path`
computes one small frame of the shipped donut through the shipped model, so those kernels are
compiled and cached before a person waits for a view; a later process loads them from the cache
(`kernel_cache`: its hits and misses say so)."""

from __future__ import annotations

import time
from importlib import resources
from pathlib import Path
from typing import Any

from nhfd.config import Config
from nhfd.models.export import load_model
from nhfd.optics import _coding
from nhfd.scene import _kernels
from nhfd.views import Orbit, View

from .encoder import Encoder
from .frame import compute_frame
from .settings import frame_settings
from .view import scene_from_file

SHIPPED = Path(str(resources.files("nhfd.models")))
MODEL = SHIPPED / "nhf-donut-512.onnx"
SCENE = SHIPPED / "scenes" / "donut.ply"
# A small frame: the kernels compile for the argument types, not the size.
WINDOW_WH = (96, 64)


def kernels() -> dict[str, Any]:
    """The frame path's cached numba kernels by name (the renderer's and the coder's
    dispatchers)."""
    out = {}
    for module in (_kernels, _coding):
        for name, obj in vars(module).items():
            if hasattr(obj, "stats") and hasattr(obj, "py_func"):
                out[f"{module.__name__.rsplit('.', 1)[-1]}.{name}"] = obj
    return out


def kernel_cache() -> dict[str, dict[str, int]]:
    """Per kernel this process has called: the compiled signatures loaded from the disk cache
    (`hits`) and compiled anew (`misses`)."""
    out = {}
    for name, k in kernels().items():
        hits, misses = sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values())
        if hits or misses:
            out[name] = {"hits": hits, "misses": misses}
    return out


def warm_frame_path() -> dict[str, Any]:
    """One frame of the shipped donut through the shipped model on a 96 x 64 window, on the
    CPU: its stage seconds, the seconds in all, and `kernel_cache()` after it."""
    t0 = time.perf_counter()
    config = Config.model_validate({"daemon": {"frames": {"size_px": list(WINDOW_WH)}}})
    model = load_model(MODEL, config)
    scene = scene_from_file(SCENE)
    env = model.info.pose_envelope
    view = (View(Orbit(sum(env.azimuth_deg) / 2, sum(env.elevation_deg) / 2,
                       sum(env.distance) / 2)) if env is not None else View(Orbit(0, 15, 2)))
    frame = compute_frame(view, scene, model, Encoder(frame_settings(config, model.info, None)))
    return {"stages_s": {k: round(v, 3) for k, v in frame.timings_s.items()},
            "seconds": round(time.perf_counter() - t0, 3), "kernels": kernel_cache()}
