"""Camera poses for a dataset: a seeded sampler around the scene, or a poses file.

The sampler orbits the scene centre (azimuth about the scene's up axis, elevation toward it,
radius), with a look-at point jittered about the centre. Splits follow the paper's setting:

- `train`: `n_train` poses, stratified in azimuth over the training sector (so they cover it
  evenly) and uniform in elevation, radius and jitter;
- `interp`: `n_interp` poses inside the training sector, each halfway (in azimuth) between two
  neighbouring training poses: views the network has not seen but is surrounded by;
- `extrap`: `n_extrap` poses from a held-out azimuth sector just beyond the training sector.

Everything derives from `seed`; the same settings give the same poses.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from nhfd.scene.cameras import look_at, orbit_position, parse_axis
from nhfd.scene.gaussians import Gaussians
from nhfd.scene.suggest import suggest_camera

SPLITS = ("train", "interp", "extrap")
# The held-out shares of an orbit's poses (train : interp : extrap = 100 : 20 : 10, the paper's
# setting) and the look-at jitter as a fraction of the camera distance.
INTERP_SHARE, EXTRAP_SHARE = 20 / 130, 10 / 130
JITTER_FRACTION = 0.02


@dataclass(frozen=True)
class Pose:
    """World-to-camera rotation `R` (3x3, row-major list) and translation `t`, with its split and
    the orbit parameters it came from (for reports; None for poses read from a file)."""

    R: tuple[tuple[float, ...], ...]
    t: tuple[float, ...]
    split: str
    azimuth_deg: float | None = None
    elevation_deg: float | None = None
    radius: float | None = None

    def matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """`(R, t)` as float64 arrays, [3, 3] and [3]."""
        return np.array(self.R, np.float64), np.array(self.t, np.float64)

    @property
    def position(self) -> np.ndarray:
        """The camera centre in world coordinates, `-R^T t`, [3] float64 (scene units)."""
        r, t = self.matrices()
        return -r.T @ t


@dataclass(frozen=True)
class PoseSampler:
    """Orbit ranges around `center` (scene units, degrees). `azimuth_deg` is the training sector;
    the extrapolation sector is `extrap_width_deg` wide, starting `extrap_gap_deg` past its upper
    end. `radius` is `(min, max)`; `jitter` moves the look-at point uniformly within a cube of
    that half-size (scene units)."""

    center: tuple[float, float, float]
    up: str
    radius: tuple[float, float]
    azimuth_deg: tuple[float, float] = (-30.0, 30.0)
    elevation_deg: tuple[float, float] = (10.0, 30.0)
    jitter: float = 0.0
    extrap_gap_deg: float = 2.0
    extrap_width_deg: float = 10.0
    n_train: int = 100
    n_interp: int = 20
    n_extrap: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("azimuth_deg", "elevation_deg", "radius"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"{name} = ({lo}, {hi}): need finite low <= high")
        if not -89.0 <= self.elevation_deg[0] <= self.elevation_deg[1] <= 89.0:
            raise ValueError(f"elevation_deg = {self.elevation_deg}: must lie in [-89, 89]")
        if not self.radius[0] > 0:
            raise ValueError(f"radius = {self.radius}: must be positive")
        if self.n_train < 1 or self.n_interp < 0 or self.n_extrap < 0:
            raise ValueError("n_train must be >= 1 and n_interp, n_extrap >= 0")
        if not (self.jitter >= 0 and self.extrap_width_deg >= 0 and self.extrap_gap_deg >= 0):
            raise ValueError("jitter, extrap_gap_deg and extrap_width_deg must be >= 0")
        parse_axis(self.up)

    def sample(self) -> list[Pose]:
        """The seeded poses: `n_train` train, then `n_interp` interp, then `n_extrap` extrap."""
        rng = np.random.default_rng(self.seed)
        a0, a1 = self.azimuth_deg
        # Stratified azimuths: one per equal slice of the sector, at a random place in it.
        edges = np.linspace(a0, a1, self.n_train + 1)
        train_az = edges[:-1] + rng.uniform(0, 1, self.n_train) * np.diff(edges)
        sorted_az = np.sort(train_az)
        if self.n_train > 1:
            n_gaps = self.n_train - 1
            gaps = rng.choice(n_gaps, self.n_interp, replace=self.n_interp > n_gaps)
            interp_az = 0.5 * (sorted_az[gaps] + sorted_az[gaps + 1])
        else:
            interp_az = np.full(self.n_interp, sorted_az[0])
        e0 = a1 + self.extrap_gap_deg
        extrap_az = rng.uniform(e0, e0 + self.extrap_width_deg, self.n_extrap)
        poses = []
        for split, azs in (("train", train_az), ("interp", interp_az), ("extrap", extrap_az)):
            for az in azs:
                poses.append(self._pose(rng, float(az), split))
        return poses

    def _pose(self, rng: np.random.Generator, az: float, split: str) -> Pose:
        el = float(rng.uniform(*self.elevation_deg))
        r = float(rng.uniform(*self.radius))
        jitter = rng.uniform(-self.jitter, self.jitter, 3)
        center = np.asarray(self.center, np.float64)
        eye = orbit_position(center, az, el, r, self.up)
        rot, t = look_at(eye, center + jitter, self.up)
        return Pose(_tuple2(rot), tuple(float(v) for v in t), split, az, el, r)

    def describe(self) -> dict:
        """The sampler's settings as a dict (for the manifest)."""
        return asdict(self)


