"""The canonical box: the cube [-1, 1]^3. Face 2 axis + (1 on the + side)."""
from __future__ import annotations

import drjit as dr
import numpy as np

from ..layout import BOX
from .row import Shape


def interval(b, o, d, param, plane_buf, start, count):
    near, far = dr.full(b.Float, -dr.inf, dr.width(o.x)), dr.full(b.Float, dr.inf, dr.width(o.x))
    near_face = dr.zeros(b.UInt32, dr.width(o.x))
    far_face = dr.zeros(b.UInt32, dr.width(o.x))
    for axis in range(3):
        oa, da = o[axis], d[axis]
        parallel = da == 0
        inv = 1.0 / dr.select(parallel, 1.0, da)
        t_minus, t_plus = (-1.0 - oa) * inv, (1.0 - oa) * inv
        inside_slab = dr.abs(oa) <= 1.0
        lo = dr.select(parallel, dr.select(inside_slab, -dr.inf, dr.inf), dr.minimum(t_minus, t_plus))
        hi = dr.select(parallel, dr.select(inside_slab, dr.inf, -dr.inf), dr.maximum(t_minus, t_plus))
        enter_face = b.UInt32(2 * axis) + dr.select(da < 0, 1, 0)   # d>0 enters the - face
        exit_face = b.UInt32(2 * axis) + dr.select(da < 0, 0, 1)
        better_near, better_far = lo > near, hi < far
        near = dr.select(better_near, lo, near)
        near_face = dr.select(better_near, enter_face, near_face)
        far = dr.select(better_far, hi, far)
        far_face = dr.select(better_far, exit_face, far_face)
    return near, far, near_face, far_face


def surface(m, face, param, plane, x):
    zero = dr.zeros(m.Float, dr.width(x.x))
    axis, plus = face // 2, (face & 1) == 1           # face 2*axis + side
    sign = dr.select(plus, 1.0, -1.0)
    coord = dr.select(axis == 0, x.x, dr.select(axis == 1, x.y, x.z))
    unit = m.Array3f(dr.select(axis == 0, sign, zero), dr.select(axis == 1, sign, zero),
                     dr.select(axis == 2, sign, zero))
    return sign * coord - 1.0, unit


def bounds(A, c, param, plane_start, plane_vertices):
    half = np.abs(A).sum(axis=2)
    return c - half, c + half


def uv(hit):
    """As Mitsuba's `cube` lays its texture out: per face (-x, +x, -y, +y, -z, +z), u and v
    run along these signed canonical axes."""
    b, x, face = hit.b, hit.x, hit.face
    zero = hit.zero()
    ex, ey, ez = (b.Array3f(2.0, 0.0, 0.0) + zero, b.Array3f(0.0, 2.0, 0.0) + zero,
                  b.Array3f(0.0, 0.0, 2.0) + zero)

    def per_face(values):
        out = values[5]
        for k in range(4, -1, -1):
            out = dr.select(face == k, values[k], out)
        return out
    u = per_face([x.y, x.y, x.z, -x.x, -x.y, x.y])
    v = per_face([x.z, -x.z, x.x, -x.z, x.x, x.x])
    du = per_face([ey, ey, ez, -ex, -ey, ey])
    dv = per_face([ez, -ez, ex, -ez, ex, ex])
    return b.module.Array2f(0.5 * (u + 1.0), 0.5 * (v + 1.0)), du, dv


SHAPE = Shape(BOX, "box", convex=True, interval=interval, surface=surface, bounds=bounds, uv=uv)
