"""The canonical sphere: the unit ball. Face 0."""
from __future__ import annotations

import drjit as dr
import numpy as np

from ..layout import SPHERE
from .row import Shape


def interval(b, o, d, param, plane_buf, start, count):
    a = dr.squared_norm(d)
    tc = -dr.dot(o, d) / a
    pc = o + tc * d                      # closest approach: robust for far-away origins
    h2 = (1.0 - dr.squared_norm(pc)) / a
    h = dr.sqrt(dr.maximum(h2, 0.0))
    near = dr.select(h2 > 0, tc - h, dr.inf)
    far = dr.select(h2 > 0, tc + h, -dr.inf)
    face = dr.zeros(b.UInt32, dr.width(a))
    return near, far, face, face


def surface(m, face, param, plane, x):
    return dr.squared_norm(x) - 1.0, 2.0 * x


def bounds(A, c, param, plane_start, plane_vertices):
    half = np.linalg.norm(A, axis=2)                   # |A_i.|: support of the unit ball
    return c - half, c + half


def uv(hit):
    """As Mitsuba's `sphere`: u = phi / 2 pi, v = theta / pi."""
    b, x = hit.b, hit.x
    phi = hit.phi()
    theta = dr.acos(dr.clip(x.z, -1.0, 1.0))
    dv = dr.pi * b.Array3f(x.z * dr.cos(phi), x.z * dr.sin(phi), -dr.sin(theta))
    return b.module.Array2f(phi / (2.0 * dr.pi), theta / dr.pi), hit.around(), dv


SHAPE = Shape(SPHERE, "sphere", convex=True, interval=interval, surface=surface, bounds=bounds, uv=uv)
