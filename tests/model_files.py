"""A model file whose nhfd metadata says something else: the same graph and weights written to
another path with keys changed (None removes a key). One helper for the tests that need a model
for other optics, another size or K, or without a record."""

from __future__ import annotations

import json
from pathlib import Path

import onnx

from nhfd.models.metadata import METADATA_KEY


def with_metadata(source: Path, path: Path, **changes: object) -> Path:
    """`source` written to `path` (which may be `source`) with `changes` to its metadata."""
    model = onnx.load(str(source))
    for prop in model.metadata_props:
        if prop.key == METADATA_KEY:
            meta = json.loads(prop.value)
            for key, value in changes.items():
                if value is None:
                    meta.pop(key, None)
                else:
                    meta[key] = value
            prop.value = json.dumps(meta)
    onnx.save(model, str(path))
    return path
