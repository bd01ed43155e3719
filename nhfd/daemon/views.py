"""View requests: validation into a normalised view, relative moves, latest-wins coalescing.

A view is one of
  {"kind": "orbit", "azimuth_deg", "elevation_deg", "radius"}   about the scene's centre
  {"kind": "pose", "position": [x, y, z], "quaternion_wxyz": [w, x, y, z]}
in scene units, OpenCV camera axes, the quaternion being camera-to-world (as in
`nhfd.scene.cameras.pose_from_quaternion`). A relative move changes the current view in its own
kind: orbit deltas for an orbit, a camera-frame translation and rotation for a pose.

`ViewSlot` keeps only the newest request: the frame worker (later) takes the latest and skips
whatever was overtaken, so a burst of requests costs one frame, and the sequence number tells a
client which request the bench shows. Pure Python: no numpy needed for a handful of numbers.
"""

from __future__ import annotations

import math
import threading
from typing import Any

from .protocol import Params, bad_param

AZIMUTH_DEG = (-360.0, 360.0)
ELEVATION_DEG = (-89.9, 89.9)
RADIUS = (0.0, 1e6)  # scene units; open at 0
COORD = (-1e6, 1e6)
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


def parse_view(params: Params, current: dict[str, Any] | None) -> dict[str, Any]:
    """Exactly one of `orbit`, `pose`, `relative`; returns the normalised absolute view."""
    given = [k for k in ("orbit", "pose", "relative") if params.has(k)]
    if len(given) != 1:
        raise bad_param("orbit|pose|relative", f"got {len(given)} of them",
                        "exactly one of orbit, pose, relative")
    kind = given[0]
    sub = params.obj(kind)
    assert sub is not None
    if kind == "orbit":
        view = {"kind": "orbit",
                "azimuth_deg": _wrap_deg(sub.number("azimuth_deg", *AZIMUTH_DEG)),
                "elevation_deg": sub.number("elevation_deg", *ELEVATION_DEG),
                "radius": sub.number("radius", *RADIUS, low_open=True)}
    elif kind == "pose":
        position = sub.vector("position", 3, *COORD)
        q = _normalised("pose.quaternion_wxyz", sub.vector("quaternion_wxyz", 4, -2.0, 2.0))
        view = {"kind": "pose", "position": position, "quaternion_wxyz": q}
    else:
        view = _relative(sub, current)
    sub.done()
    params.done()
    return view


def _relative(sub: Params, current: dict[str, Any] | None) -> dict[str, Any]:
    if current is None:
        raise bad_param("relative", "there is no current view to move from",
                        "an absolute orbit or pose first")
    if current["kind"] == "orbit":
        d_az = sub.number("d_azimuth_deg", *AZIMUTH_DEG, default=0.0)
        d_el = sub.number("d_elevation_deg", -180.0, 180.0, default=0.0)
        d_r = sub.number("d_radius", -RADIUS[1], RADIUS[1], default=0.0)
        elevation = current["elevation_deg"] + d_el
        radius = current["radius"] + d_r
        if not ELEVATION_DEG[0] <= elevation <= ELEVATION_DEG[1]:
            raise bad_param("relative.d_elevation_deg", f"would give elevation {elevation:g}",
                            f"[{ELEVATION_DEG[0] - current['elevation_deg']:g}, "
                            f"{ELEVATION_DEG[1] - current['elevation_deg']:g}] from here")
        if not 0 < radius <= RADIUS[1]:
            raise bad_param("relative.d_radius", f"would give radius {radius:g}",
                            f"(-{current['radius']:g}, {RADIUS[1] - current['radius']:g}]")
        return {"kind": "orbit", "azimuth_deg": _wrap_deg(current["azimuth_deg"] + d_az),
                "elevation_deg": elevation, "radius": radius}
    translate = sub.vector("translate", 3, *COORD, default=[0.0, 0.0, 0.0])
    rotate = sub.vector("rotate_deg", 3, *ROTATE_DEG, default=[0.0, 0.0, 0.0])
    q = list(current["quaternion_wxyz"])
    position = [p + d for p, d in zip(current["position"], _qrotate(q, translate), strict=True)]
    # Camera-frame rotation: pitch about x, yaw about y (down), roll about z (forward).
    for axis, angle in enumerate(rotate):
        if angle:
            q = _qmul(q, _q_axis_angle(axis, angle))
    if any(not COORD[0] <= p <= COORD[1] for p in position):
        raise bad_param("relative.translate", "would leave the scene's coordinate range",
                        f"positions in [{COORD[0]:g}, {COORD[1]:g}]")
    return {"kind": "pose", "position": position,
            "quaternion_wxyz": _normalised("relative.rotate_deg", q)}


class ViewSlot:
    """The newest requested view and its sequence number; older ones are overtaken."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.seq = 0
        self.view: dict[str, Any] | None = None
        self.applied_seq: int | None = None  # set by the frame worker once shown
        self.overtaken = 0  # requests replaced before any worker took them

    def submit(self, view: dict[str, Any]) -> int:
        with self._cond:
            if self.view is not None and (self.applied_seq or 0) < self.seq:
                self.overtaken += 1
            self.seq += 1
            self.view = view
            self._cond.notify_all()
            return self.seq

    def latest_after(self, seq: int, timeout_s: float) -> tuple[int, dict[str, Any]] | None:
        """For the frame worker: the newest view with a sequence number above `seq`."""
        with self._cond:
            if not self._cond.wait_for(lambda: self.seq > seq, timeout_s) or self.view is None:
                return None
            return self.seq, self.view

    def mark_applied(self, seq: int) -> None:
        with self._cond:
            self.applied_seq = max(seq, self.applied_seq or 0)

    def snapshot(self) -> dict[str, Any]:
        with self._cond:
            return {"seq": self.seq, "requested": self.view, "applied_seq": self.applied_seq,
                    "overtaken": self.overtaken}
