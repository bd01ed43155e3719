"""`nhfctl`: steer a running `nhfd serve` over its control socket.

Human output by default, `--json` for scripts. Exit codes: 0 ok, 1 the daemon refused (one line:
the error's name and message), 2 usage, 3 no daemon answers. This module must never import torch,
numba or onnxruntime (a test checks `sys.modules`): a control command answers at once.

`laser off` and `laser disarm` never depend on the daemon alone: when it cannot be reached, is
busy, refuses or does not answer within a second, they switch the lasers off through the laser
guardian (or on the port), as `nhfd laser-off` does, and say which path did it. They exit 0 only
when every channel was read back off. `laser arm` with a confirmation configured
(`daemon.arming.confirm`) prints what the person at the bench must do and waits for the arm's job.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from nhfd.cli import human
from nhfd.cli.args import config_warnings_as_lines
from nhfd.cli.cmd_laser import laser_settings, switch_all_off
from nhfd.cli.human import fields, view_words
from nhfd.config import ServerSettings, load_config
from nhfd.daemon.client import LOOPBACK_HOSTS, Client, DaemonUnavailable, TLSFailure
from nhfd.daemon.paths import socket_path
from nhfd.daemon.protocol import RpcError, describe_codes
from nhfd.device_settings import LaserSettings
from nhfd.drivers.guardian import socket_path_for
from nhfd.drivers.rundir import runtime_dir
from nhfd.views import QUALITY_TIERS

# How long `laser off` / `disarm` waits for the daemon before going to the guardian: a healthy
# daemon answers in milliseconds, and one a second late has missed its heartbeats already.
OFF_DAEMON_TIMEOUT_S = 1.0


def _floats(n: int, form: str):  # argparse type factory; argparse names the option
    def parse(text: str) -> list[float]:
        values = []
        for token in text.split(","):
            try:
                values.append(float(token))
            except ValueError:
                raise argparse.ArgumentTypeError(
                    f"{token.strip()!r} is not a number: expected {form}, {n} numbers "
                    "separated by commas") from None
        if len(values) != n:
            raise argparse.ArgumentTypeError(f"{len(values)} numbers in {text!r}: expected "
                                             f"{form}, {n} numbers separated by commas")
        return values

    return parse


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="nhfctl", description="Control a running `nhfd serve`.",
                                epilog="Error codes:\n" + describe_codes(),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--socket", help="control socket (default: from the configuration)")
    p.add_argument("--config", help="configuration file whose daemon.server.runtime_dir to use")
    p.add_argument("--tcp", metavar="HOST:PORT", help="TCP instead of the socket (a host other "
                   "than loopback only with --tls or --tls-ca)")
    p.add_argument("--token-file", help="TCP token file")
    p.add_argument("--tls", action="store_true",
                   help="TLS on --tcp, the daemon's certificate checked against the system's CAs")
    p.add_argument("--tls-ca", metavar="PEM",
                   help="TLS on --tcp, the daemon's certificate checked against this file (its "
                   "own self-signed certificate, or the CA that signed it)")
    p.add_argument("--timeout-s", type=float, default=5.0, help="per-call timeout (default 5)")
    p.add_argument("--json", action="store_true", help="print the raw JSON result")
    p.add_argument("--wait-s", type=float, default=0.0, metavar="S",
                   help="wait up to S seconds for the daemon to answer (one just started with "
                        "`nhfd serve &` takes a few); default 0: fail at once when none does")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sv = sub.add_parser("set-view", help="move the displayed view (pose, orbit or relative)")
    g = sv.add_mutually_exclusive_group(required=True)
    g.add_argument("--orbit", type=_floats(3, "AZ,EL,R"), metavar="AZ,EL,R",
                   help="azimuth and elevation (deg), radius (scene units)")
    g.add_argument("--pose", type=_floats(7, "X,Y,Z,QW,QX,QY,QZ"), metavar="X,Y,Z,QW,QX,QY,QZ",
                   help="camera position and camera-to-world quaternion (OpenCV axes)")
    g.add_argument("--by-orbit", type=_floats(3, "DAZ,DEL,DR"), metavar="DAZ,DEL,DR",
                   help="relative orbit move")
    g.add_argument("--by-pose", type=_floats(6, "DX,DY,DZ,RX,RY,RZ"), metavar="DX,DY,DZ,RX,RY,RZ",
                   help="relative camera-frame translation and rotation (deg)")
    sv.add_argument("--quality", choices=QUALITY_TIERS,
                    help="the frame tier: network (the network's frame, at once), exact (the "
                         "view's own hologram, no network: seconds), sgd (the SLM pattern "
                         "optimised through the calibrated bench model), citl (sgd, then the "
                         "bench's camera in the loop: colour_mode capture, a calibration, armed "
                         "lasers with every colour's power set); above network the "
                         "network's frame shows at once and better ones replace it while the "
                         "view rests (status shows the tier, iterations and estimated PSNR); "
                         "default: the current view's, or refine.quality")
    sv.add_argument("--wait", action="store_true",
                    help="wait until the view is shown and, above network, refined (up to 10 "
                         "min), then say how far the refinement went")

    fo = sub.add_parser("focus", help="move the camera stage to a hologram depth (mm)")
    fo.add_argument("z_mm", type=float)
    fo.add_argument("--home", action="store_true", help="home the stage first")
    fo.add_argument("--wait", action="store_true", help="wait for the job to finish")

    la = sub.add_parser("laser", help="arm, disarm, off, or per-channel power (capped)")
    la.add_argument("action", choices=("arm", "disarm", "off", "power", "enable", "disable"))
    la.add_argument("channel", nargs="?", choices=("red", "green", "blue"))
    la.add_argument("power_pct", nargs="?", type=float)
    la.add_argument("--duration-s", type=float, default=60.0, help="arming time (default 60)")
    la.add_argument("--guardian-socket", metavar="PATH",
                    help="off / disarm: the laser guardian's socket, used when the daemon does not "
                    "switch the lasers off (default: devices.readybeam.guardian.socket_path, else "
                    "laser.sock beside the control socket)")

    sub.add_parser("status", help="devices, laser, scene, model, view, errors, jobs")
    sn = sub.add_parser("snapshot", help="capture the camera to a PNG")
    sn.add_argument("--out", help="file name inside daemon.paths.snapshot_dir")
    sn.add_argument("--frames", type=int)
    sn.add_argument("--wait", action="store_true", help="wait for the job to finish")
    sub.add_parser("blank", help="show the blank (zero-amplitude) pattern")
    sub.add_parser("stop", help="stop the stage and running jobs")
    sub.add_parser("shutdown", help="shut the daemon down cleanly with lasers off")
    ls = sub.add_parser("load-scene", help="load a scene (inside daemon.paths.scene_dirs); waits "
                        "for the load and exits 1 with its error when it fails")
    ls.add_argument("path")
    lm = sub.add_parser("load-model", help="load an exported model (inside "
                        "daemon.paths.model_dirs; validated, the old one keeps running on "
                        "failure); waits for the load and exits 1 with its error when it fails")
    lm.add_argument("path")
    for load in (ls, lm):
        # A load is a job; without waiting, a refused file would exit 0 and look loaded.
        load.add_argument("--no-wait", dest="wait", action="store_false",
                          help="return once the load is queued (prints the job id)")
    jb = sub.add_parser("job", help="one job's state")
    jb.add_argument("id", type=int)
    wa = sub.add_parser("watch", help="live status")
    wa.add_argument("--interval-s", type=float, default=1.0)
    wa.add_argument("--count", type=int, default=0, help="stop after N updates (0 = never)")
    return p


def _request(args: argparse.Namespace) -> tuple[str, dict[str, Any]]:
    cmd = args.command
    if cmd == "set-view":
        method, params = _view_request(args)
        return method, {**params, **({"quality": args.quality} if args.quality else {})}
    return _other_request(args)


def _view_request(args: argparse.Namespace) -> tuple[str, dict[str, Any]]:
    if args.orbit:
        az, el, r = args.orbit
        return "set_view", {"orbit": {"azimuth_deg": az, "elevation_deg": el, "radius": r}}
    if args.pose:
        return "set_view", {"pose": {"position": args.pose[:3],
                                     "quaternion_wxyz": args.pose[3:]}}
    if args.by_orbit:
        daz, de, dr = args.by_orbit
        return "set_view", {"relative": {"d_azimuth_deg": daz, "d_elevation_deg": de,
                                         "d_radius": dr}}
    return "set_view", {"relative": {"translate": args.by_pose[:3],
                                     "rotate_deg": args.by_pose[3:]}}


def _other_request(args: argparse.Namespace) -> tuple[str, dict[str, Any]]:
    cmd = args.command
    if cmd == "focus":
        return "focus", {"z_mm": args.z_mm, **({"home": True} if args.home else {})}
    if cmd == "laser":
        params: dict[str, Any] = {"action": args.action}
        if args.action == "arm":
            params["duration_s"] = args.duration_s
        if args.action in ("power", "enable", "disable"):
            if args.channel is None:
                raise SystemExit(f"nhfctl laser {args.action}: a channel is needed")
            params["channel"] = args.channel
        if args.action == "power":
            if args.power_pct is None:
                raise SystemExit("nhfctl laser power: CHANNEL POWER_PCT")
            params["power_pct"] = args.power_pct
        return "laser", params
    if cmd == "snapshot":
        params = {}
        if args.out:
            params["path"] = args.out
        if args.frames:
            params["frames"] = args.frames
        return "snapshot", params
    if cmd == "load-scene":
        return "load_scene", {"path": args.path}
    if cmd == "load-model":
        return "load_model", {"path": args.path}
    if cmd == "job":
        return "job", {"id": args.id}
    return cmd.replace("-", "_"), {}


def _socket(args: argparse.Namespace) -> str:
    # Same rules as the daemon: the configuration is read only when no --socket is given.
    return socket_path(args.socket, lambda: load_config(args.config).config)


def _connect(args: argparse.Namespace) -> Client:
    """The client, after waiting up to `--wait-s` for a daemon to answer."""
    deadline = time.monotonic() + max(0.0, getattr(args, "wait_s", 0.0) or 0.0)
    while True:
        try:
            return _open(args)
        except TLSFailure:  # a certificate not trusted stays so
            raise
        except DaemonUnavailable:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.2)


def _open(args: argparse.Namespace) -> Client:
    if args.tcp:
        host, _, port = args.tcp.rpartition(":")
        token = Path(args.token_file).read_text().strip() if args.token_file else None
        return Client(tcp=(host.strip("[]"), int(port)), token=token, tls=args.tls,
                      tls_ca=args.tls_ca, timeout_s=args.timeout_s)
    return Client(_socket(args), timeout_s=args.timeout_s)


def human_status(s: dict[str, Any]) -> str:
    d, laser, dev = s["daemon"], s["laser"], s["devices"]
    lines = [f"daemon   {d['state']}, pid {d['pid']}, up {d['uptime_s']:.0f} s, {d['socket']}"]
    if laser.get("backend") == "none":
        lines.append("laser    none")
    else:
        on = [f"{ch} {c['power_pct']:g}%" for ch, c in laser.get("channels", {}).items()
              if c["enabled"]]
        armed = (f"ARMED {laser['armed_remaining_s']:.0f} s left" if laser["armed"]
                 else "not armed")
        lines.append(f"laser    {armed}; emitting: {', '.join(on) or 'none'}"
                     + (f"; FAULT {laser['fault']}" if laser.get("fault") else ""))
    for name, info in dev.items():
        extra = ""
        if name == "stage" and "position_mm" in info:
            extra = (f" at {info['position_mm']:.3f} mm"
                     f"{', homed' if info.get('homed') else ', not homed'}"
                     f"{', moving' if info.get('moving') else ''}")
        if name == "slm" and info["open"]:
            extra = f" showing {info['showing']}"
        state = "open" if info["open"] else "closed"
        lines.append(f"{name:<8} {info['backend']}, {state}{extra}"
                     + (f"; error: {info['error']}" if info.get("error") else ""))
    scene = s.get("scene")
    shown = f"{scene['path']} ({scene['gaussians']} Gaussians)" if scene else "none"
    lines.append(f"scene    {shown}")
    lines.append(f"model    {human_model(s['model'])}")
    if "colour" in s:
        col = s["colour"]
        lines.append(f"colour   {col['mode']}"
                     + (f" ({col['single_colour']})" if col["mode"] == "single" else ""))
    cal = s.get("calibration") or {}
    if cal.get("loaded"):
        lines.append(f"calib    {cal['file']} (fitted on {cal.get('fitted_on') or '?'})")
    else:
        lines.append("calib    none" + (f"; error: {cal['error']}" if cal.get("error") else
                                        " (uncalibrated focus mapping)"))
    nav = s.get("navigator") or {}
    if nav.get("backend", "none") != "none":
        lines.append(f"navigator {nav['backend']}, {nav['moves']} moves"
                     + (f"; error: {nav['error']}" if nav.get("error") else ""))
    v = s["view"]
    requested = view_words(v["requested"]) if v.get("requested") else "none yet"
    lines.append(f"view     seq {v['seq']}: {requested}")
    for w in s.get("warnings") or []:
        lines.append(f"warning  {w}")
    refine = (s.get("frames") or {}).get("refine")
    if refine:
        lines.append("refine   " + human_refine(refine))
    active = [j for j in s["jobs"] if j["state"] in ("queued", "running")]
    lines.append(f"jobs     {len(active)} active, {len(s['jobs'])} listed")
    for e in s["errors"][-5:]:
        lines.append(f"error    {e['source']}: {e['message']}")
    return "\n".join(lines)


def human_refine(r: dict[str, Any]) -> str:
    """One line of `status.frames.refine`: the tier, how far it went, the estimated PSNR."""
    psnr = r.get("psnr_db")
    start = r.get("start_psnr_db")
    gain = (f"{psnr:.1f} dB (from {start:.1f})" if psnr is not None and start is not None
            else "no estimate yet")
    stop = r.get("stop") or r.get("phase") or "refining"
    subframes = f", {r['subframes']} subframes" if r.get("subframes", 0) > 1 else ""
    return (f"{r['tier']} of view {r['seq']}: {r.get('iterations', 0)} iterations in "
            f"{r.get('seconds', 0.0):.1f} s, {gain}, {r.get('swaps', 0)} frames swapped in"
            f"{subframes}; {stop}")


def _size(hw: Any) -> str:
    return f"{hw[1]} x {hw[0]} px" if isinstance(hw, list | tuple) and len(hw) == 2 else "?"


def human_model(model: Any) -> str:
    """The loaded model as one line: file, profile, training size, providers, checked sizes."""
    if not isinstance(model, dict):
        return str(model)  # "none loaded"
    name = Path(str(model.get("path", "?"))).name
    parts = [f"profile {model['profile']}" if model.get("profile") else None,
             f"trained {_size(model.get('train_size_hw'))}",
             ", ".join(model.get("providers") or []) or None]
    checked = model.get("checked_sizes_hw") or (
        [model["checked_size_hw"]] if model.get("checked_size_hw") else [])
    if checked:
        parts.append("checked at " + ", ".join(_size(hw) for hw in checked))
    tuned = model.get("tuned_for")
    if tuned:
        parts.append(f"tuned for calibration {tuned.get('calibration')} ({tuned.get('date')})")
    return f"{name} ({'; '.join(p for p in parts if p)})"


def _human(cmd: str, result: Any) -> str:
    if cmd == "status":
        return human_status(result)
    if cmd in ("load-model", "load-scene") and isinstance(result, dict) and "state" in result:
        loaded = result.get("result") or {}
        what = (human_model(loaded) if cmd == "load-model" else
                f"{loaded.get('path')} ({loaded.get('gaussians')} Gaussians)")
        return f"loaded {what} (job {result['id']})"
    if isinstance(result, dict) and "state" in result and "kind" in result:
        return human.job(result)  # a job waited for (--wait), or `job N`
    if isinstance(result, dict) and "job" in result and len(result) <= 3:
        rest = fields({k: v for k, v in result.items() if k != "job"})
        return f"job {result['job']} queued" + (f" ({rest})" if rest else "")
    if cmd == "shutdown" and isinstance(result, dict) and result.get("shutting_down"):
        return "the daemon is shutting down: lasers off and read back, then it exits"
    if cmd == "set-view":
        warning = f"\nwarning: {result['warning']}" if result.get("warning") else ""
        return f"view seq {result['seq']}: {view_words(result['view'])}{warning}"
    if isinstance(result, dict):
        return fields(result)
    return human.value(result)


def _remote(args: argparse.Namespace) -> bool:
    """A daemon on another machine (--tcp beyond loopback): its guardian is not reachable here."""
    return bool(args.tcp) and args.tcp.rpartition(":")[0].strip("[]") not in LOOPBACK_HOSTS


def _guardian_socket(args: argparse.Namespace, settings: LaserSettings,
                     server: ServerSettings | None) -> Path:
    """--guardian-socket; else the configured guardian socket; else laser.sock in the daemon's
    runtime directory (the one --socket lies in, or the configured one)."""
    if args.guardian_socket:
        return Path(args.guardian_socket)
    if args.socket:
        return socket_path_for(settings, Path(args.socket).parent)
    return socket_path_for(settings, runtime_dir(server.runtime_dir if server else ""))


def _laser_off(args: argparse.Namespace) -> int:
    """`laser off` / `laser disarm`: through the daemon, else through the guardian (or the
    port). 0 only when the lasers were read back off; the output says which path did it."""
    cmd = f"nhfctl laser {args.action}"
    args.timeout_s = min(args.timeout_s, OFF_DAEMON_TIMEOUT_S)
    unavailable = False
    try:
        with _connect(args) as client:
            result = client.call("laser", action=args.action)
            where = client.where
        # The daemon's guardian switched every channel off and read it back, or this raised.
        print(json.dumps({**result, "switched_off_by": "daemon"}) if args.json else
              f"all laser channels off (through the daemon at {where}, read back by its laser "
              "guardian)")
        return 0
    except RpcError as exc:
        reason = f"the daemon refused: {exc.name}: {exc.message}"
    except DaemonUnavailable as exc:
        reason, unavailable = str(exc), True
    except (OSError, ValueError) as exc:
        reason, unavailable = str(exc), True
    if _remote(args):
        print(f"{cmd}: error: lasers NOT confirmed off: {reason}; the laser guardian is on the "
              "bench's machine: run `nhfd laser-off` there", file=sys.stderr)
        return 3 if unavailable else 1
    print(f"{cmd}: the daemon did not switch the lasers off ({reason}); switching them off "
          "through the laser guardian", file=sys.stderr, flush=True)
    settings, server = laser_settings(args.config, prog=cmd)
    path = _guardian_socket(args, settings, server)
    outcome = switch_all_off(settings, path, server, timeout_s=3.0, prog=cmd,
                             port_hint="devices.readybeam.port, or nhfd laser-off --port")
    if not outcome.confirmed:
        print(f"{cmd}: error: lasers NOT confirmed off: {outcome.how}", file=sys.stderr)
        return 3 if unavailable else 1
    by = "guardian" if outcome.how.startswith("read back by the guardian") else "port"
    print(json.dumps({"armed": False, "all_off": True, "switched_off_by": by,
                      "how": outcome.how, "daemon": reason}) if args.json else
          f"all laser channels off (without the daemon, {outcome.how})")
    return 0


def _wait_for_arm(client: Client, result: dict[str, Any]) -> tuple[int, Any]:
    """A `laser arm` that waits for a person at the bench: say what to do, wait for its job."""
    print(f"nhfctl laser arm: waiting for the person at the bench to {result['prompt']} "
          f"(job {result['job']})", file=sys.stderr, flush=True)
    job = client.wait_job(int(result["job"]))
    if job["state"] != "done":
        why = job["error"] or "still waiting after the wait"
        print(f"nhfctl laser arm: error: job {job['id']} {job['state']}: {why}", file=sys.stderr)
        return 1, job
    return 0, job["result"]


def _wait_view(client: Client, args: argparse.Namespace, placed: dict[str, Any]) -> int:
    """`set-view --wait`: the view placed, then once it rests its refinement (the tier, its
    iterations, seconds and estimated PSNR); exit 1 when it did not get there."""
    seq, refined = int(placed["seq"]), placed["view"].get("quality", "network") != "network"
    s = client.wait_view(seq, refined)
    refine = (s.get("frames") or {}).get("refine")
    refine = refine if refine and refine.get("seq") == seq else None
    problem = None
    if s["view"]["seq"] != seq:
        problem = f"view seq {s['view']['seq']} replaced it before it rested"
    elif (s["view"].get("applied_seq") or 0) < seq:
        problem = "not shown after the wait"
    elif refined and not (refine and refine.get("stop")):
        problem = "its refinement still running after the wait"
    if args.json:
        print(json.dumps({**placed, "refine": refine}))
    else:
        print(_human("set-view", placed) + ("\nrefine   " + human_refine(refine) if refine
                                            else ""))
    if problem:
        print(f"nhfctl set-view: error: view seq {seq}: {problem}", file=sys.stderr)
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    with config_warnings_as_lines("nhfctl"):
        return _main(args)


def _main(args: argparse.Namespace) -> int:
    cmd = args.command
    if cmd == "laser" and args.action in ("off", "disarm"):
        try:
            return _laser_off(args)
        except KeyboardInterrupt:
            return 130
    try:
        method, params = _request(args)
        with _connect(args) as client:
            if cmd == "watch":
                n = 0
                while True:
                    s = client.status()
                    print(json.dumps(s) if args.json else human_status(s) + "\n", flush=True)
                    n += 1
                    if args.count and n >= args.count:
                        return 0
                    time.sleep(args.interval_s)
            result = client.call(method, **params)
            if cmd == "laser" and isinstance(result, dict) and result.get("pending"):
                code, result = _wait_for_arm(client, result)
                if code:
                    return code
            if cmd == "set-view" and args.wait:
                return _wait_view(client, args, result)
            if getattr(args, "wait", False) and isinstance(result, dict) and "job" in result:
                result = client.wait_job(int(result["job"]))
                if result["state"] != "done":
                    why = result["error"] or "still running after the wait"
                    print(f"nhfctl {cmd}: error: job {result['id']} {result['state']}: {why}",
                          file=sys.stderr)
                    return 1
        print(json.dumps(result) if args.json else _human(cmd, result))
        return 0
    except RpcError as exc:
        print(f"nhfctl {cmd}: error: {exc.name}: {exc.message}", file=sys.stderr)
        return 1
    except DaemonUnavailable as exc:
        print(f"nhfctl {cmd}: error: {exc}", file=sys.stderr)
        return 3
    except (OSError, ValueError) as exc:
        print(f"nhfctl {cmd}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
