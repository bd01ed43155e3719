"""The frame pipeline: a view of the scene -> the SLM's grey frame (issue 7, optics.md).

    render the central view (the model's training window, its trained fx)
      -> onnxruntime: amplitude, phase on the reference plane (x the model's amplitude scale)
      -> one cached kernel per colour: the Fourier aperture and the propagation by
         -(z0 + refocus + the colour's calibrated focus offset) to the SLM plane, on the window
         plus the margin the kernel reaches only
      -> double-phase coding with the model's amplitude scale and coding.zero_below
      -> grey levels through the configured phase curve(s)
      -> the full panel: the precomputed zero-amplitude pattern with the coded region pasted in.

Everything here is a pure function of its inputs (no devices, no processes); the spawned frame
worker (`nhfd.daemon.worker`) runs it, the tests and `nhfd bench pipeline` call it directly.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from nhfd import spec
from nhfd.models.inputs import network_input
from nhfd.optics import Aperture, KernelCache, double_phase_grey, fft
from nhfd.optics.refplane import margin_px, window_offset
from nhfd.spec import PhaseCurve

# Stage names, in order, as status and the benchmark report them.
STAGES = ("render", "inference", "propagation", "coding", "output")
# Envelope checks allow this much beyond the trained range before warning (a view at the edge of
# the training poses is still a trained view).
ENVELOPE_SLACK_DEG = 1.0
ENVELOPE_SLACK_FRACTION = 0.02


@dataclass(frozen=True)
class FrameSettings:
    """Everything a frame depends on besides the view, the scene and the network's weights."""

    panel_hw: tuple[int, int]
    window_hw: tuple[int, int]
    pitch_m: float
    wavelengths_m: tuple[float, ...]
    z0_m: float
    aperture_shape: str
    cutoff_per_px: tuple[float, ...]
    amplitude_scale: float
    zero_below: float
    phase_stroke_rad: tuple[float, ...]
    phase_sign: int = 1
    grey_invert: bool = False
    # Digital refocus: the reference plane is placed at z0 + refocus_m from the SLM (positive
    # moves the whole volume toward the viewer).
    refocus_m: float = 0.0
    padding: str = "auto"
    # Measured grey -> phase tables per colour (a calibration file); () = linear curves of
    # phase_stroke_rad.
    phase_tables_rad: tuple[tuple[float, ...], ...] = ()
    # Per-colour focus offsets (a calibration file; () = none): colour c's reference plane is
    # placed at z0 + refocus_m + colour_offset_m[c], where the relay's chromatic focal shift
    # makes the camera (or eye) see it at the same place as green's.
    colour_offset_m: tuple[float, ...] = ()
    # The illumination per colour (a calibration file; () = uniform): (1/e^2 intensity radius,
    # centre x, centre y) on the SLM plane, metres. The SLM-plane amplitude is divided by the
    # source's amplitude, relative to its value at the window's centre and at most
    # max_amplitude_gain (the dim edges of the beam cannot be lifted without limit: double-phase
    # coding clips amplitudes beyond amplitude_scale).
    source_profile: tuple[tuple[float, float, float], ...] = ()
    max_amplitude_gain: float = 2.0
    # Relay aberrations (a calibration file; () = none): Zernike coefficients for Noll
    # j = 5, 6, ... in radians at zernike_wavelength_m, pupil radius = the aperture's cutoff
    # (nhfd.calib.bench_model.pupil_phase). Each colour's kernel carries the conjugate phase.
    zernike_rad: tuple[float, ...] = ()
    zernike_wavelength_m: float = 0.0

    @property
    def aperture(self) -> Aperture:
        return Aperture(self.aperture_shape, tuple(self.cutoff_per_px))  # type: ignore[arg-type]

    @property
    def propagation_z_m(self) -> float:
        return -(self.z0_m + self.refocus_m)

    @property
    def colour_propagation_z_m(self) -> tuple[float, ...]:
        """Each colour's propagation to the SLM: -(z0 + refocus + its focus offset)."""
        offsets = self.colour_offset_m or (0.0,) * len(self.wavelengths_m)
        return tuple(self.propagation_z_m - o for o in offsets)

    def curves(self) -> list[PhaseCurve]:
        return spec.phase_curves(self.phase_stroke_rad, self.phase_tables_rad)


