"""Hardware triggers on the simulated bench (nhfd.drivers.trigger): the SLM's frame-flip output
wired to the camera's trigger input. The simulated panel flips `flip_latency_ms` after a write
(an HDMI panel's display pipeline); the simulated camera images what the panel shows at the
exposure's start. A triggered capture sees the new frame, never the old, without the host's
settle sleep; an untriggered one that does not wait long enough sees the old one; a missed
trigger fails with an error naming the trigger and its timeout.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from nhfd.config import Config
from nhfd.device_settings import TriggerSettings
from nhfd.drivers.factory import BenchDevices, make_bench
from nhfd.drivers.simcamera import TrueBench
from nhfd.drivers.trigger import TriggerTimeout

PANEL = 64
FLIP_LATENCY_MS = 60.0  # long against a capture's own time, so "too early" is unambiguous
DELAY_MS = 5.0


@contextmanager
def bench(source: str, *, timeout_ms: float = 150.0) -> Iterator[BenchDevices]:
    d = Config().devices
    devices = d.model_copy(update={
        # No settle sleep at all: only the trigger can make a capture wait for the flip.
        "slm_output": d.slm_output.model_copy(update={"settle_ms": 0.0,
                                                      "flip_latency_ms": FLIP_LATENCY_MS}),
        "trigger": TriggerSettings(source=source, delay_ms=DELAY_MS, timeout_ms=timeout_ms)})
    true = TrueBench(zero_order_fraction=0.0)
    with make_bench(devices, PANEL, PANEL, bench=true,
                    roi=true.roi_for_panel((PANEL, PANEL))) as out:
        out.laser.arm(60)
        out.laser.set_power("green", 10.0)
        out.laser.enable("green")
        yield out


def frames(seed: int) -> list[np.ndarray]:
    """Three different panel frames: seeded random grey steps (each diffracts differently)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(3):
        f = np.zeros((PANEL, PANEL), np.uint8)
        f[:, int(rng.integers(8, 56)):] = int(rng.integers(64, 256))
        f[int(rng.integers(8, 56)):, :] //= 2
        out.append(f)
    return out


def settled_image(b: BenchDevices, frame: np.ndarray) -> np.ndarray:
    b.slm.show(frame)
    time.sleep(FLIP_LATENCY_MS / 1000 + 0.02)
    b.camera.trigger = None  # an exposure after the flip, whatever the wiring
    return b.camera.capture(1, subtract_dark=False).image


def nearest(image: np.ndarray, references: list[np.ndarray]) -> int:
    return int(np.argmin([np.abs(image - r).mean() for r in references]))


@pytest.mark.parametrize("seed", [0, 1])
def test_a_triggered_capture_sees_the_new_frame_never_the_old(seed):
    shown = frames(seed)
    with bench("slm_flip") as b:
        line = b.camera.trigger
        assert line is b.slm.trigger and b.slm.settle_s == 0.0  # no host settle sleep
        refs = [settled_image(b, f) for f in shown]
        b.camera.trigger = line
        for k in (1, 2, 0):  # each capture right after its frame was written
            before = len(line.record)
            b.slm.show(shown[k])
            image = b.camera.capture(1, subtract_dark=False).image
            assert nearest(image, refs) == k
            (rec,) = line.record[before:]
            # The twin's record: the flip came FLIP_LATENCY_MS after the write, and the exposure
            # started DELAY_MS after the flip, never before it.
            assert rec.flip_s - rec.written_s == pytest.approx(FLIP_LATENCY_MS / 1000, abs=2e-3)
            assert rec.exposure_start_s == pytest.approx(rec.flip_s + DELAY_MS / 1000)
    # Without the wire and without a settle wait, the same capture sees the old frame: the
    # trigger is what made the difference.
    with bench("none") as b:
        assert b.camera.trigger is None and b.slm.trigger is None
        b.slm.show(shown[0])
        time.sleep(FLIP_LATENCY_MS / 1000 + 0.02)
        b.slm.show(shown[1])
        image = b.camera.capture(1, subtract_dark=False).image
        assert nearest(image, refs) == 0


