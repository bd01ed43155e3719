"""Fixtures: a laser twin in the test process, a small simulated bench, an in-process daemon."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import tempfile
import threading
import time
import tomllib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from nhfd.config import Config, _overlay, default_text
from nhfd.daemon.client import Client
from nhfd.daemon.frame_link import SHM_PREFIX
from nhfd.daemon.service import Daemon
from nhfd.drivers.twins.mecom_twin import MecomTwin
from tests.conftest import made_once


@pytest.fixture
def short_dir() -> Iterator[Path]:
    """Unix socket paths must stay under ~107 bytes: pytest's tmp_path can be longer."""
    path = Path(tempfile.mkdtemp(prefix="nhfd-d-", dir="/tmp"))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def bench_config(root: Path, twin: MecomTwin | None, **daemon: Any) -> Config:
    """A small simulated bench: 64 x 36 panel, no camera, the laser twin given (or the
    daemon's own simulated laser when None), everything under `root`; `daemon`: sections of
    `[daemon]` on top (server={"tcp_port": ...}), merged key by key with this bench's."""
    for sub in ("scenes", "models", "snaps"):
        (root / sub).mkdir(exist_ok=True)
    laser: dict[str, Any] = {
        # No test here silences the laser twin, so this only bounds a reply on a loaded machine:
        # at 0.2 s, 3 tries missed the twin's all-off at start-up once in CI.
        "reply_timeout_s": 1.0,
        "guardian": {"socket_path": str(root / "laser.sock"), "heartbeat_timeout_s": 0.5},
    }
    if twin is not None:
        laser["port"] = twin.port_path
    user = {
        "slm": {"width_px": 64, "height_px": 36},
        "optics": {"hologram_width_px": 32, "hologram_height_px": 18},
        "devices": {"laser": "readybeam" if twin is not None else "simulated",
                    "camera": "none", "readybeam": laser,
                    "apt": {"enable_settle_s": 0.0, "reply_timeout_s": 0.5,
                            "velocity_mm_s": 2.0}},
        "daemon": {"server": {"runtime_dir": str(root / "run")},
                   "paths": {"scene_dirs": [str(root / "scenes")],
                             "model_dirs": [str(root / "models")],
                             "snapshot_dir": str(root / "snaps")}},
    }
    user = _overlay(user, {"daemon": daemon})
    return Config.model_validate(_overlay(tomllib.loads(default_text()), user))


class Running:
    """A daemon whose control loop runs on a thread of this process."""

    def __init__(self, config: Config, root: Path, env: dict[str, str] | None = None) -> None:
        self.daemon = Daemon(config, base_dir=root, env=env or {}, handle_signals=False)
        self.daemon.start()
        self.thread = threading.Thread(target=self.daemon.run, daemon=True)
        self.thread.start()
        self.socket = self.daemon.socket_path

    def client(self, **kw: Any) -> Client:
        return Client(self.socket, **kw)

    def web_view(self) -> Any:
        """The daemon's web view on a thread of this process, started as `nhfd serve` starts
        it (`nhfd.cli.cmd_serve`): `stop()` it before the daemon."""
        from nhfd.web.server import serve_web_view  # aiohttp: the web extra

        d = self.daemon
        return serve_web_view(d.config.daemon, socket_path=d.socket_path,
                              runtime_dir=d.runtime_dir, base_dir=d.base_dir,
                              tcp_token=d.rpc.tcp_token, audit=d.audit)

    def stop(self) -> None:
        self.daemon.request_shutdown("test over")
        self.thread.join(10)
        assert not self.thread.is_alive()


@contextlib.contextmanager
def running_daemon(make_config: Any, prefix: str = "nhfd-r-") -> Iterator[tuple[Running, Path]]:
    """A `Running` daemon of `make_config(root)` in a fresh directory under /tmp (its Unix socket
    path must stay short), stopped and removed afterwards."""
    root = Path(tempfile.mkdtemp(prefix=prefix, dir="/tmp"))
    r = None
    try:
        r = Running(make_config(root), root)
        yield r, root
    finally:
        if r is not None:
            with contextlib.suppress(Exception):
                r.stop()
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture
def running(short_dir: Path, mecom_twin: MecomTwin) -> Iterator[Running]:
    r = Running(bench_config(short_dir, mecom_twin), short_dir)
    try:
        yield r
    finally:
        with contextlib.suppress(Exception):
            r.stop()


def wait_until(condition: Any, timeout_s: float = 20.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.02)


@pytest.fixture(scope="session")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 2-step model exported to ONNX and a small Gaussian cloud, made once per run (~10 s;
    `made_once`: both pytest-xdist workers read the one pair) and shared by every test file
    that needs the frame worker; the frame kernels compiled in this process."""
    from .test_frames import make_tiny_model, make_tiny_scene

    def make(root: Path) -> None:
        make_tiny_model(root)
        make_tiny_scene(root / "cloud.ply")

    root = made_once(tmp_path_factory, "tiny_model", make)
    paths = {"model": root / "tiny.onnx", "scene": root / "cloud.ply"}
    _compile_frame_kernels(paths)
    return paths


def _compile_frame_kernels(tiny: dict[str, Path]) -> None:
    """One frame in this process, outside every test's deadline: numba compiles the renderer and
    the coder once and caches them, so a daemon's spawned worker loads them instead of spending
    20 s or more compiling on its first frame (a fresh checkout has no cache)."""
    from nhfd.calibration import CalibrationStore
    from nhfd.models.export import load_model
    from nhfd.pipeline.encoder import Encoder
    from nhfd.pipeline.frame import compute_frame
    from nhfd.pipeline.settings import frame_settings
    from nhfd.pipeline.view import Scene, SceneFrame
    from nhfd.scene.io import load_scene

    from .test_frames import FRONT_VIEW, small_config

    config = small_config()
    model = load_model(tiny["model"], config)
    encoder = Encoder(frame_settings(config, model.info, CalibrationStore.of(config).active()))
    scene = Scene(load_scene(tiny["scene"]), SceneFrame((0.0, 0.0, 0.0), "-y"))
    compute_frame(FRONT_VIEW, scene, model, encoder)


def _frame_segments() -> set[str]:
    return {p.name for p in Path("/dev/shm").glob(f"{SHM_PREFIX}{os.getpid()}-*")}


@pytest.fixture
def our_segments() -> Callable[[], list[str]]:
    """This process's frame segments (/dev/shm) made since the test began, by name: a test
    judges only its own, whatever another test's daemon is still closing."""
    before = _frame_segments()
    return lambda: sorted(_frame_segments() - before)
