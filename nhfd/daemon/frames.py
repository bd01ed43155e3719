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

from nhfd.optics import Aperture, KernelCache, PhaseCurve, double_phase, phase_to_grey, propagate
from nhfd.optics.refplane import margin_px, window_offset

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
        if self.phase_tables_rad:
            return [PhaseCurve(table) for table in self.phase_tables_rad]
        return [PhaseCurve.linear(stroke) for stroke in self.phase_stroke_rad]


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
    """The whole panel coding zero amplitude, through the same curves as frames."""
    return zero_amplitude_grey(s.panel_hw, s.curves(), s.phase_sign, s.grey_invert)


def zero_amplitude_grey(panel_hw: tuple[int, int], curves: list[PhaseCurve], sign: int,
                        invert: bool) -> np.ndarray:
    """`[C, H, W]` uint8 grey levels that show nothing: double-phase coding of amplitude 0 is
    +pi/2 / -pi/2 on the pixel checkerboard (+ on even row + col), which the aperture blocks.
    The one definition of the blank pattern (the daemon's `blank` shows it too)."""
    pair = torch.tensor([math.pi / 2, -math.pi / 2], dtype=torch.float64).expand(
        len(curves), 1, 2).contiguous()
    grey = phase_to_grey(pair, curves, sign=sign, invert=invert).numpy()
    rows = np.arange(panel_hw[0])[:, None]
    cols = np.arange(panel_hw[1])[None, :]
    even = (rows + cols) % 2 == 0
    return np.stack([np.where(even, grey[c, 0, 0], grey[c, 0, 1])
                     for c in range(grey.shape[0])]).astype(np.uint8)


@dataclass
class Frame:
    """One computed frame: the coded region (grey `[3, h, w]` uint8) and where it goes, the
    rendered view (sRGB `[3, H, W]` float32) and the seconds each stage took."""

    region: Region
    grey: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)
    rgb: np.ndarray | None = None
    clipped_fraction: tuple[float, ...] = ()


class Encoder:
    """Reference-plane field -> coded grey region; owns the kernel cache and the zero pattern."""

    def __init__(self, settings: FrameSettings, cache_bytes: int = 256 * 2**20) -> None:
        self.settings = settings
        self.region = frame_region(settings)
        self.cache = KernelCache(cache_bytes)
        self.curves = settings.curves()
        self._zero: np.ndarray | None = None
        self._gain_map: torch.Tensor | None = None

    @property
    def zero(self) -> np.ndarray:
        if self._zero is None:  # 6 MB at 1920 x 1080: only where a full panel is wanted
            self._zero = zero_pattern(self.settings)
        return self._zero

    def to_slm(self, reference: torch.Tensor) -> torch.Tensor:
        """Window field `[3, h, w]` on the reference plane -> region field on the SLM plane."""
        s, r = self.settings, self.region
        h, w = reference.shape[-2:]
        buf = torch.zeros((reference.shape[0], r.height, r.width), dtype=torch.complex64)
        buf[:, r.window_top : r.window_top + h, r.window_left : r.window_left + w] = reference
        zs = s.colour_propagation_z_m
        if any(s.zernike_rad):
            return self._to_slm_precompensated(buf, zs)
        if len(set(zs)) == 1:
            return propagate(buf, zs[0], s.pitch_m, s.wavelengths_m,
                             padding=s.padding, aperture=s.aperture, cache=self.cache)  # type: ignore[arg-type]
        # Per-colour depths (calibrated focus offsets): one kernel per colour, each cached.
        cutoffs = s.aperture.cutoffs(len(zs))
        return torch.cat([
            propagate(buf[c : c + 1], z, s.pitch_m, [s.wavelengths_m[c]], padding=s.padding,  # type: ignore[arg-type]
                      aperture=Aperture(s.aperture.shape, (cutoffs[c],)), cache=self.cache)
            for c, z in enumerate(zs)])

    def _to_slm_precompensated(self, buf: torch.Tensor, zs: tuple[float, ...]) -> torch.Tensor:
        """Per colour: the ASM kernel (nhfd.optics) times the conjugate of the relay's pupil
        phase, cached under a key that names the aberration (a kernel for other coefficients
        is never reused)."""
        from nhfd.calib.bench_model import pupil_phase
        from nhfd.optics.asm import transfer_function
        from nhfd.optics.padding import plan_padding

        s = self.settings
        h, w = buf.shape[-2:]
        cutoffs = s.aperture.cutoffs(len(zs))
        lam_ref = s.zernike_wavelength_m or s.wavelengths_m[len(s.wavelengths_m) // 2]
        out = []
        for c, z in enumerate(zs):
            lam = s.wavelengths_m[c]
            ap = Aperture(s.aperture.shape, (cutoffs[c],))
            plan = plan_padding((h, w), s.pitch_m, (lam,), abs(z), ap, s.padding)  # type: ignore[arg-type]

            def kernel(plan: object = plan, z: float = z, lam: float = lam, ap: Aperture = ap,
                       c: int = c) -> torch.Tensor:
                hw = plan.padded_hw  # type: ignore[attr-defined]
                k = transfer_function(hw, s.pitch_m, [lam], [z], aperture=ap)[0, 0]
                ph = pupil_phase(hw, cutoffs[c], tuple(s.zernike_rad), lam_ref / lam)
                return k * torch.polar(torch.ones_like(ph), -ph).to(k.dtype)

            key = ("asm-pupil", plan.padded_hw, s.pitch_m, lam, z, ap, tuple(s.zernike_rad),
                   lam_ref)
            k = self.cache.get(key, kernel)
            spec = torch.fft.fft2(buf[c], s=plan.padded_hw)
            out.append(torch.fft.ifft2(spec * k)[:h, :w])
        return torch.stack(out)

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

        No antialias pass: the propagation kernel already applied the aperture."""
        s = self.settings
        gain = self.amplitude_gain_map()
        if gain is not None:
            slm_field = slm_field * gain
        coded = double_phase(slm_field, s.amplitude_scale, zero_below=s.zero_below)
        grey = phase_to_grey(coded.phase_rad, self.curves, sign=s.phase_sign,
                             invert=s.grey_invert)
        return grey.numpy(), tuple(float(c) for c in coded.clipped_fraction)

    def panel(self, grey: np.ndarray) -> np.ndarray:
        """The full panel frame: the zero pattern with the coded region pasted in."""
        out = self.zero.copy()
        out[:, self.region.rows, self.region.cols] = grey
        return out


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
        rgb = render(self.scene, cam).rgb
        t1 = time.perf_counter()
        t["render"] = t1 - t0
        amp, phase = self.model(rgb)
        t2 = time.perf_counter()
        t["inference"] = t2 - t1
        with torch.no_grad():
            slm = self.encoder.to_slm(reference_field(amp, phase, s.amplitude_scale))
            t3 = time.perf_counter()
            t["propagation"] = t3 - t2
            grey, clipped = self.encoder.code(slm)
        t["coding"] = time.perf_counter() - t3
        return Frame(self.encoder.region, grey, t, rgb, clipped)


def frame_settings(config: Any, metadata: dict[str, Any], *, refocus_m: float = 0.0
                   ) -> FrameSettings:
    """The settings of frames for a model under a configuration. The optics (z0, aperture,
    wavelengths, pitch) are the model's: `load_model` has already checked they match the
    configuration. The window is the model's training size unless `daemon.frame_size_px` says
    otherwise (the trained fx is kept either way)."""
    from nhfd.calib.active import active_calibration

    size = list(config.daemon.frame_size_px)
    window_hw = (size[1], size[0]) if size else tuple(int(v) for v in metadata["train_size_hw"])
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
