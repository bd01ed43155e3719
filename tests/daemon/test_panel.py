"""The panel (nhfd/daemon/panel.py) is the one owner of what the SLM shows, and the control
plane's modules take narrow Protocols of the parts they use instead of the daemon (issues 22
and 33; tests/daemon/test_parts.py keeps the daemon out of their constructors)."""

from __future__ import annotations

import ast
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Generic, Protocol

import numpy as np
import pytest

from nhfd.calibration import CalibrationStore
from nhfd.daemon import arming, colour, frame_link, methods, pacing
from nhfd.daemon import panel as panel_module
from nhfd.daemon.panel import Panel, blank_pattern
from nhfd.daemon.service import Daemon

from .conftest import bench_config

DAEMON = Path(methods.__file__).parent


class RecordingSLM:
    def __init__(self) -> None:
        self.shown: list[tuple[np.ndarray, bool]] = []

    def show(self, frame: np.ndarray, wait_settled: bool = False) -> None:
        self.shown.append((np.array(frame), wait_settled))

    @property
    def last(self) -> np.ndarray:
        return self.shown[-1][0]


def make_panel(root: Path, slm: Any, **daemon: Any) -> Panel:
    config = bench_config(root, None, **daemon)
    return Panel(config,
                 SimpleNamespace(slm=slm, errors={"slm": "unplugged" if slm is None else None}),
                 CalibrationStore.of(config))


def frame_of(panel: Panel, *levels: int) -> np.ndarray:
    s = panel.config.slm
    return np.stack([np.full((s.height_px, s.width_px), v, np.uint8) for v in levels])


def test_blank_view_and_pattern_take_turns(short_dir):
    slm = RecordingSLM()
    panel = make_panel(short_dir, slm, frames={"colour_mode": "hw-sync"})
    assert (panel.current, panel.showing, panel.held) == ("blank", "nothing", False)
    panel.blank()
    assert np.array_equal(slm.last, blank_pattern(panel.config, None))
    assert (panel.current, panel.showing) == ("blank", "blank")

    view = frame_of(panel, 10, 20, 30)
    assert np.array_equal(panel.show_view(view, 1), view)
    assert np.array_equal(slm.last, view) and (panel.current, panel.showing) == ("view 1",) * 2

    pattern = frame_of(panel, 1, 2, 3)
    panel.show_pattern(pattern, "p.npy")
    assert np.array_equal(slm.last, pattern) and panel.held
    assert (panel.current, panel.showing) == ("calibration pattern p.npy", "pattern p.npy")
    # A view computed meanwhile waits: the SLM and what status says keep the pattern.
    n = len(slm.shown)
    later = panel.show_view(frame_of(panel, 40, 50, 60), 2)
    assert len(slm.shown) == n and panel.current == "calibration pattern p.npy"
    panel.resume(later, 2)  # set_view ends the pattern: the last view again
    assert np.array_equal(slm.last, later) and not panel.held
    assert (panel.current, panel.showing, panel.pattern) == ("view 2", "view 2", None)

    panel.show_pattern(pattern, "p.npy")
    panel.blank()  # blank ends it too
    assert panel.pattern is None and panel.current == "blank"
    panel.show_pattern(pattern, "p.npy")
    panel.resume(None, 0)  # no view yet: the blank
    assert np.array_equal(slm.last, blank_pattern(panel.config, None)) and panel.current == "blank"


def test_a_capture_sequence_holds_the_panel_one_colour_at_a_time(short_dir):
    slm = RecordingSLM()
    panel = make_panel(short_dir, slm, frames={"colour_mode": "capture"})
    view = frame_of(panel, 10, 20, 30)
    with panel.hold():
        assert panel.held
        panel.show_colour(view, "blue")
        frame, settled = slm.shown[-1]
        assert settled and (frame == 30).all()
        n = len(slm.shown)
        panel.show_view(frame_of(panel, 1, 1, 1), 3)  # computed, not shown
        assert len(slm.shown) == n and panel.current == "view 3"
    assert not panel.held


def test_single_mode_shows_its_colour_in_every_channel(short_dir):
    slm = RecordingSLM()
    panel = make_panel(short_dir, slm, frames={"colour_mode": "single", "single_colour": "red"})
    panel.show_view(frame_of(panel, 10, 20, 30), 1)
    assert (slm.last == 10).all()
    panel.show_pattern(frame_of(panel, 7, 8, 9), "p.npy")
    assert (slm.last == 7).all()


