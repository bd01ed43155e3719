"""nhfd.lab.bluesky: a Bluesky RunEngine focus scan against a daemon on the simulated bench.

The daemon shows a lattice of dots focused at `FOCUS_MM`; the scan's documents must say what a
scan says (start, one descriptor with the camera's image, one event per point, a successful
stop), the focus readbacks must be the requested depths within the stage's resolution, the stage
twin must have moved, and the images must refocus: sharpest at the dots' depth, blurred at both
ends. Failures (a refused focus, a failed job, a refused view) fail the Status with the daemon's
message.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import numpy as np
import pytest

pytest.importorskip("ophyd", reason="nhfd[bluesky] is not installed (pip install nhfd[bluesky])")
pytest.importorskip("bluesky", reason="nhfd[bluesky] is not installed (pip install nhfd[bluesky])")

from bluesky import RunEngine
from bluesky.plan_stubs import mv
from bluesky.utils import FailedStatus
from ophyd.utils import ReadOnlyError

from nhfd.lab.bluesky import DaemonError
from nhfd.lab.bluesky_demo import (
    FOCUS_MM,
    SimBench,
    run_scan,
    scan_table,
    sharpness,
    simulated_bench,
)

# The daemon runs on a thread of this process with the guardian's 0.5 s heartbeat: another test's
# load beside it once stalled it past that, and the guardian rightly switched the lasers off under
# the scan. make test runs it alone.
pytestmark = pytest.mark.solo

START_MM, STOP_MM, POINTS = -0.5, 1.5, 5  # FOCUS_MM (0.5) is the middle point
JOB_TIMEOUT_S = 30.0


@pytest.fixture(scope="module")
def sim() -> Iterator[SimBench]:
    with simulated_bench() as s:
        s.bench.link.job_timeout_s = JOB_TIMEOUT_S  # a stuck job fails the test, not hangs it
        yield s


def test_focus_scan_documents_readbacks_and_refocus(sim: SimBench) -> None:
    docs = run_scan(sim.bench, START_MM, STOP_MM, POINTS)
    names = [name for name, _ in docs]
    assert names[0] == "start" and names[-1] == "stop"
    assert names.count("descriptor") == 1 and names.count("event") == POINTS
    start = docs[0][1]
    assert start["plan_name"] == "scan" and list(start["motors"]) == ["focus"]
    assert list(start["detectors"]) == ["camera"] and start["num_points"] == POINTS
    stop = docs[-1][1]
    assert stop["exit_status"] == "success" and stop["num_events"] == {"primary": POINTS}

    # The descriptor: the camera's image as a float32 array of the camera region's shape.
    keys = next(d for n, d in docs if n == "descriptor")["data_keys"]
    *_, h, w = sim.daemon.config.daemon.bench.camera_roi_px
    assert keys["camera_image"]["dtype"] == "array"
    assert keys["camera_image"]["shape"] == [h, w]
    assert keys["camera_image"]["dtype_numpy"] == "<f4"
    assert {"focus", "focus_setpoint", "focus_stage_mm", "camera_exposure_s", "camera_gain_db",
            "camera_frames", "camera_saturated_fraction", "camera_stage_mm"} <= set(keys)

    table = scan_table(docs)
    requested = np.linspace(START_MM, STOP_MM, POINTS)
    assert table["images"].shape == (POINTS, h, w)
    np.testing.assert_array_equal(table["setpoint_mm"], requested)
    # Readbacks come from the stage's reading in `status`: the requested depth within one count.
    resolution_mm = 1.0 / sim.daemon.config.devices.apt.counts_per_mm
    assert np.abs(table["focus_mm"] - requested).max() <= resolution_mm
    # The stage really moved (uncalibrated: stage = reference + z), as each capture recorded it
    # and as the twin holds it now.
    reference_mm = sim.daemon.config.daemon.bench.stage_at_reference_mm
    assert np.abs(table["camera_stage_mm"] - (reference_mm + requested)).max() <= resolution_mm
    assert sim.daemon.bench.stage.twin.position_mm == pytest.approx(reference_mm + STOP_MM,
                                                                    abs=resolution_mm)
    events = [d for n, d in docs if n == "event"]
    assert [e["data"]["camera_exposure_s"] for e in events] == [sim.bench.camera.exposure_s.get()
                                                                ] * POINTS

    # The images refocus: the dots are sharpest at their depth and blurred at both ends (a focus
    # that did nothing would give five equal images).
    s = table["sharpness"]
    assert int(np.argmax(s)) == int(np.argmin(np.abs(requested - FOCUS_MM)))
    assert s.max() > 1.4 * s[0] and s.max() > 1.4 * s[-1], s
    assert table["images"].max() < 1.0 and np.all(np.isfinite(table["images"]))


def test_camera_snapshot_mode_sees_the_same_dots(sim: SimBench) -> None:
    cam, focus = sim.bench.camera, sim.bench.focus
    focus.set(FOCUS_MM).wait(30)
    cam.trigger().wait(30)
    captured = cam.read()
    cam.mode.put("snapshot")
    try:
        cam.trigger().wait(30)
        snap = cam.read()
        desc = cam.describe()
    finally:
        cam.mode.put("capture")
    assert snap["camera_path"]["value"].endswith(".png")
    assert "camera_gain_db" not in snap and "camera_gain_db" not in desc  # a PNG has none
    a, b = captured["camera_image"]["value"], snap["camera_image"]["value"]
    assert a.shape == b.shape and 0.0 <= b.min() and b.max() <= 1.0
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.9
    assert snap["camera_stage_mm"]["value"] == pytest.approx(captured["camera_stage_mm"]["value"])
    assert sharpness(b) > 1.4 * sharpness(np.full_like(b, b.mean()) + 1e-3 * a)


def test_lasers_are_read_only_signals_of_the_daemons_readback(sim: SimBench) -> None:
    lasers = sim.bench.lasers
    reading = lasers.read()
    cap = sim.daemon.config.devices.readybeam.max_power_pct[1]
    assert reading["lasers_green_power_pct"]["value"] == cap  # the demo armed green at its cap
    assert reading["lasers_red_power_pct"]["value"] == 0.0
    assert reading["lasers_armed"]["value"] is True
    with pytest.raises(ReadOnlyError):
        lasers.green_power_pct.put(1.0)
    assert sim.daemon.laser.status()["channels"]["green"]["power_pct"] == cap


def test_view_set_reads_back_and_a_bad_view_fails_with_the_daemons_message(sim: SimBench
                                                                            ) -> None:
    view = sim.bench.view
    seq_before = view.seq.get()
    view.set({"orbit": {"azimuth_deg": 12.5, "elevation_deg": 8.0, "radius": 2.0}}).wait(10)
    reading = view.read()
    shown = json.loads(reading["view"]["value"])
    assert shown["kind"] == "orbit" and shown["azimuth_deg"] == 12.5
    assert reading["view_seq"]["value"] == seq_before + 1
    # A view as read back is accepted as a target too.
    view.set(shown).wait(10)
    assert view.seq.get() == seq_before + 2

    status = view.set({"orbit": {"azimuth_deg": 0.0, "elevation_deg": 95.0, "radius": 2.0}})
    with pytest.raises(DaemonError, match="elevation_deg"):
        status.wait(10)
    assert view.seq.get() == seq_before + 2  # refused: nothing changed


def test_a_refused_focus_fails_the_status_with_the_daemons_message(sim: SimBench) -> None:
    focus = sim.bench.focus
    status = focus.set(50.0)
    with pytest.raises(DaemonError) as info:
        status.wait(10)
    message = str(info.value)
    assert "z_mm: got 50" in message and "allowed: a finite number in [-5, 5]" in message, message
    # Through a plan, the RunEngine raises it as a failed status.
    engine = RunEngine({}, context_managers=[])
    with pytest.raises(FailedStatus) as failed:
        engine(mv(focus, 50.0))
    assert "allowed: a finite number in [-5, 5]" in str(failed.value.__cause__ or failed.value)


def test_a_failed_focus_job_fails_the_status_with_the_jobs_error() -> None:
    with simulated_bench(arm=False) as s:
        s.bench.link.job_timeout_s = JOB_TIMEOUT_S
        twin = s.daemon.bench.stage.twin
        twin.vanish()
        deadline = time.monotonic() + 5
        while s.bench.link.status(fresh=True)["devices"]["stage"]["error"] is None:
            assert time.monotonic() < deadline, "the stage error never showed"
            time.sleep(0.05)
        status = s.bench.focus.set(1.0)
        with pytest.raises(DaemonError) as info:
            status.wait(15)
        message = str(info.value)
        assert "focus job" in message and "failed" in message and "stage" in message, message
        job = [j for j in s.bench.link.status(fresh=True)["jobs"] if j["kind"] == "focus"][-1]
        assert job["state"] == "failed" and job["error"] in message
