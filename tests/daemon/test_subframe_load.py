"""K subframes never stall the control loop: at the largest K, on the full 1920 x 1080 panel,
with a CPU burner beside the daemon and a diode armed and on, the guardian sees every heartbeat
within 200 ms and never disarms; what crosses the pipe per better frame is small whatever K; the
daemon's own memory does not grow by the K subframes' panels, and is back after the view
changes.

(Before, the daemon unpickled all K subframes and built K whole panels in one turn of its loop:
the outside test saw gaps of 253-262 ms with nothing beside it, 557 ms with a burner, and a
disarm.)"""

from __future__ import annotations

import pickle
import subprocess
import sys
import time

import pytest

from nhfd.config import Config, _overlay
from nhfd.worker_messages import BetterFrame

from .conftest import Running, wait_until
from .test_frame_shm import arrays_in
from .test_frames import FRONT_POSE, daemon_config, serve_tiny

K_MAX = 16  # refine.subframes' upper bound
PANEL = {"width_px": 1920, "height_px": 1080}
# The guardian's limit is 0.5 s (the test bench's heartbeat_timeout_s). At a 100 ms tick the
# gaps measured 100 to 153 ms with the fix (153.2 ms once, on a fresh clone after a whole suite);
# the defect the test guards against gave 253-262 ms with nothing beside it and 557 ms with the
# burner. 200 ms lies between: the defect fails it, a loaded machine's jitter does not.
MAX_GAP_MS = 200.0
# Its heartbeat gaps are this test's own load: make test runs it with no other test beside it.
pytestmark = pytest.mark.solo
BURN = "import time\nend = time.monotonic() + 60\nwhile time.monotonic() < end:\n    pass\n"


def rss_anon_mb() -> float:
    """This process's private resident memory (MB): the daemon runs on a thread of it."""
    for line in open("/proc/self/status"):
        if line.startswith("RssAnon:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no RssAnon in /proc/self/status")


def test_the_largest_k_under_a_cpu_burner_keeps_every_heartbeat_on_time(short_dir, mecom_twin,
                                                                         tiny):
    base = daemon_config(short_dir, mecom_twin, tiny)
    config = Config.model_validate(_overlay(base.model_dump(), {
        "slm": PANEL,
        "refine": {"iterations": 5000, "seconds": 60.0, "tolerance": 0.0, "swap_every": 1,
                   "subframes": K_MAX, "planes": 2}}))
    r = Running(config, short_dir)
    burner = None
    received: list[BetterFrame] = []
    try:
        c = r.client()
        serve_tiny(c, short_dir)
        receive = r.daemon.frames.worker.receive  # a spy on what crosses the pipe

        def spy() -> list:
            msgs = receive()
            received.extend(m for m in msgs if isinstance(m, BetterFrame))
            return msgs

        r.daemon.frames.worker.receive = spy
        c.call("laser", action="arm", duration_s=600.0)
        c.call("laser", action="power", channel="green", power_pct=5.0)
        c.call("laser", action="enable", channel="green")
        # The panel's own history (`history_frames` panels) filled first: memory it keeps for
        # any frame, not for the subframes.
        for i in range(12):
            last = c.call("set_view", pose=dict(FRONT_POSE, position=[0.01 * i, 0.0, -2.0]),
                          quality="network")["seq"]
            wait_until(lambda last=last: c.status()["view"]["applied_seq"] == last, 20,
                       "a network frame")
        burner = subprocess.Popen([sys.executable, "-c", BURN])
        before_mb = rss_anon_mb()
        seq = c.call("set_view", pose=FRONT_POSE, quality="sgd")["seq"]
        peak_mb = before_mb

        def refined(n: int) -> bool:
            nonlocal peak_mb
            peak_mb = max(peak_mb, rss_anon_mb())
            refine = c.status()["frames"]["refine"] or {}
            return refine.get("seq") == seq and refine.get("swaps", 0) >= n

        wait_until(lambda: refined(8), 25, "eight better frames of 16 subframes")
        status = c.status()
        assert status["frames"]["refine"]["subframes"] == K_MAX
        guardian = status["laser"]["guardian"]
        assert status["laser"]["armed"], status["laser"]
        assert status["laser"]["channels"]["green"]["enabled"]
        assert guardian["trips"] == 0, guardian
        assert guardian["seen_max_heartbeat_gap_ms"] < MAX_GAP_MS, guardian
        assert guardian["max_heartbeat_gap_ms"] < MAX_GAP_MS, guardian
        # Each better frame crossed as a few hundred bytes: its subframes are in shared memory.
        assert received and all(arrays_in(m) == [] and len(pickle.dumps(m)) < 2000
                                for m in received)
        # K whole panels would be 16 x 6.2 MB: the daemon holds none of them.
        assert peak_mb - before_mb < 40.0, (before_mb, peak_mb)

        seq2 = c.call("set_view", pose=dict(FRONT_POSE, position=[0.05, 0.0, -2.0]),
                      quality="network")["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq2, 20, "the new view")
        time.sleep(0.5)
        assert c.status()["frames"]["refine"] is None
        assert rss_anon_mb() - before_mb < 40.0
    finally:
        if burner is not None:
            burner.kill()
            burner.wait()
        r.stop()
