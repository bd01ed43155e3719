"""The README's first command: the whole optics chain on a three-depth target."""

from __future__ import annotations

import json

from nhfd.cli.main import main
from nhfd.config import load_config
from nhfd.demos.optics import run_demo, sharpness

SMALL = """
[slm]
width_px = 448
height_px = 320
[optics]
hologram_width_px = 256
hologram_height_px = 192
"""


def test_each_word_is_sharpest_at_its_own_depth_on_the_phase_only_display(tmp_path):
    path = tmp_path / "small.toml"
    path.write_text(SMALL)
    result = run_demo(load_config(path, env={}).config)
    assert result.word_depths_m == (3e-3, 0.0, -3e-3)
    for stack in (result.target_stack, result.shown_stack):
        for rows, z in zip(result.word_rows, result.word_depths_m, strict=True):
            scores = [sharpness(stack[d][:, rows]) for d in range(len(result.planes_m))]
            assert result.planes_m[scores.index(max(scores))] == z
    assert result.psnr_db > 20  # the display resembles the complex hologram
    assert max(result.clipped_fraction) < 0.01
    assert result.slm_grey.shape == (3, 320, 448)


def test_demo_command_writes_its_files(tmp_path, monkeypatch):
    path = tmp_path / "small.toml"
    path.write_text(SMALL)
    out = tmp_path / "demo"
    assert main(["demo", "optics", "--config", str(path), "--out", str(out)]) == 0
    assert (out / "focal_stack.png").stat().st_size > 10_000
    assert (out / "slm_green.png").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["focus"]["NEAR"]["sharpest_plane_mm"] == 3.0
