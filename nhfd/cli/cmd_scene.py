"""`nhfd scene info|render|reduce`: what a splat scene holds, one view of it (RGB, depth,
alpha), and the scene reduced to what a dataset's pose envelope shows (nhfd.scene.cull).

Imported only when `nhfd scene` runs (nhfd.cli.main's registry); numba compiles the renderer's
kernels on first use, matplotlib (the depth colour map) loads only when a depth PNG is written,
and `reduce` loads the dataset's envelope (nhfd.dataset.envelope: torch) only when it runs.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from PIL.PngImagePlugin import PngInfo

from nhfd.cli.args import MAX_SIDE_PX, SCENE_FORMATS, parse_wxh
from nhfd.config import load_config
from nhfd.scene import cameras
from nhfd.scene.io import is_sog_folder, read_scene, save_ply, scene_summary
from nhfd.scene.raster import RasterSettings, render
from nhfd.scene.suggest import detect_up_axis, format_hint, robust_frame, suggest_camera

AXIS_NAMES = tuple(cameras.AXES)
DEFAULT_SIZE = "1024x576"
DEFAULT_FOV_DEG = 40.0

# Pose kinds, their fields, and the form shown in errors and help.
POSE_FIELDS = {
    "orbit": ("AZ", "EL", "R"),
    "lookat": ("EX", "EY", "EZ", "TX", "TY", "TZ"),
    "pos": ("X", "Y", "Z", "qw", "qx", "qy", "qz"),
    "ypr": ("X", "Y", "Z", "YAW", "PITCH", "ROLL"),
}
POSE_FORMS = " | ".join(f"{k}:{','.join(v)}" for k, v in POSE_FIELDS.items())

POSE_HELP = (
    "camera pose (default: the suggested camera of `nhfd scene info`). "
    "orbit:AZ,EL,R = azimuth and elevation in degrees about the up axis and radius, around the "
    "scene centre; lookat:EX,EY,EZ,TX,TY,TZ = eye and target; pos:X,Y,Z,qw,qx,qy,qz = position "
    "and camera-to-world quaternion (OpenCV axes: x right, y down, z forward); "
    "ypr:X,Y,Z,YAW,PITCH,ROLL = position, yaw about up, pitch toward up, roll, in degrees. "
    "World units are the scene's."
)
UP_HELP = (
    f"scene up axis, one of {', '.join(AXIS_NAMES)} (default: detected; write --up=-y, since "
    "argparse reads a bare -y as an option)"
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "scene",
        help="inspect and render 3D Gaussian splat scenes: " + SCENE_FORMATS,
        description="Inspect a Gaussian splat scene file or render one view of it on the CPU.",
    )
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    _register_info(verbs)
    _register_render(verbs)
    _register_reduce(verbs)


def _add_view_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--size", default=DEFAULT_SIZE, metavar="WxH",
                   help=f"image size in pixels (default {DEFAULT_SIZE})")
    p.add_argument("--fov", type=float, default=DEFAULT_FOV_DEG, metavar="DEG",
                   help=f"horizontal field of view in degrees (default {DEFAULT_FOV_DEG:g})")
    p.add_argument("--up", metavar="AXIS", help=UP_HELP)


def _register_info(verbs: argparse._SubParsersAction) -> None:
    info = verbs.add_parser(
        "info",
        help="counts, SH degree, bounds, up axis and a suggested camera",
        description="Print the Gaussian count, SH degree, bounds (all and 1st-99th percentile), "
        "centre, extent and mean opacity of a scene, the detected up axis with the reason, and a "
        "suggested camera as the exact `nhfd scene render` arguments that reproduce it.",
    )
    info.add_argument("file", metavar="FILE", help="scene: " + SCENE_FORMATS)
    info.add_argument("--json", action="store_true", help="machine-readable output")
    _add_view_options(info)
    info.set_defaults(handler=_info)


def _register_render(verbs: argparse._SubParsersAction) -> None:
    render = verbs.add_parser(
        "render",
        help="render one view: RGB PNG, optionally depth and alpha (PNG or .npy)",
        description="Render one view of a scene with the CPU rasteriser and write it as an\n"
        "8-bit sRGB PNG. Depth (expected camera z, scene units, 0 where nothing was\n"
        "drawn) and alpha go to .npy as raw float32 [H, W], or to .png: depth\n"
        "colour-mapped (turbo, near = blue) with its near/far in the PNG's text\n"
        "metadata (nhfd:depth_near, nhfd:depth_far), alpha as 8-bit grey.",
        epilog="examples:\n  nhfd scene render donut.ply -o view.png --depth depth.npy\n"
        "  nhfd scene render donut.ply -o top.png --pose orbit:0,80,0.5 --size 512x512\n"
        "  nhfd scene render guitar.compressed.ply -o v.png --pose orbit:0,10,20 --up=-y",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    render.add_argument("file", metavar="FILE", help="scene: " + SCENE_FORMATS)
    render.add_argument("-o", "--out", required=True, metavar="PNG", help="RGB output (.png)")
    _add_view_options(render)
    render.add_argument("--pose", metavar="SPEC", help=POSE_HELP)
    render.add_argument("--near", type=float, metavar="DIST",
                        help="near plane in scene units (default: 1%% of the distance from the "
                        "camera to its target or to the scene centre)")
    render.add_argument("--depth", metavar="PATH", help="also write depth (.png or .npy)")
    render.add_argument("--alpha", metavar="PATH", help="also write alpha (.png or .npy)")
    render.add_argument("--antialias", action="store_true",
                        help="antialiased splatting (opacity-compensated dilation); use for "
                        "scenes trained with it, e.g. Mip-Splatting")
    render.set_defaults(handler=_render)


def _register_reduce(verbs: argparse._SubParsersAction) -> None:
    reduce = verbs.add_parser(
        "reduce",
        help="cull what a dataset's pose envelope cannot show; drop SH bands that change no "
        "pixel by a grey level",
        description="Make the cameras `nhfd dataset build` would render with the same options "
        "(every pose's light field and its depth-pass view), then cull the Gaussians no view "
        "draws and those too faint to change any checked pixel by more than --grey-levels, and "
        "drop SH bands within the same tolerance (nhfd.scene.cull). Prints what was kept, the "
        "largest change, the render time saved, and the depth mapping, light-field views and "
        "focal planes of the envelope; with -o writes the reduced scene as an INRIA .ply.",
        epilog="example:\n  nhfd scene reduce guitar.compressed.ply -o guitar-reduced.ply "
        "--size 512x288\n  nhfd dataset build --scene guitar-reduced.ply --up=-y ...",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    reduce.add_argument("file", metavar="FILE", help="scene file (any format `scene info` reads)")
    reduce.add_argument("-o", "--out", metavar="PLY", help="write the reduced scene (.ply)")
    _add_view_options(reduce)
    reduce.add_argument("--views", type=int, default=130, help="poses (default 130)")
    reduce.add_argument("--azimuth", default="-30,30", help="training azimuth sector, degrees")
    reduce.add_argument("--elevation", default="10,30", help="elevation range, degrees")
    reduce.add_argument("--radius-scale", default="0.9,1.1",
                        help="radius range as multiples of the suggested camera distance")
    reduce.add_argument("--seed", type=int, default=0, help="pose seed (default 0)")
    reduce.add_argument("--per-colour-views", action="store_true",
                        help="as `dataset build --per-colour-views`")
    reduce.add_argument("--config", help="nhfd.toml to take the optics from")
    reduce.add_argument("--grey-levels", type=float, default=1.0, metavar="G",
                        help="largest change of a checked pixel, in grey levels of 255 "
                        "(default 1)")
    reduce.add_argument("--check-views", type=int, default=24, metavar="N",
                        help="envelope views rendered to measure changes (default 24)")
    reduce.add_argument("--json", action="store_true", help="machine-readable output")
    reduce.set_defaults(handler=_reduce)


# --------------------------------------------------------------------------------------------
# Parsing and validation (ValueError -> "nhfd scene: error: ..." and exit 2)


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' -> (W, H), each 1..MAX_SIDE_PX."""
    return parse_wxh(text, "--size", MAX_SIDE_PX)


