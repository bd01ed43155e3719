"""Shared fixtures. Tests that need ../shared/data skip with a reason when it is absent
($NHFD_SHARED_DATA names another copy: a GPU machine gets the scenes inside the working tree)."""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator
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
