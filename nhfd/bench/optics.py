"""`nhfd bench optics`: propagation cost against the bare FFT pair measured in the same run.

The workload of the issue: a 3 x 1080 x 1920 complex64 field with 2x padding propagated to 8
depths. "Bare FFT pair" is the FFT work such a call cannot avoid (one forward transform of the
padded field and one inverse per depth); cached propagation should stay within 1.3x of it.
"finite check" is the refusal of NaN and Inf every field passes through on the way in
(`nhfd.optics._validate.finite_field`), on the unpadded field. "FFT checks" lists each FFT
layout's one-time known-answer check (`nhfd.optics.fft`), paid by the first call (the warm-up).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

from nhfd.cli.args import parse_wxh


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("optics", help="angular-spectrum propagation vs the bare FFT pair",
                       description=__doc__)
    p.add_argument("--size", default="1920x1080", help="field WxH (default 1920x1080)")
    p.add_argument("--depths", type=int, default=8, help="planes per call (default 8)")
    p.add_argument("--colours", type=int, default=3, choices=(1, 2, 3),
                   help="colour channels, R first (default 3)")
    p.add_argument("--padding", default="2x", choices=("none", "2x", "auto"))
    p.add_argument("--repeats", type=int, default=3, help="timed repeats; the median is kept")
    p.add_argument("--out", default="out/bench/optics.json", help="JSON file to write")
    p.set_defaults(handler=run)


def _median_s(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up: allocator, FFT plans
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def run(args: argparse.Namespace) -> int:
    import torch

    from nhfd.bench.machine import describe
    from nhfd.optics import Aperture, KernelCache, fft, plan_padding, propagate
    from nhfd.optics._validate import finite_field

    w, h = parse_wxh(args.size, "--size")
    if args.depths < 1 or args.repeats < 1 or w < 1 or h < 1:
        raise ValueError("--size, --depths and --repeats must be positive")
    pitch, lams = 8e-6, (660e-9, 520e-9, 450e-9)[: args.colours]
    zs = [-3e-3 + 6e-3 * i / max(1, args.depths - 1) for i in range(args.depths)]
    aperture = Aperture(cutoff_per_px=Aperture().cutoff_per_px[: args.colours])
    field = torch.randn(args.colours, h, w, dtype=torch.complex64)
    plan = plan_padding((h, w), pitch, lams, max(abs(z) for z in zs), aperture, args.padding)
    hp, wp = plan.padded_hw
    cache = KernelCache(max_bytes=2**34)

    def bare() -> None:
        spec = fft.fft2(field, s=(hp, wp))
        for _ in zs:
            fft.ifft2(spec)

    def cached() -> None:
        propagate(field, zs, pitch, lams, padding=args.padding, aperture=aperture, cache=cache)

    def uncached() -> None:
        propagate(field, zs, pitch, lams, padding=args.padding, aperture=aperture)

    print(f"{plan.describe()}; {args.depths} depths; {args.colours} colours; {describe()}")
    fft.clear_checks()
    rows = {}
    for name, fn, reps in (
        ("finite check", lambda: finite_field("field", field), args.repeats),
        ("bare FFT pair", bare, args.repeats),
        ("propagate, cached kernels", cached, args.repeats),
        ("propagate, uncached", uncached, max(1, args.repeats // 2)),
    ):
        rows[name] = _median_s(fn, reps)
        print(f"  {name:<28} {rows[name] * 1e3:9.1f} ms", flush=True)
    base = rows["bare FFT pair"]
    ratios = {k: v / base for k, v in rows.items()}
    print(f"  cached / bare   = {ratios['propagate, cached kernels']:.2f}x  (goal <= 1.3x)")
    print(f"  uncached / bare = {ratios['propagate, uncached']:.2f}x")
    share = rows["finite check"] / rows["propagate, cached kernels"]
    print(f"  finite check / cached = {share:.4f}")
    print("  FFT checks (one-time, per layout):")
    for check in fft.checks():
        print(f"    {check.describe()}: {check.seconds * 1e3:.0f} ms, route {check.route} "
              f"(direct error {check.direct_error:.2g})")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "workload": {"size_wh": [w, h], "padded_hw": [hp, wp], "depths": args.depths,
                     "colours": args.colours, "padding": args.padding},
        "seconds": rows, "ratio_to_bare": ratios, "machine": describe(),
        "fft_checks": [dataclasses.asdict(c) for c in fft.checks()],
    }, indent=2))
    print(f"wrote {out}")
    return 0