def parse_pose(text: str) -> tuple[str, list[float]]:
    """'kind:v1,v2,...' -> (kind, finite floats), the count checked against POSE_FIELDS."""
    kind, sep, rest = text.partition(":")
    kind = kind.strip().lower()
    if not sep or kind not in POSE_FIELDS:
        raise ValueError(f"--pose {text!r}: expected one of {POSE_FORMS}")
    fields = POSE_FIELDS[kind]
    form = f"{kind}:{','.join(fields)}"
    parts = rest.split(",")
    if len(parts) != len(fields):
        raise ValueError(f"--pose {text!r}: {kind} takes {len(fields)} numbers ({form}), "
                         f"got {len(parts)}")
    values = []
    for name, part in zip(fields, parts, strict=True):
        try:
            v = float(part)
        except ValueError:
            msg = f"--pose {text!r}: {name} = {part!r} is not a number ({form})"
            raise ValueError(msg) from None
        if not math.isfinite(v):
            raise ValueError(f"--pose {text!r}: {name} = {part!r} must be finite ({form})")
        values.append(v)
    return kind, values


def _check_up(up: str | None) -> None:
    if up is not None and up not in AXIS_NAMES:
        raise ValueError(f"--up {up!r} is not an axis; use one of {', '.join(AXIS_NAMES)} "
                         "(written --up=-y for the negative ones)")


