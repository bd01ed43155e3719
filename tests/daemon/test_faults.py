"""Faults on the simulated bench, against the daemon with its real sockets, monitor and frame
worker: the stage's port vanishes, the camera times out, the SLM's output is unplugged, a model
file is garbage. Each ends in a clear error in `status`, lasers off where the fault touches the
light path (the laser twin's emission record is the proof), and recovery when the device returns.

The fault hooks are the simulated devices' explicit test-only APIs: `AptTwin.vanish()/replug()`,
`SimulatedCamera.stall()/resume()`, `SimulatedSLM.unplug()/replug()`.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from nhfd.daemon.bench import stage_mm_for_focus
from nhfd.daemon.protocol import RpcError

from .conftest import Running, bench_config, wait_until

OFF = {"red": 0.0, "green": 0.0, "blue": 0.0}


def light(c, twin, channel: str = "red", pct: float = 5.0) -> None:
    c.call("laser", action="arm", duration_s=60.0)
    c.call("laser", action="power", channel=channel, power_pct=pct)
    c.call("laser", action="enable", channel=channel)
    assert twin.emitting()[channel] == pct


def errors_from(status: dict, source: str) -> list[str]:
    return [e["message"] for e in status["errors"] if e["source"] == source]


def test_slm_output_unplugged_turns_lasers_off_and_recovers(running: Running, mecom_twin):
    c = running.client()
    slm = running.daemon.bench.slm
    light(c, mecom_twin)
    unplugged = time.monotonic()
    slm.unplug()
    wait_until(lambda: c.status()["devices"]["slm"]["error"] is not None, 5, "the SLM error")
    wait_until(lambda: any("lasers switched off" in m for m in errors_from(c.status(), "slm")),
               5, "lasers off in status")
    status = c.status()
    assert status["devices"]["slm"]["error"] == "output lost: unplugged"
    assert status["devices"]["slm"]["health"]["ok"] is False
    # The emission record: every diode dark, within a second of the unplug.
    assert mecom_twin.emitting() == OFF
    assert mecom_twin.dark_since() is not None and mecom_twin.dark_since() - unplugged < 1.0
    assert status["laser"]["armed"] is False
    # Nothing may light a panel the daemon does not control.
    c.call("laser", action="arm", duration_s=60.0)
    with pytest.raises(RpcError) as info:
        c.call("laser", action="enable", channel="red")
    assert "SLM output lost" in info.value.message
    assert mecom_twin.emitting() == OFF

    shown = slm.count
    slm.replug()
    wait_until(lambda: c.status()["devices"]["slm"]["error"] is None
               and c.status()["devices"]["slm"]["showing"] == "blank", 5, "the SLM back")
    assert slm.count > shown  # the blank pattern was written to the panel again
    assert mecom_twin.emitting() == OFF  # never restored automatically
    light(c, mecom_twin)  # and a person can turn them on again


def test_stage_port_vanishing_is_an_error_and_it_reconnects(running: Running, mecom_twin):
    c = running.client()
    twin = running.daemon.bench.stage.twin
    light(c, mecom_twin)
    lit_changes = len(mecom_twin.emission("red"))
    job = c.call("focus", z_mm=0.0, home=True)["job"]
    wait_until(lambda: c.call("job", id=job)["state"] == "done", 20, "homing and focus")

    twin.vanish()
    wait_until(lambda: c.status()["devices"]["stage"]["error"] is not None, 5, "the stage error")
    error = c.status()["devices"]["stage"]["error"]
    assert "Vanished" in error or "LinkDown" in error or "not present" in error, error
    job = c.call("focus", z_mm=1.0)["job"]
    wait_until(lambda: c.call("job", id=job)["state"] == "failed", 10, "the focus to fail")
    assert "stage" in c.call("job", id=job)["error"]
    wait_until(lambda: any(f"job {job}" in e["source"] for e in c.status()["errors"]), 5,
               "the failed job in status")

    twin.replug()  # a new pty path, as a re-enumerated USB adapter gets; same serial number
    wait_until(lambda: c.status()["devices"]["stage"]["error"] is None, 15, "the stage back")
    assert c.status()["devices"]["stage"]["homed"] is True
    job = c.call("focus", z_mm=1.0)["job"]
    wait_until(lambda: c.call("job", id=job)["state"] == "done", 15, "a focus after it")
    assert twin.position_mm == pytest.approx(stage_mm_for_focus(running.daemon.config,
                                                            running.daemon.calibration, 1.0),
                                             abs=1e-3)
    # The stage is on the detection side: the lasers were left alone throughout.
    assert len(mecom_twin.emission("red")) == lit_changes and mecom_twin.emitting()["red"] == 5.0


def test_camera_timeout_fails_the_snapshot_and_recovers(short_dir: Path):
    # The simulated camera images the daemon's own simulated laser twin, SLM and stage.
    config = bench_config(short_dir, None, bench={"camera_roi_px": [1000, 1200, 16, 16]})
    config = config.model_copy(update={"devices": config.devices.model_copy(update={
        "camera": "simulated",
        "camera_settings": config.devices.camera_settings.model_copy(
            update={"frame_timeout_s": 0.2})})})
    r = Running(config, short_dir)
    try:
        c = r.client()
        twin = r.daemon.laser.twin
        light(c, twin)
        job = c.call("snapshot", path="a.png")["job"]
        wait_until(lambda: c.call("job", id=job)["state"] == "done", 20, "a first snapshot")

        r.daemon.bench.camera.stall()
        job = c.call("snapshot", path="b.png")["job"]
        wait_until(lambda: c.call("job", id=job)["state"] == "failed", 10, "the timeout")
        assert "CameraTimeout" in c.call("job", id=job)["error"]
        status = c.status()
        assert "CameraTimeout" in status["devices"]["camera"]["error"]
        assert any("no frame within" in e["message"] for e in status["errors"])
        assert not (short_dir / "snaps" / "b.png").exists()
        assert twin.emitting()["red"] == 5.0  # the camera is not in the light path

        r.daemon.bench.camera.resume()
        job = c.call("snapshot", path="c.png")["job"]
        wait_until(lambda: c.call("job", id=job)["state"] == "done", 20, "a snapshot after it")
        assert c.status()["devices"]["camera"]["error"] is None
        assert (short_dir / "snaps" / "c.png").stat().st_size > 0
    finally:
        r.stop()


def test_garbage_model_file_is_refused_and_the_old_model_keeps_running(short_dir, mecom_twin,
                                                                        tiny):
    from .test_frames import daemon_config, wait_for_frames

    model = short_dir / "models" / "tiny.onnx"
    config = daemon_config(short_dir, mecom_twin, tiny,
                           paths={"scene": str(short_dir / "scenes" / "cloud.ply")},
                           frames={"model": str(model)})
    r = Running(config, short_dir)
    try:
        c = r.client()
        before = wait_for_frames(c)["model"]
        light(c, mecom_twin, "green")
        good = model.read_bytes()
        model.write_bytes(b"\x08\x07garbage, not protobuf" * 50)  # replaced on disk
        job = c.call("load_model", path=str(model))["job"]
        wait_until(lambda: c.call("job", id=job)["state"] == "failed", 20, "the refusal")
        error = c.call("job", id=job)["error"]
        assert "not a readable ONNX model" in error and "tiny.onnx" in error
        status = c.status()
        assert any("not a readable ONNX model" in e["message"] for e in status["errors"])
        assert status["model"] == before  # the old model, loaded at the same time
        seq = c.call("set_view", pose={"position": [0.0, 0.05, -2.0],
                                       "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]})["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq, 20, "a frame after it")
        assert mecom_twin.emitting()["green"] == 5.0  # the light path kept its frames

        model.write_bytes(good)  # the file is back
        job = c.call("load_model", path=str(model))["job"]
        wait_until(lambda: c.call("job", id=job)["state"] == "done", 20, "the reload")
        assert c.status()["model"]["loaded_s"] > before["loaded_s"]
        assert c.status()["model"]["providers"] == ["CPUExecutionProvider"]
    finally:
        r.stop()


def test_an_unavailable_execution_provider_is_refused_listing_the_available_ones(tiny):
    import onnxruntime as ort

    from nhfd.models.export import OnnxModel, check_providers
    from nhfd.pipeline.worker import open_model

    from .test_frames import small_config

    available = ort.get_available_providers()
    assert check_providers(["CPUExecutionProvider"], available) == ["CPUExecutionProvider"]
    config = small_config(daemon={"frames": {"onnx_providers": ["TensorrtExecutionProvider",
                                                     "CPUExecutionProvider"]}})
    if "TensorrtExecutionProvider" in available:
        pytest.skip("this onnxruntime has TensorRT")
    with pytest.raises(ValueError) as info:
        open_model(str(tiny["model"]), config, threads=1)
    message = str(info.value)
    assert "daemon.frames.onnx_providers: TensorrtExecutionProvider not available" in message
    assert "available: " + ", ".join(available) in message
    # a model opened outside the daemon refuses one too, by name, not as an unreadable file
    with pytest.raises(ValueError, match="providers: TensorrtExecutionProvider not available"):
        OnnxModel(tiny["model"], providers=("TensorrtExecutionProvider",))
    model = open_model(str(tiny["model"]), small_config(), threads=1)
    assert model.session.get_providers() == ["CPUExecutionProvider"]
    # the serving session: the given threads, and pools that sleep between frames (a spinning
    # pool takes the cores from the propagation that follows inference)
    opts = model.session.get_session_options()
    assert opts.intra_op_num_threads == 1 and opts.inter_op_num_threads == 1
    assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"
