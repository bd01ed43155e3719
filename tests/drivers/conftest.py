"""Fixtures for driver tests: twins on pseudo-terminals and fast settings (the per-test
deadline is in tests/conftest.py)."""

from __future__ import annotations

import contextlib
import os
import selectors
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from nhfd.device_settings import LaserSettings, SLMOutputSettings, StageSettings
from nhfd.drivers.twins.apt_twin import AptTwin
from nhfd.drivers.twins.clock import ManualClock


@pytest.fixture
def laser_settings() -> LaserSettings:
    return LaserSettings(reply_timeout_s=0.1, retries=2, reconnect_backoff_s=0.05,
                         reconnect_attempts=4, latency_timer_ms=1)


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def stage_settings() -> StageSettings:
    return StageSettings(enable_settle_s=0.0, reply_timeout_s=0.2, reconnect_backoff_s=0.05,
                         reconnect_attempts=4, home_timeout_s=2.0, move_timeout_s=2.0)


@pytest.fixture
def apt_twin(clock: ManualClock) -> Iterator[AptTwin]:
    twin = AptTwin(clock=clock)
    twin.start()
    try:
        yield twin
    finally:
        twin.close()


@pytest.fixture
def short_dir() -> Iterator[Path]:
    """A short directory for Unix sockets (their paths are limited to ~107 bytes)."""
    path = Path(tempfile.mkdtemp(prefix="nhfd-t"))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


def read_line(proc: subprocess.Popen, timeout_s: float) -> str:
    """One line of a child's stdout, or AssertionError after timeout_s."""
    assert proc.stdout is not None
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout=timeout_s):
            raise AssertionError(f"child printed nothing within {timeout_s} s")
    return proc.stdout.readline()


@contextlib.contextmanager
def reaped(*procs: subprocess.Popen) -> Iterator[None]:
    """Kill and reap child processes whatever happens in the block."""
    try:
        yield
    finally:
        for proc in procs:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=5)


def fake_framebuffer(root: Path, *, width: int, height: int, bpp: int, stride: int,
                     connectors: dict[str, str] | None = None) -> SLMOutputSettings:
    """A file-backed /dev/fb1 (filled with 0xAB so untouched bytes show) and its sysfs."""
    fb = root / "sys" / "class" / "graphics" / "fb1"
    fb.mkdir(parents=True)
    (fb / "virtual_size").write_text(f"{width},{height}\n")
    (fb / "bits_per_pixel").write_text(f"{bpp}\n")
    (fb / "stride").write_text(f"{stride}\n")
    for name, status in (connectors or {}).items():
        d = root / "sys" / "class" / "drm" / name
        d.mkdir(parents=True)
        (d / "status").write_text(status + "\n")
    dev = root / "dev"
    dev.mkdir()
    (dev / "fb1").write_bytes(b"\xab" * stride * height)
    return SLMOutputSettings(framebuffer_device=str(dev / "fb1"), sysfs_root=str(root / "sys"))
