"""`nhfd bench tradeoff`: network size against speed and held-out quality (the paper's Fig. 3).

Every variant (the configured profiles, plus any --widths x --depths x --unshuffles x --growths
x --skips grid) is trained on the same reduced budget (--steps, said in the output), exported
to ONNX, and measured: parameter count, onnxruntime and torch latency per frame at --size on
--threads threads in the same run (their ratio reported, not assumed; every model is timed at
the end, the models taking turns in each of --repeats rounds), and held-out focal-stack PSNR/SSIM
(`nhfd eval`'s measure). --int8 adds onnxruntime's static int8 quantisation of each variant (QDQ,
per channel, the last layer kept in float32, calibrated on training views). Writes a table, a
JSON file and a PNG of PSNR against latency with the Pareto front marked. Where torch sees a
CUDA device and onnxruntime has its CUDA provider, each variant's fp16 model (`nhfd.models.half`)
is also timed there (`gpu fp16 ms`, host copies included); elsewhere that column says not
measured, and why. Runs are kept under
OUT/runs and resume; exports and evaluations are kept under OUT/models next to the step they were
made at, so a second call (on a quieter machine, say) only measures latency.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

from nhfd.benchmarks.machine import describe
from nhfd.cli.args import parse_wxh
from nhfd.config import (
    GROWTH_RANGE,
    LEARNING_RATE_RULE,
    SKIPS,
    ModelSettings,
    learning_rate_ok,
    load_config,
)
from nhfd.models.data import HoloData
from nhfd.models.evaluate import evaluate
from nhfd.models.export import CPU_ONLY, CUDA, GRAPH_FORM, OnnxModel, export_onnx
from nhfd.models.half import convert_fp16
from nhfd.models.net import parameter_count
from nhfd.models.quantise import quantise_int8
from nhfd.models.train import CHECKPOINT, TRAIN_LOG, TrainOptions, changed_options, load_run, train

# The quality gap issue 5 allows a fast variant against the best one.
WITHIN_DB = 2.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("tradeoff", help="network size vs latency vs held-out quality",
                       description=__doc__)  # fmt: skip
    p.add_argument("--data", required=True, help="dataset folder (nhfd dataset build)")
    p.add_argument("--profiles", default="all", help="comma-separated profiles, all, or none")
    p.add_argument("--widths", default="", help="grid: comma-separated base widths")
    p.add_argument("--depths", default="", help="grid: comma-separated depths")
    p.add_argument("--unshuffles", default="", help="grid: comma-separated unshuffle factors")
    p.add_argument("--growths", default="",
                   help="grid: comma-separated width growths per level (1 to 2)")
    p.add_argument("--skips", default="",
                   help=f"grid: comma-separated skip joins ({', '.join(SKIPS)})")
    p.add_argument("--steps", type=int, default=1000, help="training budget per variant")
    p.add_argument("--crop", default=None, help="training crop WxH (default: nhfd.toml)")
    p.add_argument("--lr", type=float, default=None,
                   help="Adam learning rate of every variant (default: nhfd.toml's, chosen for "
                        "the full budget; a reduced budget may want a higher one)")
    p.add_argument("--size", default="1024x576", help="latency frame WxH (default 1024x576)")
    p.add_argument("--threads", type=int, default=2, help="threads for latency (default 2)")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats; the median is kept")
    p.add_argument("--eval-views", type=int, default=4, help="held-out views per split")
    p.add_argument("--int8", action="store_true", help="also measure static int8 models")
    p.add_argument("--inputs", choices=("rgb", "rgbd"), default=None,
                   help="network inputs for every variant (default: each profile's)")
    p.add_argument("--out", default="out/bench/tradeoff", help="output folder")
    p.add_argument("--config", help="nhfd.toml to take [model] from")
    p.set_defaults(handler=run)


def _ints(text: str, name: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"{name} {text!r}: give comma-separated integers") from None
    if any(v <= 0 for v in values):
        raise ValueError(f"{name} {text!r}: values must be positive")
    return values


def _growths(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--growths {text!r}: give comma-separated numbers") from None
    lo, hi = GROWTH_RANGE
    if any(not lo <= v <= hi for v in values):
        raise ValueError(f"--growths {text!r}: each must be in [{lo:g}, {hi:g}]")
    return values


def _skips(text: str) -> list[str]:
    values = [v.strip() for v in text.split(",") if v.strip()]
    if any(v not in SKIPS for v in values):
        raise ValueError(f"--skips {text!r}: each must be one of {', '.join(SKIPS)}")
    return values


def variant_name(width: int, depth: int, unshuffle: int, growth: float,
                 skip: str = SKIPS[0]) -> str:  # fmt: skip
    """`w16-d3-u2`, with `-g1` appended where the width does not double per level and `-add`
    where the skips are summed."""
    doubling = growth == GROWTH_RANGE[1]
    return (f"w{width}-d{depth}-u{unshuffle}" + ("" if doubling else f"-g{growth:g}")
            + ("" if skip == SKIPS[0] else f"-{skip}"))  # fmt: skip


def variants(model: ModelSettings, profiles: str, widths: list[int], depths: list[int],
             unshuffles: list[int], growths: list[float] = (), skips: list[str] = ()
             ) -> list[tuple[str, str, int, int, int, float, str]]:  # fmt: skip
    """(name, profile, width, depth, unshuffle, growth, skip) of every variant, without
    duplicates: the `[model.profiles]` named in `profiles` ("all", "none" or a comma list), then
    the grid, whose missing axes take `[model].profile`'s values."""
    m = model
    names = [] if profiles == "none" else (
        sorted(m.profiles) if profiles == "all" else [p.strip() for p in profiles.split(",")]
    )  # fmt: skip
    out, seen = [], set()
    for n in names:
        if n not in m.profiles:
            raise ValueError(f"--profiles: {n!r} is not one of {', '.join(sorted(m.profiles))}")
        p = m.profiles[n]
        key = (p.width, p.depth, p.unshuffle, p.growth, p.skip)
        # the network's whole shape: two profiles may differ only in settings the grid keeps
        shape = (*key, p.single_conv_levels, p.deep_width)
        if shape not in seen:
            seen.add(shape)
            out.append((n, n, *key))
    base = m.profiles[m.profile]
    if widths or depths or unshuffles or growths or skips:
        grid = itertools.product(widths or [base.width], depths or [base.depth],
                                 unshuffles or [base.unshuffle], growths or [base.growth],
                                 skips or [base.skip])  # fmt: skip
        for key in grid:
            # grid variants keep the default profile's other settings (nhfd.models.train)
            shape = (*key, base.single_conv_levels, base.deep_width)
            if shape not in seen:
                seen.add(shape)
                out.append((variant_name(*key), m.profile, *key))
    if not out:
        raise ValueError("no variants: give --profiles and/or --widths/--depths/--unshuffles/"
                         "--growths/--skips")
    return out


