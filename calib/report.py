"""`nhfd calib report DIR`: PNGs of a capture against its fit.

- `geometry.png`: the in-focus dots (max over green's fine sweep), detected centroids and where
  the fitted geometry puts every dot of the layout.
- `response.png`: the fitted grey -> phase curves per colour.
- `slices_R.png`, `slices_G.png`, `slices_B.png`: captured vs simulated slices of each colour's
  fine sweep at three stage positions (near, at and beyond its focus) and the residual;
  the simulation is the twin camera (`nhfd.drivers.simcamera`) configured with the *fitted*
  parameters only (no zero order, gap, noise or crosstalk: what the fit does not model shows up
  in the residual), scaled to the capture by least squares.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nhfd.calibration import Calibration
from nhfd.device_settings import CameraSettings
from nhfd.drivers.simcamera import SimulatedCamera, TrueBench

from .data import default_camera_pitch_m, load_capture
from .fit import _fine_stack, fit_capture
from .geometry import Geometry, detect_dots
from .patterns import dot_layout


def simulate(cal: Calibration, frame: np.ndarray, stage_mm: float, colour: int,
             image_hw: tuple[int, int]) -> np.ndarray:
    """The fitted bench's noise-free image of `frame` ([H, W, 3] uint8) at a stage reading."""

    pitch = float(cal.fitted_on.get("camera_pitch_m") or default_camera_pitch_m())
    h, w = image_hw
    tx, ty = cal.shift_px
    bench = TrueBench(
        phase_tables_rad=cal.phase_tables_rad, phase_sign=cal.phase_sign, fill_factor=1.0,
        zero_order_fraction=0.0, crosstalk_sigma_m=0.0, oversample=1,
        source_waist_m=1.0, source_offset_m=(0.0, 0.0), magnification=cal.magnification,
        rotation_deg=cal.rotation_deg, mirror_x=cal.mirror_x,
        shift_m=((tx - (w - 1) / 2) * pitch, (ty - (h - 1) / 2) * pitch),
        stage_at_slm_mm=0.0, z_offset_m=(0.0, 0.0, 0.0), camera_pitch_m=pitch,
        sensor_hw_px=(h, w), wavelengths_m=cal.wavelengths_m, pitch_m=cal.pitch_m)
    z = (stage_mm - cal.stage_at_slm_mm) * 1e-3 * cal.stage_scale + cal.z_offset_m[colour]
    cam = SimulatedCamera(lambda: frame, lambda: (1.0, 1.0, 1.0),
                          lambda: bench.stage_mm_for(z, colour), bench,
                          CameraSettings(channels="mono"))
    lit = [c == colour for c in range(3)]
    return cam.optical_image(lit)[colour]


def write_report(root: Path | str, cal: Calibration | None = None,
                 out: Path | str | None = None) -> list[Path]:
    """Write the report's PNGs (the module's docstring) of the capture in `root` against `cal`
    (default: fitted now) into `out` (default `root/report`); returns the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = load_capture(root)
    cal = cal or fit_capture(root)
    out = Path(out or Path(root) / "report")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    spec = data.spec
    lay = dot_layout(spec)
    _, stack = _fine_stack(data, 1)
    pitch = float(cal.fitted_on.get("camera_pitch_m") or default_camera_pitch_m())

    # Geometry.

    geo = Geometry(cal.magnification / pitch, cal.rotation_deg, cal.mirror_x, cal.shift_px,
                   0.0, 0, 0.0, 0.0)
    mx = stack.max(axis=0)
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.imshow(mx, cmap="gray")
    det = detect_dots(mx)
    pred = geo.to_camera(lay.xy_m)
    ax.plot(det[:, 0], det[:, 1], "r+", label="detected")
    ax.plot(pred[:, 0], pred[:, 1], "co", mfc="none", label="fitted geometry")
    ax.set_title(f"M = {cal.magnification:.4f}, rotation {cal.rotation_deg:.2f} deg, "
                 f"mirror {cal.mirror_x}")
    ax.legend(loc="lower right")
    fig.savefig(out / "geometry.png", dpi=100)
    plt.close(fig)
    written.append(out / "geometry.png")

    # Response curves.
    fig, ax = plt.subplots(figsize=(6, 4))
    for c, colour in enumerate("rgb"):
        ax.plot(cal.phase_tables_rad[c], colour, label=f"{'RGB'[c]} fitted")
    ax.set_xlabel("grey level")
    ax.set_ylabel("phase (rad)")
    ax.legend()
    fig.savefig(out / "response.png", dpi=100)
    plt.close(fig)
    written.append(out / "response.png")

    # Captured vs simulated slices, per colour.
    frames = data.manifest["frames"]
    frame = np.load(data.root / frames.get("dots_fine", frames["dots"]))
    for colour, name in enumerate("RGB"):
        stages, stack = _fine_stack(data, colour)
        picks = [0, len(stages) // 2, len(stages) - 1]
        fig, axes = plt.subplots(3, 3, figsize=(10, 10))
        for row, k in enumerate(picks):
            sim = simulate(cal, frame, float(stages[k]), colour, stack[k].shape)
            scale = float((sim * stack[k]).sum() / max((sim * sim).sum(), 1e-30))
            sim = sim * scale
            residual = stack[k] - sim
            worst = float(np.abs(residual).max()) or 1.0
            for col, (img, title) in enumerate(((stack[k], "captured"), (sim, "simulated"),
                                                (residual, "residual"))):
                ax = axes[row, col]
                if col < 2:
                    ax.imshow(img, cmap="gray")
                else:  # symmetric, so that zero is white and the sign reads at a glance
                    shown = ax.imshow(img, cmap="RdBu", vmin=-worst, vmax=worst)
                    fig.colorbar(shown, ax=ax, fraction=0.046)
                ax.set_title(f"{name} {title}, stage {stages[k]:.3f} mm", fontsize=8)
                ax.axis("off")
        path = out / f"slices_{name}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written
