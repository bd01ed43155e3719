"""Calibration holograms: what the capture shows and what the fit knows about it.

Two kinds of frame, both computed from a small `PatternSpec` so the fit can rebuild them exactly:

- **Dots**: a lattice of tiny points, each focused at one of a few depths `depths_m` (SLM space,
  positive toward the camera), with some lattice sites left empty at seeded random places so the
  layout has no rotation or mirror symmetry (the fit identifies every dot, even with part of the
  lattice out of view). The dots give the camera geometry (centroids do not move with defocus),
  the depth mapping (each dot is sharpest where its depth is imaged) and the phase sign (with the
  conjugate shown, a dot designed at +z focuses at -z: the near/far symmetry is broken).
- **Gratings**: tiles of binary stripes (period 8 px, half grey `ref`, half grey `test`). Only the
  +-1 orders pass the half-band aperture, so the intensity's component at twice the stripe
  frequency is `K sin^2((phi(test) - phi(ref)) / 2)` whatever the defocus, zero order or gap light
  (those are DC): pairs of grey levels measure the phase response.

Frames are uint8 `[H, W, 3]` (R, G, B patterns side by side in one frame; the capture lights one
laser at a time). Coding uses the *nominal* curves the capture was told (`PhaseCurve.linear` of
`strokes_rad`) and sign +1; the fit never assumes they are right.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from nhfd.optics import Aperture, PhaseCurve, double_phase, phase_to_grey, propagate

GRATING_PERIOD_PX = 8
# Reference grey levels of the grating pairs: several, so that every test level has a reference
# about a quarter-wave away somewhere (sin^2 is flat near its extremes).
GRATING_REFS = (0, 64, 128, 192)
GRATING_TESTS = tuple(range(8, 256, 16))
# Grey levels of the flat frames (the whole panel at one level): the light leaving a flat panel
# is all zero order, so at the SLM plane the camera sees the illumination itself, and its
# brightness against the level shows the unmodulated light's interference with the modulated.
FLAT_GREYS = tuple(range(0, 256, 32))


@dataclass(frozen=True)
class PatternSpec:
    """Everything the patterns depend on. Lengths are SLM-plane metres; colours R, G, B."""

    panel_hw: tuple[int, int]
    pitch_m: float
    wavelengths_m: tuple[float, float, float]
    strokes_rad: tuple[float, float, float] = (2 * math.pi,) * 3
    cutoff_per_px: tuple[float, float, float] = (0.25, 0.25, 0.25)
    aperture_shape: str = "square"
    dot_spacing_px: int = 16
    depths_m: tuple[float, ...] = (-1.5e-3, 0.0, 1.5e-3)
    missing_fraction: float = 0.2
    seed: int = 7
    tile_px: int = 32
    refs: tuple[int, ...] = GRATING_REFS
    tests: tuple[int, ...] = GRATING_TESTS

    def __post_init__(self) -> None:
        h, w = self.panel_hw
        if h < 64 or w < 64:
            raise ValueError(f"panel_hw = {self.panel_hw}: need at least 64 x 64 pixels")
        if not (0 < self.pitch_m < 1e-3):
            raise ValueError(f"pitch_m = {self.pitch_m}: must be in (0, 1e-3)")
        if self.dot_spacing_px < 8:
            raise ValueError(f"dot_spacing_px = {self.dot_spacing_px}: must be >= 8")
        if self.tile_px % GRATING_PERIOD_PX or self.tile_px < 2 * GRATING_PERIOD_PX:
            raise ValueError(f"tile_px = {self.tile_px}: must be a multiple of "
                             f"{GRATING_PERIOD_PX} and >= {2 * GRATING_PERIOD_PX}")
        if len(self.depths_m) < 2 or len(set(self.depths_m)) != len(self.depths_m):
            raise ValueError(f"depths_m = {self.depths_m}: need >= 2 distinct depths")
        if not 0 <= self.missing_fraction < 0.5:
            raise ValueError(f"missing_fraction = {self.missing_fraction}: must be in [0, 0.5)")

    def to_dict(self) -> dict[str, object]:
        """The spec as JSON-ready values (tuples as lists), as a capture's manifest stores it."""
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> PatternSpec:
        """The spec back from `to_dict`'s form (lists as tuples), checked again."""
        kw = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**kw)  # type: ignore[arg-type]


@dataclass(frozen=True)
class DotLayout:
    """The dots: SLM-plane positions `xy_m` [N, 2] (x along columns, y along rows, origin at the
    panel centre), lattice indices `ij` [N, 2] (column, row) and depth index per dot `group` [N]."""

    xy_m: np.ndarray
    ij: np.ndarray
    group: np.ndarray
    spacing_m: float
    shape_ij: tuple[int, int]  # lattice columns, rows (present or not)


def dot_layout(spec: PatternSpec) -> DotLayout:
    """The dot lattice of `spec`: every `dot_spacing_px` pixels, centred on the panel,
    `missing_fraction` of the dots left out at random (seeded by `spec.seed`) so the pattern is not
    periodic, and the depth groups interleaved so every part of the view holds all depths."""
    h, w = spec.panel_hw
    s = spec.dot_spacing_px
    nx, ny = (w - s) // s + 1, (h - s) // s + 1
    # Lattice centred on the panel.
    x0 = -(nx - 1) * s / 2
    y0 = -(ny - 1) * s / 2
    rng = np.random.default_rng(spec.seed)
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="xy")
    ij = np.stack([ii.reshape(-1), jj.reshape(-1)], axis=1)
    keep = rng.random(len(ij)) >= spec.missing_fraction
    ij = ij[keep]
    # Depth groups interleave along the lattice so that every part of the view holds all depths.
    group = (ij[:, 0] + 2 * ij[:, 1]) % len(spec.depths_m)
    xy_px = np.stack([x0 + ij[:, 0] * s, y0 + ij[:, 1] * s], axis=1)
    return DotLayout(xy_px * spec.pitch_m, ij, group, s * spec.pitch_m, (nx, ny))


