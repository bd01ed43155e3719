"""The learned bench from captures (`nhfd.calib.learn`) on a small seeded twin: with the pixels'
crosstalk and fill and zero-order light, the learned model predicts held-out patterns and a
held-out plane better than the parametric one by a margin; with those effects switched off the
margin (nearly) disappears; sgd through it ends closer to what the camera sees; a disarm stops
the capture with nothing emitted after it and nothing written. The parametric model is the
twin's own truth (`truth_calibration`), so what is left between it and the camera is what the
learned parts are for. The capture is citl's loop: it never arms and never raises a power, and
leaves every diode off."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from nhfd.calib.citl import CameraLoop
from nhfd.calib.learn import (
    CONTENT_PEAK,
    PARTIAL_NAME,
    Captured,
    LearnPlan,
    LearnResult,
    camera_loop,
    content_field,
    fidelity,
    learn,
    learn_settings,
    load_captured,
    load_partial,
    resume_key,
    save_captured,
)
from nhfd.calibration import Calibration
from nhfd.cli.main import main
from nhfd.config import Config, RefineSettings
from nhfd.device_settings import COLOURS
from nhfd.drivers.factory import BenchDevices, make_bench
from nhfd.drivers.simcamera import TrueBench
from nhfd.models.learned_bench import LearnedOptics, learned_of
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.refine import (
    BenchForward,
    CaptureStopped,
    refine,
    stack_loss,
    target_from_field,
)

from .conftest import BENCH_SEED
from .twin_stack import quick_devices, truth_calibration

WINDOW_HW = (32, 32)
PANEL_HW = (96, 96)
POWER_PCT = 10.0  # the simulated laser's cap
# The test's plan: 10 patterns x 3 planes x 3 colours = 90 captures, a short fit.
PLAN = LearnPlan(window_hw=WINDOW_HW, planes_m=(-0.4e-3, 0.0, 0.4e-3), held_out_plane=1,
                 sgd_patterns=4, sgd_iterations=(0, 3), random_patterns=2,
                 structured_patterns=4, held_out_patterns=3, steps=60, batch=3,
                 learning_rate=0.01)
# What the parametric model leaves out on the twin (docs/refine.md), switched off: the pixels'
# fill, gaps and crosstalk, the zero order, the pixels' shape on the twin's finer grid, the
# camera's noise and non-uniformity, and its pixels (1 um instead of 3.45 um: their area no
# longer blurs the image).
OFF = dict(fill_factor=1.0, crosstalk_sigma_m=0.0, zero_order_fraction=0.0, oversample=1,
           prnu=0.0, dsnu=0.0, shot_noise=False, read_noise_e=0.0, camera_pitch_m=1.0e-6)


@contextmanager
def _devices(twin: TrueBench) -> Iterator[BenchDevices]:
    """The simulated bench over `twin`, fast (no settle time, a quick stage), armed by the test
    (a person's arming), each colour's power set."""
    d = quick_devices(exposure_s=0.005, pixel_pitch_um=twin.camera_pitch_m * 1e6)
    with make_bench(d, PANEL_HW[1], PANEL_HW[0], bench=twin,
                    roi=twin.roi_for_panel(PANEL_HW)) as devices:
        devices.laser.arm(600)
        for name in COLOURS:
            devices.laser.set_power(name, POWER_PCT)
        yield devices


def _learn(twin: TrueBench, out: Path | None) -> tuple[LearnResult, Calibration, BenchDevices]:
    cal = truth_calibration(twin, twin.roi_for_panel(PANEL_HW))
    with _devices(twin) as devices:
        result = learn(camera_loop(devices, cal), cal, Config(), PLAN, out, panel_hw=PANEL_HW,
                       say=lambda _m: None)
        assert devices.laser.twin.max_emitted_pct() <= POWER_PCT + 1e-9
        assert not any(c.enabled for c in devices.laser.status().channels.values())
    return result, cal, devices


@pytest.fixture(scope="module")
def with_effects(tmp_path_factory: pytest.TempPathFactory) -> LearnResult:
    return _learn(TrueBench.randomised(BENCH_SEED), tmp_path_factory.mktemp("learn"))[0]


@pytest.fixture(scope="module")
def without_effects() -> LearnResult:
    return _learn(TrueBench.randomised(BENCH_SEED, **OFF), None)[0]


def _gain_db(table: dict[str, tuple[float, float, float]]) -> list[float]:
    return [q - p for p, q in zip(table["parametric"], table["learned"], strict=True)]


def _removed(table: dict[str, tuple[float, float, float]]) -> list[float]:
    """Per colour, the error the learned model removes: the parametric model's mean squared
    error less the learned one's, in units of the captures' peak squared."""
    return [10 ** (-p / 10) - 10 ** (-q / 10)
            for p, q in zip(table["parametric"], table["learned"], strict=True)]


def test_the_learned_bench_predicts_held_out_captures_better(with_effects) -> None:
    r = with_effects
    print("with effects:", *r.lines(), sep="\n  ")
    # Measured (2-core CPU, shared): parametric 24.0 / 26.5 / 23.7 dB, learned 36.8 / 35.0 /
    # 27.9 dB on the held-out patterns; 27.1 / 25.6 / 24.6 against 39.4 / 35.8 / 30.1 dB at
    # the held-out plane.
    assert min(_gain_db(r.held_out_patterns_db)) > 3.0, r.lines()
    assert min(_gain_db(r.held_out_plane_db)) > 3.0, r.lines()
    assert r.train_loss[1] < 0.5 * r.train_loss[0]


def test_the_margin_disappears_without_the_effects(with_effects, without_effects) -> None:
    r = without_effects
    print("without effects:", *r.lines(), sep="\n  ")
    # Measured (2-core CPU, shared): parametric 43.2 / 49.6 / 42.0 dB, learned 43.8 / 52.1 /
    # 47.4 dB on the held-out patterns: what is left is a hundredth of the error the learned
    # model removes with the effects on (0.6 / 2.5 / 5.4 dB of a far smaller error).
    assert min(r.held_out_patterns_db["parametric"]) > 40.0, r.lines()
    for on, off in zip(_removed(with_effects.held_out_patterns_db),
                       _removed(r.held_out_patterns_db), strict=True):
        assert off < 0.05 * on, (on, off)
    # The learned model does not make a near-perfect parametric model worse.
    assert min(_gain_db(r.held_out_patterns_db)) > -0.5, r.lines()
def test_the_files_are_written_and_the_calibration_uses_them(with_effects) -> None:
    r = with_effects
    assert r.weights is not None and r.calibration is not None
    cal = Calibration.load(r.calibration)
    assert cal.learned_path() == r.weights
    model, why = learned_of(cal, LearnedOptics(cal.wavelengths_m, cal.pitch_m, PANEL_HW))
    assert why is None and model is not None
    assert float(model.unmodulated.abs().max()) > 0.01  # it learned unmodulated light


@pytest.mark.parametrize("field,value,allowed", [
    ("held_out_plane", 3, r"0 <= i < 3"), ("held_out_patterns", 9, r"\[1, 8\]"),
    ("planes_m", (0.0,), "2 to 16 planes"), ("learning_rate", 0.0, r"\(0, 1\]"),
    ("settle_s", float("nan"), r"\[0, 60\] s")])
def test_a_plan_out_of_range_is_refused_naming_the_value(field: str, value: object,
                                                         allowed: str) -> None:
    with pytest.raises(ValueError, match=rf"{field} = .*: must be {allowed}"):
        dataclasses.replace(PLAN, **{field: value})


def test_the_plan_states_its_count_and_a_real_benchs_time() -> None:
    # 10 patterns x 3 planes: a stage move each (0.5 s) and 3 colours of settle, switch and
    # exposure (0.1 + 0.02 + 0.005 s): 30 x 0.875 s = 26.25 s.
    assert PLAN.captures == 90
    assert PLAN.bench_seconds() == pytest.approx(26.25)
    text = PLAN.describe()
    assert "= 90 captures" in text and "about 0.4 min on a real bench" in text
    assert "settle 100 ms" in text


def test_the_report_scores_the_fit_again_from_its_folder(with_effects, tmp_path, capsys
                                                       ) -> None:
    """`nhfd calib report` of the folder learn wrote: the captures and the settings kept beside
    the weights give the held-out plane's figures the fit printed, and every plane, held out or
    not, favours the learned model; the pictures and the table are written."""
    out = with_effects.weights.parent
    fid = fidelity(out)
    rows = {row["held_out"]: row for row in fid.per_plane}
    assert [row["held_out"] for row in fid.per_plane] == [False, True, False]
    for model in ("parametric", "learned"):
        assert rows[True][model] == pytest.approx(with_effects.held_out_plane_db[model], abs=0.01)
    for row in fid.per_plane:
        assert min(q - p for p, q in zip(row["parametric"], row["learned"], strict=True)) > 3.0
    # The predictions carry their gain: the learned one is nearer the captures inside the mask.
    err = {k: float(((getattr(fid, k) - fid.captured)[..., fid.mask] ** 2).mean())
           for k in ("parametric", "learned")}
    assert err["learned"] < 0.5 * err["parametric"], err
    assert main(["calib", "report", str(out), "-o", str(tmp_path / "r")]) == 0
    printed = capsys.readouterr().out.split()
    assert [Path(p).name for p in printed] == ["fidelity.png", "fidelity_psnr.png",
                                               "fidelity.json"]
    # 4 rows of 5 pictures at 3.1 in a row, 90 dpi
    assert Image.open(tmp_path / "r" / "fidelity.png").size[1] == round(4 * 3.1 * 90)
    table = json.loads((tmp_path / "r" / "fidelity.json").read_text())
    assert table["per_plane"][1]["learned"] == list(rows[True]["learned"])


def test_a_damaged_capture_set_is_refused_naming_the_file(with_effects, tmp_path) -> None:
    src = with_effects.weights.parent
    for name in ("calibration.toml", "learn.json", "learned.safetensors", "captures.npz"):
        shutil.copy(src / name, tmp_path / name)
    z = dict(np.load(tmp_path / "captures.npz"))
    z["images"][0, 0, 0, 0, 0] = np.nan
    np.savez(tmp_path / "captures.npz", **z)
    with pytest.raises(ValueError, match=r"captures\.npz: captures hold NaN or Inf"):
        fidelity(tmp_path)
    z["images"] = np.asarray([object()], dtype=object)
    np.savez(tmp_path / "captures.npz", **z)
    with pytest.raises(ValueError, match=r"captures\.npz: not a capture set of nhfd calib learn "
                                         r"\(Object arrays cannot be loaded"):
        fidelity(tmp_path)
    (tmp_path / "learn.json").unlink()
    with pytest.raises(ValueError, match=r"no learn\.json: not a folder nhfd calib learn wrote"):
        fidelity(tmp_path)


def test_a_twin_file_with_an_unknown_key_is_refused_before_anything_is_captured(
        tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    twin = tmp_path / "twin.toml"
    twin.write_text("randomised_seed = 21\nfill_fraction = 0.8\n")
    out = tmp_path / "out"
    assert main(["calib", "learn", "--direct", "--twin", str(twin), "--out", str(out)]) == 2
    assert "unknown key(s) fill_fraction" in capsys.readouterr().err
    assert not out.exists()


def test_learn_without_direct_and_without_a_daemon_says_how_to_go_on(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sock = tmp_path / "none.sock"
    assert main(["calib", "learn", "--out", str(tmp_path / "out"), "--socket", str(sock)]) == 2
    err = capsys.readouterr().err
    assert f"cannot reach the daemon: no nhfd serve at {sock}" in err, err
    assert "start nhfd serve, or pass --direct" in err, err
    assert not (tmp_path / "out").exists()


def test_sgd_through_the_learned_bench_ends_closer_to_what_the_camera_sees(with_effects
                                                                          ) -> None:
    cal = Calibration.load(with_effects.calibration)
    enc = Encoder(learn_settings(Config(), cal, WINDOW_HW, PANEL_HW))
    learned, why = learned_of(cal, LearnedOptics(cal.wavelengths_m, cal.pitch_m, PANEL_HW))
    assert learned is not None, why
    # Content none of the training patterns had (another seed).
    ref = content_field(np.random.default_rng(11), 0, WINDOW_HW, PLAN.planes_m, enc.settings)
    with torch.no_grad():
        ref = ref * (CONTENT_PEAK / float(enc.to_slm(ref).abs().max()))
        start, _ = enc.code(enc.to_slm(ref))
    target = target_from_field(ref, PLAN.planes_m, enc)
    settings = RefineSettings(iterations=30, tolerance=0.0)
    frames = {name: refine(start, target, BenchForward(enc, PLAN.planes_m, model), settings)
              for name, model in (("parametric", None), ("learned", learned))}
    with _devices(TrueBench.randomised(BENCH_SEED)) as devices:
        loop = CameraLoop(devices, cal, enc)
        seen_db = {}
        for name, out in frames.items():
            captured, seen = loop(out.grey, target.planes_m)
            mask = target.mask & torch.as_tensor(seen)
            seen_db[name] = -10 * math.log10(float(stack_loss(
                torch.as_tensor(captured).float(), target, mask)))
    print("sgd as the camera sees it:", seen_db)
    # Measured (2-core CPU, shared): 26.85 dB through the parametric model, 31.52 dB through
    # the learned one, 30 steps each from the same double-phase frame.
    assert seen_db["learned"] > seen_db["parametric"] + 1.0, seen_db


def test_a_disarm_stops_the_capture_and_nothing_is_emitted_after(tmp_path: Path) -> None:
    twin = TrueBench.randomised(BENCH_SEED)
    cal = truth_calibration(twin, twin.roi_for_panel(PANEL_HW))
    with _devices(twin) as devices:
        laser, record = devices.laser, devices.laser.twin
        shots = devices.camera.capture
        disarmed_at: list[float] = []
        calls = [0]

        def capture(*args: object, **kwargs: object) -> object:
            calls[0] += 1
            if calls[0] == 5:  # the first pattern's second plane, green's diode on
                laser.disarm()  # a person disarms mid-capture
                disarmed_at.append(record.clock())
            return shots(*args, **kwargs)

        devices.camera.capture = capture  # type: ignore[method-assign]
        with pytest.raises(CaptureStopped, match="the lasers are not armed"):
            learn(camera_loop(devices, cal), cal, Config(), PLAN, tmp_path, panel_hw=PANEL_HW,
                  say=lambda _m: None)
        assert disarmed_at and 0 < record.max_emitted_pct() <= POWER_PCT + 1e-9  # it captured
        for name in COLOURS:
            after = [pct for t, pct in record.emission(name) if t >= disarmed_at[0]]
            assert not any(after), (name, after)
        assert not any(c.enabled for c in laser.status().channels.values())
    assert not (tmp_path / "learned.safetensors").exists()
    assert not (tmp_path / "calibration.toml").exists()


def test_a_partial_capture_of_another_plan_is_refused_and_kept(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    grey = rng.integers(0, 256, (4, 3, 8, 8), dtype=np.uint8)
    data = Captured(grey, ("random",) * 4, rng.random((2, 3, 3, 6, 6), dtype=np.float32),
                    np.ones((6, 6), bool), 1.5)
    path = save_captured(data, tmp_path / PARTIAL_NAME, key="plan-a")
    before = path.read_bytes()
    resumed = load_partial(path, "plan-a", grey, data.kinds)
    assert resumed is not None and np.array_equal(resumed.images, data.images)
    for key, other in (("plan-b", grey), ("plan-a", grey[::-1])):
        with pytest.raises(ValueError, match=f"{path}: 2 patterns captured with another plan"):
            load_partial(path, key, other, data.kinds)
    assert path.read_bytes() == before  # refused, not overwritten
    # A partial set is not a whole one: the fit's loader refuses it.
    with pytest.raises(ValueError, match=r"captures float32 \(2, 3, 3, 6, 6\): must be float32 "
                                         r"\[4, D, 3, h, w\]"):
        load_captured(path)
    # A plan that differs only in the fit's fields resumes; one that changes the patterns not.
    cal = truth_calibration(TrueBench(), TrueBench().roi_for_panel(PANEL_HW))
    s = learn_settings(Config(), cal, WINDOW_HW, PANEL_HW)
    key = resume_key(PLAN, s, cal)
    assert resume_key(dataclasses.replace(PLAN, steps=5, batch=1), s, cal) == key
    assert resume_key(dataclasses.replace(PLAN, seed=PLAN.seed + 1), s, cal) != key
