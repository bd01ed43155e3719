"""Scene files: load 3D Gaussian splat scenes into `Gaussians`, write them back, summarise them.

Formats read (`load_scene` picks by content first, extension second):

* INRIA float .ply: `x y z [nx ny nz] f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3`; opacity is
  a logit, scales are logs, rotation a wxyz quaternion, `f_rest` channel-major.
* PlayCanvas/SuperSplat compressed .ply: a `chunk` element (per-256-Gaussian min/max of
  position, log-scale and optionally colour), a `vertex` element of four packed uint32 and an
  optional `sh` element of uint8 `f_rest_*`.
* antimatter15 `.splat`: 32-byte records, no header.
* Niantic `.spz` versions 2-4 (`nhfd.scene.spz`, which also writes it): RUB axes, converted.
* PlayCanvas SOG version 2 (`nhfd.scene.sog`): a folder, its `meta.json`, or a `.sog` zip.
* glTF 2.0 `KHR_gaussian_splatting` `.glb`/`.gltf` (`nhfd.scene.gltf_splat`): +Y up, converted.

Formats that declare axes are converted into the project's OpenCV frame (x right, y down,
z forward; `nhfd.scene.axes`; `nhfd.scene.suggest.detect_up_axis` names the up they imply).

Writers: `save_ply` (INRIA float, the exact inverse of the loader), `save_splat` and
`save_compressed_ply` (both lossy; see their docstrings for the quantisation).

Every problem with a file is a `SceneFileError` whose message starts with the path; a file that
decodes but is not a plausible scene (`check_plausible`) is one too. Files are untrusted input:
every reader refuses more than `max_gaussians` Gaussians (default MAX_GAUSSIANS) before it
allocates for them, reads only regular files, reads and inflates no more than the declared
count needs, and keeps a scene's references inside its folder (`nhfd.scene.limits`).
"""

from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import plyfile

from nhfd.scene import gltf_splat, sog, spz
from nhfd.scene.gaussians import (
    SH_C0,
    SH_DEGREE_FOR_K,
    Gaussians,
    SceneFileError,
    make_gaussians,
)
from nhfd.scene.limits import (
    MAX_GAUSSIANS,
    check_count,
    check_max_gaussians,
    open_regular,
    read_capped,
)

__all__ = [
    "MAX_GAUSSIANS",
    "SceneLoad",
    "check_plausible",
    "load_scene",
    "read_scene",
    "save_compressed_ply",
    "save_ply",
    "save_splat",
    "scene_format",
    "scene_summary",
]

PathLike = str | os.PathLike[str]

