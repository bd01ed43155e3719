"""The wave-optics core: pure functions of tensors (no files, devices or globals).

Shapes are channel-first `[..., C, H, W]`, colours R, G, B with one wavelength each; units are SI
(metres, radians). Everything else in nhfd calls these; nothing re-implements them.

  asm       band-limited angular spectrum propagation and its kernels
  aperture  the relay's Fourier aperture (square or circular iris)
  padding   how much to zero-pad before a propagation (to 5-smooth FFT sizes)
  dpac      double-phase amplitude coding and the grey <-> phase curves (numba's fused
            pass, `double_phase_grey`, and its torch twin for GPUs, `device_grey`)
  refplane  the window on the reference plane <-> the panel on the SLM plane
  region    a window's propagation to the region of the panel around it (the frame pipeline's)
  pupil     the relay's pupil phase (Zernike aberrations) on the Fourier plane
  quality   focal stacks and their quality measures (PSNR, SSIM, speckle contrast)
  camera_grid  the camera's view of the SLM plane: the calibrated similarity, and camera images
            resampled on the SLM's pixel grid
  color     sRGB <-> linear <-> amplitude
  cache     kernels kept between calls, by key
  fft       FFTs checked once against a known answer before they are trusted
"""

from nhfd.optics import fft
from nhfd.optics.aperture import Aperture, aperture_mask, apply_aperture
from nhfd.optics.asm import propagate, transfer_function, transfer_function_z
from nhfd.optics.cache import KernelCache
from nhfd.optics.color import linear_to_srgb, srgb_to_amplitude, srgb_to_linear
from nhfd.optics.dpac import (
    DeviceCurves,
    DoublePhase,
    PhaseCurve,
    checkerboard,
    device_curves,
    device_grey,
    double_phase,
    double_phase_grey,
    grey_to_phase,
    phase_to_grey,
    wrap_phase,
)
from nhfd.optics.padding import PaddingPlan, next_fast_len, plan_padding
from nhfd.optics.pupil import pupil_phase, zernike
from nhfd.optics.quality import (
    Quality,
    colour_gains,
    focal_stack,
    focal_stack_quality,
    hologram_2d,
    quality_planes,
    speckle_contrast,
    stack_quality,
)
from nhfd.optics.refplane import (
    crop_window,
    place_window,
    reference_to_slm,
    slm_to_reference,
    window_offset,
)
from nhfd.optics.region import RegionPropagator, region_propagators

__all__ = [
    "Aperture",
    "DeviceCurves",
    "DoublePhase",
    "KernelCache",
    "PaddingPlan",
    "PhaseCurve",
    "Quality",
    "RegionPropagator",
    "aperture_mask",
    "apply_aperture",
    "checkerboard",
    "colour_gains",
    "crop_window",
    "device_curves",
    "device_grey",
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
    "pupil_phase",
    "quality_planes",
    "reference_to_slm",
    "region_propagators",
    "slm_to_reference",
    "speckle_contrast",
    "srgb_to_amplitude",
    "srgb_to_linear",
    "stack_quality",
    "transfer_function",
    "transfer_function_z",
    "window_offset",
    "wrap_phase",
    "zernike",
]
