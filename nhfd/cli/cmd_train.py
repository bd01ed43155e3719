"""`nhfd train|eval|export`: the NHF network (nhfd.models).

Imports torch, onnx and onnxruntime (through nhfd.models); `nhfd` imports this module only for
these three commands.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from nhfd.cli.args import parse_wxh
from nhfd.config import GROWTH_RANGE, SKIPS, load_config
from nhfd.models.data import HoloData
from nhfd.models.evaluate import evaluate
from nhfd.models.export import OnnxModel, export_onnx
from nhfd.models.half import CHECK_KEY as FP16_CHECK_KEY
from nhfd.models.half import convert_fp16
from nhfd.models.quantise import (
    HELDOUT_KEY,
    INT8_MAX_LOSS_DB,
    QUANTISED_OPS,
    int8_within_loss,
    quantise_int8,
    record_heldout_loss,
)
from nhfd.models.train import TrainOptions, train

TRAIN_HELP = """\
Train the U-Net that maps a view to its reference-plane hologram, with the focal-stack loss, on a
dataset folder from `nhfd dataset build`. Seeded; checkpoints every --checkpoint-every steps
and at the end; running the same command again resumes where it stopped, with the same data
order (--steps may be raised to continue). Writes RUN/train_log.csv, val_log.csv (interpolation
and extrapolation views, every epoch), curves.png and run.json. Defaults: nhfd.toml [model].

