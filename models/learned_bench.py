"""The learned bench: what the parametric bench model leaves out, learned from captures
(docs/learned_bench.md), and its one trusted file format.

`LearnedBench` wraps the parametric model that `nhfd.pipeline.refine.BenchForward` evaluates
(the physics prior) at three places, each starting as the identity:

- at the SLM plane, per colour, a small CNN on the shown phase (its cosine and sine, so a 2 pi
  wrap changes nothing) gives a residual phase and a log-amplitude: the pixels' crosstalk and
  fill, a spatially varying response;
- a learned complex field for the unmodulated light, added to the modulated field before the
  illumination: a constant per colour and a coarse map over the panel (`UNMODULATED_GRID`
  samples per axis, in panel coordinates, so one file serves any window on the panel);
- at the target planes, per colour and shared over the planes, a small CNN on the intensity
  (relative to the image's mean, so the camera's exposure stays free): the camera's pixels and
  response.

The weights live in a safetensors file, the only format read: no pickle. `load_learned` checks
the bytes before anything is built from them (see its docstring) and raises
`LearnedWeightsError` (a ValueError) naming the file and the problem.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from safetensors import SafetensorError
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save
from torch import nn

from nhfd.calibration import Calibration, parametric_fingerprint

FORMAT = "nhfd-learned-bench"
FORMAT_VERSION = 1
# Hidden channels of each colour's two small CNNs, and samples per axis of the coarse
# unmodulated-light map over the panel.
HIDDEN_CHANNELS = 8
UNMODULATED_GRID = 8
# Bounds on a file before any of it is trusted: the whole file, its JSON header, one tensor.
# The default model is about 9 KiB; a bigger `hidden` stays far below these.
MAX_FILE_BYTES = 16 * 2**20
MAX_HEADER_BYTES = 64 * 2**10
MAX_TENSOR_BYTES = 4 * 2**20
# Allowed architecture sizes (metadata `hidden_channels`, `unmodulated_grid`).
HIDDEN_RANGE = (1, 64)
GRID_RANGE = (1, 64)
# The optics the weights were learned for against the bench's (as the calibration's
# `check_bench`): wavelength 0.5 %, pitch 0.1 %; the panel exactly.
WAVELENGTH_REL_TOL = 5e-3
PITCH_REL_TOL = 1e-3
# A pickle's first bytes (protocol 2-5) and a torch.save zip's.
_PICKLE_PROTOCOLS = (2, 3, 4, 5)
_ZIP_MAGIC = b"PK\x03\x04"

log = logging.getLogger("nhfd.models.learned_bench")


class LearnedWeightsError(ValueError):
    """A learned bench's weights file is refused: missing, truncated, not safetensors (a pickle),
    oversized, of other names, shapes or dtypes, non-finite, or learned for other optics."""


@dataclass(frozen=True)
class LearnedOptics:
    """The optics a learned bench belongs to: wavelengths (m, R, G, B), SLM pitch (m) and the
    panel (rows, columns)."""

    wavelengths_m: tuple[float, float, float]
    pitch_m: float
    panel_hw: tuple[int, int]

    def __post_init__(self) -> None:
        if len(self.wavelengths_m) != 3 or not all(
                math.isfinite(w) and 0 < w < 1e-5 for w in self.wavelengths_m):
            raise ValueError(f"wavelengths_m = {self.wavelengths_m!r}: need 3 values in "
                             "(0, 1e-5) m")
        if not (math.isfinite(self.pitch_m) and 0 < self.pitch_m < 1e-3):
            raise ValueError(f"pitch_m = {self.pitch_m!r}: must be in (0, 1e-3) m")
        if len(self.panel_hw) != 2 or not all(isinstance(n, int) and 1 <= n <= 16384
                                              for n in self.panel_hw):
            raise ValueError(f"panel_hw = {self.panel_hw!r}: need 2 integers in [1, 16384]")


def _cnn(in_ch: int, hidden: int, out_ch: int) -> nn.Sequential:
    """conv 3x3 -> SiLU -> conv 3x3, the last layer zero: the identity's residual at the start."""
    net = nn.Sequential(nn.Conv2d(in_ch, hidden, 3, padding=1), nn.SiLU(),
                        nn.Conv2d(hidden, out_ch, 3, padding=1))
    nn.init.zeros_(net[2].weight)
    nn.init.zeros_(net[2].bias)
    return net


