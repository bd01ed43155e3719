"""`nhfd`: one entry point, one module per command group.

Each command module exposes `register(subparsers)` and imports heavy libraries (torch, numba)
inside its handlers only, so `nhfd --help` and `nhfd config ...` answer at once.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from nhfd import __version__
from nhfd.config import ConfigError

# Modules under nhfd.cli, in the order their commands appear in --help.
COMMANDS = (
    "cmd_config",
    "cmd_demo",
    "cmd_scene",
    "cmd_dataset",
    "cmd_train",
    "cmd_bench",
    "cmd_serve",
    "cmd_replay",
    "cmd_laser",
    "cmd_devices",
    "calib",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nhfd",
        description="Neural holographic fields: render splat scenes, compute and learn complex "
        "holograms, and drive a holographic display bench.",
    )
    parser.add_argument("--version", action="version", version=f"nhfd {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        importlib.import_module(f"nhfd.cli.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except (ConfigError, ValueError, FileNotFoundError) as exc:
        print(f"nhfd {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"nhfd {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
