"""The daemon is small parts that do not reach into each other (issue 33, item 3).

Read from the source with `ast`, so that a new module is checked without being listed:
- no module of `nhfd.daemon` reads or calls a private name of another object (`x._name` where
  `x` is not `self` or `cls`; `getattr(x, "_name")`), or imports one from another module: what a
  part needs of another is public and named, or a callback given at construction;
- no part's constructor (and no function of the daemon or the web view) takes the daemon: no
  parameter annotated `Daemon` or named `daemon`, `d` or `host`; the parts' constructors declare
  what they use, the way slmsuite's do, and python-microscope's devices know nothing of the
  server that hosts them;
- no part imports `nhfd.daemon.service`: only the daemon knows the daemon;
- the parts' constructors take typed settings, never `config: Any`; each takes its own section
  of `[daemon]` (`ArmingSettings`, `AuditSettings`, ...), not the whole `DaemonSettings`.
"""

from __future__ import annotations

import ast
import inspect
import re
from pathlib import Path

import pytest

import nhfd.daemon
from nhfd.daemon.arming import ArmingGate
from nhfd.daemon.audit import AuditLog
from nhfd.daemon.bench import Bench
from nhfd.daemon.capture_relay import CaptureRelay
from nhfd.daemon.dispatch import Dispatcher
from nhfd.daemon.errors import ErrorList
from nhfd.daemon.frame_link import FrameLink, FrameWorker
from nhfd.daemon.guardian_link import LaserLink
from nhfd.daemon.jobs import JobRunner
from nhfd.daemon.load_queue import LoadQueue
from nhfd.daemon.navigation import NavigatorInput
from nhfd.daemon.pacing import FramePacer
from nhfd.daemon.panel import Panel
from nhfd.daemon.recording import SessionRecorder
from nhfd.daemon.server import LineServer
from nhfd.daemon.views import ViewSlot

DAEMON = Path(nhfd.daemon.__file__).parent
WEB_SERVER = DAEMON.parent / "web" / "server.py"
SOURCES = sorted(DAEMON.glob("*.py"))

# (file name, "expression") pairs allowed to read a private name of another object, each with
# why. Empty: everything one part needs of another is public.
ALLOWED_PRIVATE: dict[tuple[str, str], str] = {}

# The parts the daemon wires, whose constructors must not take it.
PARTS = (Panel, Bench, FrameLink, FrameWorker, LoadQueue, FramePacer, CaptureRelay, ArmingGate,
         NavigatorInput, LaserLink, ViewSlot, SessionRecorder, AuditLog, JobRunner, ErrorList,
         Dispatcher, LineServer)
DAEMON_NAMES = {"daemon", "d", "host"}


