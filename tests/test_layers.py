"""The layers in docs/design.md, enforced: every source file's imports, read with `ast`.

A module may import only from its own layer or below. Imports inside functions and under
`TYPE_CHECKING` count: they are still dependencies, only later ones. On top of the layer order:
the daemon (a control plane) imports nothing from L2-L4 or from `nhfd.calib` (it spawns the frame
pipeline by name), torch, numba and onnxruntime are not reachable through module-level imports from
L0 or from the daemon, and an import of nhfd inside a function is allowed only at a listed seam.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# Import name -> folder (setup.py maps the design card's top-level folders into `nhfd`).
ROOTS = {"nhfd": REPO / "nhfd", "nhfd.drivers": REPO / "drivers", "nhfd.models": REPO / "models",
         "nhfd.calib": REPO / "calib"}
LAYERS = {
    "nhfd": 0, "nhfd.config": 0, "nhfd.spec": 0, "nhfd.calibration": 0, "nhfd.device_settings": 0,
    "nhfd.optics": 1, "nhfd.scene": 1, "nhfd.drivers": 1,
    "nhfd.holo": 2, "nhfd.dataset": 2,
    "nhfd.models": 3,
    "nhfd.pipeline": 4,
    "nhfd.daemon": 5, "nhfd.calib": 5,
    "nhfd.cli": 6, "nhfd.benchmarks": 6, "nhfd.demos": 6,
}
LAYER_NAMES = ["L0 vocabulary", "L1 compute and devices", "L2 data", "L3 learning", "L4 runtime",
               "L5 services", "L6 entry points"]
# Sideways edges a layer's order alone would allow.
FORBIDDEN = {
    "nhfd.daemon": {"nhfd.holo", "nhfd.dataset", "nhfd.models", "nhfd.pipeline", "nhfd.calib"},
    "nhfd.optics": {"nhfd.scene", "nhfd.drivers"},  # the optics core is pure
}
HEAVY = ("torch", "numba", "onnxruntime")
# Where an import of nhfd inside a function is the design, not a shortcut (design.md's seams).
SEAMS = {
    "nhfd/cli/main.py": "command registry: a command's module loads only when that command runs",
    "nhfd/cli/cmd_bench.py": "command registry: one benchmark's module per `nhfd bench NAME`",
    "nhfd/scene/raster.py": "numba kernels compile on first use, not on import",
}
# Today's violations, to be emptied (each entry "file -> imported module").
ALLOWED: set[str] = {
    "calib/capture.py -> nhfd.calib.fit",
    "calib/capture.py -> nhfd.config",
    "calib/capture.py -> nhfd.daemon.protocol",
    "calib/capture.py -> nhfd.device_settings",
    "calib/capture.py -> nhfd.drivers.simcamera",
    "calib/capture.py -> nhfd.optics",
    "calib/report.py -> nhfd.calib.geometry",
    "calib/report.py -> nhfd.device_settings",
    "calib/report.py -> nhfd.drivers.simcamera",
    "drivers/factory.py -> nhfd.drivers.camera",
    "drivers/factory.py -> nhfd.drivers.framebuffer",
    "drivers/factory.py -> nhfd.drivers.simcamera",
    "drivers/factory.py -> nhfd.drivers.window",
    "drivers/laser.py -> nhfd.drivers.errors",
    "models/evaluate.py -> nhfd.models.export",
    "models/evaluate.py -> nhfd.models.metadata",
    "models/evaluate.py -> nhfd.models.net",
    "models/evaluate.py -> nhfd.models.train",
    "models/export.py -> nhfd.models.metadata",
    "models/export.py -> nhfd.models.serving",
    "models/export.py -> nhfd.models.train",
    "models/loss.py -> nhfd.models.vgg",
    "models/quantise.py -> nhfd.models.net",
    "nhfd/benchmarks/holo.py -> nhfd.benchmarks.machine",
    "nhfd/benchmarks/holo.py -> nhfd.config",
    "nhfd/benchmarks/holo.py -> nhfd.dataset.shard",
    "nhfd/benchmarks/holo.py -> nhfd.holo",
    "nhfd/benchmarks/holo.py -> nhfd.optics",
    "nhfd/benchmarks/holo.py -> nhfd.scene.io",
    "nhfd/benchmarks/holo.py -> nhfd.scene.raster",
    "nhfd/benchmarks/holo.py -> nhfd.scene.suggest",
    "nhfd/benchmarks/load.py -> nhfd",
    "nhfd/benchmarks/load.py -> nhfd.benchmarks.machine",
    "nhfd/benchmarks/load.py -> nhfd.daemon.client",
    "nhfd/benchmarks/load.py -> nhfd.drivers.twins.apt_twin",
    "nhfd/benchmarks/load.py -> nhfd.drivers.twins.mecom_twin",
    "nhfd/benchmarks/load.py -> nhfd.models.export",
    "nhfd/benchmarks/optics.py -> nhfd.benchmarks.machine",
    "nhfd/benchmarks/optics.py -> nhfd.config",
    "nhfd/benchmarks/optics.py -> nhfd.optics",
    "nhfd/benchmarks/optics.py -> nhfd.optics._validate",
    "nhfd/benchmarks/optics.py -> nhfd.optics.fft",
    "nhfd/benchmarks/render.py -> nhfd.benchmarks.machine",
    "nhfd/benchmarks/render.py -> nhfd.dataset.shard",
    "nhfd/benchmarks/render.py -> nhfd.scene._kernels",
    "nhfd/benchmarks/render.py -> nhfd.scene.io",
    "nhfd/benchmarks/render.py -> nhfd.scene.lightfield",
    "nhfd/benchmarks/render.py -> nhfd.scene.raster",
    "nhfd/benchmarks/render.py -> nhfd.scene.suggest",
    "nhfd/benchmarks/safety.py -> nhfd",
    "nhfd/benchmarks/safety.py -> nhfd.benchmarks.machine",
    "nhfd/benchmarks/safety.py -> nhfd.daemon.client",
    "nhfd/benchmarks/safety.py -> nhfd.drivers.guardian",
    "nhfd/benchmarks/safety.py -> nhfd.drivers.twins.mecom_twin",
    "nhfd/benchmarks/tradeoff.py -> nhfd.benchmarks.machine",
    "nhfd/benchmarks/tradeoff.py -> nhfd.config",
    "nhfd/benchmarks/tradeoff.py -> nhfd.models.data",
    "nhfd/benchmarks/tradeoff.py -> nhfd.models.evaluate",
    "nhfd/benchmarks/tradeoff.py -> nhfd.models.export",
    "nhfd/benchmarks/tradeoff.py -> nhfd.models.net",
    "nhfd/benchmarks/tradeoff.py -> nhfd.models.quantise",
    "nhfd/benchmarks/tradeoff.py -> nhfd.models.train",
    "nhfd/cli/calib.py -> nhfd.calib.capture",
    "nhfd/cli/calib.py -> nhfd.calib.fit",
    "nhfd/cli/calib.py -> nhfd.calib.patterns",
    "nhfd/cli/calib.py -> nhfd.calib.report",
    "nhfd/cli/calib.py -> nhfd.calibration",
    "nhfd/cli/calib.py -> nhfd.config",
    "nhfd/cli/calib.py -> nhfd.daemon.client",
    "nhfd/cli/calib.py -> nhfd.daemon.paths",
    "nhfd/cli/calib.py -> nhfd.drivers.simcamera",
    "nhfd/cli/cmd_dataset.py -> nhfd.config",
    "nhfd/cli/cmd_dataset.py -> nhfd.dataset.build",
    "nhfd/cli/cmd_dataset.py -> nhfd.dataset.poses",
    "nhfd/cli/cmd_dataset.py -> nhfd.dataset.shard",
    "nhfd/cli/cmd_dataset.py -> nhfd.dataset.show",
    "nhfd/cli/cmd_dataset.py -> nhfd.scene.io",
    "nhfd/cli/cmd_dataset.py -> nhfd.scene.suggest",
    "nhfd/cli/cmd_demo.py -> nhfd.config",
    "nhfd/cli/cmd_demo.py -> nhfd.demos.optics",
    "nhfd/cli/cmd_demo.py -> nhfd.demos.serve",
    "nhfd/cli/cmd_devices.py -> nhfd.drivers.discovery",
    "nhfd/cli/cmd_laser.py -> nhfd.config",
    "nhfd/cli/cmd_laser.py -> nhfd.device_settings",
    "nhfd/cli/cmd_laser.py -> nhfd.drivers.errors",
    "nhfd/cli/cmd_laser.py -> nhfd.drivers.guardian",
    "nhfd/cli/cmd_laser.py -> nhfd.drivers.laser",
    "nhfd/cli/cmd_laser.py -> nhfd.drivers.rundir",
    "nhfd/cli/cmd_laser.py -> nhfd.drivers.transport",
    "nhfd/cli/cmd_replay.py -> nhfd.config",
    "nhfd/cli/cmd_replay.py -> nhfd.daemon.client",
    "nhfd/cli/cmd_replay.py -> nhfd.daemon.paths",
    "nhfd/cli/cmd_replay.py -> nhfd.daemon.recording",
    "nhfd/cli/cmd_scene.py -> nhfd.scene.cameras",
    "nhfd/cli/cmd_scene.py -> nhfd.scene.io",
    "nhfd/cli/cmd_scene.py -> nhfd.scene.raster",
    "nhfd/cli/cmd_scene.py -> nhfd.scene.suggest",
    "nhfd/cli/cmd_serve.py -> nhfd.config",
    "nhfd/cli/cmd_serve.py -> nhfd.daemon.service",
    "nhfd/cli/cmd_train.py -> nhfd.config",
    "nhfd/cli/cmd_train.py -> nhfd.models.data",
    "nhfd/cli/cmd_train.py -> nhfd.models.evaluate",
    "nhfd/cli/cmd_train.py -> nhfd.models.export",
    "nhfd/cli/cmd_train.py -> nhfd.models.quantise",
    "nhfd/cli/cmd_train.py -> nhfd.models.train",
    "nhfd/cli/nhfctl.py -> nhfd.config",
    "nhfd/cli/nhfctl.py -> nhfd.daemon.paths",
    "nhfd/config.py -> nhfd.calibration",
    "nhfd/daemon/bench.py -> nhfd.calibration",
    "nhfd/daemon/colour.py -> nhfd.daemon.bench",
    "nhfd/daemon/guardian_link.py -> nhfd.drivers.twins.mecom_twin",
    "nhfd/daemon/methods.py -> nhfd.calibration",
    "nhfd/daemon/methods.py -> nhfd.daemon.bench",
    "nhfd/daemon/methods.py -> nhfd.scene.io",
    "nhfd/daemon/navigation.py -> nhfd.drivers.factory",
    "nhfd/daemon/service.py -> nhfd.calibration",
    "nhfd/daemon/service.py -> nhfd.daemon.methods",
    "nhfd/dataset/build.py -> nhfd.holo",
    "nhfd/dataset/build.py -> nhfd.scene.io",
    "nhfd/dataset/build.py -> nhfd.scene.lightfield",
    "nhfd/dataset/build.py -> nhfd.scene.raster",
    "nhfd/dataset/shard.py -> nhfd.config",
    "nhfd/dataset/shard.py -> nhfd.holo",
    "nhfd/dataset/shard.py -> nhfd.optics",
    "nhfd/dataset/shard.py -> nhfd.scene.raster",
    "nhfd/dataset/show.py -> nhfd.optics",
    "nhfd/optics/dpac.py -> nhfd.optics._coding",
}


@dataclass(frozen=True)
class Edge:
    path: str  # repository-relative source file
    line: int
    source: str  # importing module
    target: str  # imported module (absolute)
    in_function: bool
    type_checking: bool

    def where(self) -> str:
        return f"{self.path}:{self.line}"


def _modules() -> dict[str, Path]:
    found: dict[str, Path] = {}
    nested = {path for name, path in ROOTS.items() if name != "nhfd"}
    for name, root in ROOTS.items():
        for path in sorted(root.rglob("*.py")):
            if name == "nhfd" and any(n in path.parents for n in nested):
                continue
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join([name, *parts])] = path
    return found


MODULES = _modules()


def _edges(module: str, rel: str, text: str) -> list[Edge]:
    package = module if rel.endswith("__init__.py") else module.rpartition(".")[0]
    edges: list[Edge] = []

    def visit(node: ast.AST, in_function: bool, type_checking: bool) -> None:
        for child in ast.iter_child_nodes(node):
            func = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
            tc = type_checking or (isinstance(child, ast.If)
                                   and "TYPE_CHECKING" in ast.unparse(child.test))
            targets: list[str] = []
            if isinstance(child, ast.Import):
                targets = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")[: len(package.split(".")) - (child.level - 1)]
                    base_name = ".".join(base + ([child.module] if child.module else []))
                else:
                    base_name = child.module or ""
                # `from pkg import name` imports pkg.name when that is a module.
                targets = [f"{base_name}.{a.name}" if f"{base_name}.{a.name}" in MODULES
                           else base_name for a in child.names]
            for target in dict.fromkeys(targets):
                edges.append(Edge(rel, child.lineno, module, target, func, tc))
            visit(child, func, tc)

    visit(ast.parse(text, filename=rel), False, False)
    return edges


EDGES = [edge for module, path in MODULES.items()
         for edge in _edges(module, str(path.relative_to(REPO)), path.read_text())]


def _unit(module: str) -> str | None:
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in LAYERS:
            return ".".join(parts[:n])
    return None


def _report(problems: list[str]) -> str:
    return "\n".join(p for p in problems if p.split(": ", 2)[1] not in ALLOWED)


def _key(edge: Edge) -> str:
    return f"{edge.path} -> {edge.target}"


def layer_problems() -> list[str]:
    problems = []
    for edge in EDGES:
        src, dst = _unit(edge.source), _unit(edge.target)
        if src is None or dst is None:
            continue
        if LAYERS[dst] > LAYERS[src]:
            problems.append(f"{edge.where()}: {_key(edge)}: {src} ({LAYER_NAMES[LAYERS[src]]}) "
                            f"imports upward from {dst} ({LAYER_NAMES[LAYERS[dst]]})")
        elif dst in FORBIDDEN.get(src, ()):
            problems.append(f"{edge.where()}: {_key(edge)}: {src} may not import {dst}")
    return problems


def _module_level_closure(start: str) -> dict[str, list[str]]:
    """Every module reachable from `start` through module-level imports, with one path to each.
    Importing a.b.c runs a/__init__ and a/b/__init__ first, so parents are reached too."""
    seen: dict[str, list[str]] = {start: [start]}
    todo = [start]
    by_source: dict[str, list[Edge]] = {}
    for edge in EDGES:
        if not edge.in_function and not edge.type_checking:
            by_source.setdefault(edge.source, []).append(edge)
    while todo:
        module = todo.pop()
        parts = module.split(".")
        nexts = [".".join(parts[:n]) for n in range(1, len(parts))]
        nexts += [e.target for e in by_source.get(module, [])]
        for target in nexts:
            if target not in seen:
                seen[target] = [*seen[module], target]
                if target in MODULES:
                    todo.append(target)
    return seen


def heavy_problems() -> list[str]:
    problems = []
    for module, path in MODULES.items():
        unit = _unit(module)
        if unit is None or not (LAYERS[unit] == 0 or unit == "nhfd.daemon"):
            continue
        for target, chain in _module_level_closure(module).items():
            if target.split(".")[0] in HEAVY:
                problems.append(f"{path.relative_to(REPO)}:1: {path.relative_to(REPO)} -> "
                                f"{target}: reachable at import: {' -> '.join(chain)}")
                break
    return problems


def seam_problems() -> list[str]:
    return [f"{e.where()}: {_key(e)}: import of nhfd inside a function outside the listed seams"
            for e in EDGES
            if e.in_function and not e.type_checking and e.target.startswith("nhfd")
            and e.path not in SEAMS]


def test_no_upward_or_forbidden_import():
    assert not _report(layer_problems()), "\n" + _report(layer_problems())


def test_heavy_libraries_not_reachable_from_vocabulary_or_daemon():
    assert not _report(heavy_problems()), "\n" + _report(heavy_problems())


def test_function_level_imports_only_at_seams():
    assert not _report(seam_problems()), "\n" + _report(seam_problems())


def test_allow_list_holds_only_live_violations():
    # An entry that no longer matches anything must go, so the list can only shrink.
    live = {p.split(": ", 2)[1] for p in layer_problems() + heavy_problems() + seam_problems()}
    assert not ALLOWED - live, sorted(ALLOWED - live)


def test_every_module_has_a_layer():
    assert [m for m in MODULES if _unit(m) is None] == []


def test_walker_sees_function_and_type_checking_imports():
    source = ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from nhfd.daemon import x\n"
              "def f():\n    from ..models import net\n")
    edges = _edges("nhfd.scene.raster", "nhfd/scene/raster.py", source)
    assert {(e.target, e.in_function, e.type_checking) for e in edges} == {
        ("typing", False, False), ("nhfd.daemon", False, True), ("nhfd.models.net", True, False)}
