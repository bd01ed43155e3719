"""`nhfd dataset build`: depth pass -> the scene's mapping -> manifest -> shards.

1. A depth-only pass over every pose (at a quarter of the resolution: percentiles of depth do
   not need more) fixes the scene's `d_near`, `d_far` before any hologram is computed, so every
   shard shares one mapping (docs/physics.md, "The hologram volume and the scene-to-volume
   mapping").
2. The manifest freezes the poses, the mapping, the angular sampling, the pose envelope, the
   settings and the scene file's SHA-256; its `key` (a hash of all that) is written into every
   shard. A rebuild with other settings into the same folder is refused unless `force`.
3. Shards are written one per view, atomically, by `build_example(manifest, index, out_dir)`,
   whose result depends on the manifest and the index alone; shards already present for the same
   key are kept, so an interrupted build resumes where it stopped. The executors only decide
   where `build_example` runs: in this process, a local process pool (`workers`), one part of N
   on each machine sharing the folder (`shard`), or Ray tasks (`executor="ray"`).
4. When every shard exists, `merge` puts the dataset's amplitude scale (a robust percentile of
   the targets' amplitude on the SLM plane, over content pixels, pooled over all shards and
   shared by R, G and B) into the manifest. Neither shards nor the manifest hold timings or
   dates: the same dataset built twice, in any way, is the same bytes.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from nhfd import __version__
from nhfd.config import device_choice
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
from nhfd.scene import gsplat_backend
from nhfd.scene.io import load_scene
from nhfd.scene.lightfield import DepthMapping
from nhfd.scene.raster import render

MANIFEST = "manifest.json"
# The depth pass that fixes a build's mapping renders at this fraction of the view size.
DEPTH_PASS_SCALE = 0.25
AMPLITUDE_PERCENTILE = 99.5


def sha256_file(path: Path) -> str:
    """The SHA-256 of the file at `path`, hex."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def shard_name(index: int) -> str:
    """The shard file name of example `index` (`view_00042.npz`)."""
    return f"view_{index:05d}.npz"


def write_json_atomic(path: Path, data: dict) -> None:
    """Write `data` as JSON to `path` atomically: a synced temporary file beside it, renamed."""
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def depth_pass_cameras(poses: list[Pose], center: np.ndarray, settings: ExampleSettings,
                       scale: float = DEPTH_PASS_SCALE) -> list:  # fmt: skip
    """The depth pass's cameras: each pose's, at `scale` of the view size."""
    small = replace(settings, width_px=max(8, round(settings.width_px * scale)),
                    height_px=max(8, round(settings.height_px * scale)))  # fmt: skip
    return [small.camera(pose, camera_distance(pose, center)) for pose in poses]


def scene_depth_pass(g, poses: list[Pose], center: np.ndarray, settings: ExampleSettings,
                     *, scale: float = DEPTH_PASS_SCALE) -> dict:  # fmt: skip
    """Robust `d_near`, `d_far` of the scene over all poses (rendered at `scale` of the size)."""
    depths, alphas = [], []
    for camera in depth_pass_cameras(poses, center, settings, scale):
        view = render(g, camera)
        depths.append(view.depth)
        alphas.append(view.alpha)
    return scene_depth_range(depths, alphas)


def plan_optics(g, poses: list[Pose], center: np.ndarray, settings: ExampleSettings, *,
                d_near: float | None = None, d_far: float | None = None):  # fmt: skip
    """The depth mapping (from the depth pass unless `d_near` and `d_far` are given), its report,
    and each colour's light-field sampling: what every example of a build shares."""
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
    return mapping, report, sampling


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

    mapping, report, sampling = plan_optics(g, poses, center, settings, d_near=d_near,
                                            d_far=d_far)  # fmt: skip
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


# Worker state: one scene per process, loaded once (keyed by its path and SHA-256).
_WORKER: dict = {}
# Test hook (tests/dataset/test_distributed.py): "INDEX:DIR" makes the first process that builds
# example INDEX while DIR/armed exists create DIR/crashed and die at once, as a killed worker
# would; the retry finds DIR/crashed and builds the example. Unset in normal use.
CRASH_ENV = "NHFD_TEST_CRASH_AT"


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
    _WORKER["scene_path"] = str(scene_path)


def _scene(manifest: dict):
    """This process's copy of the manifest's scene, checked against the manifest's SHA-256 the
    first time (a worker on another machine may see another file under the same path)."""
    path = manifest["scene"]["path"]
    if _WORKER.get("scene_path") != path:
        _worker_init(path, threads=1)
    if _WORKER.get("checked") != (path, manifest["scene"]["sha256"]):
        digest = sha256_file(Path(path))
        if digest != manifest["scene"]["sha256"]:
            raise ValueError(
                f"{path}: SHA-256 {digest[:12]} is not the manifest's "
                f"{manifest['scene']['sha256'][:12]}; every worker must see the same scene file"
            )
        _WORKER["checked"] = (path, manifest["scene"]["sha256"])
    return _WORKER["scene"]


