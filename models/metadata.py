"""What an exported model records about the optics it was trained for, and the check that refuses
a model whose optics differ from the configured ones.

The metadata is one JSON object under the ONNX metadata key `nhfd` (plus `nhfd_version` on its
own, readable by any ONNX tool). No torch or onnx import here: the daemon reads it through
onnxruntime.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

from nhfd.config import OpticsSettings, SLMSettings
from nhfd.model_info import (
    AMPLITUDE_SCALE_RANGE,
    APERTURE_SHAPES,
    COLOURS,
    CUTOFF_MAX_PER_PX,
    INPUT_MULTIPLE_MAX,
    PITCH_MAX_M,
    PIXELS_MAX,
    SUBFRAMES_RANGE,
    WAVELENGTH_RANGE_M,
    Z0_MAX_M,
    CheckedSize,
    DepthMapping,
    ModelInfo,
    PoseEnvelope,
)
from nhfd.model_info import padded_hw as padded_hw

METADATA_KEY = "nhfd"
FORMAT = "nhfd-model"
FORMAT_VERSION = 1
COLOUR_SPACE = "sRGB-encoded in [0, 1], composited on black, R, G, B"
# Keys compared against the configured optics, with the relative tolerance of float values.
OPTICS_KEYS = ("wavelengths_m", "pitch_m", "aperture_shape", "cutoff_per_px", "z0_m", "volume_m")
REL_TOL = 1e-6
# Largest absolute difference (amplitude units and radians) at which a size check passes: float32
# rounding across shapes stays far below it (measured: 2e-7 between torch and onnxruntime for the
# tiny test network at 1920 x 1080; 0, bit for bit, between the shipped model's full-size run and
# its tiles); a wrong graph or kernel at some shape is off by order 1.
SIZE_TOLERANCE = 1e-3


class ModelMismatch(ValueError):
    """A model trained for other optics than the configured ones; the message says what."""


class NotAModel(ValueError):
    """A file that is not a readable ONNX model exported by `nhfd export`."""


class InvalidMetadata(NotAModel):
    """A model whose nhfd metadata holds a value of the wrong type or outside its range; the
    message names the field, the value and what is allowed. The frame path reads these values on
    every frame, so a model that passed the load with one of them (a NaN amplitude scale, a zero
    input multiple) would fail, or show garbage, on every frame after it."""


# The ranges `validate_metadata` allows, in the metadata's units: `nhfd.model_info`'s (one
# definition: the file's check here, the value's constructor there).
# A JSON value this long is shown cut in a refusal: a hostile file chooses its own values.
SHOWN_CHARS = 80


def manifest_sha256(data_dir: str | Path) -> str | None:
    """The SHA-256 (hex) of the dataset folder's manifest.json; None when it has none."""
    path = Path(data_dir) / "manifest.json"
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else None


def training_poses(manifest: dict) -> dict[str, Any] | None:
    """The camera positions of a dataset's training split and the centre they orbit, as the
    metadata records them (`train_poses`): what `nhfd eval` measures a view's angle to the
    nearest training pose against. None when the manifest has no training poses."""
    poses, train = manifest.get("poses") or [], (manifest.get("splits") or {}).get("train") or []
    if not poses or not train:
        return None
    positions = []
    for i in train:
        r, t = poses[i]["R"], poses[i]["t"]
        # position = -R^T t of the world-to-camera R, t
        positions.append([-sum(r[k][j] * t[k] for k in range(3)) for j in range(3)])
    return {"center": [float(v) for v in manifest.get("center", [0.0, 0.0, 0.0])],
            "positions": [[float(v) for v in p] for p in positions]}