On several processes or machines, start it under torchrun (DistributedDataParallel; gloo on the
CPU, nccl on GPUs; --batch must be a multiple of the number of processes, which share each
step's views):  torchrun --nproc-per-node 2 --standalone -m nhfd.cli.main train ...
Across machines: torchrun --nnodes 2 --node-rank R --rdzv-backend c10d
--rdzv-endpoint HOST:29500 --nproc-per-node P -m nhfd.cli.main train ... (the same --data and
--out paths on every machine; rank 0 writes the run folder).
"""


def _positive(name: str, value: int | float | None) -> None:
    if value is not None and value <= 0:
        raise ValueError(f"{name} {value}: must be positive")


def register(sub: argparse._SubParsersAction) -> None:
    t = sub.add_parser("train", help="train the NHF network on a dataset", description=TRAIN_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    t.add_argument("--data", required=True, help="dataset folder (nhfd dataset build)")
    t.add_argument("--out", required=True, help="run folder (checkpoints, logs)")
    t.add_argument("--profile", help="network profile from nhfd.toml [model.profiles]")
    t.add_argument("--width", type=int, help="override the profile's base width")
    t.add_argument("--depth", type=int, help="override the profile's depth")
    t.add_argument("--growth", type=float,
                   help="override the profile's width growth per level (1 keeps the width, "
                        "2 doubles it at each level)")
    t.add_argument("--skip", choices=SKIPS,
                   help="override how the profile's decoder joins each skip: side by side "
                        "(concat, the classic U-Net) or summed (add: cheaper)")
    t.add_argument("--single-conv-levels", type=int,
                   help="override how many levels, from the first, have one 3x3 convolution "
                        "per block instead of two (0: the classic U-Net)")
    t.add_argument("--deep-width", type=int,
                   help="override the channels of the second level (0: width x growth; the "
                        "growth applies below it)")
    t.add_argument("--unshuffle", type=int, help="override the profile's unshuffle factor")
    t.add_argument("--inputs", choices=("rgb", "rgbd"),
                   help="override the profile's inputs: sRGB, or sRGB plus the mapped depth")
    t.add_argument("--steps", type=int, help="budget in optimiser steps")
    t.add_argument("--batch", type=int, help="views per step")
    t.add_argument("--crop", help="training crop WxH (nhfd.toml: 384x224; smaller than the "
                   "view, so the network learns content near and across the window's edge)")
    t.add_argument("--lr", type=float, help="Adam learning rate")
    t.add_argument("--seed", type=int, help="seed of everything random")
    t.add_argument("--planes", choices=("depth", "uniform"), help="how the loss picks planes")
    t.add_argument("--perceptual", choices=("ssim", "vgg", "none"), help="perceptual term")
    t.add_argument("--field-weight", type=float,
                   help="weight of the frequency-weighted error of the complex field itself, "
                        "which makes depth errors count (nhfd.toml: 0.05; 0 turns it off)")
    t.add_argument("--vgg-weights", help="local torchvision VGG-16 weights (for --perceptual vgg)")
    t.add_argument("--checkpoint-every", type=int, help="steps between checkpoints")
    t.add_argument("--val-views", type=int, help="held-out views per split validated per epoch")
    t.add_argument("--threads", type=int, help="torch threads (0: torch's default)")
    t.add_argument("--device", help="torch device to train on: cpu (default), cuda, cuda:N or "
                   "auto (CUDA if torch sees one)")
    t.add_argument("--force", action="store_true", help="start over in an existing run folder")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.add_argument("--config", help="nhfd.toml to read [model] from")
    t.set_defaults(handler=run_train)

    e = sub.add_parser("eval", help="hologram quality of a run or .onnx on held-out views",
                       description=__doc__)  # fmt: skip
    e.add_argument("model", help="run folder (nhfd train) or exported .onnx")
    e.add_argument("--data", required=True, help="dataset folder")
    e.add_argument("--splits", default="interp,extrap", help="comma-separated splits")
    e.add_argument("--max-views", type=int, help="at most this many views per split")
    e.add_argument("--out", help="folder for eval.json and eval.png (default: RUN/eval or "
                   "beside the .onnx)")  # fmt: skip
    e.set_defaults(handler=run_eval)

    x = sub.add_parser("export", help="export a run to ONNX (checked against torch)")
    x.add_argument("run", help="run folder (nhfd train), or an exported float .onnx to convert "
                   "with --fp16 / --int8 (a shipped model has no run folder)")
    x.add_argument("-o", "--out", help="the .onnx file to write (needed for a run folder)")
    x.add_argument("--opset", type=int, default=18, help="ONNX opset, 18 or newer (default 18)")
    x.add_argument("--no-check", action="store_true", help="skip the onnxruntime check")
    x.add_argument("--int8", metavar="OUT_INT8",
                   help="also write a static int8 model here (QDQ, per channel, the output "
                        "layers in float32), calibrated on --data's training views")
    x.add_argument("--data", help="dataset folder for --int8's calibration (its training "
                   "views) and its held-out loss (the interpolation and extrapolation views)")
    x.add_argument("--int8-eval-views", type=int, default=None, metavar="N",
                   help="held-out views per split the int8 model's loss is measured on and "
                        "recorded in its file (default: all; 0: not measured, and the daemon "
                        "then serves the float model)")
    x.add_argument("--fp16", metavar="OUT_FP16",
                   help="also write an fp16 model here (float16 weights and compute, float32 "
                        "inputs and outputs, the softplus in float32; nhfd.models.half)")
    x.set_defaults(handler=run_export)


def run_train(args: argparse.Namespace) -> int:
    config = load_config(args.config).config
    for name in ("steps", "batch", "lr", "checkpoint_every", "val_views", "width"):
        _positive("--" + name.replace("_", "-"), getattr(args, name))
    if args.threads is not None and args.threads < 0:
        raise ValueError(f"--threads {args.threads}: must be >= 0")
    if args.depth is not None and not 0 <= args.depth <= 6:
        raise ValueError(f"--depth {args.depth}: must be in 0..6")
    if args.unshuffle is not None and args.unshuffle not in (1, 2, 4, 8):
        raise ValueError(f"--unshuffle {args.unshuffle}: must be 1, 2, 4 or 8")
    lo, hi = GROWTH_RANGE
    if args.growth is not None and not lo <= args.growth <= hi:
        raise ValueError(f"--growth {args.growth:g}: must be in [{lo:g}, {hi:g}]")
    if not Path(args.data).is_dir():
        raise FileNotFoundError(f"--data {args.data}: no such dataset folder")
    crop = parse_wxh(args.crop, "--crop", 8192) if args.crop else (None, None)

    options = TrainOptions.from_config(
        config.model, args.profile, width=args.width, depth=args.depth, unshuffle=args.unshuffle,
        inputs=args.inputs, growth=args.growth, skip=args.skip,
        single_conv_levels=args.single_conv_levels, deep_width=args.deep_width,
        steps=args.steps, batch=args.batch,
        crop_width_px=crop[0], crop_height_px=crop[1],
        learning_rate=args.lr, seed=args.seed, plane_mode=args.planes,
        perceptual=args.perceptual, vgg_weights=args.vgg_weights, field_weight=args.field_weight,
        checkpoint_every=args.checkpoint_every, val_views=args.val_views, threads=args.threads,
        device=args.device, progress=not args.no_progress,
    )  # fmt: skip
    result = train(args.data, args.out, options, force=args.force)
    if int(os.environ.get("RANK", "0") or 0) != 0:
        return 0  # under torchrun, rank 0 reports for the job
    print(f"{result.run_dir}: step {result.step}, loss {result.last_loss:.4g}, "
          f"{result.seconds_per_step * 1e3:.0f} ms per step"
          + (f" (resumed at step {result.resumed_from})" if result.resumed_from else ""))
    return 0


def run_eval(args: argparse.Namespace) -> int:
    splits = tuple(s.strip() for s in args.splits.split(",") if s.strip())
    bad = [s for s in splits if s not in ("train", "interp", "extrap")]
    if bad or not splits:
        raise ValueError(f"--splits {args.splits!r}: use train, interp and/or extrap")
    _positive("--max-views", args.max_views)
    model = Path(args.model)
    if not model.exists():
        raise FileNotFoundError(f"{model}: no such run folder or .onnx file")
    out = Path(args.out) if args.out else (
        model.parent / (model.stem + "_eval") if model.suffix == ".onnx"
        else model / "eval"
    )  # fmt: skip

    result = evaluate(model, args.data, splits=splits, max_views=args.max_views, out_dir=out)
    print(f"wrote {out / 'eval.json'}" + (f" and {result['png']}" if "png" in result else ""))
    return 0


def _record_int8_loss(float_path: Path, int8_path: Path, data_dir: str,
                      views: int | None) -> dict:
    """Held-out PSNR of the float and the int8 model on `data_dir`'s interpolation and
    extrapolation views (at most `views` per split; None: all), recorded in the int8 file
    (`record_heldout_loss`): `daemon.frames.int8 = "auto"` serves it on the CPU within
    INT8_MAX_LOSS_DB (`int8_within_loss`)."""
    data = HoloData(data_dir, splits=("interp", "extrap"),
                    max_views={"interp": views, "extrap": views} if views else None)
    if not len(data.splits["interp"]) + len(data.splits["extrap"]):
        raise ValueError(f"--data {data_dir}: no held-out (interp, extrap) views to measure the "
                         "int8 model's loss on; --int8-eval-views 0 skips the measurement")
    quiet = lambda _line: None  # noqa: E731
    psnr = {name: evaluate(path, data_dir, data=data, log=quiet)["summary"]["all"]
            for name, path in (("float", float_path), ("int8", int8_path))}
    record = record_heldout_loss(int8_path, float_path,
                                 float_psnr_db=psnr["float"]["model_psnr_db"],
                                 int8_psnr_db=psnr["int8"]["model_psnr_db"],
                                 views=int(psnr["int8"]["views"]))  # fmt: skip
    served = ("served on the CPU by default" if int8_within_loss(record["loss_vs_float_db"])
              else f"more than {INT8_MAX_LOSS_DB:g} dB: the float one serves")
    print(f"{int8_path}: held-out PSNR {record['int8_psnr_db']:.2f} dB against float "
          f"{record['float_psnr_db']:.2f} dB on {record['views']} views "
          f"({-record['loss_vs_float_db']:+.2f} dB; recorded in the file, {served})")
    return record


def _refuse_reduced(source: Path, metadata: dict) -> None:
    """ValueError unless the .onnx `source` is a float32 model: --fp16 and --int8 convert only
    that. An fp16 file says so in its metadata; an int8 one carries its float model's metadata
    (precision fp32), so it is known by its held-out record or its quantised operators."""
    import onnx

    precision = metadata.get("precision", "fp32")
    if precision != "fp32":
        raise ValueError(f"{source}: precision {precision!r}, not fp32; give the float32 model "
                         "to convert")
    graph = onnx.load(str(source), load_external_data=False).graph
    why = sorted({n.op_type for n in graph.node} & QUANTISED_OPS)
    if HELDOUT_KEY in metadata:
        why.append(f"metadata {HELDOUT_KEY}")
    if why:
        raise ValueError(f"{source}: an int8 model ({', '.join(why)}); give the float32 model "
                         "to convert")


def run_export(args: argparse.Namespace) -> int:
    if args.opset < 18:
        raise ValueError(f"--opset {args.opset}: must be 18 or newer")
    source = Path(args.run)
    from_onnx = source.suffix == ".onnx"
    if from_onnx:
        if not source.is_file():
            raise FileNotFoundError(f"{source}: no such .onnx file")
        if args.out:
            raise ValueError(f"-o {args.out}: {source} is already exported; give --fp16 and/or "
                             "--int8 to convert it")  # fmt: skip
        if not (args.fp16 or args.int8):
            raise ValueError(f"{source}: an .onnx source needs --fp16 OUT_FP16 and/or --int8 "
                             "OUT_INT8")  # fmt: skip
    elif not source.is_dir():
        raise FileNotFoundError(f"{args.run}: no such run folder or .onnx file")
    elif not args.out:
        raise ValueError(f"{args.run}: exporting a run folder needs -o OUT.onnx")
    if args.int8_eval_views is not None and args.int8_eval_views < 0:
        raise ValueError(f"--int8-eval-views {args.int8_eval_views}: must be 0 (not measured) or "
                         "a positive number of views per split")
    if args.int8 and not (args.data and Path(args.data).is_dir()):
        raise ValueError(f"--int8 needs --data: a dataset folder to calibrate on (got "
                         f"{args.data!r})")  # fmt: skip
    if args.fp16 and Path(args.fp16).suffix != ".onnx":
        raise ValueError(f"--fp16 {args.fp16}: the fp16 model's file name must end in .onnx")
    if args.fp16 and Path(args.fp16).is_dir():
        raise ValueError(f"--fp16 {args.fp16}: a folder; give the .onnx file to write")

    if from_onnx:
        float_model = OnnxModel(source)  # refuses a file that is not an nhfd model
        _refuse_reduced(source, float_model.metadata)  # before anything is written
        res = None
        m = float_model.metadata
        inputs = float_model.inputs
        report: dict = {"path": str(source)}
    else:
        res = export_onnx(args.run, args.out, opset=args.opset, check=not args.no_check)
        m = res.metadata
        inputs = next(iter(m["inputs"]))  # the graph's input name ("rgb" or "rgbd") and its note
        print(f"{res.path}: profile {m['profile']}, {m['parameters']} parameters, input "
              f"multiple {m['input_multiple']}, opset {m['opset']}")  # fmt: skip
        if not args.no_check:
            sizes = ", ".join(f"{w}x{h}" for h, w in res.checked_sizes)
            print(f"onnxruntime vs torch: max abs difference {res.max_abs_diff:.3g} ({sizes})")
        report = {"path": str(res.path), "max_abs_diff": res.max_abs_diff}
    float_path = source if res is None else res.path
    if args.fp16:
        h = convert_fp16(float_path, Path(args.fp16))  # refuses one that overflows
        d = OnnxModel(h).metadata[FP16_CHECK_KEY]  # its comparison, made while converting
        print(f"{h}: fp16 ({h.stat().st_size} bytes against {float_path.stat().st_size}); "
              f"computed in float16 (emulated) vs float32: amplitude max abs difference "
              f"{d['amplitude_max_abs_diff']:.3g} (of {d['amplitude_max']:.3g}), phase "
              f"{d['phase_max_abs_diff']:.3g} rad; finite on the extreme inputs")  # fmt: skip
        report["fp16_path"] = str(h)
        report["fp16_vs_float"] = d
    if args.int8:
        data = HoloData(args.data, max_views={"interp": 1, "extrap": 1})
        q = quantise_int8(float_path, Path(args.int8), data, int(m["input_multiple"]), inputs)
        print(f"{q}: static int8, calibrated on {args.data}")
        report["int8_path"] = str(q)
        if args.int8_eval_views != 0:  # the figure the daemon serves int8 by, inside the file
            report["int8_heldout"] = _record_int8_loss(float_path, q, args.data,
                                                       args.int8_eval_views)
    json.dump(report, sys.stdout)
    print()
    return 0
