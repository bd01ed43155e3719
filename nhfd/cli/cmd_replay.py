"""`nhfd replay FILE`: play a session recording (`nhfd serve --record`) against a daemon.

Meant for the simulated bench: start `nhfd serve` there, then replay; it ends in the recorded
view, focus and laser state. Requests go over the Unix socket (arming is accepted only there),
with the recorded spacing (`--speed 2` twice as fast, `--speed 0` as fast as the daemon answers);
then the replay waits for the daemon's jobs (focus moves, loads, snapshots) to finish. Exit code
1 when any request failed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from nhfd.config import load_config
from nhfd.daemon.client import Client
from nhfd.daemon.paths import socket_path
from nhfd.daemon.recording import read_session, replay


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="replay a recorded session against a daemon",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", help="session recording (JSON lines)")
    p.add_argument("--socket", help="control socket (default: from the configuration)")
    p.add_argument("--config", help="configuration file whose daemon.server.runtime_dir to use")
    p.add_argument("--speed", type=float, default=1.0,
                   help="time scale of the recorded spacing (0 = no waiting; default 1)")
    p.add_argument("--include-shutdown", action="store_true",
                   help="also replay a recorded shutdown")
    p.add_argument("--jobs-timeout-s", type=float, default=120.0,
                   help="how long to wait for the daemon's jobs at the end")
    p.set_defaults(handler=_replay)


def _replay(args: argparse.Namespace) -> int:
    if args.speed < 0:
        raise ValueError(f"--speed {args.speed:g}: must be >= 0")
    entries = read_session(Path(args.file))
    sock = socket_path(args.socket, lambda: load_config(args.config).config)
    failed = 0
    with Client(sock, timeout_s=30.0) as c:
        for entry, result in replay(entries, c.call, speed=args.speed,
                                    include_shutdown=args.include_shutdown):
            if isinstance(result, Exception):
                failed += 1
                print(f"nhfd replay: {entry['method']} at {entry.get('t_s', 0):.3f} s failed: "
                      f"{result}", file=sys.stderr)
        if not (args.include_shutdown and entries and entries[-1]["method"] == "shutdown"):
            end = time.monotonic() + args.jobs_timeout_s
            while any(j["state"] in ("queued", "running") for j in c.status()["jobs"]):
                if time.monotonic() > end:
                    print("nhfd replay: jobs still running after --jobs-timeout-s",
                          file=sys.stderr)
                    return 1
                time.sleep(0.05)
    print(f"replayed {len(entries)} requests from {args.file}; {failed} failed")
    return 1 if failed else 0