def build_metadata(run_info: dict, *, opset: int, train_poses: dict | None = None,
                   checked_sizes: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The metadata of a model exported from a run (`run.json` of `nhfd train`), with the
    training poses (`training_poses` of its dataset) when known, and the input sizes it was
    checked at (`checked_sizes`, entries of `checked_size_entry`; `nhfd.models.sizes` adds them
    after the export's checks, so a model exported unchecked has none)."""
    ds = run_info["dataset"]
    s = ds["settings"]
    net = run_info["net"]
    opts = run_info["options"]
    camera = ds.get("camera") or {}
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "wavelengths_m": [float(v) for v in s["wavelengths_m"]],
        "pitch_m": float(s["pitch_m"]),
        "aperture_shape": s["aperture_shape"],
        "cutoff_per_px": [float(v) for v in s["cutoff_per_px"]],
        "z0_m": float(s["z0_m"]),
        "volume_m": [float(v) for v in s["volume_m"]],
        "panel_hw": list(s.get("panel_hw") or []),
        "mapping": ds["mapping"],
        "amplitude_scale": float(ds["amplitude_scale"]),
        "amplitude_units": "amplitude output x amplitude_scale = field amplitude on the "
        "reference plane (the dataset's units)",
        "fx": camera.get("fx"),
        "fy": camera.get("fy"),
        "fov_x_deg": s.get("fov_x_deg"),
        "train_size_hw": [int(s["height_px"]), int(s["width_px"])],
        "train_crop_hw": [int(opts["crop_height_px"]), int(opts["crop_width_px"])],
        "resolution_note": "another input size keeps the trained fx (the window changes)",
        "pose_envelope": ds.get("envelope"),
        "train_poses": train_poses,
        "scene_sha256": (ds.get("scene") or {}).get("sha256"),
        "colour_space": COLOUR_SPACE,
        "input_multiple": int(net["unshuffle"]) * 2 ** int(net["depth"]),
        "profile": opts.get("profile"),
        "net": net,
        "parameters": run_info.get("parameters"),
        "train_steps": run_info.get("step"),
        "dataset_manifest_key": ds.get("manifest_key"),
        "dataset_manifest_sha256": ds.get("manifest_sha256"),
        "inputs": ({"rgbd": "[B, 4, H, W] float32: sRGB, then the mapped depth scaled so the "
                             "volume spans [-1, 1] (nhfd.models.inputs); H and W multiples of "
                             "input_multiple"}
                   if net.get("inputs") == "rgbd" else
                   {"rgb": "[B, 3, H, W] float32, H and W multiples of input_multiple"}),
        "outputs": {
            "amplitude": "[B, 3, H, W] softplus, amplitude-scale units",
            "phase": "[B, 3, H, W] radians, unwrapped",
        },
        "opset": int(opset),
        "nhfd_version": run_info.get("nhfd_version"),
    } | ({"checked_sizes": list(checked_sizes)} if checked_sizes is not None else {})


def checked_size_entry(hw: tuple[int, int], max_abs_diff: float, against: str) -> dict[str, Any]:
    """One `checked_sizes` entry: the graph's input height and width (multiples of
    input_multiple), the largest absolute difference over amplitude and phase from the reference
    it was checked `against` (a sentence), and whether that is within SIZE_TOLERANCE."""
    ok = math.isfinite(max_abs_diff) and max_abs_diff <= SIZE_TOLERANCE
    return {"hw": [int(hw[0]), int(hw[1])], "max_abs_diff": float(max_abs_diff), "ok": ok,
            "against": against}


def expected_from_config(optics: OpticsSettings, slm: SLMSettings) -> dict[str, Any]:
    """The optics a configuration asks for, in the metadata's keys and units: `[optics]`
    (wavelengths, aperture, z0, volume) and `[slm]`'s pitch."""
    o = optics
    return {
        "wavelengths_m": [v * 1e-9 for v in o.wavelengths_nm],
        "pitch_m": slm.pitch_um * 1e-6,
        "aperture_shape": o.aperture.shape,
        "cutoff_per_px": list(o.aperture.cutoff_per_px),
        "z0_m": o.z0_mm * 1e-3,
        "volume_m": [v * 1e-3 for v in o.volume_mm],
    }


def expected_from_manifest(manifest: dict) -> dict[str, Any]:
    """The optics a dataset was built for (`OPTICS_KEYS`, SI units), from its manifest."""
    s = manifest["settings"]
    return {k: s[k] for k in OPTICS_KEYS}


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, int | float) and isinstance(b, int | float):
        return math.isclose(float(a), float(b), rel_tol=REL_TOL, abs_tol=1e-15)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def differences(metadata: dict, expected: dict) -> list[str]:
    """One line per key of `expected` whose value in `metadata` differs (or is missing)."""
    out = []
    for key, want in expected.items():
        have = metadata.get(key, "<missing>")
        if not _same(have, want):
            out.append(f"{key}: model {have!r}, configured {want!r}")
    return out


