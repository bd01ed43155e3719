"""`nhfd config show|check`: the resolved configuration and where each value came from."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from nhfd.calibration import check_calibration_file
from nhfd.config import check_file, load_config, migrated_text


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "config",
        help="show or check the configuration",
        description="Show the resolved configuration (search order: --config, $NHFD_CONFIG, "
        "./nhfd.toml, $XDG_CONFIG_HOME/nhfd/nhfd.toml, /etc/nhfd/nhfd.toml, packaged default) "
        "or validate a file.",
    )
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    show = verbs.add_parser("show", help="print every resolved value and where it came from")
    show.add_argument("--config", help="configuration file to use (overrides the search order)")
    show.add_argument("--json", action="store_true", help="machine-readable output")
    show.set_defaults(handler=_show)
    check = verbs.add_parser("check", help="validate a configuration file")
    check.add_argument("file", nargs="?", help="file to check (default: the one found by search); "
                       "one with keys at their old places is printed migrated, to paste")
    check.set_defaults(handler=_check)


def _flatten(data: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _show(args: argparse.Namespace) -> int:
    loaded = load_config(args.config)
    values = _flatten(loaded.config.model_dump())
    if args.json:
        rows = {k: {"value": v, "source": loaded.sources.get(k, "packaged default")}
                for k, v in values.items()}
        print(json.dumps({"file": str(loaded.path) if loaded.path else None, "values": rows},
                         indent=2))
        return 0
    print(f"# configuration file: {loaded.path or 'none (packaged default only)'}")
    width = max(len(k) for k in values)
    for key, value in values.items():
        shown = json.dumps(value)
        print(f"{key:<{width}} = {shown:<24} # {loaded.sources.get(key, 'packaged default')}")
    return 0


def _check(args: argparse.Namespace) -> int:
    """What `nhfd serve` refuses at start is refused here: every value, every rule that joins
    sections (in the model), and the calibration file it names, opened. A valid file that sets
    keys at their old places (`nhfd.config.DAEMON_KEYS_MOVED`) is then printed with them in
    their new places: the file's own keys and values only, after a comment line naming the
    moves, so the lab can paste it over the old one."""
    if args.file:
        check_calibration_file(check_file(args.file), args.file)
        path: Path | None = Path(args.file)
        origin = args.file
    else:
        loaded = load_config()
        path = loaded.path
        origin = str(path or "packaged default")
        check_calibration_file(loaded.config, origin)
    print(f"{origin}: ok")
    if path is not None:
        text, moves = migrated_text(path)
        if moves:
            moved = ", ".join(f"{old} -> {new}" for old, new in moves)
            print(f"# {origin} sets {len(moves)} keys at their old places ({moved}); the file "
                  "migrated (its keys and values; its comments are not kept):")
            print(text, end="")
    return 0
