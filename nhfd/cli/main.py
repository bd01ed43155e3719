"""`nhfd`: one entry point, one module per command group.

COMMANDS is the registry: each command's name, the module under nhfd.cli that builds its parser
and handler (`register(subparsers)`), and its one-line help. `nhfd --help` lists the registry
without importing any command module; running a command imports its module only (which imports
what it needs at module level), so `nhfd serve` and `nhfd laser-off` stay free of torch and numba
and `nhfd config ...` answers at once.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from nhfd import __version__
from nhfd.cli.args import SCENE_FORMATS, Command, LazyCommands, config_warnings_as_lines
from nhfd.config import ConfigError

# In the order --help lists them; each help line is the one its module registers (a test checks).
COMMANDS: tuple[Command, ...] = (
    Command("config", "nhfd.cli.cmd_config", "show or check the configuration"),
    Command("demo", "nhfd.cli.cmd_demo",
            "run the daemon on the simulated bench: views, a focus sweep, captures -> out/demo"),
    Command("scene", "nhfd.cli.cmd_scene",
            "inspect and render 3D Gaussian splat scenes: " + SCENE_FORMATS),
    Command("dataset", "nhfd.cli.cmd_dataset", "build and inspect training datasets"),
    Command("train", "nhfd.cli.cmd_train", "train the NHF network on a dataset"),
    Command("eval", "nhfd.cli.cmd_train", "hologram quality of a run or .onnx on held-out views"),
    Command("export", "nhfd.cli.cmd_train", "export a run to ONNX (checked against torch)"),
    Command("model", "nhfd.cli.cmd_model", "a scene to a served model in one command"),
    Command("refine", "nhfd.cli.cmd_refine",
            "a view's frame above the network's: exact, sgd or citl"),
    Command("bench", "nhfd.cli.cmd_bench", "run a benchmark"),
    Command("serve", "nhfd.cli.cmd_serve", "run the bench daemon in the foreground"),
    Command("replay", "nhfd.cli.cmd_replay", "replay a recorded session against a daemon"),
    Command("laser-off", "nhfd.cli.cmd_laser", "switch every laser channel off and read it back"),
    Command("laser-guardian", "nhfd.cli.cmd_laser", "run the laser guardian in the foreground"),
    Command("devices", "nhfd.cli.cmd_devices",
            "list connected devices and which config entry would use each"),
    Command("calib", "nhfd.cli.calib", "capture focal stacks and fit the bench model"),
    Command("warmup", "nhfd.cli.cmd_warmup",
            "compile the CPU kernels once, so the first view is fast"),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nhfd",
        description="Neural holographic fields: render splat scenes, compute and learn complex "
        "holograms, and drive a holographic display bench.",
    )
    parser.add_argument("--version", action="version", version=f"nhfd {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                action=LazyCommands)
    sub.add_registry(COMMANDS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with config_warnings_as_lines(f"nhfd {args.command}"):
            return int(args.handler(args) or 0)
    except (ConfigError, ValueError, FileNotFoundError) as exc:
        print(f"nhfd {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"nhfd {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