def _check_fov(fov: float) -> None:
    if not (math.isfinite(fov) and 0 < fov < 180):
        raise ValueError(f"--fov {fov:g} must be a horizontal field of view in (0, 180) degrees")


def _check_output(option: str, path: str | None, suffixes: tuple[str, ...]) -> None:
    if path is not None and Path(path).suffix.lower() not in suffixes:
        raise ValueError(f"{option} {path!r} must end in {' or '.join(suffixes)}")


# --------------------------------------------------------------------------------------------
# Scene and camera


@dataclass
class Loaded:
    g: Any  # Gaussians
    path: Path
    hint: str | None
    up: str
    up_reason: str
    seconds: float
    declared: int = 0  # Gaussians in the file
    dropped: int = 0  # of them, dropped for non-finite or degenerate values


FORMAT_NAMES = {"ply": "INRIA float .ply", "compressed": "PlayCanvas compressed .ply",
                "splat": "antimatter15 .splat", "spz": "Niantic .spz",
                "gltf": "glTF KHR_gaussian_splatting", "sog": "PlayCanvas SOG",
                None: "unknown format"}


def _load(file: str, up: str | None) -> Loaded:
    path = Path(file)
    if not path.exists():
        raise FileNotFoundError(f"scene file {file!r} not found")
    if not (path.is_file() or is_sog_folder(path)):
        raise ValueError(f"scene file {file!r} is not a file (nor a SOG folder with meta.json)")
    t0 = time.perf_counter()
    load = read_scene(path)  # SceneFileError is a ValueError naming the file
    seconds = time.perf_counter() - t0
    if load.dropped:
        warnings.warn(load.dropped_reason, UserWarning, stacklevel=2)
    g = load.gaussians
    hint = format_hint(path)
    if up is None:
        up, reason = detect_up_axis(g, hint)
    else:
        reason = "given with --up"
    return Loaded(g, path, hint, up, reason, seconds, load.declared, load.dropped)


def _fmt(values: Any) -> str:
    """Comma-separated numbers, 6 significant digits: exact enough to reproduce a view."""
    return ",".join(f"{float(v):.6g}" for v in values)


def _suggested(scene: Loaded, size: tuple[int, int], fov: float) -> dict[str, Any]:
    """The suggested camera and the `scene render` arguments that reproduce it."""

    cam = suggest_camera(scene.g, size[0], size[1], scene.up, fov_x_deg=fov)
    target, _, _ = robust_frame(scene.g)
    eye = cam.position
    pose = f"lookat:{_fmt(eye)},{_fmt(target)}"
    args = ["--size", f"{size[0]}x{size[1]}", "--pose", pose, "--fov", f"{fov:g}",
            f"--up={scene.up}"]
    return {
        "position": eye.tolist(),
        "target": target.tolist(),
        "radius": float(np.linalg.norm(eye - target)),
        "fov_x_deg": fov,
        "up": scene.up,
        "size": list(size),
        "near": cam.near,
        "pose": pose,
        "render_args": args,
    }