@dataclass(frozen=True)
class Region:
    """The part of the panel a frame changes: the window plus the kernel's reach, with an even
    top-left corner so its checkerboard lines up with the zero pattern's."""

    top: int
    left: int
    height: int
    width: int
    # Where the window sits inside the region.
    window_top: int
    window_left: int

    @property
    def rows(self) -> slice:
        return slice(self.top, self.top + self.height)

    @property
    def cols(self) -> slice:
        return slice(self.left, self.left + self.width)


def frame_region(s: FrameSettings) -> Region:
    ph, pw = s.panel_hw
    wh, ww = s.window_hw
    top, left = window_offset(s.panel_hw, s.window_hw)
    reach_z = max(abs(z) for z in s.colour_propagation_z_m)
    m = margin_px(reach_z, s.pitch_m, s.wavelengths_m, s.aperture)
    r0, c0 = max(0, top - m), max(0, left - m)
    r0, c0 = r0 - r0 % 2, c0 - c0 % 2  # even: the checkerboard's parity is the panel's
    r1, c1 = min(ph, top + wh + m), min(pw, left + ww + m)
    return Region(r0, c0, r1 - r0, c1 - c0, top - r0, left - c0)


def zero_pattern(s: FrameSettings) -> np.ndarray:
    """The whole panel coding zero amplitude, through the same curves as frames
    (`nhfd.spec.zero_pattern`: the blank frame's and the coder's zero too)."""
    return spec.zero_pattern(s.panel_hw, s.curves(), s.phase_sign, s.grey_invert)


@dataclass
class Frame:
    """One computed frame: the coded region (grey `[3, h, w]` uint8) and where it goes, the
    rendered view (sRGB `[3, H, W]` float32) and the seconds each stage took."""

    region: Region
    grey: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)
    rgb: np.ndarray | None = None
    clipped_fraction: tuple[float, ...] = ()


class _Group:
    """Colours propagated together (one padded grid, one stacked kernel), and the kernel reduced
    to what the propagation needs: the Fourier aperture (folded into the kernel) passes about a
    quarter of the padded spectrum, so only the rows and columns of frequencies it keeps are
    transformed, multiplied and transformed back.

    The padded field is zero outside the window, so the forward transform runs along rows over
    the window's rows only, then along columns over the kept columns only; the inverse runs along
    columns over the kept columns, then along rows over the region's rows only. The same sums as
    `propagate`'s 2D transforms, less those that multiply exact zeros, with the same kernel
    values: equal to it to float32 rounding (tests/daemon/test_encoder.py).

    The column transforms run on a transposed copy (`[n, kept columns, Hp]`: along the last
    axis, all colours in one call; along dim -2 torch makes two transposing copies of its own).
    The zero-padded inputs of the four transforms are kept between calls (~50 MB at 1024 x 576)
    and written only where they are not zero: fresh ones cost page faults and zero fills that
    measured more than the column transforms themselves."""

    def __init__(self, colours: slice, padded_hw: tuple[int, int], kernel: torch.Tensor,
                 offset: tuple[int, int], region_hw: tuple[int, int]) -> None:
        self.colours = colours
        self.padded_hw = padded_hw
        self.region_hw = region_hw
        self.offset = offset
        kept = kernel != 0
        self.row_runs = _runs(kept.any(-1).any(0))
        self.col_runs = _runs(kept.any(-2).any(0))
        cols = torch.tensor([i for a, b in self.col_runs for i in range(a, b)], dtype=torch.long)
        reduced = kernel.index_select(-1, cols)
        # Per run of kept rows: the kernel there, kept columns only, transposed: [n, nc, run].
        self.kernels = [reduced[:, a:b].transpose(-1, -2).contiguous() for a, b in self.row_runs]
        self.n_cols = len(cols)
        self._buffers: tuple[torch.Tensor, ...] = ()
        self._window_hw = (0, 0)

    def _scratch(self, n: int, h: int, w: int) -> tuple[torch.Tensor, ...]:
        if not self._buffers or self._window_hw != (h, w) or self._buffers[0].shape[0] != n:
            (hp, wp), (hr, _wr), nc = self.padded_hw, self.region_hw, self.n_cols
            z = torch.complex64
            self._buffers = (torch.zeros((n, h, wp), dtype=z), torch.zeros((n, nc, hp), dtype=z),
                             torch.zeros((n, nc, hp), dtype=z), torch.zeros((n, hr, wp), dtype=z))
            self._window_hw = (h, w)
        return self._buffers

    def propagate(self, window: torch.Tensor) -> torch.Tensor:
        """Window field `[n, h, w]` -> region field `[n, Hr, Wr]` (a crop of a fresh tensor)."""
        hr, wr = self.region_hw
        r0, c0 = self.offset
        n, h, w = window.shape
        if not self.col_runs or not self.row_runs:  # the kernel passes nothing
            return torch.zeros((n, hr, wr), dtype=torch.complex64)
        padded, columns, spectrum, back_rows = self._scratch(n, h, w)
        # Forward along rows: the window's rows, zero-padded to Wp.
        padded[..., c0 : c0 + w] = window
        rows = fft.fft(padded, dim=-1)
        # Along columns: the kept columns, transposed, at the window's rows of Hp.
        _gather_t(columns[..., r0 : r0 + h], rows, self.col_runs)
        del rows
        forward = fft.fft(columns, dim=-1)
        # Times the kernel on its kept rows (zero elsewhere), back along columns.
        for (a, b), k in zip(self.row_runs, self.kernels, strict=True):
            torch.mul(forward[..., a:b], k, out=spectrum[..., a:b])
        del forward
        back = fft.ifft(spectrum, dim=-1)
        # Back along rows: the region's rows, the kept columns (zero elsewhere).
        _scatter_t(back_rows, back[..., :hr], self.col_runs)
        del back
        return fft.ifft(back_rows, dim=-1)[..., :wr]


