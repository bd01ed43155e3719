"""`nhfd dataset build`: depth pass -> the scene's mapping -> manifest -> shards.

1. A depth-only pass over every pose (at a quarter of the resolution: percentiles of depth do
   not need more) fixes the scene's `d_near`, `d_far` before any hologram is computed, so every
   shard shares one mapping (optics.md).
2. The manifest freezes the poses, the mapping, the angular sampling, the pose envelope, the
   settings and the scene file's SHA-256; its `key` (a hash of all that) is written into every
   shard. A rebuild with other settings into the same folder is refused unless `force`.
3. Shards are written one per view, atomically; shards already present for the same key are
   kept, so an interrupted build resumes where it stopped.
4. When every shard exists, the dataset's amplitude scale (a robust percentile of the targets'
   amplitude on the SLM plane, over content pixels, pooled over all shards and shared by R, G
   and B) goes into the manifest.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from nhfd import __version__
from nhfd.dataset.poses import Pose, envelope
from nhfd.dataset.shard import (
    FORMAT_VERSION,
    ExampleSettings,
    camera_distance,
    example_seed,
    make_example,
    read_shard,
    shard_is_valid,
    write_shard,
)
from nhfd.holo import colour_sampling, sampling_report, scene_depth_range, scene_mapping
from nhfd.scene.io import load_scene
from nhfd.scene.lightfield import DepthMapping
from nhfd.scene.raster import render

MANIFEST = "manifest.json"
AMPLITUDE_PERCENTILE = 99.5


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def shard_name(index: int) -> str:
    return f"view_{index:05d}.npz"


def write_json_atomic(path: Path, data: dict) -> None:
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def scene_depth_pass(g, poses: list[Pose], center: np.ndarray, settings: ExampleSettings,
                     *, scale: float = 0.25) -> dict:  # fmt: skip
    """Robust `d_near`, `d_far` of the scene over all poses (rendered at `scale` of the size)."""
    from dataclasses import replace

    small = replace(
        settings,
        width_px=max(8, round(settings.width_px * scale)),
        height_px=max(8, round(settings.height_px * scale)),
    )
    depths, alphas = [], []
    for pose in poses:
        view = render(g, small.camera(pose, camera_distance(pose, center)))
        depths.append(view.depth)
        alphas.append(view.alpha)
    return scene_depth_range(depths, alphas)


def plan_manifest(
    scene_path: Path,
    g,
    poses: list[Pose],
    center: np.ndarray,
    settings: ExampleSettings,
    *,
    seed: int,
    sampler: dict | None,
    d_near: float | None = None,
    d_far: float | None = None,
) -> dict:
    """Everything the shards depend on, decided before any hologram is computed."""

    depth_range = None if (d_near and d_far) else scene_depth_pass(g, poses, center, settings)
    fx = 0.5 * settings.width_px / np.tan(np.radians(settings.fov_x_deg) / 2)
    mapping, report = scene_mapping(
        settings.volume_m[0], settings.volume_m[1], settings.pitch_m, float(fx),
        depth_range=depth_range, d_near=d_near, d_far=d_far,
    )  # fmt: skip
    sampling = colour_sampling(
        settings.wavelengths_m, settings.pitch_m, settings.volume_m, settings.aperture(),
        windows=settings.windows, shared=settings.shared_views,
    )  # fmt: skip
    frozen = {
        "format_version": FORMAT_VERSION,
        "scene": {"path": str(scene_path), "sha256": sha256_file(scene_path), "gaussians": len(g)},
        "settings": settings.to_json(),
        "seed": int(seed),
        "center": [float(v) for v in center],
        "poses": [asdict(p) for p in poses],
        "mapping": {**report, "a_m": mapping.a_m, "b_m": mapping.b_m},
        "sampling": sampling_report(sampling),
    }
    key = hashlib.sha256(json.dumps(frozen, sort_keys=True, default=str).encode()).hexdigest()
    return {
        **frozen,
        "key": key,
        "sampler": sampler,
        "envelope": envelope(poses, center),
        "splits": {s: [i for i, p in enumerate(poses) if p.split == s]
                   for s in ("train", "interp", "extrap")},
        "nhfd_version": __version__,
        "amplitude_scale": None,
    }


def _mapping(manifest: dict):
    return DepthMapping(manifest["mapping"]["a_m"], manifest["mapping"]["b_m"])


def _poses(manifest: dict) -> list[Pose]:
    return [
        Pose(tuple(tuple(r) for r in p["R"]), tuple(p["t"]), p["split"],
             p.get("azimuth_deg"), p.get("elevation_deg"), p.get("radius"))
        for p in manifest["poses"]
    ]  # fmt: skip


def _settings(manifest: dict) -> ExampleSettings:
    s = dict(manifest["settings"])
    for k in ("wavelengths_m", "volume_m", "panel_hw", "cutoff_per_px", "windows"):
        if s.get(k) is not None:
            s[k] = tuple(s[k])
    return ExampleSettings(**s)


# Worker state: one scene per process, loaded once.
_WORKER: dict = {}


def _worker_init(scene_path: str, threads: int) -> None:
    import torch

    torch.set_num_threads(threads)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:
        pass  # in-process builds: torch already ran, its inter-op pool is fixed
    try:
        import numba

        numba.set_num_threads(threads)
    except ImportError:
        pass

    _WORKER["scene"] = load_scene(scene_path)


def _build_one(out_dir: str, manifest: dict, index: int) -> dict:
    """Compute and write one shard (in a worker or in-process)."""
    g = _WORKER["scene"]
    poses = _poses(manifest)
    settings = _settings(manifest)
    seed = example_seed(manifest["seed"], index)
    pose = poses[index]
    t0 = time.perf_counter()
    ex = make_example(g, pose, np.array(manifest["center"]), _mapping(manifest), settings, seed)
    meta = {
        "manifest_key": manifest["key"],
        "index": index,
        "split": pose.split,
        "seed": seed,
        "pose": asdict(pose),
        "camera": ex["camera"],
        "mapping": manifest["mapping"],
        "sampling": manifest["sampling"],
        "settings": manifest["settings"],
        "timing": ex["timing"],
        "nhfd_version": __version__,
    }
    write_shard(Path(out_dir) / shard_name(index), ex, meta)
    return {"index": index, "seconds": time.perf_counter() - t0, **ex["timing"]}


def _build_star(job: tuple) -> dict:
    return _build_one(*job)


def amplitude_scale(out_dir: Path, n: int) -> dict:
    pooled = np.concatenate([read_shard(out_dir / shard_name(i))["amp_samples"] for i in range(n)])
    if pooled.size == 0:
        raise ValueError(f"{out_dir}: no content pixels in any target; is the scene in view?")
    return {
        "value": float(np.percentile(pooled, AMPLITUDE_PERCENTILE)),
        "percentile": AMPLITUDE_PERCENTILE,
        "over": "content pixels (> 1% of each target's peak) on the SLM plane, after the "
        "aperture and the -z0 propagation, pooled over all shards and colours",
        "samples": int(pooled.size),
    }


def build(
    scene_path: Path,
    out_dir: Path,
    poses: list[Pose],
    settings: ExampleSettings,
    *,
    seed: int = 0,
    sampler: dict | None = None,
    workers: int = 1,
    force: bool = False,
    d_near: float | None = None,
    d_far: float | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
) -> dict:
    """Build (or resume) a dataset; returns the final manifest."""

    scene_path, out_dir = Path(scene_path), Path(out_dir)
    g = load_scene(scene_path)
    center = np.median(g.means, axis=0) if len(g) else np.zeros(3)
    if sampler is not None:
        center = np.asarray(sampler["center"], np.float64)
    out_dir.mkdir(parents=True, exist_ok=True)
    manifest_path = out_dir / MANIFEST
    existing = json.loads(manifest_path.read_text()) if manifest_path.exists() else None
    manifest = plan_manifest(scene_path, g, poses, center, settings, seed=seed, sampler=sampler,
                             d_near=d_near, d_far=d_far)  # fmt: skip
    if existing is not None and existing.get("key") != manifest["key"]:
        if not force:
            raise ValueError(
                f"{out_dir} holds a dataset built with other settings, poses or scene "
                f"(manifest key {existing.get('key', '?')[:12]} != {manifest['key'][:12]}); "
                "use another --out, or --force to replace it"
            )
        for old in out_dir.glob("view_*.npz"):
            old.unlink()
    write_json_atomic(manifest_path, manifest)
    # Temporary files of an interrupted build are never shards; clear them.
    for stale in out_dir.glob("*.tmp"):
        stale.unlink(missing_ok=True)
    todo = [i for i in range(len(poses))
            if not shard_is_valid(out_dir / shard_name(i), manifest["key"])]  # fmt: skip
    done = len(poses) - len(todo)
    stats: list[dict] = []
    if todo:
        if workers <= 1:
            _worker_init(str(scene_path), threads=max(1, os.cpu_count() or 1))
            results = (_build_one(str(out_dir), manifest, i) for i in todo)
            for r in results:
                done += 1
                stats.append(r)
                if progress:
                    progress(done, len(poses), r)
        else:
            import multiprocessing as mp

            ctx = mp.get_context("spawn")
            # Each worker is single-threaded; together they use the cores. Spawned, not forked:
            # numba's and torch's thread pools do not survive a fork.
            with ctx.Pool(workers, initializer=_worker_init,
                          initargs=(str(scene_path), 1)) as pool:  # fmt: skip
                jobs = [(str(out_dir), manifest, i) for i in todo]
                for res in pool.imap_unordered(_build_star, jobs):
                    done += 1
                    stats.append(res)
                    if progress:
                        progress(done, len(poses), res)
    manifest["amplitude_scale"] = amplitude_scale(out_dir, len(poses))
    if stats:
        manifest["build_timing"] = {
            "examples": len(stats),
            "median_example_s": float(np.median([s["seconds"] for s in stats])),
            "median_render_s": float(np.median([s["render_s"] for s in stats])),
            "median_invert_s": float(np.median([s["invert_s"] for s in stats])),
            "workers": workers,
        }
    write_json_atomic(manifest_path, manifest)
    return manifest


def load_manifest(out_dir: Path) -> dict:
    path = Path(out_dir) / MANIFEST
    if not path.exists():
        raise FileNotFoundError(f"{out_dir}: no {MANIFEST}; is this a dataset folder?")
    return json.loads(path.read_text())
