"""`nhfd demo`: the daemon on the simulated bench, driven as a user drives it.

Starts `nhfd serve`'s daemon (in this process, its control loop on a thread; the frame worker is
its own spawned process) with the shipped model and the donut scene (or the user's: `--model`,
`--scene`, checked first by `check_model_and_scene`), then over the Unix socket:
moves the view along a short orbit inside the model's pose envelope, arms the green laser at its
power cap, sweeps the camera's focus from the near to the far end of the middle view's content
and captures the simulated camera, asks for the same view at the `sgd` tier (the network's
frame refined through the bench model while the view rests, docs/refine.md) and sweeps again,
and shuts the daemon down (lasers off). `focal_strip.png` and `focal_sweep.gif` show both sweeps
side by side. The contact sheet
judges focus by region: the nearest and the farthest quarter of the content (by mapped depth,
projected onto the camera with the simulated bench's geometry), each enlarged at both focuses,
with each capture's match to the view there. Writes to the output folder: the rendered views,
the SLM's green phase frames, the captures, the contact sheet, and summary.json with per-stage
timings and the regions' best focus.

Without a calibration file the daemon's focus is `stage = stage_at_reference_mm + z_mm` (1 mm of
stage per mm of hologram depth). The simulated relay magnifies by M = 0.75, so a hologram depth of
z needs M^2 z of stage travel: the demo converts depths with the simulated bench's own geometry,
which is what a calibration (issue 8) will provide for a real bench.
"""

from __future__ import annotations

import json
import struct
import tempfile
import threading
import time
import zlib
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nhfd.calibration import CalibrationStore
from nhfd.config import Config, _overlay
from nhfd.daemon.client import Client
from nhfd.daemon.service import Daemon
from nhfd.dataset.build import sha256_file
from nhfd.drivers.simcamera import TrueBench
from nhfd.model_info import ModelInfo, scene_mismatch
from nhfd.models.export import OnnxModel, load_model
from nhfd.models.inputs import mapped_depth
from nhfd.optics.color import srgb_to_linear
from nhfd.optics.refplane import window_offset
from nhfd.pipeline.frame import render_view
from nhfd.pipeline.settings import frame_settings
from nhfd.pipeline.view import Scene, scene_frame
from nhfd.pipeline.warmup import warm_frame_path
from nhfd.scene.io import load_scene
from nhfd.views import View, view_from_json

# Shipped as package data of nhfd.models (the repo's models/ folder): found the same way from
# a checkout, an editable install or a wheel.
_SHIPPED = Path(str(resources.files("nhfd.models")))
DEFAULT_MODEL = _SHIPPED / "nhf-donut-512.onnx"
DEFAULT_SCENE = _SHIPPED / "scenes" / "donut.ply"
ORBIT_VIEWS = 5
FOCUS_PLANES = 7
# The near and far regions: the nearest and farthest quarter of the view's content by depth.
REGION_FRACTION = 0.25
# The sweep runs between these percentiles of the view's content depth (near to far).
SWEEP_PERCENTILES = (97.0, 3.0)
EXPOSURE_S = 0.05
REFINE_ITERATIONS = 80
HOW_TO_BUILD = """\
The demo needs the trained default model {model}, which is not there.
Build it (about 8 min + 45 min on 2 cores, or a few minutes with --device cuda on a GPU; see
docs/network.md, "The shipped model"):
  .venv/bin/nhfd dataset build --scene models/scenes/donut.ply --out datasets/donut-512 \\
      --views 130 --size 512x288 --workers 2
  .venv/bin/nhfd train --data datasets/donut-512 --out runs/donut-512
  (an interrupted run continues when the same command runs again)
  .venv/bin/nhfd export runs/donut-512 -o {model}
or copy a released nhf-donut-512.onnx there, or pass --model PATH."""


def read_png16(path: Path) -> np.ndarray:
    """A 16-bit greyscale PNG written by `nhfd.daemon.png.write_png16` -> float [0, 1]."""
    data = path.read_bytes()
    pos, idat, size = 8, b"", (0, 0)
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        if kind == b"IHDR":
            size = struct.unpack(">II", body[:8])
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    w, h = size
    rows = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + 2 * w)
    if np.any(rows[:, 0]):
        raise ValueError(f"{path}: PNG row filters other than none are not supported here")
    return rows[:, 1:].copy().view(">u2").astype(np.float64) / 65535.0


