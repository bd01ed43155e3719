"""The calibration fit: geometry -> phase sign and a first depth mapping from focus peaks ->
phase response and intensity -> the depth mapping refined through the bench model
(`nhfd.calib.bench_model`: the fine sweeps' images fitted by damped Gauss-Newton through the
double-phase frames, fitted curves, aperture and ASM), with the stage scale tied to the lateral
magnification (1 / M^2).

`fit_capture(DIR)` reads a complete capture (see `nhfd.calib.capture`) and returns a
`Calibration` (see `nhfd.calibration`). Each stage refuses with a clear error when the
data cannot determine what it fits (`GeometryError`, `FocusError`, `ResponseError`,
`CalibrationDataError` naming the file at fault).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.calibration import Calibration, unmodulated_amplitude
from nhfd.optics import PhaseCurve
from nhfd.optics.camera_grid import to_slm_grid

from .bench_model import (
    AberrationFit,
    BenchModel,
    ModelDepthFit,
    fit_aberration,
    fit_depth_model,
)
from .data import CaptureData, default_camera_pitch_m, load_capture, load_frame, load_image
from .focus import FocusError, dot_metric, fit_depth, peak_position
from .geometry import Geometry, fit_geometry
from .patterns import PatternSpec, dot_layout, grating_tiles
from .response import ResponseError, ResponseFit, SourceFit, fit_curve, fit_source, tile_harmonic

COLOURS = ("R", "G", "B")


def _stack(data: CaptureData, recs: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    recs = sorted(recs, key=lambda r: r["stage_mm"])
    images = [data.image(r)[0] for r in recs]
    shapes = {im.shape for im in images}
    if len(shapes) != 1:
        raise ValueError(f"capture images differ in shape: {sorted(shapes)}")
    return np.asarray([r["stage_mm"] for r in recs]), np.stack(images)


def _dot_radius_px(geo: Geometry, spec: PatternSpec) -> float:
    # About one SLM pixel on the camera: the in-focus spot's core.
    return max(1.5, spec.pitch_m * geo.px_per_m)


def _peaks(stages: np.ndarray, stack: np.ndarray, geo: Geometry, spec: PatternSpec
           ) -> list[tuple[int, float]]:
    """(depth group, peak stage mm) per dot whose focus the sweep brackets."""
    lay = dot_layout(spec)
    metric = dot_metric(stack, geo.to_camera(lay.xy_m), _dot_radius_px(geo, spec))
    out = []
    for k in range(len(lay.xy_m)):
        p = peak_position(stages, metric[:, k])
        if p is not None:
            out.append((int(lay.group[k]), p))
    return out


def locate(root: Path | str, spec: PatternSpec, records: list[dict[str, Any]],
           camera_pitch_m: float) -> dict[str, float]:
    """From the coarse green sweep: the magnification (in-focus dots) and the stage reading
    that images the SLM plane (the peak of the dots designed at depth 0). The stage scale is
    estimated as 1 / M^2 for planning the fine sweep only."""
    if 0.0 not in spec.depths_m:
        raise FocusError("locating the SLM plane needs a dot group at depth 0")
    data = CaptureData(Path(root), {"records": records}, spec)
    stages, stack = _stack(data, records)
    geo, _, _ = fit_geometry(stack.max(axis=0), dot_layout(spec))
    g0 = spec.depths_m.index(0.0)
    peaks = [s for g, s in _peaks(stages, stack, geo, spec) if g == g0]
    if not peaks:
        raise FocusError("the coarse sweep does not bracket the SLM plane's focus: widen "
                         "--stage-range or move --stage-center")
    m = geo.magnification(camera_pitch_m)
    return {"stage_at_slm_mm": float(np.median(peaks)), "stage_scale": 1.0 / m**2,
            "magnification": m, "px_per_m": geo.px_per_m, "rotation_deg": geo.rotation_deg,
            "mirror_x": geo.mirror_x, "shift_px": list(geo.shift_px)}


def geometry_from(loc: dict[str, Any]) -> Geometry:
    """The coarse geometry that `locate` recorded in the manifest."""
    return Geometry(loc["px_per_m"], loc["rotation_deg"], bool(loc["mirror_x"]),
                    tuple(loc["shift_px"]), 0.0, 0, 0.0, 0.0)  # type: ignore[arg-type]


def _fine_stack(data: CaptureData, colour: int) -> tuple[np.ndarray, np.ndarray]:
    """Stage positions [S] and images [S, h, w] of a colour's fine sweep, each the mean of the
    dot hologram and its negated twin (the pair cancels the dots' interference with light the
    coding does not control, which would otherwise skew the focus curves)."""
    recs = data.records("fine", colour)
    if not recs:
        raise FocusError(f"no fine-sweep images for colour {COLOURS[colour]}")
    steps: dict[int, list[dict[str, Any]]] = {}
    for r in recs:
        steps.setdefault(int(r.get("step", len(steps))), []).append(r)
    stages, images = [], []
    for k in sorted(steps):
        group = steps[k]
        stages.append(float(np.mean([r["stage_mm"] for r in group])))
        images.append(np.mean([data.image(r)[0] for r in group], axis=0))
    order = np.argsort(stages)
    return np.asarray(stages)[order], np.stack(images)[order]


def _fit_depth_model(data: CaptureData, stacks: dict[int, tuple[np.ndarray, np.ndarray]],
                     geo: Geometry, sign: int, resp: ResponseFit,
                     init: tuple[float, float, tuple[float, ...]], scale_std: float,
                     say: Callable[[str], None], source: SourceFit | None = None
                     ) -> tuple[ModelDepthFit, dict[int, Any], dict[int, BenchModel]]:
    """The fine sweeps (pair means, per unit exposure and power) resampled on the SLM grid,
    fitted through the bench model of the frames they showed (with the fitted source profile
    and unmodulated light where `source` determined them). Returns the fit, the sweeps and the
    models (the aberration fit reuses them)."""
    spec = data.spec
    names = sorted({r["frame"] for r in data.records("fine")})
    frames = [load_frame(data.root, data.manifest, n) for n in names]
    sweeps, models = {}, {}
    for c in range(3):
        stages, stack = stacks[c]
        rate = _rate(data.records("fine", c), "fine", COLOURS[c])
        resampled = [to_slm_grid(im / rate, geo, spec.panel_hw, spec.pitch_m) for im in stack]
        valid = np.logical_and.reduce([ok for _, ok in resampled]) & ~_saturated(data, c, geo)
        if valid.sum() < 100:
            raise FocusError(f"colour {COLOURS[c]}: only {int(valid.sum())} panel pixels in "
                             "view of the camera: the depth mapping is undetermined")
        sweeps[c] = (stages, np.stack([v for v, _ in resampled]), valid)
        amp, unmod = _source_terms(source, spec.panel_hw, spec.pitch_m, c)
        models[c] = BenchModel(frames, c, PhaseCurve(resp.tables_rad[c]), sign, spec.pitch_m,
                               spec.wavelengths_m[c], spec.cutoff_per_px[c], spec.aperture_shape,
                               source_amplitude=amp, unmodulated=unmod,
                               zernike_scale=spec.wavelengths_m[1] / spec.wavelengths_m[c])
    return fit_depth_model(sweeps, models, init, scale_std=scale_std, say=say), sweeps, models


def _source_terms(source: SourceFit | None, panel_hw: tuple[int, int], pitch_m: float,
                  c: int) -> tuple[np.ndarray | None, complex]:
    """The bench model's source amplitude [H, W] (peak 1) and unmodulated amplitude for a
    colour, from the flat-field fit (None / 0 where it did not determine them)."""
    amp = None
    if source is not None and source.waist_m is not None and source.centre_m is not None:
        h, w = panel_hw
        x = (np.arange(w) - (w - 1) / 2) * pitch_m - source.centre_m[c][0]
        y = (np.arange(h) - (h - 1) / 2) * pitch_m - source.centre_m[c][1]
        amp = np.exp(-(x[None, :] ** 2 + y[:, None] ** 2) / source.waist_m[c] ** 2)
    unmod = 0j
    if source is not None and source.unmodulated_fraction is not None and \
            source.unmodulated_phase_rad is not None:
        unmod = unmodulated_amplitude(source.unmodulated_fraction[c],
                                      source.unmodulated_phase_rad[c])
    return amp, unmod


def measure_source(data: CaptureData, geo: Geometry, sign: int, resp: ResponseFit
                   ) -> SourceFit | None:
    """The source profile and unmodulated light from the flat frames (None: none captured)."""
    spec = data.spec
    flats: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    greys: dict[int, list[int]] = {}
    for c in range(3):
        for rec in sorted(data.records("flat", c), key=lambda r: r["grey"]):
            image, sat = data.image(rec)
            rate = rec["exposure_s"] * max(rec["powers"])
            vals, ok = to_slm_grid(image / rate, geo, spec.panel_hw, spec.pitch_m)
            if sat.any():
                hit, _ = to_slm_grid(sat.astype(np.float64), geo, spec.panel_hw, spec.pitch_m)
                ok &= hit == 0
            flats.setdefault(c, []).append((vals, ok))
            greys.setdefault(c, []).append(int(rec["grey"]))
    if len(flats) < 3:
        return None
    return fit_source(flats, greys, resp.tables_rad, sign, spec.pitch_m)


def _rate(recs: list[dict[str, Any]], sweep: str, colour: str) -> float:
    """Exposure x laser power, which must be the same for every image of a sweep (the images
    are averaged in pairs and fitted with one gain per colour)."""
    rates = {round(r["exposure_s"] * max(r["powers"]), 12) for r in recs}
    if len(rates) != 1:
        raise FocusError(f"colour {colour}: the {sweep} sweep mixes exposures or laser powers "
                         f"({sorted(rates)}): recapture with fixed settings")
    return rates.pop()


def _saturated(data: CaptureData, colour: int, geo: Geometry) -> np.ndarray:
    """[H, W] SLM pixels whose camera image is saturated in any fine-sweep image of a colour
    (clipped values would pull the fit): dilated by a pixel for the resampling's reach."""
    spec = data.spec
    out = np.zeros(spec.panel_hw, bool)
    for rec in data.records("fine", colour):
        _, sat = data.image(rec)
        if sat.any():
            hit, _ = to_slm_grid(sat.astype(np.float64), geo, spec.panel_hw, spec.pitch_m)
            out |= hit > 0
    if out.any():
        grown = out.copy()
        grown[1:] |= out[:-1]
        grown[:-1] |= out[1:]
        grown[:, 1:] |= out[:, :-1]
        grown[:, :-1] |= out[:, 1:]
        out = grown
    return out


