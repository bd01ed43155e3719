"""Navigator input: a 6-DoF puck moves the view continuously through the `set_view` path.

Every `daemon.bench.navigator_period_s` the control loop reads the navigator's velocities and turns
them into a relative move of the current view over the time since the last read: for an orbit,
yaw changes the azimuth, pitch the elevation and the z translation the radius; for a pose, the
camera-frame translation and rotation. The move goes through the same validation
(`views.parse_view`) and the same latest-wins `ViewSlot` as a client's `set_view`, so the frame
worker sees no difference and the sequence number advances. The navigator never supplies the
first view: it moves whatever a client (or the demo) set.

The read happens on the control loop: the simulated navigator is a table look-up and the
SpaceMouse reads non-blocking HID reports for at most `devices.spacemouse.read_timeout_ms`, far
below the laser heartbeat's timeout.
"""

from __future__ import annotations

import logging
from typing import Any

from nhfd.config import DeviceSettings
from nhfd.drivers import factory
from nhfd.drivers.navigator import Waypoint
from nhfd.views import Orbit, View

from .audit import AuditLog
from .protocol import Params, RpcError
from .recording import SessionRecorder
from .views import ELEVATION_DEG, ViewSlot, parse_view

log = logging.getLogger("nhfd.daemon.navigation")

WHO = {"who": "navigator"}
# How often a navigator that stopped answering (unplugged) is opened again (s).
RECONNECT_S = 1.0
# The simulated navigator's script (devices.navigator = "simulated"): yaw right at half
# deflection for 2 s, left for 4 s, right for 2 s (back where it began), then rest.
HALF = 175
SIMULATED_SCRIPT = (
    Waypoint(0.0, (0, 0, 0, 0, HALF, 0)),
    Waypoint(2.0, (0, 0, 0, 0, -HALF, 0)),
    Waypoint(6.0, (0, 0, 0, 0, HALF, 0)),
    Waypoint(8.0, (0, 0, 0, 0, 0, 0)),
)


def relative_move(view: View, reading: Any, dt_s: float) -> dict[str, Any] | None:
    """The `relative` parameters that move `view` by the reading's velocities over dt_s (None
    when the puck rests)."""
    t = [v * dt_s for v in reading.translation_m_s]
    r = [v * dt_s for v in reading.rotation_deg_s]
    if not any(t) and not any(r):
        return None
    cam = view.camera
    if isinstance(cam, Orbit):
        # Keep inside the elevation range rather than refuse the whole move at the pole.
        elevation = min(max(cam.elevation_deg + r[0], ELEVATION_DEG[0]), ELEVATION_DEG[1])
        d_radius = max(t[2], -0.5 * cam.radius)  # never through the centre
        return {"d_azimuth_deg": r[1], "d_elevation_deg": elevation - cam.elevation_deg,
                "d_radius": d_radius}
    return {"translate": t, "rotate_deg": r}


class NavigatorInput:
    """The navigator, read from the control loop: its motion moves the current view through
    the view slot, each move audited and recorded as a client's set_view is."""

    def __init__(self, devices: DeviceSettings, period_s: float, views: ViewSlot,
                 audit: AuditLog, recorder: SessionRecorder) -> None:
        """`devices`: `[devices]` (which navigator, and the SpaceMouse's settings).
        `period_s`: how often it is read (`daemon.bench.navigator_period_s`). `views`: the slot its
        moves go to (the current view read from it). `audit`, `recorder`: where each move is
        written, as the navigator's (`WHO`)."""
        self.devices = devices
        self.period_s = period_s
        self.views = views
        self.audit = audit
        self.recorder = recorder
        self.navigator: Any = None
        self.error: str | None = None
        self.moves = 0
        self.last_seq: int | None = None
        self._last_s: float | None = None
        self._next_s = 0.0
        self._retry_s = 0.0  # when a lost navigator is opened again (monotonic s)

    def open(self) -> None:
        """Open the configured navigator; one that fails is left out (`status` says why)."""
        try:
            self.navigator = factory.make_navigator(self.devices, SIMULATED_SCRIPT)
            if self.navigator is not None:
                self.navigator.open()
        except Exception as exc:  # the daemon runs on without it; status says why
            self.error = f"{type(exc).__name__}: {exc}"
            self.navigator = None
            log.error("navigator: %s", self.error)

    def close(self) -> None:
        """Close the navigator (an error only logged: the daemon is on its way out)."""
        if self.navigator is not None:
            try:
                self.navigator.close()
            except Exception as exc:
                log.warning("navigator close: %s", exc)
            self.navigator = None

    @property
    def next_read_s(self) -> float:
        """Monotonic time of the next read (the control loop sleeps no longer than this)."""
        return self._next_s

    def step(self, now: float) -> None:
        """From the control loop, every tick; reads at most every navigator_period_s."""
        if self.navigator is None or now < self._next_s:
            return
        self._next_s = now + self.period_s
        try:
            reading = self.navigator.read()
            self.error = None
        except Exception as exc:  # unplugged: say so, and open it again once it is back
            self.error = f"{type(exc).__name__}: {exc}"
            self._last_s = None
            if now >= self._retry_s:
                self._retry_s = now + RECONNECT_S
                try:
                    self.navigator.reconnect()  # starts at rest: no stale deflection
                except Exception as again:
                    self.error += f"; reconnecting: {type(again).__name__}: {again}"
            return
        last, self._last_s = self._last_s, now
        current = self.views.view
        if last is None or current is None:
            return
        rel = relative_move(current, reading, now - last)
        if rel is None:
            return
        try:
            view = parse_view(Params({"relative": rel}), current)  # keeps the refocus
        except RpcError as exc:  # e.g. a pose that would leave the coordinate range
            self.error = f"move refused: {exc.message}"
            return
        seq = self.views.submit(view)
        shown = view.to_json()
        self.audit.view(WHO, seq, shown)
        self.recorder.record_request("set_view", {}, WHO, {"view": shown})
        self.moves += 1
        self.last_seq = seq

    def status(self) -> dict[str, Any]:
        """`status.navigator`: the backend, whether it is open, its moves and last error."""
        return {"backend": self.devices.navigator, "open": self.navigator is not None,
                "moves": self.moves, "last_seq": self.last_seq, "error": self.error,
                "period_s": self.period_s}