def _tuple2(m: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in m)


def envelope(poses: list[Pose], center: np.ndarray) -> dict:
    """The pose envelope: ranges of distance to the centre and of camera positions, for the
    manifest (the daemon warns when a requested view leaves it)."""
    pos = np.array([p.position for p in poses])
    dist = np.linalg.norm(pos - np.asarray(center), axis=1)
    out: dict = {
        "n": len(poses),
        "distance": [float(dist.min()), float(dist.max())],
        "position_min": [float(v) for v in pos.min(0)],
        "position_max": [float(v) for v in pos.max(0)],
    }
    az = [p.azimuth_deg for p in poses if p.azimuth_deg is not None]
    el = [p.elevation_deg for p in poses if p.elevation_deg is not None]
    if az:
        out["azimuth_deg"] = [min(az), max(az)]
        out["elevation_deg"] = [min(el), max(el)]
    return out


def save_poses(path: Path, poses: list[Pose]) -> None:
    """Write `poses` to `path` as the JSON list `load_poses` reads."""
    path.write_text(json.dumps([asdict(p) for p in poses], indent=1))


def load_poses(path: Path) -> list[Pose]:
    """A poses file: a JSON list of objects with `R` (3x3) and `t` (3), or `position` and
    `look_at` (and optional `up`, default "+z"); `split` defaults to "train"."""
    try:
        items = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(items, list) or not items:
        raise ValueError(f"{path}: expected a non-empty JSON list of poses")
    poses = []
    for i, item in enumerate(items):
        where = f"{path}: pose {i}"
        if not isinstance(item, dict):
            raise ValueError(f"{where}: expected an object")
        split = item.get("split", "train")
        if split not in SPLITS:
            raise ValueError(f"{where}: split {split!r} is not one of {SPLITS}")
        try:
            if "R" in item:
                rot = np.array(item["R"], np.float64).reshape(3, 3)
                t = np.array(item["t"], np.float64).reshape(3)
            else:
                rot, t = look_at(item["position"], item["look_at"], item.get("up", "+z"))
        except (KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"{where}: needs R and t, or position and look_at ({exc})") from exc
        if not (np.isfinite(rot).all() and np.isfinite(t).all()):
            raise ValueError(f"{where}: values must be finite")
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5):
            raise ValueError(f"{where}: R is not a rotation matrix")
        poses.append(Pose(_tuple2(rot), tuple(float(v) for v in t), split))
    return poses


def orbit_sampler(
    g: Gaussians,
    up: str,
    *,
    width_px: int,
    height_px: int,
    fov_x_deg: float,
    views: int = 130,
    azimuth_deg: tuple[float, float] = (-30.0, 30.0),
    elevation_deg: tuple[float, float] = (10.0, 30.0),
    radius_scale: tuple[float, float] = (0.9, 1.1),
    seed: int = 0,
) -> PoseSampler:
    """The default orbit for `g` (`nhfd dataset build`, `nhfd scene reduce`, `nhfd model build`):
    `views` poses split by `INTERP_SHARE` and `EXTRAP_SHARE` around the Gaussians' median, at
    `radius_scale` times the distance of the camera `nhfd.scene.suggest` places for a
    `width_px` x `height_px` view of `fov_x_deg`."""
    if views < 1:
        raise ValueError(f"views must be >= 1, got {views}")
    cam = suggest_camera(g, width_px, height_px, up, fov_x_deg=fov_x_deg)
    center = np.median(g.means, axis=0)
    dist = float(np.linalg.norm(cam.position - center))
    n_interp, n_extrap = round(views * INTERP_SHARE), round(views * EXTRAP_SHARE)
    return PoseSampler(
        center=tuple(float(v) for v in center), up=up,
        radius=(radius_scale[0] * dist, radius_scale[1] * dist), azimuth_deg=tuple(azimuth_deg),
        elevation_deg=tuple(elevation_deg), jitter=JITTER_FRACTION * dist,
        n_train=max(1, views - n_interp - n_extrap), n_interp=n_interp, n_extrap=n_extrap,
        seed=seed,
    )  # fmt: skip
