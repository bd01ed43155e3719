"""Shared fixtures. Tests that need ../shared/data skip with a reason when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(autouse=True)
def _seeded() -> None:
    torch.manual_seed(1234)


@pytest.fixture
def shared_scenes() -> Path:
    scenes = SHARED_DATA / "scenes"
    if not scenes.is_dir():
        pytest.skip(f"shared scenes not found at {scenes} (a user checkout has no ../shared)")
    return scenes
