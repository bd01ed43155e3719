"""A picture of one shard: its central view and its hologram's focal stack (near, middle, far)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nhfd.dataset.build import load_manifest, shard_name
from nhfd.dataset.shard import read_shard
from nhfd.optics import Aperture, linear_to_srgb, propagate


def focal_images(field: np.ndarray, planes_m: list[float], settings: dict) -> np.ndarray:
    """sRGB images [D, H, W, 3] of the field's intensity at each plane, all normalised by one
    robust percentile so brightness compares across planes."""
    import torch

    aperture = Aperture(settings["aperture_shape"], tuple(settings["cutoff_per_px"]))
    stack = propagate(
        torch.from_numpy(field), planes_m, settings["pitch_m"], settings["wavelengths_m"],
        aperture=aperture,
    )  # fmt: skip
    intensity = stack.abs() ** 2
    scale = float(torch.quantile(intensity.flatten()[:: max(1, intensity.numel() // 2_000_000)],
                                 0.999)) or 1.0  # fmt: skip
    srgb = linear_to_srgb(intensity / scale)
    return srgb.permute(0, 2, 3, 1).numpy()


def show(out_dir: Path, index: int, png: Path) -> dict:
    """Write the PNG; returns what it shows (planes, split)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    manifest = load_manifest(out_dir)
    n = len(manifest["poses"])
    if not 0 <= index < n:
        raise ValueError(f"--index {index}: this dataset has views 0..{n - 1}")
    shard = read_shard(Path(out_dir) / shard_name(index))
    settings = shard["meta"]["settings"]
    z_min, z_max = settings["volume_m"]
    planes = [z_max, 0.5 * (z_min + z_max), z_min]
    images = focal_images(shard["field"], planes, settings)
    fig, axes = plt.subplots(1, 4, figsize=(16, 2.8), dpi=100)
    axes[0].imshow(np.clip(shard["rgb"].transpose(1, 2, 0), 0, 1))
    axes[0].set_title(f"view {index} ({shard['meta']['split']}): central render")
    names = ("near", "middle", "far")
    for ax, img, z, name in zip(axes[1:], images, planes, names, strict=True):
        ax.imshow(np.clip(img, 0, 1))
        ax.set_title(f"hologram focused {name}: z = {z * 1e3:+.1f} mm")
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png)
    plt.close(fig)
    return {"planes_mm": [z * 1e3 for z in planes], "split": shard["meta"]["split"]}
