"""Focal stacks of daemon-coded frames seen by the twin camera, and their PSNR against the
target: the acceptance measure of issue 8 at test size (small panel, few planes)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import torch

from nhfd.calib.sim import quick_sim_devices
from nhfd.calibration import Calibration
from nhfd.config import DeviceSettings
from nhfd.daemon.frame_link import PanelBuffer
from nhfd.device_settings import CameraSettings
from nhfd.drivers.simcamera import SimulatedCamera, TrueBench
from nhfd.optics import propagate
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.settings import FrameSettings

PANEL_HW = (128, 128)
WINDOW_HW = (64, 64)
# Planes of the stack, from the reference plane (m): the middle and either side of it.
PLANES_M = (-0.6e-3, 0.0, 0.6e-3)


def quick_devices(**camera: object) -> DeviceSettings:
    """The in-process simulated bench's quick devices (`quick_sim_devices`)."""
    return quick_sim_devices(**camera)


def target_field(settings: FrameSettings) -> torch.Tensor:
    """The reference-plane field [3, h, w] of a small 3-D scene: spots (sigma 1.2 px) at depths
    PLANES_M from the reference plane, band-limited by the aperture, and a dim smooth patch."""
    h, w = WINDOW_HW
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64) - (h - 1) / 2,
                            torch.arange(w, dtype=torch.float64) - (w - 1) / 2, indexing="ij")
    rng = np.random.default_rng(5)
    out = torch.zeros(3, h, w, dtype=torch.complex128)
    for z in PLANES_M:
        img = torch.zeros(h, w, dtype=torch.float64)
        for x, y in rng.uniform(-20, 20, (4, 2)):
            img += torch.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2**2))
        u = img.expand(3, h, w).to(torch.complex128)
        out += propagate(u, -z, settings.pitch_m, settings.wavelengths_m,
                         aperture=settings.aperture, padding="auto")
    return out


def target_stack(field: torch.Tensor, settings: FrameSettings) -> torch.Tensor:
    """|P(field; z)|^2 for z in PLANES_M: [D, 3, h, w] (what a perfect display shows)."""
    u = propagate(field, list(PLANES_M), settings.pitch_m, settings.wavelengths_m,
                  aperture=settings.aperture, padding="auto")
    return u.abs().square()


def panel_frame(settings: FrameSettings, field: torch.Tensor, amplitude: float
                ) -> np.ndarray:
    """The daemon's frame for a reference-plane field: [H, W, 3] uint8."""
    enc = Encoder(settings)
    with torch.no_grad():
        slm = enc.to_slm((field * amplitude).to(torch.complex64))
        grey, _ = enc.code(slm)
    panel = PanelBuffer(enc.zero).frame(enc.region.top, enc.region.left, grey)
    return np.ascontiguousarray(panel.transpose(1, 2, 0))


def small(settings: FrameSettings) -> FrameSettings:
    return dataclasses.replace(settings, panel_hw=PANEL_HW, window_hw=WINDOW_HW)


def stack_psnr(bench: TrueBench, frame: np.ndarray, stage_mm_for: Callable[[float], float],
               target: torch.Tensor, settings: FrameSettings) -> list[float]:
    """PSNR (dB) per colour of the twin camera's focal stack (noise-free irradiance, the stage
    moved by `stage_mm_for(z from the SLM)` for each plane) against the target mapped onto the
    sensor the same way, inside the window. Each colour's stack gets the one least-squares gain
    (exposure and laser power are free); normalised by the target's 99.5th percentile."""
    stage = [0.0]
    cam = SimulatedCamera(lambda: frame, lambda: (1.0, 1.0, 1.0), lambda: stage[0], bench,
                          CameraSettings(channels="mono"), roi=bench.roi_for_panel(PANEL_HW))
    full = torch.zeros(len(PLANES_M) * 3, *PANEL_HW, dtype=torch.float64)
    t, lft = ((PANEL_HW[0] - WINDOW_HW[0]) // 2, (PANEL_HW[1] - WINDOW_HW[1]) // 2)
    full[:, t : t + WINDOW_HW[0], lft : lft + WINDOW_HW[1]] = target.reshape(-1, *WINDOW_HW)
    tgt = cam.project_to_camera(full, settings.pitch_m).reshape(len(PLANES_M), 3,
                                                                 *cam.roi[2:])
    window = torch.zeros(1, *PANEL_HW, dtype=torch.float64)
    window[:, t : t + WINDOW_HW[0], lft : lft + WINDOW_HW[1]] = 1.0
    # The scene's pixels (docs/physics.md): inside the window, away from its edge.
    inside = cam.project_to_camera(window, settings.pitch_m)[0] > 0.999
    images = []
    for z in PLANES_M:
        stage[0] = stage_mm_for(settings.z0_m + settings.refocus_m + z)
        images.append(cam.optical_image().copy())
    seen = np.stack(images)  # [D, 3, h, w]
    out = []
    for c in range(3):
        x, y = seen[:, c][:, inside].ravel(), tgt[:, c][:, inside].ravel()
        gain = float(x @ y) / float(x @ x)
        peak = float(np.percentile(y, 99.5))
        mse = float(((gain * x - y) ** 2).mean()) / peak**2
        out.append(10 * math.log10(1 / mse))
    return out


def spot_field(settings: FrameSettings) -> torch.Tensor:
    """One tiny spot (sigma 0.7 px: the focus test's) in the window's centre, on the reference
    plane, band-limited by the aperture: [3, h, w]."""
    h, w = WINDOW_HW
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64) - (h - 1) / 2,
                            torch.arange(w, dtype=torch.float64) - (w - 1) / 2, indexing="ij")
    img = torch.exp(-(xx**2 + yy**2) / (2 * 0.7**2)).expand(3, h, w).to(torch.complex128)
    return propagate(img, 0.0, settings.pitch_m, settings.wavelengths_m,
                     aperture=settings.aperture, padding="auto")