def _runs(mask: torch.Tensor) -> list[tuple[int, int]]:
    """The [start, stop) runs of True in a 1-D bool tensor."""
    m = [bool(v) for v in mask.tolist()]
    out, i = [], 0
    while i < len(m):
        if m[i]:
            j = i
            while j < len(m) and m[j]:
                j += 1
            out.append((i, j))
            i = j
        else:
            i += 1
    return out


def _gather_t(dst: torch.Tensor, src: torch.Tensor, runs: list[tuple[int, int]]) -> None:
    """dst[..., k, i] = src[..., i, the k-th index of the runs]: the runs of src's columns,
    transposed into dst's rows."""
    k = 0
    for a, b in runs:
        dst[..., k : k + b - a, :] = src[..., a:b].transpose(-1, -2)
        k += b - a


def _scatter_t(dst: torch.Tensor, src: torch.Tensor, runs: list[tuple[int, int]]) -> None:
    """The inverse of `_gather_t`: dst[..., i, the k-th index of the runs] = src[..., k, i]."""
    k = 0
    for a, b in runs:
        dst[..., a:b] = src[..., k : k + b - a, :].transpose(-1, -2)
        k += b - a


class Encoder:
    """Reference-plane field -> coded grey region; owns the kernel cache, the zero pattern and
    the propagation's scratch buffers (so not thread-safe, like `Pipeline`)."""

    def __init__(self, settings: FrameSettings, cache_bytes: int = 256 * 2**20) -> None:
        self.settings = settings
        self.region = frame_region(settings)
        self.cache = KernelCache(cache_bytes)
        self.curves = settings.curves()
        self._zero: np.ndarray | None = None
        self._panel: PanelBuffer | None = None
        self._gain_map: torch.Tensor | None = None
        self._groups: list[_Group] | None = None

    @property
    def zero(self) -> np.ndarray:
        if self._zero is None:  # 6 MB at 1920 x 1080: only where a full panel is wanted
            self._zero = zero_pattern(self.settings)
        return self._zero

    def to_slm(self, reference: torch.Tensor) -> torch.Tensor:
        """Window field `[3, h, w]` on the reference plane -> region field on the SLM plane.

        The same field as `propagate` of the zero-padded region by each colour's depth with the
        aperture (and the relay's conjugate pupil when calibrated), to float32 rounding; the
        result may be a crop of a larger fresh tensor (not contiguous), and carries no autograd
        history."""
        r = self.region
        ref = reference.detach().to(torch.complex64)
        h, w = ref.shape[-2:]
        if (ref.dim() != 3 or h + r.window_top > r.height or w + r.window_left > r.width):
            raise ValueError(f"reference of shape {tuple(reference.shape)}: expected [C, h, w] "
                             f"inside the {r.height} x {r.width} region")
        groups = self.groups()
        if len(groups) == 1:
            return groups[0].propagate(ref)
        out = torch.empty((ref.shape[0], r.height, r.width), dtype=torch.complex64)
        for g in groups:
            out[g.colours] = g.propagate(ref[g.colours])
        return out

    def groups(self) -> list[_Group]:
        """The propagation per group of colours sharing a depth (built once: the kernels come
        through the cache, under the keys `propagate` uses)."""
        if self._groups is None:
            r = self.region
            self._groups = [
                _Group(colours, hw, kernel, (r.window_top, r.window_left), (r.height, r.width))
                for colours, hw, kernel in self._kernels()]
        return self._groups

    def _kernels(self) -> list[tuple[slice, tuple[int, int], torch.Tensor]]:
        """(colours, padded shape, kernels [n, Hp, Wp]) per group of colours."""
        from nhfd.optics.asm import propagation_kernels
        from nhfd.optics.padding import plan_padding

        s, r = self.settings, self.region
        zs = s.colour_propagation_z_m
        hw = (r.height, r.width)
        cpu = torch.device("cpu")
        if any(s.zernike_rad):
            return self._kernels_precompensated(zs)
        if len(set(zs)) == 1:
            plan = plan_padding(hw, s.pitch_m, s.wavelengths_m, abs(zs[0]), s.aperture,
                                s.padding)  # type: ignore[arg-type]
            k = propagation_kernels(plan, s.pitch_m, s.wavelengths_m, (zs[0],), s.aperture, True,
                         torch.complex64, cpu, self.cache)
            return [(slice(0, len(zs)), plan.padded_hw, k[0])]
        # Per-colour depths (calibrated focus offsets): one kernel per colour, each cached.
        cutoffs = s.aperture.cutoffs(len(zs))
        out = []
        for c, z in enumerate(zs):
            lam = (s.wavelengths_m[c],)
            ap = Aperture(s.aperture.shape, (cutoffs[c],))
            plan = plan_padding(hw, s.pitch_m, lam, abs(z), ap, s.padding)  # type: ignore[arg-type]
            k = propagation_kernels(plan, s.pitch_m, lam, (z,), ap, True, torch.complex64, cpu,
                                    self.cache)
            out.append((slice(c, c + 1), plan.padded_hw, k[0]))
        return out

    def _kernels_precompensated(self, zs: tuple[float, ...]
                                ) -> list[tuple[slice, tuple[int, int], torch.Tensor]]:
        """Per colour: the ASM kernel (nhfd.optics) times the conjugate of the relay's pupil
        phase, cached under a key that names the aberration (a kernel for other coefficients
        is never reused)."""
        from nhfd.calib.bench_model import pupil_phase
        from nhfd.optics.asm import transfer_function
        from nhfd.optics.padding import plan_padding

        s, r = self.settings, self.region
        cutoffs = s.aperture.cutoffs(len(zs))
        lam_ref = s.zernike_wavelength_m or s.wavelengths_m[len(s.wavelengths_m) // 2]
        out = []
        for c, z in enumerate(zs):
            lam = s.wavelengths_m[c]
            ap = Aperture(s.aperture.shape, (cutoffs[c],))
            plan = plan_padding((r.height, r.width), s.pitch_m, (lam,), abs(z), ap,
                                s.padding)  # type: ignore[arg-type]

            def kernel(plan: object = plan, z: float = z, lam: float = lam, ap: Aperture = ap,
                       c: int = c) -> torch.Tensor:
                hw = plan.padded_hw  # type: ignore[attr-defined]
                k = transfer_function(hw, s.pitch_m, [lam], [z], aperture=ap)[0, 0]
                ph = pupil_phase(hw, cutoffs[c], tuple(s.zernike_rad), lam_ref / lam)
                return k * torch.polar(torch.ones_like(ph), -ph).to(k.dtype)

            key = ("asm-pupil", plan.padded_hw, s.pitch_m, lam, z, ap, tuple(s.zernike_rad),
                   lam_ref)
            out.append((slice(c, c + 1), plan.padded_hw, self.cache.get(key, kernel)[None]))
        return out

    def amplitude_gain_map(self) -> torch.Tensor | None:
        """[3, h, w] factors on the region's SLM-plane field that undo the source's profile
        (None without one): A(window centre) / A(x), at most max_amplitude_gain."""
        s, r = self.settings, self.region
        if not s.source_profile:
            return None
        if self._gain_map is None:
            ph, pw = s.panel_hw
            rows = torch.arange(r.top, r.top + r.height, dtype=torch.float64)
            cols = torch.arange(r.left, r.left + r.width, dtype=torch.float64)
            y = (rows - (ph - 1) / 2) * s.pitch_m
            x = (cols - (pw - 1) / 2) * s.pitch_m
            yc = (r.top + r.window_top + (s.window_hw[0] - 1) / 2 - (ph - 1) / 2) * s.pitch_m
            xc = (r.left + r.window_left + (s.window_hw[1] - 1) / 2 - (pw - 1) / 2) * s.pitch_m
            maps = []
            for waist, x0, y0 in s.source_profile:
                # Amplitude exp(-r^2 / w^2): its inverse relative to the window's centre.
                r2 = (x[None, :] - x0) ** 2 + (y[:, None] - y0) ** 2
                rc2 = (xc - x0) ** 2 + (yc - y0) ** 2
                maps.append(torch.clamp(torch.exp((r2 - rc2) / waist**2),
                                        max=s.max_amplitude_gain))
            self._gain_map = torch.stack(maps).float()
        return self._gain_map

    def code(self, slm_field: torch.Tensor) -> tuple[np.ndarray, tuple[float, ...]]:
        """SLM-plane region field -> grey `[3, h, w]` uint8 and the clipped fraction per colour.

        One fused pass (`double_phase_grey`): the gain map, double-phase coding with the
        model's amplitude scale and zero_below, and the phase curves. No antialias pass: the
        propagation kernel already applied the aperture."""
        s = self.settings
        return double_phase_grey(slm_field, s.amplitude_scale, self.curves, sign=s.phase_sign,
                                 invert=s.grey_invert, zero_below=s.zero_below,
                                 gain=self.amplitude_gain_map())

    def panel(self, grey: np.ndarray) -> np.ndarray:
        """The full panel frame `[3, H, W]`: the zero pattern with the coded region pasted in
        (a view of an `[H, W, 3]` array: the layout the SLM takes, so showing it copies
        nothing)."""
        if self._panel is None:
            self._panel = PanelBuffer(self.zero)
        return self._panel.frame(self.region.top, self.region.left, grey)


class PanelBuffer:
    """Full panel frames from the zero pattern and a coded region, built in the SLM's `[H, W, 3]`
    layout: a frame is a fresh copy of the interleaved zero pattern with the region interleaved
    in, returned as its `[3, H, W]` view. `nhfd.drivers.slm.to_rgb` takes that view as it is,
    where a channel-first frame costs a transposing copy of the whole panel (~10 ms at
    1920 x 1080)."""

    def __init__(self, zero: np.ndarray) -> None:
        self.zero_hwc = np.ascontiguousarray(np.asarray(zero, np.uint8).transpose(1, 2, 0))

    def frame(self, top: int, left: int, grey: np.ndarray) -> np.ndarray:
        out = self.zero_hwc.copy()
        _, h, w = grey.shape
        dst = out[top : top + h, left : left + w]
        for c in range(grey.shape[0]):
            dst[..., c] = grey[c]
        return out.transpose(2, 0, 1)


def reference_field(amplitude: np.ndarray, phase: np.ndarray, amplitude_scale: float
                    ) -> torch.Tensor:
    """The network's outputs -> the complex reference-plane field in the dataset's units."""
    amp = torch.from_numpy(np.ascontiguousarray(amplitude, np.float32)) * float(amplitude_scale)
    return torch.polar(amp, torch.from_numpy(np.ascontiguousarray(phase, np.float32)))


# -- views and the render camera ---------------------------------------------------------------


@dataclass(frozen=True)
class SceneFrame:
    """What orbit views are relative to: the scene's centre and up axis (as the dataset builder
    chose them: the median of the means and the detected up axis)."""

    center: tuple[float, float, float]
    up: str


def scene_frame(g: Any, path: str | None = None) -> SceneFrame:
    from nhfd.scene.suggest import detect_up_axis, format_hint

    up = detect_up_axis(g, format_hint(path) if path else None)[0]
    center = np.median(g.means, axis=0) if len(g) else np.zeros(3)
    return SceneFrame(tuple(float(v) for v in center), up)  # type: ignore[arg-type]


def view_pose(view: dict[str, Any], frame: SceneFrame) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera `(R, t)` of a normalised view (see `nhfd.daemon.views`)."""
    from nhfd.scene.cameras import orbit, pose_from_quaternion

    if view["kind"] == "orbit":
        return orbit(np.array(frame.center), view["azimuth_deg"], view["elevation_deg"],
                     view["radius"], frame.up)
    return pose_from_quaternion(np.array(view["position"]), np.array(view["quaternion_wxyz"]))


def render_camera(view: dict[str, Any], frame: SceneFrame, metadata: dict[str, Any],
                  window_hw: tuple[int, int]) -> Any:
    """The central camera: the model's trained fx, fy (a pixel subtends the angle it was trained
    on), centred on the window; the near plane at 1% of the distance to the centre, as the
    dataset builder sets it."""
    from nhfd.scene.cameras import Camera

    r, t = view_pose(view, frame)
    h, w = window_hw
    fx = float(metadata.get("fx") or 0.0)
    fy = float(metadata.get("fy") or fx)
    if not fx > 0:
        _th, tw = metadata["train_size_hw"]
        fov = float(metadata.get("fov_x_deg") or 40.0)
        fx = fy = 0.5 * tw / math.tan(math.radians(fov) / 2)
    position = -r.T @ t
    distance = float(np.linalg.norm(position - np.array(frame.center)))
    return Camera(r, t, fx, fy, w / 2, h / 2, w, h, near=max(0.01 * distance, 1e-9))


def envelope_warnings(view: dict[str, Any], frame: SceneFrame, envelope: dict[str, Any] | None
                      ) -> list[str]:
    """Why a view lies outside the model's pose envelope (empty when inside or unknown)."""
    if not envelope:
        return []
    out: list[str] = []
    r, t = view_pose(view, frame)
    position = -r.T @ t
    distance = float(np.linalg.norm(position - np.array(frame.center)))

    def check(name: str, value: float, bounds: Any, slack: float, unit: str) -> None:
        if bounds and not bounds[0] - slack <= value <= bounds[1] + slack:
            out.append(f"{name} {value:.3g}{unit} is outside the model's trained range "
                       f"[{bounds[0]:.3g}, {bounds[1]:.3g}]{unit}")

    if view["kind"] == "orbit":
        check("azimuth", view["azimuth_deg"], envelope.get("azimuth_deg"), ENVELOPE_SLACK_DEG,
              " deg")
        check("elevation", view["elevation_deg"], envelope.get("elevation_deg"),
              ENVELOPE_SLACK_DEG, " deg")
    dist = envelope.get("distance")
    if dist:
        check("distance to the scene centre", distance, dist,
              ENVELOPE_SLACK_FRACTION * dist[1], "")
    lo, hi = envelope.get("position_min"), envelope.get("position_max")
    if view["kind"] == "pose" and lo and hi:
        span = max(float(np.max(np.subtract(hi, lo))), 1e-12)
        slack = ENVELOPE_SLACK_FRACTION * span
        if any(not a - slack <= p <= b + slack for p, a, b in zip(position, lo, hi, strict=True)):
            out.append("camera position is outside the box of the trained positions")
    return out


