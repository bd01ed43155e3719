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
    "nhfd.views": 0, "nhfd.model_info": 0, "nhfd.frame_message": 0,
    "nhfd.optics": 1, "nhfd.scene": 1, "nhfd.drivers": 1,
    "nhfd.holo": 2, "nhfd.dataset": 2,
    "nhfd.models": 3,
    "nhfd.models.sizes": 3,
    "nhfd.pipeline": 4,
    "nhfd.pipeline.device": 4,
    "nhfd.daemon": 5, "nhfd.calib": 5,
    "nhfd.cli": 6, "nhfd.benchmarks": 6, "nhfd.demos": 6,
    "nhfd.web": 6,
    "nhfd.lab": 6,
}
LAYER_NAMES = ["L0 vocabulary", "L1 compute and devices", "L2 data", "L3 learning", "L4 runtime",
               "L5 services", "L6 entry points"]
# Sideways edges a layer's order alone would allow.
FORBIDDEN = {
    "nhfd.daemon": {"nhfd.holo", "nhfd.dataset", "nhfd.models", "nhfd.pipeline", "nhfd.calib"},
    # The optics core is pure: values in (a calibration, tensors), never settings it builds.
    "nhfd.optics": {"nhfd.scene", "nhfd.drivers", "nhfd.config", "nhfd.device_settings"},
}
HEAVY = ("torch", "numba", "onnxruntime")
# Where an import of nhfd inside a function is the design, not a shortcut (design.md's seams), as
# "file -> module". The command registries (nhfd/cli/args.py's LazyCommands) and the daemon's
# frame worker (nhfd/daemon/frame_link.py's run_by_name) load modules by name with importlib, so
# they need no entry here.
SEAMS = {
    "nhfd/scene/raster.py -> nhfd.scene._kernels": "numba kernels compile on first use",
    "nhfd/scene/raster.py -> nhfd.scene.gsplat_backend": "optional backend: gsplat, CUDA only",
    # The simulated camera images through nhfd.optics (torch): it loads only when configured, so
    # the daemon's device factory stays torch-free.
    "drivers/factory.py -> nhfd.drivers.simcamera": "optional backend: the simulated camera",
    # The web view needs the `web` extra (aiohttp): `nhfd serve` loads it only when enabled.
    "nhfd/cli/cmd_serve.py -> nhfd.web.server": "optional extra: the web view (aiohttp)",
    # `nhfd scene reduce` needs the dataset's envelope (settings, mapping, sampling: torch);
    # `scene info` and `scene render` load without it.
    "nhfd/cli/cmd_scene.py -> nhfd.dataset.envelope": "scene reduce only: the dataset envelope",
}
# The twin (the simulated camera; its `TrueBench` is the simulated bench's truth) may be imported
# under calib/, nhfd/pipeline/ and models/ only by the simulated bench's I/O, listed here as
# "file": why. Everything else there, the learned bench above all, learns only from captures
# through the `Camera` interface and from the fitted calibration.
TWIN = "nhfd.drivers.simcamera"
TWIN_SCOPE = ("calib/", "nhfd/pipeline/", "models/")
TWIN_IO = {
    "calib/capture.py": "SimBenchIO: the calibration capture's simulated bench",
    "calib/report.py": "the report's pictures: the fitted model imaged by the twin camera",
    "calib/sim.py": "the simulated bench, calibrated, for nhfd refine --sim and nhfd bench",
}
# Modules that must not reach the twin through any chain of module-level imports.
TWIN_FREE = ("nhfd.calib.learn", "nhfd.models.learned_bench", "nhfd.pipeline.refine",
             "nhfd.calib.citl")
# Violations being worked off (each entry "file -> imported module"); empty, and to stay so.
ALLOWED: set[str] = set()


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
            and _key(e) not in SEAMS]


def twin_problems(edges: list[Edge] | None = None,
                  texts: dict[str, str] | None = None) -> list[str]:
    """Imports of the twin, and names `TrueBench`, under TWIN_SCOPE outside TWIN_IO (any
    import: module level, in a function, under TYPE_CHECKING); and a TWIN_FREE module that
    reaches the twin through module-level imports."""
    problems = []
    for e in EDGES if edges is None else edges:
        if e.path.startswith(TWIN_SCOPE) and e.path not in TWIN_IO and \
                (e.target == TWIN or e.target.startswith(TWIN + ".")):
            problems.append(f"{e.where()}: {_key(e)}: imports the twin outside the simulated "
                            "bench's I/O (TWIN_IO)")
    if texts is None:
        texts = {str(p.relative_to(REPO)): p.read_text() for p in MODULES.values()}
    for rel, text in texts.items():
        if not rel.startswith(TWIN_SCOPE) or rel in TWIN_IO:
            continue
        for node in ast.walk(ast.parse(text, filename=rel)):
            name = (node.id if isinstance(node, ast.Name) else
                    node.attr if isinstance(node, ast.Attribute) else None)
            if name == "TrueBench":
                problems.append(f"{rel}:{node.lineno}: names the twin's TrueBench outside "
                                "the simulated bench's I/O (TWIN_IO)")
    if edges is None:
        for module in TWIN_FREE:
            chain = _module_level_closure(module).get(TWIN)
            if chain:
                problems.append(f"{module} reaches the twin: {' -> '.join(chain)}")
    return problems


def test_only_the_simulated_benchs_io_imports_the_twin():
    assert not twin_problems(), "\n" + "\n".join(twin_problems())
    for module in TWIN_FREE:
        assert module in MODULES, module  # the list names real modules
    assert all((REPO / rel).is_file() for rel in TWIN_IO), sorted(TWIN_IO)


def test_the_twin_check_catches_a_learned_part_importing_the_twin():
    for source in ("from nhfd.drivers.simcamera import TrueBench\n",
                   "def f():\n    from nhfd.drivers import simcamera\n",
                   "import nhfd.drivers.simcamera as s\n"):
        edges = _edges("nhfd.calib.learn", "calib/learn.py", source)
        assert twin_problems(edges, {}), source
    # A twin handed in as a value and named: caught too.
    assert twin_problems([], {"models/learned_bench.py": "def f(b):\n    return b.TrueBench\n"})
    # The simulated bench's own I/O may.
    edges = _edges("nhfd.calib.sim", "calib/sim.py", "from nhfd.drivers.simcamera import x\n")
    assert not twin_problems(edges, {})


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
    function_level = {_key(e) for e in EDGES if e.in_function and not e.type_checking}
    assert not SEAMS.keys() - function_level, sorted(SEAMS.keys() - function_level)


def test_every_module_has_a_layer():
    assert [m for m in MODULES if _unit(m) is None] == []


def test_walker_sees_function_and_type_checking_imports():
    source = ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from nhfd.daemon import x\n"
              "def f():\n    from ..models import net\n")
    edges = _edges("nhfd.scene.raster", "nhfd/scene/raster.py", source)
    assert {(e.target, e.in_function, e.type_checking) for e in edges} == {
        ("typing", False, False), ("nhfd.daemon", False, True), ("nhfd.models.net", True, False)}