def sharpest_dz(bench: TrueBench, frame: np.ndarray, stage_mm_for: Callable[[float], float],
                settings: FrameSettings, dzs_m: np.ndarray) -> list[float]:
    """Per colour, the depth from the reference plane (one of `dzs_m`) whose stage setting
    shows the spot's highest peak on the twin camera."""
    stage = [0.0]
    cam = SimulatedCamera(lambda: frame, lambda: (1.0, 1.0, 1.0), lambda: stage[0], bench,
                          CameraSettings(channels="mono"), roi=bench.roi_for_panel(PANEL_HW))
    peaks = []
    for dz in dzs_m:
        stage[0] = stage_mm_for(settings.z0_m + settings.refocus_m + float(dz))
        peaks.append(cam.optical_image().max(axis=(1, 2)))
    best = np.argmax(np.asarray(peaks), axis=0)
    return [float(dzs_m[k]) for k in best]


def amplitude_for(settings: FrameSettings, field: torch.Tensor) -> float:
    """A field scale whose SLM-plane amplitude peaks at 0.9 (double-phase codes up to 1)."""
    enc = Encoder(settings)
    with torch.no_grad():
        peak = float(enc.to_slm(field.to(torch.complex64)).abs().max())
    return 0.9 / peak


__all__ = ["PANEL_HW", "PLANES_M", "WINDOW_HW", "amplitude_for", "panel_frame",
           "sharpest_dz", "small", "spot_field", "stack_psnr", "target_field", "target_stack"]


def truth_calibration(bench: TrueBench, roi: tuple[int, int, int, int] | None = None, *,
                      illumination: bool = True) -> Calibration:
    """What a perfect fit of `bench` would give: its phase tables, focus mapping and offsets,
    geometry (the SLM centre's camera position on the region `roi`, [top, left, h, w]; None:
    no shift) and, with `illumination`, its source profile and relay aberration. For tests
    whose subject is not the fit: one that judges a learned part fits it from captures."""
    zero = (0.0, 0.0, 0.0)
    shift = (0.0, 0.0)
    if roi is not None:
        col, row = bench.slm_to_camera_px(0.0, 0.0)
        shift = (col - roi[1], row - roi[0])
    light = {} if not illumination else dict(
        source_waist_m=(bench.source_waist_m,) * 3, source_waist_std_m=zero,
        source_centre_m=(bench.source_offset_m,) * 3, source_centre_std_m=((0.0, 0.0),) * 3,
        zernike_rad=bench.zernike_rad, zernike_std_rad=(0.0,) * len(bench.zernike_rad),
        zernike_wavelength_m=bench.wavelengths_m[1])
    return Calibration(
        wavelengths_m=bench.wavelengths_m, pitch_m=bench.pitch_m, phase_sign=bench.phase_sign,
        phase_tables_rad=bench.phase_tables, phase_table_std_rad=zero,
        stage_scale=bench.stage_scale, stage_scale_std=0.0,
        stage_at_slm_mm=bench.stage_at_slm_mm, stage_at_slm_std_mm=0.0,
        z_offset_m=bench.z_offset_m, z_offset_std_m=zero, magnification=bench.magnification,
        magnification_std=0.0, rotation_deg=bench.rotation_deg, rotation_std_deg=0.0,
        mirror_x=bench.mirror_x, shift_px=shift, intensity=(1.0, 1.0, 1.0),
        intensity_std=zero, fitted_on={"camera_pitch_m": bench.camera_pitch_m}, **light)
