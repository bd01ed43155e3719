"""View requests: parsing into a `nhfd.views.View` (the RPC edge: every value checked here, with
the messages clients see), relative moves, latest-wins coalescing.

A request gives one of
  orbit    {azimuth_deg, elevation_deg, radius}          about the scene's centre
  pose     {position: [x, y, z], quaternion_wxyz: [w, x, y, z]}
  relative {d_azimuth_deg, d_elevation_deg, d_radius} or {translate, rotate_deg}
and optionally refocus_mm, in scene units, OpenCV camera axes, the quaternion being
camera-to-world (as in `nhfd.scene.cameras.pose_from_quaternion`). A relative move changes the
current view in its own kind: orbit deltas for an orbit, a camera-frame translation and rotation
for a pose. The result is a `View` (frozen): the daemon, the frame link and the frame worker use
it typed; `View.to_json` is what `status`, the audit log and `set_view`'s reply show.

`ViewSlot` keeps only the newest request: the frame worker (later) takes the latest and skips
whatever was overtaken, so a burst of requests costs one frame, and the sequence number tells a
client which request the bench shows. Pure Python: no numpy needed for a handful of numbers.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import Any

from nhfd.views import (
    AZIMUTH_DEG,
    COORD,
    ELEVATION_DEG,
    QUALITY_TIERS,
    RADIUS,
    REFOCUS_MM,
    Orbit,
    Pose,
    View,
)

from .protocol import Params, bad_param

__all__ = ["AZIMUTH_DEG", "COORD", "ELEVATION_DEG", "RADIUS", "REFOCUS_MM", "ROTATE_DEG",
           "ViewSlot", "parse_view"]

ROTATE_DEG = (-360.0, 360.0)


def _wrap_deg(a: float) -> float:
    """Into (-180, 180]."""
    a = math.fmod(a, 360.0)
    if a <= -180.0:
        a += 360.0
    elif a > 180.0:
        a -= 360.0
    return a


def _qmul(a: list[float], b: list[float]) -> list[float]:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return [aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw]


def _qrotate(q: list[float], v: list[float]) -> list[float]:
    _w, x, y, z = _qmul(_qmul(q, [0.0, *v]), [q[0], -q[1], -q[2], -q[3]])
    return [x, y, z]


def _q_axis_angle(axis: int, angle_deg: float) -> list[float]:
    half = math.radians(angle_deg) / 2
    q = [math.cos(half), 0.0, 0.0, 0.0]
    q[1 + axis] = math.sin(half)
    return q


def _normalised(name: str, q: list[float]) -> list[float]:
    norm = math.sqrt(sum(c * c for c in q))
    if not 0.5 <= norm <= 2.0:
        raise bad_param(name, f"norm {norm:.3g} is not near 1",
                        "a quaternion [w, x, y, z] with norm in [0.5, 2] (it is normalised)")
    return [c / norm for c in q]


def parse_view(params: Params, current: View | None, default_quality: str = "network") -> View:
    """Exactly one of `orbit`, `pose`, `relative`, `refocus_mm` (mm, + toward the viewer;
    absent: the current view's, or 0) and `quality` (one of QUALITY_TIERS; absent: the current
    view's, or `default_quality`, `refine.quality`): the absolute view, azimuth wrapped into
    (-180, 180] and quaternions normalised. RpcError (invalid params) naming the parameter
    otherwise."""
    # Read first: its error comes before the view's, as when set_view read it itself.
    refocus = params.number("refocus_mm", *REFOCUS_MM, default=None)
    quality = params.choice("quality", QUALITY_TIERS, default=None)
    given = [k for k in ("orbit", "pose", "relative") if params.has(k)]
    if len(given) != 1:
        raise bad_param("orbit|pose|relative", f"got {len(given)} of them",
                        "exactly one of orbit, pose, relative")
    kind = given[0]
    sub = params.obj(kind)
    assert sub is not None
    if kind == "orbit":
        camera: Orbit | Pose = Orbit(_wrap_deg(sub.number("azimuth_deg", *AZIMUTH_DEG)),
                                     sub.number("elevation_deg", *ELEVATION_DEG),
                                     sub.number("radius", *RADIUS, low_open=True))
    elif kind == "pose":
        position = sub.vector("position", 3, *COORD)
        q = _normalised("pose.quaternion_wxyz", sub.vector("quaternion_wxyz", 4, -2.0, 2.0))
        camera = Pose(tuple(position), tuple(q))  # type: ignore[arg-type]
    else:
        camera = _relative(sub, current)
    sub.done()
    params.done()
    # Digital refocus travels with the view; it stays as it was when not given.
    if refocus is None:
        refocus = current.refocus_mm if current is not None else 0.0
    if quality is None:
        quality = current.quality if current is not None else default_quality
    return View(camera, refocus, quality)


def _relative(sub: Params, current: View | None) -> Orbit | Pose:
    if current is None:
        raise bad_param("relative", "there is no current view to move from",
                        "an absolute orbit or pose first")
    cam = current.camera
    if isinstance(cam, Orbit):
        d_az = sub.number("d_azimuth_deg", *AZIMUTH_DEG, default=0.0)
        d_el = sub.number("d_elevation_deg", -180.0, 180.0, default=0.0)
        d_r = sub.number("d_radius", -RADIUS[1], RADIUS[1], default=0.0)
        elevation = cam.elevation_deg + d_el
        radius = cam.radius + d_r
        if not ELEVATION_DEG[0] <= elevation <= ELEVATION_DEG[1]:
            raise bad_param("relative.d_elevation_deg", f"would give elevation {elevation:g}",
                            f"[{ELEVATION_DEG[0] - cam.elevation_deg:g}, "
                            f"{ELEVATION_DEG[1] - cam.elevation_deg:g}] from here")
        if not 0 < radius <= RADIUS[1]:
            raise bad_param("relative.d_radius", f"would give radius {radius:g}",
                            f"(-{cam.radius:g}, {RADIUS[1] - cam.radius:g}]")
        return Orbit(_wrap_deg(cam.azimuth_deg + d_az), elevation, radius)
    translate = sub.vector("translate", 3, *COORD, default=[0.0, 0.0, 0.0])
    rotate = sub.vector("rotate_deg", 3, *ROTATE_DEG, default=[0.0, 0.0, 0.0])
    q = list(cam.quaternion_wxyz)
    position = [p + d for p, d in zip(cam.position, _qrotate(q, translate), strict=True)]
    # Camera-frame rotation: pitch about x, yaw about y (down), roll about z (forward).
    for axis, angle in enumerate(rotate):
        if angle:
            q = _qmul(q, _q_axis_angle(axis, angle))
    if any(not COORD[0] <= p <= COORD[1] for p in position):
        raise bad_param("relative.translate", "would leave the scene's coordinate range",
                        f"positions in [{COORD[0]:g}, {COORD[1]:g}]")
    return Pose(tuple(position), tuple(_normalised("relative.rotate_deg", q)))  # type: ignore[arg-type]


class ViewSlot:
    """The newest requested view, its sequence number and the emission session it was asked in
    (`session()` at the request: a citl view's captures belong to it); older ones are
    overtaken."""

    def __init__(self, session: Callable[[], int] = lambda: 0) -> None:
        self._cond = threading.Condition()
        self._session_now = session
        self.seq = 0
        self.view: View | None = None
        self.session = 0  # the emission session of the newest view's request
        self.applied_seq: int | None = None  # set by the frame worker once shown
        self.overtaken = 0  # requests replaced before any worker took them

    def submit(self, view: View) -> int:
        """Make `view` the newest, in the emission session now; returns its sequence number (a view
        not yet shown is overtaken)."""
        with self._cond:
            if self.view is not None and (self.applied_seq or 0) < self.seq:
                self.overtaken += 1
            self.seq += 1
            self.view = view
            self.session = self._session_now()
            self._cond.notify_all()
            return self.seq

    def latest_after(self, seq: int, timeout_s: float) -> tuple[int, View] | None:
        """For the frame worker: the newest view with a sequence number above `seq`."""
        with self._cond:
            if not self._cond.wait_for(lambda: self.seq > seq, timeout_s) or self.view is None:
                return None
            return self.seq, self.view

    def mark_applied(self, seq: int) -> None:
        """The frame worker has shown view `seq` (or a newer one)."""
        with self._cond:
            self.applied_seq = max(seq, self.applied_seq or 0)

    def snapshot(self) -> dict[str, Any]:
        """The slot for `status`: the newest sequence number, its view (JSON), the last shown and
        how many were overtaken."""
        with self._cond:
            return {"seq": self.seq,
                    "requested": None if self.view is None else self.view.to_json(),
                    "applied_seq": self.applied_seq, "overtaken": self.overtaken}
