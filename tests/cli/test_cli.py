"""Command-line contracts: control commands stay light, errors are one line with a reason."""

from __future__ import annotations

import subprocess
import sys

from nhfd.cli.main import main

HEAVY = ("torch", "numba", "onnxruntime")


def imported_after(code: str) -> set[str]:
    probe = f"{code}\nimport sys\nprint(' '.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_control_client_and_config_import_no_heavy_libraries():
    for code in (
        "import nhfd.cli.nhfctl",
        "import nhfd.config",
        "from nhfd.cli.main import build_parser; build_parser()",
    ):
        loaded = imported_after(code)
        assert not loaded & set(HEAVY), (code, loaded & set(HEAVY))


def test_nhfctl_says_what_it_will_do_and_fails_until_the_daemon_exists():
    res = subprocess.run(
        [sys.executable, "-m", "nhfd.cli.nhfctl", "focus"], capture_output=True, text=True
    )
    assert res.returncode == 1
    assert "not available yet" in res.stderr and "stage to a hologram depth" in res.stderr


def test_bad_cli_values_give_one_line_reasons(capsys):
    assert main(["bench", "optics", "--depths", "0", "--out", "/dev/null"]) == 2
    assert "must be positive" in capsys.readouterr().err
