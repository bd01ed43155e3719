"""A snapshot a person can look at: the 16-bit linear PNG for analysis, an 8-bit preview beside
it scaled to the image's own range, and a warning when no laser emitted during the exposure
(the README's serving block once ended in a PNG of pure noise with nothing said)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from nhfd.config import Config, _overlay
from nhfd.daemon.methods import NO_LIGHT

from .conftest import Running, wait_until
from .test_citl_daemon import citl_config
from .test_frames import FRONT_POSE, serve_tiny


def _snapshot(c) -> dict:
    job = c.call("snapshot")["job"]
    wait_until(lambda: c.call("job", id=job)["state"] in ("done", "failed"), 30, "the snapshot")
    j = c.call("job", id=job)
    assert j["state"] == "done", j
    return j["result"]


def test_a_snapshot_says_when_nothing_emitted_and_has_a_preview(short_dir, tiny):
    base = citl_config(short_dir, tiny)  # the simulated bench with its camera
    config = Config.model_validate(_overlay(base.model_dump(),
                                            {"daemon": {"frames": {"colour_mode": "hw-sync"}}}))
    r = Running(config, short_dir)
    try:
        c = r.client()
        serve_tiny(c, short_dir)
        seq = c.call("set_view", pose=FRONT_POSE)["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq, 20, "the view")
        dark = _snapshot(c)
        assert dark["emitting"] == [] and dark["warning"] == NO_LIGHT
        # Armed with a power but no channel enabled: still nothing emitted.
        c.call("laser", action="arm", duration_s=60.0)
        c.call("laser", action="power", channel="green", power_pct=5.0)
        assert _snapshot(c)["warning"] == NO_LIGHT
        c.call("laser", action="enable", channel="green")
        lit = _snapshot(c)
        assert lit["emitting"] == ["green"] and "warning" not in lit
        raw = [np.asarray(Image.open(s["path"]), np.float64) / 65535 for s in (dark, lit)]
        # Signal above the noise floor: where the view is, the lit image stands out of the
        # dark one by many times the dark one's noise (at 5 % power: ~12 x here).
        signal, noise = np.percentile(raw[1] - raw[0], 99.5), raw[0].std()
        assert signal > 5 * noise, (signal, noise)
        for s in (dark, lit):
            preview = Path(s["preview"])
            assert preview.name == Path(s["path"]).stem + ".preview.png"
            img = np.asarray(Image.open(preview))
            assert img.dtype == np.uint8 and img.shape == raw[0].shape
            assert img.max() == 255 and img.min() == 0  # scaled to its own range
    finally:
        r.stop()
