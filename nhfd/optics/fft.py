"""FFTs that are checked once against a known answer before they are trusted.

The FFT backend itself can be wrong: torch 2.13.0 (CPU, MKL) returns the complex64 inverse 2-D
transform of a single 2048 x 2048 plane on two threads scaled by 1/N twice (round-trip error 3.8
on unit-variance noise; the forward transform, batches of two or more, one thread, other sizes
and complex128 are right), so a propagation silently returned 1e-13 of its input energy.

Every FFT in the product's paths goes through `fft`, `ifft`, `fft2` and `ifft2` here. The first
call with a new layout (direction, transformed dims and sizes, shape, strides, dtype, device,
torch's thread count, in place or not) transforms a known rank-1 input of that layout (a product
of seeded random vectors, one per axis, whose transform is the product of their float64 NumPy
transforms) and compares. A layout that fails is routed around, each route checked the same way:
the unscaled inverse times 1/N (inverse only), one 1-D transform per axis, a batch of two (the
field and zeros), complex128. One `FFTBackendWarning` names the layout, the torch version and the
route. `checks()` lists every check with its one-time cost (`nhfd bench optics`).
"""

from __future__ import annotations

import math
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

# Relative L2 error a correct transform stays far below (measured: 1e-7 complex64, 3e-16
# complex128); a failing one is off by order 1.
TOLERANCE = {torch.complex64: 1e-4, torch.complex128: 1e-10}
# Rows compared at a time: bounds the check's extra memory at a few tens of MB.
_BLOCK_ELEMENTS = 2**22
_SEED = 21
# Layouts remembered; a caller cycling through more re-checks the oldest (correct, only slower).
_MAX_ENTRIES = 1024


class FFTBackendWarning(UserWarning):
    """torch's FFT failed its check for one layout; a checked other route is used instead."""


@dataclass(frozen=True)
class FFTCheck:
    """One layout's check: what was transformed, the route taken, the direct route's relative
    error, and the check's one-time cost in seconds."""

    op: str
    shape: tuple[int, ...]
    dims: tuple[int, ...]
    sizes: tuple[int, ...]
    dtype: str
    device: str
    threads: int
    in_place: bool
    route: str
    direct_error: float
    seconds: float

    def describe(self) -> str:
        """The layout in words (dtype, op, shape, dims, sizes, device, threads), for warnings."""
        sizes = " x ".join(str(s) for s in self.sizes)
        place = ", in place" if self.in_place else ""
        return (f"{self.dtype} {self.op} of shape {self.shape} over dims {self.dims} to {sizes} "
                f"on {self.device} with {self.threads} threads{place}")  # fmt: skip


_lock = threading.Lock()
_routes: dict[tuple, tuple[str, FFTCheck]] = {}