CHUNK_SIZE = 256  # Gaussians per chunk in the compressed .ply
SPLAT_RECORD = np.dtype(
    [("pos", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rot", "u1", (4,))]
)
assert SPLAT_RECORD.itemsize == 32

# f_rest counts for SH degree 0..3: 3 colour channels x ((d + 1)^2 - 1) bases.
F_REST_COUNTS = (0, 9, 24, 45)

INRIA_REQUIRED = (
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)  # fmt: skip
CHUNK_REQUIRED = (
    "min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
    "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
)  # fmt: skip
CHUNK_COLOUR = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")

# Opacity is clipped this far from 0 and 1 before the logit so a saved .ply never holds +-inf;
# sigmoid(logit(1 - 1e-7)) rounds back to within 1e-7 in float32.
_OPACITY_EPS = 1e-7


# --------------------------------------------------------------------------------------------
# Loading


# What a file must look like to be taken for a scene (`check_plausible`). A file with a valid
# header and random data decodes to Gaussians too: random float32 bit patterns give 87 % of them
# non-finite or degenerate, and the rest at coordinates near 1e37.
# More than this fraction dropped (non-finite or degenerate values): not a scene with a few bad
# splats but a file that is not a scene.
MAX_DROPPED_FRACTION = 0.5
# The robust box (1st to 99th percentile of the means, per axis) within +-this, in scene units: a
# kilometre in millimetres; float32 positions keep 0.06 units there.
MAX_COORDINATE = 1e6
# The median Gaussian's largest scale at most this fraction of the robust extent (the shared
# scenes: 0.005 to 0.14), checked from MIN_FOR_EXTENT Gaussians on (fewer define no extent).
MAX_SCALE_TO_EXTENT = 0.5
MIN_FOR_EXTENT = 10


@dataclass(frozen=True)
class SceneLoad:
    """A loaded scene and what loading it dropped."""

    gaussians: Gaussians
    declared: int  # Gaussians in the file
    dropped: int  # of them, dropped for non-finite or degenerate values
    dropped_reason: str = ""  # the drop's one-line account ("" when none were dropped)

    def counts(self) -> dict[str, Any]:
        """For a job result and `status`."""
        return {"gaussians": len(self.gaussians), "declared": self.declared,
                "dropped": self.dropped, "dropped_reason": self.dropped_reason}


def read_scene(path: PathLike, max_gaussians: int = MAX_GAUSSIANS) -> SceneLoad:
    """Load a splat scene (any format `scene_format` names) as activated float32 Gaussians,
    with the count of those dropped for non-finite or degenerate values.

    Raises `SceneFileError` naming the file and the problem for anything unreadable, for a file
    declaring more than `max_gaussians` Gaussians (default MAX_GAUSSIANS, the default of
    `[daemon.paths] max_gaussians`), and for a file whose content is not a plausible scene
    (`check_plausible`); ValueError for a `max_gaussians` outside [1, 1e9]. Every reader bounds
    what it reads and decompresses by the declared count (`nhfd.scene.limits`).
    """
    path = Path(path)
    arrays = _read_arrays(path, check_max_gaussians(max_gaussians))
    n = arrays["means"].shape[0]
    if n == 0:  # a file that declares no Gaussians is a valid, empty scene
        return SceneLoad(Gaussians.empty(SH_DEGREE_FOR_K[arrays["sh"].shape[1]]), 0, 0)
    # Catch make_gaussians' drop warning: its count is part of the result.
    with warnings.catch_warnings(record=True) as caught, np.errstate(over="ignore"):
        warnings.simplefilter("always")
        g = make_gaussians(**arrays, source=str(path))
    reason = "; ".join(str(w.message) for w in caught if issubclass(w.category, UserWarning))
    if len(g) == 0:
        raise SceneFileError(
            f"{path}: no usable Gaussians, all {n} have non-finite or degenerate values ({reason})"
        )
    load = SceneLoad(g, n, n - len(g), reason)
    check_plausible(path, load)
    return load


def load_scene(path: PathLike, max_gaussians: int = MAX_GAUSSIANS) -> Gaussians:
    """`read_scene`'s Gaussians; the dropped ones are reported with one warning giving the count,
    at the caller's line."""
    load = read_scene(path, max_gaussians)
    if load.dropped:
        warnings.warn(load.dropped_reason, UserWarning, stacklevel=2)
    return load.gaussians


def _robust_box(means: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1st and 99th percentile of the means per axis (float64): stray floaters do not set it."""
    lo, hi = np.percentile(means.astype(np.float64), [1.0, 99.0], axis=0)
    return lo, hi


def check_plausible(path: PathLike, load: SceneLoad) -> None:
    """Refuse, with `SceneFileError` naming the file, the rule and the found value, content that
    is not a plausible scene: most Gaussians dropped, a robust box not finite or beyond
    +-MAX_COORDINATE, or splats large against the scene. Serves every loader (the daemon's
    load_scene and `nhfd scene info|render`): a file one refuses, the other does too."""
    g, n = load.gaussians, load.declared
    if load.dropped > MAX_DROPPED_FRACTION * n:
        raise SceneFileError(
            f"{path}: not a plausible scene: {load.dropped} of {n} Gaussians "
            f"({load.dropped / n:.0%}) have non-finite or degenerate values, more than "
            f"{MAX_DROPPED_FRACTION:.0%} (random or corrupt data?)"
        )
    lo, hi = _robust_box(g.means)
    reach = float(np.max(np.abs(np.concatenate([lo, hi]))))
    if not reach <= MAX_COORDINATE:  # NaN fails too
        raise SceneFileError(
            f"{path}: not a plausible scene: its robust bounds (1st-99th percentile of the "
            f"means) reach {reach:.3g} scene units, beyond +-{MAX_COORDINATE:g}"
        )
    extent = float(np.linalg.norm(hi - lo))
    if len(g) >= MIN_FOR_EXTENT:
        median_scale = float(np.median(g.scales.max(1)))
        if not median_scale <= MAX_SCALE_TO_EXTENT * extent:
            raise SceneFileError(
                f"{path}: not a plausible scene: the median Gaussian's largest scale "
                f"{median_scale:.3g} is more than {MAX_SCALE_TO_EXTENT:g} x the robust extent "
                f"{extent:.3g}"
            )


# Activated arrays, any float dtype, keyed as make_gaussians takes them (means, quats, ...).
Arrays = dict[str, np.ndarray]


# The file at the heart of a SOG scene (beside its WebP images, in a folder or a .sog zip).
SOG_META = "meta.json"
# The names scenes are read from: a file with one of these suffixes, a file of one of these whole
# names (a SOG scene's meta.json), or a SOG scene's folder. The daemon's load_scene and the CLI
# accept these.
SCENE_SUFFIXES = (".ply", ".splat", ".spz", ".glb", ".gltf", ".sog")
SCENE_NAMES = (SOG_META,)


def is_sog_folder(path: PathLike) -> bool:
    """A folder holding a SOG scene's meta.json (and its WebP images)."""
    path = Path(path)
    return path.is_dir() and (path / SOG_META).is_file()


def scene_format(path: PathLike) -> str | None:
    """The file's format from its header (its name only where the format has no magic):
    'ply', 'compressed' (PlayCanvas .ply), 'splat', 'spz', 'gltf', 'sog', or None when it is
    none of these or unreadable (`load_scene` says why)."""
    path = Path(path)
    if path.suffix.lower() == ".sog" or path.name.lower() in SCENE_NAMES or is_sog_folder(path):
        return "sog"
    try:  # a FIFO would block open() and a device never end: only regular files are read
        with open_regular(path, path, "the scene file") as f:
            head = f.read(4096)
    except (OSError, SceneFileError):
        return None
    if head.startswith(b"ply"):
        return "compressed" if b"element chunk" in head.split(b"end_header", 1)[0] else "ply"
    if head[:2] == b"\x1f\x8b" or head[:4] == spz.SPZ_MAGIC:  # .spz v2/v3 gzip, v4 NGSP
        return "spz"
    if head[:4] == gltf_splat.GLB_MAGIC or path.suffix.lower() == ".gltf":
        return "gltf"
    if head[:4] == sog.ZIP_MAGIC:  # a SOG zip bundle under another name
        return "sog"
    if path.suffix.lower() == ".splat":
        return "splat"
    return None


# Formats a name promises, and how their files start: a file that breaks the promise says so.
_MAGIC_OF = {".ply": ("PLY", "'ply'"), ".spz": (".spz", "gzip data or 'NGSP'"),
             ".glb": (".glb", "'glTF'")}


def _read_arrays(path: Path, max_gaussians: int) -> Arrays:
    if not is_sog_folder(path):
        # A missing or unreadable file raises OSError here, as open() words it; a FIFO, a
        # device or a directory is a SceneFileError naming its kind.
        with open_regular(path, path, "the scene file"):
            pass
    fmt = scene_format(path)
    if fmt in ("ply", "compressed"):
        return _load_ply(path, max_gaussians)
    if fmt == "splat":
        return _load_splat(path, max_gaussians)
    if fmt == "spz":
        return spz.read_spz(path, max_gaussians)
    if fmt == "gltf":
        return gltf_splat.read_gltf(path, max_gaussians)
    if fmt == "sog":
        return sog.read_sog(path, max_gaussians)
    suffix = path.suffix.lower()
    if suffix in _MAGIC_OF:
        name, magic = _MAGIC_OF[suffix]
        raise SceneFileError(f"{path}: not a {name} file (does not start with {magic})")
    raise SceneFileError(
        f"{path}: unknown scene format (expected .ply, .splat, .spz, .glb, .gltf or SOG)"
    )


# Bytes a binary PLY value of each type takes (the PLY spec's names and plyfile's aliases).
_PLY_TYPE_BYTES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2,
                   "int16": 2, "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4,
                   "float": 4, "float32": 4, "double": 8, "float64": 8}
# A PLY header names a few dozen properties (INRIA's, 62 lines); longer is not a scene's.
MAX_PLY_HEADER_BYTES = 1 << 16


def _check_ply_header(path: Path, f: BinaryIO, max_gaussians: int) -> None:
    """Refuse, before plyfile allocates an array per element, an element declaring more rows
    than `max_gaussians`, and a file too short for the rows its header declares: binary rows
    take their properties' bytes (a list at least its length field), ASCII rows at least two
    characters a value. A header this cannot parse is left to plyfile, which says what is
    wrong with it."""
    head = f.read(MAX_PLY_HEADER_BYTES)
    end = re.search(rb"(?m)^end_header[ \t]*\r?\n", head)
    if end is None:
        if len(head) == MAX_PLY_HEADER_BYTES:
            raise SceneFileError(f"{path}: PLY header longer than {MAX_PLY_HEADER_BYTES:,} "
                                 "bytes (no end_header within them)")
        return
    fmt, elements = "", []  # [name, rows, bytes a binary row, values a row]
    for line in head[: end.start()].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) >= 2 and words[0] == "format":
            fmt = words[1]
        elif len(words) == 3 and words[0] == "element":
            if not re.fullmatch(r"\d+", words[2]):
                return
            elements.append([words[1], int(words[2]), 0, 0])
        elif len(words) >= 3 and words[0] == "property" and elements:
            kind = words[2] if words[1] == "list" else words[1]  # a list: its length field
            if kind not in _PLY_TYPE_BYTES:
                return
            elements[-1][2] += _PLY_TYPE_BYTES[kind]
            elements[-1][3] += 1
    for name, rows, _, _ in elements:
        check_count(path, f"PLY element '{name}'", rows, max_gaussians,
                    unit="Gaussians" if name == "vertex" else "rows")
    if fmt == "ascii":
        need = max(0, sum(rows * 2 * values for _, rows, _, values in elements) - 1)
    else:
        need = sum(rows * row_bytes for _, rows, row_bytes, _ in elements)
    have = os.fstat(f.fileno()).st_size - end.end()
    if need > have:
        raise SceneFileError(
            f"{path}: truncated data, the file is shorter than its header declares: its "
            f"{', '.join(f'{rows:,} {name}' for name, rows, _, _ in elements)} rows need at "
            f"least {need:,} bytes after the header, the file has {have:,} bytes"
        )


def _load_ply(path: Path, max_gaussians: int) -> Arrays:
    try:
        with open_regular(path, path, "the scene file") as f:
            _check_ply_header(path, f, max_gaussians)
            f.seek(0)
            ply = plyfile.PlyData.read(f)
    except plyfile.PlyElementParseError as e:
        if "end-of-file" in str(e):
            raise SceneFileError(
                f"{path}: truncated data, the file is shorter than its header declares ({e})"
            ) from e
        raise SceneFileError(f"{path}: unreadable PLY data ({e})") from e
    except plyfile.PlyParseError as e:
        raise SceneFileError(f"{path}: unreadable PLY header ({e})") from e
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise SceneFileError(f"{path}: PLY has no 'vertex' element (elements: {names})")
    if "chunk" in names:
        return _decode_compressed(path, ply)
    return _decode_inria(path, ply["vertex"])


def _require(path: Path, element: plyfile.PlyElement, names: tuple[str, ...]) -> None:
    have = {p.name for p in element.properties}
    missing = [n for n in names if n not in have]
    if missing:
        raise SceneFileError(
            f"{path}: element '{element.name}' is missing required properties: "
            + ", ".join(missing)
        )


def _column(element: plyfile.PlyElement, name: str, dtype: type = np.float64) -> np.ndarray:
    return np.asarray(element[name], dtype=dtype)


def _f_rest_names(path: Path, element: plyfile.PlyElement) -> list[str]:
    """The element's `f_rest_*` names in index order; their count must be a valid SH size."""
    idx = sorted(
        int(m.group(1)) for p in element.properties if (m := re.fullmatch(r"f_rest_(\d+)", p.name))
    )
    if len(idx) not in F_REST_COUNTS or idx != list(range(len(idx))):
        raise SceneFileError(
            f"{path}: element '{element.name}' has {len(idx)} f_rest_* properties; expected "
            f"f_rest_0..f_rest_{{n-1}} with n in {F_REST_COUNTS} (SH degree 0-3)"
        )
    return [f"f_rest_{i}" for i in idx]


def _sh_from_columns(f_dc: np.ndarray, f_rest: np.ndarray) -> np.ndarray:
    """[N,3] DC and [N, 3*(K-1)] channel-major rest -> [N, K, 3] basis-major."""
    n, k_rest = f_dc.shape[0], f_rest.shape[1] // 3  # explicit sizes: N may be 0
    rest = f_rest.reshape(n, 3, k_rest).transpose(0, 2, 1)
    return np.concatenate([f_dc[:, None, :], rest], axis=1)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    # exp(-log(1 + e^-x)) never overflows, unlike 1 / (1 + exp(-x)) for very negative logits.
    return np.exp(-np.logaddexp(0.0, -x))


def _decode_inria(path: Path, v: plyfile.PlyElement) -> Arrays:
    _require(path, v, INRIA_REQUIRED)
    rest_names = _f_rest_names(path, v)
    n = v.count

    def stack(names: list[str] | tuple[str, ...], dtype: type = np.float64) -> np.ndarray:
        if not names:
            return np.zeros((n, 0), dtype)
        return np.stack([_column(v, name, dtype) for name in names], axis=1)

    # Values make_gaussians only casts to float32 are read as float32 (the same single
    # rounding, half the memory: SH are 48 of a Gaussian's 62 values); exp and the sigmoid are
    # computed in float64 first.
    f32 = np.float32
    with np.errstate(over="ignore", invalid="ignore"):  # bad values are dropped by load_scene
        return dict(
            means=stack(("x", "y", "z"), f32),
            quats=stack(("rot_0", "rot_1", "rot_2", "rot_3"), f32),
            scales=np.exp(stack(("scale_0", "scale_1", "scale_2"))),
            opacities=_sigmoid(_column(v, "opacity")),
            sh=_sh_from_columns(stack(("f_dc_0", "f_dc_1", "f_dc_2"), f32),
                                stack(rest_names, f32)),
        )


# --- PlayCanvas / SuperSplat compressed .ply ------------------------------------------------


def _unorm(packed: np.ndarray, shift: int, bits: int) -> np.ndarray:
    """Unsigned `bits`-bit field at `shift` as a float in [0, 1]."""
    mask = (1 << bits) - 1
    return ((packed >> np.uint32(shift)) & np.uint32(mask)).astype(np.float64) / mask


def _unpack_111011(packed: np.ndarray) -> np.ndarray:
    """11-10-11 bit x, y, z (x in the top bits) as [N, 3] in [0, 1]."""
    return np.stack([_unorm(packed, 21, 11), _unorm(packed, 11, 10), _unorm(packed, 0, 11)], 1)


def _unpack_8888(packed: np.ndarray) -> np.ndarray:
    """8-8-8-8 bit r, g, b, a (r in the top byte) as [N, 4] in [0, 1]."""
    return np.stack([_unorm(packed, s, 8) for s in (24, 16, 8, 0)], axis=1)


# For a largest-component index, the quaternion slots the three stored components go to.
_OTHER_SLOTS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def _unpack_rotation(packed: np.ndarray) -> np.ndarray:
    """Smallest-three quaternion: 2-bit index of the largest component (in rot_0..3 = w x y z
    order), then the other three in order, 10 bits each, scaled to [-1/sqrt2, 1/sqrt2]. The
    largest component is stored non-negative, so it is recovered as +sqrt(1 - sum of squares)."""
    comps = np.stack([_unorm(packed, s, 10) for s in (20, 10, 0)], axis=1)
    comps = (comps - 0.5) * math.sqrt(2.0)
    largest = (packed >> np.uint32(30)).astype(np.intp)
    q = np.empty((packed.shape[0], 4))
    np.put_along_axis(q, _OTHER_SLOTS[largest], comps, axis=1)
    q[np.arange(q.shape[0]), largest] = np.sqrt(np.maximum(0.0, 1.0 - (comps**2).sum(1)))
    return q


def _decode_sh_bytes(b: np.ndarray) -> np.ndarray:
    """uint8 -> f_rest in [-4, 4]. The SuperSplat/splat-transform writer stores
    trunc((f / 8 + 0.5) * 256) clamped to 0..255, so (like splat-transform's reader) we decode to
    the bucket centre, with 0 and 255 mapped to the range ends."""
    t = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b.astype(np.float64) + 0.5) / 256))
    return (t - 0.5) * 8.0


