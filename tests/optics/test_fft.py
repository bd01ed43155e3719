"""The FFT guard (`nhfd.optics.fft`): each layout is checked once against a known answer and a
failing backend is routed around, with one warning."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from nhfd.optics import fft, propagate, transfer_function

from .fields import band_limited, envelope

P, G = 8e-6, 520e-9


@pytest.fixture(autouse=True)
def fresh_checks():
    fft.clear_checks()
    yield
    fft.clear_checks()


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def backend_warnings(record: list[warnings.WarningMessage]) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, fft.FFTBackendWarning)]


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def test_one_colour_1024_window_with_2x_padding_conserves_energy_on_two_threads(two_threads):
    """torch 2.13.0's complex64 ifft2 of one 2048 x 2048 plane on two threads divides by N
    twice: this propagation returned 1e-13 of its energy."""
    n, z = 1024, 2e-3
    u = (band_limited((1, n, n), 0.2) * envelope(n, n)).to(torch.complex64)
    spectrum = torch.fft.fft2(u, s=(2 * n, 2 * n))
    raw = torch.fft.ifft2(spectrum)[..., :n, :n]
    backend_broken = rel(raw.numpy(), u.numpy()) > 1e-3
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        out = propagate(u, z, P, G, padding="2x")
        again = propagate(u, z, P, G, padding="2x")
    energy = float(out.abs().square().sum() / u.abs().square().sum())
    assert abs(energy - 1) < 1e-5
    kernel = transfer_function((2 * n, 2 * n), P, [G], [z], dtype=torch.complex128)[0, 0]
    ref = np.fft.ifft2(np.fft.fft2(u.numpy().astype(np.complex128), s=(2 * n, 2 * n))
                       * kernel.numpy())[..., :n, :n]  # fmt: skip
    assert rel(out.numpy(), ref) < 1e-5
    assert torch.equal(out, again)
    messages = backend_warnings(record)
    assert len(messages) == (1 if backend_broken else 0)
    if backend_broken:
        assert torch.__version__ in messages[0] and "shape (1, 2048, 2048)" in messages[0]
        assert "2 threads" in messages[0]


def _double_scaled_inverse(real_ifftn, shape):
    """An ifftn that, like torch 2.13.0's, scales by 1/N twice for `shape` (default norm)."""

    def ifftn(x, s=None, dim=None, norm=None, *, out=None):
        y = real_ifftn(x, s=s, dim=dim, norm=norm, out=out)
        if tuple(x.shape) == shape and norm in (None, "backward"):
            y.mul_(1.0 / (shape[-1] * shape[-2]))
        return y

    return ifftn


def _garbage_for_single_planes(real, shape):
    """A transform that returns noise whenever one plane of `shape`'s last two axes comes alone
    (any norm, any direction it replaces)."""

    def broken(x, *args, **kwargs):
        y = real(x, *args, **kwargs)
        if tuple(x.shape[-2:]) == shape[-2:] and x.numel() == shape[-1] * shape[-2]:
            y = torch.randn_like(y)
        return y

    return broken


@pytest.mark.parametrize(
    ("breaks", "route"),
    [
        ("double scaling", "unscaled inverse times 1/N"),
        ("single planes", "a batch of two (the field and zeros)"),
    ],
)
def test_a_failing_backend_is_routed_around_with_one_warning(monkeypatch, breaks, route):
    shape = (1, 48, 40)
    if breaks == "double scaling":
        monkeypatch.setattr(torch.fft, "ifftn", _double_scaled_inverse(torch.fft.ifftn, shape))
    else:
        monkeypatch.setattr(torch.fft, "ifftn", _garbage_for_single_planes(torch.fft.ifftn, shape))
        monkeypatch.setattr(torch.fft, "ifft", _garbage_for_single_planes(torch.fft.ifft, shape))
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(shape, dtype=torch.complex64, generator=gen)
    ref = np.fft.ifft2(x.numpy().astype(np.complex128))
    assert rel(torch.fft.ifftn(x, dim=(-2, -1)).numpy(), ref) > 0.5  # the injected fault
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        first = fft.ifft2(x)
        second = fft.ifft2(x.clone())
        buf = x.clone()
        in_place = fft.ifft2(buf, out=buf)
    for y in (first, second, in_place):
        assert rel(y.numpy(), ref) < 1e-6
    assert in_place.data_ptr() == buf.data_ptr()
    messages = backend_warnings(record)
    assert len(messages) == 2  # one per layout: a new output, and in place
    assert all(torch.__version__ in m and "shape (1, 48, 40)" in m and route in m
               for m in messages)  # fmt: skip
    assert [c.route for c in fft.checks()] == [route, route]
    # Other shapes are untouched by the fault and take the direct route, silently.
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        fft.ifft2(torch.randn(1, 48, 41, dtype=torch.complex64))
    assert backend_warnings(record) == [] and fft.checks()[-1].route == "direct"


def test_a_layout_no_route_can_fix_is_refused(monkeypatch):
    def noise(real):
        return lambda x, *a, **k: torch.randn_like(real(x, *a, **k))

    for name in ("ifftn", "ifft"):
        monkeypatch.setattr(torch.fft, name, noise(getattr(torch.fft, name)))
    with pytest.raises(RuntimeError, match=r"ifft of shape \(2, 16, 16\).*on every route"):
        fft.ifft2(torch.ones(2, 16, 16, dtype=torch.complex64))


def test_guarded_transforms_equal_numpy_for_strided_padded_and_in_place_calls():
    gen = torch.Generator().manual_seed(8)
    base = torch.randn(3, 40, 72, dtype=torch.complex128, generator=gen)
    crop = base[..., 5:, :50]  # not contiguous
    x = crop.numpy()
    np.testing.assert_allclose(fft.fft2(crop, s=(64, 60)).numpy(), np.fft.fft2(x, s=(64, 60)),
                               rtol=0, atol=1e-12 * np.abs(x).sum())  # fmt: skip
    np.testing.assert_allclose(fft.ifft(crop, n=80, dim=-2).numpy(),
                               np.fft.ifft(x, n=80, axis=-2), rtol=0, atol=1e-13)
    np.testing.assert_allclose(fft.fft(crop.real.float(), dim=-1).numpy(),  # real input
                               np.fft.fft(x.real, axis=-1), rtol=0, atol=1e-4)
    buf = base.clone()
    fft.fft2(buf, out=buf)
    np.testing.assert_allclose(buf.numpy(), np.fft.fft2(base.numpy()), rtol=0, atol=1e-10)
    layouts = {(c.op, c.shape, c.sizes, c.in_place) for c in fft.checks()}
    assert ((("fft", (3, 35, 50), (64, 60), False)) in layouts
            and ("fft", (3, 40, 72), (40, 72), True) in layouts)  # fmt: skip
    assert all(c.route == "direct" for c in fft.checks())


def test_each_layout_is_checked_once_per_thread_count():
    before = torch.get_num_threads()
    x = torch.randn(2, 24, 20, dtype=torch.complex64)
    try:
        for threads in (1, 1, 2, 2):
            torch.set_num_threads(threads)
            fft.fft2(x)
    finally:
        torch.set_num_threads(before)
    assert sorted(c.threads for c in fft.checks()) == [1, 2]