def _kept(path: Path, stamp: dict) -> dict | None:
    """The export and evaluations recorded for a variant, if made at the same step and views."""
    try:
        kept = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    same = all(kept.get(k) == v for k, v in stamp.items())
    return kept if same and "evals" in kept else None


def interleaved_ms(fns: dict[str, Callable[[], object]], repeats: int,
                   settle_s: float = 0.05) -> dict[str, float]:
    """Median milliseconds of each call over `repeats` rounds in which the calls take turns, so
    that a busy spell of a shared machine slows every variant alike and their ratios hold (timed
    one after another, two variants' figures could come from a quiet and a busy minute). Each
    call starts `settle_s` after the previous one ended, untimed: thread pools that spin after a
    call (torch's OpenMP workers) would otherwise take the next call's cores."""
    for fn in fns.values():
        fn()  # warm-up
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for key, fn in fns.items():
            time.sleep(settle_s)
            t0 = time.perf_counter()
            fn()
            times[key].append(time.perf_counter() - t0)
    return {k: 1e3 * statistics.median(v) for k, v in times.items()}


GPU_PROVIDERS = (CUDA, *CPU_ONLY)


def gpu_unavailable() -> str | None:
    """Why the GPU column is not measured here (None: it is)."""
    import onnxruntime as ort
    import torch

    if not torch.cuda.is_available():
        return "not measured: no CUDA device"
    if GPU_PROVIDERS[0] not in ort.get_available_providers():
        return "not measured: this onnxruntime has no CUDAExecutionProvider (onnxruntime-gpu)"
    return None


