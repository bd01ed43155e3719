"""glTF 2.0 scenes with `KHR_gaussian_splatting` primitives (`.glb` and `.gltf`): read them.

Facts (KhronosGroup/glTF extensions/2.0/Khronos/KHR_gaussian_splatting/README.md, and the glTF
2.0 specification):

* Every mesh primitive whose `extensions` hold `KHR_gaussian_splatting` is a set of Gaussians,
  one per vertex (`mode` POINTS). Attributes, each an accessor with N elements:
  `POSITION` VEC3 float; `KHR_gaussian_splatting:ROTATION` VEC4 x y z w (float, or normalised
  signed byte/short); `KHR_gaussian_splatting:SCALE` VEC3, linear standard deviations, never
  negative (the spec's current text, after KhronosGroup/glTF issue 2563; splat-transform writes
  exp() of the .ply's log-scales since its PR 268); `KHR_gaussian_splatting:OPACITY` SCALAR in
  [0, 1]; `KHR_gaussian_splatting:SH_DEGREE_l_COEF_n` VEC3 float r g b, degree 0 (f_dc)
  required and every band up to the highest present. `COLOR_0` is a fallback for viewers
  without splats, used here only if the SH are absent.
* Axes: "glTF uses a right-handed coordinate system ... +Y up, +Z forward, -X right" (glTF 2.0,
  section 3.4), i.e. LUF, which the .spz README also names for GLB; converted here to the
  project's RDF frame by negating x and y, so glTF's up (+y) becomes -y.
* `.glb`: 12-byte header `<I magic 'glTF', I version 2, I length>`, then chunks `<I length,
  I type>`: JSON (0x4E4F534A) first, then an optional BIN (0x004E4942) that is buffer 0.
  `.gltf`: the JSON alone, buffers by `uri` (a relative file or a base64 `data:` URI).

Not supported (a clear error): node transforms other than identity, sparse accessors, and
required compression extensions.
"""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path
from typing import Any
from urllib.parse import unquote

import numpy as np

from nhfd.scene.axes import flip_axes, signs_from_letters
from nhfd.scene.gaussians import SH_C0, SceneFileError, malformed_as_scene_error

__all__ = ["GLB_MAGIC", "read_gltf"]

GLB_MAGIC = b"glTF"
EXTENSION = "KHR_gaussian_splatting"
_GLB_HEADER = struct.Struct("<4sII")
_CHUNK = struct.Struct("<II")
_JSON, _BIN = 0x4E4F534A, 0x004E4942
_LUF = signs_from_letters("LUF")
# componentType -> (dtype, divisor when `normalized`), glTF 2.0 section 3.11.
_COMPONENTS = {5120: ("i1", 127.0), 5121: ("u1", 255.0), 5122: ("<i2", 32767.0),
               5123: ("<u2", 65535.0), 5125: ("<u4", None), 5126: ("<f4", None)}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_BANDS = (1, 3, 5, 7)  # SH coefficients per degree
_IDENTITY = {"matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
             "translation": [0, 0, 0], "rotation": [0, 0, 0, 1], "scale": [1, 1, 1]}


def read_gltf(path: Path) -> dict[str, np.ndarray]:
    """Activated arrays (means, quats wxyz, scales, opacities, sh) in the project's frame."""
    data = path.read_bytes()
    doc, bin_chunk = _parse_glb(path, data) if data[:4] == GLB_MAGIC else (_json(path, data), None)
    with malformed_as_scene_error(path, "glTF"):
        return _read_doc(path, doc, bin_chunk)


def _read_doc(path: Path, doc: dict[str, Any], bin_chunk: bytes | None) -> dict[str, np.ndarray]:
    reader = _Buffers(path, doc, bin_chunk)
    parts = [_primitive(path, doc, reader, p) for p in _splat_primitives(path, doc)]
    k = max(p["sh"].shape[1] for p in parts)
    for p in parts:  # pad lower-degree primitives with zero bands so they concatenate
        p["sh"] = np.pad(p["sh"], ((0, 0), (0, k - p["sh"].shape[1]), (0, 0)))
    arrays = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    flip_axes(arrays, _LUF)
    return arrays