def _chunk_lerp(ch: plyfile.PlyElement, prefix: tuple[str, str], axes: tuple[str, ...],
                t: np.ndarray, which: np.ndarray) -> np.ndarray:
    """Per-Gaussian lerp between the chunk's `min_*` and `max_*` columns."""
    lo = np.stack([_column(ch, f"{prefix[0]}{a}") for a in axes], axis=1)[which]
    hi = np.stack([_column(ch, f"{prefix[1]}{a}") for a in axes], axis=1)[which]
    return lo * (1.0 - t) + hi * t


def _decode_compressed(path: Path, ply: plyfile.PlyData) -> Arrays:
    ch, v = ply["chunk"], ply["vertex"]
    _require(path, ch, CHUNK_REQUIRED)
    _require(path, v, PACKED)
    n = v.count
    if ch.count != math.ceil(n / CHUNK_SIZE):
        raise SceneFileError(
            f"{path}: wrong element counts: 'chunk' has {ch.count} rows but {n} vertices need "
            f"ceil({n}/{CHUNK_SIZE}) = {math.ceil(n / CHUNK_SIZE)}"
        )
    names = [el.name for el in ply.elements]
    if "sh" in names:
        sh_el = ply["sh"]
        if sh_el.count != n:
            raise SceneFileError(
                f"{path}: wrong element counts: 'sh' has {sh_el.count} rows, 'vertex' has {n}"
            )
        columns = [_decode_sh_bytes(np.asarray(sh_el[k])) for k in _f_rest_names(path, sh_el)]
        rest = np.stack(columns, axis=1) if columns else np.zeros((n, 0))
    else:
        rest = np.zeros((n, 0))

    packed = {k: np.asarray(v[k]).astype(np.uint32) for k in PACKED}
    which = np.arange(n) // CHUNK_SIZE
    xyz = ("x", "y", "z")
    means = _chunk_lerp(ch, ("min_", "max_"), xyz, _unpack_111011(packed["packed_position"]), which)
    log_scales = _chunk_lerp(ch, ("min_scale_", "max_scale_"), xyz,
                             _unpack_111011(packed["packed_scale"]), which)
    rgba = _unpack_8888(packed["packed_color"])
    has_colour_range = set(CHUNK_COLOUR) <= {p.name for p in ch.properties}
    # Older files have no per-chunk colour range: the bytes are then the colour itself.
    colour = (
        _chunk_lerp(ch, ("min_", "max_"), ("r", "g", "b"), rgba[:, :3], which)
        if has_colour_range
        else rgba[:, :3]
    )
    with np.errstate(over="ignore", invalid="ignore"):
        return dict(
            means=means,
            quats=_unpack_rotation(packed["packed_rotation"]),
            scales=np.exp(log_scales),
            # The alpha byte is the activated opacity (splat-transform's reader takes its logit
            # to get the INRIA value), not a logit itself.
            opacities=rgba[:, 3],
            sh=_sh_from_columns((colour - 0.5) / SH_C0, rest),
        )


