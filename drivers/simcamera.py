"""The simulated camera: what the simulated SLM shows, imaged through a "true" bench.

`TrueBench` is the bench as it really is, deliberately richer than the model that calibration
fits (design.md, "twins are faithful"), so calibration is never tested against its own equations:

    grey frame --(per-colour, non-parametric, wiggly grey->phase table, random sign)--> phase
      --(SLM pixels oversampled 2x, inter-pixel crosstalk = blur of the LC phase,
         fill factor: the inter-pixel gap reflects unmodulated light)--> field on the panel
      --(zero-order leakage: a fraction of unmodulated light; Gaussian illumination, offset)-->
      --(Fourier aperture of the relay + ASM to z = (stage - stage_at_slm) / M^2 + offset[colour])
      --(lateral magnification M, rotation, mirror flip, shift; camera pixel integration)-->
      --(laser power, exposure, gain, PRNU, dark current, shot + read noise, full well,
         dark offset + DSNU, gamma-like response, ADC bits)--> raw levels

Propagation and the aperture are `nhfd.optics` (`propagate`, `Aperture`), never re-implemented.
Units are SI (metres, seconds, radians). SLM-plane coordinates: x along columns, y along rows,
origin at the panel's centre; camera pixel (row, col) has its centre at (col, row).

The camera base class (`nhfd.drivers.camera.Camera`) then inverts the response, averages bursts
and subtracts the dark frame, exactly as it does for a real camera.

Two computations of the same noise-free image: `SimulatedCamera.optical_image`, the one every
capture uses (only the lit colours, float32 from the grey levels on, what depends on the bench and
the grid alone memoised), and `optical_image_reference`, the plain one it is checked against
(every colour in float64 through `panel_field`, the pupil in complex128;
tests/drivers/test_simcamera_speed.py).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import time
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from nhfd.config import Config
from nhfd.optics import Aperture, KernelCache, PhaseCurve, propagate
from nhfd.optics.aperture import SHAPES

from .camera import Camera, CameraSettings, CameraTimeout, ResponseCurve
from .errors import DeviceError
from .slm import GREY_LEVELS

# HOLOEYE ships PLUTO-VIS panels with a 2 pi table at 532 nm; at other wavelengths the stroke
# scales roughly as 532 / lambda (docs/physics.md, "Double-phase amplitude coding and the SLM":
# phase to grey).
PANEL_CALIBRATION_WAVELENGTH_M = 532e-9

# The simulated camera's propagation kernels kept between captures. At the 1920 x 1080 panel one
# colour's kernel on the 2x oversampled, padded grid is 63-67 MiB (complex64), and computing it
# costs more than the propagation itself (0.36 s against 0.17 s, 2 cores); citl cycles through
# its default 3 planes x 3 colours in the same order every step, so a least-recently-used cache
# that holds fewer than all 9 never hits. Small panels use a small part of it.
KERNEL_CACHE_BYTES = 640 * 2**20

FrameSource = Callable[[], Any]
PowerSource = Callable[[], Sequence[float]]
PositionSource = Callable[[], float]


def wiggly_phase_table(
    stroke_rad: float, seed: int, wiggle: float = 0.25, levels: int = GREY_LEVELS
) -> tuple[float, ...]:
    """A strictly increasing grey -> phase table with `phase[levels-1] = stroke (levels-1)/levels`
    (like the linear curve's end point) but an S-shaped, wiggly course in between.

    The increments are `1 + sum_k a_k sin(2 pi k t + theta_k)` with `sum |a_k| < 1`, so they stay
    positive (monotone) whatever the seed; the S-shape is the slow start and end that real LC
    panels show at the ends of their voltage range.
    """
    rng = np.random.default_rng(seed)
    t = (np.arange(levels) + 0.5) / levels
    amps = wiggle * rng.uniform(0.5, 1.0, 4) / np.arange(1, 5) / 2.1
    phases = rng.uniform(0, 2 * np.pi, 4)
    inc = 1 + sum(a * np.sin(2 * np.pi * (k + 1) * t + p)
                  for k, (a, p) in enumerate(zip(amps, phases, strict=True)))
    inc *= 0.55 + 1.8 * t * (1 - t)  # S-shape: slow at both ends
    table = np.concatenate([[0.0], np.cumsum(inc[:-1])])
    table *= stroke_rad * (levels - 1) / levels / table[-1]
    return tuple(float(v) for v in table)


def camera_response(gamma: float, wiggle: float, bit_depth: int) -> ResponseCurve:
    """A gamma-like camera response with a small smooth wiggle (not a pure power law), as a
    table: linear = t^gamma + wiggle sin(2 pi t) t (1 - t), t = raw / max."""
    levels = 2**bit_depth
    t = np.arange(levels) / (levels - 1)
    linear = t**gamma + wiggle * np.sin(2 * np.pi * t) * t * (1 - t)
    if np.any(np.diff(linear) <= 0):
        raise ValueError(f"camera response gamma {gamma}, wiggle {wiggle} is not increasing")
    return ResponseCurve(linear / linear[-1])


_CONFIG = Config()

# What a twin's TOML (`TrueBench.from_toml`) may set, and the range each number must lie in
# (inclusive; for a list, each element, and the list's length). `randomised_seed` starts from
# `TrueBench.randomised(seed)` and the other keys override its draws.
TWIN_TOML_NUMBERS: dict[str, tuple[float, float]] = {
    "pitch_m": (1e-7, 1e-4), "wavelengths_m": (3e-7, 2e-6), "oversample": (1, 8),
    "fill_factor": (0.01, 1.0), "gap_reflectance": (0.0, 1.0),
    "crosstalk_sigma_m": (0.0, 2e-5), "phase_table_seed": (0, 2**31 - 1),
    "phase_sign": (-1, 1), "zero_order_fraction": (0.0, 0.99),
    "source_waist_m": (1e-4, 1.0), "source_offset_m": (-0.05, 0.05),
    "zernike_rad": (-10.0, 10.0), "aperture_cutoff_per_px": (0.01, 0.5),
    "magnification": (0.01, 100.0), "rotation_deg": (-360.0, 360.0),
    "shift_m": (-0.05, 0.05), "stage_at_slm_mm": (-1000.0, 1000.0),
    "z_offset_m": (-0.01, 0.01), "camera_pitch_m": (1e-7, 1e-4),
    "sensor_hw_px": (16, 20000), "electrons_per_s": (0.0, 1e12),
    "colour_matrix": (0.0, 1.0), "full_well_e": (1.0, 1e8), "bit_depth": (8, 16),
    "response_gamma": (0.2, 5.0), "response_wiggle": (0.0, 0.1), "dark_level": (0.0, 0.5),
    "dsnu": (0.0, 0.1), "dark_current_e_per_s": (0.0, 1e6), "prnu": (0.0, 0.5),
    "read_noise_e": (0.0, 1e4), "noise_seed": (0, 2**62), "pattern_seed": (0, 2**62),
    "phase_tables_rad": (-1000.0, 1000.0), "randomised_seed": (0, 2**62),
}
# Lists of a fixed length (None: any length up to the bound), and what holds whole numbers.
_TWIN_TOML_LENGTHS: dict[str, tuple[int, int]] = {
    "wavelengths_m": (3, 3), "source_offset_m": (2, 2), "zernike_rad": (0, 40),
    "aperture_cutoff_per_px": (3, 3), "shift_m": (2, 2), "z_offset_m": (3, 3),
    "sensor_hw_px": (2, 2), "electrons_per_s": (3, 3), "colour_matrix": (3, 3),
    "phase_tables_rad": (3, 3),
}
_TWIN_TOML_INTS = ("oversample", "phase_table_seed", "phase_sign", "sensor_hw_px", "bit_depth",
                   "noise_seed", "pattern_seed", "randomised_seed")
_TWIN_TOML_BOOLS = ("mirror_x", "shot_noise")
_TWIN_TOML_STRINGS = {"aperture_shape": SHAPES}


def _twin_number(key: str, value: Any, where: str) -> float | int:
    lo, hi = TWIN_TOML_NUMBERS[key]
    whole = key in _TWIN_TOML_INTS
    ok = isinstance(value, int | float) and not isinstance(value, bool) and \
        (not whole or isinstance(value, int)) and math.isfinite(value) and lo <= value <= hi
    if not ok:
        kind = "a whole number" if whole else "a number"
        raise ValueError(f"{where}: {key} = {value!r}: must be {kind} in {lo:g}..{hi:g}")
    return value


def _twin_value(key: str, value: Any, where: str) -> Any:
    """One TOML value parsed for field `key` (ValueError naming it and its range)."""
    if key in _TWIN_TOML_BOOLS:
        if not isinstance(value, bool):
            raise ValueError(f"{where}: {key} = {value!r}: must be true or false")
        return value
    if key in _TWIN_TOML_STRINGS:
        if value not in _TWIN_TOML_STRINGS[key]:
            raise ValueError(f"{where}: {key} = {value!r}: must be one of "
                             f"{', '.join(_TWIN_TOML_STRINGS[key])}")
        return value
    if key not in _TWIN_TOML_LENGTHS:
        return _twin_number(key, value, where)
    lo, hi = _TWIN_TOML_LENGTHS[key]
    if not isinstance(value, list) or not lo <= len(value) <= hi:
        n = str(lo) if lo == hi else f"{lo}..{hi}"
        raise ValueError(f"{where}: {key} = {value!r}: must be a list of {n} values")
    if key == "colour_matrix":
        if any(not isinstance(r, list) or len(r) != 3 for r in value):
            raise ValueError(f"{where}: {key}: must be 3 rows of 3 numbers")
        return tuple(tuple(_twin_number(key, v, where) for v in r) for r in value)
    if key == "phase_tables_rad":
        if any(not isinstance(t, list) or len(t) != GREY_LEVELS for t in value):
            raise ValueError(f"{where}: {key}: must be 3 tables (R, G, B) of {GREY_LEVELS} "
                             "values")
        return tuple(tuple(float(_twin_number(key, v, where)) for v in t) for t in value)
    return tuple(_twin_number(key, v, where) for v in value)




@dataclass(frozen=True)
class TrueBench:
    """The bench as it really is. Defaults are realistic, not ideal. Colours are R, G, B."""

    # --- SLM (pitch and wavelengths of the packaged nhfd.toml; the panel size comes from the
    # frames shown)
    pitch_m: float = _CONFIG.slm.pitch_um * 1e-6
    wavelengths_m: tuple[float, float, float] = tuple(  # type: ignore[assignment]
        v * 1e-9 for v in _CONFIG.optics.wavelengths_nm
    )
    # Samples per SLM pixel per axis on the simulation grid (resolves the crosstalk).
    oversample: int = 2
    # Fraction of each pixel's area that is modulated (PLUTO-2.1: 93%).
    fill_factor: float = 0.93
    # Amplitude reflectance of the inter-pixel gap (unmodulated light) relative to a pixel.
    gap_reflectance: float = 0.5
    # Fringing field: the LC phase is blurred across pixel edges by a Gaussian of this sigma.
    crosstalk_sigma_m: float = 1.0e-6
    # Grey -> phase tables, one per colour (256 values, strictly increasing, unwrapped).
    # None: wiggly tables with a stroke of 2 pi * 532 nm / lambda (see wiggly_phase_table).
    phase_tables_rad: tuple[tuple[float, ...], ...] | None = None
    phase_table_seed: int = 11
    # +1, or -1 where the bench shows the conjugate (the model's sign must match it).
    phase_sign: int = 1
    # Intensity fraction of the light that leaves the panel unmodulated (cover glass, LC that
    # does not follow): it is coherent with the signal and passes the aperture as the zero order.
    zero_order_fraction: float = 0.01
    # Gaussian illumination: 1/e^2 intensity radius and the beam centre on the panel.
    source_waist_m: float = 9e-3
    source_offset_m: tuple[float, float] = (0.35e-3, -0.2e-3)
    # Aberrations of the relay: a pupil phase in its Fourier plane, Zernike coefficients for
    # Noll j = 5, 6, ... in order (piston, tilt and defocus are the placement and z offsets),
    # radians at `wavelengths_m[1]` (green). The pupil coordinate is rho = |f| / cutoff (f in
    # cycles per SLM pixel, the colour's aperture cutoff), so the square iris's corners reach
    # rho = sqrt(2); another colour sees the same optical path, lambda_G / lambda radians.
    # () = an aberration-free relay.
    zernike_rad: tuple[float, ...] = ()

    # --- relay (4f with an iris in its Fourier plane) and camera placement
    aperture_shape: str = "square"
    aperture_cutoff_per_px: tuple[float, float, float] = (0.25, 0.25, 0.25)
    # Lateral magnification from the SLM plane to the sensor; longitudinal is its square.
    magnification: float = 0.75
    # Rotation of the image on the sensor (a 4f relay inverts: ~180 deg) and an optional flip of
    # the x axis (a fold mirror), applied before the rotation.
    rotation_deg: float = 180.4
    mirror_x: bool = False
    # Where the panel's centre lands on the sensor, from the sensor's centre (sensor plane, m).
    shift_m: tuple[float, float] = (28e-6, -17e-6)
    # Stage reading (mm) whose object plane is the SLM itself for green, and per-colour focus
    # offsets in SLM space (chromatic focal shift of the relay).
    stage_at_slm_mm: float = 10.0
    z_offset_m: tuple[float, float, float] = (70e-6, 0.0, -50e-6)

    # --- sensor (a 5 MP machine-vision colour camera, 3.45 um pixels)
    camera_pitch_m: float = _CONFIG.devices.camera_settings.pixel_pitch_um * 1e-6
    sensor_hw_px: tuple[int, int] = (2048, 2448)
    # Electrons per second per pixel where the SLM-plane relative intensity is 1 (a flat mirror
    # with the beam's peak amplitude), at full laser power, 0 dB.
    electrons_per_s: tuple[float, float, float] = (0.8e6, 1.0e6, 0.7e6)
    # Colour camera: row k = channel k's response to the R, G, B laser lines (Bayer filters).
    colour_matrix: tuple[tuple[float, float, float], ...] = (
        (0.92, 0.05, 0.02), (0.06, 0.88, 0.10), (0.01, 0.07, 0.85))
    full_well_e: float = 10500.0
    bit_depth: int = 12
    response_gamma: float = 1.06
    response_wiggle: float = 0.01
    # Dark offset (fraction of full scale), its fixed pattern (DSNU, std) and dark current.
    dark_level: float = 0.015
    dsnu: float = 0.0015
    dark_current_e_per_s: float = 5.0
    # Photo-response non-uniformity (std of the per-pixel gain).
    prnu: float = 0.008
    read_noise_e: float = 2.5
    shot_noise: bool = True
    noise_seed: int = 0
    pattern_seed: int = 1234

    def __post_init__(self) -> None:
        if self.oversample < 1:
            raise ValueError(f"oversample = {self.oversample}: must be >= 1")
        if not 0 < self.fill_factor <= 1:
            raise ValueError(f"fill_factor = {self.fill_factor}: must be in (0, 1]")
        if not 0 <= self.zero_order_fraction < 1:
            raise ValueError(f"zero_order_fraction = {self.zero_order_fraction}: need [0, 1)")
        if self.phase_sign not in (1, -1):
            raise ValueError(f"phase_sign = {self.phase_sign}: must be +1 or -1")
        if self.magnification <= 0:
            raise ValueError(f"magnification = {self.magnification}: must be > 0 "
                             "(an inverted image is rotation_deg = 180)")
        tables = self.phase_tables_rad
        if tables is None:
            tables = tuple(
                wiggly_phase_table(2 * math.pi * PANEL_CALIBRATION_WAVELENGTH_M / lam,
                                   self.phase_table_seed + c)
                for c, lam in enumerate(self.wavelengths_m)
            )
        if len(tables) != 3 or any(len(t) != GREY_LEVELS for t in tables):
            raise ValueError("phase_tables_rad: need 3 tables (R, G, B) of 256 values")
        for t in tables:
            PhaseCurve(t)  # strictly increasing and finite, or ValueError
        # Not a field: derived from phase_tables_rad / phase_table_seed (replace() re-derives it).
        object.__setattr__(self, "_tables", tuple(tuple(float(v) for v in t) for t in tables))

    @classmethod
    def randomised(cls, seed: int, **overrides: Any) -> TrueBench:
        """A plausible bench drawn at random: phase sign, tables, offsets, placement, beam."""
        rng = np.random.default_rng(seed)
        drawn: dict[str, Any] = dict(
            phase_sign=int(rng.choice([1, -1])),
            phase_table_seed=int(rng.integers(1 << 30)),
            fill_factor=float(rng.uniform(0.88, 0.96)),
            zero_order_fraction=float(rng.uniform(0.003, 0.03)),
            source_offset_m=tuple(float(v) for v in rng.normal(0, 0.4e-3, 2)),
            magnification=float(rng.uniform(0.6, 1.2)),
            rotation_deg=float(180 + rng.normal(0, 1.0)),
            mirror_x=bool(rng.random() < 0.5),
            shift_m=tuple(float(v) for v in rng.normal(0, 40e-6, 2)),
            stage_at_slm_mm=float(rng.uniform(8, 12)),
            z_offset_m=(float(rng.normal(0, 80e-6)), 0.0, float(rng.normal(0, 80e-6))),
            noise_seed=int(rng.integers(1 << 30)),
        )
        drawn.update(overrides)
        return cls(**drawn)

    @classmethod
    def from_toml(cls, path: str | Path) -> TrueBench:
        """A twin from a TOML file of `TrueBench` fields (top-level keys; lists for tuples),
        the defaults for what it leaves out; `randomised_seed = N` starts from
        `randomised(N)` instead. An unknown key, a value of the wrong kind or outside
        `TWIN_TOML_NUMBERS`' range is refused with a ValueError naming the file, the key and
        what it allows."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"--twin {path}: cannot read it ({exc})") from None
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"--twin {path}: not TOML ({exc})") from None
        where = f"twin {path}"
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(k for k in data if k not in fields and k != "randomised_seed")
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: "
                             f"randomised_seed, {', '.join(sorted(fields))}")
        values = {k: _twin_value(k, v, where) for k, v in data.items()}
        seed = values.pop("randomised_seed", None)
        try:
            return cls(**values) if seed is None else cls.randomised(int(seed), **values)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None

    # --- derived quantities -----------------------------------------------------------------

    @property
    def phase_tables(self) -> tuple[tuple[float, ...], ...]:
        """The grey -> phase tables actually in use (R, G, B)."""
        return self._tables

    def phase_curves(self) -> list[PhaseCurve]:
        """The true tables as `PhaseCurve`s: what a perfect calibration would hand the coder."""
        return [PhaseCurve(t) for t in self._tables]

    @property
    def stage_scale(self) -> float:
        """Metres of object-plane (SLM-space) depth per metre of stage travel: 1 / M^2."""
        return 1.0 / self.magnification**2

    def z_m(self, stage_mm: float, colour: int) -> float:
        """Distance from the SLM (m) that the camera sees in focus at a stage reading."""
        return (stage_mm - self.stage_at_slm_mm) * 1e-3 * self.stage_scale + \
            self.z_offset_m[colour]

    def stage_mm_for(self, z_m: float, colour: int = 1) -> float:
        """The stage reading that brings distance `z_m` from the SLM into focus for a colour."""
        return self.stage_at_slm_mm + (z_m - self.z_offset_m[colour]) / self.stage_scale * 1e3

    def response(self) -> ResponseCurve:
        """The camera's response curve (gamma with its wiggle, at the sensor's bit depth)."""
        return camera_response(self.response_gamma, self.response_wiggle, self.bit_depth)

    def gain(self, gain_db: float) -> float:
        """The linear signal gain of `gain_db` dB: 10^(gain_db / 20)."""
        return 10 ** (gain_db / 20)

    def dark_level_at(self, exposure_s: float, gain_db: float = 0.0) -> float:
        """Mean linear value of a dark frame (offset plus dark current), fraction of full
        scale."""
        signal = self.dark_current_e_per_s * exposure_s * self.gain(gain_db) / self.full_well_e
        return self.dark_level + (1 - self.dark_level) * signal

    def _matrix(self) -> np.ndarray:
        """2 x 2 map from SLM-plane metres to sensor-plane metres (flip, rotate, magnify)."""
        a = math.radians(self.rotation_deg)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        flip = np.diag([-1.0 if self.mirror_x else 1.0, 1.0])
        return self.magnification * rot @ flip

    def slm_to_camera_px(self, x_m: float, y_m: float) -> tuple[float, float]:
        """Sensor pixel (col, row) where the SLM-plane point (x, y) is imaged."""
        v = self._matrix() @ np.array([x_m, y_m]) + np.asarray(self.shift_m)
        h, w = self.sensor_hw_px
        return (float((w - 1) / 2 + v[0] / self.camera_pitch_m),
                float((h - 1) / 2 + v[1] / self.camera_pitch_m))

    def camera_px_to_slm(self, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """SLM-plane coordinates (m) imaged at sensor positions (col, row)."""
        h, w = self.sensor_hw_px
        v = np.stack([(np.asarray(col) - (w - 1) / 2) * self.camera_pitch_m - self.shift_m[0],
                      (np.asarray(row) - (h - 1) / 2) * self.camera_pitch_m - self.shift_m[1]])
        xy = np.tensordot(np.linalg.inv(self._matrix()), v, axes=1)
        return xy[0], xy[1]

    def roi_for_panel(self, panel_hw_px: tuple[int, int], margin_px: int = 8
                      ) -> tuple[int, int, int, int]:
        """(top, left, height, width) of the sensor region that holds a panel's image."""
        ph, pw = panel_hw_px
        hx, hy = pw * self.pitch_m / 2, ph * self.pitch_m / 2
        pts = [self.slm_to_camera_px(sx * hx, sy * hy) for sx in (-1, 1) for sy in (-1, 1)]
        cols, rows = [p[0] for p in pts], [p[1] for p in pts]
        h, w = self.sensor_hw_px
        top = max(0, math.floor(min(rows)) - margin_px)
        left = max(0, math.floor(min(cols)) - margin_px)
        bottom = min(h, math.ceil(max(rows)) + margin_px + 1)
        right = min(w, math.ceil(max(cols)) + margin_px + 1)
        return top, left, bottom - top, right - left


def slm_frame_source(slm: Any) -> FrameSource:
    """Adapt an `nhfd.drivers.slm.SLM` (its `last_frame`, [3, H, W] or None) to a frame source;
    a panel that has shown nothing shows grey 0. An SLM that models its flip (`panel_frame()`:
    the simulated SLM) gives what the panel shows at the moment of the exposure."""

    if hasattr(slm, "panel_frame"):
        return slm.panel_frame

    def source() -> np.ndarray:
        last = slm.last_frame
        if last is None:
            return np.zeros(slm.shape, np.uint8)
        return np.ascontiguousarray(np.asarray(last).transpose(1, 2, 0))

    return source


class SimulatedCamera(Camera):
    """Images the frame shown on the simulated SLM through a `TrueBench`.

    Decoupled from the other drivers by three callables: `frame_source()` -> uint8 [H, W] or
    [H, W, 3] (R, G, B patterns), `laser_powers()` -> 3 relative powers in [0, 1], and
    `stage_position_mm()`. `roi` = (top, left, height, width) on the sensor (default: the whole
    sensor); keep it small for speed. The response curve used to linearise defaults to the
    bench's true one (as after a radiometric calibration); pass another to model an error.
    """

    def __init__(
        self,
        frame_source: FrameSource,
        laser_powers: PowerSource,
        stage_position_mm: PositionSource,
        bench: TrueBench | None = None,
        settings: CameraSettings | None = None,
        *,
        roi: tuple[int, int, int, int] | None = None,
        response: ResponseCurve | None = None,
        cache: KernelCache | None = None,
    ) -> None:
        self.bench = bench or TrueBench()
        base = settings or CameraSettings()
        # The bench's sensor decides the ADC depth; the settings' value describes a real camera.
        base = base.model_copy(update={"bit_depth": self.bench.bit_depth})
        super().__init__(base, response=response or self.bench.response())
        self._true_response = self.bench.response()
        self._frame_source = frame_source
        self._laser_powers = laser_powers
        self._stage_mm = stage_position_mm
        sh, sw = self.bench.sensor_hw_px
        self.roi = roi or (0, 0, sh, sw)
        top, left, h, w = self.roi
        if not (0 <= top and 0 <= left and h >= 1 and w >= 1 and top + h <= sh
                and left + w <= sw):
            raise ValueError(f"roi {roi}: must lie on the {sh} x {sw} sensor")
        self._cache = cache if cache is not None else KernelCache(KERNEL_CACHE_BYTES)
        self._rng = np.random.default_rng(self.bench.noise_seed)
        self._optical_key: tuple[Any, ...] | None = None
        self._optical: np.ndarray | None = None
        # Pure functions of the bench and the grid, reused across captures (CITL captures the
        # same geometry thousands of times): the pupil factor per colour, the ROI's sampling grid,
        # the illumination and crosstalk blur of the oversampled panel.
        self._pupils: dict[tuple[Any, ...], torch.Tensor] = {}
        self._grids: dict[tuple[Any, ...], tuple[torch.Tensor, int]] = {}
        self._panel_maps: dict[tuple[Any, ...], tuple[torch.Tensor, torch.Tensor,
                                                      torch.Tensor | None]] = {}
        # The lit colours' fields leaving the panel for the frame shown last (a focal stack, or
        # a colour lit again, reuses them): (frame key, {colour: [1, s H, s W] complex64}).
        self._fields: tuple[tuple[Any, ...], dict[int, torch.Tensor]] | None = None
        self._raw_levels = _RawLevels(self._true_response)
        self._prnu, self._dsnu = self._patterns()
        self._dark_offset = self.bench.dark_level + self._dsnu
        self._stalled = False

    def reseed(self, seed: int) -> None:
        """Restart the noise generator (captures after this repeat for the same seed)."""
        self._rng = np.random.default_rng(seed)

    # -- test-only fault injection -------------------------------------------------------------

    def stall(self) -> None:
        """Test-only: from now on every frame times out as a hung real camera's does (after
        exposure + frame_timeout_s, then CameraTimeout), until `resume()`."""
        self._stalled = True

    def resume(self) -> None:
        """Test-only: frames arrive again (the camera came back)."""
        self._stalled = False

    # -- Camera hooks ------------------------------------------------------------------------

    def _do_open(self) -> None:
        pass

    def _do_close(self) -> None:
        pass

    def _exposure_limits_s(self) -> tuple[float, float]:
        return (1e-6, 10.0)

    def _apply_exposure(self, exposure_s: float) -> float:
        return exposure_s

    def _apply_gain(self, gain_db: float) -> float:
        return gain_db

    def _grab(self) -> np.ndarray:
        line = self.trigger
        if line is None or not line.exposure_gates_write:
            return self._expose()
        # The exposure-active output is wired (drivers/trigger.py, "camera_exposure"): the line is
        # high from the exposure's start, when the panel is imaged, to its end, exposure_s later
        # in time (only then does the exposure take time: other benches keep fast captures).
        start = line.exposure_begins()
        try:
            raw = self._expose()
            left = start + self._exposure_s - line.clock()
            if left > 0:
                time.sleep(left)
        finally:
            line.exposure_ends(line.clock())
        return raw

    def _expose(self) -> np.ndarray:
        if self._stalled:
            timeout_s = self._exposure_s + self.settings.frame_timeout_s
            time.sleep(timeout_s)
            raise CameraTimeout(f"{self.name}: no frame within {timeout_s:g} s "
                                "(exposure + frame_timeout_s)")
        b = self.bench
        powers = np.asarray(self._laser_powers(), dtype=np.float64).reshape(-1)
        if powers.shape != (3,) or not np.isfinite(powers).all() or \
                powers.min() < 0 or powers.max() > 1:
            raise DeviceError(f"{self.name}: laser powers {powers.tolist()}: need 3 in [0, 1]")
        t = self._exposure_s
        # Colours whose laser is off are not propagated at all (zeros), which also keeps
        # field-sequential captures three times cheaper.
        lit = tuple(bool(p > 0) for p in powers)
        per_colour = self.optical_image(lit) if any(lit) else None  # [3, h, w] relative
        _, _, h, w = self.roi
        rate = powers * np.asarray(b.electrons_per_s)
        if self.settings.channels == "rgb":
            mix = np.asarray(b.colour_matrix) * rate[None, :]  # [channel, colour]
            shape: tuple[int, ...] = (3, h, w)
        else:
            mix = rate[None, :]
            shape = (1, h, w)
        electrons = np.zeros(shape, np.float64)
        if per_colour is not None:
            # Only the lit colours' planes: the dark ones are zeros.
            for c in np.flatnonzero(lit):
                electrons += mix[:, c, None, None] * per_colour[c] * t
        electrons *= self._prnu
        electrons += b.dark_current_e_per_s * t
        if b.shot_noise:
            electrons = self._rng.poisson(electrons).astype(np.float64)
        if b.read_noise_e > 0:
            electrons += self._rng.normal(0.0, b.read_noise_e, electrons.shape)
        # The pixel holds at most its full well; the ADC then clips at full scale.
        np.clip(electrons, 0.0, b.full_well_e, out=electrons)
        # signal = dark_level + dsnu + (1 - dark_level) gain electrons / full_well, the same
        # operations in place (a full sensor's frame is 40 MB a temporary).
        signal = electrons
        signal *= (1 - b.dark_level) * b.gain(self._gain_db)
        signal /= b.full_well_e
        signal += self._dark_offset
        raw = self._raw_levels(np.clip(signal, 0.0, 1.0, out=signal))
        return raw[0] if self.settings.channels == "mono" else raw.transpose(1, 2, 0)

    # -- the optics ----------------------------------------------------------------------------

    def _frame(self) -> np.ndarray:
        """The shown frame as uint8 [3, H, W] (one pattern per colour)."""
        a = np.asarray(self._frame_source())
        if a.dtype != np.uint8:
            raise DeviceError(f"{self.name}: SLM frame dtype {a.dtype}: expected uint8")
        if a.ndim == 2:
            return np.broadcast_to(a, (3, *a.shape))
        if a.ndim == 3 and a.shape[2] == 3:
            return a.transpose(2, 0, 1)
        raise DeviceError(f"{self.name}: SLM frame shape {a.shape}: expected [H, W] or [H, W, 3]")

    def optical_image(self, colours: Sequence[bool] = (True, True, True)) -> np.ndarray:
        """Noise-free relative irradiance per laser colour on the ROI, [3, h, w] float64 (1 = a
        flat mirror at the beam's peak, full power), for the current frame and stage position;
        colours not asked for are zero. What `optical_image_reference` computes, to float32's
        precision, at a fraction of its cost (the module's docstring)."""
        frame, stage, digest = self._shown()
        lit = tuple(bool(c) for c in colours)
        key = (digest, frame.shape, stage, lit, self.bench)
        if key != self._optical_key or self._optical is None:
            with torch.no_grad():
                self._optical = self._image_fast(frame, digest, stage, lit)
            self._optical_key = key
        return self._optical

    def optical_image_reference(self, colours: Sequence[bool] = (True, True, True)
                                ) -> np.ndarray:
        """`optical_image` computed plainly, as the true bench's chain reads (the module's
        docstring): every colour's panel field in float64 (`panel_field`), the pupil in
        complex128, the ROI sampled for all three colours; nothing memoised but the kernels,
        pupils and sampling grid (pure functions of the bench and the grids). For tests."""
        frame, stage, _ = self._shown()
        with torch.no_grad():
            return self._image(self.panel_field(frame), stage, colours)

    def _shown(self) -> tuple[np.ndarray, float, bytes]:
        """The shown frame [3, H, W] uint8, the stage reading (mm) and the frame's digest."""
        frame = self._frame()
        stage = float(self._stage_mm())
        if not math.isfinite(stage):
            raise DeviceError(f"{self.name}: stage position {stage!r}")
        digest = hashlib.blake2b(np.ascontiguousarray(frame).tobytes(), digest_size=16).digest()
        return frame, stage, digest

    def panel_field(self, frame: np.ndarray) -> torch.Tensor:
        """The complex field leaving the panel, [3, s H, s W] on the oversampled grid."""
        b = self.bench
        s = b.oversample
        grey = torch.from_numpy(np.ascontiguousarray(frame)).long()
        tables = torch.tensor(b.phase_tables, dtype=torch.float64)
        phase = torch.stack([tables[c][grey[c]] for c in range(3)])  # unwrapped, per pixel
        phase = phase.repeat_interleave(s, dim=-2).repeat_interleave(s, dim=-1)
        pitch = b.pitch_m / s
        if b.crosstalk_sigma_m > 0:
            # The fringing field smooths the LC's *unwrapped* phase (the voltage), so a jump
            # from grey 0 to 255 passes through every phase in between.
            phase = _gaussian_blur(phase, b.crosstalk_sigma_m / pitch)
        modulated = torch.polar(torch.ones_like(phase), b.phase_sign * phase)
        # Each sample holds the area mean of the reflected field: the fill factor's share is
        # modulated, the gap's share reflects unmodulated light.
        u = b.fill_factor * modulated + (1 - b.fill_factor) * b.gap_reflectance
        u = math.sqrt(1 - b.zero_order_fraction) * u + math.sqrt(b.zero_order_fraction)
        hs, ws = u.shape[-2:]
        y = (torch.arange(hs, dtype=torch.float64) - (hs - 1) / 2) * pitch
        x = (torch.arange(ws, dtype=torch.float64) - (ws - 1) / 2) * pitch
        r2 = (x[None, :] - b.source_offset_m[0]) ** 2 + (y[:, None] - b.source_offset_m[1]) ** 2
        return (u * torch.exp(-r2 / b.source_waist_m**2)).to(torch.complex64)

    def _image(self, panel: torch.Tensor, stage_mm: float, colours: Sequence[bool]
               ) -> np.ndarray:
        b = self.bench
        s = b.oversample
        pitch = b.pitch_m / s
        out = []
        for c in range(3):
            if not colours[c]:
                out.append(torch.zeros(panel.shape[-2:]))
                continue
            # The aperture's cutoff is per SLM pixel; on the oversampled grid it is s times less.
            ap = Aperture(b.aperture_shape, (b.aperture_cutoff_per_px[c] / s,))
            field = panel[c : c + 1]
            if any(b.zernike_rad):
                field = self._aberrate(field, c)
            u = propagate(field, b.z_m(stage_mm, c), pitch, [b.wavelengths_m[c]],
                          aperture=ap, padding="auto", cache=self._cache)
            out.append(u.abs().square()[0])
        return self.project_to_camera(torch.stack(out), pitch)

    def _aberrate(self, field: torch.Tensor, colour: int) -> torch.Tensor:
        """The relay's pupil phase applied to a colour's panel field [1, sH, sW] (a spectral
        product, so it commutes with the propagation and the aperture); zero-padded 2x so the
        aberrated spread does not wrap around the panel."""
        h, w = field.shape[-2:]
        spec = torch.fft.fft2(field.to(torch.complex128), s=(2 * h, 2 * w))
        out = torch.fft.ifft2(spec * self._pupil(h, w, colour))
        return out[..., :h, :w].to(field.dtype)

    def _pupil(self, h: int, w: int, colour: int, dtype: torch.dtype = torch.complex128
               ) -> torch.Tensor:
        """The relay's pupil factor exp(i phase) [2h, 2w] for a colour's field of [h, w]
        samples, computed in float64, as `dtype` (memoised per bench, grid, colour and dtype)."""
        b = self.bench
        key = (b, h, w, colour, dtype)
        pupil = self._pupils.get(key)
        if pupil is not None:
            return pupil
        s = b.oversample
        fy = torch.fft.fftfreq(2 * h, dtype=torch.float64)[:, None] * s  # cycles per SLM px
        fx = torch.fft.fftfreq(2 * w, dtype=torch.float64)[None, :] * s
        cutoff = b.aperture_cutoff_per_px[colour]
        rho = torch.sqrt(fx**2 + fy**2) / cutoff
        theta = torch.atan2(fy.expand_as(rho), fx.expand_as(rho))
        phase = torch.zeros_like(rho)
        for k, a in enumerate(b.zernike_rad):
            phase += a * _zernike_noll(5 + k, rho, theta)
        phase *= b.wavelengths_m[1] / b.wavelengths_m[colour]
        pupil = torch.polar(torch.ones_like(phase), phase).to(dtype)
        if len(self._pupils) >= 8:
            self._pupils.clear()
        self._pupils[key] = pupil
        return pupil

    # -- the optics, fast: what optical_image computes ------------------------------------------

    def _image_fast(self, frame: np.ndarray, digest: bytes, stage_mm: float,
                    lit: tuple[bool, ...]) -> np.ndarray:
        """`_image(panel_field(frame), stage_mm, lit)` for the lit colours only: a colour whose
        diode is off costs nothing, and a frame's field per colour is kept for the next capture
        of it (a focal stack)."""
        b = self.bench
        s = b.oversample
        pitch = b.pitch_m / s
        _, _, h, w = self.roi
        out = np.zeros((3, h, w), np.float64)
        frame_key = (digest, frame.shape, b)
        if self._fields is None or self._fields[0] != frame_key:
            self._fields = (frame_key, {})
        fields = self._fields[1]
        for c in (c for c in range(3) if lit[c]):
            field = fields.get(c)
            if field is None:
                field = fields[c] = self._colour_field(frame[c], c)
            ap = Aperture(b.aperture_shape, (b.aperture_cutoff_per_px[c] / s,))
            u = propagate(field, b.z_m(stage_mm, c), pitch, [b.wavelengths_m[c]],
                          aperture=ap, padding="auto", cache=self._cache)
            # |u|^2 without abs()'s square root.
            intensity = torch.view_as_real(u).square().sum(dim=-1)
            out[c] = self._project_fast(intensity[0], pitch)[0]
        return out

    def _colour_field(self, grey: np.ndarray, colour: int) -> torch.Tensor:
        """One colour's `panel_field` [1, s H, s W] complex64 (aberrated by the relay's pupil
        when it has one), from its grey levels [H, W] uint8: the same chain in float32 (the
        default tables' phase, at most 2.4 pi, is then exact to ~1e-6 rad), the table looked up
        before oversampling, and the illumination, fill factor and zero order folded into two
        memoised maps: u = a(x) exp(i phase) + b(x)."""
        b = self.bench
        s = b.oversample
        hp, wp = grey.shape
        hs, ws = s * hp, s * wp
        gain, offset, blur = self._panel_maps_for(hs, ws)
        # The sign goes into the table: the blur is linear, so blur(-phase) = -blur(phase).
        table = torch.tensor(b.phase_tables[colour], dtype=torch.float64) * b.phase_sign
        phase = table.float()[torch.from_numpy(grey.astype(np.int64))]
        # Each SLM pixel is s x s samples (repeat_interleave's values, without its copies).
        phase = phase[:, None, :, None].expand(hp, s, wp, s).reshape(hs, ws)
        if blur is not None:
            phase = torch.fft.irfft2(torch.fft.rfft2(phase) * blur, s=(hs, ws))
        u = torch.polar(gain, phase)
        u.real.add_(offset)
        u = u[None]
        if any(b.zernike_rad):
            u = self._aberrate_fast(u, colour)
        return u

    def _panel_maps_for(self, hs: int, ws: int
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """For the oversampled panel grid [hs, ws] (memoised per bench and grid): the gain a(x)
        and offset b(x) of u = a exp(i phase) + b, float32 [hs, ws] (panel_field's
        u = (sqrt(1 - zero order) (fill exp(i phase) + (1 - fill) gap) + sqrt(zero order))
        times the Gaussian illumination, expanded), and the crosstalk blur's transfer function
        on rfft2's grid, float32 [hs, ws // 2 + 1] (None: no crosstalk)."""
        b = self.bench
        key = (b, hs, ws)
        hit = self._panel_maps.get(key)
        if hit is not None:
            return hit
        pitch = b.pitch_m / b.oversample
        y = (torch.arange(hs, dtype=torch.float64) - (hs - 1) / 2) * pitch
        x = (torch.arange(ws, dtype=torch.float64) - (ws - 1) / 2) * pitch
        r2 = (x[None, :] - b.source_offset_m[0]) ** 2 + (y[:, None] - b.source_offset_m[1]) ** 2
        beam = torch.exp(-r2 / b.source_waist_m**2)
        signal = math.sqrt(1 - b.zero_order_fraction)
        gain = (signal * b.fill_factor * beam).float()
        offset = ((signal * (1 - b.fill_factor) * b.gap_reflectance
                   + math.sqrt(b.zero_order_fraction)) * beam).float()
        blur = None
        if b.crosstalk_sigma_m > 0:
            blur = _gaussian_transfer(hs, ws, b.crosstalk_sigma_m / pitch).float()
        if len(self._panel_maps) >= 4:
            self._panel_maps.clear()
        self._panel_maps[key] = (gain, offset, blur)
        return gain, offset, blur

    def _aberrate_fast(self, field: torch.Tensor, colour: int) -> torch.Tensor:
        """`_aberrate` in complex64 (the pupil computed in float64, then cast: its phase is
        exact to 1e-7 rad, as `nhfd.optics.pupil_transfer`'s)."""
        h, w = field.shape[-2:]
        spec = torch.fft.fft2(field, s=(2 * h, 2 * w))
        spec *= self._pupil(h, w, colour, torch.complex64)
        return torch.fft.ifft2(spec)[..., :h, :w].contiguous()

    def _project_fast(self, image: torch.Tensor, pitch_m: float) -> np.ndarray:
        """`project_to_camera` of one SLM-plane image [H, W] float32 -> [1, h, w] float64, the
        k x k mean of each camera pixel as avg_pool2d (the same sums, in another order; half
        the time of the reshaped mean at the full sensor, 2 cores)."""
        hs, ws = image.shape
        grid, k = self._camera_grid(hs, ws, pitch_m)
        sampled = F.grid_sample(image[None, None], grid, mode="bilinear", padding_mode="zeros",
                                align_corners=True)
        if k > 1:
            sampled = F.avg_pool2d(sampled, k)
        return sampled[0].double().numpy()

    def project_to_camera(self, image: torch.Tensor | np.ndarray, pitch_m: float) -> np.ndarray:
        """Map an SLM-plane image [C, H, W] (sample pitch `pitch_m`, centred on the panel) onto
        the ROI with the bench's geometry and camera pixel integration -> [C, h, w] float64.
        Outside the image is 0. Also useful to put a target where the camera sees it."""
        img = torch.as_tensor(image, dtype=torch.float32)
        c, hs, ws = img.shape
        _, _, h, w = self.roi
        grid, k = self._camera_grid(hs, ws, pitch_m)
        sampled = F.grid_sample(img[None], grid, mode="bilinear", padding_mode="zeros",
                                align_corners=True)[0]
        return sampled.reshape(c, h, k, w, k).mean(dim=(2, 4)).double().numpy()

    def _camera_grid(self, hs: int, ws: int, pitch_m: float) -> tuple[torch.Tensor, int]:
        """grid_sample's grid [1, h k, w k, 2] of the ROI's pixels, each supersampled k x k,
        on an SLM-plane image of [hs, ws] samples at `pitch_m`, and k (memoised per bench, ROI
        and image grid)."""
        b = self.bench
        key = (b, self.roi, hs, ws, pitch_m)
        hit = self._grids.get(key)
        if hit is not None:
            return hit
        _, _, h, w = self.roi
        k = self._supersampling(pitch_m)
        grid = torch.empty((1, h * k, w * k, 2), dtype=torch.float32)
        # Blocks of about 4 million points: bounded temporaries, and few operations (under a
        # busy CPU each one waits for its OpenMP threads).
        block_rows = max(1, (4 << 20) // (k * k * w))
        for i0 in range(0, h, block_rows):
            i1 = min(h, i0 + block_rows)
            grid[0, i0 * k : i1 * k] = self._grid_rows(hs, ws, pitch_m, k, i0, i1)
        if len(self._grids) >= 4:
            self._grids.clear()
        self._grids[key] = (grid, k)
        return grid, k

    def _supersampling(self, pitch_m: float) -> int:
        """k: each camera pixel is sampled k x k times, finely enough to integrate over its
        footprint on an SLM-plane image of sample pitch `pitch_m`."""
        footprint = self.bench.camera_pitch_m / self.bench.magnification
        return max(1, math.ceil(2 * footprint / pitch_m))

    def _grid_rows(self, hs: int, ws: int, pitch_m: float, k: int, i0: int, i1: int
                   ) -> torch.Tensor:
        """The camera grid's rows for the ROI's pixel rows i0 <= i < i1: [(i1 - i0) k, w k, 2]
        float32, grid_sample's coordinates on the [hs, ws] image."""
        b = self.bench
        top, left, _, w = self.roi
        sub = (np.arange(k) + 0.5) / k - 0.5
        rows = ((top + np.arange(i0, i1))[:, None] + sub[None, :]).reshape(-1)
        cols = ((left + np.arange(w))[:, None] + sub[None, :]).reshape(-1)
        # camera_px_to_slm is affine: x = inv[0, 0] u(col) + inv[0, 1] v(row) (and y alike), so
        # the sums of two broadcast vectors give its coordinates, without its [2, h k, w k]
        # float64 meshgrid and product (9 s and 1.4 GB at the full sensor, 2 cores).
        sh, sw = b.sensor_hw_px
        u = torch.from_numpy((cols - (sw - 1) / 2) * b.camera_pitch_m - b.shift_m[0])[None, :]
        v = torch.from_numpy((rows - (sh - 1) / 2) * b.camera_pitch_m - b.shift_m[1])[:, None]
        inv = np.linalg.inv(b._matrix())
        x = inv[0, 0] * u + inv[0, 1] * v
        y = inv[1, 0] * u + inv[1, 1] * v
        # grid_sample with align_corners=True: -1 and +1 are the centres of the end samples.
        return torch.stack([x / pitch_m / ((ws - 1) / 2), y / pitch_m / ((hs - 1) / 2)],
                           dim=-1).float()

    def _patterns(self) -> tuple[np.ndarray, np.ndarray]:
        """PRNU (gain) and DSNU (offset) of the ROI's pixels, fixed for the sensor: each sensor
        row is drawn from its own seeded generator, so any ROI sees the same pixels."""
        b = self.bench
        top, left, h, w = self.roi
        sw = b.sensor_hw_px[1]
        chans = 3 if self.settings.channels == "rgb" else 1
        prnu = np.empty((chans, h, w))
        dsnu = np.empty((chans, h, w))
        for i in range(h):
            rng = np.random.default_rng([b.pattern_seed, top + i])
            draw = rng.standard_normal((2, chans, sw))[..., left : left + w]
            prnu[:, i] = 1 + b.prnu * draw[0]
            dsnu[:, i] = b.dsnu * draw[1]
        return prnu, dsnu


def _zernike_noll(j: int, rho: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Zernike polynomial of Noll index j (RMS 1 over the unit disk), for the twin's pupil."""
    n = 0
    while (n + 1) * (n + 2) // 2 < j:
        n += 1
    # Noll: within order n, |m| increases with j; even j -> cos, odd j -> sin (m != 0).
    k = j - n * (n + 1) // 2 - 1  # 0 .. n
    ms = sorted({abs(n - 2 * i) for i in range(n + 1)})
    m = [mm for mm in ms for _ in ((0,) if mm == 0 else (0, 1))][k]
    radial = torch.zeros_like(rho)
    for t in range((n - m) // 2 + 1):
        radial += ((-1) ** t * math.factorial(n - t)
                   / (math.factorial(t) * math.factorial((n + m) // 2 - t)
                      * math.factorial((n - m) // 2 - t))) * rho ** (n - 2 * t)
    if m == 0:
        return math.sqrt(n + 1) * radial
    ang = torch.cos(m * theta) if j % 2 == 0 else torch.sin(m * theta)
    return math.sqrt(2 * (n + 1)) * radial * ang


def _gaussian_transfer(h: int, w: int, sigma_px: float) -> torch.Tensor:
    """A Gaussian blur's transfer function (sigma in samples) on rfft2's grid of an [h, w]
    image, [h, w // 2 + 1] float64."""
    fy = torch.fft.fftfreq(h, dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(w, dtype=torch.float64)[None, :]
    return torch.exp(-2 * math.pi**2 * sigma_px**2 * (fx**2 + fy**2))


def _gaussian_blur(image: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Periodic Gaussian blur of a real [..., H, W] tensor (sigma in samples), via the FFT."""
    h, w = image.shape[-2:]
    transfer = _gaussian_transfer(h, w, sigma_px)
    return torch.fft.irfft2(torch.fft.rfft2(image) * transfer, s=(h, w))


class _RawLevels:
    """`rint(response.to_raw(signal))` as uint16 for a signal in [0, 1], without np.interp's
    binary search per pixel (a full-sensor frame: 0.39 s with np.interp, 0.12 s here; 2 cores):
    a uniform table of 2^16 bins gives each value its segment of the response to within one,
    then np.interp's own arithmetic, `slope[j] (signal - linear[j]) + j`, gives the same
    levels (tests/drivers/test_simcamera_speed.py compares them)."""

    BINS = 1 << 16

    def __init__(self, response: ResponseCurve) -> None:
        linear = response.linear
        steps = np.diff(linear)
        # One bin holds at most one table entry when every step is wider than a bin; a table
        # with finer steps (16 bits, or a stretch where the response barely rises) keeps
        # np.interp.
        self._exact = bool(steps.min() > 1.0 / self.BINS)
        self._response = response
        self._linear = linear
        # linear[j + 1] for j = -1 .. top: past the top entry nothing is above.
        self._next = np.append(linear, np.inf)
        # np.interp's slopes, (fp[j+1] - fp[j]) / (xp[j+1] - xp[j]) with fp = 0, 1, 2, ...; 0 at
        # the top entry, where np.interp gives the top level.
        self._slope = np.append(1.0 / steps, 0.0)
        # The last entry at or below each bin's lower edge (-1 below the table's start); the
        # extra bin holds a signal of exactly 1.
        edges = np.arange(self.BINS + 1) / self.BINS
        self._first = np.searchsorted(linear, edges, side="right") - 1

    def __call__(self, signal: np.ndarray) -> np.ndarray:
        if not self._exact:
            return np.rint(self._response.to_raw(signal)).astype(np.uint16)
        j = self._first.take((signal * self.BINS).astype(np.intp))
        # The bin's one table entry above its lower edge, if the value passed it.
        j += signal >= self._next.take(j + 1)
        if self._linear[0] > 0:
            np.maximum(j, 0, out=j)  # below the table: np.interp's first level, 0
        level = signal - self._linear.take(j)
        level *= self._slope.take(j)
        level += j
        if self._linear[0] > 0:
            np.maximum(level, 0.0, out=level)
        return np.rint(level, out=level).astype(np.uint16)


__all__ = [
    "SimulatedCamera",
    "TrueBench",
    "camera_response",
    "slm_frame_source",
    "wiggly_phase_table",
]
