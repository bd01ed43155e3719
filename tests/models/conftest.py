"""A tiny synthetic dataset and a briefly trained run, shared by the model tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from nhfd.models.synthetic import synthetic_dataset
from nhfd.models.train import TrainOptions, train


def tiny_options(**kw) -> TrainOptions:
    base = dict(width=8, depth=2, unshuffle=1, inputs="rgb", steps=4, crop_width_px=64,
                crop_height_px=64, checkpoint_every=100, val_views=1, progress=False,
                threads=1)  # fmt: skip
    base.update(kw)
    return TrainOptions(**base)


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tiny_data")
    synthetic_dataset(out, size_hw=(64, 64), splits=(4, 1, 1))
    return out


@pytest.fixture(scope="session")
def tiny_run(tiny_data, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("tiny_run")
    train(tiny_data, run, tiny_options(), log=lambda _m: None)
    return run