def check_metadata(metadata: dict, expected: dict, source: str) -> None:
    """Raise `ModelMismatch` naming `source` and every differing key when the model's optics
    are not the `expected` ones (`differences`)."""
    diff = differences(metadata, expected)
    if diff:
        raise ModelMismatch(
            f"{source} was trained for other optics than configured: " + "; ".join(diff)
            + " (retrain for this configuration, or configure the model's optics)"
        )


def parse_metadata(props: dict[str, str], source: str, graph_input: str | None = None) -> dict:
    """The nhfd metadata from an ONNX model's metadata map, checked field by field
    (`validate_metadata`; `graph_input`: the graph's input name where known), or `NotAModel`
    (`InvalidMetadata` for a value of the wrong type or out of its range)."""
    if METADATA_KEY not in props:
        raise NotAModel(
            f"{source}: an ONNX model without nhfd metadata (not exported by `nhfd export`)"
        )
    try:
        meta = json.loads(props[METADATA_KEY])
    except ValueError as exc:  # JSONDecodeError, and an integer past Python's 4300 digits
        raise NotAModel(f"{source}: nhfd metadata is not valid JSON ({str(exc)[:200]})") from None
    except RecursionError:  # json's decoder recurses once per nested array or object
        raise NotAModel(f"{source}: nhfd metadata is nested too deeply to read") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise NotAModel(f"{source}: nhfd metadata has no format {FORMAT!r}")
    version = meta.get("format_version")
    if _is_int(version) and version > FORMAT_VERSION:
        raise NotAModel(
            f"{source}: model format {version} is newer than this nhfd reads "
            f"({FORMAT_VERSION}); upgrade nhfd"
        )
    validate_metadata(meta, source, graph_input)
    return meta


def parse_model_info(meta: dict[str, Any], source: str, graph_input: str | None = None
                     ) -> ModelInfo:
    """The `ModelInfo` of metadata `validate_metadata` has passed (`parse_metadata`'s result):
    the fields the frame path, the size checks and `status` read, typed. `graph_input`: the
    graph's input name ("rgb" or "rgbd") where known, else the metadata's declared `inputs`.
    A value the constructors refuse is `InvalidMetadata` naming `source`."""
    declared = meta.get("inputs")
    if graph_input in ("rgb", "rgbd"):
        inputs = graph_input
    else:
        inputs = "rgbd" if isinstance(declared, dict) and "rgbd" in declared else "rgb"
    mapping = meta.get("mapping")
    env = meta.get("pose_envelope")
    sizes = meta.get("checked_sizes")
    try:
        return ModelInfo(
            inputs=inputs,
            wavelengths_m=tuple(float(v) for v in meta["wavelengths_m"]),
            pitch_m=float(meta["pitch_m"]),
            aperture_shape=str(meta["aperture_shape"]),
            cutoff_per_px=tuple(float(v) for v in meta["cutoff_per_px"]),
            z0_m=float(meta["z0_m"]),
            volume_m=(float(meta["volume_m"][0]), float(meta["volume_m"][1])),
            amplitude_scale=float(meta["amplitude_scale"]),
            train_size_hw=(int(meta["train_size_hw"][0]), int(meta["train_size_hw"][1])),
            input_multiple=int(meta["input_multiple"]),
            fx_px=None if meta.get("fx") is None else float(meta["fx"]),
            fy_px=None if meta.get("fy") is None else float(meta["fy"]),
            fov_x_deg=None if meta.get("fov_x_deg") is None else float(meta["fov_x_deg"]),
            # an rgb model may record a partial mapping (it never feeds one)
            mapping=(DepthMapping(float(mapping["a_m"]), float(mapping["b_m"]),
                                  mapping.get("d_near"), mapping.get("d_far"))
                     if isinstance(mapping, dict) and "a_m" in mapping and "b_m" in mapping
                     else None),
            pose_envelope=_envelope(env) if env else None,
            checked_sizes=None if sizes is None else tuple(
                CheckedSize((int(e["hw"][0]), int(e["hw"][1])), float(e["max_abs_diff"]),
                            bool(e["ok"]), str(e.get("against", ""))) for e in sizes),
            profile=meta.get("profile"),
            parameters=meta.get("parameters"),
            train_steps=meta.get("train_steps"),
            scene_sha256=meta.get("scene_sha256"),
            precision=meta.get("precision"),
            subframes=int(meta.get("subframes") or 1),
        )
    except ValueError as exc:  # validate_metadata passed: a check of the value's own
        raise InvalidMetadata(f"{source}: {exc}") from None


