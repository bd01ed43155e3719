"""Capture calibration focal stacks into a directory with a manifest.

The capture talks to the bench through `BenchIO` (show a frame, move the stage, set the lasers,
capture a linear dark-subtracted image). `SimBenchIO` drives the twins directly (a `TrueBench`
and a `SimulatedCamera`); `DaemonBenchIO` drives a running daemon (`nhfd serve`, which owns the
devices) through its JSON-RPC methods show_pattern, stage_move, laser and capture.

The capture directory's layout and its names are `nhfd.calib.data`'s (the format's one owner,
read by the fit and the report); this module writes it.

Procedure: dark frame; a coarse green sweep over the user's stage range to locate the SLM plane
and the magnification (from the in-focus dots); a fine sweep per colour around it covering every
dot depth; the grating frames per colour at the located SLM plane.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from nhfd.daemon.protocol import RpcError
from nhfd.device_settings import CameraSettings
from nhfd.drivers.simcamera import SimulatedCamera
from nhfd.optics import PhaseCurve

from .data import DARK, FRAMES_DIR, IMAGES_DIR, MANIFEST, MANIFEST_VERSION, default_camera_pitch_m
from .fit import geometry_from, locate, measure_response
from .patterns import PatternSpec, dots_frame, flat_frames, grating_frames

COLOURS = ("R", "G", "B")
SWEEPS = ("coarse", "grating", "fine")


class CaptureError(RuntimeError):
    """The capture cannot go on (existing data without --force, a foreign manifest...)."""


class BenchIO(Protocol):
    """What the capture needs from a bench. Images are linear float32 [h, w], dark subtracted
    once `capture_dark` has run (mono camera)."""

    def show(self, frame: np.ndarray) -> None:
        """Show `frame` on the SLM: uint8 `[H, W, 3]`, the whole panel."""
        ...

    def move_stage(self, position_mm: float) -> float:
        """Move the stage to `position_mm` (mm); returns where it is (mm)."""
        ...

    def set_lasers(self, powers: tuple[float, float, float]) -> None:
        """Each colour's power (R, G, B), relative to its maximum in [0, 1]; 0 switches it off."""
        ...

    def capture_dark(self, frames: int) -> np.ndarray:
        """The dark frame, lasers off: `frames` images averaged, linear float32 `[h, w]`; later
        captures subtract it."""
        ...

    def capture(self, frames: int) -> tuple[np.ndarray, np.ndarray]:
        """`frames` images averaged: (linear, dark subtracted, float32 `[h, w]`; saturated pixels,
        bool `[h, w]`)."""
        ...


class SimBenchIO:
    """The twins driven directly: a `SimulatedCamera` imaging whatever was last shown.

    `roi` defaults to the sensor region that holds the panel's image (what a lab sets once)."""

    def __init__(self, bench: Any, panel_hw: tuple[int, int], *, exposure_s: float = 0.005,
                 roi: tuple[int, int, int, int] | None = None, noise_seed: int = 0) -> None:
        self.bench = bench
        self.frame = np.zeros((*panel_hw, 3), np.uint8)
        self.powers = (0.0, 0.0, 0.0)
        self.stage_mm = float(bench.stage_at_slm_mm)
        class _Camera(SimulatedCamera):
            # The panel's field depends on the frame only, not on the stage: a sweep shows one
            # frame at many positions, so remember the last one (the twin recomputes it).
            _memo: tuple[bytes, Any] | None = None

            def panel_field(self, frame: np.ndarray) -> Any:
                key = hashlib.blake2b(np.ascontiguousarray(frame).tobytes(),
                                      digest_size=16).digest()
                if self._memo is None or self._memo[0] != key:
                    self._memo = (key, super().panel_field(frame))
                return self._memo[1]

        self.camera = _Camera(
            lambda: self.frame, lambda: self.powers, lambda: self.stage_mm, bench,
            CameraSettings(exposure_s=exposure_s, channels="mono"),
            roi=roi or bench.roi_for_panel(panel_hw))
        self.camera.reseed(noise_seed)
        self.camera.open()

    def show(self, frame: np.ndarray) -> None:
        """Keep `frame` (uint8 `[H, W, 3]`): the twin camera images it."""
        self.frame = np.ascontiguousarray(frame, dtype=np.uint8)

    def move_stage(self, position_mm: float) -> float:
        """The stage at `position_mm` (mm) at once; returns it."""
        self.stage_mm = float(position_mm)
        return self.stage_mm

    def set_lasers(self, powers: tuple[float, float, float]) -> None:
        """The twin's powers (R, G, B), relative in [0, 1]."""
        self.powers = tuple(float(p) for p in powers)  # type: ignore[assignment]

    def capture_dark(self, frames: int) -> np.ndarray:
        """The twin camera's dark frame over `frames` images, float32 `[h, w]`."""
        return self.camera.capture_dark(frames)

    def capture(self, frames: int) -> tuple[np.ndarray, np.ndarray]:
        """`frames` images of the twin camera averaged: (linear `[h, w]`, saturated `[h, w]`
        bool)."""
        cap = self.camera.capture(frames)
        return cap.image, cap.saturated

    @property
    def exposure_s(self) -> float:
        """The twin camera's exposure (s)."""
        return self.camera.exposure_s


