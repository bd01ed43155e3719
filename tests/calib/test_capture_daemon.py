"""`nhfd calib capture` through a real daemon on the simulated bench: the calibration methods
(show_pattern, stage_move, capture), a short capture that is interrupted and resumed, images equal
to the direct path's, and paths outside daemon.paths.pattern_dirs refused."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from daemon.conftest import Running, bench_config, running_daemon

from nhfd.calib.capture import (
    CaptureError,
    CapturePlan,
    DaemonBenchIO,
    SimBenchIO,
    capture,
    daemon_spec,
)
from nhfd.daemon.protocol import RpcError
from nhfd.drivers.simcamera import TrueBench

PANEL_HW = (128, 128)


def daemon_config(root: Path) -> Any:
    roi = list(TrueBench().roi_for_panel(PANEL_HW))  # the daemon's simulated camera's bench
    config = bench_config(root, None, frames={"colour_mode": "hw-sync"},
                          bench={"camera_roi_px": roi},
                          paths={"pattern_dirs": [str(root / "calib")]})
    d = config.devices
    devices = d.model_copy(update={
        "camera": "simulated",
        "slm_output": d.slm_output.model_copy(update={"settle_ms": 1.0}),
        "apt": d.apt.model_copy(update={"velocity_mm_s": 50.0, "acceleration_mm_s2": 100.0,
                                        "require_homed": False})})
    slm = config.slm.model_copy(update={"width_px": PANEL_HW[1], "height_px": PANEL_HW[0]})
    return config.model_copy(update={"devices": devices, "slm": slm})


@pytest.fixture(scope="module")
def daemon() -> Iterator[tuple[Running, Path]]:
    with running_daemon(daemon_config, "nhfd-c-") as (r, root):
        yield r, root


def plan() -> CapturePlan:
    # The default TrueBench images the SLM plane at 10 mm: a five-position coarse sweep.
    return CapturePlan(stage_center_mm=10.0, stage_range_mm=1.0, coarse_step_mm=0.5,
                       camera_pitch_m=TrueBench().camera_pitch_m, stop_after="coarse", burst=4)


class Interrupted(Exception):
    pass


class Flaky:
    """A BenchIO that fails at its n-th capture (a capture cut short)."""

    def __init__(self, io: DaemonBenchIO, fail_at: int) -> None:
        self.io, self.left = io, fail_at

    def __getattr__(self, name: str) -> Any:
        return getattr(self.io, name)

    def capture(self, frames: int) -> Any:
        self.left -= 1
        if self.left == 0:
            raise Interrupted
        return self.io.capture(frames)


def test_capture_through_the_daemon(daemon: tuple[Running, Path]) -> None:
    r, root = daemon
    c = r.client(timeout_s=30.0)
    out = root / "calib" / "run1"
    spec = daemon_spec(c.status())
    assert spec.panel_hw == PANEL_HW
    io = DaemonBenchIO(c, out / "daemon", exposure_s=0.005, arm_s=60.0)
    with pytest.raises(Interrupted):
        capture(out, Flaky(io, 3), spec, plan())
    partial = json.loads((out / "manifest.json").read_text())
    assert not partial["complete"] and len(partial["records"]) == 2
    said: list[str] = []
    manifest = capture(out, io, spec, plan(), progress=said.append)
    assert "resuming: 2 images already captured" in said
    io.lasers_off()

    # The manifest: stage positions, exposures, powers and the frames shown.
    recs = manifest["records"]
    assert manifest["complete"] and [r_["key"] for r_ in recs] == [
        f"coarse_G_{k:03d}" for k in range(5)]
    assert [r_["stage_mm"] for r_ in recs] == pytest.approx([9.0, 9.5, 10.0, 10.5, 11.0], abs=1e-3)
    cap = r.daemon.laser.settings.max_power_pct[1] / 100  # the laser's cap applies
    assert all(r_["exposure_s"] == 0.005 and r_["burst"] == 4 and r_["powers"] == [0.0, 1.0, 0.0]
               and r_["powers_applied"] == [0.0, cap, 0.0] and r_["frame"] == "dots"
               for r_ in recs)
    assert manifest["frames"] == {"dots": "frames/dots.npy"} and manifest["dark"] == "dark.npz"
    status = c.status()
    assert status["display"].startswith("calibration pattern ")
    assert status["laser"]["channels"]["green"]["enabled"] is False

    # The dots appear where the geometry says: locate() found the true bench's.
    true = TrueBench()
    loc = manifest["located"]
    assert loc["magnification"] == pytest.approx(true.magnification, rel=0.01)
    assert loc["rotation_deg"] == pytest.approx(true.rotation_deg, abs=0.5)
    assert loc["mirror_x"] == true.mirror_x
    assert loc["stage_at_slm_mm"] == pytest.approx(true.stage_at_slm_mm, abs=0.1)

    # The same image as the direct path (the same bench, frame, stage, power and region) within
    # the noise.
    rec = recs[2]
    direct = SimBenchIO(true, PANEL_HW, exposure_s=0.005, roi=tuple(r.daemon.config.daemon
                                                                    .bench.camera_roi_px))
    direct.capture_dark(4)
    direct.show(np.load(out / manifest["frames"]["dots"]))
    direct.move_stage(rec["stage_mm"])
    direct.set_lasers((0.0, cap, 0.0))
    want, _ = direct.capture(4)
    got = np.load(out / rec["file"])["image"]
    assert got.shape == want.shape
    bright = want > 0.2 * want.max()
    assert bright.mean() > 0.005
    rel = np.abs(got - want)[bright].mean() / want[bright].mean()
    assert rel < 0.1, rel  # 0.045 measured (shot and read noise of 4-frame bursts)
    assert np.corrcoef(got.ravel(), want.ravel())[0, 1] > 0.95

    # A complete capture is not overwritten.
    with pytest.raises(CaptureError, match="--force"):
        capture(out, io, spec, plan())


def test_calibration_methods_refuse_clearly(daemon: tuple[Running, Path]) -> None:
    r, root = daemon
    c = r.client()
    outside = root / "elsewhere"
    outside.mkdir(exist_ok=True)
    np.save(outside / "f.npy", np.zeros(PANEL_HW, np.uint8))
    with pytest.raises(RpcError) as info:
        c.call("show_pattern", path=str(outside / "f.npy"))
    assert info.value.data["field"] == "path" and "outside the allowed" in info.value.message
    assert info.value.data["allowed"] == [str((root / "calib").resolve())]
    with pytest.raises(RpcError) as info:
        c.call("capture", path="/tmp/x.npy")
    assert info.value.data["field"] == "path"
    # The capture path refuses a capture directory outside the allowed ones, naming them.
    io = DaemonBenchIO(c, outside / "daemon")
    with pytest.raises(CaptureError, match="outside the allowed directories"):
        io.show(np.zeros((*PANEL_HW, 3), np.uint8))

    allowed = root / "calib"
    allowed.mkdir(exist_ok=True)
    for name, array, what in [("wrong.npy", np.zeros((64, 64), np.uint8), "shape [64, 64]"),
                              ("float.npy", np.zeros(PANEL_HW, np.float32), "not uint8")]:
        np.save(allowed / name, array)
        with pytest.raises(RpcError) as info:
            c.call("show_pattern", path=name)
        assert what in info.value.message and "uint8 [3, 128, 128]" in info.value.data["allowed"]
    np.save(allowed / "ok.npy", np.full((3, *PANEL_HW), 7, np.uint8))
    assert c.call("show_pattern", path="ok.npy")["shape"] == [3, *PANEL_HW]
    assert np.all(r.daemon.bench.slm.last_frame == 7)
    assert c.status()["display"] == f"calibration pattern {(allowed / 'ok.npy').resolve()}"
    c.call("set_view", orbit={"azimuth_deg": 0, "elevation_deg": 0, "radius": 1})
    assert r.daemon.panel.pattern is None and c.status()["display"] == "blank"  # no model yet
    assert not np.any(r.daemon.bench.slm.last_frame == 7)
    c.call("show_pattern", path="ok.npy")
    c.call("blank")
    assert c.status()["display"] == "blank" and r.daemon.panel.pattern is None

    with pytest.raises(RpcError) as info:
        c.call("stage_move", position_mm=30.0)
    assert info.value.data["field"] == "position_mm" and "[0, 25]" in info.value.data["allowed"]


def test_cli_capture_through_the_daemon(daemon: tuple[Running, Path], capsys) -> None:
    from nhfd.cli.main import main

    r, root = daemon
    out = root / "calib" / "cli"
    args = ["calib", "capture", "--out", str(out), "--socket", str(r.socket),
            "--stage-range", "1.0", "--coarse-step", "0.5", "--stop-after", "coarse"]
    r.daemon.laser.off()  # all off and disarmed
    assert main(args) != 0  # not armed: a person arms, or --arm says so
    assert "not armed" in capsys.readouterr().err
    r.daemon.laser.off()
    assert main([*args, "--force", "--arm", "30"]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["complete"] and len(manifest["records"]) == 5
    assert r.daemon.laser.twin.emitting() == {"red": 0.0, "green": 0.0, "blue": 0.0}
    outside = root / "elsewhere" / "cli"
    assert main([*args, "--out", str(outside), "--arm", "30"]) != 0
    assert "outside the allowed directories" in capsys.readouterr().err
