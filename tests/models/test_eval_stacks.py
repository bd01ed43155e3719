"""Evaluation propagates each view's target once for the model and both baselines
(`stacks_quality`): each score must be the one `focal_stack_quality` gives that pair alone."""

from __future__ import annotations

import pytest
import torch

from nhfd.models.evaluate import evaluate, stacks_quality
from nhfd.optics import Aperture, KernelCache, focal_stack_quality, quality_planes


def test_one_propagation_of_the_target_scores_every_field_as_alone() -> None:
    g = torch.Generator().manual_seed(11)
    shape = (3, 48, 80)

    def field() -> torch.Tensor:
        return torch.polar(torch.rand(shape, generator=g), 6.3 * torch.rand(shape, generator=g))

    target, model, flat = field(), field(), field()
    mask = torch.zeros(shape[-2:], dtype=torch.bool)
    mask[8:40, 10:70] = True
    kw = dict(planes_m=quality_planes((-1e-3, 1e-3)), pitch_m=8e-6,
              wavelengths_m=(638e-9, 520e-9, 450e-9), aperture=Aperture(), cache=KernelCache())
    got = stacks_quality({"model": model, "hologram_2d": flat}, target, mask, **kw)
    assert set(got) == {"model", "hologram_2d", "black"}
    for name, f in (("model", model), ("hologram_2d", flat), ("black", torch.zeros_like(target))):
        alone = focal_stack_quality(f, target, mask=mask, **kw)
        assert abs(got[name].psnr_db - alone.psnr_db) < 1e-6, name
        assert abs(got[name].ssim - alone.ssim) < 1e-6, name
    assert got["model"].psnr_db > got["black"].psnr_db  # the fields differ: the scores do too


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_evaluation_on_the_gpu_scores_as_on_the_cpu(tiny_run, tiny_data, tmp_path) -> None:
    """`nhfd model build --device cuda` evaluates its focal stacks on the GPU: every view's
    scores and focus bins are the CPU's (float32 FFTs on other kernels: 1e-3 dB)."""
    quiet = dict(splits=("train", "interp", "extrap"), log=lambda _m: None)
    cpu = evaluate(tiny_run, tiny_data, **quiet)
    gpu = evaluate(tiny_run, tiny_data, device="cuda", out_dir=tmp_path, **quiet)
    assert len(gpu["views"]) == len(cpu["views"]) == 6
    for a, b in zip(cpu["views"], gpu["views"], strict=True):
        for key in ("model_psnr_db", "black_psnr_db", "hologram_2d_psnr_db"):
            assert b[key] == pytest.approx(a[key], abs=1e-3), key
        assert b["model_ssim"] == pytest.approx(a["model_ssim"], abs=1e-4)
        assert [f["pass"] for f in b["focus"]] == [f["pass"] for f in a["focus"]]
    assert (tmp_path / "eval.png").exists()
