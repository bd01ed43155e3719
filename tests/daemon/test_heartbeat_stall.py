"""A stalled control loop (issue 32, smaller items): the guardian disarms, the daemon logs the
missed heartbeats and audits the guardian's own reason, not "expiry or fault". The light is read
from the laser twin's emission record."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import pytest

from .conftest import Running, bench_config, wait_until

OFF = {"red": 0.0, "green": 0.0, "blue": 0.0}


def _audit(run_dir: Path) -> list[dict]:
    return [json.loads(x) for x in (run_dir / "audit.jsonl").read_text().splitlines()]


def test_a_stalled_loop_is_logged_and_the_disarm_audited_with_the_guardians_reason(
        short_dir, mecom_twin, caplog: pytest.LogCaptureFixture):
    r = Running(bench_config(short_dir, mecom_twin), short_dir)
    link = r.daemon.laser
    timeout_s = float(link.identity["heartbeat_timeout_s"])
    try:
        with r.client() as c:
            c.call("laser", action="arm", duration_s=60.0)
            c.call("laser", action="power", channel="red", power_pct=5.0)
            c.call("laser", action="enable", channel="red")
            assert mecom_twin.emitting()["red"] == 5.0
            caplog.set_level(logging.WARNING, logger="nhfd.daemon")
            # The control loop's next heartbeat waits on the link's lock: the loop stalls.
            with link._lock:
                wait_until(lambda: mecom_twin.emitting() == OFF, timeout_s=10 * timeout_s,
                           what="the guardian to switch the lasers off")
                time.sleep(0.1)
            wait_until(lambda: not c.status()["laser"]["armed"], what="the daemon to see it")
            guardian = c.status()["laser"]["guardian"]
        assert guardian["late_heartbeats"] >= 1
        assert guardian["max_heartbeat_gap_ms"] > timeout_s * 1e3
        stalls = [rec.getMessage() for rec in caplog.records
                  if "the control loop stalled" in rec.getMessage()]
        assert stalls and f"the guardian disarms at {timeout_s * 1e3:.0f} ms" in stalls[0]
        disarms = [e for e in _audit(r.daemon.audit.path.parent)
                   if str(e.get("what", "")).startswith("laser disarmed by the guardian")]
        assert [e["what"] for e in disarms] == [
            f"laser disarmed by the guardian: no heartbeat for {timeout_s:g} s"]
        assert disarms[0]["heartbeat_gap_ms"] > timeout_s * 1e3
    finally:
        r.stop()
