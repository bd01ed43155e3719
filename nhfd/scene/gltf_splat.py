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
  `.gltf`: the JSON alone, buffers by `uri` (a relative file or a base64 `data:` URI). Here a
  file must be a regular file inside the scene file's folder (`nhfd.scene.limits`).

Not supported (a clear error): node transforms other than identity, sparse accessors, and
required compression extensions.
"""

from __future__ import annotations

import base64
import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO
from urllib.parse import unquote

import numpy as np

from nhfd.scene.axes import flip_axes, signs_from_letters
from nhfd.scene.gaussians import SH_C0, SceneFileError, malformed_as_scene_error
from nhfd.scene.limits import (
    MAX_GAUSSIANS,
    MAX_JSON_BYTES,
    check_count,
    check_max_gaussians,
    contained,
    open_regular,
)

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
# Chunks a .glb may have before its BIN chunk (the JSON chunk and unknown ones, which are
# skipped): glTF 2.0 defines two kinds, so a long run of chunks is not a real file.
_MAX_CHUNKS = 16
# Attributes a splat primitive's accessors are checked for (with every KHR_gaussian_splatting:*)
_ATTRIBUTES = ("POSITION", "COLOR_0")
_IDENTITY = {"matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
             "translation": [0, 0, 0], "rotation": [0, 0, 0, 1], "scale": [1, 1, 1]}


def read_gltf(path: Path, max_gaussians: int = MAX_GAUSSIANS) -> dict[str, np.ndarray]:
    """Activated arrays (means, quats wxyz, scales, opacities, sh) in the project's frame.

    Bounded before any buffer is read: the splat primitives may hold at most `max_gaussians`
    Gaussians together, every accessor must lie inside its bufferView and every bufferView
    inside its buffer's byteLength (byteStride from the element size to glTF's 252), and only
    the bytes those accessors span are read. A buffer `uri` must name a regular file inside
    the scene file's folder (or be a `data:` URI, bounded with the JSON by MAX_JSON_BYTES)."""
    check_max_gaussians(max_gaussians)
    with open_regular(path, path, "the scene file") as f:
        if f.read(4) == GLB_MAGIC:
            f.seek(0)
            doc, bin_chunk = _parse_glb(path, f)
        else:
            f.seek(0)
            doc, bin_chunk = _json(path, _read_json(path, f, "glTF JSON")), None
        with malformed_as_scene_error(path, "glTF"):
            return _read_doc(path, doc, bin_chunk, max_gaussians)


def _read_doc(path: Path, doc: dict[str, Any], bin_chunk: _Chunk | None,
              max_gaussians: int) -> dict[str, np.ndarray]:
    reader = _Buffers(path, doc, bin_chunk, max_gaussians)
    prims = [(p, reader.plan(p)) for p in _splat_primitives(path, doc)]
    # Every accessor is checked and the count known before anything is read or allocated.
    check_count(path, "the splat primitives (POSITION counts, together)",
                sum(n for _, n in prims), max_gaussians)
    parts = [_primitive(path, reader, p) for p, _ in prims]
    k = max(p["sh"].shape[1] for p in parts)
    for p in parts:  # pad lower-degree primitives with zero bands so they concatenate
        p["sh"] = np.pad(p["sh"], ((0, 0), (0, k - p["sh"].shape[1]), (0, 0)))
    arrays = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    flip_axes(arrays, _LUF)
    return arrays


def _read_json(path: Path, f: BinaryIO, what: str) -> bytes:
    raw = f.read(MAX_JSON_BYTES + 1)
    if len(raw) > MAX_JSON_BYTES:
        raise SceneFileError(f"{path}: {what} is more than the {MAX_JSON_BYTES:,} bytes allowed "
                             "(MAX_JSON_BYTES)")
    return raw


def _json(path: Path, raw: bytes) -> dict[str, Any]:
    try:
        doc = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise SceneFileError(f"{path}: unreadable glTF JSON ({e})") from e
    asset = doc.get("asset") if isinstance(doc, dict) else None
    if not isinstance(asset, dict) or not str(asset.get("version", "")).startswith("2."):
        raise SceneFileError(f"{path}: not a glTF 2.0 document (asset.version must be \"2.x\")")
    return doc


@dataclass(frozen=True)
class _Chunk:
    """A .glb BIN chunk: read from the open file where needed, not held whole."""

    file: BinaryIO
    offset: int  # in the file
    length: int

    def read(self, n: int) -> bytes:
        self.file.seek(self.offset)
        return self.file.read(min(n, self.length))


