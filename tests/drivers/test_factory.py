"""`[devices]` chooses each backend; simulated is the default and runs the real driver code."""

from __future__ import annotations

import pytest

from nhfd.calib.sim import SIM_STAGE_VELOCITY_MM_S, quick_sim_devices
from nhfd.config import Config, ConfigError, check_file
from nhfd.drivers import factory
from nhfd.drivers.framebuffer import FramebufferSLM
from nhfd.drivers.laser import MecomLaser
from nhfd.drivers.navigator import SimulatedNavigator, SpaceMouseNavigator, Waypoint
from nhfd.drivers.slm import SimulatedSLM
from nhfd.drivers.stage import AptStage
from nhfd.drivers.twins.clock import ManualClock


def devices(**update):
    return Config().devices.model_copy(update=update)


def test_defaults_are_simulated_and_built_from_the_same_settings():
    d = Config().devices
    assert (d.slm, d.laser, d.stage, d.navigator) == ("simulated", "simulated", "simulated",
                                                      "none")
    assert d.readybeam.max_power_pct == [10.0, 10.0, 10.0]  # the cap for real lasers too
    laser = factory.make_laser(d)
    try:
        assert isinstance(laser, factory.SimulatedLaser) and isinstance(laser, MecomLaser)
        assert not laser.twin.requests  # nothing is opened or sent until open()
        with laser:
            laser.arm(10)
            assert laser.set_power("green", 50.0) == 10.0  # the configured cap
            laser.enable("green")
            assert laser.twin.emitting()["green"] == 10.0
        assert laser.twin.emitting()["green"] == 0.0
        assert not laser.twin.present  # closing the driver stopped its twin
    finally:
        laser.twin.close()
    assert factory.make_navigator(d) is None


def test_a_lab_config_reaches_the_simulated_laser_and_stage(tmp_path):
    path = tmp_path / "lab.toml"
    path.write_text("[devices.readybeam]\nmax_power_pct = [2.0, 3.0, 4.0]\n"
                    "[devices.apt]\nusb_serial = \"83000042\"\nallowed_models = [\"TDC001\"]\n"
                    "enable_settle_s = 0.0\n")
    d = check_file(path).devices
    laser = factory.make_laser(d)
    with laser:
        laser.arm(10)
        assert [laser.set_power(c, 99.0) for c in ("red", "green", "blue")] == [2.0, 3.0, 4.0]
    clock = ManualClock()
    stage = factory.make_stage(d, clock=clock)
    assert isinstance(stage, factory.SimulatedStage) and isinstance(stage, AptStage)
    with stage:
        assert (stage.info.model, stage.info.serial_number) == ("TDC001", "83000042")
        assert not stage.twin.moving  # never moves at start-up
    assert not stage.twin.present


