"""`nhfd model build SCENE`: a splat scene to an evaluated, exported (and served) model.

Imports torch, onnx and onnxruntime (through nhfd.models); `nhfd` imports this module only for
this command.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from nhfd.calibration import Calibration, check_bench
from nhfd.cli.args import parse_wxh
from nhfd.config import Config, load_config
from nhfd.daemon.client import Client, DaemonUnavailable
from nhfd.daemon.paths import socket_path
from nhfd.daemon.protocol import RpcError
from nhfd.model_info import SUBFRAMES_RANGE
from nhfd.models.build import STAGES, Recipe, resolve_device, run_build
from nhfd.models.export import compare_with_torch
from nhfd.models.metadata import SIZE_TOLERANCE
from nhfd.models.quantise import INT8_MAX_LOSS_DB, int8_sibling
from nhfd.models.sizes import (
    check_sizes,
    read_metadata,
    record_checked_sizes,
    sizes_to_check,
)
from nhfd.models.train import load_run, training_device
from nhfd.pipeline import tune
from nhfd.pipeline.view import scene_from_file
from nhfd.scene.cameras import parse_axis
from nhfd.scene.io import SCENE_SUFFIXES

BUILD_HELP = f"""\
Choose the poses around the scene, reduce the scene to what they can show (nhfd scene reduce),
build the dataset, train, export (float32, and int8 where it stays within {INT8_MAX_LOSS_DB:g} dB of
it),
evaluate the held-out views against the 2D-hologram and black baselines with the focus check,
and write OUT/report.json and OUT/contact_sheet.png.
Stages: {", ".join(STAGES)}.
Interrupted builds resume (run the same command again): finished stages
are skipped, the dataset keeps its shards and training its checkpoint. A folder built from
another scene, recipe or settings is refused unless --force. Recipes: nhfd.toml
[model.build.profiles] (quick: a first look in minutes; default: the shipped model's recipe).
With --calibration FILE, a last stage tunes the model through that bench's calibration (`nhfd
model tune`, on the build's training poses) into OUT/tuned/model.onnx (resumed like the others);
the calibration and the tuning's settings are checked before anything is built.
With --serve, the scene and the model (the tuned one with --calibration) are loaded into the
running daemon (`nhfd serve`).
"""
# Where `nhfd model build --calibration` tunes the built model (model.onnx, tune.json,
# checkpoint.pt).
TUNED_DIR = "tuned"


# How long --serve waits for the daemon to load the scene, then the model.
LOAD_TIMEOUT_S = 600.0

CHECK_SIZES_HELP = """\
Run the model at each size and record the result in its metadata (checked_sizes), which the
daemon reads: it refuses a frame window whose size the model was not checked at unless
[daemon.frames] allow_unchecked_sizes = true. With --run, each size is compared with the run's torch
network (as `nhfd export` does); without, the full-size inference is compared with the same
graph run on overlapping tiles of the training window's size, beyond its receptive margin (a
convolutional network computes the same function at every size away from its borders), and
must be finite. Exits 1 when a size fails (recorded as failed)."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("model", help="a scene to a served model in one command",
                       description=__doc__)  # fmt: skip
    cmds = p.add_subparsers(dest="model_command", metavar="COMMAND", required=True)
    b = cmds.add_parser("build", help="build (or resume) a scene's model", description=BUILD_HELP,
                        formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    b.add_argument("scene", help="splat scene (.ply, .compressed.ply, .splat, .spz, .glb, .sog)")
    b.add_argument("--profile", help="recipe from nhfd.toml [model.build.profiles] "
                   "(default: [model.build].profile)")
    b.add_argument("--out", help="output folder (default builds/SCENE-PROFILE)")
    b.add_argument("--device", default="auto",
                   help="where to train: cpu, cuda, cuda:N or auto (CUDA if torch sees one)")
    b.add_argument("--workers", type=int, help="dataset processes (default: every core)")
    b.add_argument("--up", help="scene up axis (default: declared or detected), e.g. --up=-y")
    b.add_argument("--force", action="store_true",
                   help="replace a build made from another scene, recipe or settings")
    b.add_argument("--serve", action="store_true",
                   help="then load the scene and the model into the running daemon")
    b.add_argument("--socket", help="the daemon's control socket (default: the configured one)")
    b.add_argument("--model-dir", help="folder the daemon loads models from, to copy the model "
                   "into (default: the first of daemon.paths.model_dirs, from here)")
    b.add_argument("--scene-dir", help="folder the daemon loads scenes from, to copy the scene "
                   "into (default: the first of daemon.paths.scene_dirs, from here)")
    b.add_argument("--no-progress", action="store_true", help="no progress bars")
    b.add_argument("--config", help="nhfd.toml to read the recipes and the optics from")
    d = tune.TuneSettings()
    b.add_argument("--calibration", help="then tune the model through this bench's calibration "
                   f"(nhfd model tune) as a last stage, into OUT/{TUNED_DIR}/model.onnx")
    tune_budget_arguments(b, d, "tune-")
    b.set_defaults(handler=run_model_build)
    c = cmds.add_parser("check-sizes", help="check a model at more input sizes and record them",
                        description=CHECK_SIZES_HELP)  # fmt: skip
    c.add_argument("model", help="an exported model (.onnx); its metadata is rewritten in place")
    c.add_argument("--sizes", nargs="+", metavar="WxH",
                   help="window sizes, width x height, e.g. 1920x1080 (rounded up to the model's "
                   "input multiple; default: its training window, 1024x576 and 1920x1080)")
    c.add_argument("--run", help="the run folder it was exported from: compare with its torch "
                   "network (default: the ONNX-only tile check)")
    c.set_defaults(handler=run_check_sizes)
    t = cmds.add_parser("tune", help="tune a scene's model through one bench's model",
                        description=tune.__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    t.add_argument("model", help="the exported model (.onnx) to tune (not changed)")
    t.add_argument("--scene", required=True, help="the splat scene the model was built from")
    t.add_argument("--calibration", required=True, help="the bench's calibration.toml")
    t.add_argument("--out", required=True, help="output folder: model.onnx, tune.json and "
                   "checkpoint.pt (an interrupted run resumes from it)")
    t.add_argument("--dataset", help="the model's dataset folder, for its training poses "
                   "(default: the poses the model records, else a grid over its pose "
                   "envelope: 12 poses, 27 for more than 12 --views)")
    d = tune.TuneSettings()
    tune_budget_arguments(t, d)
    t.add_argument("--ssim-weight", type=float, default=d.ssim_weight,
                   help=f"the structural term's weight beside the MSE (default {d.ssim_weight:g})")
    t.add_argument("--device", default=d.device, help="cpu or cuda[:N] (default cpu)")
    t.add_argument("--config", help="configuration file (default: the search order)")
    t.set_defaults(handler=run_model_tune)


def tune_budget_arguments(p: argparse.ArgumentParser, d: tune.TuneSettings,
                          prefix: str = "") -> None:
    """The tuning's budget and window, `--{prefix}steps`, `--{prefix}seconds`, `--{prefix}views`
    and `--{prefix}size`, with `d`'s values as defaults (`nhfd model tune`; `nhfd model build`'s
    last stage with the prefix "tune-")."""
    p.add_argument(f"--{prefix}steps", type=int, default=d.steps,
                   help=f"the tuning's steps (default {d.steps})")
    p.add_argument(f"--{prefix}seconds", type=float, default=d.seconds,
                   help=f"the tuning's time budget in all, s (default {d.seconds:g})")
    p.add_argument(f"--{prefix}views", type=int, default=d.views,
                   help=f"training views to tune on (default {d.views})")
    p.add_argument(f"--{prefix}size", default=f"{d.window_hw[1]}x{d.window_hw[0]}",
                   help="the tuning's frame window WxH (default %(default)s)")
    lo, hi = SUBFRAMES_RANGE
    p.add_argument(f"--{prefix}subframes", type=int, default=d.subframes, metavar="K",
                   help=f"frames per inference, {lo}..{hi}: K heads tuned jointly on their mean "
                   "intensity, shown in turn one per refresh (default %(default)s; a one-frame "
                   "model is widened)")
    p.add_argument(f"--{prefix}subframe-jitter", type=float, default=d.subframe_jitter,
                   metavar="F", help="how far the K heads' phase weights start apart, x their "
                   "rms, 0..2 (default %(default)s)")


def run_model_build(args: argparse.Namespace) -> int:
    config = load_config(args.config).config
    if args.up:
        parse_axis(args.up)
    device = resolve_device(args.device)
    training_device(device, check_available=True)  # before hours of dataset, not after
    recipe = Recipe.from_config(config.model, args.profile, device=device,
                                progress=not args.no_progress)  # fmt: skip
    tuning = build_tuning(args, config)  # refused before anything is built
    scene = Path(args.scene)
    out = Path(args.out) if args.out else Path("builds") / f"{_stem(scene)}-{recipe.name}"
    t0 = time.perf_counter()
    res = run_build(scene, out, recipe, config.optics, config.slm, force=args.force, up=args.up,
                    workers=args.workers, progress=not args.no_progress)  # fmt: skip
    r = res.report
    f = r["heldout"]["float"]
    print(f"{out}: model.onnx, {f['views']} held-out views: {f['model_psnr_db']:.2f} dB "
          f"(2D hologram {f['hologram_2d_psnr_db']:.2f}, black {f['black_psnr_db']:.2f}); "
          f"focus {f['focus_bins_passed']}/{f['focus_bins']} depth bins")
    if "int8" in r["heldout"]:
        q = r["heldout"]["int8"]
        print(f"int8: {q['model_psnr_db']:.2f} dB ({-q['loss_vs_float_db']:+.2f} dB): "
              + ("kept, model-int8.onnx" if q["kept"] else "not kept"))
    print(f"report: {out / 'report.json'}, {out / 'contact_sheet.png'}; "
          f"ran {', '.join(res.ran) or 'nothing'}"
          + (f", skipped {', '.join(res.skipped)}" if res.skipped else "")
          + f" in {time.perf_counter() - t0:.0f} s")
    served, name = out / "model.onnx", f"nhf-{_stem(scene)}-{recipe.name}.onnx"
    if tuning is not None:
        cal, settings = tuning
        t1 = time.perf_counter()
        res = tune_built(out, scene, cal, settings, config)
        print(f"tuned for {cal.label}: {res.path} ({res.steps} steps in "
              f"{time.perf_counter() - t1:.0f} s)")
        served, name = res.path, f"nhf-{_stem(scene)}-{recipe.name}-tuned.onnx"
    if args.serve:
        try:
            serve(config, scene, out, name, args, model_file=served)
        except (DaemonUnavailable, RpcError, RuntimeError) as exc:
            # The build is done and kept; only serving it failed.
            print(f"nhfd model build: --serve: {exc}; the model is built: {out / 'model.onnx'}",
                  file=sys.stderr)  # fmt: skip
            return 1
    return 0


def build_tuning(args: argparse.Namespace, config: Config
                 ) -> tuple[Calibration, tune.TuneSettings] | None:
    """`--calibration`'s tuning stage, checked: the calibration loaded and fit for the
    configuration's optics (`check_bench`), the settings in range (`TuneError`, a ValueError
    naming the option); None without --calibration."""
    if not args.calibration:
        return None
    w, h = parse_wxh(args.tune_size, "--tune-size")
    settings = tune.TuneSettings(steps=args.tune_steps, seconds=args.tune_seconds,
                                 views=args.tune_views, window_hw=(h, w),
                                 subframes=args.tune_subframes,
                                 subframe_jitter=args.tune_subframe_jitter)
    cal = Calibration.load(args.calibration)
    try:
        check_bench(cal, config.optics.wavelengths_m, config.slm.pitch_m)
    except ValueError as exc:
        raise tune.TuneError(f"--calibration {args.calibration}: {exc}") from None
    return cal, settings


def tune_built(out: Path, scene: Path, calibration: Calibration, settings: tune.TuneSettings,
               config: Config) -> tune.TuneResult:
    """The build's last stage with --calibration: `OUT/model.onnx` tuned through
    `calibration` into `OUT/tuned` (`nhfd.pipeline.tune.tune_model`; resumed from its
    checkpoint), on the poses the model records, else its dataset's training split."""
    model = out / "model.onnx"
    recorded = (read_metadata(model).get("train_poses") or {}).get("positions")
    res = tune.tune_model(model, scene_from_file(scene), scene, calibration, out / TUNED_DIR,
                          settings, config=config, dataset=None if recorded else out / "dataset")
    if res is None:  # only with stop_after, which is not given
        raise RuntimeError(f"tuning into {out / TUNED_DIR} stopped early")
    return res


def _stem(scene: Path) -> str:
    name = scene.name
    for suffix in (".compressed.ply", *SCENE_SUFFIXES):  # the double suffix first
        if name.endswith(suffix):
            return name[: -len(suffix)] or "scene"
    return scene.stem or "scene"


def _place(src: Path, folder: Path, name: str) -> Path:
    """`src` copied into `folder` as `name` (atomically), unless it already lies there."""
    folder.mkdir(parents=True, exist_ok=True)
    if src.resolve().parent == folder.resolve():
        return src.resolve()
    dst = folder / name
    tmp = dst.with_name(dst.name + ".tmp")
    shutil.copyfile(src, tmp)
    tmp.replace(dst)
    return dst.resolve()


def serve(config: Config, scene: Path, out: Path, model_name: str,
          args: argparse.Namespace, model_file: Path | None = None) -> None:
    """Load the scene and the float model (`model_file`: another, the tuned one; default
    OUT/model.onnx, with its int8 sibling) into the running daemon, then show a view from the
    middle of the trained poses. The daemon reads files only inside its configured folders, so
    both are copied there first (the original scene: the daemon takes its up axis from its
    format, as the build did).

    `config`: the configuration, whose `[daemon.paths]` names the folders and, through
    `nhfd.daemon.paths.socket_path` (which takes the configuration, as nhfctl's commands do),
    the control socket."""
    d = config.daemon.paths
    model_dir = Path(args.model_dir or d.model_dirs[0])
    scene_dir = Path(args.scene_dir or d.scene_dirs[0])
    socket = socket_path(args.socket, config)  # as nhfctl finds it
    with Client(socket, timeout_s=30.0) as c:  # no daemon: nothing is copied
        source = model_file or out / "model.onnx"
        model = _place(source, model_dir, model_name)
        # kept within INT8_MAX_LOSS_DB: the CPU serves it by default, found beside the float one
        # (not beside a tuned model: the int8 file has the untuned weights)
        if source == out / "model.onnx" and (out / "model-int8.onnx").is_file():
            _place(out / "model-int8.onnx", model_dir, int8_sibling(model_name).name)
        scene_file = _place(scene, scene_dir, scene.name)
        for method, path in (("load_scene", scene_file), ("load_model", model)):
            _load(c, method, path, LOAD_TIMEOUT_S)
            print(f"{method}: {path}", file=sys.stderr)
        report = json.loads((out / "report.json").read_text())
        r = report["recipe"]
        orbit = {"azimuth_deg": sum(r["azimuth_deg"]) / 2,
                 "elevation_deg": sum(r["elevation_deg"]) / 2,
                 "radius": report["scene"]["suggested_distance"] * sum(r["radius_scale"]) / 2}
        c.call("set_view", orbit=orbit)
    print(f"serving {model.name} on {scene_file.name}; view: orbit {orbit['azimuth_deg']:.0f}, "
          f"{orbit['elevation_deg']:.0f}, {orbit['radius']:.3g} (inside the trained poses)")


def _load(client: Client, method: str, path: Path, timeout_s: float) -> None:
    """Run the daemon's `method` ("load_scene" or "load_model") on `path` and wait for its job:
    RuntimeError if it failed (most often a file outside the daemon's folders) or is still
    queued or running after `timeout_s`."""
    job = client.call(method, path=str(path))["job"]
    state = client.wait_job(job, timeout_s)
    if state["state"] in ("queued", "running"):
        raise RuntimeError(f"{method} {path}: job {job} still {state['state']} after "
                           f"{timeout_s:g} s (`nhfctl job {job}` follows it)")
    if state["state"] != "done":
        raise RuntimeError(f"{method} {path}: {state.get('error') or state['state']}"
                           " (the daemon reads files only inside daemon.paths.scene_dirs and "
                           "daemon.paths.model_dirs: see --scene-dir, --model-dir)")


def run_model_tune(args: argparse.Namespace) -> int:
    """`nhfd model tune`: the settings checked, then `nhfd.pipeline.tune.tune_model`."""
    config = load_config(args.config).config
    w, h = parse_wxh(args.size)
    settings = tune.TuneSettings(steps=args.steps, seconds=args.seconds, views=args.views,
                                 window_hw=(h, w), ssim_weight=args.ssim_weight,
                                 device=args.device, subframes=args.subframes,
                                 subframe_jitter=args.subframe_jitter)
    cal = Calibration.load(args.calibration)
    res = tune.tune_model(args.model, scene_from_file(args.scene), args.scene, cal, args.out,
                          settings, config=config, dataset=args.dataset)
    return 0 if res is not None else 1


def run_check_sizes(args: argparse.Namespace) -> int:
    path = Path(args.model)
    meta = read_metadata(path)
    if args.sizes:
        wanted = [parse_wxh(s, "--sizes")[::-1] for s in args.sizes]
        sizes = sizes_to_check(meta, wanted, training=False)
    else:
        sizes = sizes_to_check(meta)
    compare = None
    if args.run:
        net, info = load_run(args.run)
        if (info.get("step") != meta.get("train_steps")
                or (info.get("dataset") or {}).get("manifest_key") != meta.get(
                    "dataset_manifest_key")):
            raise ValueError(f"--run {args.run}: not the run {path} was exported from (its "
                             "train steps or dataset manifest differ)")
        compare = lambda hw: compare_with_torch(net, path, [hw])[0]  # noqa: E731
    entries = check_sizes(path, sizes, compare)
    record_checked_sizes(path, entries)
    for e in entries:
        h, w = e["hw"]
        print(f"{w} x {h}: {'ok' if e['ok'] else 'FAILED'}, max abs difference "
              f"{e['max_abs_diff']:.3g} (tolerance {SIZE_TOLERANCE:g}) against {e['against']}")
    print(f"{path}: checked_sizes recorded")
    return 0 if all(e["ok"] for e in entries) else 1
