"""A tiny synthetic dataset in the real format (manifest + shards), for tests and smoke runs.

Each view holds two flat layers at known hologram depths (a nearer left part and a farther right
part, with a textured colour pattern); the target field is each layer's band-limited amplitude
propagated back from its own depth to the reference plane, so the focal stack focuses each layer
exactly at its depth. Views differ by a shift of the pattern. Seconds to write, no renderer.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from nhfd.dataset.build import MANIFEST, shard_name
from nhfd.dataset.shard import ExampleSettings, write_shard
from nhfd.optics import Aperture, propagate, srgb_to_linear


def synthetic_dataset(
    out_dir: str | Path,
    *,
    size_hw: tuple[int, int] = (64, 64),
    splits: tuple[int, int, int] = (4, 1, 1),
    depths_m: tuple[float, float] = (1.5e-3, -1.5e-3),
    seed: int = 0,
) -> dict:
    """Write `splits` = (train, interp, extrap) views to `out_dir`; returns the manifest."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    h, w = size_hw
    settings = ExampleSettings(width_px=w, height_px=h, panel_hw=(max(h, 64), max(w, 64)))
    ap = Aperture(settings.aperture_shape, settings.cutoff_per_px)
    d_near, d_far = 1.0, 2.0
    z_min, z_max = settings.volume_m
    b = (z_max - z_min) / (1 / d_near - 1 / d_far)
    a = z_min - b / d_far
    scene_depth = [b / (z - a) for z in depths_m]  # inverse of z_h = a + b / d
    rng = np.random.default_rng(seed)
    names = ["train"] * splits[0] + ["interp"] * splits[1] + ["extrap"] * splits[2]
    poses = []
    key = hashlib.sha256(f"synthetic {size_hw} {splits} {depths_m} {seed}".encode()).hexdigest()
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    for i, split in enumerate(names):
        shift = rng.uniform(0, 2 * np.pi, size=3)
        rgb = np.stack([0.5 + 0.45 * np.sin(xx / (3 + c) + yy / (4 + c) + shift[c])
                        for c in range(3)]).astype(np.float32)
        left = xx < w * (0.4 + 0.2 * (i % 3) / 2)
        alpha = np.ones((h, w), np.float32)
        depth = np.where(left, scene_depth[0], scene_depth[1]).astype(np.float32)
        amp = torch.sqrt(srgb_to_linear(torch.from_numpy(rgb)))
        field = torch.zeros(3, h, w, dtype=torch.complex64)
        for layer, z in ((left, depths_m[0]), (~left, depths_m[1])):
            part = (amp * torch.from_numpy(layer.astype(np.float32))).to(torch.complex64)
            field += propagate(part, -z, settings.pitch_m, settings.wavelengths_m, aperture=ap)
        arr = field.numpy()
        samples = np.abs(arr).reshape(-1)[:: max(1, arr.size // 2048)].astype(np.float32)
        az = -20 + 40 * i / max(1, len(names) - 1)
        pos = [2.0 * np.sin(np.radians(az)), 0.0, 2.0 * np.cos(np.radians(az))]
        poses.append({"R": np.eye(3).tolist(), "t": [-v for v in pos], "split": split,
                      "azimuth_deg": az, "elevation_deg": 0.0, "radius": 2.0})
        meta = {"manifest_key": key, "index": i, "split": split,
                "camera": {"fx": w * 1.2, "fy": w * 1.2, "cx": w / 2, "cy": h / 2}}
        write_shard(out / shard_name(i), {"rgb": rgb, "depth": depth, "alpha": alpha,
                                          "field": arr, "amp_samples": samples}, meta)
    all_amp = np.concatenate([
        np.abs(np.load(out / shard_name(i))["field"]).reshape(-1) for i in range(len(names))
    ])
    manifest = {
        "format_version": 1,
        "key": key,
        "scene": {"path": "synthetic", "sha256": hashlib.sha256(b"synthetic").hexdigest(),
                  "gaussians": 0},
        "settings": {**asdict(settings)},
        "seed": seed,
        "center": [0.0, 0.0, 0.0],
        "poses": poses,
        "mapping": {"d_near": d_near, "d_far": d_far, "z_min_m": z_min, "z_max_m": z_max,
                    "a_m": a, "b_m": b, "depth_exaggeration": 1.0},
        "sampling": [],
        "envelope": {"azimuth_deg": [-20.0, 20.0]},
        "splits": {s: [i for i, n in enumerate(names) if n == s]
                   for s in ("train", "interp", "extrap")},
        "amplitude_scale": {"value": float(np.percentile(all_amp, 99.5)), "percentile": 99.5},
        "nhfd_version": "synthetic",
    }
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1))
    return manifest