# --- antimatter15 .splat -------------------------------------------------------------------


def _load_splat(path: Path, max_gaussians: int) -> Arrays:
    size_bytes = os.stat(path).st_size
    check_count(path, f".splat file of {size_bytes:,} bytes", size_bytes // SPLAT_RECORD.itemsize,
                max_gaussians)
    data = read_capped(path, path, "the scene file", max_gaussians * SPLAT_RECORD.itemsize,
                       "max_gaussians records of 32 bytes")
    if len(data) == 0:
        raise SceneFileError(f"{path}: empty .splat file")
    if len(data) % SPLAT_RECORD.itemsize:
        raise SceneFileError(
            f"{path}: .splat size {len(data)} bytes is not a multiple of 32 (bytes per "
            f"Gaussian): truncated or not a .splat file"
        )
    rec = np.frombuffer(data, dtype=SPLAT_RECORD)
    rgba = rec["rgba"].astype(np.float64) / 255.0
    return dict(
        means=rec["pos"],
        quats=(rec["rot"].astype(np.float64) - 128.0) / 128.0,  # antimatter15's encoding
        scales=rec["scale"],
        opacities=rgba[:, 3],
        sh=((rgba[:, :3] - 0.5) / SH_C0)[:, None, :],
    )


# --------------------------------------------------------------------------------------------
# Writing


