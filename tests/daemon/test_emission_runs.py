"""Every run that could emit ends with `laser off`, `disarm`, `stop` and shutdown, and no later
arm resumes it; a remote peer cannot start emission unless the lab allows it; the audit blames
an operator's off on the operator, once.

On the simulated bench (the daemon's own laser twin, stage and camera, a calibration that is the
twin's truth): a citl view is refining with its captures under way when the run is ended. The
twin's record is the judge: after the end, no diode switches on, even when a person arms again
and sets the powers again (as the outside test that found the defect did)."""

from __future__ import annotations

import itertools
import json
import time

import pytest

from nhfd.config import Config, _overlay
from nhfd.daemon.client import Client
from nhfd.daemon.guardian_link import EmissionEnded
from nhfd.daemon.protocol import RpcError
from nhfd.daemon.service import SHUTDOWN_EMISSION_END, Daemon
from nhfd.device_settings import COLOURS

from .conftest import Running, bench_config, free_port, wait_until
from .test_citl_daemon import POWERS, _citl_jobs, _running, citl_config
from .test_frames import FRONT_POSE
from .test_tls import self_signed

# sgd then citl steps: the run is still capturing when it is ended (a citl step takes ~1 s
# here), and sgd leaves it soon enough for the test.
ITERATIONS = 12
# How long the twin is watched after the end (s): an old job finishing its sequence showed its
# switch-ons 4.8 s and more after the off, a new step's first within a second or two.
WATCH_S = 4.0


def switch_ons(twin, after: float) -> list[tuple[str, float]]:
    """(channel, time) of every switch-on (0 -> above 0) on the twin's record after `after`."""
    out = []
    for ch in COLOURS:
        log = twin.emission(ch)
        for (_, before), (t, pct) in itertools.pairwise(log):
            if t > after and pct > 0 and before <= 0:
                out.append((ch, t))
    return out


def _audit(r: Running) -> list[dict]:
    return [json.loads(line) for line in r.daemon.audit.path.read_text().splitlines()]


def _first_switch_on(r: Running, c: Client, start: float) -> None:
    c.call("set_view", pose=FRONT_POSE, quality="citl")
    wait_until(lambda: switch_ons(r.daemon.laser.twin, start), 25, "citl's first switch-on")


@pytest.mark.parametrize("end", ["off", "disarm", "stop"])
def test_an_end_mid_citl_stops_the_run_and_no_later_arm_resumes_it(short_dir, tiny, end):
    r = _running(short_dir, tiny, armed=True, iterations=ITERATIONS)
    try:
        c = r.client()
        twin = r.daemon.laser.twin
        _first_switch_on(r, c, twin.clock())
        refine = c.status()["frames"]["refine"]
        # While it captures, status says so: the tier asked for and where the bench is.
        assert refine["tier"] == "citl" and refine["stop"] == "", refine
        assert refine["phase"].startswith("citl step 1: "), refine
        if end == "stop":
            c.call("stop")
        else:
            c.call("laser", action=end)
        ended = twin.clock()
        said = {"off": "lasers off by uid", "disarm": "lasers disarmed by uid",
                "stop": "stop by uid"}[end]
        wait_until(lambda: (c.status()["frames"]["refine"] or {}).get("stop", "").startswith(
            f"stopped: {said}"), 5, "status to say the run stopped")
        if end != "stop":  # a person arms again and sets the powers again
            c.call("laser", action="arm", duration_s=600.0)
            for ch, pct in POWERS.items():
                c.call("laser", action="power", channel=ch, power_pct=pct)
        jobs = len(_citl_jobs(c))
        time.sleep(WATCH_S)
        assert switch_ons(twin, ended) == []
        assert twin.emitting() == dict.fromkeys(COLOURS, 0.0)
        status = c.status()
        refine = status["frames"]["refine"]
        assert refine["stop"].startswith(f"stopped: {said}")
        assert "does not resume; ask for quality citl again" in refine["stop"]
        assert refine["phase"] == ""
        # No capture job after the end: the refinement's citl steps ended with it.
        assert len(_citl_jobs(c)) == jobs
        assert not [j for j in _citl_jobs(c) if j["state"] in ("queued", "running")]
        if end != "stop":
            assert status["laser"]["armed"]  # the new arming holds: it just runs nothing old
        if end == "off":
            # The audit: the operator's off, once, and no disarm blamed on the guardian.
            after = [a for a in _audit(r) if a["what"].startswith("laser")]
            offs = [a for a in after if a["what"] == "laser"
                    and a.get("params") == {"action": "off"}]
            assert len(offs) == 1 and offs[0]["who"]["transport"] == "unix", offs
            assert not [a for a in after if "by the guardian" in a["what"]], after
        # A new request after the arm is a new run: it captures again.
        if end == "off":
            start = twin.clock()
            c.call("set_view", pose=dict(FRONT_POSE, position=[0.02, 0.0, -2.0]),
                   quality="citl")
            wait_until(lambda: switch_ons(twin, start), 25, "the new run's captures")
    finally:
        r.stop()


