"""The phase response (grey -> phase per colour) and the per-colour intensity, from gratings.

A tile of stripes (period 8 px: 4 px at grey `ref`, 4 at grey `test`) diffracts into orders 0,
+-1, +-3, ...; the half-band aperture passes 0 and +-1 only. The intensity's component at twice
the stripe frequency is then `|A_1|^2 ~ K sin^2((phi(test) - phi(ref)) / 2)`, independent of
defocus and of everything that only adds to order 0 (zero-order leakage, the inter-pixel gap,
the source's slow envelope), so each tile measures one phase difference. `K` per colour is the
intensity (laser, sensor) times the modulated fill factor, the same for every tile.

The curve is fitted by gradient descent (L-BFGS, float64) in the form the daemon needs:
phase values at the measured grey levels, strictly increasing by construction (cumulative
softplus increments from phi(0) = 0), linearly interpolated to all 256 levels (the panel's
response is smooth on that scale). Several starting strokes are tried; the lowest loss wins.
Uncertainties: Gauss-Newton covariance `sigma^2 (J^T J)^-1` propagated to the 256-level table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .geometry import Geometry
from .patterns import GRATING_PERIOD_PX, GratingTile

LEVELS = 256


class ResponseError(ValueError):
    """The gratings do not determine the phase response; the message says why."""


def tile_harmonic(image: np.ndarray, tile: GratingTile, geo: Geometry, pitch_m: float,
                  panel_hw: tuple[int, int], margin_px: int = 4) -> float | None:
    """|second harmonic| of the intensity over a tile's interior, sampled back on the SLM grid
    through the camera geometry (bilinear); None when the tile is not fully in view."""
    h, w = panel_hw
    n = tile.size - 2 * margin_px
    rows = tile.row + margin_px + np.arange(n)
    cols = tile.col + margin_px + np.arange(n)
    # Two samples per SLM pixel: the intensity's harmonic has a 4 px period.
    sub = np.arange(2 * n) / 2
    rr, cc = np.meshgrid(rows[0] + sub, cols[0] + sub, indexing="ij")
    xy = np.stack([(cc - (w - 1) / 2) * pitch_m, (rr - (h - 1) / 2) * pitch_m], -1)
    cam = geo.to_camera(xy.reshape(-1, 2))
    ih, iw = image.shape
    if cam[:, 0].min() < 0 or cam[:, 1].min() < 0 or cam[:, 0].max() > iw - 1 or \
            cam[:, 1].max() > ih - 1:
        return None
    grid = torch.from_numpy(np.stack([cam[:, 0] / ((iw - 1) / 2) - 1,
                                      cam[:, 1] / ((ih - 1) / 2) - 1], -1)).float()
    vals = F.grid_sample(torch.from_numpy(image).float()[None, None], grid[None, None],
                         mode="bilinear", align_corners=True)[0, 0, 0].double().numpy()
    vals = vals.reshape(2 * n, 2 * n)
    phase = 2 * math.pi * 2 * (cc - tile.col) / GRATING_PERIOD_PX
    return float(np.abs((vals * np.exp(-1j * phase)).mean()))


@dataclass(frozen=True)
class ResponseFit:
    """Per colour: the 256-level table (radians, phi(0) = 0), its 1-sigma uncertainty (RMS over
    levels), the grating constant K (linear signal per second at full power) and fit residual."""

    tables_rad: tuple[tuple[float, ...], ...]
    table_std_rad: tuple[float, float, float]
    intensity: tuple[float, float, float]
    intensity_std: tuple[float, float, float]
    rms_residual: tuple[float, float, float]
    n_tiles: tuple[int, int, int]


class _Curve(torch.nn.Module):
    def __init__(self, knots: np.ndarray, stroke_rad: float, k0: float) -> None:
        super().__init__()
        self.knots = torch.tensor(knots, dtype=torch.float64)
        inc = np.diff(knots) / (LEVELS - 1) * stroke_rad
        self.raw = torch.nn.Parameter(torch.log(torch.expm1(torch.tensor(inc))))
        self.log_k = torch.nn.Parameter(torch.tensor(math.log(k0), dtype=torch.float64))
        self.floor = torch.nn.Parameter(torch.tensor(0.0, dtype=torch.float64))

    def values(self) -> torch.Tensor:
        """Phase at the knots, phi(knots[0] = 0) = 0."""
        return torch.cat([torch.zeros(1, dtype=torch.float64),
                          torch.cumsum(F.softplus(self.raw), 0)])

    def at(self, levels: torch.Tensor) -> torch.Tensor:
        """Linear interpolation (extrapolation past the last knot) at integer levels."""
        v = self.values()
        k = self.knots
        idx = torch.clamp(torch.searchsorted(k, levels.double(), right=True) - 1, 0, len(k) - 2)
        t = (levels.double() - k[idx]) / (k[idx + 1] - k[idx])
        return v[idx] + t * (v[idx + 1] - v[idx])

    def predict(self, ref: torch.Tensor, test: torch.Tensor) -> torch.Tensor:
        d = self.at(test) - self.at(ref)
        return torch.exp(self.log_k) * torch.sin(d / 2) ** 2 + self.floor


def fit_curve(ref: np.ndarray, test: np.ndarray, measured: np.ndarray, nominal_stroke: float
              ) -> tuple[np.ndarray, float, float, float, float]:
    """One colour: (table [256], table RMS std, K, K std, RMS residual relative to K)."""
    knots = np.unique(np.concatenate([[0], ref, test])).astype(np.float64)
    measured_levels = np.unique(np.concatenate([ref, test]))
    if len(measured) < len(measured_levels) + 3:
        raise ResponseError(f"{len(measured)} grating tiles for {len(measured_levels)} grey "
                            "levels: the phase response is undetermined")
    r = torch.tensor(ref, dtype=torch.float64)
    t = torch.tensor(test, dtype=torch.float64)
    m = torch.tensor(measured, dtype=torch.float64)
    best: tuple[float, _Curve] | None = None
    for factor in (0.6, 0.8, 1.0, 1.2, 1.4):
        model = _Curve(knots, nominal_stroke * factor, float(measured.max()))
        opt = torch.optim.LBFGS(model.parameters(), lr=1, max_iter=300,
                                line_search_fn="strong_wolfe", tolerance_grad=1e-12,
                                tolerance_change=1e-14)

        def closure(model: _Curve = model, opt: torch.optim.LBFGS = opt) -> torch.Tensor:
            opt.zero_grad()
            loss = ((model.predict(r, t) - m) ** 2).sum()
            loss.backward()
            return loss

        opt.step(closure)
        with torch.no_grad():
            loss = float(((model.predict(r, t) - m) ** 2).sum())
        if math.isfinite(loss) and (best is None or loss < best[0]):
            best = (loss, model)
    if best is None:
        raise ResponseError("the phase response fit diverged")
    loss, model = best
    params = [model.raw, model.log_k, model.floor]
    flat = torch.cat([p.detach().reshape(-1) for p in params])
    sizes = [p.numel() for p in params]

    def unpack(v: torch.Tensor) -> list[torch.Tensor]:
        return list(torch.split(v, sizes))

    def residual(v: torch.Tensor) -> torch.Tensor:
        raw, log_k, floor = unpack(v)
        vals = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(F.softplus(raw), 0)])
        k = model.knots

        def at(levels: torch.Tensor) -> torch.Tensor:
            idx = torch.clamp(torch.searchsorted(k, levels, right=True) - 1, 0, len(k) - 2)
            tt = (levels - k[idx]) / (k[idx + 1] - k[idx])
            return vals[idx] + tt * (vals[idx + 1] - vals[idx])

        return torch.exp(log_k[0]) * torch.sin((at(t) - at(r)) / 2) ** 2 + floor[0] - m

    def table(v: torch.Tensor) -> torch.Tensor:
        raw = unpack(v)[0]
        vals = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(F.softplus(raw), 0)])
        levels = torch.arange(LEVELS, dtype=torch.float64)
        k = model.knots
        idx = torch.clamp(torch.searchsorted(k, levels, right=True) - 1, 0, len(k) - 2)
        tt = (levels - k[idx]) / (k[idx + 1] - k[idx])
        return vals[idx] + tt * (vals[idx + 1] - vals[idx])

    jac = torch.autograd.functional.jacobian(residual, flat)
    dof = max(1, len(measured) - len(flat))
    sigma2 = loss / dof
    jtj = (jac.T @ jac).numpy()
    cond = np.linalg.cond(jtj)
    if not math.isfinite(cond) or cond > 1e14:
        raise ResponseError(f"the phase response is undetermined by the gratings (Gauss-Newton "
                            f"condition number {cond:.3g})")
    cov = sigma2 * np.linalg.inv(jtj)
    tj = torch.autograd.functional.jacobian(table, flat).numpy()
    table_var = np.einsum("ij,jk,ik->i", tj, cov, tj)
    k_val = float(torch.exp(model.log_k.detach()))
    k_std = k_val * math.sqrt(max(cov[len(flat) - 2, len(flat) - 2], 0.0))
    tab = table(flat).detach().numpy()
    return (tab, float(np.sqrt(np.clip(table_var, 0, None).mean())), k_val, k_std,
            math.sqrt(loss / len(measured)) / k_val)