def private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_reaches(path: Path) -> list[str]:
    """Each place in `path` that reads a private name of something other than `self`/`cls`."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Attribute) and private(node.attr):
            if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                continue
            found.append(ast.unparse(node))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
              and node.func.id in ("getattr", "setattr", "hasattr", "delattr")
              and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
              and isinstance(node.args[1].value, str) and private(node.args[1].value)):
            found.append(ast.unparse(node))
        elif isinstance(node, ast.ImportFrom) and (
                node.level > 0 or (node.module or "").startswith("nhfd")):
            found += [f"from {'.' * node.level}{node.module or ''} import {a.name}"
                      for a in node.names if private(a.name)]
    return [f for f in found if (path.name, f) not in ALLOWED_PRIVATE]


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: p.name)
def test_no_module_reaches_into_a_private_name_of_another(path):
    assert private_reaches(path) == []


def test_the_check_sees_a_private_reach(tmp_path):
    """The rule itself: a private attribute, a getattr by name and an import are each seen;
    `self`, `cls` and dunder names are not."""
    probe = tmp_path / "probe.py"
    probe.write_text("from .protocol import _hidden\n"
                     "def f(link, self, cls):\n"
                     "    link._lock; getattr(link, '_beat'); self._own; cls._MISSING\n"
                     "    link.__dict__; getattr(link, '__class__')\n")
    assert sorted(private_reaches(probe)) == sorted(
        ["link._lock", "getattr(link, '_beat')", "from .protocol import _hidden"])


def test_the_allow_list_is_not_stale():
    for (name, expression), why in ALLOWED_PRIVATE.items():
        path = DAEMON / name
        assert why and path.exists(), (name, expression)
        assert expression in ast.unparse(ast.parse(path.read_text())), (name, expression)


def names_the_daemon(annotation: str) -> bool:
    """`Daemon` (not `DaemonSettings`), or a Protocol of it (`...Host`)."""
    return re.search(r"\bDaemon\b", annotation) is not None or re.search(
        r"Host\b", annotation) is not None


def takes_the_daemon(parameter: inspect.Parameter) -> bool:
    annotation = parameter.annotation
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", "")
    return parameter.name in DAEMON_NAMES or names_the_daemon(str(text))


@pytest.mark.parametrize("part", PARTS, ids=lambda c: c.__name__)
def test_no_part_is_constructed_with_the_daemon(part):
    parameters = inspect.signature(part.__init__).parameters.values()
    assert [p.name for p in parameters if takes_the_daemon(p)] == []


@pytest.mark.parametrize("path", [*SOURCES, WEB_SERVER],
                         ids=lambda p: f"{p.parent.name}/{p.name}")
def test_no_function_of_the_daemon_or_the_web_view_takes_the_daemon(path):
    """Methods, module functions and the RPC methods alike (these take the methods' context,
    `RpcContext`, that the daemon builds from its parts)."""
    bad = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        args = node.args
        for arg in [*args.posonlyargs, *args.args, *args.kwonlyargs]:
            annotation = ast.unparse(arg.annotation) if arg.annotation is not None else ""
            # A `host: str` is a network address (the web view's listening host).
            named = arg.arg in DAEMON_NAMES and annotation not in ("str", "str | None")
            if named or names_the_daemon(annotation):
                bad.append(f"{node.name}({arg.arg}: {annotation})")
    assert bad == []


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: p.name)
def test_only_the_daemon_knows_the_daemon(path):
    """No module of the control plane but `service` itself imports `service`, and none declares
    a Protocol of the daemon (a `...Host`): a part names the few parts it uses."""
    tree = ast.parse(path.read_text())
    imports = {node.module for node in ast.walk(tree)
               if isinstance(node, ast.ImportFrom) and node.module}
    if path.name != "service.py":
        assert "service" not in imports and "nhfd.daemon.service" not in imports
    hosts = [node.name for node in ast.walk(tree)
             if isinstance(node, ast.ClassDef) and node.name.endswith("Host")]
    assert hosts == []


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: p.name)
def test_settings_are_typed(path):
    """A function takes the settings section it uses (`ServerSettings`, `SLMSettings`, ...) or
    the typed `Config` where it needs several, never `config: Any` (issue 33, item 5)."""
    untyped = [f"{function}({name}: {annotation or 'unannotated'})"
               for function, name, annotation in _arguments(path)
               if ("config" in name or "settings" in name)
               and (annotation in ("", "Any") or "Any" in annotation.split(" | "))]
    assert untyped == []


def _arguments(path: Path) -> list[tuple[str, str, str]]:
    """(function, argument, its annotation as written or "") of every function in `path`."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            args = node.args
            for arg in [*args.posonlyargs, *args.args, *args.kwonlyargs]:
                annotation = ast.unparse(arg.annotation) if arg.annotation is not None else ""
                out.append((node.name, arg.arg, annotation))
    return out


# Functions of the control plane allowed to take the whole `DaemonSettings`, each with why:
# the web view's start reads four sections.
WHOLE_DAEMON_SETTINGS = {("server.py", "serve_web_view")}


@pytest.mark.parametrize("path", [*SOURCES, WEB_SERVER],
                         ids=lambda p: f"{p.parent.name}/{p.name}")
def test_each_part_takes_its_own_section_of_the_daemon_settings(path):
    """`[daemon]` is one section per part (`nhfd.config.DaemonSettings`): a function of the
    daemon or the web view takes the section it reads, not all of them; the web view's start,
    which reads four, is the one that takes them all."""
    whole = {(path.name, function) for function, _, annotation in _arguments(path)
             if re.search(r"\bDaemonSettings\b", annotation)}
    assert whole - WHOLE_DAEMON_SETTINGS == set()
