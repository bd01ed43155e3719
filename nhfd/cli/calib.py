"""`nhfd calib capture|fit|report|learn`: calibrate the bench against the simulation.

`capture` runs through the daemon (`nhfd serve` owns the devices; simulated by default): the
daemon's panel size and wavelengths from `status`, frames shown with `show_pattern` (so --out must
lie inside its daemon.paths.pattern_dirs), raw stage moves, laser power/enable (arm first, or
--arm), linear .npy captures. `--direct` drives the simulated twins in this process instead (a
`TrueBench`, optionally randomised with `--sim-seed`). `fit` writes calibration.toml; `report`
writes PNGs next to the capture (or, of a folder `learn` wrote, the learned bench's fidelity).
`learn` learns what the parametric model leaves out from captures (docs/learned_bench.md),
through the daemon (its `capture_stack` job: the daemon's calibration, the powers a person set,
never arming) or `--direct` on the simulated bench: it prints the capture plan, captures
(resuming a stopped run from --out), fits, writes the weights, the calibration referencing them
and the captures, prints the held-out PSNR, parametric against learned, per colour, and draws
the fidelity report.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nhfd.calib.capture import (
    CaptureError,
    CapturePlan,
    DaemonBenchIO,
    SimBenchIO,
    capture,
    daemon_spec,
)
from nhfd.calib.citl import DaemonCameraLoop
from nhfd.calib.fit import fit_capture
from nhfd.calib.learn import PARTIAL_NAME, LearnPlan, LearnResult, camera_loop, learn
from nhfd.calib.patterns import PatternSpec
from nhfd.calib.report import is_learn_folder, write_learned_report, write_report
from nhfd.calib.sim import (
    SIM_PANEL_MARGIN_PX,
    SIM_POWER_PCT,
    sim_devices,
    sim_panel_hw,
    twin_calibration,
)
from nhfd.calibration import Calibration, fingerprint
from nhfd.cli.args import parse_wxh
from nhfd.config import Config, load_config
from nhfd.daemon.client import Client
from nhfd.daemon.paths import socket_path
from nhfd.device_settings import COLOURS, citl_laser_refusal
from nhfd.drivers.simcamera import TrueBench
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.refine import CaptureStopped


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calib", help="capture focal stacks and fit the bench model",
                       description=__doc__)
    cmds = p.add_subparsers(dest="calib_command", metavar="COMMAND", required=True)
    c = cmds.add_parser("capture", help="capture (or resume) a calibration data set")
    c.add_argument("--out", required=True, help="capture directory")
    c.add_argument("--direct", action="store_true",
                   help="drive the simulated twins in this process, not the daemon")
    c.add_argument("--socket", help="daemon control socket (default: from the configuration)")
    c.add_argument("--config", help="configuration file whose daemon.server.runtime_dir to use")
    c.add_argument("--arm", type=float, default=None, metavar="SECONDS",
                   help="arm the lasers for this long when they are not armed (Unix socket; "
                        "default: they must be armed already)")
    c.add_argument("--home", action="store_true", help="home the stage before the first move")
    c.add_argument("--camera-pitch-um", type=float, default=None,
                   help="camera pixel pitch in um (daemon path; default: the configuration's "
                        "devices.camera_settings.pixel_pitch_um)")
    c.add_argument("--exposure", type=float, default=0.005, help="exposure s (default 0.005)")
    c.add_argument("--stop-after", choices=("coarse", "grating", "fine"), default="fine",
                   help="last sweep to capture (shorter captures are for checks)")
    c.add_argument("--panel", default="128x128",
                   help="--direct: SLM window WxH shown (default 128x128)")
    c.add_argument("--sim-seed", type=int, default=None,
                   help="--direct: randomise the simulated bench with this seed")
    c.add_argument("--stage-center", type=float, default=10.0, help="stage mm (default 10)")
    c.add_argument("--stage-range", type=float, default=2.5, help="+- mm coarse sweep")
    c.add_argument("--coarse-step", type=float, default=0.25, help="coarse step mm")
    c.add_argument("--fine-steps", type=int, default=13, help="fine sweep positions")
    c.add_argument("--force", action="store_true", help="overwrite an existing capture")
    c.set_defaults(handler=run_capture)
    f = cmds.add_parser("fit", help="fit the bench model to a capture")
    f.add_argument("dir", help="capture directory")
    f.add_argument("-o", "--out", default="calibration.toml", help="calibration file")
    f.set_defaults(handler=run_fit)
    r = cmds.add_parser("report", help="PNGs of a capture against its fit, or of a learned "
                                       "bench against the parametric one")
    r.add_argument("dir", help="a capture directory, or a folder `nhfd calib learn` wrote "
                               "(fidelity.png, fidelity_psnr.png, fidelity.json)")
    r.add_argument("--calibration", help="a capture's calibration.toml (default: fit now)")
    r.add_argument("-o", "--out", help="PNG folder (default DIR/report)")
    r.set_defaults(handler=run_report)
    learn_p = cmds.add_parser("learn", help="learn what the parametric bench model leaves out, "
                                            "from captures (docs/learned_bench.md)")
    learn_p.add_argument("--direct", action="store_true",
                         help="capture on the simulated bench in this process (default: "
                              "through the running daemon, nhfd serve)")
    learn_p.add_argument("--out", required=True,
                         help="folder for learned.safetensors, calibration.toml (the "
                              "calibration referencing it), learn.json and the captures; "
                              "through the daemon it must lie inside its "
                              "daemon.paths.pattern_dirs. A stopped run resumes from it")
    learn_p.add_argument("--calibration", default=None,
                         help="the parametric calibration to learn on top of (default: the "
                              "daemon's; with --direct, the simulated bench's, fitted into "
                              "OUT/parametric once and reused)")
    learn_p.add_argument("--socket", help="daemon control socket (default: from the "
                                          "configuration)")
    learn_p.add_argument("--config", help="configuration file (the daemon's: its optics, "
                                          "coding and daemon.server.runtime_dir)")
    learn_p.add_argument("--camera-pitch-um", type=float, default=None,
                         help="through the daemon: the camera's pixel pitch in um, where the "
                              "calibration did not record it (default: the configuration's "
                              "devices.camera_settings.pixel_pitch_um)")
    twin_g = learn_p.add_mutually_exclusive_group()
    twin_g.add_argument("--sim-seed", type=int, default=None,
                        help="--direct: randomise the simulated bench with this seed "
                             "(default: the packaged twin)")
    twin_g.add_argument("--twin", metavar="FILE", default=None,
                        help="--direct: a TOML file of the simulated bench's fields (as `nhfd "
                             "bench quality --twin`; `randomised_seed = N` starts from a "
                             "seed's draws)")
    learn_p.add_argument("--window", default="64x64", help="window WxH px (default 64x64)")
    learn_p.add_argument("--patterns", type=int, default=None,
                         help="sgd patterns (default 12; random 4 and structured 8 beside)")
    learn_p.add_argument("--random", type=int, default=None,
                         help="random grey-level patterns (default 4)")
    learn_p.add_argument("--structured", type=int, default=None,
                         help="structured patterns: gratings, blocks (default 8)")
    learn_p.add_argument("--held-out", type=int, default=None,
                         help="patterns held out for scoring (default 6)")
    learn_p.add_argument("--steps", type=int, default=None, help="fit steps (default 150)")
    learn_p.add_argument("--seed", type=int, default=0, help="patterns' and fit's seed")
    learn_p.add_argument("--power", type=float, default=None,
                         help="--direct: the simulated laser's power, %% (default 10: its cap; "
                              "through the daemon a person sets the powers)")
    learn_p.set_defaults(handler=run_learn)


def _say(msg: str) -> None:
    print(msg, file=sys.stderr)


def run_capture(args: argparse.Namespace) -> int:
    try:
        return _capture_direct(args) if args.direct else _capture_daemon(args)
    except CaptureError as exc:
        raise ValueError(str(exc)) from None


def _plan(args: argparse.Namespace, camera_pitch_m: float) -> object:
    return CapturePlan(stage_center_mm=args.stage_center, stage_range_mm=args.stage_range,
                       coarse_step_mm=args.coarse_step, fine_steps=args.fine_steps,
                       camera_pitch_m=camera_pitch_m,
                       exposure_s=args.exposure, stop_after=args.stop_after)


def _capture_direct(args: argparse.Namespace) -> int:
    w, h = parse_wxh(args.panel)
    bench = TrueBench.randomised(args.sim_seed) if args.sim_seed is not None else TrueBench()
    spec = PatternSpec((h, w), bench.pitch_m, bench.wavelengths_m)
    capture(args.out, SimBenchIO(bench, (h, w), exposure_s=args.exposure), spec,
            _plan(args, bench.camera_pitch_m), force=args.force,  # type: ignore[arg-type]
            progress=_say)
    return 0


def _capture_daemon(args: argparse.Namespace) -> int:
    config = load_config(args.config).config
    sock = socket_path(args.socket, config)
    pitch_um = args.camera_pitch_um or config.devices.camera_settings.pixel_pitch_um
    out = Path(args.out)
    with Client(sock, timeout_s=30.0) as client:
        io = DaemonBenchIO(client, out / "daemon", exposure_s=args.exposure, arm_s=args.arm,
                           home=args.home)
        try:
            capture(out, io, daemon_spec(client.status()),
                    _plan(args, pitch_um * 1e-6),  # type: ignore[arg-type]
                    force=args.force, progress=_say)
        finally:
            io.lasers_off()
    return 0


def run_fit(args: argparse.Namespace) -> int:
    cal = fit_capture(args.dir, progress=_say)
    path = cal.save(Path(args.out))
    print(f"wrote {path}")
    return 0


def run_report(args: argparse.Namespace) -> int:
    if is_learn_folder(args.dir):
        if args.calibration:
            raise ValueError(f"--calibration {args.calibration}: a learned bench's report uses "
                             f"the calibration in {args.dir}")
        paths = write_learned_report(args.dir, args.out)
    else:
        cal = Calibration.load(args.calibration) if args.calibration else None
        paths = write_report(args.dir, cal, args.out)
    for path in paths:
        print(path)
    return 0


def _learn_plan(args: argparse.Namespace, window_hw: tuple[int, int]) -> LearnPlan:
    given = {"sgd_patterns": args.patterns, "random_patterns": args.random,
             "structured_patterns": args.structured, "held_out_patterns": args.held_out,
             "steps": args.steps}
    return LearnPlan(window_hw=window_hw, seed=args.seed,
                     **{k: v for k, v in given.items() if v is not None})


def _print_learned(result: LearnResult, out: Path, where: str) -> None:
    print(f"wrote {result.weights} and {result.calibration} (capture {result.capture_s:.0f} s, "
          f"fit {result.fit_s:.0f} s {where})")
    for line in result.lines():
        print(line)
    for path in write_learned_report(out):
        print(f"wrote {path}")


def run_learn(args: argparse.Namespace) -> int:
    w, h = parse_wxh(args.window)
    out = Path(args.out)
    if not args.direct:
        return _learn_daemon(args, (h, w), out)
    if args.socket or args.camera_pitch_um is not None:
        raise ValueError(f"{'--socket' if args.socket else '--camera-pitch-um'}: for the "
                         "daemon's bench, not with --direct")
    panel_hw = sim_panel_hw((h, w), SIM_PANEL_MARGIN_PX)
    twin = (TrueBench.from_toml(args.twin) if args.twin else
            TrueBench.randomised(args.sim_seed) if args.sim_seed is not None else TrueBench())
    cal = (Calibration.load(args.calibration) if args.calibration else
           twin_calibration(out / "parametric", twin, panel_hw, say=_say))
    plan = _learn_plan(args, (h, w))
    power = SIM_POWER_PCT if args.power is None else args.power
    with sim_devices(twin, panel_hw, power_pct=power) as devices:
        result = learn(camera_loop(devices, cal), cal, Config(), plan, out, panel_hw=panel_hw,
                       say=_say)
    _print_learned(result, out, "on the simulated bench")
    return 0


def _daemon_calibration(status: dict, given: str | None) -> Calibration:
    """The calibration the daemon applies (its `status.calibration`), which moves its stage:
    `given` (a file) only when it is that one."""
    info = status.get("calibration") or {}
    if not info.get("loaded"):
        raise ValueError("the daemon has no calibration (calibration.file): nhfd calib learn "
                         "learns on top of one (nhfd calib capture, nhfd calib fit)"
                         + (f"; {info['error']}" if info.get("error") else ""))
    cal = Calibration.load(given or info["file"])
    if given and fingerprint(cal) != info.get("sha256"):
        raise ValueError(f"--calibration {given} is not the calibration the daemon applies "
                         f"({info.get('file')}, created {info.get('created')}): its focus "
                         "mapping moves the stage; give that file, or none")
    return cal


def _check_daemon_bench(status: dict, config: Config) -> None:
    """Refuse, before any pattern is made, a daemon that cannot capture the stacks or does not
    share this configuration's optics: the reference plane's distance, its colour mode, the
    arming and powers a person sets (`citl_laser_refusal`, the capture job's own rule)."""
    z0_m = float(status["panel"].get("z0_m", config.optics.z0_m))
    if abs(z0_m - config.optics.z0_m) > 1e-9:
        raise ValueError(f"optics.z0_mm = {config.optics.z0_mm:g} here, {z0_m * 1e3:g} in the "
                         "daemon: pass the daemon's configuration (--config)")
    mode = (status.get("colour") or {}).get("mode")
    if mode != "capture":
        raise ValueError(f"the daemon's daemon.frames.colour_mode is {mode!r}: nhfd calib learn "
                         "needs 'capture' (the daemon switches each diode on alone)")
    laser = status.get("laser") or {}
    channels = laser.get("channels") or {}
    refusal = citl_laser_refusal(
        laser.get("fault"), bool(laser.get("armed")), float(laser.get("armed_remaining_s") or 0),
        {ch: float((channels.get(ch) or {}).get("power_pct", 0.0)) for ch in COLOURS},
        who="nhfd calib learn")
    if refusal:
        raise ValueError(refusal)


def _learn_daemon(args: argparse.Namespace, window_hw: tuple[int, int], out: Path) -> int:
    for flag, value in (("--sim-seed", args.sim_seed), ("--twin", args.twin),
                        ("--power", args.power)):
        if value is not None:
            raise ValueError(f"{flag}: for the simulated bench (--direct); through the daemon "
                             "the bench is the daemon's and a person sets the powers")
    config = load_config(args.config).config
    sock = socket_path(args.socket, config)
    pitch_um = args.camera_pitch_um or config.devices.camera_settings.pixel_pitch_um
    plan = _learn_plan(args, window_hw)
    try:
        client = Client(sock, timeout_s=30.0)
    except OSError as exc:
        raise ValueError(f"cannot reach the daemon: {exc} (start nhfd serve, or pass --direct "
                         "for the simulated bench in this process)") from None
    with client:
        status = client.status()
        cal = _daemon_calibration(status, args.calibration)
        _check_daemon_bench(status, config)
        panel = status["panel"]
        panel_hw = (int(panel["height_px"]), int(panel["width_px"]))
        work = out / "daemon"

        def loop(encoder: Encoder) -> DaemonCameraLoop:
            return DaemonCameraLoop(client, cal, encoder, work, camera_pitch_m=pitch_um * 1e-6)

        try:
            result = learn(loop, cal, config, plan, out, panel_hw=panel_hw, say=_say)
        except CaptureStopped as exc:
            kept = out / PARTIAL_NAME
            raise ValueError(f"the capture stopped: {exc}" + (
                f"; the patterns captured so far are kept in {kept}: run the same command "
                "again to resume" if kept.is_file() else "")) from None
    _print_learned(result, out, "through the daemon")
    return 0
