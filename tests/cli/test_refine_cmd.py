"""`nhfd refine` (issue 34): a bad setting is one line naming `refine.<key>` and its range, exit
2, nothing written; citl without --sim says where a real bench's citl runs; a small sgd run on the
shipped donut writes the region's frame and a report no worse than its start."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from nhfd.cli.cmd_refine import parse_view
from nhfd.cli.main import main
from nhfd.config import Config, RefineSettings, refine_settings
from nhfd.models.export import load_model
from nhfd.pipeline.settings import frame_region, frame_settings
from tests.words import PYTHON_REPR

REPO = Path(__file__).resolve().parents[2]
MODEL = REPO / "models" / "nhf-donut-512.onnx"
SCENE = REPO / "models" / "scenes" / "donut.ply"


def test_an_out_of_range_iterations_exits_2_naming_the_setting_and_writes_nothing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "refine"
    assert main(["refine", "--scene", str(SCENE), "--iterations", "0", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == ("nhfd refine: error: refine.iterations = 0: must be "
                   "1 <= iterations <= 100000\n")
    assert not out.exists()


def test_each_override_is_checked_through_refine_settings() -> None:
    base = RefineSettings(iterations=50)
    # Every bad value named, in the settings' order.
    with pytest.raises(ValueError, match=r"^refine.seconds = 0.0: must be 0 < seconds <= 3600; "
                                         r"refine.subframes = 17: must be 1 <= subframes <= 16$"):
        refine_settings(base, {"subframes": 17, "seconds": 0.0, "planes": None})
    s = refine_settings(base, {"subframes": 4, "planes": None})
    assert (s.subframes, s.iterations, s.planes) == (4, 50, base.planes)  # the rest kept
    with pytest.raises(ValueError, match=r"--view '1,2': expected AZ,EL,R"):
        parse_view("1,2")


def test_citl_without_sim_says_where_a_real_bench_runs_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "refine"
    assert main(["refine", "--scene", str(SCENE), "--quality", "citl", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("nhfd refine: error: --quality citl needs --sim: nhfd refine drives "
                          "only the simulated bench")
    assert "belong to the daemon" in err and "nhfctl set-view ... --quality citl" in err
    assert not out.exists()


def test_a_small_sgd_run_writes_the_region_frame_and_a_report_no_worse_than_its_start(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "refine"
    assert main(["refine", "--scene", str(SCENE), "--model", str(MODEL), "--size", "96x64",
                 "--iterations", "5", "--quality", "sgd", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "sgd  iteration    0" in printed  # progress lines
    assert not PYTHON_REPR.search(printed), printed  # words, not Python
    # The region: the 96 x 64 window plus the propagation's reach, on the configured panel.
    config = Config()
    s = frame_settings(config, load_model(MODEL, config).info, None)
    region = frame_region(dataclasses.replace(s, window_hw=(64, 96)))
    frame = np.load(out / "frame.npy")
    assert frame.shape == (1, 3, region.height, region.width) == (1, 3, 112, 144)
    assert frame.dtype == np.uint8
    png = Image.open(out / "frame_0.png")
    assert png.mode == "RGB" and png.size == (region.width, region.height)
    assert np.array_equal(np.asarray(png), frame[0].transpose(1, 2, 0))
    report = json.loads((out / "report.json").read_text())
    r = report["report"]
    assert (r["tier"], r["iterations"], r["stop"]) == ("sgd", 5, "iterations")
    assert r["psnr_db"] >= r["start_psnr_db"]
    assert report["start"] == "network" and len(report["planes_m"]) == 3
    assert len(report["history"]["sgd"]) == 5
    assert report["view"]["kind"] == "orbit" and report["window_hw"] == [64, 96]
    assert "| sgd | 5 |" in (out / "report.md").read_text()
