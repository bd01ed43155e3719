"""Command-line contracts: control commands stay light, errors are one line with a reason."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from nhfd.cli.args import LazyCommands
from nhfd.cli.cmd_bench import BENCHES
from nhfd.cli.main import COMMANDS, main
from tests.words import PYTHON_REPR

HEAVY = ("torch", "numba", "onnxruntime")
DONUT = Path(__file__).resolve().parents[2] / "models" / "scenes" / "donut.ply"


def imported_after(code: str) -> set[str]:
    probe = f"{code}\nimport sys\nprint(' '.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_control_client_and_config_import_no_heavy_libraries():
    for code in (
        "import nhfd.cli.nhfctl",
        "import nhfd.config",
        "from nhfd.cli.main import build_parser; build_parser()",
        # `nhfd serve` with nothing configured and the emergency `nhfd laser-off`
        "from nhfd.cli.main import build_parser; build_parser().parse_args(['serve'])",
        "from nhfd.cli.main import build_parser; build_parser().parse_args(['laser-off'])",
    ):
        loaded = imported_after(code)
        assert not loaded & set(HEAVY), (code, loaded & set(HEAVY))


def test_nhfctl_without_a_daemon_fails_with_a_one_line_reason(tmp_path):
    res = subprocess.run(
        [sys.executable, "-m", "nhfd.cli.nhfctl", "--socket", str(tmp_path / "none.sock"),
         "focus", "1.0"], capture_output=True, text=True
    )
    assert res.returncode == 3
    assert res.stderr.count("\n") == 1
    assert res.stderr.startswith("nhfctl focus: error: no nhfd serve at ")


def test_bad_cli_values_give_one_line_reasons(capsys):
    assert main(["bench", "optics", "--depths", "0", "--out", "/dev/null"]) == 2
    assert "must be positive" in capsys.readouterr().err


def test_help_lists_every_command_without_importing_their_modules():
    loaded = imported_after("from nhfd.cli.main import build_parser\n"
                            "import contextlib, io\n"
                            "with contextlib.redirect_stdout(io.StringIO()):\n"
                            "    try:\n        build_parser().parse_args(['--help'])\n"
                            "    except SystemExit:\n        pass")
    commands = {c.module for c in COMMANDS} | {b.module for b in BENCHES}
    assert not loaded & commands, loaded & commands
    listing = subprocess.run([sys.executable, "-m", "nhfd.cli.main", "--help"],
                             capture_output=True, text=True, check=True).stdout
    assert all(c.name in listing for c in COMMANDS)


def test_registry_help_lines_are_the_ones_the_modules_register():
    # The registry lists a command before its module is imported; once imported, the module's own
    # parser is what --help shows. Both must say the same.
    for registry in (COMMANDS, BENCHES):
        sub = argparse.ArgumentParser().add_subparsers(action=LazyCommands)
        sub.add_registry(registry)
        for command in registry:
            sub.load(command.name)
        shown = {a.dest: a.help for a in sub._choices_actions}
        assert shown == {c.name: c.help for c in registry}


def test_the_help_names_every_scene_format_the_readers_take():
    from nhfd.cli.args import SCENE_FORMATS
    from nhfd.scene.io import SCENE_NAMES, SCENE_SUFFIXES

    words = SCENE_FORMATS.lower()
    for suffix in SCENE_SUFFIXES:
        assert suffix.lstrip(".") in words, suffix
    assert "sog" in words and SCENE_NAMES  # SOG: a folder or its meta.json


@pytest.mark.parametrize("argv", [
    ["config", "show"], ["config", "check"], ["devices"], ["scene", "info", str(DONUT)],
    ["warmup"], ["--version"],
])
def test_nhfd_commands_print_words(argv, capsys, monkeypatch, tmp_path):
    """Each quick command's human output: something said, and no Python repr, None or epoch
    time (the refine test holds `nhfd refine` to the same)."""
    monkeypatch.chdir(tmp_path)  # no ./nhfd.toml: the packaged default
    monkeypatch.delenv("NHFD_CONFIG", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    try:
        code = main(argv)
    except SystemExit as exc:  # --version exits through argparse
        code = exc.code
    out = capsys.readouterr().out
    assert code == 0 and out.strip(), (argv, out)
    assert not PYTHON_REPR.search(out), (argv, out)