def _envelope(env: dict[str, Any]) -> PoseEnvelope:
    """`pose_envelope` (checked by `_check_envelope`) typed: an empty range is not recorded."""
    def span(key: str) -> tuple[float, ...] | None:
        value = env.get(key)
        return tuple(float(v) for v in value) if value else None

    lo, hi = span("position_min"), span("position_max")
    both = lo is not None and hi is not None  # the warnings use the box only when both are
    return PoseEnvelope(distance=span("distance"), azimuth_deg=span("azimuth_deg"),  # type: ignore[arg-type]
                        elevation_deg=span("elevation_deg"),  # type: ignore[arg-type]
                        position_min=lo if both else None,  # type: ignore[arg-type]
                        position_max=hi if both else None,  # type: ignore[arg-type]
                        n=env.get("n"))


def _is_number(value: Any) -> bool:
    # bool is an int to Python, never a number here: `true` for a scale is a broken file
    return isinstance(value, int | float) and not isinstance(value, bool)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _shown(value: Any) -> str:
    try:
        text = json.dumps(value) if not isinstance(value, float) else repr(value)
    except (RecursionError, ValueError, TypeError):  # nested past the encoder's depth
        text = f"<a nested {type(value).__name__}>"
    return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS] + "..."


class _Missing:
    """A required field the metadata lacks (refusals say "is missing", not a value)."""

    def __repr__(self) -> str:
        return "<missing>"


MISSING: Any = _Missing()


class _Fields:
    """Checks of one model's metadata fields; each refusal names the source, the field, the
    value and what is allowed."""

    def __init__(self, source: str) -> None:
        self.source = source

    def refuse(self, field: str, value: Any, allowed: str) -> None:
        if value is MISSING:  # an incomplete file: say which field it lacks
            raise InvalidMetadata(f"{self.source}: metadata {field} is missing: expected "
                                  f"{allowed}")
        raise InvalidMetadata(f"{self.source}: metadata {field} = {_shown(value)}: expected "
                              f"{allowed}")

    def number(self, field: str, value: Any, lo: float, hi: float, unit: str, *,
               open_lo: bool = False, open_hi: bool = False) -> float:
        """`value` as a float when it is a finite number in the interval (open or closed at
        each end), else the refusal."""
        ok = _is_number(value) and math.isfinite(value)
        ok = ok and (value > lo if open_lo else value >= lo)
        ok = ok and (value < hi if open_hi else value <= hi)
        if not ok:
            self.refuse(field, value, f"a finite number{_span(lo, hi, open_lo, open_hi)}"
                        + (f" ({unit})" if unit else ""))
        return float(value)

    def integer(self, field: str, value: Any, lo: int, hi: int, what: str = "") -> int:
        if not (_is_int(value) and lo <= value <= hi):
            self.refuse(field, value, f"an integer in {lo}..{hi}" + (f" ({what})" if what else ""))
        return int(value)

    def numbers(self, field: str, value: Any, count: int, lo: float, hi: float, unit: str,
                **bounds: bool) -> list[float]:
        if not isinstance(value, list) or len(value) != count:
            self.refuse(field, value, f"a list of {count} numbers" + (f" ({unit})" if unit else ""))
        return [self.number(f"{field}[{i}]", v, lo, hi, unit, **bounds)
                for i, v in enumerate(value)]

    def pair(self, field: str, value: Any, lo: float, hi: float, unit: str) -> list[float]:
        """[low, high], finite, low <= high, both in [lo, hi]."""
        a, b = self.numbers(field, value, 2, lo, hi, unit)
        if not a <= b:
            self.refuse(field, value, f"[low, high] with low <= high ({unit})")
        return [a, b]

    def hw(self, field: str, value: Any) -> list[int]:
        if not isinstance(value, list) or len(value) != 2:
            self.refuse(field, value, f"[height, width], integers in 1..{PIXELS_MAX} px")
        return [self.integer(f"{field}[{i}]", v, 1, PIXELS_MAX, "px") for i, v in enumerate(value)]


