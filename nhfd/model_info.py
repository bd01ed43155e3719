"""What the frame path knows of a model, as a value (layer L0): `ModelInfo`.

An exported model carries its metadata as one JSON object (`nhfd.models.metadata`). It is
parsed once, when the file is loaded (`nhfd.models.metadata.parse_model_info`: every field
checked, a file whose metadata is incomplete refused naming the missing field), into a
`ModelInfo`; from there the frame settings, the render camera, the network input, the pose
envelope's warnings, the size check and `status` read its fields by name. Standard library only.

The ranges below are the one definition of what a model's metadata may hold: the metadata
checker (`nhfd.models.metadata.validate_metadata`) refuses a file outside them, naming the file
and the field; these constructors refuse a value built in code outside them, naming the field.
The optics ranges are the configuration's own (`nhfd.config`: wavelengths 200-2000 nm, pitch
(0, 1000) um, z0 (0, 1000] mm, cutoffs (0, 0.5] cycles/px, three colours, the aperture shapes),
so a model the configuration could not describe is refused even where none is given (offline).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

COLOURS = 3
WAVELENGTH_RANGE_M = (200e-9, 2000e-9)
PITCH_MAX_M = 1e-3
Z0_MAX_M = 1.0
CUTOFF_MAX_PER_PX = 0.5
APERTURE_SHAPES = ("square", "circle", "diamond")
# nhfd.config's pixel counts (slm and hologram sizes: 1..32768).
PIXELS_MAX = 32768
# The input multiple is unshuffle (1, 2, 4 or 8) x 2^depth (depth 0..nhfd.config.DEPTH_MAX = 6):
# a power of two up to 8 x 2^6.
INPUT_MULTIPLE_MAX = 8 * 2**6
# Amplitude scales are a dataset's high percentile of SLM-plane amplitudes of sRGB renders: O(1)
# (2.96 for the shipped model). Twelve orders of magnitude either way keeps amplitude x scale
# and the propagation's sums over millions of pixels far inside float32 (3.4e38).
AMPLITUDE_SCALE_RANGE = (1e-12, 1e12)
# The graph's input: sRGB, or sRGB and the mapped depth (`nhfd.models.inputs`).
INPUTS = ("rgb", "rgbd")
# Real-time subframes: a model may emit K frames per inference (one head per subframe, tuned
# jointly on their mean intensity, `nhfd model tune --subframes`), shown in turn, one per
# refresh. Eight at 60 Hz is a 7.5 Hz cycle, where flicker starts to show.
SUBFRAMES_RANGE = (1, 8)


def _number(name: str, value: Any, lo: float, hi: float, unit: str, *, open_lo: bool = False,
            open_hi: bool = False) -> float:
    """`value` as a float when it is a finite number in the interval, else ValueError naming
    `name`, the value and the interval."""
    ok = (isinstance(value, int | float) and not isinstance(value, bool)
          and math.isfinite(value) and (value > lo if open_lo else value >= lo)
          and (value < hi if open_hi else value <= hi))
    if not ok:
        if math.isinf(hi):
            span = f"{'>' if open_lo else '>='} {lo:g}"
        else:
            span = f"in {'(' if open_lo else '['}{lo:g}, {hi:g}{')' if open_hi else ']'}"
        raise ValueError(f"model info {name} = {value!r}: expected a finite number {span}"
                         + (f" ({unit})" if unit else ""))
    return float(value)


def _numbers(name: str, values: Any, count: int) -> tuple[float, ...]:
    """`values` as a tuple of `count` floats (their ranges are the caller's)."""
    if not isinstance(values, tuple | list) or len(values) != count:
        raise ValueError(f"model info {name} = {values!r}: expected {count} numbers")
    return tuple(values)


def _pair(name: str, values: Any, lo: float, hi: float, unit: str) -> None:
    a, b = _numbers(name, values, 2)
    _number(f"{name}[0]", a, lo, hi, unit)
    _number(f"{name}[1]", b, lo, hi, unit)
    if not a <= b:
        raise ValueError(f"model info {name} = {list(values)}: expected [low, high] with "
                         f"low <= high ({unit})")


def _hw(name: str, values: Any) -> None:
    h, w = _numbers(name, values, 2)
    for v in (h, w):
        if not (isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= PIXELS_MAX):
            raise ValueError(f"model info {name} = {list(values)}: expected [height, width], "
                             f"integers in 1..{PIXELS_MAX} px")


@dataclass(frozen=True)
class DepthMapping:
    """The scene's depth mapping the model was trained with: a scene depth d (scene units, along
    the optical axis) lies at z_h = a_m + b_m / d metres from the reference plane. `d_near`,
    `d_far`: the depth range it was fitted on (scene units), where recorded."""

    a_m: float
    b_m: float
    d_near: float | None = None
    d_far: float | None = None

    def __post_init__(self) -> None:
        inf = math.inf
        _number("mapping.a_m", self.a_m, -inf, inf, "m", open_lo=True, open_hi=True)
        _number("mapping.b_m", self.b_m, -inf, inf, "m", open_lo=True, open_hi=True)
        for name in ("d_near", "d_far"):
            value = getattr(self, name)
            if value is not None:
                _number(f"mapping.{name}", value, 0.0, inf, "scene units", open_lo=True,
                        open_hi=True)

    def as_dict(self) -> dict[str, float]:
        """{"a_m", "b_m"}: the form `nhfd.models.inputs.network_input` takes."""
        return {"a_m": self.a_m, "b_m": self.b_m}

    def to_json(self) -> dict[str, Any]:
        """{"a_m", "b_m"} and the fitted depth range where recorded (what `status` shows)."""
        out: dict[str, Any] = {"a_m": self.a_m, "b_m": self.b_m}
        if self.d_near is not None:
            out["d_near"] = self.d_near
        if self.d_far is not None:
            out["d_far"] = self.d_far
        return out


@dataclass(frozen=True)
class PoseEnvelope:
    """The poses the model was trained on (`nhfd.dataset.poses.envelope`): each range
    [low, high], None where the dataset did not record it. Distances and positions in scene
    units, angles in degrees."""

    distance: tuple[float, float] | None = None
    azimuth_deg: tuple[float, float] | None = None
    elevation_deg: tuple[float, float] | None = None
    position_min: tuple[float, float, float] | None = None
    position_max: tuple[float, float, float] | None = None
    n: int | None = None  # how many training poses

    def __post_init__(self) -> None:
        inf = math.inf
        for name, lo, hi, unit in (("distance", 0.0, inf, "scene units"),
                                   ("azimuth_deg", -360.0, 360.0, "deg"),
                                   ("elevation_deg", -90.0, 90.0, "deg")):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, tuple(value))
                _pair(f"pose_envelope.{name}", value, lo, hi, unit)
        if (self.position_min is None) != (self.position_max is None):
            raise ValueError("model info pose_envelope: position_min and position_max go "
                             "together (the box of the trained positions)")
        if self.position_min is not None and self.position_max is not None:
            for name in ("position_min", "position_max"):
                object.__setattr__(self, name, tuple(getattr(self, name)))
                for i, v in enumerate(_numbers(f"pose_envelope.{name}", getattr(self, name), 3)):
                    _number(f"pose_envelope.{name}[{i}]", v, -inf, inf, "scene units",
                            open_lo=True, open_hi=True)
            if not all(a <= b for a, b in zip(self.position_min, self.position_max,
                                               strict=True)):
                raise ValueError(f"model info pose_envelope.position_max = "
                                 f"{list(self.position_max)}: expected at least position_min "
                                 f"= {list(self.position_min)} in each coordinate")
        if self.n is not None and not (isinstance(self.n, int) and self.n >= 0):
            raise ValueError(f"model info pose_envelope.n = {self.n!r}: expected an integer "
                             ">= 0")

    def to_json(self) -> dict[str, Any]:
        """The metadata's form: only the ranges recorded."""
        out: dict[str, Any] = {} if self.n is None else {"n": self.n}
        for name in ("distance", "position_min", "position_max", "azimuth_deg",
                     "elevation_deg"):
            value = getattr(self, name)
            if value is not None:
                out[name] = list(value)
        return out


