"""Calibration recovery on several random twin benches: the signed error of each parameter.

Captures (through `SimBenchIO`, the test suite's small patterns and plan: tests/calib/conftest.py)
and fits `TrueBench.randomised(seed)` for each seed, and prints one row per seed and the mean:

    .venv/bin/python docs/calib_recovery_seeds.py --seeds 0-9
    .venv/bin/python docs/calib_recovery_seeds.py --seeds 0-9 --stop grating   # response only
    .venv/bin/python docs/calib_recovery_seeds.py --seeds 0-3 --set crosstalk_sigma_m=0

`--set NAME=VALUE` overrides a twin field (diagnosis: which of the twin's extras causes an
error). Columns (signed, fit minus truth):

    M %        magnification          scale %   stage scale (1/M^2)
    s0 um      where green images the SLM plane (SLM-space um); s0 %dof: of 8 p^2 / lambda_G
    offR/offB  the red and blue focus offsets (um)
    ph R/G/B   phase table RMS error, % of the true range; bias R/G/B: its mean (signed);
               end R/G/B: the error at grey 255
    nom R/G/B  the nominal 2 pi curve's RMS error, % of the true range
    shp R/G/B  the fit's RMS error after its best single scale factor; nsh: the nominal's
    I R/G, B/G intensity ratio error (%)
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nhfd.calib.capture import SimBenchIO, capture
from nhfd.calib.fit import fit_capture, geometry_from, measure_response
from nhfd.drivers.simcamera import TrueBench
from tests.calib.conftest import PANEL_HW, small_plan, small_spec


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def _value(text: str) -> object:
    for kind in (int, float):
        with contextlib.suppress(ValueError):
            return kind(text)
    return {"true": True, "false": False}.get(text.lower(), text)


def shape_rms(true: np.ndarray, got: np.ndarray) -> float:
    """RMS error of `got` times its best single scale factor, relative to the true range."""
    k = float(got @ true) / float(got @ got)
    return float(np.sqrt(((k * got - true) ** 2).mean())) / (true[-1] - true[0])


def phase_errors(true_tables, got_tables) -> dict[str, float]:
    out = {}
    nominal = 2 * np.pi * np.arange(256) / 256
    for c, name in enumerate("RGB"):
        true = np.asarray(true_tables[c])
        got = np.asarray(got_tables[c])
        span = true[-1] - true[0]
        out[f"ph {name}"] = 100 * float(np.sqrt(((got - true) ** 2).mean())) / span
        out[f"bias {name}"] = 100 * float((got - true).mean()) / span
        out[f"end {name}"] = 100 * float(got[-1] - true[-1]) / span
        out[f"nom {name}"] = 100 * float(np.sqrt(((nominal - true) ** 2).mean())) / span
        out[f"shp {name}"] = 100 * shape_rms(true, got)
        out[f"nsh {name}"] = 100 * shape_rms(true, nominal)
    return out


def intensity_errors(bench: TrueBench, intensity) -> dict[str, float]:
    rel = np.asarray(intensity) / intensity[1]
    true = np.asarray(bench.electrons_per_s) / bench.electrons_per_s[1]
    return {"I R/G": 100 * float(rel[0] / true[0] - 1), "I B/G": 100 * float(rel[2] / true[2] - 1)}


def run_seed(seed: int, stop: str, overrides: dict[str, object], root: Path) -> dict[str, float]:
    bench = TrueBench.randomised(seed, **overrides)
    spec = small_spec(bench)
    plan = small_plan(bench)
    plan.stop_after = stop
    # The lab knows roughly where the SLM plane is: the bench's draw rounded to the millimetre
    # (the test's fixed 10 mm leaves some draws near the sweep's ends).
    plan.stage_center_mm = float(round(bench.stage_at_slm_mm))
    out = root / f"seed{seed}"
    capture(out, SimBenchIO(bench, PANEL_HW, noise_seed=3), spec, plan, force=True)
    if stop == "grating":
        import json

        manifest = json.loads((out / "manifest.json").read_text())
        recs = [r for r in manifest["records"] if r.get("sweep") in ("grating", "flat")]
        resp = measure_response(out, spec, recs, geometry_from(manifest["located"]))
        return {**phase_errors(bench.phase_tables, resp.tables_rad),
                **intensity_errors(bench, resp.intensity)}
    with contextlib.redirect_stdout(io.StringIO()):
        cal = fit_capture(out)
    dof_g = 8 * bench.pitch_m**2 / bench.wavelengths_m[1]
    s0_um = (cal.stage_at_slm_mm - bench.stage_at_slm_mm) * 1e3 * bench.stage_scale
    return {
        "sign": bench.phase_sign, "mirror": float(bench.mirror_x),
        "M %": 100 * (cal.magnification / bench.magnification - 1),
        "scale %": 100 * (cal.stage_scale / bench.stage_scale - 1),
        "s0 um": s0_um, "s0 %dof": 100 * s0_um * 1e-6 / dof_g,
        "offR um": (cal.z_offset_m[0] - bench.z_offset_m[0]) * 1e6,
        "offB um": (cal.z_offset_m[2] - bench.z_offset_m[2]) * 1e6,
        **phase_errors(bench.phase_tables, cal.phase_tables_rad),
        **intensity_errors(bench, cal.intensity),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-9", help="e.g. 0-9 or 101,202,303")
    ap.add_argument("--stop", choices=("grating", "fine"), default="fine",
                    help="grating: the response fit only (fast)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="override a TrueBench field (diagnosis)")
    args = ap.parse_args(argv)
    overrides = {k: _value(v) for k, v in (s.split("=", 1) for s in args.set)}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in _seeds(args.seeds):
            t0 = time.perf_counter()
            row = run_seed(seed, args.stop, overrides, Path(tmp))
            rows.append(row)
            if len(rows) == 1:
                print("seed  " + "  ".join(f"{k:>8}" for k in row) + "    time")
            print(f"{seed:4d}  " + "  ".join(f"{v:+8.3f}" for v in row.values()) +
                  f"  {time.perf_counter() - t0:5.0f} s", flush=True)
    keys = list(rows[0])
    mean = [np.mean([r[k] for r in rows]) for k in keys]
    std = [np.std([r[k] for r in rows], ddof=1) if len(rows) > 1 else 0.0 for k in keys]
    print("mean  " + "  ".join(f"{v:+8.3f}" for v in mean))
    print(" std  " + "  ".join(f"{v:8.3f}" for v in std))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
