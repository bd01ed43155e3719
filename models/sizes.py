"""The input sizes a model was checked at: checking more, recording them, and the refusal of a
frame window the model was not checked for.

The network is fully convolutional: trained on crops, it runs at any multiple of its stride
(`input_multiple`). A size counts as checked once the exported graph, run at that size, agrees
with a reference to `SIZE_TOLERANCE` (max abs difference over amplitude and phase):

- **against torch** (a run folder at hand: `nhfd export`, `nhfd model build`, `nhfd model
  check-sizes --run`): the same comparison as the export's (`compare_with_torch`, passed in), at
  that size;
- **ONNX only** (a shipped model has no run folder): the full-size inference against the same
  graph run on overlapping tiles of the training window's size, compared where each tile's
  output is out of reach of its own edges (a receptive margin measured on the graph). A
  convolutional network computes the same function at every size away from the borders, so any
  disagreement is the runtime or the graph going wrong at the large shape (as torch's FFT once did
  at one shape, `nhfd.optics.fft`), not the model's training. It also requires finite outputs of
  the input's shape.

Each result goes into the model's metadata as a `checked_sizes` entry
(`nhfd.models.metadata.checked_size_entry`), written atomically. The frame worker refuses a
window whose padded size is not among them (`window_check`) unless
`daemon.frames.allow_unchecked_sizes`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.config import OpticsSettings, SLMSettings
from nhfd.model_info import ModelInfo
from nhfd.models.inputs import seeded_input
from nhfd.models.metadata import (
    METADATA_KEY,
    SIZE_TOLERANCE,
    checked_size_entry,
    padded_hw,
    parse_metadata,
)

# The setting that lets the daemon serve a window its model was not checked at.
ALLOW_SETTING = "daemon.frames.allow_unchecked_sizes"
_SEED = 0

# (h, w) -> max abs difference from the reference at that input size
Compare = Callable[[tuple[int, int]], float]


class UncheckedSize(ValueError):
    """A frame window whose size the model was not checked at; the message names the size, the
    checked sizes and the setting that overrides it."""


def wxh(hw: Sequence[int]) -> str:
    return f"{int(hw[1])} x {int(hw[0])}"


def default_sizes_hw() -> list[tuple[int, int]]:
    """Sizes (h, w) every export is checked at besides its training window, as the product
    serves them: the default hologram window (nhfd.toml's [optics], 1024 x 576) and the default
    panel, whole ([slm], 1920 x 1080)."""
    optics, slm = OpticsSettings(), SLMSettings()
    return [(optics.hologram_height_px, optics.hologram_width_px), (slm.height_px, slm.width_px)]


def sizes_to_check(metadata: dict[str, Any], sizes_hw: Iterable[Sequence[int]] | None = None,
                   *, training: bool = True) -> list[tuple[int, int]]:
    """The training window (unless not `training`), then `sizes_hw` (default
    `default_sizes_hw`), each rounded up to the model's input multiple, without repeats."""
    m = int(metadata["input_multiple"])
    wanted = [*([metadata["train_size_hw"]] if training else []),
              *(default_sizes_hw() if sizes_hw is None else sizes_hw)]
    out: list[tuple[int, int]] = []
    for hw in wanted:
        p = padded_hw((int(hw[0]), int(hw[1])), m)
        if p not in out:
            out.append(p)
    return out


def read_metadata(path: str | Path) -> dict[str, Any]:
    import onnx  # the export's dependency; loads where a model file is rewritten

    model = onnx.load(str(path), load_external_data=False)
    return parse_metadata({p.key: p.value for p in model.metadata_props}, str(path))


def check_sizes(path: str | Path, sizes_hw: Sequence[tuple[int, int]],
                compare: Compare | None = None, margin_px: int | None = None
                ) -> list[dict[str, Any]]:  # fmt: skip
    """A `checked_sizes` entry per size (h, w, multiples of the input multiple): `compare(hw)`
    (the torch network) when given, else the ONNX-only tile check (`tile_check`, with
    `margin_px` in place of the measured receptive margin when given)."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    meta = parse_metadata(dict(session.get_modelmeta().custom_metadata_map), str(path))
    m = int(meta["input_multiple"])
    out = []
    for hw in sizes_hw:
        if padded_hw(hw, m) != tuple(hw):
            raise ValueError(f"size {wxh(hw)}: not a multiple of the model's input multiple {m}")
        if compare is not None:
            diff = float(compare(tuple(hw)))  # type: ignore[arg-type]
            out.append(checked_size_entry(hw, diff, "the torch network of its run"))
        else:
            diff, against = tile_check(session, meta, tuple(hw),  # type: ignore[arg-type]
                                       margin_px=margin_px)
            out.append(checked_size_entry(hw, diff, against))
    return out


def record_checked_sizes(path: str | Path, entries: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Write `entries` into the model's `checked_sizes` (replacing those of the same size),
    atomically (a temporary file renamed over the model); returns the new metadata."""
    import onnx

    path = Path(path)
    model = onnx.load(str(path))
    meta = parse_metadata({p.key: p.value for p in model.metadata_props}, str(path))
    new = {tuple(e["hw"]) for e in entries}
    kept = [e for e in meta.get("checked_sizes", []) if tuple(e["hw"]) not in new]
    meta["checked_sizes"] = sorted([*kept, *entries], key=lambda e: tuple(e["hw"]))
    for prop in model.metadata_props:
        if prop.key == METADATA_KEY:
            prop.value = json.dumps(meta)
    tmp = path.with_name(path.name + ".tmp")
    onnx.save(model, str(tmp))
    os.replace(tmp, path)
    return meta


def check_and_record(path: str | Path, sizes_hw: Sequence[tuple[int, int]],
                     compare: Compare | None = None, margin_px: int | None = None
                     ) -> dict[str, Any]:  # fmt: skip
    """`check_sizes`, then `record_checked_sizes`: the model's new metadata."""
    return record_checked_sizes(path, check_sizes(path, sizes_hw, compare, margin_px))


def recheck_derived(source: str | Path, derived: str | Path,
                    checked: Sequence[dict[str, Any]]) -> None:
    """A model derived from the float model `source` (int8, fp16) carries none of its size
    checks: `checked` (the float model's `checked_sizes` entries, taken out of the derived
    file's metadata) are checked again on the derived graph itself, its full run against tiles
    that leave the float model's receptive margin (`tile_check` says why: a rounded graph's far
    reach is the float graph's, rounded into whole steps)."""
    if checked:
        check_and_record(derived, [tuple(e["hw"]) for e in checked],
                         margin_px=measured_margin_px(source))


def measured_margin_px(path: str | Path) -> int:
    """The receptive margin of the model at `path`, measured at its training window."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    meta = parse_metadata(dict(session.get_modelmeta().custom_metadata_map), str(path))
    probe = tuple(max(int(a), 16 * int(meta["input_multiple"])) for a in meta["train_size_hw"])
    return receptive_margin_px(session, meta, padded_hw(probe, int(meta["input_multiple"])))


def _run(session: Any, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    amp, phase = session.run(["amplitude", "phase"], {session.get_inputs()[0].name: x})
    return amp, phase


def receptive_margin_px(session: Any, meta: dict[str, Any], probe_hw: tuple[int, int]) -> int:
    """How far (pixels, rounded up to the input multiple, plus one multiple for the stride's
    phase) an input pixel's change reaches in the outputs: measured by changing one pixel (at two
    phases of the stride) of a seeded input and finding the farthest output that moved at all.
    Not "moved by more than a small fraction": the float graph's far moves are tiny (1e-7 of the
    largest on the guitar's model, 107 px away against 73 px at 1e-5), but an int8 graph rounds
    them into whole quantisation steps (0.02-0.04 at tile edges inside the smaller margin)."""
    m = int(meta["input_multiple"])
    x = seeded_input(_channels(session), probe_hw, _SEED)
    base = _run(session, x)
    ph, pw = probe_hw
    cy, cx = ph // 2 - (ph // 2) % m, pw // 2 - (pw // 2) % m
    radius = 0
    for d in (0, m - 1):
        y, z = min(cy + d, ph - 1), min(cx + d, pw - 1)
        x2 = x.copy()
        v = x2[0, :, y, z]
        x2[0, :, y, z] = np.where(v < 0.5, v + 0.5, v - 0.5)
        moved = np.zeros(probe_hw)
        for a, b in zip(base, _run(session, x2), strict=True):
            moved = np.maximum(moved, np.abs(a - b).max(axis=(0, 1)))
        rows, cols = np.nonzero(moved > 0)
        radius = max(radius, int(np.abs(rows - y).max()), int(np.abs(cols - z).max()))
    return radius + (-radius) % m + m


def _channels(session: Any) -> int:
    return 3 + (session.get_inputs()[0].name == "rgbd")


def _tiles(n: int, t: int, margin: int) -> list[tuple[int, int, int]]:
    """Tile starts along one axis of length n (tile t, both multiples of the stride), each with
    the [lo, hi) it vouches for: its span less `margin` on sides that are not the image's edge
    (an image edge is zero-padded alike in the tile and the full run)."""
    if t >= n:
        return [(0, 0, n)]
    step = t - 2 * margin
    starts = [*range(0, n - t, step), n - t]
    return [(p, p if p == 0 else p + margin, p + t if p + t == n else p + t - margin)
            for p in starts]


# Input pixels per batched tile call: a few full-panel inputs' worth, so a batch's activations
# stay within a few hundred MB for the networks the project builds.
TILE_BATCH_PX = 1 << 22


def _tiles_per_call(session: Any, tile_hw: tuple[int, int]) -> int:
    """How many tiles of `tile_hw` go into one call: as many as `TILE_BATCH_PX` allows, within
    the graph's batch dimension (an export's dynamic batch allows up to 64; a graph whose batch
    is fixed takes one at a time)."""
    dim = session.get_inputs()[0].shape[0]
    limit = 64 if not isinstance(dim, int) else max(1, dim)
    return max(1, min(limit, TILE_BATCH_PX // (tile_hw[0] * tile_hw[1])))


def _round_up(n: int, m: int) -> int:
    return n + (-n) % m


def tile_check(session: Any, meta: dict[str, Any], hw: tuple[int, int],
               margin_px: int | None = None) -> tuple[float, str]:
    """The ONNX-only check at `hw`: max abs difference between the full-size inference of a
    seeded input and the same graph on overlapping tiles of it (inf for outputs that are not
    finite or not of the input's shape), and what it was checked against.

    `margin_px`: the receptive margin to leave at tile edges; measured on this graph when None.
    An int8 graph's own measurement falls short (a one-pixel change far away rounds to no
    change at all), so its check takes the margin of the float model it was quantised from."""
    m = int(meta["input_multiple"])
    h, w = hw
    x = seeded_input(_channels(session), hw, _SEED)
    full = _run(session, x)
    # A model of K subframes emits K frames' colours in each output (`nhfd model tune
    # --subframes`).
    colours = len(meta.get("wavelengths_m") or [0, 0, 0]) * int(meta.get("subframes") or 1)
    if any(o.shape != (1, colours, h, w) or not np.isfinite(o).all() for o in full):
        return float("inf"), (f"finite outputs of shape [1, {colours}, {h}, {w}]: "
                              f"found {[list(o.shape) for o in full]} or non-finite values")
    train = padded_hw(meta["train_size_hw"], m)
    probe = tuple(min(n, max(a, 16 * m)) for a, n in zip(train, hw, strict=True))
    margin = (receptive_margin_px(session, meta, probe)  # type: ignore[arg-type]
              if margin_px is None else int(margin_px))
    # Tiles of the training window's size, grown to an interior of at least twice the margin;
    # at the training window itself (or below), about halves of it. The check runs tile area over
    # interior area times the full image: with an interior of one stride step (tiles of 2 margins
    # + 2 strides) a small model's full panel was 81 times its area, 32,400 tiles, a minute a
    # check; with this interior, at most 4 times.
    t = tuple(min(n, max(a, _round_up(4 * margin + 2 * m, m)))
              for a, n in zip(train, hw, strict=True))
    if t == tuple(hw):
        half = (_round_up(n // 2 + margin + m, m) for n in hw)
        t = tuple(a if 2 * margin < a < n else n for a, n in zip(half, hw, strict=True))
    if t == tuple(hw):
        return 0.0, (f"finite outputs of shape [1, {colours}, {h}, {w}] only: the receptive "
                     f"margin {margin} px leaves no tile smaller than the size to compare with")
    worst = 0.0
    spans = [(r, c) for r in _tiles(h, t[0], margin) for c in _tiles(w, t[1], margin)]
    # The tiles run in batches (one call per batch, not per tile: a small model's full panel
    # is over a thousand tiles, and each call's overhead was most of the check's time).
    per_call = _tiles_per_call(session, t)
    for k in range(0, len(spans), per_call):
        batch = spans[k:k + per_call]
        tiles = _run(session, np.concatenate(
            [x[..., r0:r0 + t[0], c0:c0 + t[1]] for (r0, _, _), (c0, _, _) in batch]))
        for i, ((r0, rlo, rhi), (c0, clo, chi)) in enumerate(batch):
            for a, b in zip(full, tiles, strict=True):
                diff = np.abs(a[..., rlo:rhi, clo:chi] - b[i:i + 1, :, rlo - r0:rhi - r0,
                                                            clo - c0:chi - c0])
                worst = max(worst, float(diff.max()) if np.isfinite(diff).all() else np.inf)
    return worst, (f"the same graph on overlapping {wxh(t)} tiles of a seeded input, compared "
                   f"beyond a {margin} px receptive margin from the tiles' inner edges "
                   "(ONNX only: no run folder)")


def window_check(info: ModelInfo, window_hw: tuple[int, int], source: str, *,
                 allow: bool) -> str | None:
    """None when the frame window (h, w px; padded to the model's input multiple) is a size the
    model `info` was checked at (`ModelInfo.checked_sizes_hw`); otherwise the reason: raised as
    `UncheckedSize` unless `allow` (`daemon.frames.allow_unchecked_sizes`), then returned as a
    warning."""
    m = info.input_multiple
    run_hw = padded_hw(window_hw, m)
    sizes, recorded = info.checked_sizes_hw()
    if run_hw in sizes:
        return None
    padded = f" (run at {wxh(run_hw)}, padded to multiples of {m})" if run_hw != tuple(
        window_hw) else ""
    checked = ", ".join(wxh(s) for s in sizes) or "none"
    why = ("" if recorded else " (its metadata has no checked_sizes, an older export: only its "
           "training window counts as checked)")
    msg = (f"{source}: frame window {wxh(window_hw)}{padded} is not a size this model was "
           f"checked at; checked: {checked}{why}. Check it with `nhfd model check-sizes "
           f"{source} --sizes {window_hw[1]}x{window_hw[0]}`, or set [daemon.frames] "
           "allow_unchecked_sizes = true to serve it unchecked")
    if allow:
        return msg
    raise UncheckedSize(msg)


__all__ = [
    "ALLOW_SETTING",
    "SIZE_TOLERANCE",
    "UncheckedSize",
    "check_and_record",
    "check_sizes",
    "default_sizes_hw",
    "record_checked_sizes",
    "sizes_to_check",
    "tile_check",
    "window_check",
]
