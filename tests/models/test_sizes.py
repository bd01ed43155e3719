"""Checked input sizes: the export records them against torch, the ONNX-only check catches a
runtime that goes wrong at one shape, `nhfd model check-sizes` records more, and the frame worker
refuses a window of a size its model was not checked at."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from nhfd.config import Config
from nhfd.models.export import OnnxModel, export_onnx
from nhfd.models.metadata import SIZE_TOLERANCE, parse_model_info
from nhfd.models.sizes import (
    UncheckedSize,
    check_sizes,
    read_metadata,
    tile_check,
    window_check,
)


@pytest.fixture(scope="module")
def exported(tiny_run, tmp_path_factory):
    return export_onnx(tiny_run, tmp_path_factory.mktemp("sizes") / "tiny.onnx")


def _rewrite_metadata(path, meta) -> None:
    import onnx

    model = onnx.load(str(path))
    for prop in model.metadata_props:
        if prop.key == "nhfd":
            prop.value = json.dumps(meta)
    onnx.save(model, str(path))


@pytest.fixture(scope="module")
def unchecked(exported, tmp_path_factory):
    """The model as an older export (or one made with --no-check) is: no checked_sizes."""
    path = tmp_path_factory.mktemp("unchecked") / "old.onnx"
    shutil.copyfile(exported.path, path)
    meta = read_metadata(path)
    del meta["checked_sizes"]
    _rewrite_metadata(path, meta)
    return path


def test_export_records_the_training_window_1024x576_and_the_panel_against_torch(exported):
    meta = OnnxModel(exported.path).metadata
    entries = meta["checked_sizes"]
    # tiny: trained at 64 x 64, input multiple 4 (so 1080 needs no rounding)
    assert [e["hw"] for e in entries] == [[64, 64], [576, 1024], [1080, 1920]]
    for e in entries:
        assert e["ok"] and 0 <= e["max_abs_diff"] < 1e-4 and e["against"].startswith("the torch")
    info = OnnxModel(exported.path).info
    assert info.checked_sizes_hw() == ([(64, 64), (576, 1024), (1080, 1920)], True)
    assert exported.metadata["checked_sizes"] == entries  # what export_onnx returns, as written


def test_a_model_without_checked_sizes_counts_its_training_window_only_and_says_so(unchecked):
    meta = read_metadata(unchecked)
    assert "checked_sizes" not in meta
    info = parse_model_info(meta, "old.onnx")
    assert info.checked_sizes is None
    assert info.checked_sizes_hw() == ([(64, 64)], False)
    assert window_check(info, (64, 64), "old.onnx", allow=False) is None
    with pytest.raises(UncheckedSize) as err:
        window_check(info, (1080, 1920), "old.onnx", allow=False)
    msg = str(err.value)
    assert msg.startswith("old.onnx: frame window 1920 x 1080 is not a size this model was "
                          "checked at; checked: 64 x 64 (its metadata has no checked_sizes")
    assert "allow_unchecked_sizes = true" in msg and "--sizes 1920x1080" in msg
    # allowed: the same reason comes back as a warning instead
    assert window_check(info, (1080, 1920), "old.onnx", allow=True) == msg


def test_a_window_is_checked_by_its_padded_size(exported):
    info = OnnxModel(exported.path).info
    assert window_check(info, (1078, 1917), "m", allow=False) is None  # runs at 1080 x 1920
    with pytest.raises(UncheckedSize, match=r"frame window 1918 x 1082 \(run at 1920 x 1084, "
                                            r"padded to multiples of 4\)"):
        window_check(info, (1082, 1918), "m", allow=False)


class _WrongAt:
    """An onnxruntime session that returns wrong values at one input shape (as torch's FFT once
    did at one shape): one output pixel off by `error`."""

    def __init__(self, session, hw, error):
        self.session, self.hw, self.error = session, hw, error

    def get_inputs(self):
        return self.session.get_inputs()

    def run(self, names, feeds):
        out = self.session.run(names, feeds)
        if next(iter(feeds.values())).shape[-2:] == self.hw:
            out[1][0, 1, self.hw[0] // 3, self.hw[1] // 2] += self.error
        return out


def test_the_onnx_only_check_passes_the_graph_and_catches_a_wrong_shape(exported):
    import onnxruntime as ort

    session = ort.InferenceSession(str(exported.path), providers=["CPUExecutionProvider"])
    meta = OnnxModel(exported.path).metadata
    hw = (160, 232)
    diff, against = tile_check(session, meta, hw)
    assert diff < 1e-5 and "tiles" in against and "receptive margin" in against
    for error in (0.01, float("nan")):  # an interior pixel, ten times the tolerance; or NaN
        bad, _ = tile_check(_WrongAt(session, hw, error), meta, hw)
        assert (bad == pytest.approx(error, rel=1e-3) if error == error else bad == np.inf)
        assert not bad <= SIZE_TOLERANCE


def test_the_tile_check_batches_its_tiles_and_finds_what_one_at_a_time_finds(exported,
                                                                             monkeypatch):
    """Tiles go through the graph in batches (its dynamic batch dimension); one tile per call
    (a graph with a fixed batch) sees the same differences, and the same wrong pixel."""
    import onnxruntime as ort

    from nhfd.models import sizes

    session = ort.InferenceSession(str(exported.path), providers=["CPUExecutionProvider"])
    meta = OnnxModel(exported.path).metadata
    hw = (160, 232)
    assert sizes._tiles_per_call(session, (32, 48)) == 64  # dynamic batch: up to 64 at a time
    batched, _ = tile_check(session, meta, hw)
    wrong_batched, _ = tile_check(_WrongAt(session, hw, 0.01), meta, hw)
    monkeypatch.setattr(sizes, "TILE_BATCH_PX", 1)  # one tile per call
    single, _ = tile_check(session, meta, hw)
    wrong_single, _ = tile_check(_WrongAt(session, hw, 0.01), meta, hw)
    assert batched == pytest.approx(single, abs=1e-6) and single < 1e-5
    assert wrong_batched == pytest.approx(wrong_single, rel=1e-6)

    class _FixedBatch:
        def get_inputs(self):
            return [type("Input", (), {"shape": [1, 4, "h", "w"]})()]

    monkeypatch.undo()
    assert sizes._tiles_per_call(_FixedBatch(), (32, 48)) == 1


def test_check_sizes_cli_records_onnx_only_checks_atomically(unchecked, tmp_path, capsys):
    from nhfd.cli.main import main

    path = tmp_path / "m.onnx"
    shutil.copyfile(unchecked, path)
    before = read_metadata(path)
    assert main(["model", "check-sizes", str(path), "--sizes", "232x160", "96x64"]) == 0
    out = capsys.readouterr().out
    assert "232 x 160: ok" in out and "96 x 64: ok" in out and "ONNX only" in out
    meta = read_metadata(path)
    assert [e["hw"] for e in meta["checked_sizes"]] == [[64, 96], [160, 232]]
    assert {k: v for k, v in meta.items() if k != "checked_sizes"} == before  # nothing else
    assert not list(tmp_path.glob("*.tmp"))
    OnnxModel(path)  # still a loadable model
    # a later check adds to the record; a size is given as WxH and rounded up to the multiple
    assert main(["model", "check-sizes", str(path), "--sizes", "95x63"]) == 0
    assert [e["hw"] for e in read_metadata(path)["checked_sizes"]] == [[64, 96], [160, 232]]
    assert main(["model", "check-sizes", str(path), "--sizes", "1080x"]) == 2
    assert "--sizes '1080x' is not of the form WxH" in capsys.readouterr().err


def test_check_sizes_against_the_run_and_refuses_another_run(exported, tiny_run, tmp_path,
                                                              capsys):
    from nhfd.cli.main import main

    path = tmp_path / "m.onnx"
    shutil.copyfile(exported.path, path)
    assert main(["model", "check-sizes", str(path), "--sizes", "200x120",
                 "--run", str(tiny_run)]) == 0
    entry = next(e for e in read_metadata(path)["checked_sizes"] if e["hw"] == [120, 200])
    assert entry["against"] == "the torch network of its run" and entry["max_abs_diff"] < 1e-4
    assert check_sizes(path, [(64, 64)], lambda hw: float("nan"))[0]["ok"] is False
    _rewrite_metadata(path, dict(read_metadata(path), train_steps=-1))
    assert main(["model", "check-sizes", str(path), "--run", str(tiny_run)]) == 2
    assert "not the run" in capsys.readouterr().err


def test_the_worker_refuses_an_unchecked_window_at_load_unless_allowed(unchecked):
    from nhfd.pipeline.worker import _WorkerState

    def state(allow: bool) -> _WorkerState:
        return _WorkerState(Config.model_validate(
            {"daemon": {"frames": {"size_px": [192, 128], "allow_unchecked_sizes": allow}}}))

    refusing = state(False)
    with pytest.raises(UncheckedSize, match=r"frame window 192 x 128 is not a size this model "
                                            r"was checked at; checked: 64 x 64"):
        refusing.load_model(str(unchecked))
    assert refusing.model is None  # nothing replaced
    info = state(True).load_model(str(unchecked)).to_json()  # status's "model"
    assert info["window_hw"] == [128, 192] and info["checked_sizes_hw"] == [[64, 64]]
    assert info["checked_sizes_recorded"] is False  # an older export: the training window only
    assert "allow_unchecked_sizes" in info["size_warning"]