class DaemonBenchIO:
    """The bench through a running daemon (`nhfd.daemon.client.Client`, standard library only).

    Frames are written as .npy into `work_dir` (which must lie inside the daemon's
    `daemon.paths.pattern_dirs`) and shown with `show_pattern`; the stage moves with `stage_move`
    (raw positions, no calibration mapping); the lasers through `laser` power / enable /
    disable (arming is a person's act: done here only when `arm_s` is given, and only over the
    Unix socket); images come back from `capture` as linear .npy files. Each job is waited for.
    A mono camera is expected."""

    def __init__(self, client: Any, work_dir: Path | str, *, exposure_s: float = 0.005,
                 arm_s: float | None = None, home: bool = False, poll_s: float = 0.01,
                 job_timeout_s: float = 300.0) -> None:
        self.client = client
        self.work_dir = Path(work_dir).resolve()
        self.exposure_s = float(exposure_s)
        self.arm_s = arm_s
        self._home = home
        self.poll_s = poll_s
        self.job_timeout_s = job_timeout_s
        self._shown: bytes | None = None
        self._powers: tuple[float, ...] | None = None
        self.powers_applied = [0.0, 0.0, 0.0]  # as the daemon applied them (caps), relative
        self.calls: list[str] = []  # the daemon methods called, in order (for the curious)

    def _call(self, method: str, **params: Any) -> Any:
        self.calls.append(method)
        try:
            return self.client.call(method, **params)
        except RpcError as exc:
            raise CaptureError(f"daemon refused {method}: {exc.message}"
                               + (f" ({exc.data})" if exc.data else "")) from None

    def _wait(self, method: str, **params: Any) -> dict[str, Any]:
        return self._wait_job(method, self._call(method, **params)["job"])

    def _wait_job(self, method: str, job_id: int) -> dict[str, Any]:
        self.calls.append("job")
        try:
            job = self.client.wait_job(job_id, self.job_timeout_s, self.poll_s)
        except RpcError as exc:
            raise CaptureError(f"daemon refused job: {exc.message}") from None
        if job["state"] == "done":
            return job["result"]
        if job["state"] in ("failed", "cancelled"):
            raise CaptureError(f"daemon {method} job {job_id} {job['state']}: {job.get('error')}")
        raise CaptureError(f"daemon {method} job {job_id} still {job['state']} after "
                           f"{self.job_timeout_s:g} s")

    def show(self, frame: np.ndarray) -> None:
        """Show `frame` (uint8 `[H, W, 3]`) through `show_pattern`, as a .npy file in `work_dir`; a
        frame already shown is not sent again."""
        frame = np.ascontiguousarray(frame, dtype=np.uint8)
        key = hashlib.blake2b(frame.tobytes(), digest_size=16).digest() + \
            str(frame.shape).encode()
        if key == self._shown:
            return
        self.work_dir.mkdir(parents=True, exist_ok=True)
        path = self.work_dir / "shown.npy"
        tmp = self.work_dir / ".shown.tmp.npy"
        np.save(tmp, frame)
        os.replace(tmp, path)
        self._call("show_pattern", path=str(path))
        self._shown = key

    def move_stage(self, position_mm: float) -> float:
        """A `stage_move` job to `position_mm` (raw mm; the first move homes first when `home` was
        given), waited for; returns the daemon's reading (mm)."""
        result = self._wait("stage_move", position_mm=float(position_mm), home=self._home)
        self._home = False
        return float(result["stage_mm"])

    def set_lasers(self, powers: tuple[float, float, float]) -> None:
        """The powers (R, G, B, relative in [0, 1]) through `laser`: the colours at 0 disabled
        first, an arm only when `arm_s` is given and the arming has under 5 s left, then each power
        set and its diode enabled. `powers_applied` keeps what the daemon applied (its caps).
        CaptureError when the lasers are not armed and `arm_s` is None."""
        powers = tuple(float(p) for p in powers)
        if powers == self._powers:
            return
        names = ("red", "green", "blue")
        for c, (name, pw) in enumerate(zip(names, powers, strict=True)):  # off first
            if pw <= 0:
                self._call("laser", action="disable", channel=name)
                self.powers_applied[c] = 0.0
        if any(pw > 0 for pw in powers):
            laser = self._call("status")["laser"]
            if not laser.get("armed") or laser.get("armed_remaining_s", 0.0) < 5.0:
                if self.arm_s is None:
                    raise CaptureError("the lasers are not armed: arm them (nhfctl laser arm) "
                                       "or pass --arm SECONDS")
                reply = self._call("laser", action="arm", duration_s=float(self.arm_s))
                if reply.get("pending"):  # daemon.arming.confirm: a person confirms at the bench
                    print(reply.get("prompt", "confirm the arm at the bench"), flush=True)
                    self._wait_job("laser arm", reply["job"])
        for c, (name, pw) in enumerate(zip(names, powers, strict=True)):
            if pw > 0:
                reply = self._call("laser", action="power", channel=name, power_pct=100.0 * pw)
                self._call("laser", action="enable", channel=name)
                self.powers_applied[c] = float(reply.get("power_pct", 100.0 * pw)) / 100.0
        self._powers = powers

    def _image(self, name: str, frames: int, dark: bool) -> tuple[np.ndarray, np.ndarray]:
        self.work_dir.mkdir(parents=True, exist_ok=True)
        path = self.work_dir / name
        result = self._wait("capture", path=str(path), frames=int(frames),
                            exposure_s=self.exposure_s, dark=dark)
        self.exposure_s = float(result["exposure_s"])
        image = np.load(result["path"], allow_pickle=False)
        saturated = np.load(result["saturated_path"], allow_pickle=False)
        if image.ndim != 2:
            raise CaptureError(f"the daemon's camera gives {list(image.shape)} images: "
                               "calibration needs a mono camera")
        return image.astype(np.float32), saturated.astype(bool)

    def lasers_off(self) -> None:
        """Every diode disabled (best effort: for a capture that stopped half-way)."""
        import contextlib

        for name in ("red", "green", "blue"):
            with contextlib.suppress(Exception):
                self.client.call("laser", action="disable", channel=name)
        self._powers = None

    def capture_dark(self, frames: int) -> np.ndarray:
        """A dark `capture` job over `frames` images: linear float32 `[h, w]`."""
        return self._image("dark.npy", frames, True)[0]

    def capture(self, frames: int) -> tuple[np.ndarray, np.ndarray]:
        """A `capture` job over `frames` images: (linear, dark subtracted, float32 `[h, w]`;
        saturated `[h, w]` bool). CaptureError for a camera that is not mono."""
        return self._image("capture.npy", frames, False)


