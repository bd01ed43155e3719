"""`nhfd dataset build|merge|show`: training data from a splat scene (views + complex holograms)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from nhfd.cli.args import parse_wxh
from nhfd.config import DEVICES, load_config
from nhfd.dataset.build import (
    EXECUTORS,
    build,
    check_device,
    merge,
    parse_shard,
    shard_indices,
)
from nhfd.dataset.poses import load_poses, orbit_sampler
from nhfd.dataset.shard import ExampleSettings
from nhfd.dataset.show import show
from nhfd.scene.io import load_scene
from nhfd.scene.suggest import detect_up_axis, format_hint

BUILD_HELP = """\
Render the central view and depth of every pose, compute each view's complex hologram on the
reference plane by wavefront inversion of its light field (all colours), and write one shard per
view plus manifest.json. A first depth-only pass over all poses fixes the scene's depth mapping.
Interrupted builds resume (run the same command again); nothing is overwritten without --force.

Beyond one process: --workers N runs N local processes; --shard K/N builds part K of N (the
examples i with i % N == K-1) so N machines sharing the --out folder each build one part (give
all parts the same arguments); the part that finds every shard present writes the manifest, or
run `nhfd dataset merge OUT`. --executor ray runs one Ray task per example (retried if a worker
dies) on the cluster at --address, or on a local Ray instance with --workers CPUs. Every way
writes the same bytes.

