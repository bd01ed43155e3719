"""The camera in the loop served by the daemon (issue 34): a `citl` view's steps ask the daemon's
bench for captures over the worker's pipe. On the simulated bench (the daemon's own laser twin,
stage and camera, a calibration that is the simulated bench's truth): the steps run with one
diode on at a time, the captures reach the refinement, every diode is off after; disarmed lasers
stop it with a clear message and the twin's record shows nothing emitted; a new view stops the
captures; a bench that cannot serve citl is refused naming what is missing."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from nhfd.config import Config, _overlay
from nhfd.daemon.protocol import RpcError
from nhfd.device_settings import COLOURS
from nhfd.drivers.simcamera import TrueBench
from tests.calib.twin_stack import truth_calibration

from .conftest import Running, wait_until
from .test_colour import on_at
from .test_frames import FRONT_POSE, daemon_config, wait_for_frames

# sgd and then citl, each a few steps (the simulated camera and stage take ~1 s a step here).
REFINE = {"iterations": 3, "seconds": 120.0, "tolerance": 0.0, "swap_every": 1, "planes": 2}
POWERS = {"red": 5.0, "green": 4.0, "blue": 3.0}


def citl_config(root: Path, tiny, **refine) -> Config:
    base = daemon_config(root, None, tiny, frames={"colour_mode": "capture"})
    bench = TrueBench()
    panel_hw = (base.slm.height_px, base.slm.width_px)
    roi = bench.roi_for_panel(panel_hw)
    cal = truth_calibration(bench, roi, illumination=False).save(root / "calibration.toml")
    return Config.model_validate(_overlay(base.model_dump(), {
        "devices": {"camera": "simulated", "slm_output": {"settle_ms": 5.0},
                    "apt": {"velocity_mm_s": 50.0}},
        "daemon": {"bench": {"camera_roi_px": list(roi)}},
        "calibration": {"file": str(cal)},
        "refine": {**REFINE, **refine}}))


def _running(root: Path, tiny, *, armed: bool, **refine) -> Running:
    r = Running(citl_config(root, tiny, **refine), root)
    c = r.client()
    c.call("load_scene", path=str(root / "scenes" / "cloud.ply"))
    c.call("load_model", path=str(root / "models" / "tiny.onnx"))
    wait_for_frames(c)
    prepare_bench(c, armed=armed)
    return r


def prepare_bench(c, *, armed: bool) -> None:
    """What a person does before the daemon captures with each diode: home the stage (citl's
    captures never home it themselves), arm (when `armed`), set each colour's power."""
    job = c.call("focus", z_mm=0.0, home=True)["job"]
    wait_until(lambda: c.call("job", id=job)["state"] == "done", 20, "the stage homed")
    if armed:
        c.call("laser", action="arm", duration_s=600.0)
    for ch, pct in POWERS.items():
        c.call("laser", action="power", channel=ch, power_pct=pct)


def _citl_jobs(c) -> list[dict]:
    return [j for j in c.status()["jobs"] if j["kind"] == "citl capture"]


def test_citl_steps_capture_one_diode_at_a_time_and_leave_every_diode_off(short_dir, tiny):
    r = _running(short_dir, tiny, armed=True)
    try:
        c = r.client()
        twin = r.daemon.laser.twin
        start = twin.clock()
        seq = c.call("set_view", pose=FRONT_POSE, quality="citl")["seq"]
        wait_until(lambda: (c.status()["frames"]["refine"] or {}).get("stop", "") != "", 120,
                   "the citl refinement to finish")
        refine = c.status()["frames"]["refine"]
        assert refine["seq"] == seq and refine["tier"] == "citl", refine
        assert refine["stop"] == "iterations" and refine["iterations"] == REFINE["iterations"]
        # One capture job per citl step, each done: planes x colours captures with the step's
        # subframe on the panel.
        jobs = _citl_jobs(c)
        assert len(jobs) == REFINE["iterations"]
        assert all(j["state"] == "done" and j["result"] == {"planes": 2, "subframes": 1}
                   for j in jobs), jobs
        # The twin's record: every colour emitted at its set power, never two at once, and
        # nothing emits now.
        changes = sorted({t for ch in COLOURS for t, _ in twin.emission(ch) if t >= start})
        assert all(len(on_at(twin, t)) <= 1 for t in changes)
        for ch in COLOURS:
            levels = {pct for t, pct in twin.emission(ch) if t >= start}
            assert levels == {0.0, POWERS[ch]}, (ch, levels)
        assert twin.emitting() == dict.fromkeys(COLOURS, 0.0)
        assert c.status()["laser"]["armed"]  # citl switches diodes; the arming stays a person's
        # Back on the panel: the refined frame, not a capture pattern.
        assert np.array_equal(r.daemon.bench.slm.last_frame, r.daemon.frames.last_frame)
    finally:
        r.stop()


