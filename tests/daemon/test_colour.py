"""Colour modes (docs/design.md, "The hardware": Colour timing) on the simulated bench. The
laser twin's emission record proves the capture sequence: never two diodes on at once, and each
capture taken with only its own diode on and its own colour's pattern on the panel."""

from __future__ import annotations

import numpy as np
import pytest

from nhfd.daemon.colour import panel_for_mode
from nhfd.daemon.protocol import RpcError
from nhfd.device_settings import COLOURS

from .conftest import Running, bench_config, wait_until


def colour_config(root, twin, mode: str, **devices):
    config = bench_config(root, twin, frames={"colour_mode": mode},
                          bench={"camera_roi_px": [1000, 1200, 16, 16]})
    slm_output = config.devices.slm_output.model_copy(update={"settle_ms": 20.0})
    return config.model_copy(update={"devices": config.devices.model_copy(
        update={"slm_output": slm_output, **devices})})


def on_at(twin, t: float) -> list[str]:
    """The channels emitting at time t, from the twin's record."""
    out = []
    for ch in COLOURS:
        level = [pct for when, pct in twin.emission(ch) if when <= t]
        if level and level[-1] > 0:
            out.append(ch)
    return out


def test_capture_mode_lights_one_diode_at_a_time_for_its_own_pattern(short_dir):
    r = Running(colour_config(short_dir, None, "capture", camera="simulated"), short_dir)
    try:
        c = r.client()
        twin, bench = r.daemon.laser.twin, r.daemon.bench
        assert c.status()["colour"]["mode"] == "capture"
        c.call("laser", action="arm", duration_s=60.0)
        powers = {"red": 5.0, "green": 4.0, "blue": 3.0}
        for ch, pct in powers.items():
            c.call("laser", action="power", channel=ch, power_pct=pct)
        with pytest.raises(RpcError) as info:  # only the daemon switches diodes in this mode
            c.call("laser", action="enable", channel="red")
        assert "colour_mode 'capture'" in info.value.message
        # A recognisable three-colour frame on the panel: a different pattern per channel.
        base = np.stack([np.full(bench.slm.shape, 40 * (i + 1), np.uint8) for i in range(3)])
        r.daemon.frames.pacer.last_frame = base  # what the frame link last showed
        # What the camera saw at each grab: the diodes on, and the panel's three channels.
        seen: list[tuple[float, dict, np.ndarray]] = []
        camera = bench.camera
        powers_of = camera._laser_powers

        def recording() -> list[float]:
            seen.append((twin.clock(), twin.emitting(), bench.slm.last_frame))
            return powers_of()

        camera._laser_powers = recording
        start = twin.clock()
        job = c.call("snapshot", path="colour.png")["job"]
        wait_until(lambda: c.call("job", id=job)["state"] in ("done", "failed"), 25, "capture")
        result = c.call("job", id=job)
        assert result["state"] == "done", result["error"]
        assert set(result["result"]["colours"]) == set(COLOURS)
        assert result["result"]["powers_pct"] == powers

        # One grab per colour, in order, each with only its diode on at its power, and the
        # panel showing that colour's pattern in every channel.
        assert [next(ch for ch, p in e.items() if p > 0) for _, e, _ in seen] == list(COLOURS)
        for (_, emitting, frame), ch in zip(seen, COLOURS, strict=True):
            assert emitting == {k: (powers[k] if k == ch else 0.0) for k in COLOURS}
            want = base[COLOURS.index(ch)]
            assert all(np.array_equal(frame[i], want) for i in range(3))
        # The twin's whole record since the snapshot began: never two diodes at once.
        changes = sorted({t for ch in COLOURS for t, _ in twin.emission(ch) if t >= start})
        assert len(changes) >= 6  # on and off for each colour
        assert all(len(on_at(twin, t)) <= 1 for t in changes)
        assert twin.emitting() == dict.fromkeys(COLOURS, 0.0)
        assert np.array_equal(bench.slm.last_frame, base)  # the view is back on the panel
        for ch in COLOURS:
            assert (short_dir / "snaps" / f"colour-{ch}.png").stat().st_size > 0
    finally:
        r.stop()


def test_single_mode_allows_only_its_colour(short_dir, mecom_twin):
    r = Running(colour_config(short_dir, mecom_twin, "single"), short_dir)
    try:
        c = r.client()
        c.call("laser", action="arm", duration_s=60.0)
        for action, extra in (("enable", {}), ("power", {"power_pct": 5.0})):
            with pytest.raises(RpcError) as info:
                c.call("laser", action=action, channel="red", **extra)
            assert "only the green diode" in info.value.message
            assert info.value.data["allowed"] == "green"
        c.call("laser", action="power", channel="red", power_pct=0.0)  # zero is always fine
        c.call("laser", action="power", channel="green", power_pct=5.0)
        c.call("laser", action="enable", channel="green")
        assert mecom_twin.emitting() == {"red": 0.0, "green": 5.0, "blue": 0.0}
    finally:
        r.stop()


def test_panel_per_mode():
    frame = np.stack([np.full((2, 4), v, np.uint8) for v in (10, 20, 30)])
    assert np.array_equal(panel_for_mode(frame, "hw-sync", "green"), frame)
    single = panel_for_mode(frame, "single", "green")
    assert single.shape == frame.shape and (single == 20).all()