def test_shutdown_mid_citl_switches_nothing_on_after_it(short_dir, tiny):
    r = _running(short_dir, tiny, armed=True, iterations=ITERATIONS)
    twin = r.daemon.laser.twin
    try:
        _first_switch_on(r, r.client(), twin.clock())
    finally:
        asked = twin.clock()
        r.stop()
    assert switch_ons(twin, asked) == []
    assert twin.emitting() == dict.fromkeys(COLOURS, 0.0)
    stops = [a for a in _audit(r) if a["what"] == "stop"]
    assert stops and stops[-1]["lasers"] == "read back off through the guardian"


def _tls_citl(short_dir, tiny, remote_emission: bool) -> tuple[Running, Client]:
    cert, key = self_signed(short_dir, "bench")
    base = citl_config(short_dir, tiny)
    config = Config.model_validate(_overlay(base.model_dump(), {"daemon": {
        "server": {"tcp_port": free_port(), "tls_cert": str(cert), "tls_key": str(key)},
        "arming": {"remote_emission": remote_emission}}}))
    r = Running(config, short_dir)
    c = r.client()
    c.call("load_scene", path=str(short_dir / "scenes" / "cloud.ply"))
    c.call("load_model", path=str(short_dir / "models" / "tiny.onnx"))
    job = c.call("focus", z_mm=0.0, home=True)["job"]
    wait_until(lambda: c.call("job", id=job)["state"] == "done", 20, "the stage homed")
    c.call("laser", action="arm", duration_s=600.0)  # a person at the bench arms
    token = (short_dir / "run" / "tcp.token").read_text().strip()
    return r, Client(tcp=r.daemon.server.tcp_address, token=token, tls_ca=cert)


def test_a_tls_peer_may_not_start_emission_by_default(short_dir, tiny):
    r, remote = _tls_citl(short_dir, tiny, remote_emission=False)
    try:
        twin = r.daemon.laser.twin
        start = twin.clock()
        for ask in (lambda: remote.call("laser", action="power", channel="red", power_pct=5.0),
                    lambda: remote.call("set_view", pose=FRONT_POSE, quality="citl"),
                    lambda: remote.call("snapshot")):
            with pytest.raises(RpcError) as info:
                ask()
            assert info.value.name == "forbidden"
            assert ("makes a laser emit, and a TCP peer at 127.0.0.1:" in info.value.message
                    and "(daemon.arming.remote_emission = false)" in info.value.message), info.value
        assert remote.status()["laser"]["channels"]["red"]["power_pct"] == 0.0
        # What it may still do: views that do not emit, power 0, and laser off (1 ms here).
        remote.call("set_view", pose=FRONT_POSE, quality="sgd")
        remote.call("laser", action="power", channel="red", power_pct=0.0)
        t0 = time.monotonic()
        remote.call("laser", action="off")
        assert time.monotonic() - t0 < 1.0
        time.sleep(1.0)
        assert twin.max_emitted_pct() == 0.0 and switch_ons(twin, start) == []
        assert not _citl_jobs(r.client())
    finally:
        remote.close()
        r.stop()


def test_remote_emission_true_lets_a_tls_peer_start_citl(short_dir, tiny):
    r, remote = _tls_citl(short_dir, tiny, remote_emission=True)
    try:
        twin = r.daemon.laser.twin
        start = twin.clock()
        for ch, pct in POWERS.items():
            remote.call("laser", action="power", channel=ch, power_pct=pct)
        remote.call("set_view", pose=FRONT_POSE, quality="citl")
        wait_until(lambda: switch_ons(twin, start), 25, "the remote peer's citl captures")
        assert remote.status()["laser"]["armed"]  # arming itself stays a person's
    finally:
        remote.close()
        r.stop()


def test_a_shutdown_refuses_the_next_switch_on_before_the_loop_steps_again(short_dir,
                                                                         mecom_twin):
    """A shutdown asked from another thread (an RPC, a signal) refuses the next switch-on of a
    run at once, whatever its session, and names the shutdown. The loop ends the session only
    at its next step; a loaded machine once let citl light green twice in between. Here the
    loop never steps: the refusal is the shutdown's own."""
    d = Daemon(bench_config(short_dir, mecom_twin), base_dir=short_dir, env={},
               handle_signals=False)
    d.start()
    try:
        d.laser.arm(60.0)
        d.laser.power("green", 5.0)
        session = d.laser.session
        d.laser.enable("green", True, session=session)  # a run lights green, then red is next
        d.laser.enable("green", False)
        asked = mecom_twin.clock()
        d.request_shutdown("test over")
        assert d.laser.session == session  # the loop has not stepped: the session still holds
        with pytest.raises(EmissionEnded, match=f"^{SHUTDOWN_EMISSION_END}$"):
            d.laser.enable("red", True, session=session)
        assert switch_ons(mecom_twin, asked) == []
    finally:
        d.close()
    assert mecom_twin.emitting() == dict.fromkeys(COLOURS, 0.0)
