"""A view of the scene -> the render camera: orbit and pose views (`nhfd.views.View`, parsed at
the daemon's edge), the scene's frame they are relative to, and whether a view lies inside the
poses the model was trained on (`nhfd.model_info.PoseEnvelope`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.model_info import ModelInfo, PoseEnvelope
from nhfd.scene.cameras import Camera, orbit, pose_from_quaternion
from nhfd.scene.io import read_scene
from nhfd.scene.suggest import detect_up_axis, format_hint, suggest_camera
from nhfd.views import Orbit, View

# Envelope checks allow this much beyond the trained range before warning (a view at the edge of
# the training poses is still a trained view).
ENVELOPE_SLACK_DEG = 1.0
ENVELOPE_SLACK_FRACTION = 0.02
# The field of view across the window of a scene served without a model (the model build's).
SCENE_FOV_X_DEG = 40.0
# A scene without a model, by default: an orbit at this azimuth and elevation (deg), at this
# multiple of the distance `nhfd scene info` suggests (its framing fills 80% of the window: a
# little farther keeps the whole object inside the window's edge, which refinement's loss
# leaves out).
NO_MODEL_VIEW = (0.0, 15.0, 1.5)


@dataclass(frozen=True)
class SceneFrame:
    """What orbit views are relative to: the scene's centre and up axis (as the dataset builder
    chose them: the median of the means and the detected up axis)."""

    center: tuple[float, float, float]
    up: str


@dataclass(frozen=True)
class Scene:
    """A loaded scene as frames use it: its Gaussians and the frame orbit views are relative to.
    `on_device`: the Gaussians uploaded to a CUDA device for gsplat, once per device (keyed by
    its name; filled by `nhfd.pipeline.frame`), not once per frame."""

    gaussians: Any
    frame: SceneFrame
    on_device: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)


def scene_frame(g: Any, path: str | None = None) -> SceneFrame:
    """The scene frame of Gaussians `g`: the median of the means [3] (origin when empty) and the
    up axis detected from the data and the file's format (`path`)."""
    up = detect_up_axis(g, format_hint(path) if path else None)[0]
    center = np.median(g.means, axis=0) if len(g) else np.zeros(3)
    return SceneFrame(tuple(float(v) for v in center), up)  # type: ignore[arg-type]


def scene_from_file(path: str | Path) -> Scene:
    """A splat scene as frames use it (its Gaussians and the frame orbit views are about)."""
    load = read_scene(path)
    return Scene(load.gaussians, scene_frame(load.gaussians, str(path)))


def suggested_radius(scene: Scene, window_hw: tuple[int, int], azimuth_deg: float,
                     elevation_deg: float) -> float:
    """The orbit radius at which `nhfd scene info`'s camera frames the scene in the window
    (h, w px) through a SCENE_FOV_X_DEG camera (a scene without a model's)."""
    h, w = window_hw
    cam = suggest_camera(scene.gaussians, w, h, scene.frame.up, fov_x_deg=SCENE_FOV_X_DEG,
                         azimuth_deg=azimuth_deg, elevation_deg=elevation_deg)
    position = -cam.R.T @ cam.t
    return float(np.linalg.norm(position - np.asarray(scene.frame.center)))


def default_view(scene: Scene, info: ModelInfo | None, window_hw: tuple[int, int]) -> View:
    """The middle of the model's pose envelope; without a model (or an envelope), an orbit at
    NO_MODEL_VIEW."""
    env = info.pose_envelope if info is not None else None
    if env is not None and env.azimuth_deg and env.elevation_deg and env.distance:
        return View(Orbit(sum(env.azimuth_deg) / 2, sum(env.elevation_deg) / 2,
                          sum(env.distance) / 2))
    az, el, k = NO_MODEL_VIEW
    return View(Orbit(az, el, k * suggested_radius(scene, window_hw, az, el)))


def view_pose(view: View, frame: SceneFrame) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera `(R [3, 3], t [3])` of a view, in scene units: an orbit about the
    scene frame's centre and up axis, or the pose as given."""
    cam = view.camera
    if isinstance(cam, Orbit):
        return orbit(np.array(frame.center), cam.azimuth_deg, cam.elevation_deg, cam.radius,
                     frame.up)
    return pose_from_quaternion(np.array(cam.position), np.array(cam.quaternion_wxyz))


def render_camera(view: View, frame: SceneFrame, info: ModelInfo, window_hw: tuple[int, int]
                  ) -> Camera:
    """The central camera for a `window_hw` (h, w px) window: the model's trained focal lengths
    (`ModelInfo.focal_px`: a pixel subtends the angle it was trained on), centred on the window;
    the near plane at 1% of the distance to the centre, as the dataset builder sets it."""
    r, t = view_pose(view, frame)
    h, w = window_hw
    fx, fy = info.focal_px()
    position = -r.T @ t
    distance = float(np.linalg.norm(position - np.array(frame.center)))
    return Camera(r, t, fx, fy, w / 2, h / 2, w, h, near=max(0.01 * distance, 1e-9))


def envelope_warnings(view: View, frame: SceneFrame, envelope: PoseEnvelope | None
                      ) -> list[str]:
    """Why a view lies outside the model's pose envelope (empty when inside or unknown)."""
    if envelope is None:
        return []
    out: list[str] = []
    r, t = view_pose(view, frame)
    position = -r.T @ t
    distance = float(np.linalg.norm(position - np.array(frame.center)))

    def check(name: str, value: float, bounds: tuple[float, float] | None, slack: float,
              unit: str) -> None:
        if bounds and not bounds[0] - slack <= value <= bounds[1] + slack:
            out.append(f"{name} {value:.3g}{unit} is outside the model's trained range "
                       f"[{bounds[0]:.3g}, {bounds[1]:.3g}]{unit}")

    cam = view.camera
    if isinstance(cam, Orbit):
        check("azimuth", cam.azimuth_deg, envelope.azimuth_deg, ENVELOPE_SLACK_DEG, " deg")
        check("elevation", cam.elevation_deg, envelope.elevation_deg, ENVELOPE_SLACK_DEG,
              " deg")
    dist = envelope.distance
    if dist:
        check("distance to the scene centre", distance, dist,
              ENVELOPE_SLACK_FRACTION * dist[1], "")
    lo, hi = envelope.position_min, envelope.position_max
    if not isinstance(cam, Orbit) and lo and hi:
        span = max(float(np.max(np.subtract(hi, lo))), 1e-12)
        slack = ENVELOPE_SLACK_FRACTION * span
        if any(not a - slack <= p <= b + slack for p, a, b in zip(position, lo, hi, strict=True)):
            out.append("camera position is outside the box of the trained positions")
    return out