def fp16_model(float_path: Path, exported_now: bool) -> Path:
    """The fp16 conversion of `float_path` beside it (`{stem}-fp16.onnx`), made (with its slow
    emulated check) only when it is missing or the float model was exported again in this call:
    a second call only measures latency."""
    half = float_path.with_name(f"{float_path.stem}-fp16.onnx")
    if exported_now or not half.is_file():
        convert_fp16(float_path, half)
    return half


def finished_run(run_dir: Path, opts, manifest_key: str | None
                 ) -> tuple[int, float, str] | None:
    """(step, median ms per training step, note) of a run already trained to `opts.steps`,
    or None. A finished run is measured as it is, also when it was trained on another build of
    the dataset (another machine's build differs in the last bits of its poses, which changes
    the manifest key): the note says so. Its network and recipe must be the variant's."""
    import csv

    import torch

    path = run_dir / CHECKPOINT
    if not path.is_file():
        return None
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    if int(ckpt["step"]) < opts.steps:
        return None
    # The profile is only a name here: a variant's network, inputs and recipe are compared in
    # full, and a grid variant carries whichever profile was the default when it was trained.
    changed = changed_options(ckpt, opts, ignore=frozenset({"profile"}))
    if changed:
        raise ValueError(f"{run_dir} was trained otherwise than this variant ({changed}); use "
                         "another --out")  # fmt: skip
    with open(run_dir / TRAIN_LOG, newline="") as f:
        seconds = [float(r["seconds"]) for r in csv.DictReader(f)]
    note = ""
    if ckpt.get("manifest_key") != manifest_key:
        note = (f"trained on another build of the dataset (manifest key "
                f"{str(ckpt.get('manifest_key'))[:12]}, this one {str(manifest_key)[:12]}); "
                "measured and evaluated on this one")  # fmt: skip
    return int(ckpt["step"]), 1e3 * statistics.median(seconds) if seconds else 0.0, note


