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

from nhfd.optics.dpac import GREY_LEVELS

from .geometry import Geometry
from .patterns import GRATING_PERIOD_PX, GratingTile

LEVELS = GREY_LEVELS


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


# -- the source's amplitude profile and the zero order, from flat frames ------------------------

# Extra SLM pixels left out along the panel's edge for the flat fields (beyond the resampling's
# EDGE_MARGIN_PX): the aperture rings a flat panel's edge over several pixels.
FLAT_EDGE_PX = 6
# A fitted quantity counts as determined when it exceeds this many of its standard deviations.
DETERMINED_SIGMA = 5.0


@dataclass(frozen=True)
class SourceFit:
    """Per colour: the illumination's 1/e^2 intensity radius and centre (SLM-plane metres, x
    along columns, y along rows from the panel's centre) with one-sigma uncertainties, and the
    coherent unmodulated light: its intensity fraction of the light leaving the panel
    `f0 = e^2 / (1 + e^2)` (`e` = unmodulated / modulated amplitude: zero-order leakage and
    inter-pixel gap light together, which no far-field measurement separates) and its phase
    against grey 0's (radians, in the fitted sign's convention). `refused` names what the data
    could not determine (then that part is None)."""

    waist_m: tuple[float, float, float] | None
    waist_std_m: tuple[float, float, float] | None
    centre_m: tuple[tuple[float, float], ...] | None
    centre_std_m: tuple[tuple[float, float], ...] | None
    unmodulated_fraction: tuple[float, float, float] | None
    unmodulated_fraction_std: tuple[float, float, float] | None
    unmodulated_phase_rad: tuple[float, float, float] | None
    rms_log_residual: float
    refused: tuple[str, ...] = ()