def check_model_and_scene(model: Path, scene: Path, config: Config) -> dict[str, Any]:
    """The demo's model and scene, checked before the daemon starts (which would otherwise wait
    for a load that fails): both files exist (FileNotFoundError; for the model, how to build
    it), the model is for the configured optics (`ModelMismatch`, a ValueError naming what
    differs), it was trained on this scene (its metadata's `scene_sha256` is the file's) and its
    hologram fits the configured panel (`panel_hw` is the SLM's, the training size within it);
    each mismatch a ValueError naming the model and the scene or panel. Returns the metadata.

    `config`: the whole configuration, because the model is checked as `load_model` checks it
    (`[optics]` and `[slm]`'s pitch) and against `[slm]`'s panel."""
    model, scene = Path(model), Path(scene)
    if not model.is_file():
        raise FileNotFoundError(HOW_TO_BUILD.format(model=model))
    if not scene.is_file():
        raise FileNotFoundError(f"the scene {scene} is not there (the donut ships in "
                                f"{DEFAULT_SCENE.parent}; pass --scene PATH for another)")
    meta = load_model(model, config).metadata
    hashes = scene_mismatch(meta, sha256_file(scene))
    if hashes:
        raise ValueError(
            f"the model {model} was trained on another scene than {scene} ({hashes}): pass "
            f"--scene with the scene the model was built from, or --model with a model built "
            f"from {scene.name}")
    panel = (int(config.slm.height_px), int(config.slm.width_px))
    model_panel = tuple(int(v) for v in meta.get("panel_hw") or panel)
    if model_panel != panel:
        raise ValueError(
            f"the model {model} makes holograms for a {model_panel[1]}x{model_panel[0]} panel, "
            f"the configured SLM ([slm] width_px, height_px) is {panel[1]}x{panel[0]}: use a "
            f"model trained for this panel")
    h, w = (int(v) for v in meta["train_size_hw"])
    if h > panel[0] or w > panel[1]:
        raise ValueError(
            f"the model {model} was trained at {w}x{h}, larger than the configured "
            f"{panel[1]}x{panel[0]} SLM")
    return meta


def demo_config(base: Config, *, model: Path, scene: Path, runtime: Path, captures: Path
                ) -> tuple[Config, TrueBench, ModelInfo]:
    """The user's configuration with the bench forced to the simulated devices, the demo's model,
    scene and folders, a camera region around the hologram window and the focus mapping of the
    simulated relay. Returns the configuration, the simulated bench's truth and the model's
    `ModelInfo`."""
    info = OnnxModel(model).info  # the window and z0 the camera region must cover
    h, w = info.train_size_hw
    truth = TrueBench()
    z0_m = info.z0_m
    roi = truth.roi_for_panel((h + 64, w + 64), margin_px=16)
    user = {
        "devices": {"slm": "simulated", "laser": "simulated", "stage": "simulated",
                    "camera": "simulated", "navigator": "none",
                    "readybeam": {"guardian": {"socket_path": str(runtime / "laser.sock")}},
                    "camera_settings": {"exposure_s": EXPOSURE_S, "channels": "mono"}},
        "daemon": {"server": {"runtime_dir": str(runtime / "run")},
                   "arming": {"guardian": "spawn"},
                   "paths": {"scene_dirs": [str(scene.parent.resolve())],
                             "model_dirs": [str(model.parent.resolve())],
                             "snapshot_dir": str(captures.resolve()),
                             "scene": str(scene.resolve())},
                   "audit": {"file": str(runtime / "audit.jsonl")},
                   "frames": {"model": str(model.resolve())},
                   "bench": {"camera_roi_px": list(roi),
                             # The stage reading that focuses the camera on the reference plane
                             # (green).
                             "stage_at_reference_mm": round(truth.stage_mm_for(z0_m, 1), 6)}},
        # The refined sweep's budget: a few seconds on 2 cores at the model's window.
        "refine": {"iterations": REFINE_ITERATIONS, "seconds": 60.0},
    }
    return Config.model_validate(_overlay(base.model_dump(), user)), truth, info


