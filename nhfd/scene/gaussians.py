"""The one in-memory representation of a Gaussian splat scene.

Every loader returns a `Gaussians`; the renderer, the light-field renderer and the CLI take one.
Values are *activated* (no logits, no log-scales) and float32:

    means      [N, 3]     world units (whatever the scene was trained in)
    quats      [N, 4]     unit quaternions, w x y z (rotation of the Gaussian's local axes)
    scales     [N, 3]     standard deviations along the local axes, > 0
    opacities  [N]        in [0, 1]
    sh         [N, K, 3]  spherical-harmonic coefficients, basis-major (K = (degree + 1)^2);
                          sh[:, 0] is the DC term `f_dc`, so colour = 0.5 + SH_C0 * sh[:, 0] + ...
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# Real spherical harmonics, degree 0 constant (the 3DGS convention).
SH_C0 = 0.28209479177387814
SH_DEGREE_FOR_K = {1: 0, 4: 1, 9: 2, 16: 3}


class SceneFileError(ValueError):
    """A scene file that cannot be read; the message names the file and the problem."""


@contextlib.contextmanager
def malformed_as_scene_error(path: Path | str, what: str) -> Iterator[None]:
    """Turn a decoder's stray lookup or type error on a structurally bad file into a
    SceneFileError naming the file and `what` was malformed; a SceneFileError passes as is."""
    try:
        yield
    except SceneFileError:
        raise
    except (KeyError, IndexError, TypeError, AttributeError, ValueError) as e:
        raise SceneFileError(f"{path}: malformed {what} ({type(e).__name__}: {e})") from e


@dataclass(frozen=True)
class Gaussians:
    """A splat scene, activated, float32: means [N, 3] (scene units), quats [N, 4] (w x y z),
    scales [N, 3] (> 0), opacities [N] in [0, 1], sh [N, K, 3]; ValueError on another shape or
    dtype."""

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expect = {
            "means": (n, 3),
            "quats": (n, 4),
            "scales": (n, 3),
            "opacities": (n,),
        }
        for name, shape in expect.items():
            arr = getattr(self, name)
            if arr.shape != shape or arr.dtype != np.float32:
                raise ValueError(
                    f"Gaussians.{name} must be float32 {shape}, got {arr.dtype} {arr.shape}"
                )
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"Gaussians.sh must be [N, K, 3], got {self.sh.shape}")
        if self.sh.shape[1] not in SH_DEGREE_FOR_K or self.sh.dtype != np.float32:
            raise ValueError(
                f"Gaussians.sh must be float32 with K in {sorted(SH_DEGREE_FOR_K)} "
                f"coefficients, got {self.sh.dtype} K={self.sh.shape[1]}"
            )

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        """The spherical-harmonic degree, 0 to 3 (K = (degree + 1)^2)."""
        return SH_DEGREE_FOR_K[self.sh.shape[1]]

    def base_colors(self) -> np.ndarray:
        """View-independent colour `0.5 + SH_C0 * f_dc`, [N, 3], not clamped."""
        return (0.5 + SH_C0 * self.sh[:, 0, :]).astype(np.float32)

    def subset(self, index: np.ndarray) -> Gaussians:
        """The Gaussians `index` selects (a boolean mask [N] or integer indices)."""
        return Gaussians(
            self.means[index],
            self.quats[index],
            self.scales[index],
            self.opacities[index],
            self.sh[index],
        )

    @staticmethod
    def empty(sh_degree: int = 0) -> Gaussians:
        """A scene of no Gaussians with SH of `sh_degree`."""
        k = (sh_degree + 1) ** 2
        z = np.zeros
        return Gaussians(
            z((0, 3), np.float32),
            z((0, 4), np.float32),
            z((0, 3), np.float32),
            z((0,), np.float32),
            z((0, k, 3), np.float32),
        )


def make_gaussians(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    opacities: np.ndarray,
    sh: np.ndarray,
    *,
    source: str = "scene",
) -> Gaussians:
    """Build a `Gaussians` from activated arrays: cast to float32, normalise quaternions, and drop
    Gaussians that are non-finite or degenerate (zero quaternion, scale <= 0) with one warning that
    says how many and why. `source` names the file in that warning.
    """
    means = np.asarray(means, np.float32).reshape(-1, 3)
    n = means.shape[0]
    quats = np.asarray(quats, np.float32).reshape(n, 4)
    scales = np.asarray(scales, np.float32).reshape(n, 3)
    opacities = np.asarray(opacities, np.float32).reshape(n)
    sh = np.asarray(sh, np.float32).reshape(n, -1, 3)

    finite = (
        np.isfinite(means).all(1)
        & np.isfinite(quats).all(1)
        & np.isfinite(scales).all(1)
        & np.isfinite(opacities)
        & np.isfinite(sh).all((1, 2))
    )
    qnorm = np.linalg.norm(quats, axis=1)
    degenerate = finite & ((qnorm < 1e-12) | (scales <= 0).any(1))
    keep = finite & ~degenerate
    dropped_nonfinite = int((~finite).sum())
    dropped_degenerate = int(degenerate.sum())
    if dropped_nonfinite or dropped_degenerate:
        warnings.warn(
            f"{source}: dropped {dropped_nonfinite + dropped_degenerate} of {n} Gaussians "
            f"({dropped_nonfinite} with non-finite values, {dropped_degenerate} degenerate: "
            "zero rotation or scale <= 0)",
            stacklevel=2,
        )
    with np.errstate(invalid="ignore", divide="ignore"):
        quats = quats / qnorm[:, None]
    return Gaussians(
        np.ascontiguousarray(means[keep]),
        np.ascontiguousarray(quats[keep]),
        np.ascontiguousarray(scales[keep]),
        np.ascontiguousarray(np.clip(opacities[keep], 0.0, 1.0)),
        np.ascontiguousarray(sh[keep]),
    )