class DevicesBenchIO:
    """The bench's drivers driven directly (`nhfd.drivers.factory.make_bench`'s `BenchDevices`:
    SLM, laser, stage and camera in this process), as the daemon's capture job drives them: each
    capture first waits out the SLM's settle time, which is none when the SLM's flip output is
    wired to the camera's trigger (`[devices.trigger]`): the camera's exposure then starts on
    the flip's edge (nhfd.drivers.trigger). The person running it arms the lasers (`arm_s`).
    `waited_s` sums the time captures spent waiting for the panel (settle or trigger)."""

    def __init__(self, devices: Any, *, exposure_s: float = 0.005, arm_s: float = 600.0) -> None:
        self.devices = devices
        self.devices.camera.set_exposure(exposure_s)
        self.powers_applied = [0.0, 0.0, 0.0]
        self.waited_s = 0.0
        self._shown: bytes | None = None
        self._powers: tuple[float, ...] | None = None
        self._arm_s = arm_s
        if devices.slm.last_frame is None:
            # A triggered camera exposes on a flip: the panel shows something from the start
            # (as the daemon's blank at start-up).
            devices.slm.blank()
        stage = devices.stage
        if stage.settings.require_homed and not stage.state().homed:
            stage.home()

    @property
    def exposure_s(self) -> float:
        """The camera's exposure (s)."""
        return float(self.devices.camera.exposure_s)

    def show(self, frame: np.ndarray) -> None:
        """Show `frame` (uint8 `[H, W, 3]`) on the SLM; a frame already shown is not sent again."""
        frame = np.ascontiguousarray(frame, dtype=np.uint8)
        key = hashlib.blake2b(frame.tobytes(), digest_size=16).digest() + \
            str(frame.shape).encode()
        if key != self._shown:  # as DaemonBenchIO: a frame already up is not sent again
            # The patterns are [H, W, 3]; the SLM takes [H, W] or [3, H, W] (a view, no copy).
            self.devices.slm.show(frame.transpose(2, 0, 1) if frame.ndim == 3 else frame)
            self._shown = key

    def move_stage(self, position_mm: float) -> float:
        """Move the stage to `position_mm` (mm); returns its reading (mm)."""
        state = self.devices.stage.move_to(float(position_mm))
        return float(state.position_mm if state else position_mm)

    def set_lasers(self, powers: tuple[float, float, float]) -> None:
        """The powers (R, G, B, relative in [0, 1]): the colours at 0 switched off first, the laser
        armed for `arm_s` when under 5 s are left, then each power set and its diode on.
        `powers_applied` keeps what the laser applied (its caps)."""
        powers = tuple(float(p) for p in powers)
        if powers == self._powers:
            return
        laser = self.devices.laser
        names = ("red", "green", "blue")
        for c, (name, pw) in enumerate(zip(names, powers, strict=True)):
            if pw <= 0:
                laser.enable(name, False)
                self.powers_applied[c] = 0.0
        if any(pw > 0 for pw in powers) and laser.armed_remaining_s < 5.0:
            laser.arm(self._arm_s)
        for c, (name, pw) in enumerate(zip(names, powers, strict=True)):
            if pw > 0:
                self.powers_applied[c] = laser.set_power(name, 100.0 * pw) / 100.0
                laser.enable(name)
        self._powers = powers

    def _settled(self) -> None:
        t0 = time.monotonic()
        self.devices.slm.wait_settled()  # 0 s with a trigger: the camera waits on the edge
        self.waited_s += time.monotonic() - t0

    def capture_dark(self, frames: int) -> np.ndarray:
        """The camera's dark frame over `frames` images, once the panel has settled: float32 `[h,
        w]`."""
        self._settled()
        return self.devices.camera.capture_dark(frames)

    def capture(self, frames: int) -> tuple[np.ndarray, np.ndarray]:
        """`frames` images averaged once the panel has settled (or on the trigger's edge): (linear
        `[h, w]`, saturated `[h, w]` bool). Adds the wait to `waited_s`."""
        self._settled()
        line = self.devices.camera.trigger
        before = len(line.record) if line is not None else 0
        called = time.monotonic()
        cap = self.devices.camera.capture(frames)
        if line is not None:  # the wait for the edge (+ delay), on the line's clock
            self.waited_s += sum(max(0.0, r.exposure_start_s - called)
                                 for r in line.record[before:])
        return cap.image, cap.saturated