@dataclass(frozen=True)
class CheckedSize:
    """One size check of the exported graph (`nhfd.models.sizes`): its input `hw` (multiples of
    the input multiple), the largest absolute difference from the reference, whether that is
    within tolerance, and what it was checked against."""

    hw: tuple[int, int]
    max_abs_diff: float
    ok: bool
    against: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "hw", tuple(self.hw))
        _hw("checked_sizes.hw", self.hw)


def padded_hw(hw: tuple[int, int] | list[int], multiple: int) -> tuple[int, int]:
    """A window's size rounded up to the input multiple (what the graph runs at)."""
    h, w = int(hw[0]), int(hw[1])
    return h + (-h) % multiple, w + (-w) % multiple


@dataclass(frozen=True)
class ModelInfo:
    """A model's metadata as the frame path uses it.

    optics          the colours' wavelengths (m), the pitch (m), the Fourier aperture (shape,
                    cutoff per colour in cycles/px), the reference plane's distance from the SLM
                    z0_m and the volume [near, far] about it (m): what frames propagate with
    network         its input (`inputs`, "rgb" or "rgbd"), its amplitude scale (output x scale =
                    the reference-plane amplitude in the dataset's units), the multiple its input
                    height and width are padded to, the depth mapping (an rgbd model's input)
    camera          the training window (h, w px) and the render's focal lengths fx_px, fy_px
                    (px), or the horizontal field of view fov_x_deg of older exports: `focal_px`
    provenance      the pose envelope, the checked sizes (None: not recorded, an older export),
                    and what `status` reports (profile, parameters, steps, scene hash, precision)
    """

    inputs: str
    wavelengths_m: tuple[float, ...]
    pitch_m: float
    aperture_shape: str
    cutoff_per_px: tuple[float, ...]
    z0_m: float
    volume_m: tuple[float, float]
    amplitude_scale: float
    train_size_hw: tuple[int, int]
    input_multiple: int
    fx_px: float | None = None
    fy_px: float | None = None
    fov_x_deg: float | None = None
    mapping: DepthMapping | None = None
    pose_envelope: PoseEnvelope | None = None
    checked_sizes: tuple[CheckedSize, ...] | None = None
    profile: str | None = None
    parameters: int | None = None
    train_steps: int | None = None
    scene_sha256: str | None = None
    precision: str | None = None
    subframes: int = 1

    def __post_init__(self) -> None:
        for name in ("wavelengths_m", "cutoff_per_px", "volume_m", "train_size_hw"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if self.checked_sizes is not None:
            object.__setattr__(self, "checked_sizes", tuple(self.checked_sizes))
        if self.inputs not in INPUTS:
            raise ValueError(f"model info inputs = {self.inputs!r}: expected one of "
                             f"{', '.join(INPUTS)}")
        _numbers("wavelengths_m", self.wavelengths_m, COLOURS)
        for i, v in enumerate(self.wavelengths_m):
            _number(f"wavelengths_m[{i}]", v, *WAVELENGTH_RANGE_M, "m")
        _number("pitch_m", self.pitch_m, 0.0, PITCH_MAX_M, "m", open_lo=True, open_hi=True)
        if self.aperture_shape not in APERTURE_SHAPES:
            raise ValueError(f"model info aperture_shape = {self.aperture_shape!r}: expected "
                             f"one of {', '.join(APERTURE_SHAPES)}")
        _numbers("cutoff_per_px", self.cutoff_per_px, COLOURS)
        for i, v in enumerate(self.cutoff_per_px):
            _number(f"cutoff_per_px[{i}]", v, 0.0, CUTOFF_MAX_PER_PX, "cycles/px", open_lo=True)
        z0 = _number("z0_m", self.z0_m, 0.0, Z0_MAX_M, "m", open_lo=True)
        near, far = _numbers("volume_m", self.volume_m, 2)
        for i, v in enumerate((near, far)):
            _number(f"volume_m[{i}]", v, -math.inf, math.inf, "m", open_lo=True, open_hi=True)
        if not near < far or not z0 + near > 0:
            raise ValueError(f"model info volume_m = {list(self.volume_m)}: expected [near, far] "
                             f"(m from the reference plane) with near < far and z0_m + near > 0 "
                             f"(z0_m = {z0:g})")
        _number("amplitude_scale", self.amplitude_scale, *AMPLITUDE_SCALE_RANGE, "")
        _hw("train_size_hw", self.train_size_hw)
        m = self.input_multiple
        if not (isinstance(m, int) and not isinstance(m, bool) and 1 <= m <= INPUT_MULTIPLE_MAX
                and m & (m - 1) == 0):
            raise ValueError(f"model info input_multiple = {m!r}: expected a power of two in "
                             f"1..{INPUT_MULTIPLE_MAX}")
        for name in ("fx_px", "fy_px"):
            if getattr(self, name) is not None:
                _number(name, getattr(self, name), 0.0, math.inf, "px", open_lo=True,
                        open_hi=True)
        if self.fov_x_deg is not None:
            _number("fov_x_deg", self.fov_x_deg, 0.0, 180.0, "deg", open_lo=True, open_hi=True)
        if self.fx_px is None and self.fov_x_deg is None:
            raise ValueError("model info fx_px = None and fov_x_deg = None: expected the "
                             "render's focal length (fx_px > 0 px) or its field of view")
        if self.inputs == "rgbd" and self.mapping is None:
            raise ValueError("model info mapping = None: an rgbd model needs the scene's depth "
                             "mapping (a_m, b_m)")
        k, (lo, hi) = self.subframes, SUBFRAMES_RANGE
        if not (isinstance(k, int) and not isinstance(k, bool) and lo <= k <= hi):
            raise ValueError(f"model info subframes = {k!r}: expected a whole number in "
                             f"{lo}..{hi} (the frames one inference emits)")

    @property
    def colours(self) -> int:
        """How many colours the model codes (one wavelength each)."""
        return len(self.wavelengths_m)

    @property
    def channels(self) -> int:
        """The network input's channels: 3 (sRGB), or 4 with the mapped depth."""
        return 4 if self.inputs == "rgbd" else 3

    @property
    def mapping_dict(self) -> dict[str, float] | None:
        """The depth mapping as `network_input` takes it (`a_m`, `b_m`, ...), or None."""
        return None if self.mapping is None else self.mapping.as_dict()

    def focal_px(self) -> tuple[float, float]:
        """The render's focal lengths (fx, fy) in px: the trained ones (fy = fx where only fx
        is recorded), or from `fov_x_deg` across the training width for older exports. Another
        window keeps them: a pixel subtends the angle it was trained on."""
        if self.fx_px is not None:
            fx = float(self.fx_px)
            return fx, float(self.fy_px) if self.fy_px is not None else fx
        _th, tw = self.train_size_hw
        assert self.fov_x_deg is not None  # the constructor refuses neither
        fx = 0.5 * tw / math.tan(math.radians(float(self.fov_x_deg)) / 2)
        return fx, fx

    def checked_sizes_hw(self) -> tuple[list[tuple[int, int]], bool]:
        """The graph input sizes (h, w) the model passed its size checks at, and whether they
        are recorded. A model without `checked_sizes` (exported before they were recorded, or
        with --no-check) counts only its training window (padded to the multiple) as checked:
        the size it was trained and evaluated at; False says so."""
        if self.checked_sizes is None:
            return [padded_hw(self.train_size_hw, self.input_multiple)], False
        return [c.hw for c in self.checked_sizes if c.ok], True

    def status_json(self) -> dict[str, Any]:
        """What `status` reports of the model (its "model" object's fields from the metadata)."""
        return {"profile": self.profile, "train_size_hw": list(self.train_size_hw),
                "fx": self.fx_px, "amplitude_scale": self.amplitude_scale, "z0_m": self.z0_m,
                "volume_m": list(self.volume_m),
                "mapping": None if self.mapping is None else self.mapping.to_json(),
                "pose_envelope": (None if self.pose_envelope is None
                                  else self.pose_envelope.to_json()),
                "parameters": self.parameters, "train_steps": self.train_steps,
                "scene_sha256": self.scene_sha256, "subframes": self.subframes}


def recorded_scenes(metadata: dict[str, Any]) -> tuple[str, ...]:
    """The scene files a model's metadata says it was built from, as SHA-256 hex: the scene it
    was trained on (`scene_sha256`) and, for a model `nhfd model build` made, the source file it
    reduced (`source_scene_sha256`). Empty when it records none (an older or foreign model)."""
    return tuple(str(s) for s in (metadata.get("scene_sha256"),
                                  metadata.get("source_scene_sha256")) if s)


def scene_mismatch(metadata: dict[str, Any], scene_sha256: str) -> str | None:
    """None when a model's metadata records no scene or records this one (`scene_sha256`, the
    file's hash); else both hashes, for the refusal that names them."""
    recorded = recorded_scenes(metadata)
    if not recorded or scene_sha256 in recorded:
        return None
    return (f"SHA-256 {recorded[0][:12]}... in the model's metadata, {scene_sha256[:12]}... for "
            "the file")
