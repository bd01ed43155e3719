"""Focal stacks captured through the daemon (`capture_stack`, what `nhfd calib learn` uses
without --direct), on the simulated bench with a calibration that is its truth: the subframes
shown at their region and captured plane by plane with each diode alone on at the power a
person set, never arming; the captures are the pattern's (the parametric model predicts them);
a disarm mid-stack stops it with nothing emitted after; bad requests are refused naming the
field, and nothing runs. Then the whole `nhfd calib learn` through the daemon: a disarm stops
it keeping what it captured, and the same command resumes and finishes."""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from nhfd.calib.citl import DaemonCameraLoop
from nhfd.calib.learn import PARTIAL_NAME, learn_settings, load_captured
from nhfd.calibration import Calibration
from nhfd.cli.main import main
from nhfd.config import Config, _overlay
from nhfd.daemon.protocol import RpcError
from nhfd.device_settings import COLOURS
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.refine import BenchForward, grey_phase

from .conftest import Running, wait_until
from .test_citl_daemon import POWERS, citl_config, prepare_bench
from .test_colour import on_at

WINDOW_HW = (32, 32)
PLANES_M = (-0.4e-3, 0.4e-3)


def _config(root: Path, tiny) -> Config:
    base = citl_config(root, tiny)
    (root / "calib").mkdir(exist_ok=True)
    return Config.model_validate(_overlay(base.model_dump(), {
        "daemon": {"paths": {"pattern_dirs": [str(root / "calib")]}}}))


def _running(root: Path, tiny, *, armed: bool = True) -> Running:
    r = Running(_config(root, tiny), root)
    prepare_bench(r.client(), armed=armed)
    return r


def _encoder(r: Running) -> Encoder:
    cfg = r.daemon.config
    cal = r.daemon.calibration.active()
    return Encoder(learn_settings(cfg, cal, WINDOW_HW, (cfg.slm.height_px, cfg.slm.width_px)))