def _parse_glb(path: Path, f: BinaryIO) -> tuple[dict[str, Any], _Chunk | None]:
    file_bytes = os.fstat(f.fileno()).st_size
    if file_bytes < _GLB_HEADER.size + _CHUNK.size:
        raise SceneFileError(f"{path}: truncated .glb header ({file_bytes} bytes)")
    _, version, length = _GLB_HEADER.unpack(f.read(_GLB_HEADER.size))
    if version != 2:
        raise SceneFileError(f"{path}: unsupported .glb version {version} (supported: 2)")
    if length > file_bytes:
        raise SceneFileError(
            f"{path}: truncated .glb data: the header declares {length} bytes, the file has "
            f"{file_bytes} bytes"
        )
    doc, at = None, _GLB_HEADER.size
    # Walk the chunk headers (seeking, not reading, past what is not JSON) up to the first BIN
    # chunk, the only one read as buffer 0; a bounded number, so a file of empty chunks ends.
    for _ in range(_MAX_CHUNKS):
        if at + _CHUNK.size > length:
            break
        f.seek(at)
        size, kind = _CHUNK.unpack(f.read(_CHUNK.size))
        if at + _CHUNK.size + size > length:
            raise SceneFileError(f"{path}: truncated .glb data (chunk at byte {at} is cut off)")
        if doc is None:
            if kind != _JSON:
                break
            if size > MAX_JSON_BYTES:
                raise SceneFileError(f"{path}: .glb JSON chunk is {size:,} bytes, more than the "
                                     f"{MAX_JSON_BYTES:,} allowed (MAX_JSON_BYTES)")
            doc = _json(path, f.read(size))
        elif kind == _BIN:
            return doc, _Chunk(f, at + _CHUNK.size, size)
        at += _CHUNK.size + size
    else:
        raise SceneFileError(f"{path}: .glb has more than {_MAX_CHUNKS} chunks before its BIN "
                             "chunk (glTF 2.0 defines two)")
    if doc is None:
        raise SceneFileError(f"{path}: .glb does not start with a JSON chunk")
    return doc, None


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


@dataclass(frozen=True)
class _Access:
    """An accessor, checked against its bufferView and buffer: where its elements lie."""

    dtype: str
    divisor: float | None  # for `normalized` integers
    width: int  # components per element
    count: int
    buffer: int
    start: int  # byte offset of element 0 in the buffer
    stride: int
    item: int  # bytes per element

    @property
    def end(self) -> int:
        """One past the last byte of the last element, in the buffer."""
        return self.start + (self.stride * (self.count - 1) + self.item if self.count else 0)


def _index(path: Path, doc: dict[str, Any], key: str, index: object, what: str) -> Any:
    """doc[key][index] for a non-negative int index (Python would take -1 as the last)."""
    items = doc.get(key)
    if (isinstance(index, bool) or not isinstance(index, int) or not isinstance(items, list)
            or not 0 <= index < len(items) or not isinstance(items[index], dict)):
        raise SceneFileError(f"{path}: {what}: {key}[{index!r}] does not exist")
    return items[index]