class Pipeline:
    """Scene + model + settings -> frames. Not thread-safe; one per worker process."""

    def __init__(self, model: Any, settings: FrameSettings, scene: Any, frame: SceneFrame,
                 cache_bytes: int = 256 * 2**20) -> None:
        self.model = model
        self.settings = settings
        self.scene = scene
        self.frame = frame
        self.encoder = Encoder(settings, cache_bytes)

    def compute(self, view: dict[str, Any]) -> Frame:
        from nhfd.scene.raster import render

        s = self.settings
        t: dict[str, float] = {}
        t0 = time.perf_counter()
        cam = render_camera(view, self.frame, self.model.metadata, s.window_hw)
        view_render = render(self.scene, cam)
        rgb = view_render.rgb
        t1 = time.perf_counter()
        t["render"] = t1 - t0
        meta = self.model.metadata
        x = network_input(rgb, self.model.inputs, depth=view_render.depth,
                          alpha=view_render.alpha, mapping=meta.get("mapping"),
                          volume_m=meta.get("volume_m"))  # fmt: skip
        amp, phase = self.model(x)
        t2 = time.perf_counter()
        t["inference"] = t2 - t1
        with torch.no_grad():
            slm = self.encoder.to_slm(reference_field(amp, phase, s.amplitude_scale))
            t3 = time.perf_counter()
            t["propagation"] = t3 - t2
            grey, clipped = self.encoder.code(slm)
        t["coding"] = time.perf_counter() - t3
        return Frame(self.encoder.region, grey, t, rgb, clipped)