def _inria_dtype(n_rest: int) -> np.dtype:
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(n_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return np.dtype([(name, "<f4") for name in names])


def save_ply(path: PathLike, g: Gaussians) -> None:
    """Write `g` as an INRIA float .ply (no normals), the exact inverse of the loader: logit
    opacity (clipped 1e-7 from 0 and 1 so no value is infinite), log scales, wxyz rotation,
    channel-major `f_rest`."""
    n, k = len(g), g.sh.shape[1]
    arr = np.empty(n, dtype=_inria_dtype(3 * (k - 1)))
    for i, name in enumerate("xyz"):
        arr[name] = g.means[:, i]
    for c in range(3):
        arr[f"f_dc_{c}"] = g.sh[:, 0, c]
    rest = g.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1))  # -> channel-major
    for i in range(rest.shape[1]):
        arr[f"f_rest_{i}"] = rest[:, i]
    op = np.clip(g.opacities.astype(np.float64), _OPACITY_EPS, 1.0 - _OPACITY_EPS)
    arr["opacity"] = np.log(op) - np.log1p(-op)
    log_s = np.log(g.scales.astype(np.float64))
    for i in range(3):
        arr[f"scale_{i}"] = log_s[:, i]
        arr[f"rot_{i}"] = g.quats[:, i]
    arr["rot_3"] = g.quats[:, 3]
    _write_ply(path, [plyfile.PlyElement.describe(arr, "vertex")])


