"""`nhfctl`: steer a running `nhfd serve` over its control socket.

The daemon arrives with issue 7; until then every command says what it will do and exits 1.
This module must never import torch, numba or onnxruntime: a control command answers at once.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

PLANNED = {
    "set-view": "move the displayed view (6-DoF pose, orbit, or a relative move)",
    "focus": "move the camera stage to a hologram depth in mm",
    "laser": "arm, disarm, or set per-channel laser power (capped)",
    "status": "devices, model, scene, calibration, last frame's timings, errors, jobs",
    "snapshot": "capture the camera to a PNG",
    "blank": "show the blank (zero-amplitude) pattern",
    "stop": "stop the stage and running jobs",
    "shutdown": "shut the daemon down cleanly with lasers off",
    "watch": "live status",
}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="nhfctl", description="Control a running `nhfd serve` (not available yet)."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, text in PLANNED.items():
        sub.add_parser(name, help=text)
    args = parser.parse_args(argv)
    print(
        f"nhfctl {args.command}: not available yet: the daemon `nhfd serve` does not exist in "
        f"this version; this command will {PLANNED[args.command]}.",
        file=sys.stderr,
    )
    return 1


if __name__ == "__main__":
    sys.exit(main())
