"""A view of the scene as a value (layer L0): where the camera is, and the digital refocus.

A view is parsed once where it enters (the daemon's `set_view`, `nhfd.daemon.views.parse_view`;
a recorded or scripted view, `view_from_json`) and travels typed from there: through the
daemon's latest-wins slot, across the pipe to the frame worker, into the render camera. Its JSON
form (`View.to_json`) is what `status`, the audit log, the session recording and `set_view`'s
reply show, unchanged from when views were plain dicts:

  {"kind": "orbit", "azimuth_deg", "elevation_deg", "radius", "refocus_mm"}   about the centre
  {"kind": "pose", "position": [x, y, z], "quaternion_wxyz": [w, x, y, z], "refocus_mm"}

in scene units, OpenCV camera axes, the quaternion camera-to-world (as in
`nhfd.scene.cameras.pose_from_quaternion`). Standard library only: the daemon's control plane and
`nhfctl` load it.

The constructors check ranges and raise ValueError naming the value and its range; they never
change a value (no wrapping, no normalising: the RPC edge does that, with its own messages),
so a view means the same numbers wherever it goes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

# The ranges a view may take (the RPC edge's ranges too: `set_view` refuses outside them).
AZIMUTH_DEG = (-360.0, 360.0)
ELEVATION_DEG = (-89.9, 89.9)
RADIUS = (0.0, 1e6)  # scene units; open at 0
COORD = (-1e6, 1e6)  # scene units, each coordinate of a pose's position
REFOCUS_MM = (-10.0, 10.0)  # digital refocus, mm, + toward the viewer
# The frame tiers a view may ask for, cheapest first (`nhfd.pipeline.refine`): the network's
# double-phase frame; the view's light-field inversion (no network); the SLM phase optimised
# through the calibrated bench model; the same with the bench's camera in the loop. Above
# "network" the daemon shows the network's frame at once and better ones while the view rests.
QUALITY_TIERS = ("network", "exact", "sgd", "citl")
# How far from 1 a pose's quaternion norm may be: the RPC edge normalises (its result is within
# a few ulp of 1); a quaternion off by more was never normalised, and its rotation would scale.
QUATERNION_NORM_TOL = 1e-6


def _finite_in(name: str, value: Any, lo: float, hi: float, unit: str, *,
               low_open: bool = False) -> None:
    ok = (isinstance(value, int | float) and not isinstance(value, bool)
          and math.isfinite(value) and (value > lo if low_open else value >= lo) and value <= hi)
    if not ok:
        span = f"{'(' if low_open else '['}{lo:g}, {hi:g}]"
        raise ValueError(f"view {name} = {value!r}: expected a finite number in {span}"
                         + (f" {unit}" if unit else ""))


@dataclass(frozen=True)
class Orbit:
    """A camera on a sphere about the scene's centre, looking at it: azimuth and elevation in
    degrees about the scene's up axis, radius in scene units."""

    azimuth_deg: float
    elevation_deg: float
    radius: float

    kind = "orbit"  # the JSON form's tag (a class attribute, not a field)

    def __post_init__(self) -> None:
        _finite_in("azimuth_deg", self.azimuth_deg, *AZIMUTH_DEG, "deg")
        _finite_in("elevation_deg", self.elevation_deg, *ELEVATION_DEG, "deg")
        _finite_in("radius", self.radius, *RADIUS, "scene units", low_open=True)

    def to_json(self) -> dict[str, Any]:
        """{"kind": "orbit", "azimuth_deg", "elevation_deg", "radius"}."""
        return {"kind": self.kind, "azimuth_deg": self.azimuth_deg,
                "elevation_deg": self.elevation_deg, "radius": self.radius}


