"""The dial at the display (issue 34): a view asking for `sgd` shows the network's frame at once
and better frames while it rests; a new view cancels the refinement and its frame comes as
quickly as an open-loop one; bad tiers are refused naming the parameter and nothing changes."""

from __future__ import annotations

import time

import numpy as np
import pytest

from nhfd.config import Config, _overlay
from nhfd.daemon.methods import NO_MODEL
from nhfd.daemon.protocol import RpcError

from .conftest import Running, wait_until
from .test_frames import FRONT_POSE, daemon_config, serve_tiny

REFINE = {"iterations": 2000, "seconds": 60.0, "tolerance": 0.0, "swap_every": 3, "planes": 2}


def _running(short_dir, mecom_twin, tiny) -> Running:
    base = daemon_config(short_dir, mecom_twin, tiny)
    config = Config.model_validate(_overlay(base.model_dump(), {"refine": REFINE}))
    r = Running(config, short_dir)
    c = r.client()
    serve_tiny(c, short_dir)
    return r


def test_sgd_swaps_in_better_frames_and_a_new_view_cancels_it(short_dir, mecom_twin, tiny):
    r = _running(short_dir, mecom_twin, tiny)
    try:
        c = r.client()
        seq = c.call("set_view", pose=FRONT_POSE, quality="sgd")["seq"]
        assert c.call("status")["view"]["requested"]["quality"] == "sgd"
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq, 20, "the network frame")
        network = r.daemon.frames.last_frame.copy()
        wait_until(lambda: (c.status()["frames"]["refine"] or {}).get("swaps", 0) >= 2, 60,
                   "two better frames")
        refine = c.status()["frames"]["refine"]
        assert refine["tier"] == "sgd" and refine["seq"] == seq and refine["stop"] == ""
        assert refine["psnr_db"] > refine["start_psnr_db"] and refine["iterations"] >= 3
        refined = r.daemon.frames.last_frame
        assert not np.array_equal(refined, network)  # the panel shows the better frame
        assert np.array_equal(r.daemon.bench.slm.last_frame, refined)

        # A new view (back to the network's frame) while refinement runs: it is shown as soon
        # as an open-loop view would be, and no refined frame of the old view follows it.
        t0 = time.monotonic()
        seq2 = c.call("set_view", pose=dict(FRONT_POSE, position=[0.05, 0.0, -2.0]),
                      quality="network")["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq2, 20, "the new view")
        took_s = time.monotonic() - t0
        status = c.status()
        assert status["frames"]["refine"] is None
        shown = r.daemon.frames.last_frame.copy()
        time.sleep(1.0)  # refinement steps take ~10 ms here: a stale frame would have come
        assert np.array_equal(r.daemon.frames.last_frame, shown)
        assert c.status()["frames"]["shown_seq"] == seq2
        # Open loop, the same move: the same latency within a refresh and noise (CI machines).
        t0 = time.monotonic()
        seq3 = c.call("set_view", pose=FRONT_POSE)["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq3, 20, "an open-loop view")
        open_s = time.monotonic() - t0
        assert took_s < open_s + 0.25, (took_s, open_s)
    finally:
        r.stop()


def test_a_new_view_during_the_inversion_cancels_without_an_error(short_dir, mecom_twin, tiny):
    """Refinement starts with the view's light-field inversion (seconds on a CPU): a new view
    then cancels it, which is not a failure (`nhfd bench pipeline --quality network,sgd` found
    each such cancel reported as "refinement failed: Cancelled")."""
    r = _running(short_dir, mecom_twin, tiny)
    try:
        c = r.client()
        for i in range(3):
            seq = c.call("set_view", pose=dict(FRONT_POSE, position=[0.02 * i, 0.0, -2.0]),
                         quality="sgd")["seq"]
            wait_until(lambda seq=seq: c.status()["view"]["applied_seq"] == seq, 20,
                       "the network frame")
            refine = c.status()["frames"]["refine"] or {}
            assert refine.get("iterations", 0) == 0  # still inverting: nothing refined yet
        seq = c.call("set_view", pose=FRONT_POSE)["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq, 20, "an open-loop view")
        time.sleep(0.5)
        assert c.status()["errors"] == []
    finally:
        r.stop()


def test_bad_tiers_are_refused_and_nothing_changes(short_dir, mecom_twin, tiny):
    r = _running(short_dir, mecom_twin, tiny)
    try:
        c = r.client()
        before = c.status()["view"]
        with pytest.raises(RpcError, match=r'quality: got "best"; allowed: one of network, '
                                           r"exact, sgd, citl"):
            c.call("set_view", pose=FRONT_POSE, quality="best")
        # citl on a bench that cannot serve it: the setting that stands in the way is named.
        with pytest.raises(RpcError, match=r"quality: 'citl' cannot be served here: "
                                           r"daemon.frames.colour_mode is 'hw-sync': citl needs "
                                           r"'capture'.*; allowed: network, exact or sgd"):
            c.call("set_view", pose=FRONT_POSE, quality="citl")
        assert c.status()["view"] == before
    finally:
        r.stop()


def test_subframes_take_turns_on_the_panel(short_dir, mecom_twin, tiny):
    base = daemon_config(short_dir, mecom_twin, tiny)
    config = Config.model_validate(_overlay(base.model_dump(),
                                            {"refine": {**REFINE, "subframes": 2}}))
    r = Running(config, short_dir)
    try:
        c = r.client()
        serve_tiny(c, short_dir)
        c.call("set_view", pose=FRONT_POSE, quality="sgd")
        wait_until(lambda: (c.status()["frames"]["refine"] or {}).get("swaps", 0) >= 1, 60,
                   "a better pair of subframes")
        assert c.status()["frames"]["refine"]["subframes"] == 2
        refinement = r.daemon.frames.refinement
        region, greys = refinement.region, refinement.greys.copy()
        assert not np.array_equal(greys[0], greys[1])
        seen = set()
        deadline = time.monotonic() + 2.0
        while len(seen) < 2 and time.monotonic() < deadline:  # 60 Hz: a turn every ~17 ms
            # The pair of now: sgd goes on swapping better pairs in meanwhile (a loaded machine
            # once swapped one in between a copy taken once and the next turn).
            greys = refinement.greys.copy()
            shown = r.daemon.bench.slm.last_frame[:, region.rows, region.cols]
            seen |= {i for i, g in enumerate(greys) if np.array_equal(shown, g)}
            time.sleep(0.004)
        assert seen == {0, 1}
    finally:
        r.stop()


def test_a_scene_without_a_model_is_served_exact(short_dir, mecom_twin, tiny):
    """No model loaded: a view at the exact tier gets the scene's own hologram (slowly), one at
    sgd that frame refined, an open-loop view nothing."""
    r = Running(daemon_config(short_dir, mecom_twin, tiny), short_dir)
    try:
        c = r.client()
        c.call("load_scene", path=str(short_dir / "scenes" / "cloud.ply"))
        wait_until(lambda: (c.status()["scene"] or {}).get("center") is not None, 30,
                   "the scene")
        assert c.status()["model"] == "none loaded"
        # No network, no open-loop frame: accepted (the latest view waits for a model), and
        # both the reply and status say what would show something.
        reply = c.call("set_view", pose=FRONT_POSE)
        assert reply["warning"] == NO_MODEL and NO_MODEL.startswith("no model: showing nothing")
        time.sleep(0.5)
        status = c.status()
        assert status["view"]["applied_seq"] != reply["seq"] and NO_MODEL in status["warnings"]
        seq = c.call("set_view", pose=FRONT_POSE, quality="exact")["seq"]
        wait_until(lambda: c.status()["view"]["applied_seq"] == seq, 60, "the exact frame")
        frame = r.daemon.frames.last_frame
        blank = r.daemon.panel.blank_frame()
        assert not np.array_equal(frame, blank)  # a coded region, not the zero pattern
        # The exact frame is all the exact tier does: its refinement reads as done.
        refine = c.status()["frames"]["refine"]
        assert (refine["tier"], refine["stop"], refine["phase"]) == ("exact", "exact", "")
        # sgd without a model: refined from the exact frame.
        seq = c.call("set_view", pose=dict(FRONT_POSE, position=[0.05, 0.0, -2.0]),
                      quality="sgd")["seq"]
        wait_until(lambda: (c.status()["frames"]["refine"] or {}).get("swaps", 0) >= 1
                   and c.status()["frames"]["refine"]["seq"] == seq, 60, "a refined frame")
        refine = c.status()["frames"]["refine"]
        assert refine["psnr_db"] > refine["start_psnr_db"]
        assert c.status()["errors"] == []
    finally:
        r.stop()


def test_a_new_view_cancels_an_exact_frame_and_starts_at_once(short_dir, mecom_twin, tiny):
    """With no model, a view's exact frame takes seconds: a newer view cancels it between the
    light field's elemental views instead of waiting its turn, and the older frame is never
    shown."""
    base = daemon_config(short_dir, mecom_twin, tiny)
    # A larger window than the other tests': its exact frame takes about a second here.
    config = Config.model_validate(_overlay(base.model_dump(), {
        "slm": {"width_px": 480, "height_px": 320},
        "optics": {"hologram_width_px": 288, "hologram_height_px": 192}}))
    r = Running(config, short_dir)
    try:
        c = r.client()
        c.call("load_scene", path=str(short_dir / "scenes" / "cloud.ply"))
        wait_until(lambda: (c.status()["scene"] or {}).get("center") is not None, 30,
                   "the scene")

        def shown_after(pose: dict, seen: list[int] | None = None) -> None:
            t0 = time.monotonic()
            seq = c.call("set_view", pose=pose, quality="exact")["seq"]
            while (applied := c.status()["view"]["applied_seq"]) != seq:
                if seen is not None:
                    seen.append(applied)
                assert time.monotonic() - t0 < 20, "no exact frame"
                time.sleep(0.01)

        shown_after(FRONT_POSE)  # the first pays for building kernels
        t0 = time.monotonic()
        shown_after(dict(FRONT_POSE, position=[0.02, 0.0, -2.0]))  # nothing before
        alone_s = time.monotonic() - t0
        assert c.status()["frames"]["frames_cancelled"] == 0
        older = c.call("set_view", pose=dict(FRONT_POSE, position=[0.04, 0.0, -2.0]),
                       quality="exact")["seq"]
        wait_until(lambda: r.daemon.frames.inflight is not None
                   and r.daemon.frames.inflight.seq == older, 5, "the older view computing")
        time.sleep(0.3 * alone_s)  # well into its inversion
        seen: list[int] = []
        shown_after(dict(FRONT_POSE, position=[-0.04, 0.0, -2.0]), seen)
        # The worker cut the older frame short (it answered cancelled, not done: a cancel that
        # came after the frame was whole would find nothing to cancel), so the newer view did
        # not wait for it, and the older frame never reached the panel. A fact, not a time: a
        # wall-clock ratio here failed on a loaded CI machine.
        frames = c.status()["frames"]
        assert frames["frames_cancelled"] == 1, frames
        assert frames["frames_dropped"] >= 1
        assert older not in seen, (alone_s, seen[:3], len(seen))
        assert c.status()["errors"] == []
    finally:
        r.stop()
