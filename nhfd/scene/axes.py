"""Axis conventions of splat formats, and the conversion into the project's frame.

The project keeps scenes in the OpenCV/COLMAP frame of the INRIA .ply files: x right, y down,
z forward ("RDF"). Formats that declare another frame store the same scene with some axes
negated; RUB (OpenGL, three.js, glTF's camera space, Niantic .spz) negates y and z, so its up
(+y) becomes -y here.

Negating axes is its own inverse, so the same `flip_axes` converts both ways.
"""

from __future__ import annotations

import numpy as np

__all__ = ["RDF", "RUB", "flip_axes", "signs_from_letters"]

RDF = (1.0, 1.0, 1.0)
RUB = (1.0, -1.0, -1.0)

# Parity (x, y, z powers mod 2) of each real SH basis after the constant, in the 3DGS order
# (degree 1: y z x; degree 2: xy yz (3z^2-1) xz (x^2-y^2); degree 3: y(3x^2-y^2) xyz y(5z^2-1)
# z(5z^2-3) x(5z^2-1) z(x^2-y^2) x(x^2-3y^2)). Negating axis a multiplies a basis by -1 to the
# power of its parity in a.
_SH_PARITY = np.array([
    (0, 1, 0), (0, 0, 1), (1, 0, 0),
    (1, 1, 0), (0, 1, 1), (0, 0, 0), (1, 0, 1), (0, 0, 0),
    (0, 1, 0), (1, 1, 1), (0, 1, 0), (0, 0, 1), (1, 0, 0), (0, 0, 1), (1, 0, 0),
])  # fmt: skip


def signs_from_letters(name: str) -> tuple[float, float, float] | None:
    """Axis signs relative to RDF for a three-letter convention such as "RUB" (x: R/L,
    y: D/U, z: F/B), or None when the letters permute the axes (e.g. "RFU")."""
    pairs = ({"R": 1.0, "L": -1.0}, {"D": 1.0, "U": -1.0}, {"F": 1.0, "B": -1.0})
    if len(name) != 3 or any(c not in p for c, p in zip(name, pairs, strict=True)):
        return None
    return tuple(p[c] for c, p in zip(name, pairs, strict=True))  # type: ignore[return-value]


def flip_axes(arrays: dict[str, np.ndarray], signs: tuple[float, float, float]) -> None:
    """Negate axes in place on activated arrays (means [N,3], quats [N,4] wxyz, sh [N,K,3]).

    A diagonal sign matrix F maps a covariance R S^2 R^T to F R S^2 R^T F = (F R F) S^2
    (F R F)^T, as F S^2 F = S^2. F R F is a rotation (det F^2 = 1) whose quaternion keeps w and
    scales each vector part by the product of the *other* two signs (the reference .spz
    converter's choice; for a proper F, F R would give the same covariance with the local axes
    named differently). Scales and opacity do not change; each SH basis takes its parity sign.
    """
    s = np.asarray(signs, np.float64)
    if (s == 1.0).all():
        return
    arrays["means"] = arrays["means"] * s
    q_sign = np.array([1.0, s[1] * s[2], s[0] * s[2], s[0] * s[1]])
    arrays["quats"] = arrays["quats"] * q_sign
    k = arrays["sh"].shape[1]
    if k > 1:
        sh_sign = np.prod(np.where(_SH_PARITY[: k - 1] == 1, s, 1.0), axis=1)
        arrays["sh"] = arrays["sh"] * np.concatenate([[1.0], sh_sign])[None, :, None]