def illumination_maps(root: Path | str, spec: PatternSpec, records: list[dict[str, Any]],
                      geo: Geometry) -> dict[int, np.ndarray]:
    """Per colour with flat frames among `records`: the illumination on the SLM grid [H, W],
    relative (mean 1 over the pixels in view; NaN where none is), non-parametric: each flat
    image (at the SLM plane a flat panel shows the source itself) divided by its own mean over
    the common view, then averaged over the levels (their brightness differs by the zero
    order's interference, not their shape)."""
    data = CaptureData(Path(root), {"records": records}, spec)
    out = {}
    for c in range(3):
        vals, oks = [], []
        for rec in data.records("flat", c):
            image, sat = data.image(rec)
            v, ok = to_slm_grid(image, geo, spec.panel_hw, spec.pitch_m)
            if sat.any():
                hit, _ = to_slm_grid(sat.astype(np.float64), geo, spec.panel_hw, spec.pitch_m)
                ok &= hit == 0
            vals.append(v)
            oks.append(ok)
        if not vals:
            continue
        ok = np.logical_and.reduce(oks)
        if ok.sum() < 100:
            continue
        m = np.mean([v / v[ok].mean() for v in vals], axis=0)
        out[c] = np.where(ok, m / m[ok].mean(), np.nan)
    return out