class LearnedBench(nn.Module):
    """The three learned parts around the parametric bench (module docstring), for `optics`.
    Applied by `BenchForward` colour by colour: `slm_field` replaces the unit-amplitude field
    of the shown phase, `intensity` follows the window's intensity at every plane."""

    def __init__(self, optics: LearnedOptics, *, hidden_channels: int = HIDDEN_CHANNELS,
                 unmodulated_grid: int = UNMODULATED_GRID) -> None:
        super().__init__()
        for name, v, (lo, hi) in (("hidden_channels", hidden_channels, HIDDEN_RANGE),
                                  ("unmodulated_grid", unmodulated_grid, GRID_RANGE)):
            if not (isinstance(v, int) and lo <= v <= hi):
                raise ValueError(f"{name} = {v!r}: must be an integer in [{lo}, {hi}]")
        self.optics = optics
        self.hidden_channels = hidden_channels
        self.unmodulated_grid = unmodulated_grid
        self.slm = nn.ModuleList(_cnn(2, hidden_channels, 2) for _ in range(3))
        self.target = nn.ModuleList(_cnn(1, hidden_channels, 1) for _ in range(3))
        # Unmodulated light relative to the modulated field's amplitude: (re, im) per colour,
        # and its coarse map over the panel.
        self.unmodulated = nn.Parameter(torch.zeros(3, 2))
        self.unmodulated_map = nn.Parameter(
            torch.zeros(3, 2, unmodulated_grid, unmodulated_grid))

    def slm_field(self, phase: torch.Tensor, colour: int,
                  box: tuple[int, int, int, int]) -> torch.Tensor:
        """The field leaving the panel `[K, Hr, Wr]` complex64 for the shown phase `[K, Hr, Wr]`
        (rad) of `colour` on the region `box` = (top, left, height, width) of the panel: the
        phase and amplitude residuals of the SLM-plane CNN, plus the unmodulated light (before
        the illumination, as in the panel)."""
        x = torch.stack([torch.cos(phase), torch.sin(phase)], dim=1)  # [K, 2, Hr, Wr]
        d = self.slm[colour](x)
        u = torch.polar(torch.exp(d[:, 1]), phase + d[:, 0])
        return u + self.unmodulated_on(colour, box)[None]

    def unmodulated_on(self, colour: int, box: tuple[int, int, int, int]) -> torch.Tensor:
        """The unmodulated field `[Hr, Wr]` complex64 on the region `box` of the panel: the
        colour's constant and its coarse map, sampled bilinearly in panel coordinates."""
        top, left, h, w = box
        ph, pw = self.optics.panel_hw
        dev = self.unmodulated.device
        ys = (torch.arange(h, device=dev, dtype=torch.float32) + top + 0.5) / ph * 2 - 1
        xs = (torch.arange(w, device=dev, dtype=torch.float32) + left + 0.5) / pw * 2 - 1
        grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)[None]  # [1, h, w, 2]
        m = F.grid_sample(self.unmodulated_map[colour][None], grid, mode="bilinear",
                          padding_mode="border", align_corners=False)[0]  # [2, h, w]
        c = self.unmodulated[colour]
        return torch.complex(m[0] + c[0], m[1] + c[1])

    def intensity(self, image: torch.Tensor, colour: int) -> torch.Tensor:
        """The camera's intensity `[..., h, w]` of the model's `image` `[..., h, w]` (any leading
        dims: subframes, planes), the target-plane CNN's residual in units of each image's mean
        (its exposure stays free), shared over the planes."""
        lead = image.shape[:-2]
        x = image.reshape(-1, 1, *image.shape[-2:])
        scale = x.detach().mean(dim=(-2, -1), keepdim=True).clamp(min=1e-12)
        out = x + scale * self.target[colour](x / scale)
        return out.reshape(*lead, *image.shape[-2:])

    # -- the file ------------------------------------------------------------------------------

    def metadata(self, extra: dict[str, Any] | None = None) -> dict[str, str]:
        """The safetensors metadata (strings): format, version, the optics, the architecture and
        `extra` (JSON values: what it was learned on, its held-out scores)."""
        meta = {"format": FORMAT, "version": str(FORMAT_VERSION),
                "wavelengths_m": json.dumps(list(self.optics.wavelengths_m)),
                "pitch_m": json.dumps(self.optics.pitch_m),
                "panel_hw": json.dumps(list(self.optics.panel_hw)),
                "hidden_channels": str(self.hidden_channels),
                "unmodulated_grid": str(self.unmodulated_grid)}
        for k, v in (extra or {}).items():
            if k in meta:
                raise ValueError(f"metadata key {k!r}: reserved")
            meta[k] = json.dumps(v)
        return meta


