"""One dataset example: the pure unit of work, and its atomic file.

`make_example(scene, pose, mapping, settings, seed)` depends only on its arguments, so results do
not depend on how many workers run or in which order (a distributed executor can call it as is).
A shard is an uncompressed `.npz` written to a temporary name and renamed into place, so an
interrupted build never leaves a half-written shard under the final name. Its bytes depend only on
its contents (fixed zip dates, fixed member order), so builds on different machines, executors or
days are compared by comparing files.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from nhfd.config import OpticsSettings, SLMSettings
from nhfd.dataset.poses import Pose
from nhfd.holo import band_limit, colour_sampling, scene_hologram
from nhfd.optics import Aperture, reference_to_slm
from nhfd.scene.cameras import Camera, intrinsics_from_fov
from nhfd.scene.gaussians import Gaussians
from nhfd.scene.lightfield import DepthMapping
from nhfd.scene.raster import RasterSettings, render

SHARD_KEYS = ("rgb", "depth", "alpha", "field", "amp_samples", "meta")
FORMAT_VERSION = 1


def _optics_defaults(optics: OpticsSettings, slm: SLMSettings) -> dict:
    """The optics of a configuration's `[optics]` and `[slm]` sections (the panel and its pitch)
    in ExampleSettings' SI fields: the one source of wavelengths, pitch, volume, z0, panel and
    aperture."""
    o = optics
    return {
        "wavelengths_m": tuple(v * 1e-9 for v in o.wavelengths_nm),
        "pitch_m": slm.pitch_um * 1e-6,
        "volume_m": (o.volume_mm[0] * 1e-3, o.volume_mm[1] * 1e-3),
        "z0_m": o.z0_mm * 1e-3,
        "panel_hw": (slm.height_px, slm.width_px),
        "aperture_shape": o.aperture.shape,
        "cutoff_per_px": tuple(o.aperture.cutoff_per_px),
    }


# The defaults of the configuration's sections (what `nhfd.config.Config()` holds).
_DEFAULT_OPTICS = _optics_defaults(OpticsSettings(), SLMSettings())


@dataclass(frozen=True)
class ExampleSettings:
    """Everything an example depends on besides the scene, the pose and the seed (SI units).
    The optics default to the packaged nhfd.toml; `from_config` takes a lab's."""

    width_px: int = 1024
    height_px: int = 576
    fov_x_deg: float = 40.0
    near_fraction: float = 0.01
    wavelengths_m: tuple[float, ...] = _DEFAULT_OPTICS["wavelengths_m"]
    pitch_m: float = _DEFAULT_OPTICS["pitch_m"]
    volume_m: tuple[float, float] = _DEFAULT_OPTICS["volume_m"]
    z0_m: float = _DEFAULT_OPTICS["z0_m"]
    panel_hw: tuple[int, int] = _DEFAULT_OPTICS["panel_hw"]
    aperture_shape: str = _DEFAULT_OPTICS["aperture_shape"]
    cutoff_per_px: tuple[float, ...] = _DEFAULT_OPTICS["cutoff_per_px"]
    phase: str = "depth"
    shared_views: bool = True
    windows: tuple[int | None, ...] | None = None
    antialias: bool = False
    amplitude_samples: int = 4096
    extra: dict = field(default_factory=dict)

    @staticmethod
    def from_config(optics: OpticsSettings, slm: SLMSettings, **overrides) -> ExampleSettings:
        """The optics of a configuration's `[optics]` and `[slm]` sections, plus `overrides`
        (ExampleSettings' fields)."""
        return ExampleSettings(**{**_optics_defaults(optics, slm), **overrides})

    def __post_init__(self) -> None:
        if not (1 <= self.width_px <= 8192 and 1 <= self.height_px <= 8192):
            raise ValueError(
                f"size {self.width_px}x{self.height_px}: width and height must be 1..8192 px"
            )
        if self.width_px > self.panel_hw[1] or self.height_px > self.panel_hw[0]:
            raise ValueError(
                f"size {self.width_px}x{self.height_px} is larger than the "
                f"{self.panel_hw[1]}x{self.panel_hw[0]} panel"
            )
        if not 1.0 <= self.fov_x_deg <= 170.0:
            raise ValueError(f"fov_x_deg = {self.fov_x_deg}: must be in [1, 170]")
        if self.phase not in ("depth", "zero", "random"):
            raise ValueError(f"phase = {self.phase!r}: must be depth, zero or random")

    def camera(self, pose: Pose, distance: float) -> Camera:
        """The pose's camera at this size; the near plane is a fraction of the distance to the
        scene centre, so it scales with the scene's units."""
        fx, fy, cx, cy = intrinsics_from_fov(self.width_px, self.height_px, self.fov_x_deg)
        r, t = pose.matrices()
        near = max(self.near_fraction * distance, 1e-9)
        return Camera(r, t, fx, fy, cx, cy, self.width_px, self.height_px, near=near)

    def aperture(self):
        """The Fourier aperture of these settings (shape, cutoff per colour in cycles/px)."""
        return Aperture(shape=self.aperture_shape, cutoff_per_px=tuple(self.cutoff_per_px))

    def to_json(self) -> dict:
        """The settings as a dict, for the manifest."""
        return asdict(self)