def _crash_hook(index: int) -> None:
    spec = os.environ.get(CRASH_ENV)
    if not spec:
        return
    at, folder = spec.split(":", 1)
    armed, crashed = Path(folder) / "armed", Path(folder) / "crashed"
    if int(at) == index and armed.exists() and not crashed.exists():
        crashed.write_text(str(os.getpid()))
        os._exit(1)


def check_device(device: str, flag: str = "--device") -> str:
    """`device` as "cpu" or "cuda:N" if it names one this build can use: "cpu", "cuda" /
    "cuda:N" on a machine whose torch sees that GPU and has gsplat, or "auto" (the first GPU
    where torch sees one and gsplat imports, else the CPU); else ValueError naming `flag` and the
    allowed values (`nhfd.config.device_choice`). The CPU path is the one without a GPU."""
    name = device_choice(device, flag, cuda_count=None)
    if name == "cpu":
        return name  # without importing torch
    import torch

    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    name = device_choice(device, flag, cuda_count=count)
    if name == "cpu":
        return name
    if not gsplat_backend.available():
        if str(device).strip().lower() == "auto":
            return "cpu"  # a GPU without gsplat: "auto" builds on the CPU
        raise ValueError(f"{flag} {name}: needs the gsplat package (pip install 'nhfd[gpu]')")
    return name


def _build_timed(manifest: dict, index: int, out_dir: str | Path, device: str = "cpu") -> dict:
    """Compute and write one shard; its path and the seconds each stage took."""
    _crash_hook(index)
    g = _scene(manifest)
    poses = _poses(manifest)
    settings = _settings(manifest)
    seed = example_seed(manifest["seed"], index)
    pose = poses[index]
    t0 = time.perf_counter()
    ex = make_example(g, pose, np.array(manifest["center"]), _mapping(manifest), settings, seed,
                      device=device)  # fmt: skip
    # Nothing that varies between runs (timings, hosts, dates) goes into a shard: a shard's bytes
    # are a function of the manifest and the index alone.
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
        "views": ex["timing"]["views"],
        "nhfd_version": __version__,
    }
    path = Path(out_dir) / shard_name(index)
    write_shard(path, ex, meta)
    return {"index": index, "path": str(path), "seconds": time.perf_counter() - t0,
            **ex["timing"]}  # fmt: skip


def build_example(manifest: dict, index: int, out_dir: str | Path, device: str = "cpu") -> Path:
    """Build example `index` of a planned dataset (`plan_manifest`'s dict) and write its shard
    atomically into `out_dir`; returns the shard's path.

    The unit every executor runs (in-process, the process pool, `--shard K/N`, Ray tasks): its
    result depends only on the manifest and the index (the example's seed is
    `example_seed(manifest seed, index)`, never the worker or the order), so a retried or
    re-run example writes the same bytes. Each process loads the scene once; a process that
    has not built from this scene yet (a pool or Ray worker) sets torch and numba to one thread,
    its share of the cores. `device`: see `build`."""
    if not 0 <= index < len(manifest["poses"]):
        raise ValueError(f"index {index}: the dataset has examples 0..{len(manifest['poses']) - 1}")
    return Path(_build_timed(manifest, index, out_dir, check_device(device))["path"])


def _build_one(out_dir: str, manifest: dict, index: int) -> dict:
    return _build_timed(manifest, index, out_dir)


def _build_star(job: tuple) -> dict:
    return _build_one(*job)


def amplitude_scale(out_dir: Path, n: int) -> dict:
    """The dataset's amplitude scale: the `AMPLITUDE_PERCENTILE` of the content-pixel amplitude
    samples pooled over shards 0..n-1, with how it was taken. ValueError when there are none."""
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


def parse_shard(text: str) -> tuple[int, int]:
    """'K/N' (part K of N, 1-based) -> (K, N)."""
    parts = str(text).split("/")
    try:
        k, n = (int(v) for v in parts)
    except ValueError:
        raise ValueError(f"--shard {text!r} is not of the form K/N (e.g. 1/4)") from None
    if n < 1 or not 1 <= k <= n:
        raise ValueError(f"--shard {text!r}: need N >= 1 and K in 1..N")
    return k, n


def shard_indices(n_examples: int, part: tuple[int, int] | None) -> list[int]:
    """The examples part (K, N) builds: every index i with i % N == K - 1 (strided, so each part
    gets a share of every split and of every region of the orbit); all when `part` is None."""
    if part is None:
        return list(range(n_examples))
    k, n = part
    if n < 1 or not 1 <= k <= n:
        raise ValueError(f"shard part {k}/{n}: need N >= 1 and K in 1..N")
    return [i for i in range(n_examples) if i % n == k - 1]


