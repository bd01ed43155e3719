"""`nhfd demo`: what the README's first command runs (the daemon demo), and `nhfd demo optics`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from nhfd.config import load_config
from nhfd.demos import serve as demo
from nhfd.demos.optics import contact_sheet, run_demo, sharpness


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run the daemon on the simulated bench: views, a focus sweep, captures -> out/demo",
        description="Start the daemon on the simulated bench with the shipped model "
        "(models/nhf-donut-512.onnx) and the donut scene, or with --model and --scene your own "
        "(the model must have been trained on that scene for the configured optics and panel), "
        "move the view along a short orbit, "
        "sweep the camera's focus from the near to the far end of the hologram volume with the "
        "green laser armed at its cap, and write the rendered views, the SLM phase frames, a "
        "contact sheet of the captures and summary.json (per-stage timings) to --out. "
        "`nhfd demo optics` is the optics-only demo (no model needed).",
    )
    p.add_argument("--config", help="configuration file (default: the search order)")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--model", default=str(demo.DEFAULT_MODEL), metavar="ONNX",
                   help="exported model, e.g. one `nhfd model build` made from your scene "
                   "(default: the shipped models/nhf-donut-512.onnx)")
    p.add_argument("--scene", default=str(demo.DEFAULT_SCENE), metavar="PATH",
                   help="the splat scene the model was trained on (default: the shipped "
                   "models/scenes/donut.ply)")
    p.set_defaults(handler=run_daemon_demo)
    which = p.add_subparsers(dest="which", metavar="optics", required=False)
    o = which.add_parser(
        "optics",
        help="propagate a three-depth test target through the display chain; write PNGs",
        description="Put the words NEAR, MID and FAR at three depths of the hologram volume, "
        "take their field through the display chain (reference plane -> SLM, double-phase "
        "coding, grey levels, Fourier aperture) and write a focal-stack contact sheet, the SLM "
        "frame and a summary to --out.",
    )
    o.add_argument("--config", help="configuration file (default: the search order)")
    o.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    o.set_defaults(handler=run)


def run_daemon_demo(args: argparse.Namespace) -> int:
    model, scene = Path(args.model), Path(args.scene)
    loaded = load_config(args.config)
    try:
        # Before the daemon starts: a missing file, or a model for another scene, optics or
        # panel (a ValueError naming both), is reported here instead of as a load that fails.
        demo.check_model_and_scene(model, scene, loaded.config)
    except FileNotFoundError as exc:
        print(f"nhfd demo: {exc}", file=sys.stderr)
        return 3
    print(f"nhfd demo: configuration {loaded.path or 'packaged default'}", flush=True)
    print(f"nhfd demo: model {model}, scene {scene}", flush=True)
    out = Path(args.out)
    summary = demo.run(out, config=loaded.config, model=model, scene=scene)
    med = summary["stages_ms_median"]
    print("  per-stage median (ms): " + ", ".join(f"{k} {v:.0f}" for k, v in med.items()))
    print(f"wrote {out / 'contact_sheet.png'}, {out / 'views'}/, {out / 'slm'}/, "
          f"{out / 'captures'}/, {out / 'summary.json'} in {summary['runtime_s']:.0f} s")
    return 0


def run(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    loaded = load_config(args.config)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"nhfd demo: configuration {loaded.path or 'packaged default'}", flush=True)
    result = run_demo(loaded.config)
    contact_sheet(result, out / "focal_stack.png")
    plt.imsave(out / "slm_green.png", result.slm_grey[1].numpy(), cmap="gray", vmin=0, vmax=255)
    focus = {}
    for word_i, (rows, z_word) in enumerate(zip(result.word_rows, result.word_depths_m,
                                                strict=True)):
        scores = [sharpness(result.shown_stack[d][:, rows]) for d in range(len(result.planes_m))]
        best = result.planes_m[max(range(len(scores)), key=scores.__getitem__)]
        focus[("NEAR", "MID", "FAR")[word_i]] = {"depth_mm": z_word * 1e3,
                                                 "sharpest_plane_mm": best * 1e3}
    summary = {
        "planes_mm": [z * 1e3 for z in result.planes_m],
        "focus": focus,
        "display_vs_complex_psnr_db": result.psnr_db,
        "clipped_fraction_rgb": result.clipped_fraction,
        "timings_s": result.timings_s,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    for word, f in focus.items():
        print(f"  {word:<4} at {f['depth_mm']:+.1f} mm: sharpest at {f['sharpest_plane_mm']:+.1f}"
              " mm")
    print(f"  phase-only display vs complex hologram: {result.psnr_db:.1f} dB focal-stack PSNR")
    print(f"wrote {out / 'focal_stack.png'}, {out / 'slm_green.png'}, {out / 'summary.json'}")
    return 0