def focus_command_mm(z_h_m: float, truth: Any) -> float:
    """The `focus` z_mm that puts hologram depth z_h in focus on the simulated bench (green),
    under the daemon's uncalibrated 1:1 mapping: stage travel is M^2 times the depth."""
    return z_h_m * 1e3 / truth.stage_scale


def run(out: Path, *, config: Config, model: Path, scene: Path, log: Any = print
        ) -> dict[str, Any]:
    """Run the demo (see the module docstring) into the folder `out`; returns the summary it
    writes there (summary.json). `config`: the user's configuration, which the demo's daemon
    runs under with the bench forced to the simulated devices (`demo_config`): the whole of it,
    as `nhfd serve` takes it. `log`: where progress lines go."""
    import matplotlib

    matplotlib.use("Agg")

    t_start = time.perf_counter()
    check_model_and_scene(model, scene, config)
    out.mkdir(parents=True, exist_ok=True)
    for sub in ("views", "slm", "captures"):
        (out / sub).mkdir(exist_ok=True)
    # The daemon's runtime directory (sockets, lock, guardian token): removed when the demo ends.
    with tempfile.TemporaryDirectory(prefix="nhfd-demo-", dir="/tmp") as runtime:
        return _run(out, Path(runtime), config=config, model=model, scene=scene, log=log,
                    t_start=t_start)


