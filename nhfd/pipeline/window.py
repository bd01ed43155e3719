"""The frame window's size. Torch-free (the package's `__init__` imports nothing), so
`nhfd bench pipeline`, whose module the CLI loads to build its parser, checks a model against the
panel without loading the pipeline."""

from __future__ import annotations

from typing import Any


def frame_window_hw(config: Any, metadata: dict[str, Any]) -> tuple[int, int]:
    """The frames' window (height, width): `daemon.frame_size_px` [W, H], or the model's
    training size when that is empty."""
    size = list(config.daemon.frame_size_px)
    if size:
        return int(size[1]), int(size[0])
    h, w = (int(v) for v in metadata["train_size_hw"])
    return h, w
