"""Every camera a dataset build renders, before it is built: the pose envelope that
`nhfd.scene.cull.reduce_scene` reduces a scene to (issue 24, part 3).

A build (`build.plan_manifest`, `shard.make_example`) renders, per pose, a quarter-size depth
view (the depth pass that fixes the mapping) and the light field of the central camera: one view
per STFT bin of each group of colours that shares views (`holo.hologram._view_groups`: all
colours with `shared_views`, else colours with equal slopes), the bin k = 0 being the central
view itself. `dataset_envelope` makes the same cameras, from the same settings and with the
same mapping, so nothing the build will render is left out of the envelope.

`orbit_sampler` (from `nhfd.dataset.poses`) is `nhfd dataset build`'s pose sampler.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nhfd.dataset.build import DEPTH_PASS_SCALE, depth_pass_cameras, plan_optics
from nhfd.dataset.poses import Pose, orbit_sampler
from nhfd.dataset.shard import ExampleSettings, camera_distance
from nhfd.holo import sampling_report
from nhfd.holo.hologram import _view_groups
from nhfd.optics.quality import quality_planes
from nhfd.scene.cameras import Camera
from nhfd.scene.cull import envelope_light_field_cameras, reduce_scene
from nhfd.scene.gaussians import Gaussians
from nhfd.scene.lightfield import DepthMapping

# `nhfd scene reduce` loads this module alone, when it runs, and takes these from it.
__all__ = ["DEPTH_PASS_SCALE", "Envelope", "ExampleSettings", "dataset_envelope",
           "orbit_sampler", "reduce_scene"]



@dataclass(frozen=True)
class Envelope:
    """`cameras`: every view the build renders (depth-pass views first, then each pose's light
    field, pose-major); `mapping` and its `mapping_report`, the `sampling` report (windows,
    views per colour), `views_per_pose` (light-field views) and the evaluation's focal planes."""

    cameras: list[Camera]
    mapping: DepthMapping
    mapping_report: dict
    sampling: list[dict]
    n_poses: int
    views_per_pose: int
    focal_planes_m: tuple[float, ...]

    def describe(self) -> dict:
        """The envelope for a report, JSON-ready: counts, the mapping's figures (depths in scene
        units, z in m), the sampling and the focal planes (m)."""
        m = self.mapping_report
        return {"n_poses": self.n_poses, "views_per_pose": self.views_per_pose,
                "n_cameras": len(self.cameras),
                "mapping": {k: m[k] for k in ("d_near", "d_far", "z_min_m", "z_max_m", "a_m",
                                              "b_m", "depth_exaggeration") if k in m},
                "sampling": self.sampling, "focal_planes_m": list(self.focal_planes_m)}


def dataset_envelope(
    g: Gaussians,
    poses: list[Pose],
    center: np.ndarray,
    settings: ExampleSettings,
    *,
    d_near: float | None = None,
    d_far: float | None = None,
) -> Envelope:
    """The cameras a build of `g` with these poses and settings renders (see the module
    docstring); the mapping comes from the same depth pass the build runs."""
    if not poses:
        raise ValueError("poses: need at least one pose, got none")
    depth_cams = depth_pass_cameras(poses, center, settings)
    mapping, report, sampling = plan_optics(g, poses, center, settings, d_near=d_near,
                                            d_far=d_far)  # fmt: skip
    taus = _view_taus(sampling, settings.shared_views)
    pose_cams = [settings.camera(p, camera_distance(p, center)) for p in poses]
    views = envelope_light_field_cameras(pose_cams, mapping, settings.pitch_m, taus)
    return Envelope(
        cameras=depth_cams + views, mapping=mapping, mapping_report=report,
        sampling=sampling_report(sampling), n_poses=len(poses),
        views_per_pose=sum(len(t) ** 2 for t in taus),
        focal_planes_m=quality_planes(settings.volume_m),
    )  # fmt: skip


def _view_taus(sampling, shared_views: bool) -> list[np.ndarray]:
    """The slopes each rendered group uses, as `holo.hologram.scene_hologram` picks them: the
    longest wavelength's in each group of colours that share views."""
    return [sampling[max(grp, key=lambda c: sampling[c].wavelength_m)].tau
            for grp in _view_groups(sampling, shared_views)]
