"""Angular sampling per colour (docs/physics.md, "Light field sampling (per wavelength)").

Each colour has its own hogel window `W` (derived from the volume and its aperture cutoff, or
given), STFT bins `fx_k = k / (W p)` and slopes `tau_k = tan(asin(lambda fx_k))`; only bins inside
the aperture are rendered. With `shared=True` the windows come from
`nhfd.scene.lightfield.shared_windows` (W proportional to lambda, each at least its own minimum),
so the directions coincide within a few percent and one set of views serves all three.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from nhfd.optics import Aperture
from nhfd.scene.lightfield import directions, hogel_window, shared_windows

DEFAULT_APERTURE = Aperture()


@dataclass(frozen=True)
class ColourSampling:
    """One colour's angular sampling: `window` (W, even), `k` (int bins inside the aperture,
    ascending, the same set on both axes), `tau` (their slopes), `wavelength_m`, `cutoff_per_px`
    and `window_source` ("derived", "override" or "shared")."""

    wavelength_m: float
    window: int
    k: np.ndarray
    tau: np.ndarray
    cutoff_per_px: float
    window_source: str

    @property
    def n_views(self) -> int:
        """Views of the light field this colour uses: `len(k)` squared."""
        return len(self.k) ** 2


def colour_sampling(
    wavelengths_m: Sequence[float],
    pitch_m: float,
    volume_m: tuple[float, float],
    aperture: Aperture = DEFAULT_APERTURE,
    *,
    windows: Sequence[int | None] | None = None,
    shared: bool = False,
) -> list[ColourSampling]:
    """Per-colour `ColourSampling` for the volume `(z_min_m, z_max_m)` and the aperture.

    `windows[c]` overrides colour c's W (None: derive). With `shared` (and no override), the
    windows are `shared_windows(...)` (one cutoff for all colours required). Only the aperture's
    per-axis cutoff is used (exact for the square aperture; for circle/diamond, use
    `inside_aperture` to skip the corner views)."""
    z_abs_max = max(abs(float(volume_m[0])), abs(float(volume_m[1])))
    cutoffs = aperture.cutoffs(len(wavelengths_m))
    given = list(windows) if windows is not None else [None] * len(wavelengths_m)
    if len(given) != len(wavelengths_m):
        raise ValueError(f"windows has {len(given)} entries for {len(wavelengths_m)} colours")

    if shared and windows is None:
        if len(set(cutoffs)) != 1:
            raise ValueError(f"shared directions need one cutoff for every colour, got {cutoffs}")
        ws, _ = shared_windows(tuple(wavelengths_m), pitch_m, z_abs_max, cutoffs[0])
        given, source = list(ws), "shared"
    else:
        source = "override"
    out = []
    for c, lam in enumerate(wavelengths_m):
        if given[c] is not None:
            w, src = int(given[c]), source
        else:
            w, src = hogel_window(lam, pitch_m, z_abs_max, cutoffs[c]), "derived"
        k, tau = directions(w, lam, pitch_m, cutoffs[c])
        out.append(ColourSampling(float(lam), w, k, tau, float(cutoffs[c]), src))
    return out


def sampling_report(sampling: Sequence[ColourSampling]) -> list[dict]:
    """JSON-friendly per-colour summary: wavelength, W and its source, views, bins, max angle."""
    return [
        {
            "wavelength_nm": s.wavelength_m * 1e9,
            "window": s.window,
            "window_source": s.window_source,
            "k": [int(v) for v in s.k],
            "n_views": s.n_views,
            "max_angle_deg": float(np.degrees(np.arctan(np.abs(s.tau).max()))),
            "cutoff_per_px": s.cutoff_per_px,
        }
        for s in sampling
    ]


def inside_aperture(s: ColourSampling, aperture: Aperture, colour: int, n_colours: int = 3):
    """Bool `[Ky, Kx]`: which (iy, ix) views of `s` pass the aperture's 2-D shape (same
    conventions as `nhfd.optics.aperture_mask`)."""
    c = aperture.cutoffs(n_colours)[colour]
    f = s.k / s.window
    fy, fx = f[:, None], f[None, :]
    if aperture.shape == "square":
        m = (fx >= -c) & (fx < c) & (fy >= -c) & (fy < c)
    elif aperture.shape == "circle":
        m = fx**2 + fy**2 < c**2
    else:
        m = np.abs(fx) + np.abs(fy) < 2 * c
    return m
