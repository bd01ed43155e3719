"""Shared fixtures. Tests that need ../shared/data skip with a reason when it is absent."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from nhfd.drivers.twins.mecom_twin import MecomTwin

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(autouse=True)
def _seeded() -> None:
    torch.manual_seed(1234)


# Tests of devices and the daemon wait on sockets, ptys and processes: none may hang.
DEADLINE_DIRS = ("drivers", "daemon", "web", "lab")
TEST_DEADLINE_S = 30


@pytest.fixture(autouse=True)
def _deadline(request: pytest.FixtureRequest) -> Iterator[None]:
    """SIGALRM interrupts any wait in the main thread after TEST_DEADLINE_S (a TimeoutError)."""
    if (request.node.path.parent.name not in DEADLINE_DIRS
            or threading.current_thread() is not threading.main_thread()):  # fmt: skip
        yield
        return

    def expired(signum: int, frame: object) -> None:
        raise TimeoutError(f"test exceeded {TEST_DEADLINE_S} s")

    old = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, TEST_DEADLINE_S)
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
