"""The wave-optics core: pure functions of tensors (no files, devices or globals).

Shapes are channel-first `[..., C, H, W]`, colours R, G, B with one wavelength each; units are SI
(metres, radians). Everything else in nhfd calls these; nothing re-implements them.
"""

from nhfd.optics import fft
from nhfd.optics.aperture import Aperture, aperture_mask, apply_aperture
from nhfd.optics.asm import propagate, transfer_function, transfer_function_z
from nhfd.optics.cache import KernelCache
from nhfd.optics.color import linear_to_srgb, srgb_to_amplitude, srgb_to_linear
from nhfd.optics.dpac import (
    DoublePhase,
    PhaseCurve,
    checkerboard,
    double_phase,
    double_phase_grey,
    grey_to_phase,
    phase_to_grey,
    wrap_phase,
)
from nhfd.optics.padding import PaddingPlan, next_fast_len, plan_padding
from nhfd.optics.quality import (
    Quality,
    focal_stack,
    focal_stack_quality,
    hologram_2d,
    quality_planes,
)
from nhfd.optics.refplane import (
    crop_window,
    place_window,
    reference_to_slm,
    slm_to_reference,
    window_offset,
)

__all__ = [
    "Aperture",
    "DoublePhase",
    "KernelCache",
    "PaddingPlan",
    "PhaseCurve",
    "Quality",
    "aperture_mask",
    "apply_aperture",
    "checkerboard",
    "crop_window",
    "double_phase",
    "double_phase_grey",
    "fft",
    "focal_stack",
    "focal_stack_quality",
    "grey_to_phase",
    "hologram_2d",
    "linear_to_srgb",
    "next_fast_len",
    "phase_to_grey",
    "place_window",
    "plan_padding",
    "propagate",
    "quality_planes",
    "reference_to_slm",
    "slm_to_reference",
    "srgb_to_amplitude",
    "srgb_to_linear",
    "transfer_function",
    "transfer_function_z",
    "window_offset",
    "wrap_phase",
]
