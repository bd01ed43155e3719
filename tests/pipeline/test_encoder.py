"""The encoder's fast paths against the definitions they replace: the region's propagation by
`propagate` of the zero-padded window (per colour depth, with the pupil pre-compensation), and
the torch coding path (`double_phase` + `phase_to_grey`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from nhfd.optics import (
    Aperture,
    double_phase,
    phase_to_grey,
    propagate,
    pupil_phase,
    transfer_function,
)
from nhfd.optics.padding import plan_padding
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.settings import FrameSettings

SETTINGS = FrameSettings(
    panel_hw=(128, 192), window_hw=(64, 96), pitch_m=8e-6,
    wavelengths_m=(660e-9, 520e-9, 450e-9), z0_m=6e-3, aperture_shape="square",
    cutoff_per_px=(0.25, 0.25, 0.25), amplitude_scale=2.0, zero_below=0.03,
    phase_stroke_rad=(2 * math.pi,) * 3)
ZERNIKE = (0.4, -0.3, 0.1, 0.05, -0.08, 0.02, 0.1)


def window_field(settings: FrameSettings, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    h, w = settings.window_hw
    amp = torch.rand(3, h, w, generator=g) * 1.2 * settings.amplitude_scale
    return torch.polar(amp, torch.rand(3, h, w, generator=g) * 2 * math.pi)


def slm_field_by_definition(enc: Encoder, reference: torch.Tensor) -> torch.Tensor:
    """The window zero-padded to the region, then propagated with `propagate` (all colours in one
    call where they share a depth, else each by its own; pre-compensated, the ASM kernel times
    the conjugate pupil on each colour's padded grid): what `Encoder.to_slm` computed before it
    was reduced to the kept frequencies."""
    s, r = enc.settings, enc.region
    h, w = reference.shape[-2:]
    buf = torch.zeros((3, r.height, r.width), dtype=torch.complex64)
    buf[:, r.window_top : r.window_top + h, r.window_left : r.window_left + w] = reference
    zs = s.colour_propagation_z_m
    if len(set(zs)) == 1 and not any(s.zernike_rad):  # all colours in one call (one padding)
        return propagate(buf, zs[0], s.pitch_m, s.wavelengths_m, aperture=s.aperture,
                         padding=s.padding)  # type: ignore[arg-type]
    out = []
    for c, z in enumerate(zs):
        lam = s.wavelengths_m[c]
        ap = Aperture(s.aperture.shape, (s.aperture.cutoffs(3)[c],))
        if not any(s.zernike_rad):
            out.append(propagate(buf[c : c + 1], z, s.pitch_m, [lam], aperture=ap,
                                 padding=s.padding)[0])  # type: ignore[arg-type]
            continue
        hw = plan_padding((r.height, r.width), s.pitch_m, (lam,), abs(z), ap,
                          s.padding).padded_hw  # type: ignore[arg-type]
        k = transfer_function(hw, s.pitch_m, [lam], [z], aperture=ap)[0, 0]
        lam_ref = s.zernike_wavelength_m or s.wavelengths_m[1]
        ph = pupil_phase(hw, s.aperture.cutoffs(3)[c], s.zernike_rad, lam_ref / lam)
        k = k * torch.polar(torch.ones_like(ph), -ph).to(k.dtype)
        out.append(torch.fft.ifft2(torch.fft.fft2(buf[c], s=hw) * k)[: r.height, : r.width])
    return torch.stack(out)


@pytest.mark.parametrize("changes", [
    {},  # one depth for all colours: one batched group
    {"colour_offset_m": (0.4e-3, 0.0, -0.3e-3), "padding": "2x"},  # a group per colour
    {"zernike_rad": ZERNIKE, "zernike_wavelength_m": 520e-9, "aperture_shape": "circle"},
    {"window_hw": (63, 95), "refocus_m": 2e-3, "cutoff_per_px": (0.2, 0.25, 0.3)},
])
def test_to_slm_is_the_padded_propagation(changes):
    enc = Encoder(dataclasses.replace(SETTINGS, **changes))
    first = enc.to_slm(window_field(enc.settings, 7))  # the buffers it keeps: nothing stale
    ref = window_field(enc.settings)
    got = enc.to_slm(ref)
    want = slm_field_by_definition(enc, ref)
    assert got.shape == want.shape == (3, enc.region.height, enc.region.width)
    err = float((got - want).abs().max() / want.abs().max())
    rel = float((got - want).norm() / want.norm())
    # Float32 rounding of two FFTs (measured ~3e-7 relative L2).
    assert rel < 3e-6 and err < 3e-6
    assert torch.equal(enc.to_slm(ref), got)  # the same every call
    assert not torch.equal(first, got) and first.data_ptr() != got.data_ptr()  # fresh output


def test_code_is_the_torch_coding_path_within_one_level():
    """Calibrated curves (over 2 pi), the conjugate sign, inverted grey and the source's gain
    map, as the daemon's calibration sets them."""
    curves = tuple(tuple(0.2 + (6.9 + 0.2 * c) * (g / 255) ** 1.2 for g in range(256))
                   for c in range(3))
    s = dataclasses.replace(SETTINGS, phase_tables_rad=curves, phase_sign=-1, grey_invert=True,
                            source_profile=((0.5e-3, 0.1e-3, 0.0),) * 3)
    enc = Encoder(s)
    slm = enc.to_slm(window_field(s, 1))
    grey, clipped = enc.code(slm)
    gain = enc.amplitude_gain_map()
    assert gain is not None and float(gain.max()) > 1.5
    coded = double_phase(slm * gain, s.amplitude_scale, zero_below=s.zero_below)
    ref = phase_to_grey(coded.phase_rad, enc.curves, sign=-1, invert=True).numpy()
    assert clipped == pytest.approx(coded.clipped_fraction.tolist(), abs=1e-6)
    assert min(clipped) > 0.001
    # Off by one level only next to a decision boundary (levels sorted on the circle).
    for c in range(3):
        rank = np.argsort(np.argsort(np.remainder(curves[c], 2 * math.pi)))
        d = np.abs(rank[255 - grey[c].astype(np.int64)] - rank[255 - ref[c].astype(np.int64)])
        d = np.minimum(d, 256 - d)
        assert d.max() <= 1 and np.mean(d != 0) < 1e-3
