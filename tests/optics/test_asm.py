"""Angular spectrum propagation: facts of physics and of the numerical contract."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nhfd.optics import Aperture, KernelCache, propagate, transfer_function
from nhfd.optics.aperture import aperture_mask

from .fields import band_limited, envelope, gaussian_beam

P = 8e-6
RGB = (660e-9, 520e-9, 450e-9)
G = 520e-9


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


def test_zero_distance_is_identity():
    u = torch.randn(3, 40, 56, dtype=torch.complex64)
    assert rel(propagate(u, 0.0, P, RGB), u) < 1e-6


def test_forward_then_backward_returns_band_limited_field():
    u = band_limited((3, 128, 128), 0.2)
    for z in (1e-3, 2e-2):
        there = propagate(u, z, P, RGB, padding="none")
        assert rel(propagate(there, -z, P, RGB, padding="none"), u) < 1e-10
        # Parseval: propagation only changes phases within the band.
        assert abs(float(there.abs().square().sum() / u.abs().square().sum()) - 1) < 1e-10


def test_tilted_plane_wave_moves_by_z_tan_theta():
    n, tilt = 512, 0.1  # cycles per pixel along x
    u = gaussian_beam(n, 20.0, P, tilt)
    z = 0.05
    out = propagate(u, z, P, G)
    i = out.abs().square()[0]
    x = torch.arange(n, dtype=torch.float64) - n / 2
    centroid_px = float((i.sum(0) * x).sum() / i.sum())
    sin_t = G * tilt / P
    expected_px = z * sin_t / math.sqrt(1 - sin_t**2) / P
    assert expected_px > 40
    assert abs(centroid_px - expected_px) < 0.02


def test_gaussian_beam_width_follows_analytic_w_of_z():
    n, w0_px = 256, 10.0
    w0 = w0_px * P
    z_r = math.pi * w0**2 / G
    x = (torch.arange(n, dtype=torch.float64) - n / 2) * P
    for z in (0.5 * z_r, z_r, 1.5 * z_r):
        i = propagate(gaussian_beam(n, w0_px, P), z, P, G).abs().square()[0]
        # For I ~ exp(-2 x^2 / w^2), the second moment along x is w^2 / 4.
        w = 2 * math.sqrt(float((i.sum(0) * x**2).sum() / i.sum()))
        w_expected = w0 * math.sqrt(1 + (z / z_r) ** 2)
        assert abs(w / w_expected - 1) < 0.01


def rayleigh_sommerfeld(u0: torch.Tensor, z: float, lam: float, pts: list[tuple[int, int]]):
    """Direct first Rayleigh-Sommerfeld sum in float64, carrier exp(ikz) removed."""
    n = u0.shape[-1]
    c = (torch.arange(n, dtype=torch.float64) - n / 2) * P
    ys, xs = torch.meshgrid(c, c, indexing="ij")
    k = 2 * math.pi / lam
    out = []
    for r_, c_ in pts:
        r = torch.sqrt((c[c_] - xs) ** 2 + (c[r_] - ys) ** 2 + z**2)
        h = z / (2 * math.pi) * (1 / r - 1j * k) * torch.exp(1j * k * (r - z)) / r**2
        out.append(complex((u0 * h).sum() * P * P))
    return torch.tensor(out)


@pytest.mark.parametrize("z", [5e-3, 20e-3, 100e-3])
def test_matches_direct_rayleigh_sommerfeld_sum(z):
    n, sigma_px = 128, 4.0
    c = torch.arange(n, dtype=torch.float64) - n / 2
    u0 = torch.exp(-(c[:, None] ** 2 + c[None, :] ** 2) / (2 * sigma_px**2)).to(torch.complex128)
    asm = propagate(u0[None], z, P, G, padding=(4 * n, 4 * n), band_limit=True)[0]
    gen = torch.Generator().manual_seed(3)
    pts = [
        (int(a), int(b)) for a, b in torch.randint(n // 2 - 12, n // 2 + 12, (12, 2), generator=gen)
    ]
    rs = rayleigh_sommerfeld(u0, z, G, pts)
    got = torch.stack([asm[r, c_] for r, c_ in pts])
    assert rel(got, rs) < 1e-6


def float32_kernel_with_carrier(shape, z, lam):
    """The naive kernel: exp(i 2 pi z sqrt(1/lambda^2 - f^2)) with its phase in float32."""
    fy = torch.fft.fftfreq(shape[0], d=P, dtype=torch.float32)[:, None]
    fx = torch.fft.fftfreq(shape[1], d=P, dtype=torch.float32)[None, :]
    arg = torch.clamp(torch.tensor(1 / lam**2, dtype=torch.float32) - fx**2 - fy**2, min=0)
    phase = torch.tensor(2 * math.pi * z, dtype=torch.float32) * torch.sqrt(arg)
    return torch.polar(torch.ones_like(phase), phase)


def test_precision_against_float64():
    u64 = torch.randn(1, 512, 512, dtype=torch.complex128)
    u32 = u64.to(torch.complex64)
    cache = KernelCache()
    for z in (0.0, 1e-6, 1e-3, 1e-2, 0.1, 1.0):
        ref = propagate(u64, z, P, G, padding="2x")
        assert rel(propagate(u32, z, P, G, padding="2x", cache=cache), ref) <= 1e-6
        z_t = torch.tensor(z, dtype=torch.float32, requires_grad=True)
        assert rel(propagate(u32, z_t, P, G, padding="2x").detach(), ref) <= 1e-4
    # The same bound fails for a float32 kernel that keeps the carrier, at 10 cm.
    z, shape = 0.1, (1024, 1024)
    k32 = float32_kernel_with_carrier(shape, z, G)
    naive = torch.fft.ifft2(torch.fft.fft2(u32, s=shape) * k32)[..., :512, :512]
    naive = naive * math.e ** complex(0, -2 * math.pi * (z / G % 1))  # drop the carrier exactly
    ref = propagate(u64, z, P, G, padding="2x", band_limit=False)
    assert rel(naive.to(torch.complex128), ref) > 1e-4


def test_differentiable_in_field_and_depth():
    u = band_limited((1, 32, 32), 0.2, dtype=torch.complex64).requires_grad_()
    z = torch.tensor([2e-3, 3e-3], requires_grad=True)
    out = propagate(u, z, P, G)
    assert out.shape == (2, 1, 32, 32)
    out.abs().square().sum().backward()
    assert u.grad is not None and torch.isfinite(u.grad).all()
    assert z.grad is not None and torch.isfinite(z.grad).all()
    # Gradient in z agrees with a finite difference of the cached path.
    zf = torch.tensor(2e-3, dtype=torch.float64, requires_grad=True)
    u64 = u.detach().to(torch.complex128)
    target = torch.roll(u64, 3, -1)
    loss = (propagate(u64, zf, P, G) - target).abs().square().sum()
    (g,) = torch.autograd.grad(loss, zf)
    h = 1e-7

    def f(z_):
        return float((propagate(u64, z_, P, G) - target).abs().square().sum())

    assert abs(float(g) - (f(2e-3 + h) - f(2e-3 - h)) / (2 * h)) < 1e-4 * abs(float(g)) + 1e-6


def test_batched_colours_and_depths_match_single_calls():
    u = band_limited((2, 3, 48, 40), 0.2, dtype=torch.complex64)
    zs = [-2e-3, 1e-3, 4e-3]
    pad = (96, 80)  # the same grid for both: "auto" sizes for the largest depth in the call
    many = propagate(u, zs, P, RGB, padding=pad)
    assert many.shape == (2, 3, 3, 48, 40)
    for d, z in enumerate(zs):
        for c, lam in enumerate(RGB):
            one = propagate(u[:, c : c + 1], z, P, lam, padding=pad)
            assert rel(many[:, d, c : c + 1], one) < 1e-6


def test_auto_padding_matches_a_large_padding_where_none_fails():
    h = w = 256
    u = band_limited((3, h, w), 0.18) * envelope(h, w)
    ap = Aperture()
    z = 0.05  # reach ~131 px at 660 nm, beyond the content's ~70 px margin
    ref = propagate(u, z, P, RGB, padding=(2048, 2048), aperture=ap)
    auto = propagate(u.to(torch.complex64), z, P, RGB, padding="auto", aperture=ap)
    none = propagate(u.to(torch.complex64), z, P, RGB, padding="none", aperture=ap)
    assert rel(auto, ref) < 1e-5
    assert rel(none, ref) > 1e-2


def test_cache_reuses_and_is_bounded():
    u = torch.randn(3, 64, 64, dtype=torch.complex64)
    cache = KernelCache(max_bytes=3 * 64 * 64 * 8 * 4)  # room for a few kernels
    a = propagate(u, 1e-3, P, RGB, padding="none", cache=cache)
    b = propagate(u, 1e-3, P, RGB, padding="none", cache=cache)
    assert cache.hits == 1 and cache.misses == 1 and torch.equal(a, b)
    propagate(u, 1e-3, P, (661e-9, 520e-9, 450e-9), padding="none", cache=cache)
    assert cache.misses == 2  # another wavelength is another kernel
    for z in (2e-3, 3e-3, 4e-3, 5e-3):
        propagate(u, z, P, RGB, padding="none", cache=cache)
    assert cache.nbytes <= cache.max_bytes and len(cache) <= 4


# ---- extremes: never NaN or Inf, invalid physics named


@pytest.mark.parametrize(
    "field",
    [
        torch.zeros(3, 33, 47, dtype=torch.complex64),
        torch.ones(3, 33, 47, dtype=torch.complex64),
        torch.polar(torch.ones(3, 33, 47), torch.full((3, 33, 47), math.pi)),
        torch.polar(torch.ones(3, 33, 47), torch.full((3, 33, 47), -math.pi)),
    ],
)
def test_extreme_fields_stay_finite_and_conserve_energy(field):
    out = propagate(field, 3e-3, P, RGB, padding="none")
    assert torch.isfinite(torch.view_as_real(out)).all()
    assert out.shape == field.shape
    e_in, e_out = field.abs().square().sum(), out.abs().square().sum()
    assert abs(float(e_out - e_in)) <= 1e-5 * float(e_in) + 1e-6


def test_single_bright_pixel_on_odd_grid():
    u = torch.zeros(1, 31, 17, dtype=torch.complex64)
    u[0, 15, 8] = 1.0
    out = propagate(u, 1e-3, P, G, padding="none", band_limit=False)
    assert torch.isfinite(torch.view_as_real(out)).all()
    assert abs(float(out.abs().square().sum()) - 1) < 1e-5


def test_wavelength_beyond_twice_the_pitch_zeroes_evanescent_frequencies():
    pitch = 0.2e-6  # lambda / (2 p) = 1.3: the grid's outer frequencies are evanescent
    u = torch.randn(1, 64, 64, dtype=torch.complex128)
    out = propagate(u, 1e-6, pitch, G, padding="none", band_limit=False)
    assert torch.isfinite(torch.view_as_real(out)).all()
    spec = torch.fft.fft2(out)[0]
    f = torch.fft.fftfreq(64, d=pitch, dtype=torch.float64)
    evanescent = (f[:, None] ** 2 + f[None, :] ** 2) * G**2 >= 1
    assert evanescent.any()
    assert spec[evanescent].abs().max() < 1e-12 * spec.abs().max()


def test_long_distance_warns_that_band_limit_keeps_only_low_frequencies():
    u = torch.randn(1, 64, 64, dtype=torch.complex64)
    with pytest.warns(UserWarning, match="band limit keeps only"):
        out = propagate(u, 5.0, P, G, padding="none")
    assert torch.isfinite(torch.view_as_real(out)).all()


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"pitch_m": 0.0}, "pitch_m"),
        ({"pitch_m": -8e-6}, "pitch_m"),
        ({"pitch_m": float("nan")}, "pitch_m"),
        ({"wavelengths_m": (660e-9, 0.0, 450e-9)}, r"wavelengths_m\[1\]"),
        ({"wavelengths_m": (660e-9, float("inf"), 450e-9)}, r"wavelengths_m\[1\]"),
        ({"wavelengths_m": (660e-9, 520e-9)}, "2 values for 3 colour channels"),
        ({"z_m": float("nan")}, "z_m"),
        ({"padding": "3x"}, "padding"),
    ],
)
def test_invalid_physics_raises_value_error_naming_it(kwargs, name):
    args = {"field": torch.ones(3, 8, 8), "z_m": 1e-3, "pitch_m": P, "wavelengths_m": RGB}
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        propagate(**args)


def test_a_non_finite_sample_is_refused_with_the_count_and_the_first_index():
    """One NaN would otherwise turn its whole colour channel into NaN through the FFT."""
    u = torch.randn(2, 3, 8, 8, dtype=torch.complex128)
    u[1, 2, 0, 0] = complex(float("inf"), 0.0)
    u[0, 1, 2, 5] = complex(0.0, float("nan"))
    u[1, 0, 7, 7] = complex(float("nan"), 1.0)
    expected = (r"field has 3 non-finite value\(s\) \(NaN or Inf\), "
                r"the first at index \(0, 1, 2, 5\)")
    with pytest.raises(ValueError, match=expected):
        propagate(u, 1e-3, P, RGB)
    real = torch.ones(3, 8, 8)
    real[2, 4, 1] = float("-inf")
    with pytest.raises(ValueError, match=r"1 non-finite value\(s\).*\(2, 4, 1\)"):
        propagate(real, 1e-3, P, RGB)
    # Finite fields whose float32 sum overflows are still accepted.
    huge = torch.full((1, 4, 4), 3e38, dtype=torch.complex64)
    assert propagate(huge, 0.0, P, G, padding="none").shape == (1, 4, 4)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"wavelengths_m": (660e-9, 520.0, 450e-9)},
         r"wavelengths_m\[1\] = 520.0: outside 1e-07..1e-05 m; did you pass nanometres\?"),
        ({"wavelengths_m": 0.52}, r"wavelengths_m\[0\] = 0.52: .*did you pass micrometres\?"),
        ({"wavelengths_m": 0.05}, r"wavelengths_m\[0\] = 0.05: outside 1e-07..1e-05 m$"),
        ({"pitch_m": 8.0}, r"pitch_m = 8.0: outside 1e-07..0.001 m; did you pass micrometres\?"),
        ({"pitch_m": 0.008}, r"pitch_m = 0.008: .*did you pass millimetres\?"),
        ({"pitch_m": 8e-9}, r"pitch_m = 8e-09: outside 1e-07..0.001 m$"),
        ({"z_m": 1e300}, r"z_m = 1e\+300: outside -10..10 m"),
        ({"z_m": [1e-3, -20.0]}, r"z_m\[1\] = -20.0: outside -10..10 m"),
        ({"z_m": torch.tensor([1e-3, 1e300], dtype=torch.float64)}, r"z_m\[1\] = 1e\+300"),
        ({"z_m": np.zeros((2, 2))}, r"z_m has shape \(2, 2\): give a scalar or a 1-D"),
    ],
)
def test_implausible_units_and_distances_are_refused_with_the_range(kwargs, message):
    args = {"field": torch.ones(3, 8, 8), "z_m": 1e-3, "pitch_m": P, "wavelengths_m": RGB}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        propagate(**args)


def test_transfer_function_refuses_absurd_depths_and_unit_slips():
    with pytest.raises(ValueError, match=r"z_m\[1\] = 1e\+300: outside -10..10 m"):
        transfer_function((8, 8), P, RGB, [1e-3, 1e300])
    with pytest.raises(ValueError, match=r"wavelengths_m\[0\] = 660.0: .*nanometres"):
        transfer_function((8, 8), P, [660.0], [1e-3])


def test_numpy_scalars_and_0d_arrays_are_depths_like_floats():
    u = band_limited((3, 16, 16), 0.2, dtype=torch.complex64)
    plain = propagate(u, 2e-3, P, RGB)
    for z in (np.array(2e-3), np.float64(2e-3), torch.tensor(2e-3, dtype=torch.float64)):
        assert torch.equal(propagate(u, z, P, RGB), plain)
    assert propagate(u, np.float32(2e-3), P, RGB).shape == (3, 16, 16)
    both = propagate(u, np.array([2e-3, -1e-3]), P, RGB)
    assert both.shape == (2, 3, 16, 16) and torch.equal(both[0], plain)


def test_empty_field_is_rejected_with_its_shape():
    with pytest.raises(ValueError, match=r"shape \(3, 0, 8\)"):
        propagate(torch.ones(3, 0, 8), 1e-3, P, RGB)


def test_float16_input_is_upcast_and_matches_float32():
    u = band_limited((3, 32, 32), 0.2, dtype=torch.complex64)
    amp = u.abs().to(torch.float16)
    out16 = propagate(amp, 2e-3, P, RGB)
    out32 = propagate(amp.float(), 2e-3, P, RGB)
    assert out16.dtype == torch.complex64 and torch.equal(out16, out32)


def test_aperture_is_applied_with_propagation():
    u = torch.randn(3, 64, 64, dtype=torch.complex64)
    out = propagate(u, 0.0, P, RGB, padding="none", aperture=Aperture())
    spec = torch.fft.fft2(out)
    blocked = ~aperture_mask((64, 64), Aperture(), 3)
    assert float(spec[blocked].abs().max()) < 1e-4 * float(spec.abs().max())
    # square cutoff 1/4 with the half-open convention: k = -16..15 of 64 pass
    assert aperture_mask((64, 64), Aperture("square", (0.25,)), 1)[
        0, 0
    ].nonzero().flatten().tolist() == (list(range(16)) + list(range(48, 64)))


def test_cache_reuses_each_depth_across_different_plane_sets():
    """A caller whose planes change between calls (the training loss) still hits the cache for
    every plane it has used before, and cached results equal uncached ones."""
    field = torch.randn(3, 48, 40, dtype=torch.complex64)
    lams = (660e-9, 520e-9, 450e-9)
    cache = KernelCache(max_bytes=2**28)
    first = propagate(field, [1e-3, -2e-3], 8e-6, lams, padding=(64, 64), cache=cache)
    assert (cache.hits, cache.misses) == (0, 2)
    second = propagate(field, [-2e-3, 3e-3, 1e-3], 8e-6, lams, padding=(64, 64), cache=cache)
    assert (cache.hits, cache.misses) == (2, 3)
    plain = propagate(field, [-2e-3, 3e-3, 1e-3], 8e-6, lams, padding=(64, 64))
    assert torch.equal(second, plain)
    assert torch.equal(second[0], first[1]) and torch.equal(second[2], first[0])
