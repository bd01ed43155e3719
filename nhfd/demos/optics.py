"""The optics demo: a three-depth test target through the whole display chain.

Three words sit at the near end, the reference plane and the far end of the hologram volume. Their
complex field on the reference plane is taken to the SLM (-z0), double-phase coded with a fixed
amplitude scale, quantised to grey levels through the configured phase curves, decoded as the
panel would show it, and seen through the Fourier aperture at planes across the volume. The
contact sheet shows the ideal complex hologram's focal stack above what the phase-only display
shows; each word is sharp at its own depth in both rows.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nhfd.config import Config
from nhfd.optics import (
    Aperture,
    KernelCache,
    PhaseCurve,
    apply_aperture,
    crop_window,
    double_phase,
    focal_stack,
    focal_stack_quality,
    grey_to_phase,
    linear_to_srgb,
    phase_to_grey,
    propagate,
    quality_planes,
    reference_to_slm,
    slm_to_reference,
)

WORDS = (("NEAR", (1.0, 0.55, 0.15)), ("MID", (1.0, 1.0, 1.0)), ("FAR", (0.2, 0.75, 1.0)))
AMPLITUDE_PERCENTILE = 99.5
# The words fill this central part of the window (rows, cols); the contact sheet shows it.
TARGET_HW = (216, 256)
# A smooth random phase, band-limited well inside the aperture, spreads each point over the
# aperture's cone (so defocus blurs) without speckle at focus (the field stays in band).
PHASE_CUTOFF_PER_PX = 0.1
SEED = 7


@dataclass(frozen=True)
class DemoResult:
    planes_m: tuple[float, ...]
    word_depths_m: tuple[float, ...]
    word_rows: tuple[slice, ...]
    target_stack: torch.Tensor  # [D, 3, h, w] linear intensity in the window
    shown_stack: torch.Tensor  # [D, 3, h, w]
    slm_grey: torch.Tensor  # [3, H, W] uint8
    clipped_fraction: tuple[float, ...]
    psnr_db: float
    timings_s: dict[str, float]


def target_box(window_hw: tuple[int, int]) -> tuple[slice, slice]:
    """Rows and columns of the window that the words occupy (centred)."""
    h, w = min(TARGET_HW[0], window_hw[0]), min(TARGET_HW[1], window_hw[1])
    top, left = (window_hw[0] - h) // 2, (window_hw[1] - w) // 2
    return slice(top, top + h), slice(left, left + w)


def text_target(window_hw: tuple[int, int]) -> tuple[list[torch.Tensor], tuple[slice, ...]]:
    """One linear-intensity image `[3, h, w]` per word, each in its own horizontal band of the
    target box; returns the images and each word's rows."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    box_r, box_c = target_box(window_hw)
    band = (box_r.stop - box_r.start) // len(WORDS)
    width = box_c.stop - box_c.start
    images, rows = [], []
    for i, (word, colour) in enumerate(WORDS):
        fig = Figure(figsize=(width / 100, band / 100), dpi=100)
        fig.text(0.5, 0.5, word, ha="center", va="center", fontsize=band * 0.36,
                 family="DejaVu Sans")
        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        ink = 1.0 - np.asarray(canvas.buffer_rgba())[..., 0].astype(np.float32) / 255.0
        img = torch.zeros(3, *window_hw)
        r0 = box_r.start + i * band
        img[:, r0 : r0 + ink.shape[0], box_c.start : box_c.start + ink.shape[1]] = (
            torch.tensor(colour)[:, None, None] * torch.from_numpy(ink)[None]
        )
        images.append(img)
        rows.append(slice(r0, r0 + band))
    return images, tuple(rows)


def smooth_phase(shape_hw: tuple[int, int], seed: int) -> torch.Tensor:
    """A random phase `[h, w]` whose phasor is band-limited to `PHASE_CUTOFF_PER_PX`."""
    gen = torch.Generator().manual_seed(seed)
    noise = torch.randn(1, *shape_hw, dtype=torch.complex64, generator=gen)
    smooth = apply_aperture(noise, Aperture("square", (PHASE_CUTOFF_PER_PX,)))
    return torch.angle(smooth[0])