def _span(lo: float, hi: float, open_lo: bool, open_hi: bool) -> str:
    """The allowed interval as text: ' in [lo, hi]' (with its open ends), ' > lo' where the
    upper end is infinite, nothing where both are."""
    if math.isinf(lo) and math.isinf(hi):
        return ""
    if math.isinf(hi):
        return f" {'>' if open_lo else '>='} {lo:g}"
    return f" in {'(' if open_lo else '['}{lo:g}, {hi:g}{')' if open_hi else ']'}"


def _first_non_finite(value: Any, path: str) -> tuple[str, Any] | None:
    """The first float in `value` (a parsed JSON tree) that is NaN or infinite, with its path;
    iterative, so no nesting depth the decoder accepted can overflow the stack here."""
    stack = [(path, value)]
    while stack:
        where, v = stack.pop()
        if isinstance(v, float) and not math.isfinite(v):
            return where, v
        if isinstance(v, dict):
            stack.extend((f"{where}.{str(k)[:SHOWN_CHARS]}", x) for k, x in v.items())
        elif isinstance(v, list):
            stack.extend((f"{where}[{i}]", x) for i, x in enumerate(v))
    return None


def validate_metadata(meta: dict[str, Any], source: str, graph_input: str | None = None) -> None:
    """Refuse, with `InvalidMetadata` naming the field, metadata whose values the frame path,
    `status` or the size checks could not use: every field they read is of its type and in its
    range (the optics as `nhfd.config` allows them, a positive amplitude scale and focal length,
    a power-of-two input multiple, [near, far] volumes and envelopes in order, sizes in pixels),
    a model fed depth (`graph_input` "rgbd", else the metadata's own `inputs`) has its scene
    mapping, and no number anywhere is NaN or infinite (JSON from Python writes them) except a
    failed size check's difference (`checked_size_entry` records NaN there, with ok false)."""
    f = _Fields(source)
    version = meta.get("format_version", MISSING)
    f.integer("format_version", version, 1, FORMAT_VERSION)
    # The optics: what the frame path propagates and codes with.
    f.numbers("wavelengths_m", meta.get("wavelengths_m", MISSING), COLOURS, *WAVELENGTH_RANGE_M,
              "m")
    f.number("pitch_m", meta.get("pitch_m", MISSING), 0.0, PITCH_MAX_M, "m", open_lo=True,
             open_hi=True)
    if meta.get("aperture_shape") not in APERTURE_SHAPES:
        f.refuse("aperture_shape", meta.get("aperture_shape", MISSING),
                 f"one of {', '.join(APERTURE_SHAPES)}")
    f.numbers("cutoff_per_px", meta.get("cutoff_per_px", MISSING), COLOURS, 0.0,
              CUTOFF_MAX_PER_PX,
              "cycles/px", open_lo=True)
    z0 = f.number("z0_m", meta.get("z0_m", MISSING), 0.0, Z0_MAX_M, "m", open_lo=True)
    volume = meta.get("volume_m", MISSING)
    near, far = f.numbers("volume_m", volume, 2, -math.inf, math.inf, "m", open_lo=True,
                          open_hi=True)
    if not near < far:
        f.refuse("volume_m", volume, "[near, far] in metres from the reference plane with near "
                                     "< far")
    if not z0 + near > 0:
        f.refuse("volume_m", volume, f"a near end in front of the SLM (z0_m + near > 0, z0_m = "
                                     f"{z0:g})")
    panel = meta.get("panel_hw")
    if panel not in (None, []):
        f.hw("panel_hw", panel)
    f.number("amplitude_scale", meta.get("amplitude_scale", MISSING), *AMPLITUDE_SCALE_RANGE,
             "")
    # The camera: the render's focal lengths (None: from fov_x_deg, as older exports).
    for key in ("fx", "fy"):
        if meta.get(key) is not None:
            f.number(key, meta[key], 0.0, math.inf, "px", open_lo=True, open_hi=True)
    if meta.get("fov_x_deg") is not None:
        f.number("fov_x_deg", meta["fov_x_deg"], 0.0, 180.0, "deg", open_lo=True,
                 open_hi=True)
    if meta.get("fx") is None and meta.get("fov_x_deg") is None:
        # The render needs one or the other: without both, every frame would be drawn at a
        # focal length the model was not trained at.
        f.refuse("fx", meta.get("fx", MISSING), "the render's focal length, a finite number > 0 "
                 "(px) (or fov_x_deg, as older exports record it)")
    # Sizes: the frame window and the graph's padding.
    f.hw("train_size_hw", meta.get("train_size_hw", MISSING))
    if meta.get("train_crop_hw") is not None:
        f.hw("train_crop_hw", meta["train_crop_hw"])
    multiple = meta.get("input_multiple", MISSING)
    if not (_is_int(multiple) and 1 <= multiple <= INPUT_MULTIPLE_MAX
            and multiple & (multiple - 1) == 0):
        f.refuse("input_multiple", multiple, f"a power of two in 1..{INPUT_MULTIPLE_MAX} "
                                             "(unshuffle x 2^depth)")
    net = meta.get("net")
    if net is not None and not isinstance(net, dict):
        f.refuse("net", net, "an object (the network spec)")
    if net and _is_int(net.get("unshuffle")) and _is_int(net.get("depth")) \
            and 0 <= net["depth"] <= 16 and multiple != net["unshuffle"] * 2 ** net["depth"]:
        f.refuse("input_multiple", multiple, f"net.unshuffle x 2^net.depth = "
                                             f"{net['unshuffle'] * 2 ** net['depth']}")
    _check_mapping(f, meta, graph_input)
    _check_envelope(f, meta.get("pose_envelope"))
    _check_train_poses(f, meta.get("train_poses"))
    _check_sizes(f, meta.get("checked_sizes"))
    for key in ("parameters", "train_steps", "opset"):  # status reports them as numbers
        if meta.get(key) is not None and not _is_int(meta[key]):
            f.refuse(key, meta[key], "an integer or null")
    if meta.get("subframes") is not None:  # one head per subframe (nhfd model tune)
        f.integer("subframes", meta["subframes"], *SUBFRAMES_RANGE, "frames one inference emits")
    for key in ("profile", "scene_sha256", "precision", "nhfd_version"):
        if meta.get(key) is not None and not isinstance(meta[key], str):
            f.refuse(key, meta[key], "a string or null")
    rest = {k: v for k, v in meta.items() if k != "checked_sizes"}
    bad = _first_non_finite(rest, "")
    if bad is not None:
        raise InvalidMetadata(f"{source}: metadata {bad[0][1:]} = {bad[1]!r}: expected a finite "
                              "number (no NaN or infinity anywhere in the metadata)")