def _camera(scene: Loaded, args: argparse.Namespace, size: tuple[int, int]) -> tuple[Any, str]:
    """The camera for `scene render`, and its pose as text."""

    centre, lo, hi = robust_frame(scene.g)
    if args.pose is None:
        cam = suggest_camera(scene.g, size[0], size[1], scene.up, fov_x_deg=args.fov)
        pose_text = f"lookat:{_fmt(cam.position)},{_fmt(centre)} (suggested)"
        if args.near is not None:
            cam = _with_near(cam, args.near)
        return cam, pose_text
    kind, v = parse_pose(args.pose)
    if kind == "orbit":
        if v[2] <= 0:
            raise ValueError(f"--pose {args.pose!r}: orbit radius R must be positive")
        r, t = cameras.orbit(centre, v[0], v[1], v[2], scene.up)
        target = centre
    elif kind == "lookat":
        if v[:3] == v[3:]:
            raise ValueError(f"--pose {args.pose!r}: eye and target must differ")
        r, t = cameras.look_at(np.array(v[:3]), np.array(v[3:]), scene.up)
        target = np.array(v[3:])
    elif kind == "pos":
        if not any(v[3:]):
            raise ValueError(f"--pose {args.pose!r}: the quaternion qw,qx,qy,qz must be non-zero")
        r, t = cameras.pose_from_quaternion(np.array(v[:3]), np.array(v[3:]))
        target = centre
    else:
        r, t = cameras.pose_from_ypr(np.array(v[:3]), v[3], v[4], v[5], scene.up)
        target = centre
    eye = -r.T @ t
    # A near plane proportional to the viewing distance keeps close-ups and far views alike
    # unclipped in any scene unit; the floor covers a camera placed at its target.
    dist = float(np.linalg.norm(eye - target))
    near = args.near if args.near is not None else max(
        0.01 * dist, 1e-4 * float(np.linalg.norm(hi - lo)), 1e-6
    )
    fx, fy, cx, cy = cameras.intrinsics_from_fov(size[0], size[1], args.fov)
    return cameras.Camera(r, t, fx, fy, cx, cy, size[0], size[1], near=near), args.pose


def _with_near(cam: Any, near: float) -> Any:
    return replace(cam, near=near)


# --------------------------------------------------------------------------------------------
# Handlers


def _info(args: argparse.Namespace) -> int:
    size = parse_size(args.size)
    _check_fov(args.fov)
    _check_up(args.up)
    scene = _load(args.file, args.up)
    summary = scene_summary(scene.g)
    out: dict[str, Any] = {"file": str(scene.path), "format": scene.hint, **summary,
                           "declared": scene.declared, "dropped": scene.dropped,
                           "up_axis": scene.up, "up_reason": scene.up_reason}
    out["suggested_camera"] = _suggested(scene, size, args.fov) if len(scene.g) else None
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    _print_info(out)
    return 0


def _vec(v: list[float] | None) -> str:
    return "-" if v is None else "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def _print_info(d: dict[str, Any]) -> None:
    print(f"file          {d['file']} ({FORMAT_NAMES.get(d['format'], d['format'])})")
    dropped = (f" (dropped {d['dropped']} of {d['declared']}: non-finite or degenerate)"
               if d.get("dropped") else "")
    print(f"gaussians     {d['count']}{dropped}")
    print(f"sh degree     {d['sh_degree']}")
    if d["count"] == 0:
        print("empty scene: no bounds, no suggested camera")
        return
    print(f"bounds        min {_vec(d['bounds_min'])}  max {_vec(d['bounds_max'])}")
    print(f"robust 1-99%  min {_vec(d['robust_min'])}  max {_vec(d['robust_max'])}")
    print(f"centre        {_vec(d['centre'])} (per-axis median)")
    print(f"extent        {d['extent']:.4g} (diagonal of the robust box)")
    print(f"mean opacity  {d['mean_opacity']:.3f}")
    print(f"median scale  {d['median_scale']:.4g}")
    print(f"up axis       {d['up_axis']}: {d['up_reason']}")
    cam = d["suggested_camera"]
    print(f"camera        at {_vec(cam['position'])} looking at {_vec(cam['target'])}, "
          f"up {cam['up']}, fov {cam['fov_x_deg']:g} deg, distance {cam['radius']:.4g}")
    cmd = ["nhfd", "scene", "render", d["file"], "-o", "view.png", *cam["render_args"]]
    print("render it:    " + shlex.join(cmd))


