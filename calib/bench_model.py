"""The differentiable bench model, and the depth mapping fitted through it.

The model is the nominal bench: a grey frame goes through the fitted grey->phase table and the
fitted sign to the SLM's phase (each pixel a flat square: `pixel_transfer`), the relay's Fourier
aperture and the angular spectrum method (`nhfd.optics.propagate`, never re-implemented) carry
it to depth `z`. The comparison happens at the SLM pixel centres: each captured image is
resampled there once through the fitted camera geometry (`to_slm_grid`, kornia's `warp_affine`;
the camera samples the SLM plane two to three times finer than its pixels, so this loses little;
the camera pixels' area, a blur of a third of an SLM pixel, is left out), which saves mapping
every rendered image onto the sensor. What the model leaves out (fill factor, gap light, zero
order, illumination envelope) reaches the camera, after the dot/negated-dot pair average of the
fine sweep, as an additive smooth background and a common factor: each colour gets a gain and a
background level. Both frames of the pair are rendered and averaged, as captured.

Why a model fit for the depths: a dot's focus curve, sampled every half depth of field or so, is
neither symmetric nor alone (neighbouring dots' defocused light and the coding haze interfere
with it), so peak-finding on it is biased by about a tenth of the depth of field. The model
contains all of that interference, so fitting whole images removes most of the bias (measured on
randomised twins: from 8-14% of the depth of field to about 2%).

The depth mapping is `z = ((stage - s0) * scale + offset[colour]) * 1e-3` (metres, SLM space;
s0 and stage in mm, offsets in mm here, offset[G] = 0). Fitted by Levenberg-Marquardt (a damped
Gauss-Newton descent) on the sum of squared residuals over every fine-sweep image, with the
image's derivative in `z` taken by a forward difference of the propagation (the model is smooth
in z on the scale of the depth of field, hundreds of times the step). The relay's aberrations
(`fit_aberration`) are fitted through the same model by `scipy.optimize.least_squares`. Both
report one-sigma uncertainties from the residuals' Jacobian (`ModelDepthFit` and `AberrationFit`
say how).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import OptimizeResult, least_squares

from nhfd.optics import Aperture, PhaseCurve, grey_to_phase, propagate
from nhfd.optics.pupil import FIRST_NOLL, N_ZERNIKE, apply_pupil

from .focus import STAGE_M_PER_MM, FocusError

# Forward-difference step for d(image)/dz (SLM metres): far below the depth of field (~1 mm)
# and far above float32 noise in the propagated intensity.
DZ_M = 5e-6
# The descent stops when no image's depth moves by more than this (SLM metres): a thousandth of
# the depth of field, far below the 5% the calibration must reach.
Z_TOL_M = 1e-6


def pixel_transfer(hw: tuple[int, int]) -> torch.Tensor:
    """Spectrum factor [H, W] of a flat square pixel (width = pitch) on the fftfreq grid.

    Within the aperture's band (|f| < 1/(2 pitch)) the continuous field leaving a panel of flat
    pixels has the spectrum `sinc(fx p) sinc(fy p)` times that of the pixel values, so the
    samples that propagate from pixel values filtered by this are the exact band-limited field at
    the pixel centres: no oversampled grid is needed."""
    fy = torch.fft.fftfreq(hw[0], dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(hw[1], dtype=torch.float64)[None, :]
    return torch.sinc(fx) * torch.sinc(fy)


# Forward-difference step of the images' derivative in a Zernike coefficient (radians): small
# against the 0.1 rad the fit must reach, large against float32 noise.
DA_RAD = 0.02
# Starting points of the aberration fit's astigmatism (j = 5, 6; radians at the reference
# wavelength): a relay's astigmatism reaches the better part of a radian.
ASTIG_GRID_RAD = (-0.6, -0.3, 0.0, 0.3, 0.6)


class BenchModel:
    """What the camera sees of a grey frame at depth z, for one colour, sampled at the SLM
    pixel centres (the captured images are resampled there once, with `to_slm_grid`).

    Optional, once fitted (`nhfd.calib.response.fit_source`): the source's amplitude profile
    `source_amplitude` [H, W] and the unmodulated light `unmodulated` (complex amplitude
    relative to the modulated light's); and the relay's aberrations (`set_aberration`)."""

    def __init__(self, frames: list[np.ndarray], colour: int, curve: PhaseCurve, sign: int,
                 pitch_m: float, wavelength_m: float, cutoff_per_px: float,
                 aperture_shape: str, *, source_amplitude: np.ndarray | None = None,
                 unmodulated: complex = 0j, zernike_scale: float = 1.0) -> None:
        grey = torch.from_numpy(np.stack([f[..., colour] for f in frames]))[:, None]
        phase = grey_to_phase(grey, [curve], sign=sign).double()
        u = torch.polar(torch.ones_like(phase), phase) + unmodulated
        if source_amplitude is not None:
            u = u * torch.from_numpy(np.asarray(source_amplitude, np.float64))
        u = torch.fft.ifft2(torch.fft.fft2(u) * pixel_transfer(tuple(u.shape[-2:])))
        self.base_field = u.to(torch.complex64)
        self.field = self.base_field  # [F, 1, H, W]: the frames whose images are averaged
        self.pitch_m = pitch_m
        self.wavelength_m = wavelength_m
        self.cutoff_per_px = cutoff_per_px
        self.zernike_scale = zernike_scale
        self.aperture = Aperture(aperture_shape, (cutoff_per_px,))  # type: ignore[arg-type]

    def set_aberration(self, zernike_rad: tuple[float, ...]) -> None:
        """Render through a pupil phase (coefficients at the reference wavelength)."""
        self.field = apply_pupil(self.base_field, self.cutoff_per_px, tuple(zernike_rad),
                                 self.zernike_scale)

    def render(self, z_m: np.ndarray | list[float]) -> torch.Tensor:
        """Relative irradiance at the pixel centres [D, H, W] (float64) at depths `z_m`."""
        with torch.no_grad():
            # A depth tensor that requires grad selects propagate's differentiable path, which
            # computes the frequency coefficients once per call, not once per depth: several
            # times cheaper for a batch of depths (the result is the same to ~1e-7).
            z = torch.tensor(np.asarray(z_m, np.float64), requires_grad=True)
            u = propagate(self.field, z, self.pitch_m, [self.wavelength_m],
                          aperture=self.aperture, padding="auto")
            return u.abs().square()[:, :, 0].mean(dim=0).double()


@dataclass(frozen=True)
class ModelDepthFit:
    """The depth mapping fitted through the bench model (see the module docstring), with
    one-sigma uncertainties and the colours' gains.

    Units: `stage_scale` (SLM mm per stage mm, dimensionless) and `stage_at_slm_mm` (stage mm);
    `z_offset_m` per colour (R, G, B; SLM metres, green's 0). Each `*_std` is the larger of
    the formal one, `sqrt(diag(s^2 (J^T J)^-1))` with `J` the residuals' Jacobian at the
    solution (or at the step before it, less than Z_TOL_M away in every image's depth) and
    `s^2` the residual variance (sum of squares / (pixels - parameters)), and the scatter of the
    images' own preferred depths about the fitted line (the formal one assumes the model
    exact); `stage_scale_std` is `scale_std` where the scale was held. `gain` per fitted colour
    (image units per unit model irradiance); `rms_rel` the RMS image residual relative to the
    RMS image; `iterations` the trial steps evaluated."""

    stage_scale: float
    stage_at_slm_mm: float
    z_offset_m: tuple[float, float, float]
    stage_scale_std: float
    stage_at_slm_std_mm: float
    z_offset_std_m: tuple[float, float, float]
    gain: tuple[float, float, float]
    rms_rel: float
    iterations: int


def fit_depth_model(sweeps: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]],
                    models: dict[int, BenchModel], init: tuple[float, float, tuple[float, ...]],
                    *, scale_std: float | None = None, max_iter: int = 12,
                    say: Callable[[str], None] = lambda _m: None) -> ModelDepthFit:
    """Levenberg-Marquardt on (s0 mm, scale, offset_R mm, offset_B mm, gain_c, background_c)
    over every valid pixel of every fine-sweep image.

    `sweeps[c]` = (stage mm [S], images [S, H, W] resampled on the SLM grid, valid [H, W] bool);
    `init` = (s0 mm, scale, offsets m [3]), e.g. from the focus peaks. With `scale_std` given,
    the scale stays at `init`'s (set from the lateral magnification, 1 / M^2) and that is its
    uncertainty; otherwise the images fit it too. Stops when no image's depth moves by more
    than Z_TOL_M, or after `max_iter` trial steps. Uncertainties: see `ModelDepthFit`. Raises
    FocusError when the normal equations are singular (too few in-view dots or stage
    positions)."""
    s0, scale, offsets = init
    colours = sorted(sweeps)
    # Parameters: 0 s0 (mm), 1 scale, 2 off_R (mm), 3 off_B (mm), then gain_c, bg_c per colour.
    theta = np.zeros(4 + 2 * len(colours))
    theta[0], theta[1] = s0, scale
    theta[2], theta[3] = offsets[0] * 1e3, offsets[2] * 1e3
    ys = {c: sweeps[c][1][:, sweeps[c][2]] for c in colours}  # [S, P] valid samples
    masks = {c: sweeps[c][2] for c in colours}

    def z_of(th: np.ndarray, c: int, stages: np.ndarray) -> np.ndarray:
        off_mm = {0: th[2], 1: 0.0, 2: th[3]}[c]
        return ((stages - th[0]) * th[1] + off_mm) * STAGE_M_PER_MM

    def dz_dtheta(th: np.ndarray, c: int, stages: np.ndarray) -> np.ndarray:
        """[S, 4] derivative of z (m) w.r.t. (s0, scale, off_R, off_B)."""
        j = np.zeros((len(stages), 4))
        j[:, 0] = -th[1] * STAGE_M_PER_MM
        j[:, 1] = (stages - th[0]) * STAGE_M_PER_MM
        if c == 0:
            j[:, 2] = STAGE_M_PER_MM
        elif c == 2:
            j[:, 3] = STAGE_M_PER_MM
        return j

    # Per image at the last Jacobian: the Gauss-Newton step in its own depth alone (m), which
    # shows how far each image would rather sit from the fitted line (model mismatch, noise).
    own_step: dict[int, np.ndarray] = {}

    def evaluate(th: np.ndarray, with_jac: bool
                 ) -> tuple[float, np.ndarray, np.ndarray, int]:
        cost = 0.0
        jtj = np.zeros((len(th), len(th)))
        jtr = np.zeros(len(th))
        npix = 0
        for ci, c in enumerate(colours):
            stages = sweeps[c][0]
            z = z_of(th, c, stages)
            zs = np.concatenate([z, z + DZ_M]) if with_jac else z
            imgs = models[c].render(zs).numpy()[:, masks[c]]  # [S or 2S, P]
            n = len(stages)
            m = imgs[:n]
            gain, bg = th[4 + ci], th[4 + len(colours) + ci]
            r = gain * m + bg - ys[c]
            cost += float((r**2).sum())
            npix += r.size
            if not with_jac:
                continue
            # Forward difference: its O(DZ_M) error only slows the descent, it cannot move the
            # minimum (the cost itself is exact).
            dm_dz = (imgs[n:] - m) / DZ_M
            dzt = dz_dtheta(th, c, stages)
            jz = gain * dm_dz  # [S, P]
            own_step[c] = -(jz * r).sum(axis=1) / np.maximum((jz * jz).sum(axis=1), 1e-300)
            for i in range(n):
                cols = np.zeros((r.shape[1], len(th)))
                cols[:, :4] = gain * dm_dz[i][:, None] * dzt[i][None, :]
                cols[:, 4 + ci] = m[i]
                cols[:, 4 + len(colours) + ci] = 1.0
                jtj += cols.T @ cols
                jtr += cols.T @ r[i]
        return cost, jtj, jtr, npix

    # Linear parameters first (gain, background) at the initial depths.
    for ci, c in enumerate(colours):
        m = models[c].render(z_of(theta, c, sweeps[c][0])).numpy()[:, masks[c]].ravel()
        y = ys[c].ravel()
        a = np.stack([m, np.ones_like(m)], 1)
        (theta[4 + ci], theta[4 + len(colours) + ci]), *_ = np.linalg.lstsq(a, y, rcond=None)

    free = np.array([i for i in range(len(theta)) if not (i == 1 and scale_std is not None)])
    # Not scipy.optimize.least_squares (as fit_aberration): on the test benches (~5e5 residuals,
    # 9 parameters) it took 0.65-2.6 s to this loop's 0.34-0.45 s for the same depths to 0.01 um
    # (its trust-region solver passes over the tall Jacobian several times a step; this forms
    # the normal equations once).
    lam = 1e-3
    cost, jtj, jtr, npix = evaluate(theta, True)
    it = 0
    for it in range(1, max_iter + 1):
        a = jtj[np.ix_(free, free)]
        step = np.zeros_like(theta)
        step[free] = np.linalg.solve(a + lam * np.diag(np.diag(a)), -jtr[free])
        trial = theta + step
        # Converged when no image's depth moves by more than Z_TOL_M.
        moved = max(float(np.abs(z_of(trial, c, sweeps[c][0]) -
                                 z_of(theta, c, sweeps[c][0])).max()) for c in colours)
        new_cost = evaluate(trial, False)[0]
        say(f"  LM {it}: cost {cost:.6g} -> {new_cost:.6g}, s0 {trial[0]:.5f} mm, scale "
            f"{trial[1]:.5f}, offsets R {trial[2] * 1e3:.1f} B {trial[3] * 1e3:.1f} um")
        if new_cost < cost:
            theta = trial
            if moved < Z_TOL_M:
                cost = new_cost
                break
            cost, jtj, jtr, npix = evaluate(theta, True)
            lam = max(lam / 10, 1e-7)
        elif moved < Z_TOL_M or lam > 1e6:
            break
        else:
            lam *= 10
    dof = max(1, npix - len(theta))
    sigma2 = cost / dof
    a = jtj[np.ix_(free, free)]
    if not np.isfinite(a).all() or np.linalg.cond(a) > 1e14:
        raise FocusError("the depth mapping is undetermined by the fine sweeps (singular "
                         "normal equations: too few in-view dots or stage positions)")
    std = np.zeros_like(theta)
    std[free] = np.sqrt(np.clip(np.diag(sigma2 * np.linalg.inv(a)), 0, None))
    # Honest depth uncertainties: the formal ones above assume the model exact and are far too
    # small; the scatter of the images' own preferred depths about the fitted line is not.
    design = np.concatenate([dz_dtheta(theta, c, sweeps[c][0]) for c in colours])
    e = np.concatenate([own_step[c] for c in colours])
    dcols = [0, 2, 3] if scale_std is not None else [0, 1, 2, 3]
    d = design[:, dcols]
    sol, *_ = np.linalg.lstsq(d, e, rcond=None)
    s2 = float(((e - d @ sol) ** 2).sum()) / max(1, len(e) - len(dcols))
    dstd = np.sqrt(np.clip(np.diag(s2 * np.linalg.pinv(d.T @ d)), 0, None))
    for k, i in enumerate(dcols):
        std[i] = max(std[i], dstd[k])
    if scale_std is not None:
        std[1] = scale_std
    y_rms = math.sqrt(sum(float((ys[c] ** 2).sum()) for c in colours) / npix)
    return ModelDepthFit(
        stage_scale=float(theta[1]), stage_at_slm_mm=float(theta[0]),
        z_offset_m=(float(theta[2]) * 1e-3, 0.0, float(theta[3]) * 1e-3),
        stage_scale_std=float(std[1]), stage_at_slm_std_mm=float(std[0]),
        z_offset_std_m=(float(std[2]) * 1e-3, 0.0, float(std[3]) * 1e-3),
        gain=tuple(float(theta[4 + i]) for i in range(len(colours))),  # type: ignore[arg-type]
        rms_rel=math.sqrt(cost / npix) / y_rms, iterations=it)


class _Renders:
    """The last `keep` renders [S, P] of each colour in one fit, by the coefficients [K] that
    determine them: least_squares asks for the residuals and then the Jacobian at the same
    point (and, internally, the residuals again), which need one render, not two or three."""

    def __init__(self, render: Callable[[int, np.ndarray], np.ndarray], keep: int = 2) -> None:
        self._render = render
        self._keep = keep
        self._items: dict[int, dict[bytes, np.ndarray]] = {}

    def __call__(self, c: int, key: np.ndarray) -> np.ndarray:
        """The images [S, P] of colour `c` for `key` (rendered unless among the last few)."""
        k = np.ascontiguousarray(key, np.float64).tobytes()
        items = self._items.setdefault(c, {})
        items[k] = items.pop(k) if k in items else self._render(c, key)  # the newest last
        while len(items) > self._keep:
            del items[next(iter(items))]
        return items[k]


@dataclass(frozen=True)
class AberrationFit:
    """Zernike coefficients (Noll j = FIRST_NOLL...), radians at the reference wavelength, with
    one-sigma uncertainties, the RMS image residual relative to the RMS image before and after,
    the trial steps evaluated, and the terms the data could not determine (Noll indices).

    `zernike_std_rad` is the larger of the formal one, `sqrt(diag(s^2 (J^T J)^+))` with `J`
    the residuals' Jacobian at the solution (coefficients, gains and backgrounds) and `s^2` the
    residual variance, and the spread of the colours' separate Gauss-Newton solutions (standard
    error of their mean)."""

    zernike_rad: tuple[float, ...]
    zernike_std_rad: tuple[float, ...]
    rms_rel_before: float
    rms_rel: float
    iterations: int
    undetermined: tuple[int, ...] = ()


def fit_aberration(sweeps: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]],
                   models: dict[int, BenchModel], depth: ModelDepthFit, *,
                   n_terms: int = N_ZERNIKE, max_iter: int = 10,
                   astig_grid_rad: tuple[float, ...] = ASTIG_GRID_RAD,
                   say: Callable[[str], None] = lambda _m: None) -> AberrationFit:
    """Least squares (`scipy.optimize.least_squares`, "trf") on the Zernike coefficients
    shared by the colours (one optical path: each colour's phase is lambda_ref / lambda times
    it) and each colour's gain and background, the depth mapping held at `depth`'s. The
    defocused dots carry the information: astigmatism stretches a dot one way before its focus
    and the other way after, coma skews it, spherical makes the two sides differ in spread.
    Derivatives in the coefficients by forward differences (DA_RAD), the linear terms exact.
    `sweeps` and `models` as `fit_depth_model`'s; `n_terms` coefficients from Noll FIRST_NOLL.
    Stops when an accepted step moves no coefficient by more than 2e-3 rad, or after
    `max_iter` trial steps. Leaves each model rendering through the fitted pupil. Uncertainties:
    see `AberrationFit`."""
    colours = sorted(sweeps)
    nc = len(colours)
    ys = {c: sweeps[c][1][:, sweeps[c][2]] for c in colours}
    masks = {c: sweeps[c][2] for c in colours}

    def z_of(c: int) -> np.ndarray:
        return ((sweeps[c][0] - depth.stage_at_slm_mm) * depth.stage_scale * STAGE_M_PER_MM
                + depth.z_offset_m[c])

    zs = {c: z_of(c) for c in colours}

    def render(c: int, a: np.ndarray) -> np.ndarray:
        models[c].set_aberration(tuple(float(v) for v in a))
        return models[c].render(zs[c]).numpy()[:, masks[c]]

    images = _Renders(render)

    def linear(c: int, m: np.ndarray) -> tuple[float, float]:
        a = np.stack([m.ravel(), np.ones(m.size)], 1)
        (g, b), *_ = np.linalg.lstsq(a, ys[c].ravel(), rcond=None)
        return float(g), float(b)

    npix = sum(ys[c].size for c in colours)
    y_rms = math.sqrt(sum(float((ys[c] ** 2).sum()) for c in colours) / npix)
    npar = n_terms + 2 * nc
    theta = np.zeros(npar)
    for ci, c in enumerate(colours):
        theta[n_terms + ci], theta[n_terms + nc + ci] = linear(c, images(c, theta[:n_terms]))

    def residuals(th: np.ndarray) -> np.ndarray:
        return np.concatenate([
            (th[n_terms + ci] * images(c, th[:n_terms]) + th[n_terms + nc + ci]
             - ys[c]).ravel() for ci, c in enumerate(colours)])

    def jacobian(th: np.ndarray) -> np.ndarray:
        jac = np.zeros((npix, npar), order="F")  # column-major, as LAPACK takes it
        row = 0
        for ci, c in enumerate(colours):
            m = images(c, th[:n_terms])
            rows = slice(row, row + m.size)
            for k in range(n_terms):
                step = th[:n_terms].copy()
                step[k] += DA_RAD
                jac[rows, k] = th[n_terms + ci] * (render(c, step) - m).ravel() / DA_RAD
            jac[rows, n_terms + ci] = m.ravel()
            jac[rows, n_terms + nc + ci] = 1.0
            row += m.size
        return jac

    r0 = residuals(theta)
    rms_before = math.sqrt(float(r0 @ r0) / npix) / y_rms
    # The images are far from linear in astigmatism of half a radian and more: started from
    # zero, the descent can stop in a local minimum that trades astigmatism for the higher
    # terms. So the astigmatism starts from the best point of a coarse grid, scored on one
    # colour (green where swept) with its gain and background fitted.
    # Then coma (j = 7, 8) the same way, on a grid half as wide, the astigmatism held.
    if n_terms >= 2 and astig_grid_rad:
        ref = 1 if 1 in colours else colours[0]
        for k0, scale in ((0, 1.0), (2, 0.5)):
            if k0 + 2 > n_terms:
                continue
            best = (math.inf, theta[k0], theta[k0 + 1])
            for a in astig_grid_rad:
                for b_ in astig_grid_rad:
                    trial = theta[:n_terms].copy()
                    trial[k0 : k0 + 2] = scale * a, scale * b_
                    m = render(ref, trial)
                    g, b = linear(ref, m)
                    r = g * m + b - ys[ref]
                    best = min(best, (float((r * r).sum()), scale * a, scale * b_))
            theta[k0 : k0 + 2] = best[1:]
        for ci, c in enumerate(colours):
            theta[n_terms + ci], theta[n_terms + nc + ci] = linear(c, images(c, theta[:n_terms]))

    # scipy's trust-region Levenberg-Marquardt ("trf"), variables scaled by the Jacobian's
    # column norms (as MINPACK's), stopped as the hand-written loop it replaced: when an accepted
    # step moves no coefficient by more than 2e-3 rad, or after `max_iter` trial steps (ftol,
    # xtol and gtol only guard against a degenerate descent). Measured against that loop on the
    # test benches: the same coefficients to 1e-3 rad, 3.0-3.5 s a three-colour fit against
    # 5.5-5.8 s, 1.0-2.3 s a green-only one against 1.0-2.7 s. The subproblem by LSMR: as
    # accurate as the SVD of the tall Jacobian [~5e5, 13] here, and up to 40% faster.
    tried = {theta.tobytes()}
    last = [theta.copy()]

    def counted(th: np.ndarray) -> np.ndarray:
        tried.add(th.tobytes())  # least_squares evaluates some points twice
        return residuals(th)

    def step(intermediate_result: OptimizeResult) -> None:  # the name scipy looks for
        th = intermediate_result.x
        say(f"  aberration LM {intermediate_result.nit}: cost "
            f"{2 * float(intermediate_result.cost):.6g}, Zernike "
            f"{np.round(th[:n_terms], 3).tolist()} rad")
        moved = float(np.abs(th[:n_terms] - last[0][:n_terms]).max())
        last[0] = th.copy()
        if moved < 2e-3:
            raise StopIteration

    res = least_squares(counted, theta, jac=jacobian, method="trf", x_scale="jac",
                        tr_solver="lsmr", ftol=1e-10, xtol=1e-10, gtol=1e-10,
                        max_nfev=max_iter + 1, callback=step)
    theta, r, jac = res.x, res.fun, res.jac
    cost = float(r @ r)
    jtj = jac.T @ jac
    sigma2 = cost / max(1, npix - npar)
    cond = np.linalg.cond(jtj)
    diag = np.sqrt(np.clip(np.diag(sigma2 * np.linalg.pinv(jtj)), 0, None))[:n_terms] \
        if math.isfinite(cond) else np.full(n_terms, math.inf)
    std = diag.copy()
    # Each colour's own Gauss-Newton solution for the coefficients (its own gain and background
    # free): the colours' spread is an honest error bar.
    per_colour: dict[int, np.ndarray] = {}
    row = 0
    for ci, c in enumerate(colours):
        n = ys[c].size
        idx = [*range(n_terms), n_terms + ci, n_terms + nc + ci]
        jc, rc = jac[row : row + n][:, idx], r[row : row + n]
        row += n
        try:
            per_colour[c] = theta[:n_terms] + np.linalg.solve(jc.T @ jc, -(jc.T @ rc))[:n_terms]
        except np.linalg.LinAlgError:
            pass
    if len(per_colour) >= 2:
        spread = np.std(np.stack(list(per_colour.values())), axis=0, ddof=1) / \
            math.sqrt(len(per_colour))
        std = np.maximum(std, spread)
    # A term whose derivative is (nearly) a mix of the others' cannot be told apart from them.
    jn = jtj[:n_terms, :n_terms]
    d = np.sqrt(np.clip(np.diag(jn), 1e-300, None))
    corr_cond = np.linalg.cond(jn / d[:, None] / d[None, :])
    undetermined = tuple(FIRST_NOLL + k for k in range(n_terms)
                         if not math.isfinite(std[k]) or d[k] < 1e-12 or corr_cond > 1e10)
    for c in colours:
        models[c].set_aberration(tuple(float(v) for v in theta[:n_terms]))
    return AberrationFit(tuple(float(v) for v in theta[:n_terms]),
                         tuple(float(v) for v in std), rms_before,
                         math.sqrt(cost / npix) / y_rms, len(tried) - 1, undetermined)