def _json(path: Path, raw: bytes) -> dict[str, Any]:
    try:
        doc = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SceneFileError(f"{path}: unreadable glTF JSON ({e})") from e
    asset = doc.get("asset") if isinstance(doc, dict) else None
    if not isinstance(asset, dict) or not str(asset.get("version", "")).startswith("2."):
        raise SceneFileError(f"{path}: not a glTF 2.0 document (asset.version must be \"2.x\")")
    return doc


def _parse_glb(path: Path, data: bytes) -> tuple[dict[str, Any], bytes | None]:
    if len(data) < _GLB_HEADER.size + _CHUNK.size:
        raise SceneFileError(f"{path}: truncated .glb header ({len(data)} bytes)")
    _, version, length = _GLB_HEADER.unpack_from(data)
    if version != 2:
        raise SceneFileError(f"{path}: unsupported .glb version {version} (supported: 2)")
    if length > len(data):
        raise SceneFileError(
            f"{path}: truncated .glb data: the header declares {length} bytes, the file has "
            f"{len(data)}"
        )
    chunks, at = [], _GLB_HEADER.size
    while at + _CHUNK.size <= length:
        size, kind = _CHUNK.unpack_from(data, at)
        if at + _CHUNK.size + size > length:
            raise SceneFileError(f"{path}: truncated .glb data (chunk at byte {at} is cut off)")
        chunks.append((kind, data[at + _CHUNK.size : at + _CHUNK.size + size]))
        at += _CHUNK.size + size
    if not chunks or chunks[0][0] != _JSON:
        raise SceneFileError(f"{path}: .glb does not start with a JSON chunk")
    bins = [c for kind, c in chunks[1:] if kind == _BIN]
    return _json(path, chunks[0][1]), (bins[0] if bins else None)


def _splat_primitives(path: Path, doc: dict[str, Any]) -> list[dict[str, Any]]:
    known = {EXTENSION}
    unknown = [e for e in doc.get("extensionsRequired", []) if e not in known]
    if unknown:
        raise SceneFileError(f"{path}: glTF requires unsupported extensions: {', '.join(unknown)}")
    for node in doc.get("nodes", []):  # a transform on a mesh's node or any parent moves it
        moves = any(node.get(k, v) != v for k, v in _IDENTITY.items())
        if moves and ("mesh" in node or "children" in node):
            raise SceneFileError(
                f"{path}: a node transforms its splat mesh; node transforms are not supported"
            )
    found = [p for m in doc.get("meshes", []) for p in m.get("primitives", [])
             if EXTENSION in p.get("extensions", {})]
    if not found:
        raise SceneFileError(f"{path}: glTF has no mesh primitive with the {EXTENSION} extension")
    return found


