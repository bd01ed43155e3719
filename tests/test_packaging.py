"""The wheel holds every subpackage and the package data (a new subfolder cannot drop out)."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROOTS = {"nhfd": "nhfd", "nhfd.drivers": "drivers", "nhfd.models": "models", "nhfd.calib": "calib"}


def source_modules() -> list[str]:
    """Every importable module of the source tree, under its installed name."""
    names = []
    for package, folder in ROOTS.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            rel = path.relative_to(REPO / folder).with_suffix("")
            if "__pycache__" in rel.parts or not (path.parent / "__init__.py").exists():
                continue
            parts = [p for p in rel.parts if p != "__init__"]
            names.append(".".join([package, *parts]))
    return names


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(out),
            str(REPO),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    (found,) = out.glob("nhfd-*.whl")
    return found


def test_wheel_contains_every_module_and_the_default_config(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for module in source_modules():
        path = module.replace(".", "/")
        assert f"{path}.py" in names or f"{path}/__init__.py" in names, module
    with zipfile.ZipFile(wheel) as zf:
        assert zf.read("nhfd/default.toml") == (REPO / "nhfd.toml").read_bytes()


def test_installed_wheel_imports_every_module_from_a_clean_environment(wheel, tmp_path):
    env_dir = tmp_path / "clean"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    site = Path(
        subprocess.run(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "-q",
            "--target",
            str(site),
            str(wheel),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    # Dependencies (torch, numpy, ...) come from the project's environment, appended after the
    # clean site-packages; the editable install there is inert (.pth files are not processed in
    # a path added this way), and the check below proves nhfd itself came from the wheel.
    (site / "deps.pth").write_text(sysconfig.get_path("purelib") + "\n")
    modules = source_modules()
    script = (
        "import importlib, sys\n"
        f"mods = {modules!r}\n"
        "for m in mods:\n"
        "    f = importlib.import_module(m).__file__\n"
        f"    assert f.startswith({str(site)!r}), (m, f)\n"
        "import nhfd.config as c\n"
        "assert c.load_config(env={}, cwd=__import__('pathlib').Path('/')).config.slm.width_px\n"
        "print(len(mods))\n"
    )
    res = subprocess.run(
        [str(python), "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=300
    )
    assert res.returncode == 0, res.stderr[-3000:]
    assert int(res.stdout.strip()) == len(modules) > 10