def _profile_lsq(logs: list[np.ndarray], wts: list[np.ndarray], xs: list[np.ndarray],
                 ys: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted least squares of `ln I_i = c_i - k r^2 + bx x + by y` over images i (each on
    its own pixels) sharing (k, bx, by): (parameters [k, bx, by, c_0..], covariance, RMS
    weighted residual). Coordinates in mm (conditioning)."""
    n = len(logs)
    rows = []
    for i, (x, y) in enumerate(zip(xs, ys, strict=True)):
        a = np.zeros((len(x), 3 + n))
        a[:, 0], a[:, 1], a[:, 2], a[:, 3 + i] = -(x**2 + y**2), x, y, 1.0
        rows.append(a)
    a = np.concatenate(rows)
    b = np.concatenate(logs)
    sw = np.sqrt(np.concatenate(wts))
    aw = a * sw[:, None]
    sol, *_ = np.linalg.lstsq(aw, b * sw, rcond=None)
    res = (a @ sol - b) * sw
    sigma2 = float((res**2).sum()) / max(1, len(b) - len(sol))
    return sol, sigma2 * np.linalg.pinv(aw.T @ aw), math.sqrt(sigma2)


def fit_source(flats: dict[int, list[tuple[np.ndarray, np.ndarray]]],
               greys: dict[int, list[int]], tables_rad: tuple[tuple[float, ...], ...],
               sign: int, pitch_m: float) -> SourceFit:
    """The illumination's profile and the unmodulated light from flat frames at the SLM plane.

    `flats[c]` = per grey level: (image per unit exposure and power resampled on the SLM grid,
    valid mask) (see `nhfd.optics.camera_grid.to_slm_grid`); `greys[c]` the levels. A flat
    panel sends all its light into the zero order, so the image is the source intensity `S(x)`
    times a brightness `B(g) = P (1 + e^2 + 2 e cos(sign phi(g) + d))`: the modulated light
    interferes with the unmodulated (relative amplitude `e`, phase `-d`) as the level turns the
    phase.
    The profile is a Gaussian per colour (each laser has its own beam), fitted as a quadratic
    in log intensity, weighted by intensity (shot noise). Its uncertainty is the larger of the
    formal one and the scatter of the levels' separate fits. The brightness over the levels
    is linear in (a, b, d) = P (1 + e^2), 2 P e cos d, -2 P e sin d."""
    refused: list[str] = []
    waists, wstd, centres, cstd, fracs, fstd, phases = [], [], [], [], [], [], []
    rms_all = []
    for c in sorted(flats):
        logs, wts, xs, ys, per_level = [], [], [], [], []
        for img, ok in flats[c]:
            h, w = img.shape
            rows, cols = np.mgrid[0:h, 0:w]
            inner = ok & (rows >= FLAT_EDGE_PX) & (rows < h - FLAT_EDGE_PX) & \
                (cols >= FLAT_EDGE_PX) & (cols < w - FLAT_EDGE_PX)
            keep = inner & (img > 0.05 * np.percentile(img[inner], 99)) if inner.any() \
                else inner
            if keep.sum() < 100:
                raise ResponseError(f"colour {'RGB'[c]}: the flat frames show under 100 panel "
                                    "pixels: the source profile is undetermined")
            xs.append((cols[keep] - (w - 1) / 2) * pitch_m * 1e3)
            ys.append((rows[keep] - (h - 1) / 2) * pitch_m * 1e3)
            logs.append(np.log(img[keep]))
            wts.append(img[keep] / img[keep].mean())
            per_level.append(_profile_lsq(logs[-1:], wts[-1:], xs[-1:], ys[-1:])[0][:3])
        sol, cov, rms = _profile_lsq(logs, wts, xs, ys)
        rms_all.append(rms)
        k, bx, by = sol[:3]
        scatter = np.std(np.asarray(per_level), axis=0, ddof=1) / math.sqrt(len(per_level)) \
            if len(per_level) > 2 else np.zeros(3)
        std3 = np.maximum(np.sqrt(np.clip(np.diag(cov)[:3], 0, None)), scatter)
        if not k > DETERMINED_SIGMA * std3[0]:
            refused.append(f"colour {'RGB'[c]}: the source profile is flat over the panel "
                           f"within the noise (curvature {k:.3g} +- {std3[0]:.2g} /mm^2): its "
                           "waist and centre are undetermined (a larger panel area would "
                           "show them)")
            waists.append(math.nan)
            wstd.append(math.nan)
            centres.append((math.nan, math.nan))
            cstd.append((math.nan, math.nan))
        else:
            # ln I = c - k r^2 + ..., k = 2 / w^2 (w the 1/e^2 intensity radius); centre b/(2k).
            wmm = math.sqrt(2 / k)
            waists.append(wmm * 1e-3)
            wstd.append(0.5 * wmm * std3[0] / k * 1e-3)
            x0, y0 = bx / (2 * k), by / (2 * k)
            centres.append((x0 * 1e-3, y0 * 1e-3))
            cstd.append((math.hypot(std3[1] / (2 * k), x0 * std3[0] / k) * 1e-3,
                         math.hypot(std3[2] / (2 * k), y0 * std3[0] / k) * 1e-3))
        # Brightness per level: the fitted intercepts (log of the profile's value at x = 0).
        bright = np.exp(sol[3:])
        phi = sign * np.asarray([tables_rad[c][g] for g in greys[c]])
        if np.ptp(phi) < math.pi:
            refused.append(f"colour {'RGB'[c]}: the flat levels span {np.ptp(phi):.2f} rad "
                           "(< pi): the zero order is undetermined")
            fracs.append(math.nan)
            fstd.append(math.nan)
            phases.append(math.nan)
            continue
        a = np.stack([np.ones_like(phi), np.cos(phi), np.sin(phi)], 1)
        abd, *_ = np.linalg.lstsq(a, bright, rcond=None)
        res = a @ abd - bright
        s2 = float((res**2).sum()) / max(1, len(bright) - 3)
        cov_abd = s2 * np.linalg.inv(a.T @ a)

        def frac(v: np.ndarray) -> float:
            q = min(math.hypot(v[1], v[2]) / (2 * v[0]), 0.4999)
            e = (1 - math.sqrt(1 - 4 * q * q)) / (2 * q) if q > 0 else 0.0
            return e * e / (1 + e * e)

        f0 = frac(abd)
        grad = np.array([(frac(abd + d) - f0) / 1e-7 for d in np.eye(3) * 1e-7 *
                         max(1.0, float(abs(abd).max()))]) / max(1.0, float(abs(abd).max()))
        f_std = math.sqrt(max(float(grad @ cov_abd @ grad), 0.0))
        if not f0 > 2 * f_std:
            refused.append(f"colour {'RGB'[c]}: the unmodulated fraction {f0:.4f} +- "
                           f"{f_std:.4f} is not distinguished from zero")
        fracs.append(f0)
        fstd.append(f_std)
        phases.append(math.atan2(-abd[2], abd[1]))
    ok_src = all(math.isfinite(v) for v in waists)
    ok_zo = all(math.isfinite(v) for v in fracs)
    return SourceFit(
        waist_m=tuple(waists) if ok_src else None,  # type: ignore[arg-type]
        waist_std_m=tuple(wstd) if ok_src else None,  # type: ignore[arg-type]
        centre_m=tuple(centres) if ok_src else None,
        centre_std_m=tuple(cstd) if ok_src else None,
        unmodulated_fraction=tuple(fracs) if ok_zo else None,  # type: ignore[arg-type]
        unmodulated_fraction_std=tuple(fstd) if ok_zo else None,  # type: ignore[arg-type]
        unmodulated_phase_rad=tuple(phases) if ok_zo else None,  # type: ignore[arg-type]
        rms_log_residual=float(np.mean(rms_all)), refused=tuple(refused))
