"""The simulated bench, calibrated: a `TrueBench` twin's calibration (captured and fitted once
per twin and panel, then reused) and its devices with the laser armed, for `nhfd refine --sim`
and `nhfd bench quality`, which drive the twin themselves (a real bench's lasers are armed by a
person, through the daemon)."""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from nhfd.calibration import Calibration, CalibrationFileError
from nhfd.config import Config, DeviceSettings
from nhfd.device_settings import COLOURS
from nhfd.drivers.factory import BenchDevices, make_bench
from nhfd.drivers.simcamera import TrueBench

from .capture import CapturePlan, SimBenchIO, capture
from .fit import fit_capture
from .patterns import PatternSpec

# The panel is the window plus this margin on each side (the twin simulates the whole panel, so
# every camera capture costs in proportion to it; a frame's region reaches 24 px beyond the
# window at the packaged optics).
SIM_PANEL_MARGIN_PX = 64
SIM_BENCH_SEED = 7  # TrueBench.randomised: phase sign -1, no mirror, M ~ 1.12
SIM_POWER_PCT = 10.0  # the simulated laser's cap
SIM_ARM_S = 900.0  # the longest arming the laser accepts
# The in-process simulated bench's stage: the settings' caps (`devices.apt`). The twin's light
# and panel are instantaneous, so at a real actuator's 2 mm/s and 50 ms settle the waits were
# most of a capture's wall time (38 of 60 s in a learned-tier run); a real bench's time is the
# plans' printed estimate, not the twin's.
SIM_STAGE_VELOCITY_MM_S = 50.0
SIM_STAGE_ACCELERATION_MM_S2 = 100.0


def sim_panel_hw(window_hw: tuple[int, int], margin_px: int = SIM_PANEL_MARGIN_PX
                 ) -> tuple[int, int]:
    """The simulated bench's panel (h, w px): the window plus `margin_px` on each side."""
    return window_hw[0] + 2 * margin_px, window_hw[1] + 2 * margin_px


def _twin_key(twin: TrueBench, panel_hw: tuple[int, int]) -> str:
    return hashlib.sha256(f"{twin!r} {tuple(panel_hw)}".encode()).hexdigest()[:16]


def twin_calibration(folder: Path, twin: TrueBench, panel_hw: tuple[int, int], *,
                     say: Callable[[str], None] = print) -> Calibration:
    """The twin's calibration on a `panel_hw` panel: `folder`/calibration.toml when it was
    fitted for this twin and panel (`twin.json` says so), else a capture (the small pattern
    set the calibration tests use: 3 reference and 13 test grey levels) into `folder`/capture
    and its fit (minutes at 416 x 640 on 2 cores)."""
    folder = Path(folder)
    toml, stamp = folder / "calibration.toml", folder / "twin.json"
    key = _twin_key(twin, panel_hw)
    if toml.is_file() and stamp.is_file():
        try:
            ok = json.loads(stamp.read_text()).get("key") == key
        except ValueError:
            ok = False
        if ok:
            try:
                cal = Calibration.load(toml)
            except CalibrationFileError as exc:
                say(f"calibration {toml}: {exc}; capturing again")
            else:
                say(f"calibration {toml} (reused: this twin and panel)")
                return cal
    folder.mkdir(parents=True, exist_ok=True)
    stamp.unlink(missing_ok=True)
    t0 = time.perf_counter()
    say(f"calibrating the simulated bench ({panel_hw[1]} x {panel_hw[0]} panel) into {folder}")
    spec = PatternSpec(tuple(panel_hw), twin.pitch_m, twin.wavelengths_m, refs=(0, 96, 176),
                       tests=tuple(range(8, 256, 20)))
    plan = CapturePlan(stage_center_mm=10.0, stage_range_mm=2.5, coarse_step_mm=0.5,
                       fine_steps=13, camera_pitch_m=twin.camera_pitch_m)
    capture(folder / "capture", SimBenchIO(twin, tuple(panel_hw), noise_seed=3), spec, plan,
            force=True)
    cal = fit_capture(folder / "capture")
    cal.save(toml)
    stamp.write_text(json.dumps({"key": key, "panel_hw": list(panel_hw),
                                 "seconds": round(time.perf_counter() - t0, 1)}))
    say(f"calibrated in {time.perf_counter() - t0:.0f} s: {toml}")
    return Calibration.load(toml)


def quick_sim_devices(**camera: object) -> DeviceSettings:
    """The packaged simulated devices made quick for the in-process simulated bench: a mono
    camera (on the sensor region that holds the panel's image, as in its calibration;
    `camera` sets more of its settings), no settle after a frame, the stage at
    `SIM_STAGE_VELOCITY_MM_S` (homing too: the simulated controller homes at its velocity)."""
    d = Config().devices
    return d.model_copy(update={
        "camera_settings": d.camera_settings.model_copy(update={"channels": "mono", **camera}),
        "slm_output": d.slm_output.model_copy(update={"settle_ms": 0.0}),
        "apt": d.apt.model_copy(update={"velocity_mm_s": SIM_STAGE_VELOCITY_MM_S,
                                        "acceleration_mm_s2": SIM_STAGE_ACCELERATION_MM_S2})})


@contextmanager
def sim_devices(twin: TrueBench, panel_hw: tuple[int, int], *, power_pct: float = SIM_POWER_PCT,
                devices: DeviceSettings | None = None) -> Iterator[BenchDevices]:
    """The simulated bench over `twin` (`devices`, by default `quick_sim_devices()`; a mono
    camera either way), its laser armed (`SIM_ARM_S`; `arm_twin` re-arms) with every colour at
    `power_pct`. Closing switches every laser off."""
    d = devices if devices is not None else quick_sim_devices()
    d = d.model_copy(update={"camera_settings": d.camera_settings.model_copy(
        update={"channels": "mono"})})
    with make_bench(d, panel_hw[1], panel_hw[0], bench=twin,
                    roi=twin.roi_for_panel(panel_hw)) as devices:
        arm_twin(devices)
        for name in COLOURS:
            devices.laser.set_power(name, power_pct)
        yield devices


def arm_twin(devices: BenchDevices) -> None:
    """Arm the simulated laser for SIM_ARM_S (before each citl frame: a long one may outlast
    an arming)."""
    devices.laser.arm(SIM_ARM_S)