def test_a_missed_trigger_times_out_naming_the_trigger_and_the_timeout():
    with bench("slm_flip", timeout_ms=80.0) as b:
        line = b.camera.trigger
        b.slm.never_flip()  # the panel never takes the frame: no edge
        b.slm.show(np.full((PANEL, PANEL), 100, np.uint8))
        t0 = time.monotonic()
        with pytest.raises(TriggerTimeout, match=r"trigger slm_flip: no frame-flip edge within "
                                                 r"80 ms \(devices\.trigger\.timeout_ms\)"):
            b.camera.capture(1)
        assert time.monotonic() - t0 >= 0.08
        b.slm.never_flip(False)
        line.cut()  # the panel flips, but the wire is cut
        b.slm.show(np.full((PANEL, PANEL), 50, np.uint8))
        with pytest.raises(TriggerTimeout, match="no frame-flip edge within 80 ms"):
            b.camera.capture(1)
        line.mend()
        b.slm.show(np.full((PANEL, PANEL), 60, np.uint8))
        b.camera.capture(1)  # wired again: the next frame triggers


def test_the_trigger_is_refused_where_this_process_cannot_see_the_flip():
    d = Config().devices.model_copy(update={
        "slm": "framebuffer", "trigger": TriggerSettings(source="slm_flip")})
    with pytest.raises(ValueError, match=r"devices.trigger.source = 'slm_flip' needs "
                                         r"devices.slm = 'simulated'.*'framebuffer'"):
        make_bench(d, PANEL, PANEL)
    with pytest.raises(ValueError, match=r"source"):
        TriggerSettings(source="camera_line")  # type: ignore[arg-type]


def test_through_the_daemon_a_capture_right_after_show_pattern_sees_the_new_frame(tmp_path):
    """The daemon's capture job sleeps the SLM's settle time (none with the wire) and the camera
    exposes on the flip: calibration's DaemonBenchIO gets the pattern it just showed."""
    import contextlib
    import shutil
    import tempfile
    from pathlib import Path

    from daemon.conftest import Running, bench_config

    from nhfd.calib.capture import DaemonBenchIO

    root = Path(tempfile.mkdtemp(prefix="nhfd-t-", dir="/tmp"))  # short: a Unix socket
    true = TrueBench()
    config = bench_config(root, None, frames={"colour_mode": "hw-sync"},
                          bench={"camera_roi_px": list(true.roi_for_panel((PANEL, PANEL)))},
                          paths={"pattern_dirs": [str(root / "calib")]})
    d = config.devices
    devices = d.model_copy(update={
        "camera": "simulated",
        "slm_output": d.slm_output.model_copy(update={"settle_ms": 0.0,
                                                      "flip_latency_ms": FLIP_LATENCY_MS}),
        "trigger": TriggerSettings(source="slm_flip", delay_ms=DELAY_MS, timeout_ms=500.0)})
    slm = config.slm.model_copy(update={"width_px": PANEL, "height_px": PANEL})
    r = Running(config.model_copy(update={"devices": devices, "slm": slm}), root)
    try:
        io = DaemonBenchIO(r.client(timeout_s=30.0), root / "calib" / "io", arm_s=60.0)
        io.set_lasers((0.0, 1.0, 0.0))
        shown = frames(2)
        refs = []
        for f in shown:
            io.show(f)
            time.sleep(FLIP_LATENCY_MS / 1000 + 0.05)
            refs.append(io.capture(1)[0])
        line = r.daemon.bench.camera.trigger
        assert line is not None and r.daemon.bench.slm.settle_s == 0.0
        for k in (1, 0, 2):
            before = len(line.record)
            io.show(shown[k])
            assert nearest(io.capture(1)[0], refs) == k
            (rec,) = line.record[before:]
            assert rec.exposure_start_s >= rec.flip_s + DELAY_MS / 1000 > rec.written_s
        io.lasers_off()
    finally:
        with contextlib.suppress(Exception):
            r.stop()
        shutil.rmtree(root, ignore_errors=True)