def _size(path: Path, spec: dict[str, Any], field: str, what: str, default: int | None) -> int:
    """A byte offset or length of the document: a non-negative int."""
    value = spec.get(field, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise SceneFileError(f"{path}: {what}: {field} is {value!r}; allowed: an integer >= 0")
    return value


class _Buffers:
    """Checks accessors against their bufferViews and buffers (`plan`), then reads of each
    buffer only the bytes the checked accessors span, once."""

    def __init__(self, path: Path, doc: dict[str, Any], bin_chunk: _Chunk | None,
                 max_gaussians: int) -> None:
        self.path, self.doc, self.bin_chunk = path, doc, bin_chunk
        self.max_gaussians = max_gaussians
        self.access: dict[int, _Access] = {}
        self.needed: dict[int, int] = {}  # buffer -> bytes the planned accessors span
        self.cache: dict[int, bytes] = {}

    def plan(self, prim: dict[str, Any]) -> int:
        """Check every attribute accessor of a splat primitive; its Gaussian count."""
        attrs = prim.get("attributes", {})
        if not isinstance(attrs, dict):
            raise SceneFileError(f"{self.path}: a splat primitive's attributes are not an object")
        if "POSITION" not in attrs:
            raise SceneFileError(f"{self.path}: splat primitive lacks the required attribute "
                                 "POSITION")
        counts = {name: self.check(index, name).count for name, index in attrs.items()
                  if name in _ATTRIBUTES or name.startswith(f"{EXTENSION}:")}
        n = counts.get("POSITION", 0)
        for name, count in counts.items():
            if count != n:
                raise SceneFileError(f"{self.path}: {name} has {count} elements, POSITION has {n}")
        return n

    def check(self, index: object, name: str) -> _Access:
        if isinstance(index, int) and index in self.access:
            return self.access[index]
        path, doc = self.path, self.doc
        acc = _index(path, doc, "accessors", index, name)
        if "sparse" in acc:
            raise SceneFileError(f"{path}: {name}: sparse accessors are not supported")
        try:
            dtype, divisor = _COMPONENTS[acc["componentType"]]
            width = _WIDTH[acc["type"]]
        except (KeyError, TypeError) as e:
            raise SceneFileError(f"{path}: {name}: malformed accessor {index} ({e!r})") from e
        count = check_count(path, f"{name} (accessor {index}) count", acc.get("count"),
                            self.max_gaussians)
        view_index = acc.get("bufferView")
        view = _index(path, doc, "bufferViews", view_index, name)
        buffer_index = view.get("buffer")
        buffer = _index(path, doc, "buffers", buffer_index, name)
        item = np.dtype(dtype).itemsize * width
        stride = view.get("byteStride", item)
        if isinstance(stride, bool) or not isinstance(stride, int) or not item <= stride <= 252:
            raise SceneFileError(
                f"{path}: {name}: bufferView {view_index} byteStride is {stride!r}; allowed: "
                f"{item} (its element's size) to 252 (glTF 2.0's maximum)"
            )
        what = f"{name} (accessor {index}, bufferView {view_index})"
        view_offset = _size(path, view, "byteOffset", what, 0)
        view_length = _size(path, view, "byteLength", what, None)
        buffer_length = _size(path, buffer, "byteLength", f"buffer {buffer_index}", None)
        access = _Access(dtype, divisor, width, count, buffer_index,
                         view_offset + _size(path, acc, "byteOffset", what, 0), stride, item)
        if access.end > view_offset + view_length or view_offset + view_length > buffer_length:
            raise SceneFileError(f"{path}: truncated data: {name} runs past its buffer")
        self.needed[buffer_index] = max(self.needed.get(buffer_index, 0), access.end)
        self.access[index] = access
        return access

    def buffer(self, index: int) -> bytes:
        if index not in self.cache:
            spec = self.doc["buffers"][index]
            declared, needed = spec["byteLength"], self.needed[index]
            uri = spec.get("uri")
            if uri is None:
                if self.bin_chunk is None:
                    raise SceneFileError(f"{self.path}: buffer {index} has no uri and no BIN chunk")
                available = self.bin_chunk.length
                blob = self.bin_chunk.read(needed) if available >= declared else b""
            elif not isinstance(uri, str):
                raise SceneFileError(f"{self.path}: buffer {index} uri is {uri!r}, not a string")
            elif uri.startswith("data:"):  # in the JSON, so within MAX_JSON_BYTES already
                blob = base64.b64decode(uri.split(",", 1)[1])
                available = len(blob)
            else:
                what = f"glTF buffer {index} uri"
                target = contained(self.path.parent, unquote(uri), self.path, what)
                try:
                    with open_regular(target, self.path, f"{what} {uri!r}") as f:
                        available = os.fstat(f.fileno()).st_size
                        blob = f.read(needed) if available >= declared else b""
                except OSError as e:
                    raise SceneFileError(f"{self.path}: cannot read buffer {uri!r} ({e})") from e
            if available < declared or len(blob) < needed:
                raise SceneFileError(
                    f"{self.path}: truncated buffer {index}: {min(available, len(blob))} of "
                    f"{declared} bytes"
                )
            self.cache[index] = blob[:needed]
        return self.cache[index]

    def accessor(self, index: int, name: str) -> np.ndarray:
        """[count, width] float64, normalised integers scaled as glTF 2.0 section 3.11 says."""
        a = self.check(index, name)
        if not a.count:
            return np.zeros((0, a.width))
        raw = np.frombuffer(self.buffer(a.buffer), np.uint8, a.end - a.start, a.start)
        rows = np.lib.stride_tricks.as_strided(raw, (a.count, a.item), (a.stride, 1))
        out = np.ascontiguousarray(rows).view(a.dtype).reshape(a.count, a.width).astype(np.float64)
        if self.doc["accessors"][index].get("normalized") and a.divisor:
            out = np.maximum(out / a.divisor, -1.0)
        return out


def _primitive(path: Path, buffers: _Buffers, prim: dict[str, Any]) -> dict[str, np.ndarray]:
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
    # Every attribute has POSITION's count (`_Buffers.plan` checked it before reading).
    return dict(means=means, quats=xyzw[:, [3, 0, 1, 2]], scales=scales,
                opacities=get(prefix + "OPACITY", 1)[:, 0], sh=sh)
