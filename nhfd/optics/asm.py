"""Band-limited angular spectrum propagation (docs/physics.md, "The SLM, the field and
propagation").

`P(U; z)` multiplies the spectrum of U, on the `fftfreq` grid of the zero-padded array, by

    H(fx, fy; z) = exp(-i 2 pi z lambda f^2 / (1 + sqrt(1 - lambda^2 f^2)))

which is `exp(i 2 pi z sqrt(1/lambda^2 - f^2))` with the carrier `exp(i 2 pi z / lambda)` removed
analytically (no intensity sees that global phase, and keeping it costs float32 all its phase
resolution at centimetre distances). H is zero outside the propagating circle `lambda f < 1` and
outside the Matsushima-Shimobaba band limit `|fx| < 1 / (lambda sqrt((2 z / (Npad p))^2 + 1))`.
Positive z points from the SLM toward the viewer.

Two paths: kernels for fixed depths are computed in float64 and cast (accurate to ~1e-7, cacheable
in a `KernelCache`); a depth given as a tensor that requires grad gets its phase in the working
precision from float64 coefficients, so the result is differentiable in z.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import torch

from nhfd.optics import _validate, fft
from nhfd.optics.aperture import Aperture, aperture_mask, frequency_indices
from nhfd.optics.cache import KernelCache
from nhfd.optics.padding import PaddingPlan, Policy, plan_padding

Depths = float | Sequence[float] | torch.Tensor

# Below this fraction of the grid's frequencies kept per axis, the band limit leaves so little of
# the spectrum that the result is a blur of the lowest frequencies: say so.
BAND_LIMIT_WARN_FRACTION = 0.05


def _depths(z_m: Depths) -> tuple[torch.Tensor | tuple[float, ...], bool]:
    """Normalise depths to a tuple of floats (or a 1-D tensor needing grad) and whether the
    caller gave a scalar (then the depth axis is dropped from the result). NumPy scalars and 0-d
    arrays are scalars, 1-D arrays sequences."""
    if isinstance(z_m, torch.Tensor):
        scalar = z_m.dim() == 0
        flat = z_m.reshape(-1)
        values = tuple(float(v) for v in flat.detach().tolist())
        if not values:
            raise ValueError("z_m is empty: give at least one depth")
        for i, v in enumerate(values):
            _validate.distance("z_m" if scalar else f"z_m[{i}]", v)
        return (flat, scalar) if flat.requires_grad else (values, scalar)
    z_m, scalar = _validate.scalar_or_sequence("z_m", z_m)
    if scalar:
        return (_validate.distance("z_m", z_m),), True
    values = tuple(_validate.distance(f"z_m[{i}]", v) for i, v in enumerate(z_m))
    if not values:
        raise ValueError("z_m is empty: give at least one depth")
    return values, False


def _frequencies_sq(
    padded_hw: tuple[int, int], pitch_m: float, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """fx^2 [1, W] and fy^2 [H, 1] in cycles^2 / m^2, float64, on the padded fftfreq grid."""
    hp, wp = padded_hw
    fy = frequency_indices(hp, device) / (hp * pitch_m)
    fx = frequency_indices(wp, device) / (wp * pitch_m)
    return (fx**2)[None, :], (fy**2)[:, None]


def _band_limit(
    padded_hw: tuple[int, int], pitch_m: float, lam: float, z: float, device: torch.device
) -> torch.Tensor:
    """Matsushima-Shimobaba mask [H, W] (bool) for one wavelength and depth."""
    hp, wp = padded_hw
    fy = (frequency_indices(hp, device) / (hp * pitch_m)).abs()[:, None]
    fx = (frequency_indices(wp, device) / (wp * pitch_m)).abs()[None, :]
    lim_x = 1.0 / (lam * math.sqrt((2 * z / (wp * pitch_m)) ** 2 + 1))
    lim_y = 1.0 / (lam * math.sqrt((2 * z / (hp * pitch_m)) ** 2 + 1))
    kept = min(lim_x * pitch_m * 2, lim_y * pitch_m * 2)
    if kept < BAND_LIMIT_WARN_FRACTION:
        warnings.warn(
            f"z = {z:g} m: the band limit keeps only |f| < {kept / 2:.3g} cycles/px at "
            f"{lam * 1e9:.0f} nm on a {hp} x {wp} grid; only the lowest frequencies survive "
            "(pad more, or propagate in steps with a larger window)",
            stacklevel=4,
        )
    return (fx < lim_x) & (fy < lim_y)


def _phase_coefficient(
    padded_hw: tuple[int, int], pitch_m: float, lam: float, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """`-2 pi lambda f^2 / (1 + sqrt(1 - lambda^2 f^2))` [H, W] (rad per metre of z, float64) and
    the propagating mask `lambda f < 1` (bool); evanescent entries are 0, never NaN."""
    fx2, fy2 = _frequencies_sq(padded_hw, pitch_m, device)
    lf2 = (fx2 + fy2) * lam * lam
    propagating = lf2 < 1.0
    root = torch.sqrt(torch.clamp(1.0 - lf2, min=0.0))
    coef = -2 * math.pi * lam * (fx2 + fy2) / (1.0 + root)
    return torch.where(propagating, coef, torch.zeros_like(coef)), propagating


def transfer_function(
    padded_hw: tuple[int, int],
    pitch_m: float,
    wavelengths_m: Sequence[float],
    z_m: Sequence[float],
    *,
    aperture: Aperture | None = None,
    band_limit: bool = True,
    dtype: torch.dtype = torch.complex64,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """Kernels `[D, C, Hpad, Wpad]` (complex, unshifted fftfreq layout) for fixed depths.

    Phases are computed in float64 and cast, so complex64 kernels are accurate to ~1e-7.
    The aperture, when given, is folded in (one multiply per propagation instead of two).
    """
    device = torch.device(device)
    lams = _validate.wavelengths(wavelengths_m)
    pitch = _validate.pitch("pitch_m", pitch_m)
    z_m = tuple(_validate.distance(f"z_m[{i}]", z) for i, z in enumerate(z_m))
    out = torch.empty((len(z_m), len(lams), *padded_hw), dtype=dtype, device=device)
    ap = aperture_mask(padded_hw, aperture, len(lams), device) if aperture is not None else None
    for c, lam in enumerate(lams):
        coef, propagating = _phase_coefficient(padded_hw, pitch, lam, device)
        for d, z in enumerate(z_m):
            keep = propagating
            if band_limit and z != 0:
                keep = keep & _band_limit(padded_hw, pitch, lam, z, device)
            if ap is not None:
                keep = keep & ap[c]
            kernel = torch.polar(keep.to(torch.float64), coef * z)
            out[d, c] = kernel.to(dtype)
    return out


def transfer_function_z(
    padded_hw: tuple[int, int],
    pitch_m: float,
    wavelengths_m: Sequence[float],
    z_m: torch.Tensor,
    *,
    aperture: Aperture | None = None,
    band_limit: bool = True,
    dtype: torch.dtype = torch.complex64,
) -> torch.Tensor:
    """Kernels `[D, C, Hpad, Wpad]` differentiable in `z_m` (a 1-D real tensor, metres).

    The phase is `z * coef` with `coef` from float64; only the product is in working precision
    (relative phase error ~1e-7, i.e. ~1e-4 rad at 10 cm). Masks use the detached depths.
    """
    device = z_m.device
    lams = _validate.wavelengths(wavelengths_m)
    pitch = _validate.pitch("pitch_m", pitch_m)
    real = torch.float64 if dtype == torch.complex128 else torch.float32
    ap = aperture_mask(padded_hw, aperture, len(lams), device) if aperture is not None else None
    zs = z_m.to(real)
    per_colour = []
    for c, lam in enumerate(lams):
        coef, propagating = _phase_coefficient(padded_hw, pitch, lam, device)
        masks = []
        for z in zs.detach().tolist():
            keep = propagating
            if band_limit and z != 0:
                keep = keep & _band_limit(padded_hw, pitch, lam, z, device)
            if ap is not None:
                keep = keep & ap[c]
            masks.append(keep)
        mask = torch.stack(masks).to(real)
        phase = zs[:, None, None] * coef.to(real)[None]
        per_colour.append(torch.polar(mask, phase))
    return torch.stack(per_colour, dim=1)


def propagate(
    field: torch.Tensor,
    z_m: Depths,
    pitch_m: float,
    wavelengths_m: float | Sequence[float],
    *,
    padding: Policy | tuple[int, int] = "auto",
    aperture: Aperture | None = None,
    band_limit: bool = True,
    cache: KernelCache | None = None,
) -> torch.Tensor:
    """Propagate `field` by `z_m` with the band-limited angular spectrum method.

    Args:
        field: complex `[..., C, H, W]` on a grid of pitch `pitch_m`; real or half-precision
            input is upcast (complex64; float64/complex128 stay complex128). Every sample must
            be finite.
        z_m: depth in metres, |z| <= 10 m (float, NumPy scalar, 0-d array or 0-d tensor: result
            `[..., C, H, W]`), or several depths (sequence, 1-D array or 1-D tensor: result
            `[..., D, C, H, W]`). A tensor that requires grad
            makes the result differentiable in z (that path is not cached).
        pitch_m: sample pitch in metres, 0.1 um to 1 mm.
        wavelengths_m: one wavelength per colour channel C (or one for all), metres, 100 nm to
            10 um.
        padding: "none", "2x", "auto" (see `nhfd.optics.padding`) or an explicit (Hpad, Wpad).
        aperture: Fourier aperture applied with the propagation (None: full band).
        band_limit: apply the Matsushima-Shimobaba limit (on by default; off only for tests).
        cache: a `KernelCache` to reuse kernels for fixed depths (None: compute each call).

    Returns:
        The propagated field(s), complex, same H x W (the padding is cropped away). The carrier
        `exp(i 2 pi z / lambda)` is not included.
    """
    u = _validate.field("field", field)
    lams = _validate.wavelengths(wavelengths_m, u.shape[-3])
    pitch = _validate.pitch("pitch_m", pitch_m)
    depths, scalar = _depths(z_m)
    h, w = u.shape[-2:]
    max_z = (
        float(depths.detach().abs().max()) if isinstance(depths, torch.Tensor)
        else max(abs(z) for z in depths)
    )
    plan = plan_padding((h, w), pitch, lams, max_z, aperture, padding)
    kernels = propagation_kernels(plan, pitch, lams, depths, aperture, band_limit, u.dtype,
                                  u.device, cache)
    spectrum = fft.fft2(u, s=plan.padded_hw)
    # One depth at a time bounds memory at one padded stack per colour, not one per depth.
    n_depths = len(kernels)
    kernel_grad = any(k.requires_grad for k in kernels)
    if torch.is_grad_enabled() and (spectrum.requires_grad or kernel_grad):
        slices = [fft.ifft2(spectrum * kernels[d])[..., :h, :w] for d in range(n_depths)]
        out = torch.stack(slices, dim=-4)
    else:
        # Without autograd, reuse one padded buffer: fresh 100 MB allocations per depth cost
        # page faults that rival the FFTs themselves.
        out = torch.empty((*u.shape[:-3], n_depths, *u.shape[-3:]), dtype=u.dtype,
                          device=u.device)
        buf = torch.empty_like(spectrum)
        for d in range(n_depths):
            torch.mul(spectrum, kernels[d], out=buf)
            fft.ifft2(buf, out=buf)
            out[..., d, :, :, :] = buf[..., :h, :w]
    return out.squeeze(-4) if scalar else out


def propagation_kernels(
    plan: PaddingPlan,
    pitch: float,
    lams: tuple[float, ...],
    depths: torch.Tensor | tuple[float, ...],
    aperture: Aperture | None,
    band_limit: bool,
    dtype: torch.dtype,
    device: torch.device,
    cache: KernelCache | None,
) -> torch.Tensor | list[torch.Tensor]:
    """The transfer functions `propagate` multiplies by (the daemon's encoder uses the same, under
    the same cache keys), indexable by depth: a `[D, C, Hpad, Wpad]` tensor, or a list of
    `[C, Hpad, Wpad]` tensors when several fixed depths come from the cache."""
    if isinstance(depths, torch.Tensor):
        return transfer_function_z(
            plan.padded_hw, pitch, lams, depths.to(device),
            aperture=aperture, band_limit=band_limit, dtype=dtype,
        )

    def compute() -> torch.Tensor:
        return transfer_function(
            plan.padded_hw, pitch, lams, depths,
            aperture=aperture, band_limit=band_limit, dtype=dtype, device=device,
        )

    if cache is None:
        return compute()
    if len(depths) == 1:
        key = ("asm", plan.padded_hw, pitch, lams, depths, aperture, band_limit, dtype, str(device))
        return cache.get(key, compute)

    # One entry per depth: a caller whose set of planes changes from call to call (the training
    # loss picks planes from each view's depths) still hits the cache for every plane it reuses.
    def one(z: float) -> torch.Tensor:
        key = ("asm", plan.padded_hw, pitch, lams, (z,), aperture, band_limit, dtype, str(device))
        return cache.get(key, lambda: transfer_function(
            plan.padded_hw, pitch, lams, (z,),
            aperture=aperture, band_limit=band_limit, dtype=dtype, device=device,
        ))  # fmt: skip

    # A list, not a stacked tensor: stacking would copy every kernel on every call.
    return [one(z)[0] for z in depths]
