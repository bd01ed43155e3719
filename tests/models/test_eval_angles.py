"""`nhfd eval`'s angle to the nearest training pose: measured against the poses the model was
trained on (its metadata), not the evaluated dataset's own train split."""

from __future__ import annotations

import math

import pytest

from nhfd.models.evaluate import ANGLE_FALLBACK, evaluate, nearest_train_angle_deg
from nhfd.models.export import OnnxModel, export_onnx
from nhfd.models.synthetic import synthetic_dataset

# synthetic_dataset places view i of n at azimuth -20 + 40 i / (n - 1) degrees, radius 2,
# about the origin: the tiny run trained on views 0-3 of 6 (-20, -12, -4, +4 degrees).
TRAINED_AZ = (-20.0, -12.0, -4.0, 4.0)


def _expected(n: int) -> list[float]:
    return [min(abs(-20 + 40 * i / (n - 1) - a) for a in TRAINED_AZ) for i in range(n)]


@pytest.fixture(scope="module")
def exported(tiny_run, tmp_path_factory):
    return export_onnx(tiny_run, tmp_path_factory.mktemp("angles") / "m.onnx", check=False)


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    """Another dataset of the same optics: 3 train, 1 interp, 1 extrap views at -20..20 deg."""
    out = tmp_path_factory.mktemp("fresh")
    synthetic_dataset(out, size_hw=(32, 32), splits=(3, 1, 1), seed=1)
    return out


def test_export_records_the_training_poses(exported):
    poses = OnnxModel(exported.path).metadata["train_poses"]
    assert poses["center"] == [0.0, 0.0, 0.0]
    assert [round(p[0], 6) for p in poses["positions"]] == \
        [round(2 * math.sin(math.radians(a)), 6) for a in TRAINED_AZ]


@pytest.mark.parametrize("which", ["onnx", "run"])
def test_angles_are_to_the_models_own_training_poses(exported, tiny_run, tiny_data, fresh,
                                                     which):  # fmt: skip
    source = exported.path if which == "onnx" else tiny_run
    own = evaluate(source, tiny_data, splits=("train", "interp", "extrap"), log=lambda _m: None)
    angles = [v["nearest_train_deg"] for v in own["views"]]
    assert angles == pytest.approx(_expected(6), abs=1e-4)
    assert angles[:4] == pytest.approx([0.0] * 4, abs=1e-4) and min(angles[4:]) > 7.9
    other = evaluate(source, fresh, splits=("train", "interp", "extrap"), log=lambda _m: None)
    angles = [v["nearest_train_deg"] for v in other["views"]]
    # the fresh dataset's own training views are not the model's: 0, 2 and 4 degrees off
    assert angles == pytest.approx(_expected(5), abs=1e-4)
    assert other["model"]["angle_reference"].startswith("the poses the model was trained on")


def test_a_model_without_training_poses_falls_back_to_the_dataset_and_says_so(fresh):
    import json

    manifest = json.loads((fresh / "manifest.json").read_text())
    # the old measure: a fresh dataset's train views read 0 against their own split
    assert [nearest_train_angle_deg(manifest, i) for i in range(3)] == [0.0, 0.0, 0.0]
    trained = {"center": [0.0, 0.0, 0.0], "positions": [[0.0, 0.0, 2.0]]}  # azimuth 0
    assert [nearest_train_angle_deg(manifest, i, trained) for i in range(5)] == \
        pytest.approx([20.0, 10.0, 0.0, 10.0, 20.0], abs=1e-4)
    assert "records no training poses" in ANGLE_FALLBACK
