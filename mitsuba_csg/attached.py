"""Differentiable hit geometry: t, position and normal of the winning primitive, attached.

The traversal finds the winning primitive and face with detached arithmetic. Here the hit
is recomputed with Dr.Jit's AD types from the primitives' canonical-to-world matrices
(which may carry gradients), by one Newton step on the face's implicit function
g(x(t)) = 0 at the detached t: its value stays the detached t, and its derivative is the
implicit-function one, dt = -dg / (grad g . dx/dt). This gives interior derivatives; a
change of the visible primitive (silhouettes, CSG edges) is not differentiated.
"""
from __future__ import annotations

import sys

import drjit as dr

from . import primitives as P
from .intersect import surface_function
from .kernel import FLIP_BIT


def ad_module(array):
    """drjit.llvm.ad or drjit.cuda.ad for a Dr.Jit array."""
    backend = dr.backend_v(type(array))
    return sys.modules["drjit.llvm.ad" if backend == dr.JitBackend.LLVM else "drjit.cuda.ad"]


def attached_hit(to_world, tree, prim, info, t, o, d, active):
    """(t, p, n) with AD: `to_world` holds 12 floats per primitive (canonical -> world rows).

    `prim`, `info` and `t` come from the detached traversal; o and d are the (AD) rays.
    """
    from .kernel import gather_prim
    m = ad_module(to_world)
    rows = [dr.gather(m.Array4f, to_world, prim * 3 + r, active) for r in range(3)]
    A = m.Matrix3f(rows[0].x, rows[0].y, rows[0].z,
                   rows[1].x, rows[1].y, rows[1].z,
                   rows[2].x, rows[2].y, rows[2].z)
    centre = m.Array3f(rows[0].w, rows[1].w, rows[2].w)
    inv = dr.rcp(A)                 # the matrix inverse (dr.inverse is deprecated)
    o_c = inv @ (m.Array3f(o) - centre)
    d_c = inv @ m.Array3f(d)
    b = tree.b
    _, shape, param, plane_start, _ = gather_prim(b, tree, b.UInt32(dr.detach(prim)), b.Bool(dr.detach(active)))
    shape, plane_start = m.UInt32(shape), m.UInt32(plane_start)
    param = (m.Float(param[0]), m.Float(param[1]))
    face = m.UInt32(dr.detach(info)) >> 3
    plane = dr.gather(m.Array4f, m.Float(tree.planes), plane_start + face, active & (shape == P.CONVEX))
    t_det = m.Float(dr.detach(t))
    x = o_c + t_det * d_c
    g, grad = surface_function(m, shape, face, param, plane, x)
    slope = dr.dot(grad, d_c)
    step = g / slope
    t_att = dr.select(dr.isfinite(step) & (slope != 0), t_det - step, t_det)
    x = o_c + t_att * d_c
    _, grad = surface_function(m, shape, face, param, plane, x)
    # normals transform with the inverse transpose of canonical -> world
    n = m.Array3f(*(inv[0][i] * grad.x + inv[1][i] * grad.y + inv[2][i] * grad.z for i in range(3)))
    n = n * dr.rsqrt(dr.squared_norm(n))
    n = dr.select((m.UInt32(dr.detach(info)) & FLIP_BIT) != 0, -n, n)
    p = m.Array3f(o) + t_att * m.Array3f(d)
    return t_att, p, n
