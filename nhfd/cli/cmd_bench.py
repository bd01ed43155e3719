"""`nhfd bench NAME`: measured figures for the README (never timed tests).

BENCHES is the registry: each benchmark lives in `nhfd.benchmarks.NAME` and exposes
`register(subparsers)`; only the one named on the command line is imported. It prints a table,
writes JSON, and compares against a baseline measured in the same run (these machines are noisy,
ratios are what carry over).
"""

from __future__ import annotations

import argparse

from nhfd.cli.args import Command, LazyCommands

# Each help line is the one its module registers (a test checks).
BENCHES: tuple[Command, ...] = (
    Command("optics", "nhfd.benchmarks.optics",
            "angular-spectrum propagation vs the bare FFT pair"),
    Command("render", "nhfd.benchmarks.render", "CPU splat rendering vs NumPy compositing"),
    Command("holo", "nhfd.benchmarks.holo", "wavefront inversion: seconds per full-colour example"),
    Command("tradeoff", "nhfd.benchmarks.tradeoff",
            "network size vs latency vs held-out quality"),
    Command("pipeline", "nhfd.benchmarks.pipeline", "view-change-to-SLM latency per stage"),
    Command("load", "nhfd.benchmarks.load", "status latency and memory under a set_view storm"),
    Command("safety", "nhfd.benchmarks.safety", "time from each fault to every laser off"),
    Command("hostile", "nhfd.benchmarks.hostile",
            "attacks on a lit daemon: status, disarms, memory, laser off"),
    Command("triggers", "nhfd.benchmarks.triggers",
            "calibration capture time with and without hardware triggers"),
    Command("distributed", "nhfd.benchmarks.distributed",
            "2 local workers vs 1: dataset build and training"),
    Command("geometry", "nhfd.benchmarks.geometry",
            "dot geometry, warps and SSIM vs OpenCV and kornia"),
    Command("quality", "nhfd.benchmarks.quality",
            "speed against captured quality of the frame tiers"),
    Command("refine", "nhfd.benchmarks.refine",
            "ms per sgd iteration per device at the panel's size"),
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark", description=__doc__)
    benches = p.add_subparsers(dest="bench", metavar="NAME", required=True, action=LazyCommands)
    benches.add_registry(BENCHES)