def measure_response(root: Path | str, spec: PatternSpec, records: list[dict[str, Any]],
                     geo: Geometry) -> ResponseFit:
    """Phase tables and intensities per colour from the grating captures. Where `records`
    also hold flat frames, each tile's harmonic is divided by the illumination over the tile
    (`illumination_maps`): a beam that is not flat over the panel would otherwise make the
    tiles' brightness, not only their phase differences, differ (K is then the panel mean)."""
    data = CaptureData(Path(root), {"records": records}, spec)
    tiles = grating_tiles(spec)
    illum = illumination_maps(root, spec, records, geo)
    tables, stds, ks, k_stds, rms, counts = [], [], [], [], [], []
    for c in range(3):
        ref, test, meas = [], [], []
        for rec in data.records("grating", c):
            image, _ = data.image(rec)
            rate = rec["exposure_s"] * max(rec["powers"])
            for t in tiles:
                if t.frame != rec.get("grating_frame"):
                    continue
                v = tile_harmonic(image, t, geo, spec.pitch_m, spec.panel_hw)
                if v is not None and c in illum:
                    patch = illum[c][t.row : t.row + t.size, t.col : t.col + t.size]
                    v = v / float(np.nanmean(patch)) if np.isfinite(patch).any() else None
                if v is not None:
                    ref.append(t.ref)
                    test.append(t.test)
                    meas.append(v / rate)
        if not meas:
            raise ResponseError(f"colour {COLOURS[c]}: no grating tile in view")
        table, std, k, k_std, res = fit_curve(np.asarray(ref), np.asarray(test),
                                              np.asarray(meas), spec.strokes_rad[c])
        tables.append(tuple(float(v) for v in table))
        stds.append(std)
        ks.append(k)
        k_stds.append(k_std)
        rms.append(res)
        counts.append(len(meas))
    return ResponseFit(tuple(tables), tuple(stds), tuple(ks), tuple(k_stds),  # type: ignore
                       tuple(rms), tuple(counts))  # type: ignore[arg-type]