def _run(out: Path, runtime: Path, *, config: Config, model: Path, scene: Path, log: Any,
         t_start: float) -> dict[str, Any]:
    import matplotlib.pyplot as plt

    cfg, truth, info = demo_config(config, model=model, scene=scene, runtime=runtime,
                                   captures=out / "captures")
    # The demo renders views itself, in this process, beside the daemon's control loop: its
    # kernels are loaded (or, after a fresh install, compiled) here first, so their loading never
    # holds up the loop's heartbeat to the laser guardian (a "control loop stalled" warning).
    warm = warm_frame_path()
    misses = sum(k["misses"] for k in warm["kernels"].values())
    log(f"nhfd demo: frame kernels ready in {warm['seconds']:.1f} s "
        f"({'compiled now: nhfd warmup does this once' if misses else 'from the kernel cache'})")
    daemon = Daemon(cfg, base_dir=Path.cwd(), env={}, handle_signals=False)
    daemon.start()
    loop = threading.Thread(target=daemon.run, name="nhfd-demo-daemon", daemon=True)
    loop.start()
    summary: dict[str, Any] = {"model": str(model), "scene": str(scene), "views": [],
                               "focus_sweep": []}
    try:
        c = Client(daemon.socket_path, timeout_s=30)
        log(f"nhfd demo: daemon up (socket {daemon.socket_path}); loading model and scene")
        _wait(lambda: (c.status()["frames"]["state"] == "running"
                       and c.status()["model"] != "none loaded"
                       and (c.status()["scene"] or {}).get("center") is not None),
              120, "the frame worker with the model and the scene", c)
        env = info.pose_envelope
        az = (env and env.azimuth_deg) or (-20.0, 20.0)
        el = (env and env.elevation_deg) or (20.0, 20.0)
        dist = (env and env.distance) or (2.0, 2.0)
        elevation = 0.5 * (el[0] + el[1])
        radius = 0.5 * (dist[0] + dist[1])
        azimuths = np.linspace(az[0] + 0.25 * (az[1] - az[0]), az[1] - 0.25 * (az[1] - az[0]),
                               ORBIT_VIEWS)
        for i, a in enumerate(azimuths):
            seq = c.call("set_view", orbit={"azimuth_deg": float(a), "elevation_deg": elevation,
                                            "radius": radius})["seq"]
            _wait(lambda seq=seq: c.status()["view"]["applied_seq"] == seq, 60, f"view {seq}", c)
            st = c.status()
            plt.imsave(out / "views" / f"view_{i:02d}.png",
                       daemon.frames.last_rgb.transpose(1, 2, 0))
            plt.imsave(out / "slm" / f"slm_green_{i:02d}.png", daemon.frames.last_frame[1],
                       cmap="gray", vmin=0, vmax=255)
            summary["views"].append({"azimuth_deg": float(a), "elevation_deg": elevation,
                                     "radius": radius, "seq": seq, "timings": st["timings"],
                                     "warnings": st["warnings"]})
            t = st["timings"]
            log(f"  view {i} (azimuth {a:+.1f} deg): render {t['render_ms']:.0f} ms, inference "
                f"{t['inference_ms']:.0f}, propagation {t['propagation_ms']:.0f}, coding "
                f"{t['coding_ms']:.0f}, output {t['output_ms']:.0f}")
        # The middle view for the focus sweep, rendered here too for its depth map.
        mid = float(azimuths[len(azimuths) // 2])
        placed = c.call("set_view", orbit={"azimuth_deg": mid, "elevation_deg": elevation,
                                           "radius": radius})  # fmt: skip
        seq = placed["seq"]
        _wait(lambda: c.status()["view"]["applied_seq"] == seq, 60, "the middle view", c)
        settings = frame_settings(cfg, info, CalibrationStore.of(cfg).active())
        rgb, zh = view_depth(view_from_json(placed["view"]), scene, info, settings.window_hw)
        sweep_m = np.linspace(*np.nanpercentile(zh, SWEEP_PERCENTILES), FOCUS_PLANES)
        cap = cfg.devices.readybeam.max_power_pct[1]
        c.call("laser", action="arm", duration_s=300.0)
        applied = c.call("laser", action="power", channel="green", power_pct=cap)["power_pct"]
        c.call("laser", action="enable", channel="green")
        log(f"  green laser armed at its cap ({applied:g}%); focus sweep over the view's content "
            f"depth, {sweep_m[0] * 1e3:+.2f} (near) to {sweep_m[-1] * 1e3:+.2f} mm (far)")
        images = _focus_sweep(c, out, sweep_m, truth, "network", summary, log)
        # The same view at the sgd tier: the network's frame at once, then better ones while
        # it rests (docs/refine.md); swept again once the refinement stops.
        refined_seq = c.call("set_view", orbit={"azimuth_deg": mid, "elevation_deg": elevation,
                                                "radius": radius}, quality="sgd")["seq"]
        _wait(lambda: c.status()["view"]["applied_seq"] == refined_seq, 60, "the sgd view", c)
        _wait(lambda: bool((c.status()["frames"]["refine"] or {}).get("stop")), 120,
              "the sgd refinement", c)
        summary["refine"] = c.status()["frames"]["refine"]
        r = summary["refine"]
        log(f"  sgd: {r['iterations']} iterations in {r['seconds']:.1f} s, estimated "
            f"{r['start_psnr_db']:.1f} -> {r['psnr_db']:.1f} dB ({r['stop']}); sweeping again")
        refined = _focus_sweep(c, out, sweep_m, truth, "sgd", summary, log)
        c.call("laser", action="off")
        summary["regions"] = focus_regions(images, rgb, zh, daemon.bench.camera,
                                           settings.panel_hw, settings.pitch_m)
        summary["regions_sgd"] = focus_regions(refined, rgb, zh, daemon.bench.camera,
                                               settings.panel_hw, settings.pitch_m)
        focal_strip(images, refined, summary["regions"], out / "focal_strip.png")
        focal_gif(images, refined, summary["regions"], out / "focal_sweep.gif")
        for tier, key in (("network", "regions"), ("sgd", "regions_sgd")):
            for name, r in summary[key].items():
                log(f"  {tier}: {name} content at {r['content_mm']:+.2f} mm: best match with "
                    f"the view at focus {r['best_focus_mm']:+.2f} mm")
        contact_sheet(images, summary["regions"], rgb, zh, out / "contact_sheet.png")
        for regions in (summary["regions"], summary["regions_sgd"]):
            for r in regions.values():
                for key in ("mask_window", "mask_camera"):
                    r.pop(key)
        summary["stages_ms_median"] = {
            k: float(np.median([v["timings"][f"{k}_ms"] for v in summary["views"]]))
            for k in ("render", "inference", "propagation", "coding", "output")}
        c.call("shutdown")
    finally:
        daemon.request_shutdown("demo over")
        loop.join(30)
    summary["lasers_off_at_exit"] = daemon.laser.status().get("error") is None
    summary["runtime_s"] = round(time.perf_counter() - t_start, 1)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def _focus_sweep(c: Any, out: Path, sweep_m: np.ndarray, truth: Any, tier: str,
                 summary: dict[str, Any], log: Any) -> list[tuple[float, np.ndarray]]:
    """Capture the shown frame at each hologram depth of `sweep_m` (the green laser on):
    [(z_h m, image)], each image also written to the captures folder."""
    images = []
    for k, z_h in enumerate(sweep_m):
        z_mm = focus_command_mm(float(z_h), truth)
        job = c.call("focus", z_mm=z_mm, home=k == 0 and tier == "network")["job"]
        _job(c, job, 120)
        # The daemon resolves snapshot paths inside its snapshot_dir (the captures folder).
        name = f"focus_{tier}_{k:02d}_{z_h * 1e3:+.2f}mm.png"
        path = out / "captures" / name
        _job(c, c.call("snapshot", path=name)["job"], 120)
        images.append((float(z_h), read_png16(path)))
        summary["focus_sweep"].append({"tier": tier, "hologram_depth_mm": float(z_h) * 1e3,
                                       "focus_z_mm": z_mm, "capture": str(path)})
    log(f"  {tier}: captured at {len(images)} depths, {sweep_m[0] * 1e3:+.2f} to "
        f"{sweep_m[-1] * 1e3:+.2f} mm")
    return images


def _upright(sweeps: list[list[tuple[float, np.ndarray]]], regions: dict[str, dict[str, Any]]
             ) -> tuple[list[list[np.ndarray]], float, list[np.ndarray]]:
    """The captures rotated upright (the relay images the panel upside down) and cropped to the
    content (the near and far regions' box), the one level every crop is shown against (the
    99.9th percentile of the brightest), and the regions' masks on the crops."""
    masks = [np.rot90(r["mask_camera"], 2) for r in regions.values()]
    box = _box(np.logical_or.reduce(masks), pad=12)
    up = [[np.rot90(img, 2)[box] for _, img in sweep] for sweep in sweeps]
    norm = max(float(np.percentile(img, 99.9)) for row in up for img in row) or 1.0
    return up, norm, [m[box] for m in masks]


def focal_strip(network: list[tuple[float, np.ndarray]], refined: list[tuple[float, np.ndarray]],
                regions: dict[str, dict[str, Any]], path: Path) -> None:
    """The focal sweep as a still strip: the network's frame (top) and the sgd-refined one
    (bottom) captured at each depth, near to far, the near and far content outlined."""
    import matplotlib.pyplot as plt

    (net, ref), norm, masks = _upright([network, refined], regions)
    n = len(network)
    h, w = net[0].shape
    # Thumbnails large enough to see the focus move (~290 px wide at dpi 110).
    fig, axes = plt.subplots(2, n, figsize=(2.6 * n, 2 * 2.6 * h / w + 1.0))
    colours = ["C1", "C0"]  # near, far
    for row, (label, images) in enumerate((("network", net), ("sgd-refined", ref))):
        for k, img in enumerate(images):
            ax = axes[row, k]
            ax.imshow(np.clip(img / norm, 0, 1) ** 0.5, cmap="gray", vmin=0, vmax=1)
            for mask, colour in zip(masks, colours, strict=True):
                ax.contour(mask.astype(float), levels=[0.5], colors=colour, linewidths=0.6)
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"focus {network[k][0] * 1e3:+.1f} mm", fontsize=9)
            if k == 0:
                ax.set_ylabel(label, fontsize=10)
    fig.suptitle("Simulated camera swept from the near (orange) to the far (blue) content: the "
                 "network's frame and the same view refined (sgd)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def focal_gif(network: list[tuple[float, np.ndarray]], refined: list[tuple[float, np.ndarray]],
              regions: dict[str, dict[str, Any]], path: Path, frame_ms: int = 450) -> None:
    """The focal sweep as an animated GIF, near to far and back: the network's frame (left) and
    the sgd-refined one (right) at each focus, side by side, with the depth written in; below
    them the near and the far region of each, enlarged (`region_insets`), where the focus is
    seen to move."""
    from PIL import Image, ImageDraw

    (net, ref), norm, masks = _upright([network, refined], regions)
    frames = []
    for k in list(range(len(net))) + list(range(len(net) - 2, 0, -1)):
        shown = [np.clip(img / norm, 0, 1) ** 0.5 for img in (net[k], ref[k])]
        # 2 x 2 camera pixels to one in the overview (the camera samples the panel finer than
        # its pixels) and 64 greys: the sensor's noise would otherwise cost a megabyte a sweep.
        pair = [_bin2(img) for img in shown]
        gap = np.ones((pair[0].shape[0], 4))
        top = np.hstack([pair[0], gap, pair[1]])
        insets, _ = region_insets(shown, masks, width_px=top.shape[1])
        canvas = np.vstack([top, np.ones((4, top.shape[1])), insets])
        grey = Image.fromarray((canvas * 255).astype(np.uint8))
        draw = ImageDraw.Draw(grey)
        draw.text((3, 1), f"network {network[k][0] * 1e3:+.1f} mm", fill=255)
        draw.text((pair[0].shape[1] + 7, 1), "sgd-refined", fill=255)
        draw.text((3, top.shape[0] + 5), "near region, enlarged (far below)", fill=255)
        frames.append(grey.convert("P", palette=Image.Palette.ADAPTIVE, colors=64))
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=frame_ms, loop=0,
                   optimize=True)


