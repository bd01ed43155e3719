"""`nhfd bench optics`: propagation cost against the bare FFT pair measured in the same run.

The workload of the issue: a 3 x 1080 x 1920 complex64 field with 2x padding propagated to 8
depths. "Bare FFT pair" is the FFT work such a call cannot avoid (one forward transform of the
padded field and one inverse per depth); cached propagation should stay within 1.3x of it.
"finite check" is the refusal of NaN and Inf every field passes through on the way in
(`nhfd.optics._validate.finite_field`), on the unpadded field. "FFT checks" lists each FFT
layout's one-time known-answer check (`nhfd.optics.fft`), paid by the first call (the warm-up).

`--accuracy` measures instead how far each padding policy lands from a 4x-padded propagation
(relative L2, complex128 so only the padding differs) for the configured window, aperture,
wavelengths and depths (-z0 to the SLM, the volume's ends), on three seeded fields: noise filtered
by the aperture over the whole window (as every target and prediction fills the band), the same
under a smooth envelope (nothing near the window's edges), and content well inside both the band
(0.18 cycle/px) and the window. The last row, green only, is 4x's own distance from 8x.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

from nhfd.benchmarks.machine import describe
from nhfd.cli.args import parse_wxh
from nhfd.config import load_config
from nhfd.optics import Aperture, KernelCache, apply_aperture, fft, plan_padding, propagate
from nhfd.optics._validate import finite_field


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("optics", help="angular-spectrum propagation vs the bare FFT pair",
                       description=__doc__)
    p.add_argument("--size", default=None,
                   help="field WxH (default 1920x1080; with --accuracy the configured window)")
    p.add_argument("--depths", type=int, default=8, help="planes per call (default 8)")
    p.add_argument("--colours", type=int, default=3, choices=(1, 2, 3),
                   help="colour channels, R first (default 3)")
    p.add_argument("--padding", default="2x", choices=("none", "2x", "auto"))
    p.add_argument("--repeats", type=int, default=3, help="timed repeats; the median is kept")
    p.add_argument("--accuracy", action="store_true",
                   help="padding policies against 4x padding instead of timings")
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
    if args.accuracy:
        return padding_accuracy(args)
    import torch

    w, h = parse_wxh(args.size or "1920x1080", "--size")
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


def _accuracy_fields(h: int, w: int, aperture, colours: int) -> dict[str, object]:
    """The seeded test fields of `--accuracy`, complex128 `[C, h, w]`."""
    import torch

    gen = torch.Generator().manual_seed(17)
    noise = torch.randn(colours, h, w, dtype=torch.complex128, generator=gen)
    y = torch.linspace(-1, 1, h, dtype=torch.float64)[:, None]
    x = torch.linspace(-1, 1, w, dtype=torch.float64)[None, :]
    envelope = torch.exp(-(((y**2 + x**2) / 0.45**2) ** 3))
    band = apply_aperture(noise, aperture)
    inside = apply_aperture(noise, Aperture("square", (0.18,))) * envelope
    return {"fills the band": band, "fills the band, envelope": band * envelope,
            "0.18 cycle/px, envelope": inside}


def padding_accuracy(args: argparse.Namespace) -> int:
    cfg = load_config().config
    o = cfg.optics
    w, h = (parse_wxh(args.size, "--size") if args.size
            else (o.hologram_width_px, o.hologram_height_px))  # fmt: skip
    n = args.colours
    lams = o.wavelengths_m[:n]
    ap = Aperture(o.aperture.shape, tuple(o.aperture.cutoff_per_px[:n]))
    pitch = cfg.slm.pitch_m
    zs = (-o.z0_m, *o.volume_m)
    fields = _accuracy_fields(h, w, ap, n)
    print(f"padding accuracy: {w} x {h} window, {n} colours, {ap}; relative L2 against 4x "
          f"(complex128); {describe()}")  # fmt: skip
    rows = []
    for z in zs:
        plan = plan_padding((h, w), pitch, lams, abs(z), ap, "auto")
        for name, u in fields.items():
            ref = propagate(u, z, pitch, lams, padding=(4 * h, 4 * w), aperture=ap)
            row = {"z_m": z, "field": name, "auto_hw": list(plan.padded_hw)}
            for pad in ("auto", "2x", "none"):
                out = propagate(u, z, pitch, lams, padding=pad, aperture=ap)
                row[pad] = float((out - ref).norm() / ref.norm())
            rows.append(row)
            print(f"  z = {z * 1e3:+5.1f} mm  {name:<26} auto {plan.padded_hw}: "
                  f"{row['auto']:.2e}  2x: {row['2x']:.2e}  none: {row['none']:.2e}", flush=True)
    green = min(1, n - 1)
    u = fields["fills the band"][green : green + 1]
    one = Aperture(ap.shape, (ap.cutoffs(n)[green],))
    four, eight = (propagate(u, zs[0], pitch, lams[green], padding=(k * h, k * w), aperture=one)
                   for k in (4, 8))  # fmt: skip
    own = float((four - eight).norm() / eight.norm())
    print(f"  4x against 8x (fills the band, z = {zs[0] * 1e3:+.1f} mm, "
          f"{lams[green] * 1e9:.0f} nm): {own:.2e}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"window_wh": [w, h], "rows": rows, "four_vs_eight": own,
                               "machine": describe()}, indent=2))  # fmt: skip
    print(f"wrote {out}")
    return 0
