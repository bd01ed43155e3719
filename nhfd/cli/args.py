"""Argument parsing shared by the command modules (no heavy imports), and the lazy subcommand
registry that `nhfd` and `nhfd bench` list their commands from.

Errors are ValueErrors that name the option, the value and the allowed form; `nhfd` prints them
as one line and exits 2.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import re
import sys
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from nhfd.config import ConfigMigrationWarning

MAX_SIDE_PX = 16384
# The scene formats, as help texts name them (every suffix `nhfd.scene.io` reads; a test holds
# the two together).
SCENE_FORMATS = ".ply (INRIA and PlayCanvas compressed), .splat, .spz, glTF (.glb, .gltf) and SOG"


def parse_wxh(text: str, option: str = "--size", max_px: int = MAX_SIDE_PX) -> tuple[int, int]:
    """'WxH' -> (W, H), each in 1..max_px."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise ValueError(f"{option} {text!r} is not of the form WxH (e.g. 1024x576)")
    w, h = int(m.group(1)), int(m.group(2))
    if not (1 <= w <= max_px and 1 <= h <= max_px):
        raise ValueError(f"{option} {text!r}: width and height must be 1..{max_px} px")
    return w, h


@dataclass(frozen=True)
class Command:
    """One registry row: the command's name, the module that builds its parser and handler
    (`register(subparsers)`), and the one-line help `--help` lists without importing it."""

    name: str
    module: str
    help: str


class LazyCommands(argparse._SubParsersAction):
    """Subcommands listed from a registry and built on demand: each starts as a stub parser that
    carries only its help line; parsing a command imports its module, which replaces the stubs of
    every command it registers with the real parsers. So `--help` lists everything and a command
    imports its own module only (a heavy one costs a second or more, and `nhfd serve` and
    `nhfd laser-off` must not pay for the others). Uses argparse's subparser map, which is
    private but stable since Python 3.2."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._stubs: dict[str, str] = {}  # command name -> its module, until loaded

    def add_registry(self, commands: tuple[Command, ...]) -> None:
        for command in commands:
            self.add_parser(command.name, help=command.help, add_help=False)
            self._stubs[command.name] = command.module

    def load(self, name: str) -> None:
        """Replace `name`'s stub (and its module's other stubs) with the module's parsers."""
        module = self._stubs.get(name)
        if module is None:
            return
        siblings = {n for n, m in self._stubs.items() if m == module}
        for n in siblings:
            del self._stubs[n]
            del self._name_parser_map[n]
        position = next(i for i, a in enumerate(self._choices_actions) if a.dest in siblings)
        kept = [a for a in self._choices_actions if a.dest not in siblings]
        self._choices_actions[:] = kept[:position]
        importlib.import_module(module).register(self)
        self._choices_actions.extend(kept[position:])  # the module's rows where its stubs were

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        self.load(values[0])
        super().__call__(parser, namespace, values, option_string)


@contextlib.contextmanager
def config_warnings_as_lines(prog: str) -> Iterator[None]:
    """Inside: a configuration warning (`nhfd.config.ConfigMigrationWarning`, a key read from
    its old place) is printed to stderr as one line, `prog: warning: message`, not as Python's
    warning with its source line; other warnings are shown as before."""
    shown = warnings.showwarning

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
             file: Any = None, line: str | None = None) -> None:
        if issubclass(category, ConfigMigrationWarning):
            print(f"{prog}: warning: {message}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = shown