def region_insets(images: list[np.ndarray], masks: list[np.ndarray], width_px: int
                  ) -> tuple[np.ndarray, int]:
    """The regions (each mask's box, a row each: near, far) of each image in `images` (values
    in [0, 1], one shape; a column each), on white with 4 px gaps, enlarged by the one whole
    factor (at least 1) that fits a row into `width_px`; a region wider than its column even at
    factor 1 shows its central part at 1:1. (`[H, width_px]` canvas, the factor)."""
    boxes = [_box(m, pad=4) for m in masks]
    n = len(images)
    column = (width_px - 4 * (n - 1)) // n
    widest = max(b[1].stop - b[1].start for b in boxes)
    factor = max(1, column // widest)
    rows = []
    for box in boxes:
        row_h = (box[0].stop - box[0].start) * factor
        row = np.ones((row_h, width_px))
        for i, img in enumerate(images):
            big = np.kron(img[box], np.ones((factor, factor)))
            cut = max(0, (big.shape[1] - column) // 2)  # the central part where it is wider
            big = big[:, cut : cut + column]
            left = i * (column + 4)
            row[:, left : left + big.shape[1]] = big
        rows.append(row)
    gaps = [np.ones((4, width_px))] * (len(rows) - 1)
    return np.vstack([x for pair in zip(rows, [*gaps, None], strict=True) for x in pair
                      if x is not None]), factor


def _bin2(image: np.ndarray) -> np.ndarray:
    """The mean of each 2 x 2 block (an odd last row or column dropped)."""
    h, w = image.shape[0] // 2 * 2, image.shape[1] // 2 * 2
    return image[:h, :w].reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))