def _write_ply(path: PathLike, elements: list[plyfile.PlyElement]) -> None:
    plyfile.PlyData(elements, text=False, byte_order="<").write(str(path))


def _to_unorm(t: np.ndarray, bits: int) -> np.ndarray:
    """[0, 1] float -> nearest `bits`-bit integer (as uint32)."""
    mask = (1 << bits) - 1
    return np.clip(np.rint(t * mask), 0, mask).astype(np.uint32)


def save_splat(path: PathLike, g: Gaussians) -> None:
    """Write `g` as an antimatter15 .splat (degree-0 colour only; higher SH bands are dropped).

    Quantisation: positions and scales are exact float32; colour (clamped to [0, 1]) and
    opacity are rounded to 1/255 (error <= 0.5/255); each quaternion component is rounded to
    1/128 (error <= 1/256 before the loader renormalises; +1.0 clips to 127/128).
    """
    rec = np.empty(len(g), dtype=SPLAT_RECORD)
    rec["pos"] = g.means
    rec["scale"] = g.scales
    colour = np.clip(g.base_colors().astype(np.float64), 0.0, 1.0)
    rec["rgba"][:, :3] = _to_unorm(colour, 8)
    rec["rgba"][:, 3] = _to_unorm(g.opacities.astype(np.float64), 8)
    rec["rot"] = np.clip(np.rint(g.quats.astype(np.float64) * 128.0 + 128.0), 0, 255)
    Path(path).write_bytes(rec.tobytes())