def test_real_backends_are_chosen_by_name_and_nothing_is_opened():
    d = devices(laser="readybeam", stage="apt", slm="framebuffer", navigator="spacemouse")
    with pytest.raises(ValueError, match=r"devices\.readybeam: set usb_serial"):
        factory.make_laser(d)
    with pytest.raises(ValueError, match=r"devices\.apt: set usb_serial"):
        factory.make_stage(d)
    d = d.model_copy(update={
        "readybeam": d.readybeam.model_copy(update={"usb_serial": "FT5LASER"}),
        "apt": d.apt.model_copy(update={"port": "/dev/ttyUSB0"})})
    assert type(factory.make_laser(d)) is MecomLaser
    assert type(factory.make_stage(d)) is AptStage
    slm = factory.make_slm(d, 1920, 1080)
    assert isinstance(slm, FramebufferSLM) and slm.shape == (1080, 1920)
    assert isinstance(factory.make_navigator(d), SpaceMouseNavigator)
    assert isinstance(factory.make_slm(Config().devices, 8, 4), SimulatedSLM)
    sim = factory.make_navigator(devices(navigator="simulated"),
                                 [Waypoint(0.0, (350, 0, 0, 0, 0, 0))])
    assert isinstance(sim, SimulatedNavigator) and sim.read().translation_m_s[0] == 0.1
    none = devices(laser="none", stage="none", slm="none")
    assert (factory.make_laser(none), factory.make_stage(none),
            factory.make_slm(none, 8, 4)) == (None, None, None)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[devices]\nlaser = 'real'\n", r"devices\.laser = 'real': Input should be 'simulated'"),
        ("[devices.readybeam]\nmax_power_pct = [10.0, 150.0, 10.0]\n",
         r"devices\.readybeam\.max_power_pct\.1 = 150\.0: Input should be less than or equal "
         r"to 100"),
        ("[devices.apt]\nsoft_limits_mm = [5.0, 1.0]\n", r"needs min < max"),
        ("[devices.readybeam]\ncap = 5\n",
         r"devices\.readybeam\.cap: unknown key; allowed here: address, arm_max_s"),
        ("[devices.readybeam.guardian]\nheartbeat_timeout_s = 60.0\n",
         r"devices\.readybeam\.guardian\.heartbeat_timeout_s = 60\.0"),
    ],
)
def test_device_settings_are_validated_with_the_key_named(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        check_file(path)


def test_simulated_camera_sees_the_simulated_bench():
    """The factory's camera images what the simulated SLM shows, only while a laser emits."""
    import numpy as np

    from nhfd.drivers.simcamera import TrueBench

    d = Config().devices
    # A small panel and sensor crop keep this fast; the bench's geometry is its own.
    bench = TrueBench(zero_order_fraction=0.0)
    roi = bench.roi_for_panel((128, 128))
    with factory.make_bench(d, 128, 128, bench=bench, roi=roi) as devices:
        slm, laser, camera = devices.slm, devices.laser, devices.camera
        # A grey step: phase 0 on the left, pi on the right; its edge diffracts.
        frame = np.zeros((128, 128), np.uint8)
        frame[:, 64:] = 128
        slm.show(frame)
        camera.capture_dark(4)  # lasers are off on open: this is the dark frame
        dark = camera.capture().image
        assert float(np.abs(dark).mean()) < 1e-3
        laser.arm(10)
        laser.set_power("green", 10.0)
        laser.enable("green")
        lit = camera.capture().image
        assert float(lit.mean()) > 20 * max(float(np.abs(dark).mean()), 1e-5)
        laser.enable("green", False)
        assert float(np.abs(camera.capture().image).mean()) < 1e-3


def test_simulated_camera_needs_the_simulated_bench():
    d = Config().devices
    with pytest.raises(ValueError, match="needs the simulated SLM, laser and stage"):
        factory.make_camera(d)
    assert factory.make_camera(devices(camera="none")) is None


def test_make_bench_reports_a_failed_device_and_still_builds_the_rest():
    """The daemon's way: a device that cannot be built is reported and left None; the others
    open, in wiring order, and the laser opens with every channel off."""
    d = devices(stage="apt", camera="none")  # no port for the real stage
    failed, opened = {}, []
    bench = factory.make_bench(d, 8, 4, on_error=lambda name, exc: failed.update({name: exc}),
                               on_open=lambda name, device: opened.append(name))
    with bench:
        assert opened == ["slm", "laser"]
        assert bench.stage is None and bench.camera is None
        assert isinstance(failed["stage"], ValueError)
        assert not bench.laser.status().any_on
        twin = bench.laser.twin
    assert not twin.present and not any(twin.emitting().values())


def test_make_bench_without_on_error_closes_what_it_opened_and_raises():
    d = devices(stage="apt")
    with pytest.raises(ValueError, match=r"devices\.apt: set usb_serial"):
        factory.make_bench(d, 8, 4)


def test_the_simulated_stage_homes_at_its_settings_velocity():
    """A simulated controller homes at the velocity its settings move at (the in-process
    simulated bench runs at the settings' cap; the packaged default is a real actuator's)."""
    d = Config().devices
    for devices, mm_s in ((d, 2.0), (quick_sim_devices(), SIM_STAGE_VELOCITY_MM_S)):
        assert devices.apt.velocity_mm_s == mm_s
        clock = ManualClock()
        stage = factory.make_stage(devices, clock=clock)
        try:
            assert stage.twin.home_speed == pytest.approx(mm_s * devices.apt.counts_per_mm)
        finally:
            stage.twin.close()
    quick = quick_sim_devices()
    assert quick.slm_output.settle_ms == 0.0 and quick.camera_settings.channels == "mono"
    caps = [m.le for m in type(d.apt).model_fields["velocity_mm_s"].metadata if hasattr(m, "le")]
    assert caps == [SIM_STAGE_VELOCITY_MM_S]  # the settings' cap