def _check_mapping(f: _Fields, meta: dict[str, Any], graph_input: str | None) -> None:
    """The scene mapping `z_h = a_m + b_m / d`: an rgbd model feeds it every frame."""
    declared = meta.get("inputs")
    rgbd = graph_input == "rgbd" if graph_input is not None else (
        isinstance(declared, dict) and "rgbd" in declared)
    mapping = meta.get("mapping", MISSING if rgbd else None)
    if mapping is None and not rgbd:
        return
    if not isinstance(mapping, dict):
        f.refuse("mapping", mapping, "an object with a_m and b_m (the scene's depth mapping"
                 + (", which a model fed depth needs)" if rgbd else ")"))
    for key in ("a_m", "b_m"):
        if key in mapping or rgbd:
            f.number(f"mapping.{key}", mapping.get(key, MISSING), -math.inf, math.inf, "m",
                     open_lo=True, open_hi=True)
    for key in ("d_near", "d_far"):
        if mapping.get(key) is not None:
            f.number(f"mapping.{key}", mapping[key], 0.0, math.inf, "scene units",
                     open_lo=True, open_hi=True)


def _check_envelope(f: _Fields, env: Any) -> None:
    """The pose envelope (`nhfd.dataset.poses.envelope`): each view's warnings compare with it."""
    if env is None:
        return
    if not isinstance(env, dict):
        f.refuse("pose_envelope", env, "an object or null")
    if env.get("n") is not None:
        f.integer("pose_envelope.n", env["n"], 0, 1 << 40)
    inf = math.inf
    if env.get("distance"):
        f.pair("pose_envelope.distance", env["distance"], 0.0, inf, "scene units")
    for key, lo, hi in (("azimuth_deg", -360.0, 360.0), ("elevation_deg", -90.0, 90.0)):
        if env.get(key):
            f.pair(f"pose_envelope.{key}", env[key], lo, hi, "deg")
    lo3, hi3 = env.get("position_min"), env.get("position_max")
    if lo3 or hi3:
        a = f.numbers("pose_envelope.position_min", lo3, 3, -inf, inf, "scene units",
                      open_lo=True, open_hi=True)
        b = f.numbers("pose_envelope.position_max", hi3, 3, -inf, inf, "scene units",
                      open_lo=True, open_hi=True)
        if not all(x <= y for x, y in zip(a, b, strict=True)):
            f.refuse("pose_envelope.position_max", hi3, f"at least position_min = {_shown(lo3)} "
                                                        "in each coordinate")


