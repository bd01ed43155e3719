"""One frame: a view of the scene -> the SLM's coded grey region (issue 7, optics.md).

`compute_frame` is the whole data flow, its stages in order:

    render       the central view (the model's training window, its trained fx)
    inference    onnxruntime: amplitude, phase on the reference plane (x the model's amplitude
                 scale)
    propagation  one cached kernel per colour: the Fourier aperture and the propagation by
                 -(z0 + refocus + the colour's calibrated focus offset) to the SLM plane, on the
                 window plus the margin the kernel reaches only
    coding       double-phase coding with the model's amplitude scale and coding.zero_below,
                 grey levels through the configured (or calibrated) phase curves

The daemon adds the fifth stage, output: the coded region pasted into the precomputed
zero-amplitude pattern of the full panel, shown on the SLM.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from nhfd.models.inputs import network_input
from nhfd.scene.raster import Render, render

from .encoder import Encoder, reference_field
from .settings import Region
from .view import Scene, render_camera


@dataclass
class Frame:
    """One computed frame: the coded region (grey `[3, h, w]` uint8) and where it goes, the
    rendered view (sRGB `[3, H, W]` float32) and the seconds each stage took."""

    region: Region
    grey: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)
    rgb: np.ndarray | None = None
    clipped_fraction: tuple[float, ...] = ()


def compute_frame(view: dict[str, Any], scene: Scene, model: Any, encoder: Encoder) -> Frame:
    """A normalised view (`nhfd.daemon.views`) -> the frame the SLM shows for it.

    render       view -> sRGB `[3, h, w]` float32 (with depth, alpha `[h, w]`), `(h, w)` the
                 frame window (`encoder.settings.window_hw`)
    inference    `[C, h, w]` network input (C = 3, or 4 for an rgbd model) -> amplitude, phase
                 `[3, h, w]` float32 (amplitude in the model's units, phase in radians)
    propagation  the reference-plane field `[3, h, w]` complex64 (amplitude x amplitude_scale)
                 -> the SLM-plane field `[3, Hr, Wr]` complex64 on `encoder.region`
    coding       -> grey `[3, Hr, Wr]` uint8 and the clipped fraction per colour

    `model`: an `nhfd.models.export.OnnxModel` (or anything with its `metadata`, `inputs` and
    call). Not thread-safe: the encoder keeps scratch buffers."""
    s = encoder.settings
    clock = _StageClock()
    rendered = render_view(view, scene, model.metadata, s.window_hw)
    clock.stage("render")
    amplitude, phase = infer(model, rendered)
    clock.stage("inference")
    with torch.no_grad():
        slm_field = encoder.to_slm(reference_field(amplitude, phase, s.amplitude_scale))
        clock.stage("propagation")
        grey, clipped = encoder.code(slm_field)
        clock.stage("coding")
    return Frame(encoder.region, grey, clock.seconds, rendered.rgb, clipped)


def render_view(view: dict[str, Any], scene: Scene, metadata: dict[str, Any],
                window_hw: tuple[int, int]) -> Render:
    """The view rendered through the model's camera (`render_camera`) on the frame window."""
    return render(scene.gaussians, render_camera(view, scene.frame, metadata, window_hw))


def infer(model: Any, rendered: Render) -> tuple[np.ndarray, np.ndarray]:
    """The network's amplitude and phase for a render, fed as training fed it (an rgbd model
    gets the render's mapped depth)."""
    meta = model.metadata
    x = network_input(rendered.rgb, model.inputs, depth=rendered.depth, alpha=rendered.alpha,
                      mapping=meta.get("mapping"), volume_m=meta.get("volume_m"))
    return model(x)


class _StageClock:
    """Seconds per stage: each `stage(name)` ends the stage that began at the previous one."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._t = time.perf_counter()

    def stage(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[name] = now - self._t
        self._t = now