def run_demo(cfg: Config) -> DemoResult:
    """The three-word target through the whole display chain (see the module docstring): to the
    SLM, double-phase coding to grey levels, back through the panel's phase curves to the
    volume, with the focal stacks of the target and of what is shown.

    `cfg`: the whole configuration, because the chain spans three sections: `[optics]`
    (wavelengths, window, z0, volume, aperture, padding, precision, kernel cache), `[slm]`
    (panel, pitch, phase stroke, sign, inversion) and `[coding]` (antialiasing, `zero_below`)."""
    o, s = cfg.optics, cfg.slm
    lams, pitch = o.wavelengths_m, s.pitch_m
    aperture = Aperture(o.aperture.shape, tuple(o.aperture.cutoff_per_px))
    window_hw = (o.hologram_height_px, o.hologram_width_px)
    panel_hw = (s.height_px, s.width_px)
    z_min, z_max = o.volume_m
    word_depths = (z_max, 0.5 * (z_min + z_max), z_min)
    cache = KernelCache(o.kernel_cache_mb * 2**20)
    kw = dict(aperture=aperture, padding=o.padding, cache=cache)
    dtype = torch.complex128 if o.precision == "float64" else torch.complex64
    t: dict[str, float] = {}

    t0 = time.perf_counter()
    images, rows = text_target(window_hw)
    reference = sum(
        propagate(torch.polar(torch.sqrt(img), smooth_phase(window_hw, SEED + i)).to(dtype), -z,
                  pitch, lams, **kw)
        for i, (img, z) in enumerate(zip(images, word_depths, strict=True))
    )
    t["target"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    slm_field = reference_to_slm(reference, panel_hw, o.z0_m, pitch, lams, **kw)
    t["to_slm"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # The percentile is taken over the content (amplitude above 1% of the peak): over the whole,
    # mostly empty panel it would land inside the content and clip a large part of it.
    amp = slm_field.abs().flatten()
    content = amp[amp > 0.01 * amp.max()]
    scale = float(torch.quantile(content[:: max(1, content.numel() // 4_000_000)],
                                 AMPLITUDE_PERCENTILE / 100))
    coded = double_phase(slm_field, scale, antialias=aperture if cfg.coding.antialias else None,
                         zero_below=cfg.coding.zero_below)
    curves = [PhaseCurve.linear(r) for r in s.phase_stroke_rad]
    grey = phase_to_grey(coded.phase_rad, curves, sign=s.phase_sign, invert=s.grey_invert)
    t["coding"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    shown_phase = grey_to_phase(grey, curves, sign=s.phase_sign, invert=s.grey_invert)
    panel = torch.polar(torch.ones_like(shown_phase), shown_phase)
    seen = crop_window(slm_to_reference(panel, o.z0_m, pitch, lams, **kw), window_hw) * scale
    planes = quality_planes(o.volume_m, 5)
    shown_stack = focal_stack(seen, planes, pitch, lams, aperture, padding=o.padding, cache=cache)
    target_stack = focal_stack(reference, planes, pitch, lams, aperture, padding=o.padding,
                               cache=cache)
    t["display_and_view"] = time.perf_counter() - t0
    quality = focal_stack_quality(seen, reference, planes_m=planes, pitch_m=pitch,
                                  wavelengths_m=lams, aperture=aperture, padding=o.padding,
                                  cache=cache)
    return DemoResult(
        planes_m=planes, word_depths_m=word_depths, word_rows=rows,
        target_stack=target_stack, shown_stack=shown_stack, slm_grey=grey,
        clipped_fraction=tuple(float(c) for c in coded.clipped_fraction),
        psnr_db=quality.psnr_db, timings_s=t,
    )


def sharpness(image: torch.Tensor) -> float:
    """Normalised gradient energy of a `[C, h, w]` intensity image (scale-free)."""
    gy, gx = image.diff(dim=-2), image.diff(dim=-1)
    return float((gy.square().sum() + gx.square().sum()) / image.square().sum().clamp(min=1e-30))


def contact_sheet(result: DemoResult, path: Path) -> None:
    """Two rows (ideal complex hologram, phase-only display) by the focal planes, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(result.planes_m)
    box_r, box_c = target_box(tuple(result.target_stack.shape[-2:]))
    h, w = box_r.stop - box_r.start, box_c.stop - box_c.start
    fig, axes = plt.subplots(2, n, figsize=(2.6 * n, 2 * 2.6 * h / w + 0.9), squeeze=False)
    for row, (label, stack) in enumerate(
        (("complex hologram", result.target_stack), ("phase-only display", result.shown_stack))
    ):
        norm = float(torch.quantile(stack.flatten()[::5], 0.999)) or 1.0
        for col, z in enumerate(result.planes_m):
            img = linear_to_srgb(stack[col][:, box_r, box_c] / norm).permute(1, 2, 0).numpy()
            ax = axes[row][col]
            ax.imshow(img, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"z = {z * 1e3:+.1f} mm", fontsize=9)
            if col == 0:
                ax.set_ylabel(label, fontsize=9)
    fig.suptitle("Focal stack across the hologram volume: NEAR, MID and FAR each focus at "
                 "their own depth", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
