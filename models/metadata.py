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


def manifest_sha256(data_dir: str | Path) -> str | None:
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


def padded_hw(hw: tuple[int, int], multiple: int) -> tuple[int, int]:
    """A window's size rounded up to the input multiple (what the graph runs at)."""
    h, w = int(hw[0]), int(hw[1])
    return h + (-h) % multiple, w + (-w) % multiple


def checked_sizes_hw(metadata: dict[str, Any]) -> tuple[list[tuple[int, int]], bool]:
    """The graph input sizes (h, w) a model passed its size checks at, and whether they come
    from its metadata. A model without `checked_sizes` (exported before they were recorded, or
    with --no-check) counts only its training window (padded to the multiple) as checked: the
    size it was trained and evaluated at; False says so."""
    m = int(metadata.get("input_multiple") or 1)
    if "checked_sizes" not in metadata:
        return [padded_hw(metadata["train_size_hw"], m)], False
    return [(int(e["hw"][0]), int(e["hw"][1])) for e in metadata["checked_sizes"]
            if e.get("ok")], True


def expected_from_config(config) -> dict[str, Any]:
    """The optics a validated `nhfd.config.Config` asks for, in the metadata's keys and units."""
    o = config.optics
    return {
        "wavelengths_m": [v * 1e-9 for v in o.wavelengths_nm],
        "pitch_m": config.slm.pitch_um * 1e-6,
        "aperture_shape": o.aperture.shape,
        "cutoff_per_px": list(o.aperture.cutoff_per_px),
        "z0_m": o.z0_mm * 1e-3,
        "volume_m": [v * 1e-3 for v in o.volume_mm],
    }


def expected_from_manifest(manifest: dict) -> dict[str, Any]:
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
    diff = differences(metadata, expected)
    if diff:
        raise ModelMismatch(
            f"{source} was trained for other optics than configured: " + "; ".join(diff)
            + " (retrain for this configuration, or configure the model's optics)"
        )


def parse_metadata(props: dict[str, str], source: str) -> dict:
    """The nhfd metadata from an ONNX model's metadata map, or `NotAModel`."""
    if METADATA_KEY not in props:
        raise NotAModel(
            f"{source}: an ONNX model without nhfd metadata (not exported by `nhfd export`)"
        )
    try:
        meta = json.loads(props[METADATA_KEY])
    except json.JSONDecodeError as exc:
        raise NotAModel(f"{source}: nhfd metadata is not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise NotAModel(f"{source}: nhfd metadata has no format {FORMAT!r}")
    if int(meta.get("format_version", -1)) > FORMAT_VERSION:
        raise NotAModel(
            f"{source}: model format {meta.get('format_version')} is newer than this nhfd reads "
            f"({FORMAT_VERSION}); upgrade nhfd"
        )
    return meta
