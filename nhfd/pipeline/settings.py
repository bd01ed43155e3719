"""What a frame depends on besides the view, the scene and the network's weights: the frame
settings (optics of the model, the configured coding, the calibration), and the region of the
panel a frame changes (`Region`, a value of `nhfd.frame_message`: the daemon reads it too)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from nhfd import spec
from nhfd.calibration import Calibration, panel_coding
from nhfd.config import Config, FramesSettings, SLMSettings
from nhfd.frame_message import Region
from nhfd.model_info import ModelInfo
from nhfd.optics import Aperture
from nhfd.optics.refplane import margin_px, window_offset
from nhfd.spec import PhaseCurve


@dataclass(frozen=True)
class FrameSettings:
    """Everything a frame depends on besides the view, the scene and the network's weights."""

    panel_hw: tuple[int, int]
    window_hw: tuple[int, int]
    pitch_m: float
    wavelengths_m: tuple[float, ...]
    z0_m: float
    aperture_shape: str
    cutoff_per_px: tuple[float, ...]
    amplitude_scale: float
    zero_below: float
    phase_stroke_rad: tuple[float, ...]
    phase_sign: int = 1
    grey_invert: bool = False
    # Digital refocus: the reference plane is placed at z0 + refocus_m from the SLM (positive
    # moves the whole volume toward the viewer).
    refocus_m: float = 0.0
    padding: str = "auto"
    # Measured grey -> phase tables per colour (a calibration file); () = linear curves of
    # phase_stroke_rad.
    phase_tables_rad: tuple[tuple[float, ...], ...] = ()
    # Per-colour focus offsets (a calibration file; () = none): colour c's reference plane is
    # placed at z0 + refocus_m + colour_offset_m[c], where the relay's chromatic focal shift
    # makes the camera (or eye) see it at the same place as green's.
    colour_offset_m: tuple[float, ...] = ()
    # The illumination per colour (a calibration file; () = uniform): (1/e^2 intensity radius,
    # centre x, centre y) on the SLM plane, metres. The SLM-plane amplitude is divided by the
    # source's amplitude, relative to its value at the window's centre and at most
    # max_amplitude_gain (the dim edges of the beam cannot be lifted without limit: double-phase
    # coding clips amplitudes beyond amplitude_scale).
    source_profile: tuple[tuple[float, float, float], ...] = ()
    max_amplitude_gain: float = 2.0
    # Relay aberrations (a calibration file; () = none): Zernike coefficients for Noll
    # j = 5, 6, ... in radians at zernike_wavelength_m, pupil radius = the aperture's cutoff
    # (nhfd.optics.pupil.pupil_phase). Each colour's kernel carries the conjugate phase.
    zernike_rad: tuple[float, ...] = ()
    zernike_wavelength_m: float = 0.0

    @property
    def aperture(self) -> Aperture:
        """The Fourier aperture (shape, cutoff per colour in cycles/px)."""
        return Aperture(self.aperture_shape, tuple(self.cutoff_per_px))  # type: ignore[arg-type]

    @property
    def propagation_z_m(self) -> float:
        """The propagation from the reference plane to the SLM, m: -(z0 + refocus)."""
        return -(self.z0_m + self.refocus_m)

    @property
    def colour_propagation_z_m(self) -> tuple[float, ...]:
        """Each colour's propagation to the SLM: -(z0 + refocus + its focus offset)."""
        offsets = self.colour_offset_m or (0.0,) * len(self.wavelengths_m)
        return tuple(self.propagation_z_m - o for o in offsets)

    def curves(self) -> list[PhaseCurve]:
        """The phase curves in use per colour: the calibration's tables, else linear curves of
        `phase_stroke_rad`."""
        return spec.phase_curves(self.phase_stroke_rad, self.phase_tables_rad)


def frame_region(s: FrameSettings) -> Region:
    """The region of the panel a frame with settings `s` changes: the window plus the reach of
    the propagation kernel (`margin_px`), clipped to the panel, its corner even."""
    ph, pw = s.panel_hw
    wh, ww = s.window_hw
    top, left = window_offset(s.panel_hw, s.window_hw)
    reach_z = max(abs(z) for z in s.colour_propagation_z_m)
    m = margin_px(reach_z, s.pitch_m, s.wavelengths_m, s.aperture)
    r0, c0 = max(0, top - m), max(0, left - m)
    r0, c0 = r0 - r0 % 2, c0 - c0 % 2  # even: the checkerboard's parity is the panel's
    r1, c1 = min(ph, top + wh + m), min(pw, left + ww + m)
    return Region(r0, c0, r1 - r0, c1 - c0, top - r0, left - c0)


