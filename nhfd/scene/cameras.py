"""Pinhole cameras and poses, OpenCV conventions (docs/physics.md, "Units and names").

x right, y down, z forward; a pose is world-to-camera `[R | t]` (a point `X` in world units maps
to `R X + t` in camera units); intrinsics `fx, fy, cx, cy` are in pixels, with the pixel `(i, j)`
centred at `(j + 0.5, i + 0.5)` (so `cx = W / 2` puts the optical axis at the image centre).
Rotations are float64: they are composed and inverted, and float32 drifts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

AXES = {
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),
}


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: pose (world-to-camera), intrinsics in pixels, image size, clip range.

    `near` and `far` are depths along the optical axis in scene units; Gaussians whose centre lies
    outside `[near, far]` are culled.
    """

    R: np.ndarray
    t: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width_px: int
    height_px: int
    near: float = 0.01
    far: float = 1e10

    def __post_init__(self) -> None:
        r = np.asarray(self.R, np.float64)
        t = np.asarray(self.t, np.float64).reshape(3)
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
            raise ValueError("Camera.R must be a 3x3 rotation matrix")
        if not np.isfinite(t).all():
            raise ValueError(f"Camera.t must be finite, got {t}")
        object.__setattr__(self, "R", r)
        object.__setattr__(self, "t", t)
        for name in ("fx", "fy"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"Camera.{name} must be a positive focal length in px, got {v}")
        for name in ("cx", "cy"):
            if not math.isfinite(float(getattr(self, name))):
                raise ValueError(f"Camera.{name} must be finite")
        if int(self.width_px) < 1 or int(self.height_px) < 1:
            raise ValueError(
                f"image size must be at least 1 x 1 px, got {self.width_px} x {self.height_px}"
            )
        if not (0 < self.near < self.far):
            raise ValueError(f"need 0 < near < far, got near={self.near}, far={self.far}")

    @property
    def position(self) -> np.ndarray:
        """Camera centre in world units."""
        return -self.R.T @ self.t

    def with_size(self, width_px: int, height_px: int) -> Camera:
        """The same camera at another resolution: `fx` is kept and only the window changes, so a
        pixel subtends the same angle (the runtime's convention)."""
        return replace(
            self,
            width_px=int(width_px),
            height_px=int(height_px),
            cx=self.cx + (width_px - self.width_px) / 2,
            cy=self.cy + (height_px - self.height_px) / 2,
        )

    def translated(self, dx: float, dy: float, dcx_px: float = 0.0, dcy_px: float = 0.0) -> Camera:
        """Move the camera centre by `(dx, dy, 0)` in its own frame and the principal point by
        `(dcx_px, dcy_px)`: the light-field view of docs/physics.md ("Rendering the light field
        with translated cameras": `t' = t - (dx, dy, 0)`)."""
        return replace(
            self,
            t=self.t - np.array([dx, dy, 0.0]),
            cx=self.cx + dcx_px,
            cy=self.cy + dcy_px,
        )


def intrinsics_from_fov(width_px: int, height_px: int, fov_x_deg: float) -> tuple[float, ...]:
    """`(fx, fy, cx, cy)` for square pixels and a horizontal field of view in degrees."""
    if not (0 < fov_x_deg < 180):
        raise ValueError(f"fov_x_deg must be in (0, 180), got {fov_x_deg}")
    fx = 0.5 * width_px / math.tan(math.radians(fov_x_deg) / 2)
    return fx, fx, width_px / 2, height_px / 2


def parse_axis(up: str | np.ndarray) -> np.ndarray:
    """An up vector from `"+z"`, `"-y"`, ... or a 3-vector (normalised)."""
    if isinstance(up, str):
        if up not in AXES:
            raise ValueError(f"up axis must be one of {sorted(AXES)}, got {up!r}")
        return np.array(AXES[up])
    v = np.asarray(up, np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not (np.isfinite(n) and n > 0):
        raise ValueError(f"up vector must be finite and non-zero, got {v}")
    return v / n


def look_at(eye: np.ndarray, target: np.ndarray, up: str | np.ndarray = "+z") -> tuple:
    """World-to-camera `(R, t)` for a camera at `eye` looking at `target`, image "up" along `up`.

    Rows of R are the camera's x (right), y (down) and z (forward) axes in world coordinates.
    """
    eye = np.asarray(eye, np.float64)
    forward = np.asarray(target, np.float64) - eye
    n = np.linalg.norm(forward)
    if not n > 0:
        raise ValueError("look_at: eye and target coincide")
    z = forward / n
    u = parse_axis(up)
    x = np.cross(z, u)
    if np.linalg.norm(x) < 1e-9:
        # Looking straight along up: any right vector will do; pick one deterministically.
        helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(z, helper)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    return r, -r @ eye


def _horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane normal to `up`; azimuth 0 is along the first."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - up * (ref @ up)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def orbit(
    center: np.ndarray,
    azimuth_deg: float,
    elevation_deg: float,
    radius: float,
    up: str | np.ndarray = "+z",
) -> tuple:
    """`(R, t)` of a camera on a sphere around `center` looking at it. Azimuth turns about `up`
    (0 along the world axis first in x, y order that is not `up`), elevation tilts toward `up`."""
    center = np.asarray(center, np.float64)
    eye = orbit_position(center, azimuth_deg, elevation_deg, radius, up)
    return look_at(eye, center, up)


def orbit_position(
    center: np.ndarray,
    azimuth_deg: float,
    elevation_deg: float,
    radius: float,
    up: str | np.ndarray = "+z",
) -> np.ndarray:
    """The camera position of `orbit(...)`: on the sphere of `radius` around `center`."""
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"orbit radius must be positive, got {radius}")
    u = parse_axis(up)
    e1, e2 = _horizontal_basis(u)
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    direction = math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * u
    return np.asarray(center, np.float64) + radius * direction


def quat_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (not necessarily unit) quaternion w, x, y, z."""
    w, x, y, z = np.asarray(q_wxyz, np.float64) / np.linalg.norm(q_wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_from_quaternion(position: np.ndarray, q_wxyz: np.ndarray) -> tuple:
    """`(R, t)` from a camera position and its camera-to-world rotation (OpenCV axes)."""
    r_wc = quat_to_matrix(q_wxyz)
    r = r_wc.T
    return r, -r @ np.asarray(position, np.float64)


def pose_from_ypr(
    position: np.ndarray,
    yaw_deg: float,
    pitch_deg: float,
    roll_deg: float = 0.0,
    up: str | np.ndarray = "+z",
) -> tuple:
    """`(R, t)` from a position and yaw (about `up`, 0 = along the orbit's azimuth-0 axis),
    pitch (positive looks toward `up`) and roll (about the viewing direction, clockwise in the
    image)."""
    u = parse_axis(up)
    e1, e2 = _horizontal_basis(u)
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    forward = math.cos(pitch) * (math.cos(yaw) * e1 + math.sin(yaw) * e2) + math.sin(pitch) * u
    position = np.asarray(position, np.float64)
    r, _ = look_at(position, position + forward, u)
    c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    r = roll @ r
    return r, -r @ position
