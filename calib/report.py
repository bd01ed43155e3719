"""`nhfd calib report DIR`: PNGs of a capture against its fit.

- `geometry.png`: the in-focus dots (max over green's fine sweep), detected centroids and where
  the fitted geometry puts every dot of the layout.
- `response.png`: the fitted grey -> phase curves per colour.
- `slices_R.png`, `slices_G.png`, `slices_B.png`: captured vs simulated slices of each colour's
  fine sweep at three stage positions (near, at and beyond its focus) and the residual;
  the simulation is the twin camera (`nhfd.drivers.simcamera`) configured with the *fitted*
  parameters only (no zero order, gap, noise or crosstalk: what the fit does not model shows up
  in the residual), scaled to the capture by least squares.

Of a folder `nhfd calib learn` wrote (`write_learned_report`), the learned bench against the
parametric one on what the fit never saw (`nhfd.calib.learn.fidelity`):

- `fidelity.png`: held-out patterns at a training plane and patterns at the held-out plane,
  captured, each model's prediction and each model's residual, in false colour per laser;
- `fidelity_psnr.png` and `fidelity.json`: PSNR per colour and plane, the two models side by
  side.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nhfd.calibration import Calibration
from nhfd.device_settings import CameraSettings
from nhfd.drivers.simcamera import SimulatedCamera, TrueBench

from .data import default_camera_pitch_m, load_capture
from .fit import _fine_stack, fit_capture
from .geometry import Geometry, detect_dots
from .learn import RECORD_NAME, Fidelity, fidelity
from .patterns import dot_layout

# The rows of fidelity.png: (pattern, plane) pairs, at most this many.
FIDELITY_ROWS = 4
# The fidelity pictures show at most this many pixels a side, cut from the window's centre: at
# 512 x 288 a whole window drawn 3 inches wide hides the pixel-scale structure the learned parts
# model (crosstalk, the camera's pixels).
FIDELITY_CROP_PX = 160


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


def is_learn_folder(root: Path | str) -> bool:
    """Whether `root` is a folder `nhfd calib learn` wrote (not a capture)."""
    return (Path(root) / RECORD_NAME).is_file()


def _rgb(image: np.ndarray, peak: np.ndarray) -> np.ndarray:
    """`[C, h, w]` -> `[h, w, 3]` in 0..1, each laser's colour in its own channel."""
    return np.clip(np.moveaxis(image / peak[:, None, None], 0, -1), 0.0, 1.0)


def _fidelity_rows(fid: Fidelity) -> list[tuple[int, int]]:
    """(pattern, plane) pairs: held-out patterns at the first and last training planes, then a
    held-out and a training pattern at the held-out plane."""
    d, hp = len(fid.plan.planes_m), fid.plan.held_out_plane
    train_planes = [i for i in range(d) if i != hp]
    others = [i for i in range(fid.captured.shape[0]) if i not in set(fid.held.tolist())]
    rows = [(int(fid.held[0]), train_planes[0]), (int(fid.held[-1]), train_planes[-1]),
            (int(fid.held[len(fid.held) // 2]), hp)]
    if others:
        rows.append((others[0], hp))
    return rows[:FIDELITY_ROWS]


def write_learned_report(root: Path | str, out: Path | str | None = None) -> list[Path]:
    """Write the learned bench's fidelity report (the module's docstring) of the folder `root`
    into `out` (default `root/report`); returns the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fid = fidelity(root)
    out = Path(out or Path(root) / "report")
    out.mkdir(parents=True, exist_ok=True)
    mask = fid.mask
    # One scale per laser for every picture: the captures' 99.5th percentile inside the window.
    peak = np.array([np.percentile(fid.captured[:, :, c][..., mask], 99.5) or 1.0
                     for c in range(3)])
    rows = _fidelity_rows(fid)
    h, w = mask.shape
    ch, cw = min(h, FIDELITY_CROP_PX), min(w, FIDELITY_CROP_PX)
    crop = (slice((h - ch) // 2, (h - ch) // 2 + ch), slice((w - cw) // 2, (w - cw) // 2 + cw))
    # Rows as tall as the crop's aspect: 3.1 in for a square one.
    fig, axes = plt.subplots(len(rows), 5, figsize=(15, (0.5 + 2.6 * ch / cw) * len(rows)),
                             squeeze=False)
    for r, (n, i) in enumerate(rows):
        cap = fid.captured[n, i]
        res = {k: np.abs(getattr(fid, k)[n, i] - cap) for k in ("parametric", "learned")}
        worst = max(float(v[:, mask].max()) for v in res.values()) or 1.0
        where = "held-out plane" if i == fid.plan.held_out_plane else "training plane"
        cells = [(_rgb(cap, peak), f"captured: pattern {n}, {where} "
                  f"{fid.plan.planes_m[i] * 1e3:+.2f} mm")]
        for k in ("parametric", "learned"):
            cells.append((_rgb(getattr(fid, k)[n, i], peak), f"{k} bench model"))
        for k in ("parametric", "learned"):
            err = float(np.mean(res[k][:, mask] ** 2 / peak[:, None] ** 2))
            cells.append((_rgb(res[k], np.full(3, worst)),
                          f"|{k} - captured|, {-10 * np.log10(max(err, 1e-12)):.1f} dB"))
        for c, (img, title) in enumerate(cells):
            axes[r, c].imshow(img[crop])
            axes[r, c].set_title(title, fontsize=8)
            axes[r, c].axis("off")
    cut = "" if (ch, cw) == (h, w) else f"; the central {cw} x {ch} px of the {w} x {h} window"
    fig.suptitle("the learned bench against the parametric one, on captures the fit never saw\n"
                 f"(residuals on one scale per row; PSNR over the whole window{cut})",
                 fontsize=10)
    fig.tight_layout()
    written = [out / "fidelity.png"]
    fig.savefig(written[0], dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 4))
    labels = [f"{row['plane_m'] * 1e3:+.2f} mm{' (held out)' if row['held_out'] else ''}"
              for row in fid.per_plane]
    x = np.arange(len(labels))
    for c, colour in enumerate("rgb"):
        for k, (model, hatch) in enumerate((("parametric", "//"), ("learned", ""))):
            ax.bar(x + (2 * c + k - 2.5) * 0.13, [row[model][c] for row in fid.per_plane], 0.13,
                   color=colour, alpha=0.45 if model == "parametric" else 0.9, hatch=hatch,
                   label=f"{'RGB'[c]} {model}")
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel("PSNR against the captures (dB)")
    ax.set_title("per colour and plane: held-out patterns at the training planes, every "
                 "pattern at the held-out one", fontsize=9)
    # Headroom above the tallest bar keeps the legend off the bars.
    ax.set_ylim(0, 1.25 * max(max(row["learned"] + row["parametric"]) for row in fid.per_plane))
    ax.legend(fontsize=7, ncol=3, loc="upper center")
    fig.tight_layout()
    written.append(out / "fidelity_psnr.png")
    fig.savefig(written[-1], dpi=90)
    plt.close(fig)
    written.append(out / "fidelity.json")
    written[-1].write_text(json.dumps(fid.to_json(), indent=2))
    return written