def fastest_within(rows: list[dict], db: float) -> tuple[dict, dict]:
    """The best variant (highest PSNR) and the fastest whose PSNR is within `db` of it (issue 5
    asks for one at or under 40 ms within 2 dB)."""
    best = max(rows, key=lambda r: r["psnr_db"])
    near = [r for r in rows if r["psnr_db"] >= best["psnr_db"] - db]
    return best, min(near, key=lambda r: r["onnxruntime_ms"])


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of points (latency, psnr) that no other point beats on both."""
    front = []
    for i, (lat, q) in enumerate(points):
        if not any((l2 <= lat and q2 >= q) and (l2 < lat or q2 > q) for l2, q2 in points):
            front.append(i)
    return sorted(front, key=lambda i: points[i][0])


def run(args: argparse.Namespace) -> int:
    w, h = parse_wxh(args.size, "--size")
    crop = parse_wxh(args.crop, "--crop") if args.crop else None
    widths = _ints(args.widths, "--widths")
    depths = _ints(args.depths, "--depths")
    unshuffles = _ints(args.unshuffles, "--unshuffles")
    growths = _growths(args.growths)
    skips = _skips(args.skips)
    if args.lr is not None and not learning_rate_ok(args.lr):
        raise ValueError(f"--lr {args.lr:g}: {LEARNING_RATE_RULE}")
    for name in ("steps", "threads", "repeats", "eval_views"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} {getattr(args, name)}: must be positive")
    bad = [u for u in unshuffles if u not in (1, 2, 4, 8)]
    if bad:
        raise ValueError(f"--unshuffles {args.unshuffles!r}: each must be 1, 2, 4 or 8")
    if not Path(args.data).is_dir():
        raise FileNotFoundError(f"--data {args.data}: no such dataset folder")

    config = load_config(args.config).config
    todo = variants(config.model, args.profiles, widths, depths, unshuffles, growths, skips)

    import numpy as np
    import torch

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = HoloData(args.data, max_views={"interp": args.eval_views, "extrap": args.eval_views})
    machine = describe()
    lr = args.lr if args.lr is not None else config.model.train.learning_rate
    print(f"{len(todo)} variants, each trained for {args.steps} steps (a reduced budget) at "
          f"learning rate {lr:g}; "
          f"latency at {w}x{h} on {args.threads} threads; {machine}", flush=True)
    rows, timed = [], {}
    no_gpu = gpu_unavailable()
    gpu_timed: dict[str, Callable[[], object]] = {}
    print(f"GPU column: {no_gpu or 'fp16 on onnxruntime CUDA'}", flush=True)
    for name, profile, width, depth, unshuffle, growth, skip in todo:
        crop_kw = {"crop_width_px": crop[0], "crop_height_px": crop[1]} if crop else {}
        opts = TrainOptions.from_config(config.model, profile, width=width, depth=depth,
                                        unshuffle=unshuffle, growth=growth, skip=skip,
                                        steps=args.steps, learning_rate=args.lr,
                                        val_views=args.eval_views,
                                        inputs=args.inputs, **crop_kw)  # fmt: skip
        run_dir = out / "runs" / name
        finished = finished_run(run_dir, opts, data.manifest.get("key"))
        if finished is None:
            train(args.data, run_dir, opts, data=data)
            finished = finished_run(run_dir, opts, data.manifest.get("key"))
        assert finished is not None
        step, ms_per_step, note = finished
        if note:
            print(f"  {name}: {note}", flush=True)
        net, info = load_run(run_dir)
        # an export made by another graph form is made again (its latency would be stale)
        stamp = {"step": step, "eval_views": args.eval_views, "graph": GRAPH_FORM}
        kept = _kept(out / "models" / f"{name}.json", stamp)
        files = [out / "models" / f"{name}{tag}.onnx" for tag in ("", "-int8")[: 1 + args.int8]]
        exported_now = kept is None or not all(f.is_file() for f in files)
        if exported_now:
            exported = export_onnx(run_dir, out / "models" / f"{name}.onnx")
            kept = {**stamp, "max_abs_diff": exported.max_abs_diff, "evals": {}}
            if args.int8:
                quantise_int8(exported.path, out / "models" / f"{name}-int8.onnx", data,
                              net.spec.multiple, net.spec.inputs)  # fmt: skip
        models = [(name, out / "models" / f"{name}.onnx", kept["max_abs_diff"])]
        if args.int8:
            models.append((f"{name}-int8", out / "models" / f"{name}-int8.onnx", float("nan")))
        m = net.spec.multiple
        x = np.random.default_rng(0).random((1, net.spec.channels, h + (-h) % m, w + (-w) % m),
                                            np.float32)  # fmt: skip
        xt = torch.from_numpy(x)
        timed[f"torch:{name}"] = lambda n=net, t=xt: n(t)
        if no_gpu is None:
            half = fp16_model(out / "models" / f"{name}.onnx", exported_now)
            gpu_model = OnnxModel(half, providers=GPU_PROVIDERS)
            gpu_timed[name] = lambda om=gpu_model, xx=x: om.run_raw(xx)
        for label, path, diff in models:
            if label not in kept["evals"]:
                ev = evaluate(path, args.data, data=data, log=lambda _m: None)
                kept["evals"][label] = ev["summary"]["all"]
                (out / "models" / f"{name}.json").write_text(json.dumps(kept, indent=1))
            ort_model = OnnxModel(path, threads=args.threads)
            timed[label] = lambda om=ort_model, xx=x: om.run_raw(xx)
            s = kept["evals"][label]
            rows.append({
                "name": label, "profile": profile, "width": width, "depth": depth,
                "unshuffle": unshuffle, "growth": growth, "skip": skip,
                "inputs": net.spec.inputs, "int8": label.endswith("-int8"),
                "parameters": parameter_count(net), "steps": step,
                "train_ms_per_step": ms_per_step,
                "trained_on": info["options"].get("device", "cpu"),
                "psnr_db": s["model_psnr_db"], "ssim": s["model_ssim"],
                "psnr_2d_db": s["hologram_2d_psnr_db"], "focus_bins_passed":
                f"{s['focus_bins_passed']}/{s['focus_bins']}", "onnx_vs_torch_max_abs": diff,
                "torch_key": f"torch:{name}",
            })  # fmt: skip
    print(f"timing {len(timed)} models in {args.repeats} interleaved rounds", flush=True)
    torch.set_num_threads(args.threads)
    with torch.no_grad():
        ms = interleaved_ms(timed, args.repeats)
    gpu_ms = interleaved_ms(gpu_timed, args.repeats) if gpu_timed else {}
    for r in rows:
        r["onnxruntime_ms"], r["torch_ms"] = ms[r["name"]], ms[r.pop("torch_key")]
        r["gpu_fp16_ms"] = gpu_ms.get(r["name"])  # None: not measured (see report["gpu"])
        r["torch_over_onnxruntime"] = r["torch_ms"] / r["onnxruntime_ms"]
        print(f"  {r['name']:<18} {r['parameters']:>8} params  ort {r['onnxruntime_ms']:7.1f} "
              f"ms  torch {r['torch_ms']:7.1f} ms  PSNR {r['psnr_db']:6.2f} dB  SSIM "
              f"{r['ssim']:.3f}", flush=True)  # fmt: skip
    front = pareto([(r["onnxruntime_ms"], r["psnr_db"]) for r in rows])
    for i, r in enumerate(rows):
        r["pareto"] = i in front
    print_table(rows)
    best, near = fastest_within(rows, WITHIN_DB)
    print(f"best: {best['name']} {best['psnr_db']:.2f} dB; fastest within {WITHIN_DB:g} dB of "
          f"it: {near['name']} {near['psnr_db']:.2f} dB at {near['onnxruntime_ms']:.1f} ms")
    report = {"machine": machine, "budget_steps": args.steps, "learning_rate": lr,
              "size_wh": [w, h],
              "threads": args.threads, "data": str(Path(args.data).resolve()), "rows": rows,
              "gpu": no_gpu or f"fp16 on onnxruntime CUDA, {torch.cuda.get_device_name()}",
              "fastest_within_db": {"db": WITHIN_DB, "name": near["name"]}}
    (out / "tradeoff.json").write_text(json.dumps(report, indent=1))
    plot(rows, out / "tradeoff.png", args.steps, (w, h), args.threads)
    print(f"wrote {out / 'tradeoff.json'} and {out / 'tradeoff.png'}")
    return 0


def print_table(rows: list[dict]) -> None:
    print(f"{'variant':<18}{'params':>9}{'ort ms':>9}{'torch ms':>10}{'torch/ort':>10}"
          f"{'gpu fp16 ms':>14}{'PSNR dB':>9}{'SSIM':>7}{'2D dB':>7}{'focus':>7}"
          "  pareto")  # fmt: skip
    for r in rows:
        gpu = r.get("gpu_fp16_ms")
        print(f"{r['name']:<18}{r['parameters']:>9}{r['onnxruntime_ms']:>9.1f}"
              f"{r['torch_ms']:>10.1f}{r['torch_over_onnxruntime']:>10.2f}"
              f"{'not measured' if gpu is None else f'{gpu:.2f}':>14}{r['psnr_db']:>9.2f}"
              f"{r['ssim']:>7.3f}{r['psnr_2d_db']:>7.2f}{r['focus_bins_passed']:>7}  "
              f"{'*' if r['pareto'] else ''}")  # fmt: skip


def plot(rows: list[dict], path: Path, steps: int, size: tuple[int, int], threads: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for r in rows:
        ax.scatter(r["onnxruntime_ms"], r["psnr_db"], marker="s" if r["int8"] else "o",
                   color="C1" if r["pareto"] else "C0")  # fmt: skip
        ax.annotate(r["name"], (r["onnxruntime_ms"], r["psnr_db"]), fontsize=7,
                    xytext=(3, 3), textcoords="offset points")  # fmt: skip
    front = sorted((r for r in rows if r["pareto"]), key=lambda r: r["onnxruntime_ms"])
    ax.plot([r["onnxruntime_ms"] for r in front], [r["psnr_db"] for r in front], "C1--",
            label="Pareto front")  # fmt: skip
    if rows:
        ax.axhline(rows[0]["psnr_2d_db"], color="grey", lw=0.8, label="2D hologram")
        best = max(r["psnr_db"] for r in rows)
        ax.axhline(best - WITHIN_DB, color="C2", lw=0.8, ls=":",
                   label=f"{WITHIN_DB:g} dB below the best")  # fmt: skip
    ax.set_xlabel(f"onnxruntime ms per {size[0]}x{size[1]} frame ({threads} threads)")
    ax.set_ylabel("held-out focal-stack PSNR (dB)")
    ax.set_title(f"speed vs quality, {steps} training steps each", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