def frame_window_hw(config: Any, metadata: dict[str, Any]) -> tuple[int, int]:
    """The frames' window (height, width): `daemon.frame_size_px` [W, H], or the model's
    training size when that is empty."""
    size = list(config.daemon.frame_size_px)
    if size:
        return int(size[1]), int(size[0])
    h, w = (int(v) for v in metadata["train_size_hw"])
    return h, w


def frame_settings(config: Any, metadata: dict[str, Any], *, refocus_m: float = 0.0
                   ) -> FrameSettings:
    """The settings of frames for a model under a configuration. The optics (z0, aperture,
    wavelengths, pitch) are the model's: `load_model` has already checked they match the
    configuration. The window is the model's training size unless `daemon.frame_size_px` says
    otherwise (the trained fx is kept either way)."""
    from nhfd.calibration import active_calibration

    window_hw = frame_window_hw(config, metadata)
    s = config.slm
    cal = active_calibration(config)  # measured curves and sign replace the configured ones
    return FrameSettings(
        panel_hw=(s.height_px, s.width_px),
        window_hw=window_hw,  # type: ignore[arg-type]
        pitch_m=float(metadata["pitch_m"]),
        wavelengths_m=tuple(float(v) for v in metadata["wavelengths_m"]),
        z0_m=float(metadata["z0_m"]),
        aperture_shape=str(metadata["aperture_shape"]),
        cutoff_per_px=tuple(float(v) for v in metadata["cutoff_per_px"]),
        amplitude_scale=float(metadata["amplitude_scale"]),
        zero_below=float(config.coding.zero_below),
        phase_stroke_rad=tuple(float(v) for v in s.phase_stroke_rad),
        phase_sign=int(cal.phase_sign if cal else s.phase_sign),
        grey_invert=bool(s.grey_invert),
        refocus_m=float(refocus_m),
        padding=config.optics.padding,
        phase_tables_rad=cal.phase_tables_rad if cal else (),
        colour_offset_m=tuple(cal.refocus_m(c) for c in range(3)) if cal else (),
        source_profile=tuple((cal.source_waist_m[c], *cal.source_centre_m[c])  # type: ignore[misc]
                             for c in range(3)) if cal and cal.source_waist_m else (),
        zernike_rad=cal.zernike_rad if cal else (),
        zernike_wavelength_m=cal.zernike_wavelength_m if cal else 0.0,
    )
