"""Wavefront inversion: light fields to complex holograms (docs/physics.md, "Wavefront inversion
(inverse STFT, overlap-add with hop 1)").

Pure functions of arrays and tensors (no files, devices or globals):

  mapping    the scene-level depth mapping: robust d_near / d_far over poses, a, b, the report
  sampling   per-colour hogel window W, STFT bins and slopes inside the aperture
  phase      phase heuristics (depth-aware default, zero, random) and a view's spectrum
  istft      the inverse STFT (hop 1, Hann, overlap-add) in the per-direction convolution form
  hologram   views -> [3, H, W] complex64 reference-plane field; aperture filtering
"""

from nhfd.holo.hologram import (
    ColourInverter,
    Hologram,
    band_limit,
    hologram_from_light_field,
    scene_hologram,
)
from nhfd.holo.istft import InverseSTFT, hann_window, modulated_window, patch_offsets
from nhfd.holo.mapping import depth_exaggeration, scene_depth_range, scene_mapping
from nhfd.holo.phase import (
    PHASE_MODES,
    PhaseMode,
    hologram_depth,
    sec_minus_one,
    srgb_amplitude,
    view_phase,
    view_spectrum,
)
from nhfd.holo.sampling import ColourSampling, colour_sampling, inside_aperture, sampling_report

__all__ = [
    "PHASE_MODES",
    "ColourInverter",
    "ColourSampling",
    "Hologram",
    "InverseSTFT",
    "PhaseMode",
    "band_limit",
    "colour_sampling",
    "depth_exaggeration",
    "hann_window",
    "hologram_depth",
    "hologram_from_light_field",
    "inside_aperture",
    "modulated_window",
    "patch_offsets",
    "sampling_report",
    "scene_depth_range",
    "scene_hologram",
    "scene_mapping",
    "sec_minus_one",
    "srgb_amplitude",
    "view_phase",
    "view_spectrum",
]
