"""nhfd.spec: the torch-free quantisation agrees with nhfd.optics' torch one."""

from __future__ import annotations

import numpy as np
import torch

from nhfd.optics import phase_to_grey
from nhfd.spec import PhaseCurve, nearest_level, zero_grey, zero_pattern

CURVES = (PhaseCurve.linear(), PhaseCurve.linear(1.8 * np.pi),
          PhaseCurve(tuple(float(v) for v in 2.3 * np.pi * (np.arange(256) / 255) ** 1.2)))


def test_nearest_level_is_phase_to_greys_rule():
    phases = np.random.default_rng(7).uniform(-10.0, 10.0, 400)
    for curve in CURVES:
        want = phase_to_grey(torch.from_numpy(phases).reshape(1, 1, -1), [curve])
        assert [nearest_level(p, curve) for p in phases] == want.flatten().tolist()


def test_zero_grey_nominal_sign_and_inversion():
    nominal = [PhaseCurve.linear()]
    assert zero_grey(nominal, 1, False).tolist() == [[64, 192]]
    assert zero_grey(nominal, -1, False).tolist() == [[192, 64]]
    assert zero_grey(nominal, 1, True).tolist() == [[191, 63]]
    pattern = zero_pattern((3, 4), CURVES, -1, False)
    pair = zero_grey(CURVES, -1, False)
    assert pattern.shape == (3, 3, 4) and pattern.dtype == np.uint8
    assert pattern[:, 0, 0].tolist() == pair[:, 0].tolist()
    assert pattern[:, 1, 2].tolist() == pair[:, 1].tolist()
    assert pattern[:, 2, 1].tolist() == pair[:, 1].tolist()
