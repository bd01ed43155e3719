"""Scene-level depth mapping and per-colour angular sampling."""

from __future__ import annotations

import numpy as np
import pytest

from nhfd.holo import (
    colour_sampling,
    depth_exaggeration,
    inside_aperture,
    sampling_report,
    scene_depth_range,
    scene_mapping,
)
from nhfd.optics import Aperture

LAMS = (660e-9, 520e-9, 450e-9)
P = 8e-6


def test_depth_range_is_pooled_percentile_of_opaque_pixels() -> None:
    rng = np.random.default_rng(0)
    depths = [rng.uniform(1.0, 3.0, (20, 30)).astype(np.float32) for _ in range(5)]
    alphas = [rng.uniform(0, 1, (20, 30)).astype(np.float32) for _ in range(5)]
    # Haze (alpha <= 0.5) far away and very near must not move the range.
    for d, a in zip(depths, alphas, strict=True):
        d[a <= 0.5] = rng.choice([0.01, 100.0], size=int((a <= 0.5).sum()))
    got = scene_depth_range(iter(depths), iter(alphas), percentiles=(5, 95))
    pooled = np.concatenate([d[a > 0.5] for d, a in zip(depths, alphas, strict=True)])
    assert got["n_maps"] == 5 and got["n_pixels"] == pooled.size
    assert got["d_near"] == pytest.approx(np.percentile(pooled, 5), rel=2e-3)
    assert got["d_far"] == pytest.approx(np.percentile(pooled, 95), rel=2e-3)
    assert 1.0 <= got["d_min"] and got["d_max"] <= 3.0


def test_depth_range_subsampling_stays_close() -> None:
    rng = np.random.default_rng(1)
    depths = [rng.lognormal(0.5, 0.3, (200, 300)) for _ in range(3)]
    alphas = [np.ones((200, 300)) for _ in range(3)]
    full = scene_depth_range(depths, alphas)
    sub = scene_depth_range(depths, alphas, samples_per_map=500)
    assert sub["n_pixels"] == full["n_pixels"] == 3 * 200 * 300
    assert sub["d_near"] == pytest.approx(full["d_near"], rel=1e-2)
    assert sub["d_far"] == pytest.approx(full["d_far"], rel=1e-2)


def test_depth_range_errors_and_flat_scene() -> None:
    empty = [np.zeros((4, 4))]
    with pytest.raises(ValueError, match="alpha"):
        scene_depth_range(empty, empty)
    with pytest.raises(ValueError, match="percentiles"):
        scene_depth_range([np.ones((2, 2))], [np.ones((2, 2))], percentiles=(50, 50))
    flat = scene_depth_range([np.full((4, 4), 2.0)], [np.ones((4, 4))])
    assert flat["d_near"] < 2.0 < flat["d_far"]


def test_mapping_puts_near_at_z_max_and_reports_exaggeration() -> None:
    measured = {"d_near": 1.5, "d_far": 4.0}
    mapping, rep = scene_mapping(-3e-3, 3e-3, P, 900.0, depth_range=measured)
    assert float(mapping.z_h(1.5)) == pytest.approx(3e-3)
    assert float(mapping.z_h(4.0)) == pytest.approx(-3e-3)
    assert rep["source"] == {"d_near": "measured", "d_far": "measured"}
    assert rep["depth_exaggeration"] == pytest.approx(mapping.b_m / (P * 900.0) ** 2)
    assert rep["depth_exaggeration"] == depth_exaggeration(mapping, P, 900.0)
    # Physical check of the factor: the mapping's dz/dd over the physical (p fx / d)^2.
    d = 2.0
    slope = (float(mapping.z_h(d - 1e-6)) - float(mapping.z_h(d + 1e-6))) / 2e-6
    assert slope / (P * 900.0 / d) ** 2 == pytest.approx(rep["depth_exaggeration"], rel=1e-4)
    # Overrides win over the measurement, and are reported as such.
    m2, rep2 = scene_mapping(-2e-3, 2e-3, P, 900.0, depth_range=measured, d_far=3.0)
    assert rep2["d_far"] == 3.0 and rep2["source"]["d_far"] == "override"
    assert float(m2.z_h(3.0)) == pytest.approx(-2e-3)
    with pytest.raises(ValueError, match="d_near"):
        scene_mapping(-2e-3, 2e-3, P, 900.0, d_near=1.0)


def test_window_per_colour_from_volume_and_aperture() -> None:
    s = colour_sampling(LAMS, P, (-3e-3, 3e-3))
    assert [c.window for c in s] == [16, 14, 12]  # docs/physics.md's +-3 mm example
    assert [len(c.k) for c in s] == [8, 7, 6]
    assert all(c.window_source == "derived" for c in s)
    for c in s:  # half-open aperture: -f_cut <= k / W < f_cut
        assert np.all(c.k / c.window >= -0.25) and np.all(c.k / c.window < 0.25)
        np.testing.assert_allclose(np.sin(np.arctan(c.tau)), c.wavelength_m * c.k / (c.window * P))
    over = colour_sampling(LAMS, P, (-3e-3, 3e-3), windows=[20, None, 12])
    assert [c.window for c in over] == [20, 14, 12]
    assert [c.window_source for c in over] == ["override", "derived", "override"]
    rep = sampling_report(s)
    assert rep[0]["n_views"] == 64 and rep[0]["window"] == 16
    assert rep[0]["max_angle_deg"] == pytest.approx(np.degrees(np.arctan(abs(s[0].tau[0]))))


def test_shared_directions_coincide() -> None:
    s = colour_sampling(LAMS, P, (-3e-3, 3e-3), shared=True)
    assert all(c.window_source == "shared" for c in s)
    own = colour_sampling(LAMS, P, (-3e-3, 3e-3))
    for c, o in zip(s, own, strict=True):
        assert c.window >= o.window
    # The same bin k has nearly the same slope in every colour.
    for c in s[1:]:
        common = np.isin(s[0].k, c.k)
        np.testing.assert_allclose(c.tau, s[0].tau[common], rtol=0.03)


def test_inside_aperture_shapes() -> None:
    s = colour_sampling(LAMS, P, (-3e-3, 3e-3))[0]
    assert inside_aperture(s, Aperture(), 0).all()
    diamond = inside_aperture(s, Aperture("diamond"), 0)
    assert diamond.sum() < diamond.size and diamond[4, 4]
