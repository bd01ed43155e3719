"""The simulated navigator (a scripted yaw) moves the view through the latest-wins set_view
path: the sequence number advances and the azimuth follows the script."""

from __future__ import annotations

import time
from types import SimpleNamespace

from nhfd.daemon.navigation import relative_move
from nhfd.views import Orbit, Pose, View

from .conftest import Running, bench_config, wait_until


def navigator_config(root, twin):
    """The small simulated bench with the simulated navigator, read every 20 ms."""
    config = bench_config(root, twin, bench={"navigator_period_s": 0.02})
    return config.model_copy(update={"devices": config.devices.model_copy(
        update={"navigator": "simulated"})})


def test_simulated_navigator_moves_the_view_and_advances_the_sequence(short_dir, mecom_twin):
    config = navigator_config(short_dir, mecom_twin)
    r = Running(config, short_dir)
    try:
        c = r.client()
        assert c.status()["navigator"]["open"] is True
        assert c.status()["navigator"]["moves"] == 0  # no view yet: nothing to move
        seq = c.call("set_view", orbit={"azimuth_deg": 0.0, "elevation_deg": 10.0,
                                        "radius": 2.0}, refocus_mm=1.5)["seq"]
        wait_until(lambda: c.status()["view"]["seq"] >= seq + 5, 10, "navigator moves")
        status = c.status()
        view = status["view"]["requested"]
        assert status["navigator"]["moves"] >= 5 and status["navigator"]["error"] is None
        assert status["navigator"]["last_seq"] == status["view"]["seq"]
        # The script yaws right (+azimuth) first, at half of 45 deg/s; elevation, radius and the
        # digital refocus stay.
        assert view["kind"] == "orbit" and 0.0 < view["azimuth_deg"] < 45.0
        assert view["elevation_deg"] == 10.0 and view["radius"] == 2.0
        assert view["refocus_mm"] == 1.5
        # A client's set_view still wins over whatever the navigator did before it.
        seq = c.call("set_view", orbit={"azimuth_deg": -90.0, "elevation_deg": 0.0,
                                        "radius": 3.0})["seq"]
        wait_until(lambda: c.status()["view"]["seq"] > seq, 10, "moves from the new view")
        assert -100.0 < c.status()["view"]["requested"]["azimuth_deg"] < -80.0
    finally:
        r.stop()


def test_relative_move_from_velocities():
    still = SimpleNamespace(translation_m_s=(0, 0, 0), rotation_deg_s=(0, 0, 0))
    orbit = View(Orbit(0.0, 89.0, 1.0))
    assert relative_move(orbit, still, 0.1) is None
    up = SimpleNamespace(translation_m_s=(0, 0, -20.0), rotation_deg_s=(30.0, 10.0, 0))
    rel = relative_move(orbit, up, 0.1)
    assert rel["d_azimuth_deg"] == 1.0
    assert 89.0 + rel["d_elevation_deg"] == 89.9  # clamped at the pole, not refused
    assert rel["d_radius"] == -0.5  # never through the centre
    pose = View(Pose((0, 0, 0), (1, 0, 0, 0)))
    assert relative_move(pose, up, 0.5) == {"translate": [0, 0, -10.0],
                                            "rotate_deg": [15.0, 5.0, 0]}


def test_an_unplugged_navigator_is_opened_again_once_it_is_back(short_dir, mecom_twin):
    config = navigator_config(short_dir, mecom_twin)
    r = Running(config, short_dir)
    try:
        c = r.client()
        seq = c.call("set_view", orbit={"azimuth_deg": 0.0, "elevation_deg": 10.0,
                                        "radius": 2.0})["seq"]
        wait_until(lambda: c.status()["view"]["seq"] > seq, 10, "navigator moves")
        r.daemon.navigation.navigator.unplug()
        wait_until(lambda: c.status()["navigator"]["error"] is not None, 5, "the loss seen")
        moves = c.status()["navigator"]["moves"]
        time.sleep(0.3)
        assert c.status()["navigator"]["moves"] == moves  # nothing moves while it is gone
        r.daemon.navigation.navigator.replug()
        # Opened again within RECONNECT_S, and moving the view again.
        wait_until(lambda: c.status()["navigator"]["error"] is None
                   and c.status()["navigator"]["moves"] > moves, 5, "moves after the replug")
    finally:
        r.stop()
