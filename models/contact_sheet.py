"""The contact sheet of a model build: refocusing on held-out views, made visible.

For each of a few held-out views, two rows (the target hologram, then the model's), each:
the view with its nearest and farthest quarter of content outlined; the whole frame focused on
the near content, then on the far content; then the near region and the far region enlarged,
each at both focuses. All crops are the same size and enlarged by the same factor, so near
sharp / far blurred and the reverse sit side by side at the same scale. Focus planes are the
regions' median mapped depth (the hologram depth of the content, `nhfd.models.inputs`); both
rows of a view share one brightness scale (the target's 99.5th percentile).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from nhfd.models.data import HoloData
from nhfd.models.export import OnnxModel
from nhfd.models.inputs import ALPHA_CONTENT
from nhfd.optics import Aperture, KernelCache, focal_stack, linear_to_srgb

# Content quantiles that define the near and far regions (by mapped depth: larger is nearer).
REGION_QUANTILE = 0.25
# Crop side as a fraction of the view's shorter side; figure layout (inches, dots per inch).
CROP_FRACTION = 0.3
COLUMNS = ("view", "focus near", "focus far", "near region\nfocus near",
           "near region\nfocus far", "far region\nfocus near", "far region\nfocus far")
PANEL_IN, LABEL_IN, DPI = 1.9, 0.75, 100
PLANE_STEP_M = 1e-4  # focus planes rounded to 0.1 mm (kernels reused)


def sheet_size_px(n_views: int, size_hw: tuple[int, int]) -> tuple[int, int]:
    """(width, height) in pixels of the sheet for `n_views` views of `size_hw`."""
    h, w = size_hw
    width_in = PANEL_IN * len(COLUMNS)
    row_in = PANEL_IN * max(h / w, 1.0) * 0.75 + 0.15
    return round(width_in * DPI), round((2 * n_views * row_in + LABEL_IN) * DPI)


def _regions(zh: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    content = np.isfinite(zh) & (alpha >= ALPHA_CONTENT)
    if content.sum() < 16:
        return None
    lo, hi = np.quantile(zh[content], [REGION_QUANTILE, 1 - REGION_QUANTILE])
    return content & (zh >= hi), content & (zh <= lo)


def _box(region: np.ndarray, side: int) -> tuple[int, int]:
    """Top-left of a `side` square around the region pixel nearest the region's centroid (a
    ring's centroid can lie in its hole), kept inside the frame."""
    ys, xs = np.nonzero(region)
    cy, cx = ys.mean(), xs.mean()
    k = int(np.argmin((ys - cy) ** 2 + (xs - cx) ** 2))
    h, w = region.shape
    top = int(np.clip(ys[k] - side // 2, 0, max(0, h - side)))
    left = int(np.clip(xs[k] - side // 2, 0, max(0, w - side)))
    return top, left


def _pick_views(data: HoloData, n: int) -> list[tuple[str, int]]:
    """Up to `n` held-out views, alternating interpolation and extrapolation."""
    lists = [[(s, j) for j in range(len(data.splits[s]))] for s in ("interp", "extrap")
             if s in data.splits]  # fmt: skip
    out: list[tuple[str, int]] = []
    while len(out) < n and any(lists):
        for lst in lists:
            if lst and len(out) < n:
                out.append(lst.pop(0))
    return out


def contact_sheet(model_path: str | Path, data_dir: str | Path, out_png: str | Path, *,
                  n_views: int = 3) -> dict:  # fmt: skip
    """Write the sheet (PNG, atomically) for `n_views` held-out views; returns what it shows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    data = HoloData(data_dir, splits=("interp", "extrap"),
                    max_views={"interp": n_views, "extrap": n_views})  # fmt: skip
    model = OnnxModel(model_path)
    m = data.manifest["settings"]
    pitch, lams = float(m["pitch_m"]), [float(v) for v in m["wavelengths_m"]]
    ap = Aperture(m["aperture_shape"], tuple(m["cutoff_per_px"]))
    cache = KernelCache()
    picks = _pick_views(data, n_views)
    h, w = data.size_hw
    side = max(8, int(CROP_FRACTION * min(h, w)))
    size = sheet_size_px(len(picks), (h, w))
    fig = plt.figure(figsize=(size[0] / DPI, size[1] / DPI), dpi=DPI)
    rows = 2 * len(picks)
    top_frac = 1 - LABEL_IN * DPI / size[1]
    grid = fig.add_gridspec(rows, len(COLUMNS), left=0.08, right=0.995, bottom=0.01,
                            top=top_frac, wspace=0.04, hspace=0.12)  # fmt: skip
    shown = []
    for v, (split, j) in enumerate(picks):
        s = data.splits[split]
        index = s.indices[j]
        zh, alpha = s.zh[j].numpy(), s.alpha[j].numpy()
        regions = _regions(zh, alpha)
        if regions is None:
            continue
        near, far = regions
        z_near = round(float(np.median(zh[near])) / PLANE_STEP_M) * PLANE_STEP_M
        z_far = round(float(np.median(zh[far])) / PLANE_STEP_M) * PLANE_STEP_M
        amp, phase = model(s.inputs(model.inputs, j).numpy())
        pred = torch.polar(torch.from_numpy(amp), torch.from_numpy(phase))
        stacks = focal_stack(torch.stack([s.field[j], pred]).to(torch.complex64),
                             [z_near, z_far], pitch, lams, ap, cache=cache)  # fmt: skip
        scale = float(torch.quantile(stacks[0].flatten()[::7].double(), 0.995)) or 1.0
        boxes = {"near": _box(near, side), "far": _box(far, side)}
        rgb = s.rgb[j].permute(1, 2, 0).clamp(0, 1).numpy()
        for r, name in enumerate(("target", "model")):
            img = linear_to_srgb((stacks[r] / scale).clamp(0, 1)).permute(0, 2, 3, 1).numpy()
            panels = [rgb, img[0], img[1]]
            for region in ("near", "far"):
                top, left = boxes[region]
                for k in (0, 1):
                    panels.append(img[k][top:top + side, left:left + side])
            for c, panel in enumerate(panels):
                ax = fig.add_subplot(grid[2 * v + r, c])
                ax.imshow(panel, interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                if c == 0:
                    for region, colour in (("near", "#00e5ff"), ("far", "#ff3df5")):
                        top, left = boxes[region]
                        ax.add_patch(Rectangle((left - 0.5, top - 0.5), side, side, fill=False,
                                               ec=colour, lw=1.0))  # fmt: skip
                if c >= 3:
                    colour = "#00e5ff" if c < 5 else "#ff3df5"
                    for spine in ax.spines.values():
                        spine.set_edgecolor(colour)
                        spine.set_linewidth(2)
                if c == 0:
                    planes = (f"\nnear {z_near * 1e3:+.1f}, far {z_far * 1e3:+.1f} mm"
                              if r == 0 else "")
                    ax.set_ylabel(f"{split} #{index}\n{name}{planes}", fontsize=7)
                if v == 0 and r == 0:
                    ax.set_title(COLUMNS[c], fontsize=8)
        shown.append({"split": split, "index": int(index), "near_focus_mm": z_near * 1e3,
                      "far_focus_mm": z_far * 1e3, "crop_px": side,
                      "near_box": list(boxes["near"]), "far_box": list(boxes["far"])})
    fig.suptitle("held-out views: the hologram focused on the near content (cyan), then on "
                 "the far content (magenta); crops at the same enlargement", fontsize=9,
                 y=1 - 0.05 * DPI / size[1], va="top")  # fmt: skip
    out_png = Path(out_png)
    tmp = out_png.with_name(out_png.stem + ".tmp.png")
    fig.savefig(tmp, dpi=DPI)
    plt.close(fig)
    tmp.replace(out_png)
    return {"path": out_png.name, "size_px": list(size), "views": shown,
            "planes_mm": sorted({round(x[k], 1) for x in shown
                                 for k in ("near_focus_mm", "far_focus_mm")})}  # fmt: skip
