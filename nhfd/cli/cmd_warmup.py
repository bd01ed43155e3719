"""`nhfd warmup`: compile and cache the frame path's CPU kernels now, not at the first view."""

from __future__ import annotations

import argparse
import json

from nhfd.pipeline.warmup import warm_frame_path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("warmup", help="compile the CPU kernels once, so the first view is fast",
                       description="Compute one small frame of the shipped donut so that the "
                       "renderer's and the double-phase coder's kernels are compiled and cached "
                       "on disk (about 25 s once after an install on 2 cores; a second or two "
                       "when they are cached already). `make demo` and `make test` run it; a "
                       "service can run it before `nhfd serve` (ExecStartPre=).")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if not args.json:
        print("nhfd warmup: compiling the frame path's CPU kernels (render, double-phase "
              "coding) once; they are cached on disk for every later start", flush=True)
    result = warm_frame_path()
    if args.json:
        print(json.dumps(result))
        return 0
    kernels = result["kernels"]
    compiled = sum(k["misses"] for k in kernels.values())
    loaded = sum(k["hits"] for k in kernels.values())
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in result["stages_s"].items())
    how = (f"{compiled} kernel signatures compiled and cached" if compiled else
           f"all {loaded} kernel signatures loaded from the cache")
    print(f"warm in {result['seconds']:.1f} s ({how}; the frame: {stages})")
    return 0
