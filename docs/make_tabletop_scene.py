"""Write `models/scenes/tabletop.spz`: a synthetic splat scene with depth, for `nhfd model build`.

A checkered floor (its depth runs continuously away from an elevated camera) with five striped
spheres and two textured blocks standing on it at different depths. Every surface carries a
fine texture so that focus is visible at every depth. The scene is built in the project's OpenCV
frame (x right, y down, z forward; the floor at y = 0, objects at y < 0, so up is -y) and written
as Niantic .spz, which declares its axes (RUB): loaders take the up axis from the file instead of
guessing it. Seeded: the same file every run.

    .venv/bin/python docs/make_tabletop_scene.py [OUT]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from nhfd.scene.gaussians import SH_C0, Gaussians
from nhfd.scene.spz import save_spz

SEED = 7
SPACING = 0.02  # splat spacing on every surface (scene units)
FLOOR_HALF = 1.2  # the floor spans [-FLOOR_HALF, FLOOR_HALF] in x and z
CHECK = 0.3  # checker square size
OPACITY = 0.95


def _texture(rng: np.random.Generator, n: int) -> np.ndarray:
    """A multiplicative fine texture, +-20 %, so that each surface has detail to focus on."""
    return 1.0 + 0.2 * rng.uniform(-1.0, 1.0, (n, 1))


def floor(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ticks = np.arange(-FLOOR_HALF, FLOOR_HALF + 1e-9, SPACING)
    x, z = np.meshgrid(ticks, ticks, indexing="xy")
    x, z = x.ravel(), z.ravel()
    means = np.stack([x, np.zeros_like(x), z], axis=1)
    dark = (np.floor(x / CHECK) + np.floor(z / CHECK)) % 2 == 0
    rgb = np.where(dark[:, None], [0.12, 0.35, 0.38], [0.92, 0.86, 0.70]) * _texture(rng, len(x))
    scales = np.tile([0.6 * SPACING, 0.1 * SPACING, 0.6 * SPACING], (len(x), 1))
    return means, rgb, scales


def sphere(rng: np.random.Generator, centre: tuple[float, float, float], radius: float,
           colours: tuple[tuple[float, float, float], tuple[float, float, float]]):
    n = int(4 * np.pi * radius**2 / SPACING**2)
    k = np.arange(n) + 0.5
    polar = np.arccos(1 - 2 * k / n)  # Fibonacci sphere: even coverage
    azimuth = np.pi * (1 + 5**0.5) * k
    unit = np.stack([np.sin(polar) * np.cos(azimuth), np.cos(polar),
                     np.sin(polar) * np.sin(azimuth)], axis=1)
    bands = (np.floor(polar / (np.pi / 8)) % 2).astype(bool)  # eight latitude stripes
    rgb = np.where(bands[:, None], colours[0], colours[1]) * _texture(rng, n)
    scales = np.full((n, 3), 0.6 * SPACING)
    return np.asarray(centre) + radius * unit, rgb, scales


def block(rng: np.random.Generator, centre: tuple[float, float, float],
          size: tuple[float, float, float], colour: tuple[float, float, float]):
    """The faces of an axis-aligned box (x, height, z), with a grid of darker lines."""
    pts = []
    half = np.asarray(size) / 2
    for axis in range(3):
        for side in (-1.0, 1.0):
            u_axis, v_axis = [a for a in range(3) if a != axis]
            u = np.arange(-half[u_axis], half[u_axis] + 1e-9, SPACING)
            v = np.arange(-half[v_axis], half[v_axis] + 1e-9, SPACING)
            uu, vv = np.meshgrid(u, v)
            p = np.zeros((uu.size, 3))
            p[:, axis] = side * half[axis]
            p[:, u_axis], p[:, v_axis] = uu.ravel(), vv.ravel()
            pts.append(p)
    local = np.concatenate(pts)
    lines = (np.abs((local / 0.08) - np.round(local / 0.08)) < 0.15).any(axis=1)
    rgb = np.where(lines[:, None], np.asarray(colour) * 0.35, colour) * _texture(rng, len(local))
    scales = np.full((len(local), 3), 0.6 * SPACING)
    return np.asarray(centre) + local, rgb, scales


def tabletop() -> Gaussians:
    rng = np.random.default_rng(SEED)
    parts = [floor(rng)]
    for centre, radius, colours in [
        ((-0.6, -0.25, -0.6), 0.25, ((0.85, 0.2, 0.15), (0.95, 0.9, 0.85))),
        ((0.55, -0.2, -0.3), 0.20, ((0.2, 0.45, 0.9), (0.95, 0.95, 0.6))),
        ((-0.2, -0.18, 0.2), 0.18, ((0.25, 0.75, 0.3), (0.1, 0.1, 0.1))),
        ((0.7, -0.22, 0.7), 0.22, ((0.9, 0.6, 0.1), (0.4, 0.15, 0.5))),
        ((-0.75, -0.15, 0.85), 0.15, ((0.9, 0.9, 0.9), (0.8, 0.1, 0.5))),
    ]:
        parts.append(sphere(rng, centre, radius, colours))
    parts.append(block(rng, (0.1, -0.3, -0.85), (0.3, 0.6, 0.3), (0.75, 0.55, 0.35)))
    parts.append(block(rng, (0.2, -0.125, 0.75), (0.4, 0.25, 0.25), (0.55, 0.6, 0.7)))
    means = np.concatenate([p[0] for p in parts]).astype(np.float32)
    rgb = np.clip(np.concatenate([p[1] for p in parts]), 0.0, 1.0)
    scales = np.concatenate([p[2] for p in parts]).astype(np.float32)
    n = len(means)
    quats = np.tile(np.float32([1, 0, 0, 0]), (n, 1))
    sh = ((rgb - 0.5) / SH_C0).astype(np.float32)[:, None, :]
    return Gaussians(means, quats, scales, np.full(n, OPACITY, np.float32), sh)


def main() -> None:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("models/scenes/tabletop.spz")
    g = tabletop()
    save_spz(out, g)
    print(f"{out}: {len(g)} Gaussians, {out.stat().st_size / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