def _patterns(encoder: Encoder, n: int, seed: int) -> np.ndarray:
    """`n` smooth random patterns on the encoder's region `[n, 3, Hr, Wr]` uint8 (smooth: most
    of their light stays inside the window)."""
    r = encoder.region
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, 256, (n, 3, r.height // 4 + 1, r.width // 4 + 1))
    return np.kron(coarse, np.ones((1, 1, 4, 4)))[..., : r.height, : r.width].astype(np.uint8)


def _corr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    x, y = a[..., mask].ravel(), b[..., mask].ravel()
    return float(np.corrcoef(x, y)[0, 1])


def test_a_stack_is_the_patterns_light_one_diode_at_a_time_and_never_arms(short_dir, tiny):
    r = _running(short_dir, tiny)
    try:
        c = r.client()
        twin = r.daemon.laser.twin
        encoder = _encoder(r)
        cal = r.daemon.calibration.active()
        loop = DaemonCameraLoop(c, cal, encoder, short_dir / "calib" / "learn",
                                camera_pitch_m=r.daemon.config.devices.camera_settings
                                .pixel_pitch_um * 1e-6)
        grey = _patterns(encoder, 2, seed=5)
        start = twin.clock()
        seen = [loop(g[None], PLANES_M) for g in grey]
        # The twin's record: each colour at the power a person set, never two at once, nothing
        # emitting after, and the arming still the person's.
        changes = sorted({t for ch in COLOURS for t, _ in twin.emission(ch) if t >= start})
        assert changes and all(len(on_at(twin, t)) <= 1 for t in changes)
        for ch in COLOURS:
            assert {pct for t, pct in twin.emission(ch) if t >= start} == {0.0, POWERS[ch]}
        assert twin.emitting() == dict.fromkeys(COLOURS, 0.0)
        assert c.status()["laser"]["armed"]
        assert loop.captures == 2 * len(PLANES_M) * 3
        jobs = [j for j in c.status()["jobs"] if j["kind"] == "capture_stack"]
        assert [j["state"] for j in jobs] == ["done", "done"], jobs
        # What was captured is each pattern's light at its planes: the parametric model's
        # prediction of pattern i matches capture i far better than the other pattern's.
        model = BenchForward(encoder, PLANES_M)
        with torch.no_grad():
            predicted = model(grey_phase(grey, encoder).float()).numpy()  # [N, D, C, h, w]
        mask = seen[0][1] & seen[1][1]
        assert mask.mean() > 0.5
        for i in range(2):
            own = _corr(predicted[i], seen[i][0], mask)
            other = _corr(predicted[1 - i], seen[i][0], mask)
            assert own > 0.8 and own > other + 0.2, (i, own, other)
        # The panel shows what the control loop last showed again (here the blank), not the
        # last pattern.
        assert r.daemon.panel.showing == "blank"
        assert np.array_equal(r.daemon.bench.slm.last_frame, r.daemon.panel.blank_frame())
    finally:
        r.stop()


def test_a_disarm_mid_stack_stops_it_and_nothing_is_emitted_after(short_dir, tiny):
    r = _running(short_dir, tiny)
    try:
        c = r.client()
        twin = r.daemon.laser.twin
        encoder = _encoder(r)
        path = short_dir / "calib" / "p.npy"
        np.save(path, _patterns(encoder, 1, seed=6))
        z0_m = encoder.settings.z0_m
        job = c.call("capture_stack", path=str(path), top=encoder.region.top,
                     left=encoder.region.left, z_m=[z0_m + 1e-4 * k for k in range(12)],
                     out=str(short_dir / "calib" / "p.npz"))["job"]
        wait_until(lambda: any(twin.emitting().values()), 20, "a diode on for the stack")
        c.call("laser", action="disarm")
        disarmed_at = twin.clock()
        wait_until(lambda: c.call("job", id=job)["state"] in ("failed", "done"), 20,
                   "the stack to stop")
        state = c.call("job", id=job)
        assert state["state"] == "failed", state
        assert "disarmed" in state["error"] or "not armed" in state["error"], state
        for ch in COLOURS:
            after = [pct for t, pct in twin.emission(ch) if t > disarmed_at + 0.05]
            assert not any(after), (ch, after)
        assert twin.emitting() == dict.fromkeys(COLOURS, 0.0)
        assert not (short_dir / "calib" / "p.npz").exists()
    finally:
        r.stop()


BAD_REQUESTS = [
    ({"path": "p.npz"}, "path", "wrong suffix"),
    ({"top": 128}, "top", "an integer in [0, 127]"),
    ({"z_m": []}, "z_m", "a list of 1 to 16 finite numbers"),
    ({"z_m": [0.1] * 17}, "z_m", "a list of 1 to 16 finite numbers"),
    ({"z_m": [0.1, 2.0]}, "z_m[1]", "[-1, 1]"),
    ({"out": "x.npy"}, "out", "does not end in .npz"),
    ({"out": "/tmp/elsewhere.npz"}, "out", "outside the allowed directories"),
    ({"frames": 0}, "frames", "an integer in [1, 1000]"),
    ({"extra": 1}, "extra", "unknown"),
]
BAD_FILES = [
    ((1, 3, 16, 16), np.float32, "not uint8"),
    ((3, 16, 16), np.uint8, "not subframes of a region"),
    ((17, 3, 16, 16), np.uint8, "not subframes of a region"),
    ((1, 3, 16, 200), np.uint8, "not subframes of a region"),
]


def test_a_bad_stack_request_or_file_is_refused_naming_it_and_nothing_runs(short_dir, tiny):
    r = _running(short_dir, tiny, armed=False)
    try:
        c = r.client()
        good = short_dir / "calib" / "p.npy"
        np.save(good, np.zeros((1, 3, 16, 16), np.uint8))
        params = {"path": "p.npy", "top": 0, "left": 0, "z_m": [0.1, 0.12], "out": "p.npz"}
        jobs = len(c.status()["jobs"])
        for change, field, words in BAD_REQUESTS:
            with pytest.raises(RpcError) as err:
                c.call("capture_stack", **{**params, **change})
            text = str(err.value) + str(err.value.data)
            assert field in text and words in text, (change, text)
        for k, (shape, dtype, words) in enumerate(BAD_FILES):
            np.save(short_dir / "calib" / f"bad{k}.npy", np.zeros(shape, dtype))
            with pytest.raises(RpcError, match=words):
                c.call("capture_stack", **{**params, "path": f"bad{k}.npy"})
        assert len(c.status()["jobs"]) == jobs  # nothing queued
        assert r.daemon.laser.twin.max_emitted_pct() == 0.0
    finally:
        r.stop()


def test_calib_learn_through_the_daemon_stops_on_a_disarm_and_the_same_command_resumes(
        short_dir, tiny, capsys):
    r = _running(short_dir, tiny)
    try:
        c = r.client()
        twin = r.daemon.laser.twin
        out = short_dir / "calib" / "learned"
        argv = ["calib", "learn", "--out", str(out), "--socket", str(r.socket),
                "--window", "32x32", "--patterns", "2", "--random", "1", "--structured", "1",
                "--held-out", "1", "--steps", "5"]
        # A person disarms once two patterns are kept.
        def disarm_after_two() -> None:
            wait_until(lambda: (out / PARTIAL_NAME).is_file()
                       and len(load_captured(out / PARTIAL_NAME, partial=True).images) >= 2,
                       60, "two patterns captured")
            c.call("laser", action="disarm")

        person = threading.Thread(target=disarm_after_two)
        person.start()
        assert main(argv) == 2
        person.join(5)
        err = capsys.readouterr().err
        assert "the capture stopped" in err and "run the same command again to resume" in err, err
        kept = load_captured(out / PARTIAL_NAME, partial=True)
        assert 2 <= len(kept.images) < 4
        assert not (out / "calibration.toml").exists()
        assert twin.emitting() == dict.fromkeys(COLOURS, 0.0)
        # Armed again by the person and the powers set again (a disarm zeroes them), the same
        # command takes up where it stopped.
        c.call("laser", action="arm", duration_s=600.0)
        for ch, pct in POWERS.items():
            c.call("laser", action="power", channel=ch, power_pct=pct)
        jobs_before = len([j for j in c.status()["jobs"] if j["kind"] == "capture_stack"])
        assert main(argv) == 0
        text = capsys.readouterr()
        assert f"resuming: {len(kept.images)} of 4 patterns captured" in text.err, text.err
        done = [j for j in c.status()["jobs"] if j["kind"] == "capture_stack"]
        assert len(done) - jobs_before == 4 - len(kept.images)
        final = load_captured(out / "captures.npz")
        assert np.array_equal(final.images[: len(kept.images)], kept.images)  # not retaken
        assert not (out / PARTIAL_NAME).exists()
        cal = Calibration.load(out / "calibration.toml")
        assert cal.learned_file == "learned.safetensors" and (out / cal.learned_file).is_file()
        assert "held-out patterns: PSNR R/G/B parametric" in text.out
        assert twin.emitting() == dict.fromkeys(COLOURS, 0.0)
    finally:
        r.stop()


def test_calib_learn_through_the_daemon_refuses_what_it_cannot_capture_with(short_dir, tiny,
                                                                            capsys):
    r = _running(short_dir, tiny, armed=False)
    try:
        active = r.daemon.calibration.active()
        other = dataclasses.replace(active, stage_at_slm_mm=active.stage_at_slm_mm + 1.0)
        path = other.save(short_dir / "other.toml")
        argv = ["calib", "learn", "--out", str(short_dir / "calib" / "x"), "--socket",
                str(r.socket), "--calibration", str(path)]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"--calibration {path} is not the calibration the daemon applies" in err, err
        assert main([*argv[:-2], "--sim-seed", "3"]) == 2
        assert "--sim-seed: for the simulated bench (--direct)" in capsys.readouterr().err
        # Checked before any pattern is made: the optics this command codes with, the arming.
        other_z0 = short_dir / "other-z0.toml"
        other_z0.write_text(f"[optics]\nz0_mm = {r.daemon.config.optics.z0_mm + 5}\n")
        assert main([*argv[:-2], "--config", str(other_z0)]) == 2
        assert (f"optics.z0_mm = {r.daemon.config.optics.z0_mm + 5:g} here, "
                f"{r.daemon.config.optics.z0_mm:g} in the daemon") in capsys.readouterr().err
        assert main(argv[:-2]) == 2
        assert ("the lasers are not armed; nhfd calib learn never arms: arm the lasers"
                in capsys.readouterr().err)
        assert not (short_dir / "calib" / "x").exists()
        assert r.daemon.laser.twin.max_emitted_pct() == 0.0
    finally:
        r.stop()
