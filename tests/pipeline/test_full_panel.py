"""The whole 1920 x 1080 panel on the CPU: one frame of the shipped model with the window set to
the panel (`daemon.frames.size_px = [1920, 1080]`), as the frame worker computes it.

At that size the region is the panel itself (the kernel's margin is clipped by its edges), and
the propagation runs on the FFT lengths the full panel really uses: "auto" padding takes the
1080 x 1920 region to 1125 x 1944 (one kernel reach plus a guard, 5-smooth), "2x" to 2160 x 3840.
torch's FFT was once wrong at one shape (`nhfd.optics.fft`), so both are compared with an
independent float64 NumPy angular spectrum on the same padded grid."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nhfd.config import Config
from nhfd.models.export import OnnxModel, load_model
from nhfd.optics import double_phase_grey
from nhfd.optics.refplane import reference_to_slm
from nhfd.pipeline.encoder import Encoder, reference_field
from nhfd.pipeline.frame import compute_frame, infer, render_view
from nhfd.pipeline.settings import Region, frame_settings, zero_pattern
from nhfd.pipeline.view import Scene, scene_frame
from nhfd.scene.io import read_scene
from nhfd.views import Orbit, View

REPO = Path(__file__).resolve().parents[2]
MODEL = REPO / "models" / "nhf-donut-512.onnx"
SCENE = REPO / "models" / "scenes" / "donut.ply"
PANEL_HW = (1080, 1920)


@pytest.fixture(scope="module")
def panel():
    config = Config.model_validate({"daemon": {"frames": {"size_px": [PANEL_HW[1], PANEL_HW[0]]}}})
    model = load_model(MODEL, config)
    settings = frame_settings(config, model.info, None)
    encoder = Encoder(settings)
    load = read_scene(SCENE)
    scene = Scene(load.gaussians, scene_frame(load.gaussians, str(SCENE)))
    env = model.info.pose_envelope  # a view in the middle of the trained ones
    view = View(Orbit(sum(env.azimuth_deg) / 2, sum(env.elevation_deg) / 2,
                      sum(env.distance) / 2))
    frame = compute_frame(view, scene, model, encoder)
    # The frame's stages again, to look inside it: its reference-plane field.
    amplitude, phase = infer(model, render_view(view, scene, model.info, settings.window_hw))
    reference = reference_field(amplitude, phase, settings.amplitude_scale)
    return SimpleNamespace(settings=settings, encoder=encoder, frame=frame, amplitude=amplitude,
                           phase=phase, reference=reference)


def numpy_asm(field: np.ndarray, padded_hw: tuple[int, int], pitch_m: float, lam_m: float,
              z_m: float, cutoff_per_px: float) -> np.ndarray:
    """float64 angular spectrum of one colour: zero-padded at the bottom and right to
    `padded_hw`, the square aperture |fx|, |fy| < cutoff (cycles/px, [-c, c) as the product
    samples it), the transfer function exp(i 2 pi z (sqrt(1/lambda^2 - f^2) - 1/lambda)) (the
    carrier removed, as docs/physics.md defines it), cropped back to the top left. No band limit: at
    z = 6 mm on these grids it passes more than the aperture does."""
    hp, wp = padded_hw
    fy, fx = np.fft.fftfreq(hp)[:, None], np.fft.fftfreq(wp)[None, :]
    keep = (fx >= -cutoff_per_px) & (fx < cutoff_per_px) & (fy >= -cutoff_per_px) & (
        fy < cutoff_per_px)
    f2 = (fx**2 + fy**2) / pitch_m**2
    kernel = keep * np.exp(2j * math.pi * z_m * (np.sqrt(1 / lam_m**2 - f2) - 1 / lam_m))
    spectrum = np.fft.fft2(field.astype(np.complex128), s=padded_hw)
    return np.fft.ifft2(spectrum * kernel)[: field.shape[0], : field.shape[1]]


def relative_error(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def test_the_frame_is_the_whole_panel_finite_and_zero_coded_where_dark(panel):
    s, f = panel.settings, panel.frame
    assert s.window_hw == s.panel_hw == PANEL_HW
    assert f.region == Region(0, 0, *PANEL_HW, 0, 0)  # the margin is clipped by the panel
    assert f.grey.shape == (3, *PANEL_HW) and f.grey.dtype == np.uint8
    assert f.rgb.shape == (3, *PANEL_HW) and 0 <= f.rgb.min() and f.rgb.max() <= 1
    for out in (panel.amplitude, panel.phase):
        assert out.shape == (3, *PANEL_HW) and np.isfinite(out).all()
    assert f.rgb.max() > 0.5  # the scene is in view, not a black frame
    # Where the SLM-plane amplitude is below zero_below of the scale, the coder writes the
    # panel's zero pattern (the checkerboard the aperture blocks), in the panel's own parity.
    amp = panel.encoder.to_slm(panel.reference).abs().numpy()
    threshold = s.zero_below * s.amplitude_scale
    dark = amp < threshold * (1 - 1e-3)  # off the decision boundary by float32 rounding
    assert dark.mean() > 0.05
    assert np.array_equal(f.grey[dark], zero_pattern(s)[dark])
    assert max(f.clipped_fraction) < 0.01


@pytest.mark.parametrize("padding, padded_hw", [("auto", (1125, 1944)), ("2x", (2160, 3840))])
def test_the_full_panel_propagation_agrees_with_float64_numpy(panel, padding, padded_hw):
    """"auto" (the product's default, what the frame above ran) on all three colours; "2x"
    (optics.padding = "2x") on green alone: its grids are four times larger."""
    assert panel.settings.padding == "auto"
    s, ref = panel.settings, panel.reference
    if padding == "auto":
        encoder, colours = panel.encoder, (0, 1, 2)
    else:
        s = dataclasses.replace(s, padding=padding, wavelengths_m=s.wavelengths_m[1:2],
                                cutoff_per_px=s.cutoff_per_px[1:2],
                                phase_stroke_rad=s.phase_stroke_rad[1:2])
        encoder, colours, ref = Encoder(s), (0,), ref[1:2]
    (group,) = encoder.groups()  # one depth for all colours: one padded grid
    assert group.padded_hw == padded_hw
    with torch.no_grad():
        slm = encoder.to_slm(ref).numpy()
    for c in colours:
        want = numpy_asm(ref[c].numpy(), padded_hw, s.pitch_m, s.wavelengths_m[c],
                         s.colour_propagation_z_m[c], s.cutoff_per_px[c])
        assert relative_error(slm[c], want) < 1e-5, (padding, c)


def test_the_frame_is_the_coding_of_the_optics_cores_whole_panel_propagation(panel):
    """The encoder's reduced transforms and `reference_to_slm` (the window placed on the panel
    and propagated with `propagate`'s 2-D transforms) give the same field, and its coding is
    the frame, but for levels within float32 rounding of a decision boundary (one step,
    circularly: 255 and 0 are neighbours)."""
    s = panel.settings
    with torch.no_grad():
        whole = reference_to_slm(panel.reference, s.panel_hw, s.z0_m, s.pitch_m,
                                 s.wavelengths_m, aperture=s.aperture, padding=s.padding)
        assert relative_error(panel.encoder.to_slm(panel.reference).numpy(),
                              whole.numpy()) < 1e-5
    grey, _ = double_phase_grey(whole.to(torch.complex64), s.amplitude_scale, s.curves(),
                                sign=s.phase_sign, invert=s.grey_invert,
                                zero_below=s.zero_below)
    step = np.abs(grey.astype(int) - panel.frame.grey.astype(int))
    step = np.minimum(step, 256 - step)
    assert step.max() <= 1 and (step > 0).mean() < 1e-3


def test_the_window_is_any_size_up_to_the_panel_and_a_larger_training_size_is_refused():
    from nhfd.pipeline.settings import frame_window_hw

    meta = OnnxModel(MODEL).info  # trained at 512 x 288
    assert meta.train_size_hw == (288, 512)
    whole = Config.model_validate({"daemon": {"frames": {"size_px": [1920, 1080]}}})
    assert frame_window_hw(whole.daemon.frames, whole.slm, meta) == PANEL_HW
    default = Config()
    # empty: the training size
    assert frame_window_hw(default.daemon.frames, default.slm, meta) == (288, 512)
    small = Config.model_validate({"slm": {"width_px": 400, "height_px": 200}, "optics": {
        "hologram_width_px": 256, "hologram_height_px": 128}})
    with pytest.raises(ValueError, match=r"^frame window 512 x 288 \(the model's training size: "
                       r"daemon\.frames\.size_px is empty\) does not fit the panel 400 x 200 .*"
                       r"set daemon\.frames\.size_px to at most \[400, 200\]$"):
        frame_window_hw(small.daemon.frames, small.slm, meta)