Poses: --views N samples a train / interpolation / extrapolation split around the scene (about
100 / 20 / 10 of N by default; see nhfd.dataset.poses), or --poses FILE reads them.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dataset", help="build and inspect training datasets",
                       description=__doc__)  # fmt: skip
    cmds = p.add_subparsers(dest="dataset_command", metavar="COMMAND", required=True)
    b = cmds.add_parser("build", help="build (or resume) a dataset", description=BUILD_HELP,
                        formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    b.add_argument("--scene", required=True, help="splat scene (.ply, .compressed.ply, .splat)")
    b.add_argument("--out", required=True, help="dataset folder")
    b.add_argument("--views", type=int, default=130, help="poses to sample (default 130)")
    b.add_argument("--poses", help="JSON poses file instead of sampling (see nhfd.dataset.poses)")
    b.add_argument("--size", default="1024x576", help="view and hologram WxH (default 1024x576)")
    b.add_argument("--fov", type=float, default=40.0, help="horizontal field of view, degrees")
    b.add_argument("--up", default=None, help="scene up axis (default: detected), e.g. --up=-y")
    b.add_argument("--azimuth", default="-30,30", help="training azimuth sector, degrees")
    b.add_argument("--elevation", default="10,30", help="elevation range, degrees")
    b.add_argument("--radius-scale", default="0.9,1.1",
                   help="radius range as multiples of the suggested camera distance")
    b.add_argument("--phase", default="depth", choices=("depth", "zero", "random"),
                   help="phase heuristic (docs/physics.md; default depth-aware)")
    b.add_argument("--per-colour-views", action="store_true",
                   help="render each colour's own directions instead of one shared set")
    b.add_argument("--d-near", type=float, help="override the measured scene near depth")
    b.add_argument("--d-far", type=float, help="override the measured scene far depth")
    b.add_argument("--seed", type=int, default=0, help="base seed (poses, random phase)")
    b.add_argument("--workers", type=int, default=1,
                   help="local processes, or a local Ray instance's CPUs (2 uses both cores)")
    b.add_argument("--threads", type=int, default=None,
                   help="threads of a one-process build (default: one per core)")
    b.add_argument("--shard", default=None, metavar="K/N",
                   help="build only part K of N (examples i with i %% N == K-1)")
    b.add_argument("--executor", default="local", choices=EXECUTORS,
                   help="local processes (default) or Ray tasks (pip install 'nhfd[ray]')")
    b.add_argument("--address", default=None,
                   help="Ray cluster address (e.g. 10.0.0.1:6379 or auto); default: start a "
                        "local Ray instance")  # fmt: skip
    b.add_argument("--device", default="cpu", metavar="|".join(DEVICES),
                   help="cpu (default): the CPU rasteriser and inversion; cuda or cuda:N: gsplat "
                        "renders the light fields, batched over views, and the inversion runs "
                        "on that GPU (pip install 'nhfd[gpu]'); auto: the GPU where torch sees "
                        "one and gsplat imports, else the CPU")  # fmt: skip
    b.add_argument("--force", action="store_true", help="replace a dataset built differently")
    b.add_argument("--config", help="nhfd.toml to take the optics from")
    b.set_defaults(handler=run_build)
    m = cmds.add_parser("merge", help="write the manifest once every part's shards exist",
                        description="Check that every example's shard exists and was built for "
                        "the folder's manifest, then complete the manifest (amplitude scale). "
                        "Names the missing examples, or the settings a stray shard differs in.")
    m.add_argument("dir", help="dataset folder")
    m.set_defaults(handler=run_merge)
    s = cmds.add_parser("show", help="PNG of a shard's view and its hologram's focal stack")
    s.add_argument("dir", help="dataset folder")
    s.add_argument("--index", type=int, default=0, help="view index (default 0)")
    s.add_argument("-o", "--out", default=None, help="PNG path (default DIR/show_INDEX.png)")
    s.set_defaults(handler=run_show)


def _pair(text: str, name: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{name} {text!r}: give two numbers, LOW,HIGH") from None
    if not lo <= hi:
        raise ValueError(f"{name} {text!r}: need LOW <= HIGH")
    return lo, hi


def run_build(args: argparse.Namespace) -> int:
    w, h = parse_wxh(args.size, "--size", 8192)
    if args.workers < 1:
        raise ValueError(f"--workers {args.workers}: must be >= 1")
    if args.threads is not None and args.threads < 1:
        raise ValueError(f"--threads {args.threads}: must be >= 1")
    part = parse_shard(args.shard) if args.shard is not None else None
    # build() checks it too (its other callers), but only after this loads the scene, samples
    # the poses and draws the progress bar: a bad --device is refused here before any of it.
    device = check_device(args.device)
    if args.address and args.executor != "ray":
        raise ValueError(f"--address {args.address!r}: only with --executor ray")
    config = load_config(args.config).config
    settings = ExampleSettings.from_config(config.optics, config.slm, width_px=w, height_px=h,
                                           fov_x_deg=args.fov, phase=args.phase,
                                           shared_views=not args.per_colour_views)  # fmt: skip
    scene = Path(args.scene)
    g = load_scene(scene)
    sampler = None
    if args.poses:
        poses = load_poses(Path(args.poses))
    else:
        if args.views < 1:
            raise ValueError(f"--views {args.views}: must be >= 1")
        up = args.up or detect_up_axis(g, format_hint(scene))[0]
        ps = orbit_sampler(g, up, width_px=w, height_px=h, fov_x_deg=args.fov, views=args.views,
                           azimuth_deg=_pair(args.azimuth, "--azimuth"),
                           elevation_deg=_pair(args.elevation, "--elevation"),
                           radius_scale=_pair(args.radius_scale, "--radius-scale"),
                           seed=args.seed)  # fmt: skip
        poses, sampler = ps.sample(), ps.describe()
    n_mine = len(shard_indices(len(poses), part))
    bar = tqdm(total=n_mine, unit="view", desc="dataset", file=sys.stderr)

    def progress(done: int, total: int, r: dict) -> None:
        bar.n = done
        bar.set_postfix(render=f"{r['render_s']:.1f}s", invert=f"{r['invert_s']:.1f}s")
        bar.refresh()

    manifest = build(scene, Path(args.out), poses, settings, seed=args.seed, sampler=sampler,
                     workers=args.workers, force=args.force, d_near=args.d_near,
                     d_far=args.d_far, progress=progress, shard=part, executor=args.executor,
                     address=args.address, threads=args.threads, device=device)  # fmt: skip
    bar.close()
    if manifest["amplitude_scale"] is None:
        print(f"{args.out}: part {args.shard} built ({n_mine} views); "
              "the manifest is completed when every part is (or by `nhfd dataset merge`)")
        return 0
    m = manifest["mapping"]
    print(f"{args.out}: {len(poses)} views ({', '.join(f'{k} {len(v)}' for k, v in manifest['splits'].items())})")  # noqa: E501
    print(f"mapping: d_near {m['d_near']:.4g}, d_far {m['d_far']:.4g} -> z_h in "
          f"[{m['z_min_m'] * 1e3:+.1f}, {m['z_max_m'] * 1e3:+.1f}] mm; depth exaggeration "
          f"{m['depth_exaggeration']:.0f}x")  # fmt: skip
    print("windows: " + ", ".join(f"{s['wavelength_nm']:.0f} nm W={s['window']} "
                                  f"({s['n_views']} views)" for s in manifest["sampling"]))
    print(f"amplitude scale: {manifest['amplitude_scale']['value']:.4g} "
          f"(p{manifest['amplitude_scale']['percentile']} on the SLM plane)")
    return 0


def run_merge(args: argparse.Namespace) -> int:
    manifest = merge(Path(args.dir))
    print(f"{args.dir}: {len(manifest['poses'])} views merged; amplitude scale "
          f"{manifest['amplitude_scale']['value']:.4g}")  # fmt: skip
    return 0


def run_show(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else Path(args.dir) / f"show_{args.index:05d}.png"
    info = show(Path(args.dir), args.index, out)
    print(f"wrote {out} (planes {', '.join(f'{z:+.1f}' for z in info['planes_mm'])} mm)")
    return 0