def view_depth(view: View, scene: Path, info: ModelInfo, window_hw: tuple[int, int]
               ) -> tuple[np.ndarray, np.ndarray]:
    """The view rendered as the frame worker renders it: sRGB `[3, H, W]` and the mapped
    hologram depth `z_h` `[H, W]` (m, NaN off content; the model's depth mapping, which an rgbd
    model such as the demo's always has)."""
    g = load_scene(scene)
    r = render_view(view, Scene(g, scene_frame(g, str(scene))), info, window_hw)
    if info.mapping is None:
        raise ValueError("the model records no depth mapping: the demo's focus sweep needs one")
    m = info.mapping
    return r.rgb, mapped_depth(r.depth, r.alpha, m.a_m, m.b_m)


def depth_regions(zh_m: np.ndarray, fraction: float = REGION_FRACTION
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the nearest and the farthest `fraction` of the content pixels, by `z_h`."""
    content = np.isfinite(zh_m)
    if not content.any():
        raise ValueError("the view shows no content: no near or far region to focus on")
    z = np.where(content, zh_m, 0.0)
    lo, hi = np.quantile(zh_m[content], [fraction, 1 - fraction])
    return content & (z >= hi), content & (z <= lo)


def on_camera(camera: Any, images: np.ndarray, panel_hw: tuple[int, int],
              pitch_m: float) -> np.ndarray:
    """Window-sized images `[C, h, w]` placed on the panel (centred, as frames are) and mapped
    onto the camera's region of interest by the simulated bench's geometry -> `[C, rh, rw]`."""
    c, h, w = images.shape
    top, left = window_offset(panel_hw, (h, w))
    panel = np.zeros((c, *panel_hw), np.float32)
    panel[:, top : top + h, left : left + w] = images
    return camera.project_to_camera(panel, pitch_m)


def focus_correlation(captures: list[np.ndarray], reference: np.ndarray,
                      mask: np.ndarray) -> list[float]:
    """Pearson correlation, inside `mask`, of each capture with `reference` (the view's linear
    intensity where the camera sees it): largest where that region is in focus. docs/physics.md's
    measure for whole scenes ("The focus test"); gradient energy is not one, since coherent
    ringing dominates it."""
    v = reference[mask] - reference[mask].mean()
    out = []
    for img in captures:
        x = img[mask] - img[mask].mean()
        out.append(float(x @ v / max(float(np.linalg.norm(x) * np.linalg.norm(v)), 1e-30)))
    return out


def _box(mask: np.ndarray, pad: int = 6) -> tuple[slice, slice]:
    rows, cols = np.nonzero(mask)
    h, w = mask.shape
    return (slice(max(0, rows.min() - pad), min(h, rows.max() + 1 + pad)),
            slice(max(0, cols.min() - pad), min(w, cols.max() + 1 + pad)))  # fmt: skip


def focus_regions(sweep: list[tuple[float, np.ndarray]], rgb: np.ndarray, zh_m: np.ndarray,
                  camera: Any, panel_hw: tuple[int, int], pitch_m: float) -> dict[str, Any]:
    """For the near and far regions of the view: their mean depth, their masks (window and
    camera), and each capture's match with the view there (`focus_correlation`)."""
    near, far = depth_regions(zh_m)
    green = srgb_to_linear(torch.from_numpy(np.ascontiguousarray(rgb[1]))).numpy()
    mapped = on_camera(camera, np.stack([green, near, far]).astype(np.float32), panel_hw,
                       pitch_m)  # fmt: skip
    captures = [img for _, img in sweep]
    out = {}
    for k, (name, mask) in enumerate((("near", near), ("far", far)), start=1):
        on_cam = mapped[k] > 0.5
        corr = focus_correlation(captures, mapped[0], on_cam)
        out[name] = {"content_mm": float(np.mean(zh_m[mask])) * 1e3,
                     "best_focus_mm": sweep[int(np.argmax(corr))][0] * 1e3,
                     "correlation": corr, "mask_window": mask, "mask_camera": on_cam}
    return out


def contact_sheet(sweep: list[tuple[float, np.ndarray]], regions: dict[str, dict[str, Any]],
                  rgb: np.ndarray, zh_m: np.ndarray, path: Path) -> None:
    """The view and its mapped depth with the near and far regions; the captures focused on
    each region; each region enlarged at both focuses (sharp at its own, blurred at the other);
    and the focus curves. Captures are rotated upright (the relay images the panel upside
    down)."""
    import matplotlib.pyplot as plt

    depths = [z for z, _ in sweep]
    upright = [np.rot90(img, 2) for _, img in sweep]
    colours = {"near": "C1", "far": "C0"}
    best = {name: int(np.argmin([abs(z - r["content_mm"] * 1e-3) for z in depths]))
            for name, r in regions.items()}  # the sweep plane at each region's depth
    fig = plt.figure(figsize=(17, 7.2))
    gs = fig.add_gridspec(2, 5)
    ax = fig.add_subplot(gs[0, 0])
    ax.imshow(np.clip(rgb.transpose(1, 2, 0), 0, 1))
    for name, r in regions.items():
        ax.contour(r["mask_window"].astype(float), levels=[0.5], colors=colours[name],
                   linewidths=0.8)
    ax.set_title("view: near (orange), far (blue) content", fontsize=9)
    ax = fig.add_subplot(gs[0, 1])
    im = ax.imshow(zh_m * 1e3, cmap="viridis")
    fig.colorbar(im, ax=ax, fraction=0.03, label="z_h (mm)")
    ax.set_title("mapped hologram depth", fontsize=9)
    norm = max(float(np.percentile(img, 99.9)) for img in upright) or 1.0
    for col, name in ((2, "near"), (3, "far")):
        k = best[name]
        ax = fig.add_subplot(gs[0, col])
        ax.imshow(np.clip(upright[k] / norm, 0, 1) ** 0.5, cmap="gray", vmin=0, vmax=1)
        for other, r in regions.items():
            rs, cs = _box(np.rot90(r["mask_camera"], 2))
            ax.add_patch(plt.Rectangle((cs.start, rs.start), cs.stop - cs.start,
                                       rs.stop - rs.start, fill=False, color=colours[other],
                                       lw=0.8))  # fmt: skip
        ax.set_title(f"capture, focus {depths[k] * 1e3:+.1f} mm ({name} content)", fontsize=9)
    ax = fig.add_subplot(gs[0, 4])
    for name, r in regions.items():
        corr = np.asarray(r["correlation"])
        ax.plot(np.asarray(depths) * 1e3, corr, "o-", color=colours[name], label=name)
        ax.axvline(r["content_mm"], color=colours[name], ls="--", lw=0.8)
    ax.set_xlabel("focus: hologram depth (mm)", fontsize=8)
    ax.set_title("match with the view (dashed: content depth)", fontsize=8)
    ax.legend(fontsize=7)
    ax.tick_params(labelsize=7)
    col = 0
    for name, r in regions.items():
        mask_up = np.rot90(r["mask_camera"], 2)
        box = _box(mask_up)
        dim = 0.3 + 0.7 * mask_up[box]  # the region itself at full brightness
        crops = [upright[best[n]][box] * dim for n in ("near", "far")]
        scale = max(float(np.percentile(c, 99.5)) for c in crops) or 1.0
        for focus_name, crop in zip(("near", "far"), crops, strict=True):
            k = best[focus_name]
            ax = fig.add_subplot(gs[1, col])
            ax.imshow(np.clip(crop / scale, 0, 1) ** 0.5, cmap="gray", vmin=0, vmax=1)
            verdict = "in focus" if focus_name == name else "defocused"
            ax.set_title(f"{name} content at focus {depths[k] * 1e3:+.1f} mm: {verdict}",
                         fontsize=8, color=colours[name])  # fmt: skip
            col += 1
    ax = fig.add_subplot(gs[1, 4])
    ax.axis("off")
    lines = [f"{name}: content at {r['content_mm']:+.2f} mm,\n  best match at focus "
             f"{r['best_focus_mm']:+.2f} mm" for name, r in regions.items()]
    ax.text(0, 0.5, "\n\n".join(lines), fontsize=9, va="center")
    for a in fig.axes:
        if a.get_xlabel() == "":
            a.set_xticks([])
            a.set_yticks([])
    fig.suptitle("Simulated camera, green: the hologram refocuses from the near to the far "
                 "content", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _wait(cond: Any, timeout_s: float, what: str, client: Any) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            errors = client.status()["errors"]
            raise TimeoutError(f"timed out after {timeout_s:g} s waiting for {what}; "
                               f"daemon errors: {errors[-3:]}")
        time.sleep(0.05)


def _job(client: Any, job_id: int, timeout_s: float) -> dict[str, Any]:
    """The job once done (`Client.wait_job`); TimeoutError, with the daemon's last errors, when
    it is still queued or running after `timeout_s`; RuntimeError when it failed."""
    job = client.wait_job(job_id, timeout_s)
    if job["state"] in ("queued", "running"):
        errors = client.status()["errors"]
        raise TimeoutError(f"timed out after {timeout_s:g} s waiting for job {job_id} (still "
                           f"{job['state']}); daemon errors: {errors[-3:]}")
    if job["state"] != "done":
        raise RuntimeError(f"{job['kind']} job {job_id} {job['state']}: {job['error']}")
    return job