def camera_distance(pose: Pose, center: np.ndarray) -> float:
    """The distance from the pose's camera to `center` [3] (scene units)."""
    return float(np.linalg.norm(pose.position - np.asarray(center, np.float64)))


def make_example(
    g: Gaussians,
    pose: Pose,
    center: np.ndarray,
    mapping: DepthMapping,
    settings: ExampleSettings,
    seed: int,
    device: str = "cpu",
) -> dict:
    """Render the central view and compute the band-limited reference-plane hologram.

    `device` "cuda" (or "cuda:N") renders with gsplat and inverts and propagates on that GPU;
    the arrays returned are on the host either way.

    Returns a dict of arrays (`rgb` [3,H,W] sRGB, `depth`/`alpha` [H,W], `field` [3,H,W]
    complex64, `amp_samples` [n] float32: amplitudes of content pixels on the SLM plane, which the
    builder pools into the dataset's amplitude scale) and `timing` (seconds per stage)."""
    import time

    import torch

    t0 = time.perf_counter()
    cam = settings.camera(pose, camera_distance(pose, center))
    raster = RasterSettings(antialias=settings.antialias)
    central = (render(g, cam, raster) if device == "cpu" else
               render(g, cam, raster, backend="gsplat", device=device))
    aperture = settings.aperture()
    sampling = colour_sampling(
        settings.wavelengths_m,
        settings.pitch_m,
        settings.volume_m,
        aperture,
        windows=settings.windows,
        shared=settings.shared_views,
    )
    holo = scene_hologram(
        g,
        cam,
        mapping,
        settings.pitch_m,
        sampling,
        phase=settings.phase,  # type: ignore[arg-type]
        seed=seed,
        shared_views=settings.shared_views,
        settings=raster,
        device=device,
    )
    t1 = time.perf_counter()
    field = band_limit(holo.field, aperture)
    on_slm = reference_to_slm(
        field, settings.panel_hw, settings.z0_m, settings.pitch_m, settings.wavelengths_m,
        aperture=aperture,
    )  # fmt: skip
    amp = on_slm.abs().reshape(-1)
    peak = float(amp.max()) if amp.numel() else 0.0
    content = amp[amp > 0.01 * peak] if peak > 0 else amp[:0]
    rng = np.random.default_rng(seed)
    n = min(settings.amplitude_samples, int(content.numel()))
    idx = rng.choice(int(content.numel()), n, replace=False) if n else np.zeros(0, np.int64)
    samples = content[torch.from_numpy(idx).to(content.device)].cpu().numpy().astype(np.float32)
    t2 = time.perf_counter()
    return {
        "rgb": central.rgb,
        "depth": central.depth,
        "alpha": central.alpha,
        "field": field.cpu().numpy().astype(np.complex64),
        "amp_samples": samples,
        "timing": {
            "render_s": holo.render_s + (t1 - t0 - holo.render_s - holo.invert_s),
            "invert_s": holo.invert_s,
            "slm_amplitude_s": t2 - t1,
            "views": holo.n_views,
        },
        "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "near": cam.near},
    }


# Zip member dates: numpy's savez stamps the time of writing, which would make two builds of the
# same example differ in their bytes. 1980-01-01 is the earliest date a zip can hold.
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def _write_npz(f, arrays: dict[str, np.ndarray]) -> None:
    """An uncompressed .npz (np.load reads it) whose bytes depend only on `arrays`."""
    with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, array in arrays.items():
            info = zipfile.ZipInfo(name + ".npy", date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_STORED
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)


def write_shard(path: Path, example: dict, meta: dict) -> None:
    """Write atomically: a temporary file in the same folder, flushed, then renamed."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.stem + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            _write_npz(f, {
                "rgb": example["rgb"],
                "depth": example["depth"],
                "alpha": example["alpha"],
                "field": example["field"],
                "amp_samples": example["amp_samples"],
                "meta": np.array(json.dumps(meta)),
            })  # fmt: skip
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_shard(path: Path) -> dict:
    """A shard's arrays and its `meta` dict; a clear error if it is not a complete shard."""
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in SHARD_KEYS if k not in z.files]
            if missing:
                raise ValueError(f"{path}: not a complete shard (missing {missing})")
            out = {k: z[k] for k in SHARD_KEYS if k != "meta"}
            out["meta"] = json.loads(str(z["meta"]))
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        if isinstance(exc, ValueError) and "not a complete shard" in str(exc):
            raise
        raise ValueError(f"{path}: unreadable shard ({exc})") from exc
    for k in ("rgb", "depth", "field"):
        a = out[k]
        if not np.isfinite(a.real if np.iscomplexobj(a) else a).all() or (
            np.iscomplexobj(a) and not np.isfinite(a.imag).all()
        ):
            raise ValueError(f"{path}: {k} holds non-finite values")
    return out


def shard_is_valid(path: Path, manifest_key: str) -> bool:
    """True if `path` is a complete shard written for this manifest."""
    if not path.exists():
        return False
    try:
        return read_shard(path)["meta"].get("manifest_key") == manifest_key
    except ValueError:
        return False


def example_seed(base_seed: int, index: int) -> int:
    """A per-example seed from the base seed and the pose index (independent of workers)."""
    return int(np.random.SeedSequence([int(base_seed), int(index)]).generate_state(1)[0])


