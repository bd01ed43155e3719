"""Would the bench model that refinement steps through predict the camera better with the two
terms the calibration's own model has and it lacks: the fitted coherent unmodulated light, and
the pixels' flat square shape? On the quality benchmark's calibrated twin (`nhfd bench
quality`'s seed, 512 x 288, its calibration folder reused or made), for the zero pattern, a flat
grey frame and the donut network's frame of its first seeded view: each frame captured at the
content planes, and each model variant's prediction scored against the capture (PSNR, a gain
fitted per colour), with the mean captured and predicted light of the zero pattern against the
flat frame's. With `--crosstalk-um S --sgd-steps N`, also `sgd` from the network's frame through
the shipped model and through a crosstalk of S and the unmodulated light, both captured.

    .venv/bin/python scripts/bench_model_terms.py [--twin TWIN.toml] [--calibration-dir DIR]
        [--crosstalk-um S [--sgd-steps N]]

`--twin`: another twin, a TOML of the simulated bench's fields as `nhfd bench quality --twin`
takes (`randomised_seed = 7` and the fields to change), calibrated into its own folder.

What it measured is in docs/refine.md ("Two terms the bench model leaves out on purpose").
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from nhfd.benchmarks.quality import BENCH_SEED, DONUT, DONUT_MODEL, seeded_views
from nhfd.calib.citl import CameraLoop
from nhfd.calib.sim import arm_twin, sim_devices, sim_panel_hw, twin_calibration
from nhfd.calibration import unmodulated_amplitude
from nhfd.config import load_config, refine_settings
from nhfd.drivers.simcamera import TrueBench
from nhfd.models.export import load_model
from nhfd.optics import Aperture, propagate
from nhfd.optics.pupil import apply_pupil, pupil_scales
from nhfd.optics.quality import stack_quality
from nhfd.pipeline.encoder import Encoder
from nhfd.pipeline.frame import compute_frame
from nhfd.pipeline.refine import BenchForward, Prepared, grey_phase, prepare, sgd_frame
from nhfd.pipeline.view import scene_from_file

WINDOW_HW = (288, 512)
# Each variant: (its name, with the unmodulated light, with the pixels' shape).
VARIANTS = (("as shipped", False, False), ("unmodulated light", True, False),
            ("flat pixels", False, True), ("both", True, True))
# Samples per pixel per axis where the crosstalk is modelled (it blurs the phase within pixels).
CROSSTALK_OVERSAMPLE = 2


class TermsBench(BenchForward):
    """The shipped bench model with the terms it leaves out, each where asked: the unmodulated
    light `unmodulated` added to the panel's field; the pixels' square shape (`pixels`, a sinc
    in the spectrum); a crosstalk `crosstalk_m` (a Gaussian's sigma, metres), which blurs the
    liquid crystal's unwrapped phase (its voltage) across pixel edges, on a grid
    `CROSSTALK_OVERSAMPLE` times finer (flat pixels there by construction), each pixel's
    intensity the mean of its samples. Then the illumination, pupil, aperture and propagation
    as `BenchForward` has them. Differentiable, so `sgd` can step through it."""

    def __init__(self, encoder: Encoder, planes_m: tuple[float, ...],
                 unmodulated: tuple[complex, ...], pixels: bool, crosstalk_m: float) -> None:
        super().__init__(encoder, planes_m)
        self.light, self.pixel_shape, self.crosstalk_m = unmodulated, pixels, crosstalk_m

    def __call__(self, phase: torch.Tensor, cancelled: object = None) -> torch.Tensor:
        s = self.encoder.settings
        n = CROSSTALK_OVERSAMPLE if self.crosstalk_m > 0 else 1
        fine = phase.repeat_interleave(n, dim=-2).repeat_interleave(n, dim=-1)
        if self.crosstalk_m > 0:
            sigma = self.crosstalk_m / (s.pitch_m / n)
            fine = torch.fft.ifft2(torch.fft.fft2(fine) * torch.exp(
                -2 * np.pi**2 * sigma**2 * _frequencies_sq(fine.shape[-2:], fine.device))).real
        scales = pupil_scales(s.zernike_wavelength_m, s.wavelengths_m)
        out = []
        for c, lam in enumerate(s.wavelengths_m):
            u = torch.polar(torch.ones_like(fine[:, c]), fine[:, c])
            if self.light:
                u = u + self.light[c]
            if self.source is not None:
                u = u * self.source[c].repeat_interleave(n, dim=-2).repeat_interleave(n, dim=-1)
            if self.pixel_shape and n == 1:
                h, w = u.shape[-2:]
                fy = torch.fft.fftfreq(2 * h, device=u.device)[:, None]
                fx = torch.fft.fftfreq(2 * w, device=u.device)[None, :]
                u = torch.fft.ifft2(torch.fft.fft2(u, s=(2 * h, 2 * w))
                                    * torch.sinc(fx) * torch.sinc(fy))[..., :h, :w]
            u = apply_pupil(u, self.cutoffs[c] / n, s.zernike_rad, scales[c])
            v = propagate(u[:, None], self.z_m[c], s.pitch_m / n, [lam],
                          aperture=Aperture(s.aperture_shape, (self.cutoffs[c] / n,)),  # type: ignore[arg-type]
                          padding=s.padding)[:, :, 0].abs().square()  # [K, D, nHr, nWr]
            if n > 1:
                k, d, hh, ww = v.shape
                v = F.avg_pool2d(v.reshape(k * d, 1, hh, ww), n).reshape(k, d, hh // n, ww // n)
            out.append(v[..., self.window[0], self.window[1]])
        return torch.stack(out, dim=2)


def _frequencies_sq(hw: tuple[int, int], device: torch.device) -> torch.Tensor:
    """fx^2 + fy^2 on the fftfreq grid of an H x W field (cycles per sample)."""
    fy = torch.fft.fftfreq(hw[0], device=device)[:, None]
    fx = torch.fft.fftfreq(hw[1], device=device)[None, :]
    return fx**2 + fy**2


def predict(p: Prepared, grey: np.ndarray, unmodulated: tuple[complex, ...], pixels: bool,
            crosstalk_m: float = 0.0) -> torch.Tensor:
    """What a bench model predicts of one frame, `[D, C, h, w]`: the shipped one
    (`BenchForward`, the benchmark's own) where no term is asked for, else `TermsBench`."""
    bench = (p.model if not (unmodulated or pixels or crosstalk_m) else
             TermsBench(p.encoder, p.target.planes_m, unmodulated, pixels, crosstalk_m))
    with torch.no_grad():
        return bench(grey_phase(grey[None], p.encoder))[0].float()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--twin", help="a twin's TOML (default: the quality benchmark's seed)")
    parser.add_argument("--calibration-dir", help="where its calibration is made or reused "
                        "(default: bench quality's, or out/bench/terms-<twin file's stem>)")
    parser.add_argument("--crosstalk-um", type=float, default=0.0,
                        help="also model a crosstalk of this sigma (um, 0..4), alone and with "
                             "the unmodulated light: a value you supply, not a fitted one")
    parser.add_argument("--sgd-steps", type=int, default=0,
                        help="with --crosstalk-um: also refine the network frame by sgd for "
                             "this many steps through the shipped model and through the "
                             "crosstalk and unmodulated light, and capture both (1..1000)")
    args = parser.parse_args()
    if not 0 <= args.crosstalk_um <= 4:
        parser.error(f"--crosstalk-um {args.crosstalk_um}: must be in 0..4 um")
    if args.sgd_steps and not (args.crosstalk_um and 1 <= args.sgd_steps <= 1000):
        parser.error(f"--sgd-steps {args.sgd_steps}: must be in 1..1000, with --crosstalk-um")
    variants = [(name, dc, px, 0.0) for name, dc, px in VARIANTS]
    if args.crosstalk_um:
        x = args.crosstalk_um * 1e-6
        variants += [(f"crosstalk {args.crosstalk_um:g} um", False, False, x),
                     (f"crosstalk {args.crosstalk_um:g} um + unmodulated light", True, False, x)]
    config = load_config(None).config
    panel_hw = sim_panel_hw(WINDOW_HW)
    if args.twin:
        twin = TrueBench.from_toml(args.twin)
        default_dir = f"out/bench/terms-{Path(args.twin).stem}"
    else:
        twin = TrueBench.randomised(BENCH_SEED)
        default_dir = f"out/bench/quality-calibration-{WINDOW_HW[1]}x{WINDOW_HW[0]}"
    cal_dir = Path(args.calibration_dir or default_dir)
    cal = twin_calibration(cal_dir, twin, panel_hw)
    dc = tuple(unmodulated_amplitude(f, ph) for f, ph in
               zip(cal.unmodulated_fraction, cal.unmodulated_phase_rad, strict=True))
    print(f"the calibration's unmodulated light: {[f'{a:.3f}' for a in dc]} (relative amplitude)")
    model = load_model(DONUT_MODEL, config)
    scene = scene_from_file(DONUT)
    view = seeded_views(np.random.default_rng(0), 1, scene, model.info, WINDOW_HW)[0]
    with sim_devices(twin, panel_hw) as devices:
        arm_twin(devices)
        p = prepare(config, view, scene, info=model.info, calibration=cal, window_hw=WINDOW_HW,
                    panel_hw=panel_hw, planes=config.refine.planes)
        loop = CameraLoop(devices, cal, p.encoder)
        r = p.encoder.region
        network = np.asarray(compute_frame(view, scene, model, p.encoder).grey)
        frames = {"zero pattern": p.encoder.zero[:, r.top : r.top + r.height,
                                                 r.left : r.left + r.width].copy(),
                  "flat grey 128": np.full_like(network, 128), "network frame": network}
        light = {}
        for name, grey in frames.items():
            captured, seen = loop(grey[None], p.target.planes_m)
            cap = torch.as_tensor(captured).float()
            mask = p.target.mask & torch.as_tensor(seen)
            scores = []
            for variant, with_dc, pixels, crosstalk_m in variants:
                pred = predict(p, grey, dc if with_dc else (), pixels, crosstalk_m)
                q = stack_quality(cap, pred, planes_m=p.target.planes_m, mask=mask,
                                  fit_gains=True)
                scores.append(f"{variant} {q.psnr_db:.2f} dB")
                light[name, variant] = float(pred[:, :, mask].mean())
            light[name, "captured"] = float(cap[:, :, mask].mean())
            print(f"{name}: the capture predicted by " + ", ".join(scores), flush=True)
        if args.sgd_steps:
            settings = refine_settings(config.refine, {"iterations": args.sgd_steps,
                                                       "tolerance": 0.0})
            models = {"the shipped model": p.model,
                      f"crosstalk {args.crosstalk_um:g} um + unmodulated light":
                          TermsBench(p.encoder, p.target.planes_m, dc, False,
                                     args.crosstalk_um * 1e-6)}
            for label, bench in models.items():
                refined = sgd_frame(replace(p, model=bench), settings, start=network)
                grey = np.asarray(refined.grey)
                captured, seen = loop(grey[None] if grey.ndim == 3 else grey, p.target.planes_m)
                q = stack_quality(torch.as_tensor(captured).float(), p.target.intensity,
                                  planes_m=p.target.planes_m,
                                  mask=p.target.mask & torch.as_tensor(seen), fit_gains=True)
                print(f"sgd, {args.sgd_steps} steps through {label}: captured {q.psnr_db:.2f} "
                      f"dB, SSIM {q.ssim:.3f} (its model's {refined.report.psnr_db:.2f} dB)",
                      flush=True)
    for variant in ("captured", *(v[0] for v in variants)):
        ratio = light["zero pattern", variant] / light["flat grey 128", variant]
        print(f"zero pattern's light / the flat frame's, {variant}: {ratio:.2g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
