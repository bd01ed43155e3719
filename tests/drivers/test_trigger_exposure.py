"""The camera's exposure-active line wired to the host (`[devices.trigger] source =
"camera_exposure"`, nhfd.drivers.trigger) on the simulated bench: a cut wire lets frames be
written inside exposures, and the twin's record of exposures and writes shows it; the settle
time stays; the settings refuse an unknown source. What every line keeps (the write waits while
the line is high, a line stuck high times out naming the trigger and its timeout, no write
inside an exposure, close and reopen) is the trigger contract's:
tests/drivers/contracts/test_trigger.py.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pydantic
import pytest

from nhfd.config import Config
from nhfd.device_settings import TriggerSettings
from nhfd.drivers.factory import BenchDevices, make_bench
from nhfd.drivers.simcamera import TrueBench
from nhfd.drivers.trigger import TriggerLine

PANEL = 64
EXPOSURE_S = 0.03  # long against a write, so an unguarded write lands inside an exposure


@contextmanager
def bench(*, settle_ms: float = 0.0, timeout_ms: float = 500.0) -> Iterator[BenchDevices]:
    d = Config().devices
    devices = d.model_copy(update={
        "slm_output": d.slm_output.model_copy(update={"settle_ms": settle_ms}),
        "trigger": TriggerSettings(source="camera_exposure", timeout_ms=timeout_ms)})
    true = TrueBench(zero_order_fraction=0.0)
    with make_bench(devices, PANEL, PANEL, bench=true,
                    roi=true.roi_for_panel((PANEL, PANEL))) as out:
        out.camera.set_exposure(EXPOSURE_S)
        yield out


def shows_while_capturing(b: BenchDevices, seed: int, n: int = 8) -> int:
    """A camera capturing continuously in one thread while the host shows `n` seeded random
    frames at seeded random intervals; returns the number of exposures taken meanwhile."""
    rng = np.random.default_rng(seed)
    stop = threading.Event()
    errors: list[BaseException] = []

    def grab() -> None:
        try:
            while not stop.is_set():
                b.camera.capture(1, subtract_dark=False)
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    line = b.slm.trigger
    before = len(line.exposures)
    worker = threading.Thread(target=grab)
    worker.start()
    try:
        for _ in range(n):
            time.sleep(float(rng.uniform(0.002, 0.012)))
            b.slm.show(rng.integers(0, 256, (PANEL, PANEL), dtype=np.uint8))
    finally:
        stop.set()
        worker.join(5.0)
    assert not errors, errors
    return len(line.exposures) - before


@pytest.mark.parametrize("seed", [0, 1])
def test_a_cut_line_lets_frames_into_exposures_and_the_twins_record_shows_it(seed):
    # With the wire, no write falls inside an exposure (the trigger contract,
    # tests/drivers/contracts/test_trigger.py). Without it (the host's input reads low) and
    # without a settle wait, the same sequence writes frames while the sensor integrates: the
    # twin's check is what would catch a missing gate.
    with bench() as b:
        line = b.slm.trigger
        assert line is b.camera.trigger and line.source == "camera_exposure"
        line.cut()
        shows_while_capturing(b, seed)
        assert line.writes_during_exposures()


def test_the_settle_time_stays_with_the_exposure_line():
    # Unlike the frame-flip trigger, the exposure line says nothing of the panel's flip.
    with bench(settle_ms=40.0) as b:
        assert b.slm.settle_s == pytest.approx(0.04)


def test_an_unknown_source_is_refused_listing_the_allowed_ones():
    with pytest.raises(pydantic.ValidationError,
                       match=r"'none', 'slm_flip' or 'camera_exposure'"):
        TriggerSettings(source="camera_line")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"trigger source 'camera_line': expected one of "
                                         r"\('slm_flip', 'camera_exposure'\)"):
        TriggerLine("camera_line")
    d = Config().devices.model_copy(update={
        "camera": "opencv", "trigger": TriggerSettings(source="camera_exposure")})
    with pytest.raises(ValueError, match=r"devices.trigger.source = 'camera_exposure' needs "
                                         r"devices.camera = 'simulated'.*'opencv'"):
        make_bench(d, PANEL, PANEL)
