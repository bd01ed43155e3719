"""A model tuned for one bench serves on that bench only: the frame worker refuses it under
another calibration or under none, naming both, and the model in service stays;
`daemon.frames.allow_other_bench` serves it anyway and says so; status names the model's bench,
and warns when the calibration changes under it."""

from __future__ import annotations

from pathlib import Path

import pytest

from nhfd.calibration import Calibration, bench_record, fingerprint, other_bench
from nhfd.config import Config
from nhfd.pipeline.worker import ModelUnfit, _WorkerState
from tests.daemon.test_bad_inputs import write_calibration
from tests.models.test_hostile_models import SHIPPED, hostile_copy, setting

from .conftest import Running

FRAME = [512, 288]  # the shipped model's training window (checked)


def tuned_copy(tmp_path: Path, cal: Calibration) -> Path:
    """The shipped model with a `tuned_for` record naming `cal`, as `nhfd model tune` writes."""
    record = {**bench_record(cal, "2026-12-02T06:00:00+00:00"), "steps": 1}
    return hostile_copy(SHIPPED, tmp_path / "tuned.onnx", meta=setting("tuned_for", record))


def worker(cal_path: Path | None, **frames: object) -> _WorkerState:
    data: dict = {"daemon": {"frames": {"size_px": FRAME, **frames}}}
    if cal_path is not None:
        data["calibration"] = {"file": str(cal_path)}
    return _WorkerState(Config.model_validate(data))


@pytest.fixture
def benches(tmp_path):
    """Two calibrations of the default bench that differ in one fitted value, and a model
    tuned for the first."""
    a = write_calibration(tmp_path / "bench-a.toml", stage_at_slm_mm=5.0)
    b = write_calibration(tmp_path / "bench-b.toml", stage_at_slm_mm=7.0)
    model = tuned_copy(tmp_path, Calibration.load(a))
    return a, b, model


def test_the_fingerprint_is_the_fit_not_the_file(tmp_path):
    a = write_calibration(tmp_path / "a.toml", stage_at_slm_mm=5.0)
    moved = write_calibration(tmp_path / "elsewhere.toml", stage_at_slm_mm=5.0)
    other = write_calibration(tmp_path / "b.toml", stage_at_slm_mm=5.001)
    ca, cm, cb = (Calibration.load(p) for p in (a, moved, other))
    assert fingerprint(ca) == fingerprint(cm) != fingerprint(cb)
    record = {"calibration": ca.label, "calibration_sha256": fingerprint(ca), "date": "d"}
    assert other_bench(record, cm) is None and other_bench(None, cb) is None
    assert other_bench(record, cb).startswith(f"the model was tuned for calibration {ca.label}")


def test_a_tuned_model_serves_on_its_own_bench_and_status_names_it(benches):
    a, _, model = benches
    loaded = worker(a).load_model(str(model))
    shown = loaded.to_json()
    cal = Calibration.load(a)
    assert shown["tuned_for"] == {"calibration": cal.label,
                                  "calibration_sha256": fingerprint(cal),
                                  "date": "2026-12-02T06:00:00+00:00"}
    assert "bench_warning" not in shown
    untuned = worker(a).load_model(str(SHIPPED)).to_json()
    assert untuned["tuned_for"] is None


@pytest.mark.parametrize("elsewhere", ["another calibration", "no calibration"])
def test_on_another_bench_it_is_refused_naming_both_and_the_served_model_stays(benches,
                                                                              elsewhere):
    a, b, model = benches
    state = worker(b if elsewhere == "another calibration" else None)
    state.load_model(str(SHIPPED))
    serving = state.model
    with pytest.raises(ModelUnfit) as info:
        state.load_model(str(model))
    message = str(info.value)
    assert f"the model was tuned for calibration {Calibration.load(a).label}" in message
    if elsewhere == "another calibration":
        assert f"this bench applies calibration {Calibration.load(b).label}" in message
    else:
        assert "this bench applies no calibration (calibration.file is empty)" in message
    assert "daemon.frames.allow_other_bench = true" in message
    assert state.model is serving and state.model_id == 1  # the model in service stays


def test_allow_other_bench_serves_it_and_says_so(benches):
    a, b, model = benches
    loaded = worker(b, allow_other_bench=True).load_model(str(model))
    warning = loaded.to_json()["bench_warning"]
    assert warning.startswith(f"the model was tuned for calibration {Calibration.load(a).label}")
    assert warning.endswith("served because daemon.frames.allow_other_bench = true")


def test_a_calibration_changed_under_a_tuned_model_is_a_warning_and_it_keeps_serving(
        short_dir, mecom_twin, tiny):
    from .test_bad_inputs import _with_calibration
    from .test_frames import daemon_config, wait_for_frames

    a = write_calibration(short_dir / "calibration.toml", stage_at_slm_mm=5.0)
    record = bench_record(Calibration.load(a), "2026-12-02")
    (short_dir / "models").mkdir(exist_ok=True)
    model = hostile_copy(tiny["model"], short_dir / "models" / "tuned.onnx",
                         meta=setting("tuned_for", record))
    config = _with_calibration(daemon_config(
        short_dir, mecom_twin, tiny, paths={"scene": str(short_dir / "scenes" / "cloud.ply")},
        frames={"model": str(model)}), a)
    r = Running(config, short_dir)
    try:
        c = r.client()
        s = wait_for_frames(c)
        assert s["model"]["tuned_for"]["calibration"] == record["calibration"]
        assert not [w for w in s["warnings"] if "tuned for" in w]
        write_calibration(short_dir / "new.tmp", stage_at_slm_mm=6.0).replace(a)  # a new fit
        s = c.status()
        warnings = [w for w in s["warnings"] if "the model was tuned for" in w]
        assert len(warnings) == 1, s["warnings"]
        assert warnings[0].endswith("the calibration changed since the model was loaded; it "
                                    "keeps serving until another model is loaded")
        assert s["model"]["path"] == str(model)  # still the one serving
    finally:
        r.stop()