def test_disarmed_lasers_stop_citl_with_a_clear_message_and_nothing_is_emitted(short_dir, tiny):
    r = _running(short_dir, tiny, armed=False)
    try:
        c = r.client()
        twin = r.daemon.laser.twin
        seq = c.call("set_view", pose=FRONT_POSE, quality="citl")["seq"]
        wait_until(lambda: (c.status()["frames"]["refine"] or {}).get("stop", "") != "", 120,
                   "citl to stop")
        refine = c.status()["frames"]["refine"]
        assert refine["seq"] == seq
        assert refine["stop"].startswith("capture stopped: the lasers are not armed; citl never "
                                         "arms: arm the lasers (nhfctl laser arm)"), refine
        assert twin.max_emitted_pct() == 0.0
        assert not c.status()["laser"]["armed"]
        # The sgd frame it had reached stays on the panel.
        assert np.array_equal(r.daemon.bench.slm.last_frame, r.daemon.frames.last_frame)
    finally:
        r.stop()


def test_a_new_view_stops_the_captures(short_dir, tiny):
    # 12: sgd's steps end soon (200 took most of the test's 30 s on a loaded machine) and
    # citl's last many seconds, so a capture is under way when the new view comes.
    r = _running(short_dir, tiny, armed=True, iterations=12)
    try:
        c = r.client()
        twin = r.daemon.laser.twin
        c.call("set_view", pose=FRONT_POSE, quality="citl")
        wait_until(lambda: any(j["state"] == "running" for j in _citl_jobs(c)), 120,
                   "a citl capture under way")
        seq2 = c.call("set_view", pose=dict(FRONT_POSE, position=[0.05, 0.0, -2.0]),
                      quality="network")["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq2, 20, "the new view")
        wait_until(lambda: not any(j["state"] in ("queued", "running") for j in _citl_jobs(c)),
                   10, "the capture job to stop")
        settled = len(_citl_jobs(c))
        time.sleep(1.0)
        assert len(_citl_jobs(c)) == settled  # no capture follows the new view
        assert twin.emitting() == dict.fromkeys(COLOURS, 0.0)
        assert c.status()["frames"]["refine"] is None
        assert np.array_equal(r.daemon.bench.slm.last_frame, r.daemon.frames.last_frame)
    finally:
        r.stop()


@pytest.mark.parametrize(("change", "named"), [
    ({"daemon": {"frames": {"colour_mode": "single"}}},
     "daemon.frames.colour_mode is 'single': citl needs 'capture'"),
    ({"devices": {"camera": "none"}}, "citl needs the bench's camera (devices.camera"),
    ({"calibration": {"file": ""}}, "citl needs a calibration (calibration.file)"),
])
def test_a_bench_that_cannot_serve_citl_is_refused_naming_what_is_missing(short_dir, tiny,
                                                                         change, named):
    config = Config.model_validate(_overlay(citl_config(short_dir, tiny).model_dump(), change))
    r = Running(config, short_dir)
    try:
        c = r.client()
        before = c.status()["view"]
        with pytest.raises(RpcError, match="quality: 'citl' cannot be served here: ") as info:
            c.call("set_view", pose=FRONT_POSE, quality="citl")
        assert named in info.value.message
        assert info.value.message.endswith("allowed: network, exact or sgd on this bench "
                                           "(refine.quality sets the default)")
        assert c.status()["view"] == before
    finally:
        r.stop()
