"""`nhfd bench holo`: time per full-colour training example, split into rendering and inversion.

Workload (issue 4): the donut from its suggested camera at 512 x 288 and 1024 x 576, W derived for
the configured volume (+-3 mm) and aperture (half band), depth-aware phase; R, G and B from one
shared set of views (the default) and, at the smaller size, from each colour's own directions,
with the error between the two. The paper reports about 3.5 minutes per monochrome hologram
for this step; its ratio to ours is printed. Peak memory is the process's peak resident size.

`--device cuda` (or cuda:N) renders the light fields with gsplat, several views per call, and
inverts on that GPU (`nhfd dataset build --device cuda`'s path), timed with the GPU
synchronised; the CPU path is `--device cpu`, the default. Each row records its device.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np

from nhfd.benchmarks.machine import describe
from nhfd.cli.args import parse_wxh
from nhfd.config import DEVICES, load_config
from nhfd.dataset.build import check_device
from nhfd.dataset.shard import ExampleSettings
from nhfd.holo import band_limit, colour_sampling, scene_hologram, scene_mapping
from nhfd.optics import Aperture, propagate
from nhfd.scene.io import load_scene
from nhfd.scene.raster import render
from nhfd.scene.suggest import detect_up_axis, format_hint, suggest_camera

PAPER_S_PER_MONOCHROME = 210.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("holo", help="wavefront inversion: seconds per full-colour example",
                       description=__doc__)  # fmt: skip
    p.add_argument("--scene", default=None, help="scene file (default: the shared donut)")
    p.add_argument("--sizes", default="512x288,1024x576", help="comma-separated WxH list")
    p.add_argument("--out", default="out/bench/holo.json", help="JSON file to write")
    p.add_argument("--device", default="cpu", metavar="|".join(DEVICES),
                   help="cpu (default), or cuda / cuda:N: gsplat renders and the GPU inverts; "
                        "auto: the GPU where torch sees one and gsplat imports")
    p.set_defaults(handler=run)


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run(args: argparse.Namespace) -> int:
    import torch

    device = check_device(args.device)
    on_gpu = device != "cpu"

    def sync() -> None:
        if on_gpu:
            torch.cuda.synchronize(device)

    scene = Path(args.scene) if args.scene else (
        Path(__file__).resolve().parents[2].parent / "shared" / "data" / "scenes" / "donut.ply"
    )  # fmt: skip
    if not scene.exists():
        raise FileNotFoundError(f"scene {scene} not found; pass --scene FILE")
    g = load_scene(scene)
    up, _ = detect_up_axis(g, format_hint(scene))
    config = load_config().config
    machine = describe()
    gpu = torch.cuda.get_device_name(device) if on_gpu else None
    print(f"{scene.name}: {len(g)} Gaussians; {machine}; device {device}"
          f"{' (' + gpu + ')' if gpu else ''}")  # fmt: skip
    results: dict = {"scene": scene.name, "device": device, "gpu": gpu, "sizes": {}}
    for size in args.sizes.split(","):
        w, h = parse_wxh(size, "--sizes")
        s = ExampleSettings.from_config(config.optics, config.slm, width_px=w, height_px=h)
        cam = suggest_camera(g, w, h, up, fov_x_deg=s.fov_x_deg)
        central = render(g, cam)  # the mapping from the CPU render, as dataset builds do
        d = central.depth[central.alpha > 0.5]
        mapping, _ = scene_mapping(
            s.volume_m[0], s.volume_m[1], s.pitch_m, cam.fx,
            d_near=float(np.percentile(d, 1)), d_far=float(np.percentile(d, 99)),
        )  # fmt: skip
        aperture = Aperture(s.aperture_shape, s.cutoff_per_px)
        shared = colour_sampling(s.wavelengths_m, s.pitch_m, s.volume_m, aperture, shared=True)
        rss0 = _rss_mb()
        if on_gpu:  # warm-up: gsplat's first call loads (or JIT-compiles) its kernels
            scene_hologram(g, cam, mapping, s.pitch_m, shared[:1], shared_views=True,
                           device=device)  # fmt: skip
            sync()
        t0 = time.perf_counter()
        holo = scene_hologram(g, cam, mapping, s.pitch_m, shared, shared_views=True,
                              device=device)  # fmt: skip
        sync()
        total = time.perf_counter() - t0
        row = {
            "device": device, "views_rendered": holo.n_views,
            "windows": [c.window for c in shared],
            "render_s": holo.render_s, "invert_s": holo.invert_s, "total_s": total,
            "peak_rss_mb": _rss_mb(), "peak_rss_growth_mb": _rss_mb() - rss0,
            "paper_ratio_vs_3_colours": 3 * PAPER_S_PER_MONOCHROME / total,
        }  # fmt: skip
        print(f"  {w} x {h}: shared views ({holo.n_views}): render {holo.render_s:.1f} s, "
              f"invert {holo.invert_s:.1f} s, total {total:.1f} s "
              f"({row['paper_ratio_vs_3_colours']:.0f}x faster than 3 x 3.5 min); "
              f"peak RSS {row['peak_rss_mb']:.0f} MB", flush=True)  # fmt: skip
        if w * h <= 512 * 288:
            own = colour_sampling(s.wavelengths_m, s.pitch_m, s.volume_m, aperture)
            t0 = time.perf_counter()
            per = scene_hologram(g, cam, mapping, s.pitch_m, own, shared_views=False,
                                 device=device)  # fmt: skip
            sync()
            per_s = time.perf_counter() - t0
            a = band_limit(holo.field, aperture)
            b = band_limit(per.field, aperture)
            err = [float((a[c] - b[c]).norm() / b[c].norm()) for c in range(3)]
            planes = [s.volume_m[1], 0.0, s.volume_m[0]]
            ia = propagate(a, planes, s.pitch_m, s.wavelengths_m, aperture=aperture).abs() ** 2
            ib = propagate(b, planes, s.pitch_m, s.wavelengths_m, aperture=aperture).abs() ** 2
            peak = float(torch.quantile(ib.flatten()[::7], 0.999))
            mse = float(((ia - ib) / peak).pow(2).mean())
            psnr = 10 * np.log10(1.0 / mse) if mse > 0 else float("inf")
            row["per_colour"] = {
                "views_rendered": per.n_views, "windows": [c.window for c in own],
                "total_s": per_s, "field_rel_l2_shared_vs_per_colour": err,
                "focal_stack_psnr_db_shared_vs_per_colour": psnr,
            }  # fmt: skip
            print(f"  {w} x {h}: per-colour views ({per.n_views}): total {per_s:.1f} s; shared "
                  f"vs per-colour field error R/G/B {err[0]:.3f}/{err[1]:.3f}/{err[2]:.3f}, "
                  f"focal-stack PSNR {psnr:.1f} dB", flush=True)  # fmt: skip
        results["sizes"][f"{w}x{h}"] = row
    results["machine"] = machine
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(f"wrote {out}")
    return 0