def test_without_an_slm_blank_and_patterns_say_why(short_dir):
    panel = make_panel(short_dir, None)
    for act in (panel.blank, lambda: panel.show_pattern(frame_of(panel, 1, 2, 3), "p.npy")):
        with pytest.raises(RuntimeError, match="unplugged"):
            act()
    assert panel.showing == "nothing" and panel.pattern is None
    panel.show_view(frame_of(panel, 1, 2, 3), 4)  # computed views are still reported
    assert panel.current == "view 4"


def test_output_lost(short_dir):
    panel = make_panel(short_dir, RecordingSLM())
    panel.output_lost()
    assert (panel.current, panel.showing) == ("nothing (SLM output lost)", "nothing (output lost)")


# -- the Protocols and the methods' context ---------------------------------------------------


def members(declared: type) -> set[str]:
    """What a Protocol (its Protocol bases included) or a dataclass declares."""
    out: set[str] = set()
    for cls in declared.__mro__:
        if cls in (Protocol, Generic, object) or not (
                getattr(cls, "_is_protocol", False) or cls is declared):
            continue
        out |= set(getattr(cls, "__annotations__", {}))
        out |= {k for k in vars(cls) if not k.startswith("_")}
    return out


def used(path: Path, name: str, via: str | None = None) -> set[str]:
    """Attributes read or written on `name` (or on `via.name`) anywhere in the module."""
    def is_host(node: ast.AST) -> bool:
        if via is None:
            return isinstance(node, ast.Name) and node.id == name
        return (isinstance(node, ast.Attribute) and node.attr == name
                and isinstance(node.value, ast.Name) and node.value.id == via)

    tree = ast.parse(path.read_text())
    return {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute) and is_host(n.value)}


@pytest.mark.parametrize(("module", "declared", "name", "via"), [
    ("methods.py", methods.RpcContext, "ctx", None),
    ("colour.py", colour.CaptureBench, "bench", None),
    ("colour.py", colour.CapturePanel, "panel", None),
    ("colour.py", colour.ShownViews, "shown", None),
    ("arming.py", arming.NavigatorState, "navigation", "self"),
    ("frame_link.py", frame_link.ViewSource, "views", "self"),
    ("pacing.py", pacing.ViewSource, "views", "self"),
])
def test_each_protocol_names_what_its_module_uses_of_another_part(module, declared, name, via):
    assert used(DAEMON / module, name, via) <= members(declared)


def test_the_parts_the_daemon_wires_have_what_each_protocol_names(short_dir):
    daemon = Daemon(bench_config(short_dir, None), base_dir=short_dir, env={},
                    handle_signals=False)
    ctx = daemon.rpc
    for declared, part in ((colour.CaptureBench, ctx.bench), (colour.CapturePanel, ctx.panel),
                           (colour.ShownViews, ctx.frames), (methods.Frames, ctx.frames),
                           (frame_link.PanelView, daemon.panel),
                           (frame_link.ViewSource, daemon.views),
                           (panel_module.PanelDevices, daemon.bench),
                           (arming.NavigatorState, daemon.navigation)):
        assert [m for m in members(declared) if not hasattr(part, m)] == [], declared
    # The methods act on the daemon's own parts, not copies.
    for name in ("audit", "laser", "arming", "bench", "panel", "views", "frames", "bench_jobs",
                 "load_jobs"):
        assert getattr(ctx, name) is getattr(daemon, name), name


def test_the_daemon_package_imports_without_a_circle():
    """Every import between the daemon's modules, those under TYPE_CHECKING and inside
    functions included, goes one way."""
    graph: dict[str, set[str]] = {}
    for path in sorted(DAEMON.glob("*.py")):
        deps = graph.setdefault(path.stem, set())
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level == 1:
                    base = node.module
                elif node.module and node.module.startswith("nhfd.daemon."):
                    base = node.module.removeprefix("nhfd.daemon.")
                else:
                    continue
                names = [base] if base else [a.name for a in node.names]
                deps.update(n.split(".")[0] for n in names)
    graph = {m: {d for d in deps if d in graph and d != m} for m, deps in graph.items()}

    def cycle_from(module: str, path: list[str]) -> list[str] | None:
        if module in path:
            return [*path[path.index(module):], module]
        for dep in sorted(graph[module]):
            found = cycle_from(dep, [*path, module])
            if found:
                return found
        return None

    assert [c for m in graph if (c := cycle_from(m, []))] == []