def save_learned(model: LearnedBench, path: Path | str, extra: dict[str, Any] | None = None
                 ) -> str:
    """Write `model`'s weights to `path` (safetensors, float32) atomically (a temporary file,
    then a rename); returns the file's SHA-256 (hex), which the calibration records."""
    path = Path(path)
    state = {k: v.detach().to("cpu", torch.float32).contiguous()
             for k, v in model.state_dict().items()}
    for k, v in state.items():
        if not bool(torch.isfinite(v).all()):
            raise ValueError(f"learned bench weight {k}: not finite, not written")
    data = st_save(state, metadata=model.metadata(extra))
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)
    return hashlib.sha256(data).hexdigest()


def _refuse(path: Path, problem: str) -> LearnedWeightsError:
    return LearnedWeightsError(f"learned bench weights {path}: {problem}")


def _header(path: Path, data: bytes) -> tuple[dict[str, Any], int]:
    """The JSON header of safetensors bytes and where the tensors' bytes start, refusing what
    is not safetensors, a header over MAX_HEADER_BYTES and a truncated file."""
    # A safetensors header length's low byte may be 0x80 too; its JSON then starts at byte 8.
    json_at_8 = len(data) > 8 and data[8:9] == b"{"
    if len(data) >= 2 and data[0] == 0x80 and data[1] in _PICKLE_PROTOCOLS and not json_at_8:
        raise _refuse(path, "a pickle, not safetensors (refused, never unpickled)")
    if data[:4] == _ZIP_MAGIC:
        raise _refuse(path, "a zip archive (torch.save), not safetensors (refused, never "
                            "unpickled)")
    if len(data) < 8:
        raise _refuse(path, f"truncated: {len(data)} bytes, less than the 8-byte header length")
    (n,) = struct.unpack("<Q", data[:8])
    if n > MAX_HEADER_BYTES:
        raise _refuse(path, f"the header declares {n} bytes, more than the cap of "
                            f"{MAX_HEADER_BYTES} (not safetensors, or hostile)")
    if 8 + n > len(data):
        raise _refuse(path, f"truncated: the header declares {n} bytes, the file holds "
                            f"{len(data) - 8} after its length")
    try:
        header = json.loads(data[8 : 8 + n])
    except (UnicodeDecodeError, ValueError):
        raise _refuse(path, "not safetensors: its header is not JSON") from None
    if not isinstance(header, dict):
        raise _refuse(path, "not safetensors: its header is not a JSON object")
    return header, 8 + n


