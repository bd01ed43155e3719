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


def _first_switch_on(r: Running, c: Client, start: float, pose: dict = FRONT_POSE) -> None:
    c.call("set_view", pose=pose, quality="citl")
    wait_until(lambda: switch_ons(r.daemon.laser.twin, start), 25, "citl's first switch-on")


# The ends, in the order one daemon meets them: each ends the run under way, and the next
# request starts a new run that the next end meets (one daemon for all four: a daemon's start,
# loads and homing took 15 s of each 27 s case).
ENDS = ("off", "disarm", "stop")
SAID = {"off": "lasers off by uid", "disarm": "lasers disarmed by uid", "stop": "stop by uid"}


def _end_mid_citl(r: Running, c: Client, end: str, pose: dict) -> None:
    """A citl run at `pose` is ended by `end` once it captures; nothing it started switches on
    afterwards, even when a person arms again and sets the powers again."""
    twin = r.daemon.laser.twin
    _first_switch_on(r, c, twin.clock(), pose)
    refine = c.status()["frames"]["refine"]
    # While it captures, status says so: the tier asked for and where the bench is.
    assert refine["tier"] == "citl" and refine["stop"] == "", (end, refine)
    assert refine["phase"].startswith("citl step 1: "), (end, refine)
    offs_before = len(_operator_offs(r))
    if end == "stop":
        c.call("stop")
    else:
        c.call("laser", action=end)
    ended = twin.clock()
    wait_until(lambda: (c.status()["frames"]["refine"] or {}).get("stop", "").startswith(
        f"stopped: {SAID[end]}"), 5, f"status to say the run stopped ({end})")
    # A person arms again and sets the powers again (after a stop too: the old run must not
    # take them).
    c.call("laser", action="arm", duration_s=600.0)
    for ch, pct in POWERS.items():
        c.call("laser", action="power", channel=ch, power_pct=pct)
    jobs = len(_citl_jobs(c))
    time.sleep(WATCH_S)
    assert switch_ons(twin, ended) == [], end
    assert twin.emitting() == dict.fromkeys(COLOURS, 0.0), end
    status = c.status()
    refine = status["frames"]["refine"]
    assert refine["stop"].startswith(f"stopped: {SAID[end]}"), (end, refine)
    assert "does not resume; ask for quality citl again" in refine["stop"], refine
    assert refine["phase"] == "", (end, refine)
    # No capture job after the end: the refinement's citl steps ended with it.
    assert len(_citl_jobs(c)) == jobs, end
    assert not [j for j in _citl_jobs(c) if j["state"] in ("queued", "running")], end
    assert status["laser"]["armed"], end  # the new arming holds: it just runs nothing old
    # The audit: an operator's off is the operator's, once, and no disarm is the guardian's.
    after = [a for a in _audit(r) if a["what"].startswith("laser")]
    assert len(_operator_offs(r)) == offs_before + (end == "off"), (end, after)
    assert not [a for a in after if "by the guardian" in a["what"]], (end, after)


def _operator_offs(r: Running) -> list[dict]:
    offs = [a for a in _audit(r) if a["what"] == "laser" and a.get("params") == {"action": "off"}]
    assert all(a["who"]["transport"] == "unix" for a in offs), offs
    return offs


@pytest.mark.deadline_s(90)
def test_each_end_mid_citl_stops_its_run_and_no_later_arm_resumes_it(short_dir, tiny):
    """`laser off`, `disarm`, `stop`, then a shutdown, each while a citl run captures (each
    later run a new request at a new pose, which captures again: a new run after an end)."""
    r = _running(short_dir, tiny, armed=True, iterations=ITERATIONS)
    twin = r.daemon.laser.twin
    try:
        c = r.client()
        for i, end in enumerate(ENDS):
            _end_mid_citl(r, c, end, dict(FRONT_POSE, position=[0.02 * i, 0.0, -2.0]))
        # Last, the daemon shuts down mid-citl.
        _first_switch_on(r, c, twin.clock(), dict(FRONT_POSE, position=[0.0, 0.02, -2.0]))
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
