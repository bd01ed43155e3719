"""`nhfd demo`: the daemon on the simulated bench, driven as a user drives it.

Starts `nhfd serve`'s daemon (in this process, its control loop on a thread; the frame worker is
its own spawned process) with the shipped model and the donut scene, then over the Unix socket:
moves the view along a short orbit inside the model's pose envelope, arms the green laser at its
power cap, sweeps the camera's focus from the near to the far end of the hologram volume and
captures the simulated camera, and shuts the daemon down (lasers off). Writes to the output
folder: the rendered views, the SLM's green phase frames, a contact sheet of the focus sweep
(near and far captures side by side), and summary.json with per-stage timings.

Without a calibration file the daemon's focus is `stage = stage_at_reference_mm + z_mm` (1 mm of
stage per mm of hologram depth). The simulated relay magnifies by M = 0.75, so a hologram depth of
z needs M^2 z of stage travel: the demo converts depths with the simulated bench's own geometry,
which is what a calibration (issue 8) will provide for a real bench.
"""

from __future__ import annotations

import json
import struct
import tempfile
import time
import zlib
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

# Shipped as package data of nhfd.models (the repo's models/ folder): found the same way from
# a checkout, an editable install or a wheel.
_SHIPPED = Path(str(resources.files("nhfd.models")))
DEFAULT_MODEL = _SHIPPED / "nhf-donut-512.onnx"
DEFAULT_SCENE = _SHIPPED / "scenes" / "donut.ply"
ORBIT_VIEWS = 5
FOCUS_PLANES = 5
EXPOSURE_S = 0.05
HOW_TO_BUILD = """\
The demo needs the trained default model {model}, which is not there.
Build it (about 8 min + 45 min on 2 cores; see README "The network"):
  .venv/bin/nhfd dataset build --scene models/scenes/donut.ply --out datasets/donut-512 \\
      --views 130 --size 512x288 --workers 2
  .venv/bin/nhfd train --data datasets/donut-512 --out runs/donut-512-balanced \\
      --profile balanced --steps 3000 --checkpoint-every 250
  (run the same command again with --steps 6000 to continue, as the shipped model was)
  .venv/bin/nhfd export runs/donut-512-balanced -o {model}
or copy a released nhf-donut-512.onnx there, or pass --model PATH."""


def read_png16(path: Path) -> np.ndarray:
    """A 16-bit greyscale PNG written by `nhfd.daemon.bench.write_png16` -> float [0, 1]."""
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


def demo_config(base: Any, *, model: Path, scene: Path, runtime: Path, captures: Path) -> Any:
    """The user's configuration with the bench forced to the simulated devices, the demo's model,
    scene and folders, a camera region around the hologram window and the focus mapping of the
    simulated relay."""
    from nhfd.config import Config, _overlay
    from nhfd.drivers.simcamera import TrueBench
    from nhfd.models.export import OnnxModel

    meta = OnnxModel(model).metadata  # the window and z0 the camera region must cover
    h, w = (int(v) for v in meta["train_size_hw"])
    truth = TrueBench()
    z0_m = float(meta["z0_m"])
    roi = truth.roi_for_panel((h + 64, w + 64), margin_px=16)
    user = {
        "devices": {"slm": "simulated", "laser": "simulated", "stage": "simulated",
                    "camera": "simulated", "navigator": "none",
                    "readybeam": {"guardian": {"socket_path": str(runtime / "laser.sock")}},
                    "camera_settings": {"exposure_s": EXPOSURE_S, "channels": "mono"}},
        "daemon": {"runtime_dir": str(runtime / "run"), "guardian": "spawn",
                   "scene_dirs": [str(scene.parent.resolve())],
                   "model_dirs": [str(model.parent.resolve())],
                   "snapshot_dir": str(captures.resolve()),
                   "audit_log": str(runtime / "audit.jsonl"),
                   "scene": str(scene.resolve()), "model": str(model.resolve()),
                   "camera_roi_px": list(roi),
                   # The stage reading that focuses the camera on the reference plane (green).
                   "stage_at_reference_mm": round(truth.stage_mm_for(z0_m, 1), 6)},
    }
    return Config.model_validate(_overlay(base.model_dump(), user)), truth, meta


