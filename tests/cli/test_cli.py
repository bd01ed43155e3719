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
