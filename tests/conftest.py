"""Shared fixtures. Tests that need ../shared/data skip with a reason when it is absent
($NHFD_SHARED_DATA names another copy: a GPU machine gets the scenes inside the working tree)."""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import torch

from nhfd.drivers.twins.mecom_twin import MecomTwin

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("NHFD_SHARED_DATA") or REPO.parent / "shared" / "data")


# NHFD_REQUIRE_CUDA=1 (`make gpu-check`, on a GPU workstation): a test skipped because it needs
# CUDA fails instead, so a run whose CUDA tests all skipped (a CPU-only torch, no driver, gsplat
# or onnxruntime-gpu absent) cannot pass as a GPU check. The skip reasons the CUDA tests use:
REQUIRE_CUDA_ENV = "NHFD_REQUIRE_CUDA"
NEEDS_CUDA_REASONS = ("needs CUDA", "needs a CUDA device", "needs onnxruntime's CUDA provider")


def _cuda_skip_reason(report: pytest.TestReport) -> str | None:
    """The reason of a skip for want of CUDA (skipif marks and pytest.skip() alike), else None."""
    if not report.skipped or not isinstance(report.longrepr, tuple):
        return None
    reason = str(report.longrepr[2]).removeprefix("Skipped: ")
    return reason if any(r in reason for r in NEEDS_CUDA_REASONS) else None


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]
                              ) -> Iterator[None]:
    report = yield
    if os.environ.get(REQUIRE_CUDA_ENV, "") not in ("", "0"):
        reason = _cuda_skip_reason(report)
        if reason is not None:
            report.outcome = "failed"
            # A skipif mark skips in setup: reported as the test's own failure, not a fixture
            # error.
            report.when = "call"
            report.longrepr = (f"{REQUIRE_CUDA_ENV}={os.environ[REQUIRE_CUDA_ENV]}: this test "
                               f"must run on CUDA here, but it skipped: {reason}")
    return report


# The longest test files (minutes on 2 cores, measured with --durations), run first: the two
# pytest-xdist workers take a file at a time in collection order (`--dist loadfile`), and one of
# these collected last kept one worker busy for a minute and more after the other had finished.
SLOW_FILES_FIRST = (
    "test_readme_blocks.py", "pipeline/test_tune.py", "benchmarks/test_quality_bench.py",
    "daemon/test_refine_daemon.py", "calib/test_learn.py", "daemon/test_emission_runs.py",
    "daemon/test_citl_daemon.py", "models/test_model_build.py", "pipeline/test_warmup.py",
    "daemon/test_bench_pipeline.py", "daemon/test_bad_inputs.py", "calib/test_recovery.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    rank = {REPO / "tests" / name: i for i, name in enumerate(SLOW_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.path, len(rank)))  # stable: the rest in order


@pytest.fixture(autouse=True)
def _seeded() -> None:
    torch.manual_seed(1234)


# Tests of devices and the daemon wait on sockets, ptys and processes: none may hang.
DEADLINE_DIRS = ("drivers", "daemon", "web", "lab")
TEST_DEADLINE_S = 30


@pytest.fixture(autouse=True)
def _deadline(request: pytest.FixtureRequest) -> Iterator[None]:
    """SIGALRM interrupts any wait in the main thread after TEST_DEADLINE_S (a TimeoutError), or
    the test's own `@pytest.mark.deadline_s(s)` (one that walks a daemon through several runs)."""
    if (request.node.path.parent.name not in DEADLINE_DIRS
            or threading.current_thread() is not threading.main_thread()):  # fmt: skip
        yield
        return

    mark = request.node.get_closest_marker("deadline_s")
    deadline_s = float(mark.args[0]) if mark else TEST_DEADLINE_S

    def expired(signum: int, frame: object) -> None:
        raise TimeoutError(f"test exceeded {deadline_s:g} s")

    old = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, deadline_s)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@pytest.fixture
def shared_scenes() -> Path:
    scenes = SHARED_DATA / "scenes"
    if not scenes.is_dir():
        pytest.skip(f"shared scenes not found at {scenes} (a user checkout has no ../shared)")
    return scenes


@pytest.fixture
def mecom_twin() -> Iterator[MecomTwin]:
    """The READYBeam twin on a pseudo-terminal (driver, daemon and calibration tests)."""
    twin = MecomTwin()
    twin.start()
    try:
        yield twin
    finally:
        twin.close()


def made_once(tmp_path_factory: pytest.TempPathFactory, name: str,
              make: Callable[[Path], None]) -> Path:
    """The folder `name`, filled by `make(folder)` once per test run: the pytest-xdist workers
    of one run share it (the first to ask makes it under a lock, the others wait and read it),
    so a session fixture that costs half a minute is not paid once per worker. A `make` that
    fails leaves no folder: the next to ask tries again."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # shared by workers
    folder, done = root / name, root / f"{name}.done"
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            try:
                make(folder)
            except BaseException:
                shutil.rmtree(folder, ignore_errors=True)
                raise
            done.touch()
    return folder