# The manifest fields the key hashes (plan_manifest's `frozen`): what a mismatch is named by.
_FROZEN = ("format_version", "scene", "settings", "seed", "center", "poses", "mapping",
           "sampling")  # fmt: skip


def manifest_differences(a: dict, b: dict) -> list[str]:
    """The frozen fields (one level into dicts: "settings.width_px") in which two manifests
    differ, as "name: A != B" strings."""
    out = []
    for key in _FROZEN:
        va, vb = a.get(key), b.get(key)
        if va == vb:
            continue
        if isinstance(va, dict) and isinstance(vb, dict):
            for sub in sorted(set(va) | set(vb)):
                if va.get(sub) != vb.get(sub):
                    out.append(f"{key}.{sub}: {_short(va.get(sub))} != {_short(vb.get(sub))}")
        else:
            out.append(f"{key}: {_short(va)} != {_short(vb)}")
    return out


def _short(v) -> str:
    text = json.dumps(v, default=str)
    return text if len(text) <= 60 else text[:57] + "..."


def missing_shards(out_dir: Path, manifest: dict) -> list[int]:
    """Indices whose shard is absent, unreadable or written for another manifest key."""
    return [i for i in range(len(manifest["poses"]))
            if not shard_is_valid(out_dir / shard_name(i), manifest["key"])]  # fmt: skip


def merge(out_dir: Path, manifest: dict | None = None) -> dict:
    """Write the dataset's one manifest once every example's shard exists: the planned manifest
    (`manifest`, or the folder's own) plus the amplitude scale pooled over all shards. Any number
    of parts may call it: the result depends only on the shards, so it is written identically."""
    out_dir = Path(out_dir)
    on_disk = load_manifest(out_dir)
    manifest = dict(manifest or on_disk)
    if on_disk.get("key") != manifest["key"]:
        diff = manifest_differences(on_disk, manifest)
        raise ValueError(f"{out_dir}: its manifest was planned with other settings ("
                         f"{'; '.join(diff) or 'key ' + str(on_disk.get('key'))[:12]})")
    for path in sorted(out_dir.glob("view_*.npz")):
        meta = _shard_meta(path)
        if meta is not None and meta.get("manifest_key") != manifest["key"]:
            theirs = {**manifest, **{k: meta[k] for k in ("settings", "mapping", "sampling")
                                     if k in meta}}  # fmt: skip
            diff = manifest_differences(manifest, theirs)
            raise ValueError(f"{path}: built for another dataset (manifest key "
                             f"{str(meta.get('manifest_key'))[:12]} != {manifest['key'][:12]}"
                             f"{'; ' + '; '.join(diff) if diff else ''}); "
                             "rebuild it with the same settings, or --force")  # fmt: skip
    missing = missing_shards(out_dir, manifest)
    if missing:
        shown = ", ".join(str(i) for i in missing[:10]) + (" ..." if len(missing) > 10 else "")
        raise ValueError(f"{out_dir}: {len(missing)} of {len(manifest['poses'])} shards are "
                         f"missing or incomplete (examples {shown}); build the remaining parts "
                         "first")  # fmt: skip
    manifest.pop("build_timing", None)
    manifest["amplitude_scale"] = amplitude_scale(out_dir, len(manifest["poses"]))
    write_json_atomic(out_dir / MANIFEST, manifest)
    return manifest


def _shard_meta(path: Path) -> dict | None:
    try:
        return read_shard(path)["meta"]
    except ValueError:
        return None


def _run_ray(manifest: dict, out_dir: Path, todo: list[int], *, address: str | None,
             workers: int, on_result: Callable[[dict], None]) -> None:  # fmt: skip
    """One Ray task per example, each calling build_example; a task whose worker dies or
    raises is retried (up to 3 times). Without `address`, a local Ray instance with `workers`
    CPUs is started (and stopped); with one, the cluster there runs the tasks, and every node
    must see `out_dir` and the scene file under the same paths."""
    try:
        import ray
    except ImportError:
        raise ValueError("--executor ray needs Ray: pip install 'nhfd[ray]'") from None
    started = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        started = True
    try:
        task = ray.remote(num_cpus=1, max_retries=3, retry_exceptions=True)(_build_timed)
        ref = ray.put(manifest)
        pending = [task.remote(ref, i, str(out_dir)) for i in todo]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for r in ray.get(ready):
                on_result(r)
    finally:
        if started:
            ray.shutdown()