def _pack_111011(t: np.ndarray) -> np.ndarray:
    return (_to_unorm(t[:, 0], 11) << 21) | (_to_unorm(t[:, 1], 10) << 11) | _to_unorm(t[:, 2], 11)


def _pack_rotation(q: np.ndarray) -> np.ndarray:
    """Inverse of `_unpack_rotation`: q and -q are the same rotation, so flip the sign to make
    the largest component positive, then store the other three."""
    q = q.astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)
    q = q * np.where(q[np.arange(q.shape[0]), largest] < 0, -1.0, 1.0)[:, None]
    others = np.take_along_axis(q, _OTHER_SLOTS[largest], axis=1)
    t = others / math.sqrt(2.0) + 0.5
    out = largest.astype(np.uint32) << 30
    for j, shift in enumerate((20, 10, 0)):
        out |= _to_unorm(t[:, j], 10) << shift
    return out


def _chunk_ranges(x: np.ndarray, n_chunks: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-chunk min and max of x [N, C] (the last chunk may be partial)."""
    pad = n_chunks * CHUNK_SIZE - x.shape[0]
    # Repeat the last row to fill the final chunk: it changes neither its min nor its max.
    full = np.concatenate([x, np.repeat(x[-1:], pad, axis=0)]).reshape(n_chunks, CHUNK_SIZE, -1)
    return full.min(1), full.max(1)


def _normalise_in_chunk(x: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                        which: np.ndarray) -> np.ndarray:
    span = (hi - lo)[which]
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(span > 0, (x - lo[which]) / span, 0.0)
    return t


def save_compressed_ply(path: PathLike, g: Gaussians) -> None:
    """Write `g` as a PlayCanvas/SuperSplat compressed .ply (in the given order, no reordering).

    Quantisation: position and log-scale to 11/10/11 bits of the chunk's range, colour and
    opacity to 8 bits (colour of the chunk's range), rotation components to 10 bits of
    [-1/sqrt2, 1/sqrt2], f_rest to 8 bits of [-4, 4] (values outside are clipped).
    """
    n = len(g)
    n_chunks = math.ceil(n / CHUNK_SIZE)
    which = np.arange(n) // CHUNK_SIZE
    means = g.means.astype(np.float64)
    log_s = np.log(g.scales.astype(np.float64))
    colour = g.base_colors().astype(np.float64)
    pos_lo, pos_hi = _chunk_ranges(means, n_chunks) if n else (np.zeros((0, 3)),) * 2
    s_lo, s_hi = _chunk_ranges(log_s, n_chunks) if n else (np.zeros((0, 3)),) * 2
    c_lo, c_hi = _chunk_ranges(colour, n_chunks) if n else (np.zeros((0, 3)),) * 2

    chunk = np.empty(n_chunks, dtype=[(name, "<f4") for name in CHUNK_REQUIRED + CHUNK_COLOUR])
    for i, a in enumerate("xyz"):
        chunk[f"min_{a}"], chunk[f"max_{a}"] = pos_lo[:, i], pos_hi[:, i]
        chunk[f"min_scale_{a}"], chunk[f"max_scale_{a}"] = s_lo[:, i], s_hi[:, i]
    for i, a in enumerate("rgb"):
        chunk[f"min_{a}"], chunk[f"max_{a}"] = c_lo[:, i], c_hi[:, i]

    # Normalise against the float32 bounds actually stored, so decoding lerps the same numbers.
    def stored(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return lo.astype(np.float32).astype(np.float64), hi.astype(np.float32).astype(np.float64)

    t_pos = _normalise_in_chunk(means, *stored(pos_lo, pos_hi), which)
    t_s = _normalise_in_chunk(log_s, *stored(s_lo, s_hi), which)
    t_c = _normalise_in_chunk(colour, *stored(c_lo, c_hi), which)
    c8 = _to_unorm(t_c, 8)
    vertex = np.empty(n, dtype=[(name, "<u4") for name in PACKED])
    vertex["packed_position"] = _pack_111011(t_pos)
    vertex["packed_rotation"] = _pack_rotation(g.quats)
    vertex["packed_scale"] = _pack_111011(t_s)
    vertex["packed_color"] = (
        (c8[:, 0] << 24) | (c8[:, 1] << 16) | (c8[:, 2] << 8)
        | _to_unorm(g.opacities.astype(np.float64), 8)
    )
    elements = [
        plyfile.PlyElement.describe(chunk, "chunk"),
        plyfile.PlyElement.describe(vertex, "vertex"),
    ]
    if g.sh.shape[1] > 1:
        k_rest = 3 * (g.sh.shape[1] - 1)
        rest = g.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, k_rest).astype(np.float64)
        b = np.clip(np.trunc((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8)
        sh = np.empty(n, dtype=[(f"f_rest_{i}", "u1") for i in range(rest.shape[1])])
        for i in range(rest.shape[1]):
            sh[f"f_rest_{i}"] = b[:, i]
        elements.append(plyfile.PlyElement.describe(sh, "sh"))
    _write_ply(path, elements)


# --------------------------------------------------------------------------------------------
# Summary


def scene_summary(g: Gaussians) -> dict[str, Any]:
    """Counts and extents for `nhfd scene info`, as plain Python values (JSON-ready).

    Keys: count, sh_degree, bounds_min/bounds_max (of the means), robust_min/robust_max (1st and
    99th percentile per axis, so stray floaters do not set the framing), centre (per-axis
    median), extent (length of the robust diagonal), mean_opacity, median_scale (median of each
    Gaussian's largest scale). Geometric entries are None for an empty scene.
    """
    out: dict[str, Any] = {"count": len(g), "sh_degree": g.sh_degree}
    if len(g) == 0:
        keys = ("bounds_min", "bounds_max", "robust_min", "robust_max", "centre", "extent",
                "mean_opacity", "median_scale")
        return out | dict.fromkeys(keys)
    m = g.means.astype(np.float64)
    lo, hi = _robust_box(m)
    out |= {
        "bounds_min": m.min(0).tolist(),
        "bounds_max": m.max(0).tolist(),
        "robust_min": lo.tolist(),
        "robust_max": hi.tolist(),
        "centre": np.median(m, axis=0).tolist(),
        "extent": float(np.linalg.norm(hi - lo)),
        "mean_opacity": float(g.opacities.astype(np.float64).mean()),
        "median_scale": float(np.median(g.scales.max(1))),
    }
    return out