def _aperture(spec: PatternSpec, colour: int) -> Aperture:
    return Aperture(spec.aperture_shape, (spec.cutoff_per_px[colour],))  # type: ignore[arg-type]


def dots_field(spec: PatternSpec, colour: int) -> torch.Tensor:
    """The wanted complex field on the SLM plane [1, H, W] (complex128) for one colour: each
    group's points, band-limited by the aperture, propagated back from their depth."""
    h, w = spec.panel_hw
    lay = dot_layout(spec)
    yy = (torch.arange(h, dtype=torch.float64) - (h - 1) / 2) * spec.pitch_m
    xx = (torch.arange(w, dtype=torch.float64) - (w - 1) / 2) * spec.pitch_m
    sigma = 0.6 * spec.pitch_m  # "tiny": no larger than the diffraction-limited spot
    total = torch.zeros(1, h, w, dtype=torch.complex128)
    lam = spec.wavelengths_m[colour]
    for g, z in enumerate(spec.depths_m):
        pts = lay.xy_m[lay.group == g]
        img = torch.zeros(h, w, dtype=torch.float64)
        for x, y in pts:
            img += torch.exp(-((xx[None, :] - x) ** 2 + (yy[:, None] - y) ** 2) / (2 * sigma**2))
        u = img[None].to(torch.complex128)
        total += propagate(u, -z, spec.pitch_m, [lam], aperture=_aperture(spec, colour),
                           padding="auto")
    return total


def dots_frame(spec: PatternSpec, curves: list[PhaseCurve] | None = None,
               phase_offset_rad: float = 0.0) -> np.ndarray:
    """The dot hologram for all three colours as uint8 [H, W, 3], coded through `curves` (the
    measured response; default the nominal linear curves) with `phase_offset_rad` added (pi
    negates the dots' field, so averaging the two cancels their interference with light the
    coding does not control: zero order, pixel gaps)."""
    out = []
    for c in range(3):
        u = dots_field(spec, c)
        scale = float(u.abs().max())
        coded = double_phase(u, scale, antialias=_aperture(spec, c), zero_below=1e-3)
        curve = curves[c] if curves is not None else PhaseCurve.linear(spec.strokes_rad[c])
        grey = phase_to_grey(coded.phase_rad + phase_offset_rad, [curve])
        out.append(grey[0].numpy())
    return np.ascontiguousarray(np.stack(out, axis=-1))


@dataclass(frozen=True)
class GratingTile:
    """One grating tile: top-left pixel (row, col), its size, and the two grey levels."""

    frame: int
    row: int
    col: int
    size: int
    ref: int
    test: int


def grating_tiles(spec: PatternSpec) -> list[GratingTile]:
    """All (ref, test) pairs spread over as many frames as needed, one tile each."""
    h, w = spec.panel_hw
    t = spec.tile_px
    # A margin of half a tile keeps tiles away from the panel edge (the edge diffracts).
    rows = range(t // 2, h - t - t // 2 + 1, t)
    cols = range(t // 2, w - t - t // 2 + 1, t)
    slots = [(r, c) for r in rows for c in cols]
    if not slots:
        raise ValueError(f"panel {spec.panel_hw} is too small for {t} px grating tiles")
    pairs = [(r, g) for r in spec.refs for g in spec.tests if r != g]
    tiles = []
    for k, (ref, test) in enumerate(pairs):
        frame, slot = divmod(k, len(slots))
        r, c = slots[slot]
        tiles.append(GratingTile(frame, r, c, t, ref, test))
    return tiles


def grating_frames(spec: PatternSpec) -> list[np.ndarray]:
    """Grating frames, uint8 [H, W, 3] (the same grey levels in every colour: the phase they
    show differs by colour, which is what is measured). Outside the tiles: a checkerboard of
    grey 0 / 128, which the aperture mostly blocks."""
    h, w = spec.panel_hw
    tiles = grating_tiles(spec)
    n = max(t.frame for t in tiles) + 1
    cols = np.arange(w)
    rows = np.arange(h)
    background = (((rows[:, None] + cols[None, :]) % 2) * 128).astype(np.uint8)
    frames = [background.copy() for _ in range(n)]
    for t in tiles:
        stripe = ((cols[t.col : t.col + t.size] - t.col) // (GRATING_PERIOD_PX // 2)) % 2
        block = np.where(stripe == 0, t.ref, t.test).astype(np.uint8)
        frames[t.frame][t.row : t.row + t.size, t.col : t.col + t.size] = block[None, :]
    return [np.ascontiguousarray(np.repeat(f[:, :, None], 3, axis=2)) for f in frames]


def flat_frames(spec: PatternSpec, greys: tuple[int, ...] = FLAT_GREYS
                ) -> list[tuple[int, np.ndarray]]:
    """(grey, frame) per level: the whole panel at that grey in every colour, uint8 [H, W, 3]."""
    return [(g, np.full((*spec.panel_hw, 3), g, np.uint8)) for g in greys]