def _check_entries(path: Path, header: dict[str, Any], body_bytes: int,
                   expected: dict[str, tuple[int, ...]]) -> None:
    """Every tensor's dtype, shape, byte range (inside the file, under MAX_TENSOR_BYTES) and
    the names against `expected`."""
    entries = {k: v for k, v in header.items() if k != "__metadata__"}
    for name, e in entries.items():
        if not isinstance(e, dict) or not isinstance(e.get("shape"), list) or \
                not all(isinstance(d, int) and d >= 0 for d in e["shape"]):
            raise _refuse(path, f"tensor {name}: malformed entry {e!r}")
        if e.get("dtype") != "F32":
            raise _refuse(path, f"tensor {name}: dtype {e.get('dtype')!r}, expected 'F32'")
        nbytes = 4 * math.prod(e["shape"])
        off = e.get("data_offsets")
        if not (isinstance(off, list) and len(off) == 2 and all(isinstance(o, int) for o in off)
                and 0 <= off[0] <= off[1]):
            raise _refuse(path, f"tensor {name}: malformed data_offsets {off!r}")
        if nbytes > MAX_TENSOR_BYTES:
            raise _refuse(path, f"tensor {name}: declares {nbytes} bytes (shape {e['shape']}), "
                                f"more than the cap of {MAX_TENSOR_BYTES}")
        if off[1] > body_bytes:
            raise _refuse(path, f"tensor {name}: declares bytes {off[0]}..{off[1]}, larger than "
                                f"the file's {body_bytes} bytes of tensors (truncated?)")
        if off[1] - off[0] != nbytes:
            raise _refuse(path, f"tensor {name}: {off[1] - off[0]} bytes for shape "
                                f"{e['shape']} of F32 ({nbytes})")
    missing = sorted(expected.keys() - entries.keys())
    unexpected = sorted(entries.keys() - expected.keys())
    if missing or unexpected:
        raise _refuse(path, f"tensor names differ from the model's: missing {missing}, "
                            f"unexpected {unexpected}")
    for name, shape in expected.items():
        if tuple(entries[name]["shape"]) != shape:
            raise _refuse(path, f"tensor {name}: shape {entries[name]['shape']}, expected "
                                f"{list(shape)}")


def _meta_value(path: Path, meta: dict[str, str], key: str) -> Any:
    try:
        return json.loads(meta[key])
    except KeyError:
        raise _refuse(path, f"metadata has no {key!r}") from None
    except ValueError:
        raise _refuse(path, f"metadata {key} = {meta[key]!r}: not JSON") from None


def _check_optics(path: Path, meta: dict[str, str], optics: LearnedOptics) -> None:
    """Refuse weights learned for other wavelengths, pitch or panel than `optics`."""
    wl = _meta_value(path, meta, "wavelengths_m")
    pitch = _meta_value(path, meta, "pitch_m")
    panel = _meta_value(path, meta, "panel_hw")
    if not (isinstance(wl, list) and len(wl) == 3 and all(isinstance(v, float | int) for v in wl)):
        raise _refuse(path, f"metadata wavelengths_m = {wl!r}: need 3 numbers (m)")
    for c, (got, want) in enumerate(zip(wl, optics.wavelengths_m, strict=True)):
        if not abs(got - want) <= WAVELENGTH_REL_TOL * want:
            raise _refuse(path, f"learned for other optics: wavelengths_m[{c}] = {got:.6g} m, "
                                f"this bench's {want:.6g} m (within {WAVELENGTH_REL_TOL:.1%})")
    if not (isinstance(pitch, float | int) and abs(pitch - optics.pitch_m)
            <= PITCH_REL_TOL * optics.pitch_m):
        raise _refuse(path, f"learned for other optics: pitch_m = {pitch!r} m, this bench's "
                            f"{optics.pitch_m:.6g} m (within {PITCH_REL_TOL:.1%})")
    if panel != list(optics.panel_hw):
        raise _refuse(path, f"learned for other optics: panel_hw = {panel!r}, this bench's "
                            f"{list(optics.panel_hw)}")


