"""One frame: a view of the scene -> the SLM's coded grey region (issue 7, docs/physics.md).

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

The encoder's device (`Encoder(settings, device=...)`, `daemon.frames.device`) decides where: on the
CPU the stages above as they always ran (numba render and coding, onnxruntime on NumPy arrays,
torch propagation). With `encoder.device_coding` (every CUDA device) the frame stays on the
device: gsplat renders, the network input is built there, onnxruntime binds device memory
(`OnnxModel.run_on`), the propagation and `device_grey` run there, and only the uint8 region
and the uint8 preview of the view cross to the host, in one asynchronous pinned copy; the stage
times come from CUDA events (the copy counts in coding). With `daemon.frames.cuda_graphs` each stage
after the render is replayed as one CUDA graph (`nhfd.pipeline.device.CudaGraphs`), and the
grey region comes back in the SLM's interleaved `[h, w, 3]` layout.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from nhfd.frame_message import Region
from nhfd.model_info import ModelInfo
from nhfd.models.inputs import network_input, network_input_torch
from nhfd.scene import gsplat_backend
from nhfd.scene.raster import RasterSettings, Render, render
from nhfd.views import View

from .device import StageClock
from .encoder import Encoder, reference_field
from .view import Scene, render_camera


def preview_levels(rgb: np.ndarray) -> np.ndarray:
    """The view as the worker sends it for display: `round(clip(rgb, 0, 1) * 255)` as uint8
    `[3, H, W]` (a device frame computes the same on the GPU, `compute_frame_on_device`). One
    float32 scratch array, written in place: at 1920 x 1080 the plain expression's four
    temporaries took 8 ms."""
    scratch = np.clip(np.asarray(rgb, np.float32), 0.0, 1.0)
    scratch *= np.float32(255.0)
    scratch += np.float32(0.5)
    return scratch.astype(np.uint8)


@dataclass
class Frame:
    """One computed frame: the coded region (grey `[3, h, w]` uint8; from a device frame a view
    of its `[h, w, 3]` array, the SLM's layout) and where it goes, the
    rendered view (sRGB `[3, H, W]` float32; None from a device frame, which brings back only
    its preview) and the seconds each stage took. A model of K > 1 subframes
    (`ModelInfo.subframes`) gives all K, `subframes` `[K, 3, h, w]` uint8 (`grey` is the
    first; the clipped fractions the largest per colour); None for one."""

    region: Region
    grey: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)
    rgb: np.ndarray | None = None
    clipped_fraction: tuple[float, ...] = ()
    preview_u8: np.ndarray | None = None
    subframes: np.ndarray | None = None

    @property
    def preview(self) -> np.ndarray | None:
        """The view as uint8 `[3, H, W]` (`preview_levels`), computed once."""
        if self.preview_u8 is None and self.rgb is not None:
            self.preview_u8 = preview_levels(self.rgb)
        return self.preview_u8


def compute_frame(view: View, scene: Scene, model: Any, encoder: Encoder) -> Frame:
    """A view (`nhfd.views.View`; its refocus is the encoder's, `Encoder(frame_settings(...,
    refocus_m=view.refocus_m))`) -> the frame the SLM shows for it.

    render       view -> sRGB `[3, h, w]` float32 (with depth, alpha `[h, w]`), `(h, w)` the
                 frame window (`encoder.settings.window_hw`)
    inference    `[C, h, w]` network input (C = 3, or 4 for an rgbd model) -> amplitude, phase
                 `[3, h, w]` float32 (amplitude in the model's units, phase in radians)
    propagation  the reference-plane field `[3, h, w]` complex64 (amplitude x amplitude_scale)
                 -> the SLM-plane field `[3, Hr, Wr]` complex64 on `encoder.region`
    coding       -> grey `[3, Hr, Wr]` uint8 and the clipped fraction per colour

    `model`: an `nhfd.models.export.OnnxModel` (or anything with its `info`, `inputs` and
    call; with `run_on` too on a device path). Not thread-safe: the encoder keeps scratch
    buffers."""
    if encoder.device_coding:
        return compute_frame_on_device(view, scene, model, encoder)
    s = encoder.settings
    clock = StageClock()
    rendered = render_view(view, scene, model.info, s.window_hw)
    clock.stage("render")
    amplitude, phase = infer(model, rendered)
    clock.stage("inference")
    greys, clips = [], []
    with torch.no_grad():
        # K subframes: the same stages per subframe (the propagation's and coding's times are
        # the K together)
        pairs = subframe_fields(amplitude, phase)
        for a, p in pairs:
            slm_field = encoder.to_slm(reference_field(a, p, s.amplitude_scale))
            clock.stage("propagation")
            grey, clipped = encoder.code(slm_field)
            # the coder's output buffer serves the next subframe: K > 1 copies each out
            greys.append(grey if len(pairs) == 1 else grey.copy())
            clips.append(clipped)
            clock.stage("coding")
    return _frame_of(encoder, greys, clips, clock.seconds, rendered.rgb)


def subframe_fields(amplitude: Any, phase: Any) -> list[tuple[Any, Any]]:
    """A network's outputs `[3 K, h, w]` (arrays or tensors) as K (amplitude, phase) pairs
    `[3, h, w]`: subframe k in channels 3k..3k+2 (`ServingNet(subframes=K)`)."""
    c = int(amplitude.shape[0])
    if c % 3 or phase.shape[0] != c:
        raise ValueError(f"network outputs of {c} and {phase.shape[0]} channels: expected "
                         "3 K each (K subframes of three colours)")
    return [(amplitude[i : i + 3], phase[i : i + 3]) for i in range(0, c, 3)]


def _frame_of(encoder: Encoder, greys: list[np.ndarray], clips: list[tuple[float, ...]],
              timings_s: dict[str, float], rgb: np.ndarray | None,
              preview: np.ndarray | None = None) -> Frame:
    """The `Frame` of K coded subframes (one is kept as the coder gave it; K are stacked into
    one array)."""
    if len(greys) == 1:
        return Frame(encoder.region, greys[0], timings_s, rgb, clips[0], preview)
    stacked = np.stack(greys)
    clipped = tuple(float(max(c[i] for c in clips)) for i in range(len(clips[0])))
    return Frame(encoder.region, stacked[0], timings_s, rgb, clipped, preview, stacked)


def render_view(view: View, scene: Scene, info: ModelInfo, window_hw: tuple[int, int],
                backend: str = "cpu") -> Render:
    """The view rendered through the model's camera (`render_camera`) on the frame window
    (h, w px): sRGB `[3, h, w]`, depth and alpha `[h, w]`."""
    return render(scene.gaussians, render_camera(view, scene.frame, info, window_hw),
                  backend=backend)


def compute_frame_on_device(view: View, scene: Scene, model: Any, encoder: Encoder) -> Frame:
    """`compute_frame` with every stage on `encoder.device`; see the module's docstring."""
    s, dev = encoder.settings, encoder.device
    model_device = getattr(model, "device", None)
    if model_device is not None and torch.device(model_device) != dev:
        raise ValueError(f"the model runs on {model_device}, the encoder on {dev}: load both "
                         "for one device (daemon.frames.device)")
    clock = StageClock(dev)
    # each stage after the render one CUDA graph (daemon.frames.cuda_graphs)
    graphs = encoder.graphs
    with torch.no_grad():
        rgb, depth, alpha = render_on_device(view, scene, model.info, s.window_hw, dev)
        clock.stage("render")
        info = model.info
        x = network_input_on_device(rgb, model.inputs, depth=depth, alpha=alpha,
                                    mapping=info.mapping_dict, volume_m=info.volume_m)
        if getattr(model, "graphable", False):  # torch's network (onnxruntime's is not)
            amplitude, phase = graphs.run("inference", model.run_on, x)
        elif hasattr(model, "run_on"):
            amplitude, phase = model.run_on(x)
        else:  # a callable on NumPy arrays (tests' stand-ins)
            amplitude, phase = (_on(v, dev) for v in model(x.cpu().numpy()))
        clock.stage("inference")
        pairs = subframe_fields(amplitude, phase)
        greys, clips = [], []
        for a, p in pairs:
            slm_field = graphs.run("propagation", lambda a, p: encoder.to_slm(
                reference_field(a, p, s.amplitude_scale)), a.contiguous(), p.contiguous())
            clock.stage("propagation")
            coded = graphs.run("coding", lambda f, v: _code_on_device(encoder, f, v), slm_field,
                               rgb)
            started = encoder.host.start(*coded)
            clock.stage("coding")
            grey_hwc, clipped, bad, preview = encoder.host.wait(started)
            clips.append(encoder.check_coded(clipped, bad))
            # [3, h, w] as a view of the [h, w, 3] array: the SLM's layout, which the daemon
            # pastes into its panel row by row (`PanelBuffer`) instead of interleaving three
            # planes. The host copy's buffers serve the next subframe: K > 1 copies each out.
            grey = grey_hwc.transpose(2, 0, 1)
            greys.append(grey if len(pairs) == 1 else grey.copy())
            if len(pairs) > 1:
                preview = preview.copy()
    return _frame_of(encoder, greys, clips, clock.seconds, None, preview)


def _code_on_device(encoder: Encoder, slm_field: torch.Tensor, rgb: torch.Tensor
                    ) -> tuple[torch.Tensor, ...]:
    """The coding stage on the device: grey `[h, w, 3]` uint8 (the SLM's interleaved layout),
    the clipped fraction `[3]`, the non-finite count, and the view's preview `[3, H, W]` uint8
    (`preview_levels` on the GPU: the float view and its conversion on the host took 14 ms a
    frame at 1920 x 1080)."""
    grey, clipped, bad = encoder.code_on_device(slm_field)
    preview = (rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
    return grey.permute(1, 2, 0).contiguous(), clipped, bad, preview


def render_on_device(view: View, scene: Scene, info: ModelInfo, window_hw: tuple[int, int],
                     device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`render_view` as tensors on `device`: sRGB `[3, h, w]`, depth and alpha `[h, w]`. On CUDA
    gsplat renders the scene uploaded once per device (`Scene.on_device`), and nothing crosses
    to the host; elsewhere the CPU rasteriser's arrays are moved there."""
    if device.type != "cuda":
        r = render_view(view, scene, info, window_hw)
        return _on(r.rgb, device), _on(r.depth, device), _on(r.alpha, device)
    key = str(device)
    if key not in scene.on_device:
        scene.on_device[key] = gsplat_backend.GsplatScene(scene.gaussians, key)
    raster = RasterSettings()  # render_view's (the CPU path's) settings
    views = scene.on_device[key].render([render_camera(view, scene.frame, info, window_hw)],
                                        raster.eps2d_px2, raster.antialias)
    return views.rgb[0], views.depth[0], views.alpha[0]


def _on(value: Any, device: torch.device) -> torch.Tensor:
    """A render's or a model's array as a tensor on `device` (gsplat's may already be one)."""
    if isinstance(value, torch.Tensor):
        return value.to(device)
    return torch.from_numpy(np.ascontiguousarray(value)).to(device)


# The network input on the device path, defined once in `nhfd.models.inputs` (bit for
# bit `network_input`, which the CPU path uses); this name is the call site's.
network_input_on_device = network_input_torch


def infer(model: Any, rendered: Render) -> tuple[np.ndarray, np.ndarray]:
    """The network's amplitude and phase for a render, fed as training fed it (an rgbd model
    gets the render's mapped depth): amplitude (the model's units) and phase (rad), each
    `[3, h, w]` float32."""
    info = model.info
    x = network_input(rendered.rgb, model.inputs, depth=rendered.depth, alpha=rendered.alpha,
                      mapping=info.mapping_dict, volume_m=info.volume_m)
    return model(x)