def daemon_spec(status: dict[str, Any], **kw: Any) -> PatternSpec:
    """The patterns for the daemon's whole panel (its `status`: panel size, pitch, wavelengths)."""
    panel = status["panel"]
    return PatternSpec((int(panel["height_px"]), int(panel["width_px"])), float(panel["pitch_m"]),
                       tuple(float(x) for x in panel["wavelengths_m"]), **kw)  # type: ignore[arg-type]


@dataclass
class CapturePlan:
    """User choices. Stage positions in mm; `depth_margin_m` widens the fine sweep beyond the
    dot depths (SLM space) so each dot's focus curve is sampled on both sides."""

    stage_center_mm: float = 10.0
    stage_range_mm: float = 2.5
    coarse_step_mm: float = 0.25
    fine_steps: int = 17
    depth_margin_m: float = 1.2e-3
    burst: int = 1
    power: float = 1.0
    exposure_s: float = 0.005
    # The camera's pixel pitch (sensor metres): turns pixels per SLM metre into magnification.
    camera_pitch_m: float = field(default_factory=default_camera_pitch_m)
    # The last sweep captured: "coarse" (dark + coarse sweep + locate), "grating" (also the
    # grating and flat frames) or "fine" (everything). Shorter captures are for checks only.
    stop_after: str = "fine"

    def __post_init__(self) -> None:
        for name in ("stage_range_mm", "coarse_step_mm", "depth_margin_m", "exposure_s",
                     "camera_pitch_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v!r}: must be finite and > 0")
        if self.fine_steps < 1:
            raise ValueError(f"fine_steps = {self.fine_steps}: must be >= 1")
        if not 0 < self.power <= 1:
            raise ValueError(f"power = {self.power}: must be in (0, 1]")
        if self.burst < 1:
            raise ValueError(f"burst = {self.burst}: must be >= 1")
        if self.stop_after not in SWEEPS:
            raise ValueError(f"stop_after = {self.stop_after!r}: one of {', '.join(SWEEPS)}")


