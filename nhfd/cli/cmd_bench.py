"""`nhfd bench NAME`: measured figures for the README (never timed tests).

Each benchmark lives in `nhfd.benchmarks.NAME` and exposes `register(subparsers)`; it prints a
table, writes JSON, and compares against a baseline measured in the same run (these machines are
noisy, ratios are what carry over).
"""

from __future__ import annotations

import argparse
import importlib

BENCHES: tuple[str, ...] = ("optics", "render", "holo", "tradeoff", "pipeline", "load",
                            "safety")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark", description=__doc__)
    benches = p.add_subparsers(dest="bench", metavar="NAME", required=True)
    for name in BENCHES:
        importlib.import_module(f"nhfd.benchmarks.{name}").register(benches)