def load_learned(path: Path | str, optics: LearnedOptics, *, sha256: str = "",
                 parametric_sha256: str = "", device: torch.device | str = "cpu"
                 ) -> LearnedBench:
    """The learned bench in the safetensors file `path`, for a bench of `optics`, checked before
    it is trusted, each refusal a `LearnedWeightsError` naming the file and the problem:

    - the file missing, over MAX_FILE_BYTES, or with another SHA-256 than `sha256` (the
      calibration's record; "" = not checked);
    - a pickle or a torch.save zip named .safetensors (never unpickled), or a header that is
      not JSON;
    - a header declaring more than MAX_HEADER_BYTES, a tensor over MAX_TENSOR_BYTES or beyond
      the file's end (truncated);
    - another format or version, architecture sizes out of range;
    - weights for other optics (wavelengths, pitch, panel), or learned on top of another
      parametric fit than `parametric_sha256` (its `parametric_fingerprint`; "" = not checked);
    - tensor names, shapes or dtypes (float32 only) other than the model's;
    - a NaN or infinite weight.

    In evaluation mode, its parameters frozen, on `device`."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError:
        raise _refuse(path, "not found") from None
    if size > MAX_FILE_BYTES:
        raise _refuse(path, f"{size} bytes, more than the cap of {MAX_FILE_BYTES}")
    data = path.read_bytes()
    if sha256 and hashlib.sha256(data).hexdigest() != sha256:
        raise _refuse(path, f"SHA-256 {hashlib.sha256(data).hexdigest()[:12]}..., the "
                            f"calibration records {sha256[:12]}...: another file")
    header, start = _header(path, data)
    meta = header.get("__metadata__") or {}
    if not isinstance(meta, dict) or not all(isinstance(v, str) for v in meta.values()):
        raise _refuse(path, "metadata: not a map of strings")
    if meta.get("format") != FORMAT or meta.get("version") != str(FORMAT_VERSION):
        raise _refuse(path, f"format {meta.get('format')!r} version {meta.get('version')!r}: "
                            f"this nhfd reads {FORMAT!r} version {FORMAT_VERSION}")
    _check_optics(path, meta, optics)
    if parametric_sha256:
        on = _meta_value(path, meta, "parametric_sha256")
        if on != parametric_sha256:
            raise _refuse(path, f"learned on top of another calibration (parametric fit "
                                f"{str(on)[:12]}..., this one's {parametric_sha256[:12]}...)")
    sizes = {}
    for key, (lo, hi) in (("hidden_channels", HIDDEN_RANGE),
                          ("unmodulated_grid", GRID_RANGE)):
        v = _meta_value(path, meta, key)
        if not (isinstance(v, int) and lo <= v <= hi):
            raise _refuse(path, f"metadata {key} = {v!r}: must be an integer in [{lo}, {hi}]")
        sizes[key] = v
    model = LearnedBench(optics, **sizes)
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    _check_entries(path, header, len(data) - start, expected)
    try:
        tensors = st_load(data)
    except SafetensorError as exc:
        raise _refuse(path, f"not readable as safetensors ({exc})") from None
    for name, t in tensors.items():
        if not bool(torch.isfinite(t).all()):
            raise _refuse(path, f"tensor {name}: {int((~torch.isfinite(t)).sum())} NaN or "
                                "infinite values")
    model.load_state_dict(tensors, strict=True)
    model.requires_grad_(False)
    return model.eval().to(device)


def learned_of(cal: Calibration | None, optics: LearnedOptics, *,
               device: torch.device | str = "cpu") -> tuple[LearnedBench | None, str | None]:
    """The learned bench a calibration references, for a bench of `optics`: (the model, None);
    (None, None) when it references none; (None, why) when its file is refused (logged): the
    parametric model stays in use."""
    path = cal.learned_path() if cal is not None else None
    if cal is None or path is None:
        return None, None
    try:
        return load_learned(path, optics, sha256=cal.learned_sha256,
                            parametric_sha256=parametric_fingerprint(cal), device=device), None
    except LearnedWeightsError as exc:
        why = f"{exc}; the parametric bench model stays in use"
        log.warning("%s", why)
        return None, why


__all__ = ["FORMAT", "FORMAT_VERSION", "LearnedBench", "LearnedOptics", "LearnedWeightsError",
           "learned_of", "load_learned", "save_learned"]