def focus_command_mm(z_h_m: float, truth: Any) -> float:
    """The `focus` z_mm that puts hologram depth z_h in focus on the simulated bench (green),
    under the daemon's uncalibrated 1:1 mapping: stage travel is M^2 times the depth."""
    return z_h_m * 1e3 / truth.stage_scale


def run(out: Path, *, config: Any, model: Path, scene: Path, log: Any = print) -> dict[str, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from nhfd.daemon.client import Client
    from nhfd.daemon.service import Daemon

    t_start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    for sub in ("views", "slm", "captures"):
        (out / sub).mkdir(exist_ok=True)
    runtime = Path(tempfile.mkdtemp(prefix="nhfd-demo-", dir="/tmp"))
    cfg, truth, meta = demo_config(config, model=model, scene=scene, runtime=runtime,
                                   captures=out / "captures")
    daemon = Daemon(cfg, base_dir=Path.cwd(), env={}, handle_signals=False)
    daemon.start()
    import threading

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
        env = meta.get("pose_envelope") or {}
        az = env.get("azimuth_deg") or [-20.0, 20.0]
        el = env.get("elevation_deg") or [20.0, 20.0]
        dist = env.get("distance") or [2.0, 2.0]
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
        # The middle view for the focus sweep.
        mid = float(azimuths[len(azimuths) // 2])
        seq = c.call("set_view", orbit={"azimuth_deg": mid, "elevation_deg": elevation,
                                        "radius": radius})["seq"]
        _wait(lambda: c.status()["view"]["applied_seq"] == seq, 60, "the middle view", c)
        cap = cfg.devices.readybeam.max_power_pct[1]
        c.call("laser", action="arm", duration_s=300.0)
        applied = c.call("laser", action="power", channel="green", power_pct=cap)["power_pct"]
        c.call("laser", action="enable", channel="green")
        log(f"  green laser armed at its cap ({applied:g}%); focus sweep near -> far")
        z_min, z_max = (float(v) for v in meta["volume_m"])
        images = []
        for k, z_h in enumerate(np.linspace(z_max, z_min, FOCUS_PLANES)):
            z_mm = focus_command_mm(float(z_h), truth)
            job = c.call("focus", z_mm=z_mm, home=k == 0)["job"]  # a fresh stage homes first
            _job(c, job, 120)
            # The daemon resolves snapshot paths inside its snapshot_dir (the captures folder).
            name = f"focus_{k:02d}_{z_h * 1e3:+.1f}mm.png"
            path = out / "captures" / name
            _job(c, c.call("snapshot", path=name)["job"], 120)
            image = read_png16(path)
            images.append((float(z_h), image))
            summary["focus_sweep"].append({"hologram_depth_mm": float(z_h) * 1e3,
                                           "focus_z_mm": z_mm, "capture": str(path),
                                           "sharpness": _sharpness(image)})
            log(f"  captured at hologram depth {z_h * 1e3:+.1f} mm")
        c.call("laser", action="off")
        summary["region_sharpness"] = contact_sheet(images, out / "contact_sheet.png",
                                                    daemon.frames.last_rgb)
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


def _sharpness(image: np.ndarray) -> float:
    """Normalised gradient energy (scale-free): larger when the capture is in focus."""
    a = image - np.median(image)
    gy, gx = np.diff(a, axis=0), np.diff(a, axis=1)
    return float((np.square(gy).sum() + np.square(gx).sum()) / max(np.square(a).sum(), 1e-30))


def region_sharpness(images: list[np.ndarray]) -> tuple[list[float], list[float], tuple]:
    """Sharpness of the content's near (bottom) and far (top) thirds in upright captures.

    The orbit looks down at the donut, so its front edge (nearest the viewer, the hologram's
    near side) is at the bottom of the upright image and its back at the top. Content is where
    the brightest capture exceeds a fifth of its 99.9th percentile over most of a 9 x 9 box, so
    thin lines (a window's edge, stray fringes) do not count. Returns the two sharpness lists
    (one value per capture) and the two regions as (row slice, column slice)."""
    peak = np.max(np.stack(images), axis=0)
    level = np.median(peak)
    mask = _box_mean(peak - level > 0.2 * (np.percentile(peak, 99.9) - level), 9) > 0.8
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        whole = (slice(0, peak.shape[0]), slice(0, peak.shape[1]))
        return [_sharpness(i) for i in images], [_sharpness(i) for i in images], (whole, whole)
    top, bottom = int(rows.min()), int(rows.max()) + 1
    left, right = int(cols.min()), int(cols.max()) + 1
    third = max(1, (bottom - top) // 3)
    near = (slice(bottom - third, bottom), slice(left, right))
    far = (slice(top, top + third), slice(left, right))
    return ([_sharpness(i[near]) for i in images], [_sharpness(i[far]) for i in images],
            (near, far))  # fmt: skip


def _box_mean(mask: np.ndarray, k: int) -> np.ndarray:
    """Mean of a boolean image over the k x k box centred on each pixel (edges: zero padded)."""
    c = np.pad(mask.astype(np.float64), k // 2 + 1).cumsum(0).cumsum(1)
    h, w = mask.shape
    box = c[k : k + h, k : k + w] - c[:h, k : k + w] - c[k : k + h, :w] + c[:h, :w]
    return box / (k * k)


def contact_sheet(images: list[tuple[float, np.ndarray]], path: Path,
                  rgb: np.ndarray | None) -> dict[str, list[float]]:
    """The rendered view, then the captures from near to far focus (the relay images the panel
    upside down: rotated back for people); below, the near third of the content enlarged at each
    focus, and the sharpness of the near and far thirds against focus (each region should be
    sharpest where its depth is in focus). Returns those sharpness curves."""
    import matplotlib.pyplot as plt

    upright = [np.rot90(img, 2) for _, img in images]
    near_s, far_s, (near, far) = region_sharpness(upright)
    n = len(images) + 1
    fig, axes = plt.subplots(2, n, figsize=(3.2 * n, 5.0), squeeze=False)
    if rgb is not None:
        axes[0][0].imshow(rgb.transpose(1, 2, 0))
        axes[0][0].set_title("rendered view", fontsize=9)
    norm = max(float(np.percentile(img, 99.9)) for img in upright) or 1.0
    for i, ((z_h, _), img) in enumerate(zip(images, upright, strict=True)):
        label = "near" if i == 0 else "far" if i == len(images) - 1 else ""
        shown = np.clip(img / norm, 0, 1) ** 0.5
        ax = axes[0][1 + i]
        ax.imshow(shown, cmap="gray", vmin=0, vmax=1)
        for (rs, cs), colour in ((near, "C1"), (far, "C0")):
            ax.add_patch(plt.Rectangle((cs.start, rs.start), cs.stop - cs.start,
                                       rs.stop - rs.start, fill=False, color=colour, lw=0.8))
        ax.set_title(f"focus {z_h * 1e3:+.1f} mm {label}", fontsize=9)
        zoom = axes[1][1 + i]
        zoom.imshow(shown[near], cmap="gray", vmin=0, vmax=1)
        zoom.set_title(f"near third, sharpness {near_s[i]:.3f}", fontsize=8)
    depths = [z_h * 1e3 for z_h, _ in images]
    curve = axes[1][0]
    curve.plot(depths, np.asarray(near_s) / max(near_s), "o-", color="C1", label="near third")
    curve.plot(depths, np.asarray(far_s) / max(far_s), "s-", color="C0", label="far third")
    curve.set_xlabel("focus: hologram depth (mm)", fontsize=8)
    curve.set_title("sharpness / its maximum", fontsize=8)
    curve.legend(fontsize=7)
    curve.tick_params(labelsize=7)
    for row in axes:
        for ax in row[1:] if row is axes[1] else row:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle("Simulated camera, green: the hologram refocuses from the near (front of the "
                 "donut) to the far end of the volume", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return {"near_third": near_s, "far_third": far_s}


def _wait(cond: Any, timeout_s: float, what: str, client: Any) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            errors = client.status()["errors"]
            raise TimeoutError(f"timed out after {timeout_s:g} s waiting for {what}; "
                               f"daemon errors: {errors[-3:]}")
        time.sleep(0.05)


def _job(client: Any, job_id: int, timeout_s: float) -> dict[str, Any]:
    _wait(lambda: client.call("job", id=job_id)["state"] in ("done", "failed", "cancelled"),
          timeout_s, f"job {job_id}", client)
    job = client.call("job", id=job_id)
    if job["state"] != "done":
        raise RuntimeError(f"{job['kind']} job {job_id} {job['state']}: {job['error']}")
    return job