def _check_train_poses(f: _Fields, poses: Any) -> None:
    """`training_poses`: `nhfd eval` measures view angles against them."""
    if poses is None:
        return
    if not isinstance(poses, dict) or not isinstance(poses.get("positions"), list):
        f.refuse("train_poses", poses, "an object with center and positions, or null")
    inf = math.inf
    f.numbers("train_poses.center", poses.get("center"), 3, -inf, inf, "scene units",
              open_lo=True, open_hi=True)
    for i, p in enumerate(poses["positions"]):
        f.numbers(f"train_poses.positions[{i}]", p, 3, -inf, inf, "scene units",
                  open_lo=True, open_hi=True)


def _check_sizes(f: _Fields, sizes: Any) -> None:
    """`checked_sizes` (entries of `checked_size_entry`): the frame worker serves a window only
    at a size listed ok, so an entry may not claim ok without a difference within tolerance."""
    if sizes is None:
        return
    if not isinstance(sizes, list):
        f.refuse("checked_sizes", sizes, "a list of size check entries")
    for i, e in enumerate(sizes):
        where = f"checked_sizes[{i}]"
        if not isinstance(e, dict) or not isinstance(e.get("ok"), bool):
            f.refuse(where, e, "an object with hw, max_abs_diff, ok (true or false), against")
        f.hw(f"{where}.hw", e.get("hw"))
        diff = e.get("max_abs_diff")
        if e["ok"]:
            f.number(f"{where}.max_abs_diff", diff, 0.0, SIZE_TOLERANCE, "ok is true")
        elif not _is_number(diff):  # NaN or infinite: a failed check, recorded as failed
            f.refuse(f"{where}.max_abs_diff", diff, "a number")
        if not isinstance(e.get("against", ""), str):
            f.refuse(f"{where}.against", e.get("against"), "a string")
