"""Source profile, zero order and aberrations (issue 8, "Fit"): the twin's pupil, the daemon's
pre-compensation, and what the fit recovers on the session's randomised bench."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nhfd.drivers.simcamera import SimulatedCamera, TrueBench
from nhfd.optics.pupil import apply_pupil
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.settings import FrameSettings


def _zernike(seed: int) -> tuple[float, ...]:
    # Astigmatism up to 0.6 rad RMS, the higher terms up to 0.25 rad (a decent relay).
    rng = np.random.default_rng(seed)
    return tuple(float(v) for v in np.concatenate([rng.uniform(-0.6, 0.6, 2),
                                                   rng.uniform(-0.25, 0.25, 5)]))


def test_twin_and_model_pupils_agree() -> None:
    z = _zernike(3)
    b = TrueBench.randomised(3, oversample=1, zernike_rad=z)
    cam = SimulatedCamera(lambda: np.zeros((64, 64), np.uint8), lambda: (0, 1, 0),
                          lambda: 10.0, b, roi=b.roi_for_panel((64, 64)))
    f = torch.randn(1, 64, 64, dtype=torch.complex64, generator=torch.Generator().manual_seed(0))
    for c in range(3):
        twin = cam._aberrate(f, c)
        model = apply_pupil(f, 0.25, z, b.wavelengths_m[1] / b.wavelengths_m[c])
        assert float((twin - model).abs().max()) < 1e-4 * float(f.abs().max())


def _encoder(z: tuple[float, ...]) -> Encoder:
    return Encoder(FrameSettings(
        panel_hw=(128, 128), window_hw=(64, 64), pitch_m=8e-6,
        wavelengths_m=(638e-9, 532e-9, 450e-9), z0_m=1e-3, aperture_shape="square",
        cutoff_per_px=(0.25,) * 3, amplitude_scale=1.0, zero_below=1e-3,
        phase_stroke_rad=(2 * math.pi,) * 3, zernike_rad=z, zernike_wavelength_m=532e-9))


def test_precompensation_undoes_the_bench_pupil() -> None:
    """The bench's pupil applied to the pre-compensated SLM field gives the field an
    aberration-free relay needs, for every colour; with the pupil itself (the conjugate
    forgotten) it would be doubled instead."""
    z = _zernike(5)
    yy, xx = np.mgrid[0:64, 0:64]
    amp = np.exp(-((xx - 32) ** 2 + (yy - 24) ** 2) / 2.0) + \
        np.exp(-((xx - 20) ** 2 + (yy - 40) ** 2) / 4.0)
    ref = torch.polar(torch.from_numpy(np.stack([amp] * 3)).float(), torch.zeros(3, 64, 64))
    plain = _encoder(()).to_slm(ref)
    enc = _encoder(z)
    comp = enc.to_slm(ref)
    wrong = _encoder(tuple(-v for v in z)).to_slm(ref)
    peak = float(plain.abs().max())
    for c, lam in enumerate((638e-9, 532e-9, 450e-9)):
        scale = 532e-9 / lam
        seen = apply_pupil(comp[c : c + 1], 0.25, z, scale)
        seen_wrong = apply_pupil(wrong[c : c + 1], 0.25, z, scale)
        err = float((seen - plain[c : c + 1]).abs().max()) / peak
        err_wrong = float((seen_wrong - plain[c : c + 1]).abs().max()) / peak
        assert err < 0.02, f"colour {c}: {err:.3%}"
        assert err_wrong > 10 * err
    # The kernels are cached under keys that name the aberration and, as every ASM kernel's, the
    # device (the CPU's too).
    assert all(key[0] == "asm-pupil" and key[6] == z and key[-1] == "cpu"
               for key in enc.cache._items)


def test_amplitude_compensation_lifts_the_beam_edge() -> None:
    s = _encoder(())
    prof = ((0.8e-3, 0.1e-3, 0.0),) * 3
    enc = Encoder(FrameSettings(**{**s.settings.__dict__, "source_profile": prof}))
    g = enc.amplitude_gain_map()
    assert g is not None and float(g.max()) <= 2.0 + 1e-6
    # Unity near the window's centre, more where the beam is dimmer (away from x0 = 0.1 mm).
    h, w = g.shape[-2:]
    assert abs(float(g[1, h // 2, w // 2]) - 1) < 0.05
    assert float(g[1, h // 2, 0]) > float(g[1, h // 2, w - 1]) > 1


def _effective_unmodulated(b: TrueBench) -> float:
    # The twin's coherent unmodulated light: zero-order leakage plus the gap's (inseparable).
    m = math.sqrt(1 - b.zero_order_fraction) * b.fill_factor
    c0 = math.sqrt(1 - b.zero_order_fraction) * (1 - b.fill_factor) * b.gap_reflectance + \
        math.sqrt(b.zero_order_fraction)
    return c0**2 / (c0**2 + m**2)


def test_zero_order_and_source_recovered(bench: TrueBench, fitted) -> None:
    true_f0 = _effective_unmodulated(bench)
    assert fitted.unmodulated_fraction, fitted.refused
    for c in range(3):
        got = fitted.unmodulated_fraction[c]
        assert abs(got - true_f0) < max(0.3 * true_f0, 0.003), (c, got, true_f0)
    if fitted.source_waist_m:
        for c in range(3):
            assert abs(fitted.source_waist_m[c] / bench.source_waist_m - 1) < 0.05
            err = np.hypot(*np.subtract(fitted.source_centre_m[c], bench.source_offset_m))
            assert err < 0.03 * bench.source_waist_m
    else:
        assert any("source profile" in r for r in fitted.refused)


def test_no_aberration_found_where_there_is_none(fitted) -> None:
    if not fitted.zernike_rad:
        pytest.skip("aberrations refused: " + "; ".join(fitted.refused))
    assert max(abs(a) for a in fitted.zernike_rad[:2]) < 0.1
