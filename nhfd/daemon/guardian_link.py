"""The daemon's side of the laser guardian: start or connect, heartbeat, commands, read-back.

The guardian process owns the laser port; the daemon never opens it. Heartbeats go out from the
control loop (never a helper thread: a stuck loop must stop them, so the guardian switches the
lasers off). With `devices.laser = "simulated"` the daemon hosts the READYBeam twin on a pty and
the guardian drives it through the same MeCom code as the real unit.

Laser state changes the guardian makes by itself (arming expiry, a tripped heartbeat) are seen in
the heartbeat replies and written to the audit log.
"""

from __future__ import annotations

import contextlib
import logging
import subprocess
import threading
import time
from typing import Any

from nhfd.drivers.guardian import (
    GuardianClient,
    GuardianError,
    GuardianUnavailable,
    socket_path_for,
    spawn_guardian,
)
from nhfd.drivers.settings import LaserSettings

from .audit import AuditLog
from .protocol import LASER_REFUSED, NOT_AVAILABLE, RpcError

log = logging.getLogger("nhfd.daemon.laser")

SYSTEM = {"who": "daemon"}


class LasersNotOff(RuntimeError):
    """Every channel could not be read back off: the daemon must not report ready."""


class LaserLink:
    def __init__(self, settings: LaserSettings, backend: str, mode: str, audit: AuditLog, *,
                 call_timeout_s: float = 1.0, refresh_s: float = 1.0) -> None:
        self.settings = settings
        self.backend = backend  # "simulated", "readybeam" or "none"
        self.mode = mode  # "auto", "spawn" or "connect"
        self.audit = audit
        self.call_timeout_s = call_timeout_s
        self.refresh_s = refresh_s
        self.socket_path = socket_path_for(settings)
        self.twin: Any = None  # the simulated laser's MecomTwin (the simulated camera reads it)
        self.proc: subprocess.Popen[str] | None = None
        self.client: GuardianClient | None = None
        self.error: str | None = None
        self._beat: dict[str, Any] = {}
        self._channels: dict[str, Any] = {}
        self._read_at = 0.0
        self._next_reconnect = 0.0
        # One socket, one request at a time: the control loop (heartbeats, commands) and the
        # capture-mode snapshot job (per-colour enables) both use it.
        self._lock = threading.RLock()

    @property
    def present(self) -> bool:
        return self.backend != "none"

    # -- start / stop --------------------------------------------------------------------------

    def start(self) -> None:
        """Connect to (or start) the guardian, switch every channel off and read it back."""
        if not self.present:
            return
        if self.mode in ("auto", "connect"):
            with contextlib.suppress(GuardianUnavailable):
                self.client = GuardianClient(self.socket_path, timeout_s=self.call_timeout_s)
                log.info("laser guardian found at %s", self.socket_path)
        if self.client is None:
            if self.mode == "connect":
                raise GuardianUnavailable(f"no laser guardian at {self.socket_path} and "
                                          "daemon.guardian = 'connect'")
            self._spawn()
        self.all_off_confirmed("start")

    def _spawn(self) -> None:
        port = None
        if self.backend == "simulated":
            from nhfd.drivers.twins.mecom_twin import MecomTwin

            s = self.settings
            self.twin = MecomTwin(device_type=s.device_type, address=s.address,
                                  channel_instances=s.channel_instances,
                                  parameter_ids=s.parameter_ids)
            self.twin.start()
            port = self.twin.port_path
        self.proc = spawn_guardian(self.settings, port=port, socket_path=self.socket_path)
        log.info("laser guardian started, pid %d, socket %s", self.proc.pid, self.socket_path)
        self.client = GuardianClient(self.socket_path, timeout_s=self.call_timeout_s)

    def all_off_confirmed(self, why: str) -> None:
        """Disarm, all channels off, then read every channel back; LasersNotOff otherwise."""
        client = self._require()
        # No heartbeat here: `off` needs none, and a first heartbeat would start the guardian's
        # watchdog before the control loop runs (start-up opens slow devices in between).
        client.all_off()  # the guardian reads back too, and raises if it could not confirm
        status = client.status()
        on = {ch: c for ch, c in status["channels"].items()
              if c["enabled"] or abs(c["power_pct"]) > self.settings.readback_tolerance_pct}
        if on or status["armed"]:
            raise LasersNotOff(f"lasers not read back off ({why}): {on or 'still armed'}")
        self._channels, self._read_at = status["channels"], time.monotonic()
        self._beat = {"armed": False, "armed_remaining_s": 0.0, "fault": status["fault"]}
        self.audit.write(SYSTEM, "laser all off (read back)", reason=why)

    def close(self) -> str:
        """All off with read-back, then leave; returns how the lasers were confirmed off."""
        if not self.present:
            return "no laser"
        how = "not confirmed"
        try:
            if self.client is not None:
                self.all_off_confirmed("shutdown")
                how = "read back off through the guardian"
        except (GuardianError, LasersNotOff, OSError) as exc:
            log.error("laser all-off at shutdown: %s", exc)
        finally:
            if self.client is not None:
                self.client.close()  # the guardian trips as well when a controller leaves
                self.client = None
            if self.proc is not None:
                if self.proc.poll() is None:
                    self.proc.terminate()  # it switches everything off and exits 0
                with contextlib.suppress(subprocess.TimeoutExpired):
                    code = self.proc.wait(timeout=5)
                    if code == 0 and how == "not confirmed":
                        how = "guardian exited cleanly (its exit switches everything off)"
                if self.proc.poll() is None:
                    self.proc.kill()
                    self.proc.wait()
            if self.twin is not None:
                self.twin.close()
        return how

    # -- loop ----------------------------------------------------------------------------------

    def heartbeat(self, now: float) -> None:
        """From the control loop, every tick."""
        if not self.present:
            return
        with self._lock:
            self._heartbeat(now)

    def _heartbeat(self, now: float) -> None:
        if self.client is None:
            self._reconnect(now)
            return
        try:
            beat = self.client.heartbeat()
        except GuardianError as exc:
            self._lost(f"guardian heartbeat failed: {exc}")
            return
        if self._beat.get("armed") and not beat["armed"]:
            self.audit.write(SYSTEM, "laser disarmed by the guardian (expiry or fault)",
                             fault=beat.get("fault"))
        self._beat = beat
        self.error = None
        if now - self._read_at >= self.refresh_s:
            self.refresh(now)

    def refresh(self, now: float | None = None) -> None:
        with self._lock:
            self._refresh(now)

    def _refresh(self, now: float | None) -> None:
        client = self._require()
        try:
            self._channels = client.status()["channels"]
        except GuardianError as exc:
            self._lost(f"guardian status failed: {exc}")
        self._read_at = time.monotonic() if now is None else now

    def _lost(self, why: str) -> None:
        log.error("%s; lasers are off by the guardian's rule (no heartbeat)", why)
        self.error = why
        if self.client is not None:
            self.client.close()
            self.client = None
        self._beat = {}
        self._channels = {}

    def _reconnect(self, now: float) -> None:
        if now < self._next_reconnect:
            return
        self._next_reconnect = now + 1.0
        try:
            if self.proc is not None and self.proc.poll() is not None and self.mode != "connect":
                self.proc = None
                self._spawn()
            else:
                self.client = GuardianClient(self.socket_path, timeout_s=self.call_timeout_s)
            self.all_off_confirmed("guardian reconnected")  # arming is never restored
            self.error = None
            log.warning("laser guardian link back; all channels off, not armed")
        except (GuardianError, LasersNotOff, OSError) as exc:
            self.error = f"laser guardian unreachable: {exc}"
            if self.client is not None:
                self.client.close()
                self.client = None

    # -- commands ------------------------------------------------------------------------------

    def _require(self) -> GuardianClient:
        if not self.present:
            raise RpcError(NOT_AVAILABLE, "no laser configured (devices.laser = 'none')",
                           {"device": "laser"})
        if self.client is None:
            raise RpcError(LASER_REFUSED, self.error or "laser guardian not connected",
                           {"device": "laser"})
        return self.client

    def _call(self, op: str, **params: Any) -> dict[str, Any]:
        with self._lock:
            return self._call_locked(op, **params)

    def _call_locked(self, op: str, **params: Any) -> dict[str, Any]:
        client = self._require()
        try:
            reply = client.call(op, **params)
        except GuardianUnavailable as exc:
            self._lost(str(exc))
            raise RpcError(LASER_REFUSED, str(exc), {"device": "laser"}) from None
        except GuardianError as exc:
            raise RpcError(LASER_REFUSED, str(exc), {"device": "laser"}) from None
        finally:
            with contextlib.suppress(RpcError, GuardianError):
                if self.client is not None:
                    self.refresh()
        return reply

    def arm(self, duration_s: float) -> dict[str, Any]:
        self._call("heartbeat")
        return self._call("arm", duration_s=duration_s)

    def disarm(self) -> None:
        self._call("disarm")

    def off(self) -> None:
        self._call("off")

    def power(self, channel: str, power_pct: float) -> float:
        return float(self._call("power", channel=channel, power_pct=power_pct)["power_pct"])

    def enable(self, channel: str, on: bool) -> None:
        self._call("enable", channel=channel, on=on)

    def status(self) -> dict[str, Any]:
        if not self.present:
            return {"backend": "none"}
        return {
            "backend": self.backend,
            "guardian": {"socket": str(self.socket_path), "connected": self.client is not None,
                         "spawned_pid": self.proc.pid if self.proc else None},
            "armed": bool(self._beat.get("armed", False)),
            "armed_remaining_s": self._beat.get("armed_remaining_s", 0.0),
            "fault": self._beat.get("fault"),
            "channels": self._channels,
            "channels_read_s_ago": round(time.monotonic() - self._read_at, 3),
            "max_power_pct": list(self.settings.max_power_pct),
            "error": self.error,
        }