def fit_capture(root: Path | str, progress: Callable[[str], None] | None = None
                ) -> Calibration:
    """Fit the calibration of the complete capture in `root` (the module's docstring: geometry,
    phase sign and depth mapping, response and intensity, source and unmodulated light, the depth
    mapping through the bench model); `progress` gets a line per stage. GeometryError, FocusError,
    ResponseError or CalibrationDataError when the data cannot determine a stage."""
    say = progress or (lambda _m: None)
    data = load_capture(root)
    spec = data.spec
    plan = data.manifest.get("plan", {})
    camera_pitch_m = float(plan.get("camera_pitch_m") or default_camera_pitch_m())
    if data.manifest.get("dark"):
        load_image(data.root / data.manifest["dark"], "dark")  # present and readable
    lay = dot_layout(spec)

    # 1. Geometry from the in-focus dots of every colour's fine sweep (max over the stack).
    stacks = {c: _fine_stack(data, c) for c in range(3)}
    geo, _pts, _idx = fit_geometry(stacks[1][1].max(axis=0), lay)
    mag = geo.magnification(camera_pitch_m)
    say(f"geometry: M = {mag:.5f}, rotation {geo.rotation_deg:.3f} deg, mirror "
        f"{geo.mirror_x}, {geo.n_dots} dots, rms {geo.rms_px:.3f} px")

    # 2. Depth mapping and sign from each dot's focus.
    triples = []
    for c in range(3):
        stages, stack = stacks[c]
        if len(np.unique(np.round(stages, 6))) < 2:
            raise FocusError(f"colour {COLOURS[c]}: captured at one stage position only: the "
                             "stage scale is undetermined")
        for g, s in _peaks(stages, stack, geo, spec):
            triples.append((c, spec.depths_m[g], s))
    depth = fit_depth(triples)
    say(f"focus peaks: sign {depth.phase_sign:+d}, scale {depth.stage_scale:.5f} "
        f"(1/M^2 = {1 / mag**2:.5f}), stage at SLM {depth.stage_at_slm_mm:.4f} mm, offsets "
        f"{[round(z * 1e6, 1) for z in depth.z_offset_m]} um, rms {depth.rms_mm * 1e3:.1f} um")

    # 3. Phase response and intensity from the gratings.
    resp = measure_response(data.root, spec, data.records("grating") + data.records("flat"),
                            geo)

    # 4. The depth mapping refined through the bench model (the peaks above are biased by about
    # a tenth of the depth of field: see nhfd.calib.bench_model). The stage scale is tied to
    # the lateral magnification (longitudinal magnification = M^2): the centroids of dozens of
    # dots measure M to ~0.05%, far better than the images can measure the scale, whose fit
    # trades against model mismatch near the SLM plane.
    scale = 1.0 / mag**2
    scale_std = 2 * scale * geo.px_per_m_std / geo.px_per_m
    # 3b. The source profile and the unmodulated light from the flat frames (older captures
    # have none: then neither is fitted, and the file says so).
    source = measure_source(data, geo, depth.phase_sign, resp)
    refused: list[str] = []
    if source is None:
        refused.append("source and zero order: the capture has no flat frames")
    else:
        refused.extend(source.refused)
        for m in source.refused:
            say(f"refused: {m}")
        if source.waist_m is not None:
            say(f"source: waist {[round(w * 1e3, 3) for w in source.waist_m]} mm, centre "
                f"{[tuple(round(v * 1e6, 1) for v in xy) for xy in source.centre_m or ()]} um")
        if source.unmodulated_fraction is not None:
            say(f"unmodulated light: {[round(f, 4) for f in source.unmodulated_fraction]} +- "
                f"{[round(f, 4) for f in source.unmodulated_fraction_std or ()]}")
    model, sweeps, models = _fit_depth_model(
        data, stacks, geo, depth.phase_sign, resp,
        (depth.stage_at_slm_mm, scale, depth.z_offset_m), scale_std, say, source)
    # 5. Aberrations through the same models, the depth mapping held; then the depth mapping
    # again through the aberrated model when the aberration is significant (spherical and the
    # square iris's corners trade a little with defocus).
    aber: AberrationFit = fit_aberration(sweeps, models, model, say=say)
    say(f"aberration: Zernike j=5.. {np.round(aber.zernike_rad, 3).tolist()} +- "
        f"{np.round(aber.zernike_std_rad, 3).tolist()} rad, image residual "
        f"{aber.rms_rel_before:.1%} -> {aber.rms_rel:.1%}")
    if aber.undetermined:
        refused.append(f"aberration: Noll terms {list(aber.undetermined)} are not separated "
                       "by the fine sweeps")
    if max(abs(a) for a in aber.zernike_rad) > 0.05:
        model = fit_depth_model(sweeps, models, (model.stage_at_slm_mm, scale, model.z_offset_m),
                                scale_std=scale_std, say=say)
    say(f"depth (model): stage at SLM {model.stage_at_slm_mm:.4f} +- "
        f"{model.stage_at_slm_std_mm * 1e3:.1f} um, offsets "
        f"{[round(z * 1e6, 1) for z in model.z_offset_m]} +- "
        f"{[round(z * 1e6, 1) for z in model.z_offset_std_m]} um, image residual "
        f"{model.rms_rel:.1%}, {model.iterations} iterations")
    for c in range(3):
        say(f"response {COLOURS[c]}: range {resp.tables_rad[c][-1]:.3f} rad "
            f"(+- {resp.table_std_rad[c]:.3f} RMS), K {resp.intensity[c]:.4g}, residual "
            f"{resp.rms_residual[c]:.3%} of K, {resp.n_tiles[c]} tiles")
    tables, stds, ks, k_stds = (resp.tables_rad, resp.table_std_rad, resp.intensity,
                                resp.intensity_std)
    rms, counts = resp.rms_residual, list(resp.n_tiles)

    digest = hashlib.sha256((data.root / "manifest.json").read_bytes()).hexdigest()[:16]
    return Calibration(
        wavelengths_m=spec.wavelengths_m,
        pitch_m=spec.pitch_m,
        phase_sign=depth.phase_sign,
        phase_tables_rad=tuple(tables),
        phase_table_std_rad=tuple(stds),
        stage_scale=model.stage_scale,
        stage_scale_std=model.stage_scale_std,
        stage_at_slm_mm=model.stage_at_slm_mm,
        stage_at_slm_std_mm=model.stage_at_slm_std_mm,
        z_offset_m=model.z_offset_m,
        z_offset_std_m=model.z_offset_std_m,
        magnification=mag,
        magnification_std=geo.px_per_m_std * camera_pitch_m,
        rotation_deg=geo.rotation_deg,
        rotation_std_deg=geo.rotation_std_deg,
        mirror_x=geo.mirror_x,
        shift_px=geo.shift_px,
        intensity=tuple(ks),
        intensity_std=tuple(k_stds),
        residuals={"geometry_rms_px": geo.rms_px, "focus_rms_mm": depth.rms_mm,
                   "response_rms_rel": [float(v) for v in rms],
                   # The focus peaks' own scale against 1 / M^2: a check of the tie.
                   "longitudinal_vs_lateral": depth.stage_scale * mag**2 - 1.0,
                   "depth_model_rms_rel": model.rms_rel,
                   "sign_margin_sigma": depth.sign_margin,
                   "source_rms_log": source.rms_log_residual if source else float("nan"),
                   "aberration_rms_rel": [aber.rms_rel_before, aber.rms_rel]},
        fitted_on={"capture": str(Path(root).resolve()), "manifest_sha256_16": digest,
                   "images": len(data.manifest["records"]), "dots": geo.n_dots,
                   "focus_peaks": depth.n_peaks, "grating_tiles": counts,
                   "camera_pitch_m": camera_pitch_m, "panel_hw": list(spec.panel_hw)},
        **_source_fields(source),
        zernike_rad=() if aber.undetermined else aber.zernike_rad,
        zernike_std_rad=() if aber.undetermined else aber.zernike_std_rad,
        zernike_wavelength_m=spec.wavelengths_m[1],
        refused=tuple(refused),
    )


def _source_fields(source: SourceFit | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if source is not None and source.waist_m is not None:
        out.update(source_waist_m=source.waist_m, source_waist_std_m=source.waist_std_m,
                   source_centre_m=source.centre_m, source_centre_std_m=source.centre_std_m)
    if source is not None and source.unmodulated_fraction is not None:
        out.update(unmodulated_fraction=source.unmodulated_fraction,
                   unmodulated_fraction_std=source.unmodulated_fraction_std,
                   unmodulated_phase_rad=source.unmodulated_phase_rad)
    return out


__all__ = ["fit_capture", "locate"]