@dataclass(frozen=True)
class Pose:
    """A camera anywhere: `position` (x, y, z) in scene units and its camera-to-world rotation
    as a unit quaternion (w, x, y, z)."""

    position: tuple[float, float, float]
    quaternion_wxyz: tuple[float, float, float, float]

    kind = "pose"

    def __post_init__(self) -> None:
        # Tuples whatever sequence was given: the view is hashable (the worker's frame cache
        # keys on it) and cannot change under its holder.
        object.__setattr__(self, "position", tuple(self.position))
        object.__setattr__(self, "quaternion_wxyz", tuple(self.quaternion_wxyz))
        if len(self.position) != 3:
            raise ValueError(f"view position = {list(self.position)}: expected 3 coordinates "
                             f"[x, y, z] in [{COORD[0]:g}, {COORD[1]:g}] scene units")
        for i, p in enumerate(self.position):
            _finite_in(f"position[{i}]", p, *COORD, "scene units")
        q = self.quaternion_wxyz
        if len(q) != 4 or not all(isinstance(c, int | float) and math.isfinite(c) for c in q):
            raise ValueError(f"view quaternion_wxyz = {list(q)}: expected 4 finite numbers "
                             "[w, x, y, z]")
        norm = math.sqrt(sum(c * c for c in q))
        if abs(norm - 1.0) > QUATERNION_NORM_TOL:
            raise ValueError(f"view quaternion_wxyz = {list(q)}: norm {norm:.9g}, expected a "
                             f"unit quaternion (norm within {QUATERNION_NORM_TOL:g} of 1)")

    def to_json(self) -> dict[str, Any]:
        """{"kind": "pose", "position": [x, y, z], "quaternion_wxyz": [w, x, y, z]}."""
        return {"kind": self.kind, "position": list(self.position),
                "quaternion_wxyz": list(self.quaternion_wxyz)}


@dataclass(frozen=True)
class View:
    """One requested view: where the camera is (`camera`, an `Orbit` or a `Pose`), the
    digital refocus in mm (+ toward the viewer: the reference plane moves by refocus_mm) and the
    frame tier asked for (`QUALITY_TIERS`)."""

    camera: Orbit | Pose
    refocus_mm: float = 0.0
    quality: str = "network"

    def __post_init__(self) -> None:
        if not isinstance(self.camera, Orbit | Pose):
            raise ValueError(f"view camera = {self.camera!r}: expected an Orbit or a Pose")
        _finite_in("refocus_mm", self.refocus_mm, *REFOCUS_MM, "mm")
        if self.quality not in QUALITY_TIERS:
            raise ValueError(f"view quality = {self.quality!r}: expected one of "
                             f"{', '.join(QUALITY_TIERS)}")

    @property
    def kind(self) -> str:
        """"orbit" or "pose"."""
        return self.camera.kind

    @property
    def refocus_m(self) -> float:
        """The refocus in metres, as the frame settings take it."""
        return self.refocus_mm * 1e-3

    def with_refocus(self, refocus_mm: float) -> View:
        """The same camera, refocused to `refocus_mm` (mm)."""
        return replace(self, refocus_mm=refocus_mm)

    def with_quality(self, quality: str) -> View:
        """The same camera and refocus at another tier."""
        return replace(self, quality=quality)

    def describe(self) -> str:
        """The view in words, for people: "orbit azimuth 30 deg, elevation 10 deg, radius 4",
        then the refocus and the tier when they are not 0 and "network"."""
        c = self.camera
        if isinstance(c, Orbit):
            words = (f"orbit azimuth {c.azimuth_deg:g} deg, elevation {c.elevation_deg:g} deg, "
                     f"radius {c.radius:g}")
        else:
            words = (f"pose at ({', '.join(f'{v:g}' for v in c.position)}), quaternion "
                     f"({', '.join(f'{v:g}' for v in c.quaternion_wxyz)})")
        if self.refocus_mm:
            words += f", refocus {self.refocus_mm:+g} mm"
        if self.quality != "network":
            words += f", quality {self.quality}"
        return words

    def to_json(self) -> dict[str, Any]:
        """The plain form `status`, the audit log and `set_view`'s reply show (`quality` only
        above "network", so open-loop views read as they always did)."""
        out = {**self.camera.to_json(), "refocus_mm": self.refocus_mm}
        if self.quality != "network":
            out["quality"] = self.quality
        return out


def view_from_json(data: dict[str, Any]) -> View:
    """A view from its JSON form (`View.to_json`; `refocus_mm` may be absent: 0, `quality`:
    "network"). ValueError
    naming the key for a kind or a key that is missing; the constructors check the values."""
    if not isinstance(data, dict):
        raise ValueError(f"view = {data!r}: expected an object with kind orbit or pose")
    kind = data.get("kind")
    try:
        if kind == "orbit":
            camera: Orbit | Pose = Orbit(data["azimuth_deg"], data["elevation_deg"],
                                         data["radius"])
        elif kind == "pose":
            camera = Pose(data["position"], data["quaternion_wxyz"])
        else:
            raise ValueError(f"view kind = {kind!r}: expected \"orbit\" or \"pose\"")
    except KeyError as exc:
        raise ValueError(f"view: a {kind} view needs {exc.args[0]}") from None
    return View(camera, data.get("refocus_mm", 0.0), data.get("quality", "network"))