def zero_pattern(s: FrameSettings) -> np.ndarray:
    """The whole panel coding zero amplitude, through the same curves as frames
    (`nhfd.spec.zero_pattern`: the blank frame's and the coder's zero too)."""
    return spec.zero_pattern(s.panel_hw, s.curves(), s.phase_sign, s.grey_invert)


def frame_window_hw(frames: FramesSettings, slm: SLMSettings, info: ModelInfo
                    ) -> tuple[int, int]:
    """The frames' window (height, width) in pixels: `daemon.frames.size_px` [W, H], or the
    model's training size when that is empty; any size up to the panel (`slm.width_px` x
    `height_px`), the whole panel included (the frame worker then refuses a size the model was
    not checked at: `nhfd.models.sizes`)."""
    size = list(frames.size_px)
    if size:  # the configuration checked it fits the panel
        return int(size[1]), int(size[0])
    h, w = info.train_size_hw
    ph, pw = slm.height_px, slm.width_px
    if h > ph or w > pw:
        raise ValueError(f"frame window {w} x {h} (the model's training size: "
                         f"daemon.frames.size_px is empty) does not fit the panel {pw} x {ph} "
                         f"(slm.width_px x height_px); set daemon.frames.size_px to at most "
                         f"[{pw}, {ph}]")
    return h, w


def frame_settings(config: Config, info: ModelInfo, calibration: Calibration | None, *,
                   refocus_m: float = 0.0) -> FrameSettings:
    """The settings of frames for a model under a configuration and a calibration (None: the
    configured curves and sign; else its measured curves, sign, focus offsets, source profile
    and aberrations replace them; `nhfd.calibration.CalibrationStore` gives the configured
    one). The optics (z0, aperture, wavelengths, pitch) are the model's: `load_model` has
    already checked they match the configuration. The window is the model's training size
    unless `daemon.frames.size_px` says otherwise (the trained fx is kept either way).

    `config`: the whole configuration, because a frame's settings join four sections: `[slm]`
    (panel, phase stroke, sign, inversion), `[coding]` (`zero_below`), `[optics]` (`padding`)
    and `[daemon.frames]` (`size_px`)."""
    window_hw = frame_window_hw(config.daemon.frames, config.slm, info)
    s = config.slm
    _, sign, invert = panel_coding(s, calibration)
    base = FrameSettings(
        panel_hw=(s.height_px, s.width_px),
        window_hw=window_hw,
        pitch_m=info.pitch_m,
        wavelengths_m=info.wavelengths_m,
        z0_m=info.z0_m,
        aperture_shape=info.aperture_shape,
        cutoff_per_px=info.cutoff_per_px,
        amplitude_scale=info.amplitude_scale,
        zero_below=float(config.coding.zero_below),
        phase_stroke_rad=tuple(float(v) for v in s.phase_stroke_rad),
        phase_sign=sign,
        grey_invert=invert,
        refocus_m=float(refocus_m),
        padding=config.optics.padding,
    )
    return with_calibration(base, calibration)


def with_calibration(s: FrameSettings, cal: Calibration | None) -> FrameSettings:
    """`s` coded through a calibration (None: `s` itself): its measured phase curves and sign
    (as `panel_coding` rules), focus offsets, source profile and aberrations."""
    if cal is None:
        return s
    return replace(
        s,
        phase_tables_rad=cal.phase_tables_rad,
        phase_sign=int(cal.phase_sign),
        colour_offset_m=tuple(cal.refocus_m(c) for c in range(3)),
        source_profile=tuple((cal.source_waist_m[c], *cal.source_centre_m[c])  # type: ignore[misc]
                             for c in range(3)) if cal.source_waist_m else (),
        zernike_rad=cal.zernike_rad,
        zernike_wavelength_m=cal.zernike_wavelength_m,
    )
