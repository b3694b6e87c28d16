"""Affine 4x4 transforms (numpy, float64) and their validation.

Every node of a model carries a local-to-parent matrix; the lowering step multiplies
them down to the leaves, so the kernel only ever sees one world-to-local matrix per
primitive.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import ModelError
from . import values

IDENTITY = np.eye(4)
IDENTITY.setflags(write=False)


def _frozen(m: np.ndarray) -> np.ndarray:
    m.setflags(write=False)
    return m


def number(value, what: str) -> float:
    """A finite float (bools refused), or a ModelError naming `what`."""
    return values.checked(values.number, value, what)


def vector3(value, what: str) -> np.ndarray:
    """A finite 3-vector from a scalar (broadcast) or a sequence, or a ModelError."""
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ModelError(f"{what}: expected 3 numbers, got {value!r}") from None
    if v.ndim == 0:
        v = np.full(3, float(v))
    if v.shape != (3,):
        raise ModelError(f"{what}: expected 3 numbers, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ModelError(f"{what}: must be finite, got {v.tolist()}")
    return v


def translation(offset) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = vector3(offset, "translate")
    return _frozen(m)


def scaling(factors) -> np.ndarray:
    s = vector3(factors, "scale")
    if np.any(s == 0):
        raise ModelError(f"scale: a zero factor makes the solid flat (singular transform), got {s.tolist()}")
    m = np.diag([*s, 1.0])
    return _frozen(m)


_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def rotation(axis, degrees: float) -> np.ndarray:
    """Right-handed, active rotation by `degrees` about `axis` ('x', 'y', 'z' or a 3-vector)."""
    if isinstance(axis, str):
        if axis not in _AXES:
            raise ModelError(f"rotate: unknown axis {axis!r}; use 'x', 'y', 'z' or a 3-vector")
        axis = _AXES[axis]
    a = vector3(axis, "rotate axis")
    norm = np.linalg.norm(a)
    if norm == 0:
        raise ModelError("rotate: the axis must not be the zero vector")
    degrees = number(degrees, "rotate angle")
    x, y, z = a / norm
    th = np.radians(degrees)
    c, s, C = np.cos(th), np.sin(th), 1.0 - np.cos(th)
    m = np.eye(4)
    m[:3, :3] = [[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                 [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                 [z * x * C - y * s, z * y * C + x * s, c + z * z * C]]
    return _frozen(m)


def affine(matrix) -> np.ndarray:
    """Validate a user 4x4 (or 3x4) affine matrix: finite, last row (0,0,0,1), invertible."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise ModelError(f"transform: expected a 4x4 or 3x4 matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise ModelError("transform: the matrix has NaN or infinite entries")
    if np.abs(m[3] - _AFFINE_ROW).max() > 1e-8 + 1e-5:     # np.allclose's tolerances, without its cost
        raise ModelError(f"transform: the last row must be (0, 0, 0, 1) (affine), got {m[3].tolist()}")
    check_invertible(m, "transform")
    m = m.copy()
    m[3] = (0.0, 0.0, 0.0, 1.0)     # exactly affine: the kernel reads only the top 3x4
    return _frozen(m)


_AFFINE_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def check_invertible(m: np.ndarray, what: str) -> None:
    """Refuse a linear part that is singular relative to its own scale."""
    lin = m[:3, :3]
    # sigma_min / sigma_max >= |det| / |M|_F^3: most matrices pass this cheap bound (a
    # placement walk validates one per placed volume); the rest get their singular values.
    (a, b, c), (d, e, f), (g, h, i) = lin.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    frobenius = math.sqrt(a * a + b * b + c * c + d * d + e * e + f * f + g * g + h * h + i * i)
    if math.isfinite(det) and 0.0 < frobenius < 1e100 and abs(det) > 1e-12 * frobenius ** 3:
        return
    sv = np.linalg.svd(lin, compute_uv=False)
    if not np.all(np.isfinite(sv)) or sv[-1] <= sv[0] * 1e-12:
        raise ModelError(f"{what}: singular transform (singular values {sv.tolist()})")


def compose(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    if inner is IDENTITY:
        return outer
    if outer is IDENTITY:
        return inner
    return _frozen(outer @ inner)