def _write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def _save_npz(path: Path, **arrays: np.ndarray) -> None:
    tmp = path.with_name(f".{path.stem}.tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


class Capture:
    """One capture directory being written (resumable)."""

    def __init__(self, out: Path, io: BenchIO, spec: PatternSpec, plan: CapturePlan,
                 *, force: bool = False, progress: Callable[[str], None] | None = None) -> None:
        self.out = Path(out)
        self.io = io
        self.spec = spec
        self.plan = plan
        self.progress = progress or (lambda _msg: None)
        manifest = self.out / MANIFEST
        if manifest.exists() and not force:
            old = json.loads(manifest.read_text())
            if old.get("kind") != "nhfd-calib-capture":
                raise CaptureError(f"{manifest}: not an nhfd calibration capture")
            if old.get("complete"):
                raise CaptureError(f"{self.out} holds a complete capture: use --force to "
                                   "overwrite it")
            if old.get("spec") != spec.to_dict():
                raise CaptureError(f"{self.out} holds an interrupted capture of other patterns:"
                                   " use --force to start again")
            self.manifest = old
            self.progress(f"resuming: {len(old['records'])} images already captured")
        else:
            if self.out.exists() and any(self.out.iterdir()) and not force and \
                    not manifest.exists():
                raise CaptureError(f"{self.out} exists and is not empty: use --force")
            self.manifest = {
                "kind": "nhfd-calib-capture", "version": MANIFEST_VERSION, "complete": False,
                "spec": spec.to_dict(), "plan": plan.__dict__.copy(), "frames": {},
                "records": [], "dark": None, "located": None,
            }
        (self.out / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
        (self.out / FRAMES_DIR).mkdir(exist_ok=True)
        self._done = {r["key"] for r in self.manifest["records"]}

    # -- helpers -----------------------------------------------------------------------------

    def _save(self) -> None:
        _write_json(self.out / MANIFEST, self.manifest)

    def _frame(self, name: str, frame: np.ndarray) -> None:
        path = self.out / FRAMES_DIR / f"{name}.npy"
        np.save(path, frame)
        self.manifest["frames"][name] = f"{FRAMES_DIR}/{name}.npy"

    def _shoot(self, key: str, frame_name: str, frame: np.ndarray, colour: int,
               stage_mm: float, **extra: Any) -> None:
        if key in self._done:
            return
        self.io.show(frame)
        actual = self.io.move_stage(stage_mm)
        powers = [0.0, 0.0, 0.0]
        powers[colour] = self.plan.power
        self.io.set_lasers(tuple(powers))  # type: ignore[arg-type]
        # What the bench applied (a daemon's laser caps power): relative, per colour.
        applied = [float(x) for x in getattr(self.io, "powers_applied", powers)]
        image, saturated = self.io.capture(self.plan.burst)
        self.io.set_lasers((0.0, 0.0, 0.0))
        _save_npz(self.out / IMAGES_DIR / f"{key}.npz", image=image.astype(np.float32),
                  saturated=saturated.astype(bool))
        self.manifest["records"].append({
            "key": key, "file": f"{IMAGES_DIR}/{key}.npz", "frame": frame_name, "colour": colour,
            "stage_mm": float(actual),
            "exposure_s": float(getattr(self.io, "exposure_s", self.plan.exposure_s)),
            "powers": powers, "burst": self.plan.burst,
            "powers_applied": applied,
            "saturated_fraction": float(saturated.mean()), **extra})
        self._done.add(key)
        self._save()

    def _flats(self, stage_mm: float) -> None:
        """Flat frames per colour at the SLM plane (nhfd.calib.patterns.flat_frames): the
        source's amplitude profile and the zero-order leakage are fitted from them."""
        for grey, frame in flat_frames(self.spec):
            name = f"flat_{grey:03d}"
            self._frame(name, frame)
            for c in range(3):
                self._shoot(f"{name}_{COLOURS[c]}", name, frame, c, stage_mm, sweep="flat",
                            grey=grey)

    # -- the procedure -------------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        """Run the procedure (the module's docstring), skipping every image already captured;
        returns the manifest, marked complete."""
        p = self.plan
        if self.manifest["dark"] is None:
            self.io.set_lasers((0.0, 0.0, 0.0))
            dark = self.io.capture_dark(max(p.burst, 4))
            _save_npz(self.out / DARK, image=dark.astype(np.float32))
            self.manifest["dark"] = DARK
            self._save()
        self.progress("computing the dot hologram")
        dots = dots_frame(self.spec)
        self._frame("dots", dots)
        n = round(2 * p.stage_range_mm / p.coarse_step_mm) + 1
        coarse = np.linspace(p.stage_center_mm - p.stage_range_mm,
                             p.stage_center_mm + p.stage_range_mm, n)
        for k, s in enumerate(coarse):
            self._shoot(f"coarse_G_{k:03d}", "dots", dots, 1, float(s), sweep="coarse")
        self.progress(f"coarse sweep: {n} images")
        if self.manifest["located"] is None:
            recs = [r for r in self.manifest["records"] if r.get("sweep") == "coarse"]
            self.manifest["located"] = locate(self.out, self.spec, recs, p.camera_pitch_m)
            self._save()
        if p.stop_after == "coarse":
            return self._complete()
        loc = self.manifest["located"]
        s0, scale = loc["stage_at_slm_mm"], loc["stage_scale"]
        # Gratings first: their response curves code the dots of the fine sweep, so the dots
        # carry little coding haze (whose interference with a dot skews its focus curve).
        for f, frame in enumerate(grating_frames(self.spec)):
            name = f"grating_{f:02d}"
            self._frame(name, frame)
            for c in range(3):
                self._shoot(f"{name}_{COLOURS[c]}", name, frame, c, float(s0),
                            sweep="grating", grating_frame=f)
        self._flats(float(s0))
        if p.stop_after == "grating":
            return self._complete()
        recs = [r for r in self.manifest["records"] if r.get("sweep") in ("grating", "flat")]
        curves = [PhaseCurve(tuple(t)) for t in
                  measure_response(self.out, self.spec, recs, geometry_from(loc)).tables_rad]
        pair = {"dots_fine": dots_frame(self.spec, curves),
                "dots_fine_pi": dots_frame(self.spec, curves, math.pi)}
        for name, frame in pair.items():
            self._frame(name, frame)
        zmin = min(self.spec.depths_m) - p.depth_margin_m
        zmax = max(self.spec.depths_m) + p.depth_margin_m
        fine = s0 + np.linspace(zmin, zmax, p.fine_steps) / scale * 1e3 if p.fine_steps > 1 \
            else np.array([s0])
        for c in range(3):
            for k, s in enumerate(fine):
                for name, frame in pair.items():
                    self._shoot(f"fine_{COLOURS[c]}_{k:03d}{name[9:]}", name, frame, c,
                                float(s), sweep="fine", step=k)
            self.progress(f"fine sweep {COLOURS[c]}: {len(fine)} positions x 2 frames")
        return self._complete()

    def _complete(self) -> dict[str, Any]:
        self.manifest["complete"] = True
        self._save()
        self.progress(f"capture complete: {len(self.manifest['records'])} images in {self.out}")
        return self.manifest


def capture(out: Path | str, io: BenchIO, spec: PatternSpec, plan: CapturePlan | None = None,
            *, force: bool = False, progress: Callable[[str], None] | None = None
            ) -> dict[str, Any]:
    """Capture (or resume) a calibration data set into `out`; returns the manifest."""
    return Capture(Path(out), io, spec, plan or CapturePlan(), force=force,
                   progress=progress).run()