def _render(args: argparse.Namespace) -> int:
    size = parse_size(args.size)
    _check_fov(args.fov)
    _check_up(args.up)
    if args.pose is not None:
        parse_pose(args.pose)  # syntax errors before the (slow) load
    if args.near is not None and not (math.isfinite(args.near) and args.near > 0):
        raise ValueError(f"--near {args.near:g} must be a positive distance")
    _check_output("-o", args.out, (".png",))
    _check_output("--depth", args.depth, (".png", ".npy"))
    _check_output("--alpha", args.alpha, (".png", ".npy"))
    scene = _load(args.file, args.up)
    cam, pose_text = _camera(scene, args, size)
    print(f"{scene.path}: {len(scene.g)} Gaussians, SH degree {scene.g.sh_degree}, "
          f"loaded in {1e3 * scene.seconds:.0f} ms; up {scene.up} ({scene.up_reason})")
    print(f"camera: {pose_text}, fov {args.fov:g} deg, {size[0]}x{size[1]}, near {cam.near:.4g}")
    t0 = time.perf_counter()
    result = render(scene.g, cam, RasterSettings(antialias=args.antialias))
    seconds = time.perf_counter() - t0
    # Wall time of the whole call: the first view in a process also loads numba's cached kernels.
    print(f"rendered in {1e3 * seconds:.0f} ms (wall): {_stats_text(result.stats)}")
    written = [_write_rgb(args.out, result.rgb)]
    if args.depth:
        written.append(_write_depth(args.depth, result.depth, result.alpha))
    if args.alpha:
        written.append(_write_alpha(args.alpha, result.alpha))
    print("wrote " + "; ".join(written))
    return 0


def _stats_text(stats: dict[str, Any]) -> str:
    parts = [f"{k.removesuffix('_ms')} {v:.1f} ms" if k.endswith("_ms") else f"{k} {v}"
             for k, v in stats.items()]
    return ", ".join(parts)


# --------------------------------------------------------------------------------------------
# Writers


def _prepare_dir(path: str) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


def _write_rgb(path: str, rgb: Any) -> str:
    img = np.rint(np.clip(rgb.transpose(1, 2, 0), 0.0, 1.0) * 255).astype(np.uint8)
    Image.fromarray(img, "RGB").save(_prepare_dir(path))
    return f"{path} ({img.shape[1]}x{img.shape[0]} RGB)"


def _write_alpha(path: str, alpha: Any) -> str:
    if path.lower().endswith(".npy"):
        np.save(_prepare_dir(path), alpha.astype(np.float32))
        return f"{path} (alpha, float32)"
    img = np.rint(np.clip(alpha, 0.0, 1.0) * 255).astype(np.uint8)
    Image.fromarray(img, "L").save(_prepare_dir(path))
    return f"{path} (alpha, 8-bit)"


def depth_range(depth: Any, alpha: Any) -> tuple[float, float]:
    """Near and far of the colour map: over pixels at least half covered, so faint floaters'
    depths do not stretch the scale (all drawn pixels if none is; (0, 0) for an empty view)."""
    for mask in (alpha >= 0.5, alpha > 0):
        if mask.any():
            d = depth[mask]
            return float(d.min()), float(d.max())
    return 0.0, 0.0


def _write_depth(path: str, depth: Any, alpha: Any) -> str:
    if path.lower().endswith(".npy"):
        np.save(_prepare_dir(path), depth.astype(np.float32))
        return f"{path} (depth, float32 scene units, 0 where nothing was drawn)"
    import matplotlib

    near, far = depth_range(depth, alpha)
    t = np.clip((depth - near) / (far - near), 0.0, 1.0) if far > near else np.zeros_like(depth)
    rgb = matplotlib.colormaps["turbo"](t)[..., :3]
    rgb[alpha <= 0] = 0.0  # nothing drawn: black, not the colour of `near`
    meta = PngInfo()
    for key, value in (("nhfd:depth_near", f"{near:.9g}"), ("nhfd:depth_far", f"{far:.9g}"),
                       ("nhfd:colormap", "turbo, near = 0 (blue) .. far = 1 (red)"),
                       ("nhfd:units", "scene units, camera z")):
        meta.add_text(key, value)
    img = np.rint(rgb * 255).astype(np.uint8)
    Image.fromarray(img, "RGB").save(_prepare_dir(path), pnginfo=meta)
    return f"{path} (depth, turbo from near {near:.4g} to far {far:.4g})"