def fft(x: torch.Tensor, n: int | None = None, dim: int = -1, *,
        out: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """`torch.fft.fft`, checked."""
    return _transform(False, x, None if n is None else (n,), (dim,), out)


def ifft(x: torch.Tensor, n: int | None = None, dim: int = -1, *,
         out: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """`torch.fft.ifft`, checked."""
    return _transform(True, x, None if n is None else (n,), (dim,), out)


def fft2(x: torch.Tensor, s: Sequence[int] | None = None, dim: tuple[int, int] = (-2, -1), *,
         out: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """`torch.fft.fft2`, checked."""
    return _transform(False, x, None if s is None else tuple(s), tuple(dim), out)


def ifft2(x: torch.Tensor, s: Sequence[int] | None = None, dim: tuple[int, int] = (-2, -1), *,
          out: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """`torch.fft.ifft2`, checked."""
    return _transform(True, x, None if s is None else tuple(s), tuple(dim), out)


def checks() -> tuple[FFTCheck, ...]:
    """Every layout checked so far (oldest first)."""
    with _lock:
        return tuple(check for _, check in _routes.values())


def clear_checks() -> None:
    """Forget every check (the next call of each layout checks again, and warns again)."""
    with _lock:
        _routes.clear()


# ---- routes: (inverse, x, sizes, dims, out) -> the transform


def _nd(inverse: bool) -> Callable[..., torch.Tensor]:
    return torch.fft.ifftn if inverse else torch.fft.fftn


def _finish(y: torch.Tensor, out: torch.Tensor | None) -> torch.Tensor:
    if out is None or y is out:
        return y
    return out.copy_(y)


def _direct(inverse, x, sizes, dims, out):
    return _nd(inverse)(x, s=sizes, dim=dims, out=out)


def _unscaled(inverse, x, sizes, dims, out):
    # norm="forward" leaves the inverse unscaled; the 1/N is one multiply of our own.
    y = torch.fft.ifftn(x, s=sizes, dim=dims, norm="forward", out=out)
    scale = 1.0 / math.prod(sizes)
    return y * scale if y.requires_grad else y.mul_(scale)


def _per_axis(inverse, x, sizes, dims, out):
    one = torch.fft.ifft if inverse else torch.fft.fft
    y = x
    for d, n in reversed(tuple(zip(dims, sizes, strict=True))):
        y = one(y, n=n, dim=d)
    return _finish(y, out)


def _batch_of_two(inverse, x, sizes, dims, out):
    pair = torch.stack([x, torch.zeros_like(x)])
    return _finish(_nd(inverse)(pair, s=sizes, dim=tuple(d + 1 for d in dims))[0], out)


def _complex128(inverse, x, sizes, dims, out):
    return _finish(_nd(inverse)(x.to(torch.complex128), s=sizes, dim=dims).to(x.dtype), out)


_ROUTES: dict[str, Callable[..., torch.Tensor]] = {
    "direct": _direct,
    "unscaled inverse times 1/N": _unscaled,
    "one 1-D transform per axis": _per_axis,
    "a batch of two (the field and zeros)": _batch_of_two,
    "complex128": _complex128,
}


def _candidates(inverse: bool, n_dims: int, dtype: torch.dtype) -> list[str]:
    names = ["unscaled inverse times 1/N"] if inverse else []
    if n_dims > 1:
        names.append("one 1-D transform per axis")
    names.append("a batch of two (the field and zeros)")
    if dtype == torch.complex64:
        names.append("complex128")
    return names


# ---- the check


def _transform(inverse: bool, x: torch.Tensor, sizes: tuple[int, ...] | None,
               dims: tuple[int, ...], out: torch.Tensor | None) -> torch.Tensor:  # fmt: skip
    if not x.is_complex():
        x = x.to(torch.complex128 if x.dtype == torch.float64 else torch.complex64)
    nd = x.dim()
    if (x.dtype not in TOLERANCE or x.numel() == 0
            or not all(-nd <= d < nd for d in dims)):  # complex32, or torch's own error
        return _direct(inverse, x, sizes, tuple(dims), out)
    if any(st == 0 and n > 1 for st, n in zip(x.stride(), x.shape, strict=True)):
        x = x.contiguous()  # a broadcast view: no layout of its own to check
    dims = tuple(d % nd for d in dims)
    sizes = sizes if sizes is not None else tuple(x.shape[d] for d in dims)
    in_place = out is not None and out is x
    layout = None if x.is_contiguous() else tuple(x.stride())
    key = (inverse, dims, sizes, tuple(x.shape), layout, x.dtype, str(x.device),
           torch.get_num_threads(), "none" if out is None else "same" if in_place else "other")
    entry = _routes.get(key)
    if entry is None:
        entry = _plan(key, inverse, x, sizes, dims, out is not None, in_place)
    return _ROUTES[entry[0]](inverse, x, sizes, dims, out)


def _plan(
    key: tuple, inverse: bool, x: torch.Tensor, sizes: tuple[int, ...], dims: tuple[int, ...],
    has_out: bool, in_place: bool,
) -> tuple[str, FFTCheck]:
    with _lock:
        if key in _routes:
            return _routes[key]
        t0 = time.perf_counter()
        with torch.no_grad():
            probe = _Probe(inverse, x, sizes, dims)
            direct_error = probe.error("direct", has_out, in_place)
            route = "direct"
            if not direct_error < TOLERANCE[x.dtype]:
                route = next((name for name in _candidates(inverse, len(dims), x.dtype)
                              if probe.error(name, has_out, in_place) < TOLERANCE[x.dtype]),
                             "")  # fmt: skip
        check = FFTCheck(
            "ifft" if inverse else "fft", tuple(x.shape), tuple(d - x.dim() for d in dims), sizes,
            str(x.dtype).removeprefix("torch."), str(x.device), torch.get_num_threads(),
            in_place, route, direct_error, time.perf_counter() - t0,
        )
        if not route:
            raise RuntimeError(f"torch {torch.__version__}: {check.describe()} fails a "
                               f"known-answer check on every route (relative error "
                               f"{direct_error:.3g}); no FFT of this layout can be trusted")
        if route != "direct":
            warnings.warn(
                f"torch {torch.__version__}: {check.describe()} fails a known-answer check "
                f"(relative error {direct_error:.3g}); nhfd.optics uses {route} instead, which "
                f"passes it", FFTBackendWarning, stacklevel=4,
            )
        if len(_routes) >= _MAX_ENTRIES:
            _routes.pop(next(iter(_routes)))
        _routes[key] = (route, check)
        return route, check


class _Probe:
    """A rank-1 input of `x`'s layout, `prod_k v_k[i_k]` with seeded random complex vectors,
    and its exact transform: the same product with each transformed axis's vector replaced by
    its float64 NumPy transform (zero-padded or cut to the size asked for)."""

    def __init__(self, inverse: bool, x: torch.Tensor, sizes: tuple[int, ...],
                 dims: tuple[int, ...]) -> None:  # fmt: skip
        rng = np.random.default_rng(_SEED)
        vectors = [rng.standard_normal(n) + 1j * rng.standard_normal(n) for n in x.shape]
        expected = list(vectors)
        for d, n in zip(dims, sizes, strict=True):
            v = np.zeros(n, np.complex128)
            k = min(n, len(vectors[d]))
            v[:k] = vectors[d][:k]
            expected[d] = np.fft.ifft(v) if inverse else np.fft.fft(v)
        self.inverse, self.sizes, self.dims = inverse, sizes, dims
        self.dtype, self.device = x.dtype, x.device
        self.shape, self.stride = tuple(x.shape), tuple(x.stride())
        self.vectors, self.expected = vectors, expected

    def input(self) -> torch.Tensor:
        """A fresh copy of the rank-1 input with the caller's strides."""
        lead, last = _outer(self.vectors, self.dtype, self.device)
        t = torch.empty_strided(self.shape, self.stride, dtype=self.dtype, device=self.device)
        return torch.mul(lead.reshape(*self.shape[:-1], 1), last, out=t)

    def error(self, route: str, has_out: bool, in_place: bool) -> float:
        """Relative L2 error of `route` on the input (inf if it raises or is not finite)."""
        t = self.input()
        out = t if in_place else torch.empty(0, dtype=self.dtype, device=self.device) \
            if has_out else None  # fmt: skip
        try:
            y = _ROUTES[route](self.inverse, t, self.sizes, self.dims, out)
        except RuntimeError:
            return math.inf
        lead, last = _outer(self.expected, self.dtype, self.device)
        y2 = y.reshape(-1, y.shape[-1])
        block = max(1, _BLOCK_ELEMENTS // y2.shape[1])
        num = 0.0
        for i in range(0, y2.shape[0], block):
            d = torch.mul(lead[i : i + block, None], last[None, :])
            torch.sub(y2[i : i + block], d, out=d)
            d = d.reshape(-1)
            num += float(torch.vdot(d, d).real)
        den = math.prod(float(np.vdot(e, e).real) for e in self.expected)
        err = math.sqrt(num / den) if den > 0 else math.inf
        return err if math.isfinite(err) else math.inf


def _outer(vectors: list[np.ndarray], dtype: torch.dtype, device: torch.device
           ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """The rank-1 product of `vectors` as (all axes but the last, flattened) and (the last)."""
    lead = np.ones(1, np.complex128)
    for v in vectors[:-1]:
        lead = np.multiply.outer(lead, v).reshape(-1)
    last = vectors[-1] if vectors else np.ones(1, np.complex128)
    return (torch.from_numpy(lead).to(device=device, dtype=dtype),
            torch.from_numpy(np.ascontiguousarray(last)).to(device=device, dtype=dtype))