EXECUTORS = ("local", "ray")


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
    shard: tuple[int, int] | None = None,
    executor: str = "local",
    address: str | None = None,
    threads: int | None = None,
    device: str = "cpu",
) -> dict:
    """Build (or resume) a dataset; returns the final manifest.

    `device` "cpu" (the default) renders with the CPU rasteriser and inverts with torch on the
    CPU; "cuda" or "cuda:N" renders each example's light field with gsplat, several views per
    call, and inverts and propagates on that GPU, in this process (`workers` 1, the local
    executor). The depth pass that fixes the mapping runs on the CPU either way, so a CPU and a
    GPU build of the same settings share one manifest (and key); their shards agree to float
    rounding and the renderers' one residual difference (gsplat_backend: the alpha cap).

    `shard` (K, N) builds only part K of N (`shard_indices`); the manifest is completed by
    whichever part finds every shard present (or by `merge`), and until then this returns the
    planned manifest (`amplitude_scale` None). `executor` "ray" runs one Ray task per example
    (`address`: a running cluster's; None starts a local instance with `workers` CPUs).
    `threads`: torch's and numba's threads of an in-process build (`workers` 1; default: one per
    core); pool and Ray workers run one thread each.
    The returned dict carries `build_timing` (this run's speed); the file does not, so that two
    builds of the same dataset are identical byte for byte."""

    if executor not in EXECUTORS:
        raise ValueError(f"executor = {executor!r}: must be one of {', '.join(EXECUTORS)}")
    if workers < 1:
        raise ValueError(f"workers = {workers}: must be >= 1")
    if threads is not None and threads < 1:
        raise ValueError(f"threads = {threads}: must be >= 1")
    device = check_device(device)
    if device != "cpu" and (workers > 1 or executor != "local"):
        raise ValueError(f"--device {device}: builds in this process on one GPU; use "
                         "--workers 1 and the local executor (--shard K/N splits a build over "
                         "GPUs)")  # fmt: skip
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
            diff = manifest_differences(existing, manifest)
            raise ValueError(
                f"{out_dir} holds a dataset built with other settings, poses or scene "
                f"(manifest key {existing.get('key', '?')[:12]} != {manifest['key'][:12]}"
                f"{': ' + '; '.join(diff) if diff else ''}); "
                "use another --out, or --force to replace it"
            )
        for old in out_dir.glob("view_*.npz"):
            old.unlink()
        existing = None
    if existing is None:
        # Parts of a sharded build plan the same manifest (same bytes), so whichever writes it
        # first writes what the others would.
        write_json_atomic(manifest_path, manifest)
    # Temporary files of an interrupted build are never shards; clear them (only in a
    # whole-dataset build: other parts may be writing theirs right now).
    if shard is None and executor == "local":
        for stale in out_dir.glob("*.tmp"):
            stale.unlink(missing_ok=True)
    mine = shard_indices(len(poses), shard)
    todo = [i for i in mine if not shard_is_valid(out_dir / shard_name(i), manifest["key"])]
    done = len(mine) - len(todo)
    stats: list[dict] = []

    def record(r: dict) -> None:
        nonlocal done
        done += 1
        stats.append(r)
        if progress:
            progress(done, len(mine), r)

    t_start = time.perf_counter()
    if todo:
        if executor == "ray":
            _run_ray(manifest, out_dir, todo, address=address, workers=workers, on_result=record)
        elif workers <= 1:
            _worker_init(str(scene_path), threads=threads or max(1, os.cpu_count() or 1))
            for i in todo:
                record(_build_timed(manifest, i, out_dir, device))
        else:
            import multiprocessing as mp

            ctx = mp.get_context("spawn")
            # Each worker is single-threaded; together they use the cores. Spawned, not forked:
            # numba's and torch's thread pools do not survive a fork.
            with ctx.Pool(workers, initializer=_worker_init,
                          initargs=(str(scene_path), 1)) as pool:  # fmt: skip
                jobs = [(str(out_dir), manifest, i) for i in todo]
                for res in pool.imap_unordered(_build_star, jobs):
                    record(res)
    wall_s = time.perf_counter() - t_start
    if shard is None or not missing_shards(out_dir, manifest):
        manifest = merge(out_dir, manifest)
    if stats:
        manifest["build_timing"] = {
            "examples": len(stats),
            "wall_s": wall_s,
            "median_example_s": float(np.median([s["seconds"] for s in stats])),
            "median_render_s": float(np.median([s["render_s"] for s in stats])),
            "median_invert_s": float(np.median([s["invert_s"] for s in stats])),
            "workers": workers,
            "executor": executor,
            "device": device,
        }
    return manifest


def load_manifest(out_dir: Path) -> dict:
    """The dataset folder's manifest.json as a dict; FileNotFoundError when it has none."""
    path = Path(out_dir) / MANIFEST
    if not path.exists():
        raise FileNotFoundError(f"{out_dir}: no {MANIFEST}; is this a dataset folder?")
    return json.loads(path.read_text())