def _pair(text: str, option: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{option} {text!r}: give two numbers, LOW,HIGH") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"{option} {text!r}: need finite LOW <= HIGH")
    return lo, hi


def _reduce(args: argparse.Namespace) -> int:
    # The envelope needs the dataset's settings, mapping and sampling (torch): loaded here only,
    # so `scene info` and `scene render` stay light.
    from nhfd.dataset import envelope as env_mod

    w, h = parse_size(args.size)
    _check_fov(args.fov)
    _check_up(args.up)
    if args.out is not None:
        _check_output("-o", args.out, (".ply",))
    if args.views < 1:
        raise ValueError(f"--views {args.views}: must be >= 1")
    if not (math.isfinite(args.grey_levels) and 0 <= args.grey_levels <= 255):
        raise ValueError(f"--grey-levels {args.grey_levels:g}: must be in [0, 255]")
    if args.check_views < 1:
        raise ValueError(f"--check-views {args.check_views}: must be >= 1")
    ranges = {k: _pair(getattr(args, k.replace("-", "_")), f"--{k}")
              for k in ("azimuth", "elevation", "radius-scale")}
    config = load_config(args.config).config
    settings = env_mod.ExampleSettings.from_config(
        config.optics, config.slm, width_px=w, height_px=h, fov_x_deg=args.fov,
        shared_views=not args.per_colour_views)
    scene = _load(args.file, args.up)
    if len(scene.g) == 0:
        raise ValueError(f"{scene.path}: the scene holds no Gaussians; nothing to reduce")
    sampler = env_mod.orbit_sampler(scene.g, scene.up, width_px=w, height_px=h,
                                    fov_x_deg=args.fov, views=args.views,
                                    azimuth_deg=ranges["azimuth"],
                                    elevation_deg=ranges["elevation"],
                                    radius_scale=ranges["radius-scale"], seed=args.seed)
    t0 = time.perf_counter()
    env = env_mod.dataset_envelope(scene.g, sampler.sample(), np.array(sampler.center), settings)
    t1 = time.perf_counter()
    reduced, report = env_mod.reduce_scene(scene.g, env.cameras, grey_levels=args.grey_levels,
                                   check_views=args.check_views)
    t2 = time.perf_counter()
    out = {"file": str(scene.path), "up_axis": scene.up, "up_reason": scene.up_reason,
           "envelope": env.describe(), "reduction": report.to_dict(),
           "seconds": {"envelope": t1 - t0, "reduce": t2 - t1}, "written": None}
    if args.out is not None:
        save_ply(args.out, reduced)
        out["written"] = str(args.out)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    e, m = out["envelope"], out["envelope"]["mapping"]
    print(f"{scene.path}: up {scene.up} ({scene.up_reason})")
    print(f"envelope      {e['n_poses']} poses x {e['views_per_pose']} light-field views + "
          f"{e['n_poses']} depth-pass views = {e['n_cameras']} cameras ({w}x{h}, fov "
          f"{args.fov:g} deg)")
    print(f"mapping       d_near {m['d_near']:.4g}, d_far {m['d_far']:.4g} -> z_h in "
          f"[{m['z_min_m'] * 1e3:+.1f}, {m['z_max_m'] * 1e3:+.1f}] mm")
    print("windows       " + ", ".join(f"{s['wavelength_nm']:.0f} nm W={s['window']} "
                                       f"({s['n_views']} views)" for s in e["sampling"]))
    print("focal planes  " + ", ".join(f"{z * 1e3:+.1f}" for z in e["focal_planes_m"]) + " mm")
    print(f"reduced       {report.summary()}")
    print(f"took          envelope {t1 - t0:.1f} s, reduction {t2 - t1:.1f} s")
    if args.out is not None:
        # An INRIA .ply carries no up axis; the detector may read it differently from FILE.
        print(f"wrote {args.out} (INRIA .ply; pass --up={scene.up} when using it)")
    return 0
