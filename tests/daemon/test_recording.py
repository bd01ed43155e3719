"""Session recording and replay: a session recorded on one simulated bench, replayed by
`nhfd replay` against a fresh one, ends in the same view, focus and laser state."""

from __future__ import annotations

import json

import pytest

from nhfd.cli.main import main
from nhfd.daemon.bench import stage_mm_for_focus
from nhfd.daemon.protocol import RpcError

from .conftest import Running, bench_config, wait_until


def bench_state(r: Running) -> dict:
    c = r.client()
    wait_until(lambda: not any(j["state"] in ("queued", "running") for j in c.status()["jobs"]),
               20, "jobs to finish")
    r.daemon.laser.refresh()
    st = c.status()
    return {"view": st["view"]["requested"],
            "stage_mm": round(r.daemon.bench.stage.twin.position_mm, 4),
            "homed": st["devices"]["stage"]["homed"],
            "laser": r.daemon.laser.twin.emitting(), "armed": st["laser"]["armed"],
            "channels": st["laser"]["channels"]}


def fast_stage(config):
    """No homing (the twin homes at 2 mm/s) and a quick stage: the test is about the replay."""
    apt = config.devices.apt.model_copy(update={"require_homed": False, "velocity_mm_s": 25.0,
                                                "acceleration_mm_s2": 100.0})
    return config.model_copy(update={"devices": config.devices.model_copy(update={"apt": apt})})


def test_a_replayed_session_ends_in_the_same_state(short_dir):
    record = short_dir / "session.jsonl"
    (short_dir / "a").mkdir()
    (short_dir / "b").mkdir()
    a = Running(fast_stage(bench_config(short_dir / "a", None, audit={"record": str(record)})),
                short_dir / "a")
    try:
        c = a.client()
        c.call("set_view", orbit={"azimuth_deg": 10.0, "elevation_deg": 5.0, "radius": 2.0})
        c.call("set_view", relative={"d_azimuth_deg": 15.0}, refocus_mm=0.5)
        c.call("laser", action="arm", duration_s=120.0)
        c.call("laser", action="power", channel="red", power_pct=4.0)
        c.call("laser", action="power", channel="blue", power_pct=2.5)
        c.call("laser", action="enable", channel="red")
        with pytest.raises(RpcError):  # refused: changes nothing, not recorded
            c.call("focus", z_mm=99.0)
        job = c.call("focus", z_mm=1.0)["job"]
        wait_until(lambda: c.call("job", id=job)["state"] == "done", 20, "focus")
        c.call("set_view", relative={"d_elevation_deg": -3.0})
        c.call("focus", z_mm=-0.5)
        c.call("status")  # read-only: not recorded
        want = bench_state(a)
    finally:
        a.stop()
    lines = [json.loads(x) for x in record.read_text().splitlines()]
    assert lines[0]["nhfd_session"] == 1
    methods = [x["method"] for x in lines[1:]]
    assert methods == ["set_view", "set_view", "laser", "laser", "laser", "laser", "focus",
                       "set_view", "focus"]
    # Views are recorded absolute: the relative move became an orbit.
    assert lines[2]["params"] == {"orbit": {"azimuth_deg": 25.0, "elevation_deg": 5.0,
                                            "radius": 2.0}, "refocus_mm": 0.5}
    assert all(x["t_s"] >= 0 for x in lines[1:])
    assert want["laser"]["red"] == 4.0 and want["armed"]
    assert want["stage_mm"] == pytest.approx(
        stage_mm_for_focus(a.daemon.config, a.daemon.calibration, -0.5), abs=1e-3)

    b = Running(fast_stage(bench_config(short_dir / "b", None)), short_dir / "b")
    try:
        assert b.client().status()["view"]["requested"] is None
        assert main(["replay", str(record), "--socket", str(b.socket), "--speed", "0"]) == 0
        got = bench_state(b)
    finally:
        b.stop()
    assert got == want