class _Buffers:
    """Resolves accessors to arrays, loading each buffer once."""

    def __init__(self, path: Path, doc: dict[str, Any], bin_chunk: bytes | None) -> None:
        self.path, self.doc, self.bin_chunk, self.cache = path, doc, bin_chunk, {}

    def buffer(self, index: int) -> bytes:
        if index not in self.cache:
            spec = self.doc["buffers"][index]
            uri = spec.get("uri")
            if uri is None:
                if self.bin_chunk is None:
                    raise SceneFileError(f"{self.path}: buffer {index} has no uri and no BIN chunk")
                blob = self.bin_chunk
            elif uri.startswith("data:"):
                blob = base64.b64decode(uri.split(",", 1)[1])
            else:
                try:
                    blob = (self.path.parent / unquote(uri)).read_bytes()
                except OSError as e:
                    raise SceneFileError(f"{self.path}: cannot read buffer {uri!r} ({e})") from e
            if len(blob) < spec.get("byteLength", 0):
                raise SceneFileError(
                    f"{self.path}: truncated buffer {index}: {len(blob)} of "
                    f"{spec['byteLength']} bytes"
                )
            self.cache[index] = blob
        return self.cache[index]

    def accessor(self, index: int, name: str) -> np.ndarray:
        """[count, width] float64, normalised integers scaled as glTF 2.0 section 3.11 says."""
        try:
            acc = self.doc["accessors"][index]
            if "sparse" in acc:
                raise SceneFileError(f"{self.path}: {name}: sparse accessors are not supported")
            dtype, divisor = _COMPONENTS[acc["componentType"]]
            width, count = _WIDTH[acc["type"]], int(acc["count"])
            view = self.doc["bufferViews"][acc["bufferView"]]
            blob = self.buffer(view["buffer"])
        except (KeyError, IndexError, TypeError) as e:
            raise SceneFileError(f"{self.path}: {name}: malformed accessor {index} ({e!r})") from e
        item = np.dtype(dtype).itemsize * width
        stride = view.get("byteStride", item)
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        end = start + (stride * (count - 1) + item if count else 0)
        if end > min(len(blob), view.get("byteOffset", 0) + view["byteLength"]):
            raise SceneFileError(f"{self.path}: truncated data: {name} runs past its buffer")
        raw = np.frombuffer(blob, np.uint8, end - start, start) if count else np.zeros(0, np.uint8)
        rows = np.lib.stride_tricks.as_strided(raw, (count, item), (stride, 1)) if count else raw
        out = np.ascontiguousarray(rows).view(dtype).reshape(count, width).astype(np.float64)
        if acc.get("normalized") and divisor:
            out = np.maximum(out / divisor, -1.0)
        return out


def _primitive(path: Path, doc: dict[str, Any], buffers: _Buffers,
               prim: dict[str, Any]) -> dict[str, np.ndarray]:
    attrs = prim.get("attributes", {})

    def get(name: str, width: int) -> np.ndarray:
        if name not in attrs:
            raise SceneFileError(f"{path}: splat primitive lacks the required attribute {name}")
        arr = buffers.accessor(attrs[name], name)
        if arr.shape[1] != width:
            raise SceneFileError(f"{path}: {name} has {arr.shape[1]} components, expected {width}")
        return arr

    prefix = f"{EXTENSION}:"
    means = get("POSITION", 3)
    xyzw = get(prefix + "ROTATION", 4)
    scales = get(prefix + "SCALE", 3)
    if (scales < 0).any():
        raise SceneFileError(
            f"{path}: {prefix}SCALE holds negative values; the extension stores linear scales, "
            "never negative (log-scales come from an older draft)"
        )
    degree = -1
    while degree < 3 and f"{prefix}SH_DEGREE_{degree + 1}_COEF_0" in attrs:
        degree += 1
    if degree < 0 and "COLOR_0" in attrs:  # no SH: the fallback's diffuse colour
        sh = ((buffers.accessor(attrs["COLOR_0"], "COLOR_0")[:, :3] - 0.5) / SH_C0)[:, None, :]
    elif degree < 0:
        raise SceneFileError(
            f"{path}: splat primitive lacks the required attribute {prefix}SH_DEGREE_0_COEF_0"
        )
    else:
        sh = np.stack([get(f"{prefix}SH_DEGREE_{d}_COEF_{c}", 3)
                       for d in range(degree + 1) for c in range(_BANDS[d])], axis=1)
    n = means.shape[0]
    arrays = dict(means=means, quats=xyzw[:, [3, 0, 1, 2]], scales=scales,
                  opacities=get(prefix + "OPACITY", 1)[:, 0], sh=sh)
    for name, arr in arrays.items():
        if arr.shape[0] != n:
            raise SceneFileError(f"{path}: {name} has {arr.shape[0]} elements, POSITION has {n}")
    return arrays
