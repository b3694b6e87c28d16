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
from .kernel import FLIP_BIT


def ad_module(array):
    """drjit.llvm.ad or drjit.cuda.ad for a Dr.Jit array."""
    backend = dr.backend_v(type(array))
    return sys.modules["drjit.llvm.ad" if backend == dr.JitBackend.LLVM else "drjit.cuda.ad"]


def implicit(m, shape, face, param, plane, x):
    """(g, grad g) of the hit face in canonical coordinates; g = 0 on the surface, < 0 inside."""
    zero = dr.zeros(m.Float, dr.width(x.x))
    # sphere
    g = dr.squared_norm(x) - 1.0
    grad = 2.0 * x
    # box: face 2*axis + side
    axis, plus = face // 2, (face & 1) == 1
    sign = dr.select(plus, 1.0, -1.0)
    coord = dr.select(axis == 0, x.x, dr.select(axis == 1, x.y, x.z))
    unit = m.Array3f(dr.select(axis == 0, sign, zero), dr.select(axis == 1, sign, zero),
                     dr.select(axis == 2, sign, zero))
    box_g = sign * coord - 1.0
    # cone: side 0, bottom 1, top 2
    a, c = 0.5 * (param[0] + param[1]), 0.5 * (param[1] - param[0])
    r = a + c * x.z
    side_g = x.x * x.x + x.y * x.y - r * r
    side_grad = m.Array3f(2.0 * x.x, 2.0 * x.y, -2.0 * c * r)
    cap_sign = dr.select(face == 1, -1.0, 1.0)
    cone_g = dr.select(face == 0, side_g, cap_sign * x.z - 1.0)
    cone_grad = dr.select(face == 0, side_grad, m.Array3f(zero, zero, cap_sign + zero))
    # torus (major 1, minor k)
    k = param[0]
    s = dr.squared_norm(x) + 1.0 - k * k
    torus_g = s * s - 4.0 * (x.x * x.x + x.y * x.y)
    torus_grad = m.Array3f(4.0 * s * x.x - 8.0 * x.x, 4.0 * s * x.y - 8.0 * x.y, 4.0 * s * x.z)
    # convex polyhedron: the face's plane
    n = m.Array3f(plane.x, plane.y, plane.z)
    plane_g = dr.dot(n, x) - plane.w
    g = dr.select(shape == P.BOX, box_g, g)
    grad = dr.select(shape == P.BOX, unit, grad)
    g = dr.select(shape == P.CONE, cone_g, g)
    grad = dr.select(shape == P.CONE, cone_grad, grad)
    g = dr.select(shape == P.TORUS, torus_g, g)
    grad = dr.select(shape == P.TORUS, torus_grad, grad)
    g = dr.select(shape == P.CONVEX, plane_g, g)
    grad = dr.select(shape == P.CONVEX, n, grad)
    return g, grad


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
    g, grad = implicit(m, shape, face, param, plane, x)
    slope = dr.dot(grad, d_c)
    step = g / slope
    t_att = dr.select(dr.isfinite(step) & (slope != 0), t_det - step, t_det)
    x = o_c + t_att * d_c
    _, grad = implicit(m, shape, face, param, plane, x)
    # normals transform with the inverse transpose of canonical -> world
    n = m.Array3f(*(inv[0][i] * grad.x + inv[1][i] * grad.y + inv[2][i] * grad.z for i in range(3)))
    n = n * dr.rsqrt(dr.squared_norm(n))
    n = dr.select((m.UInt32(dr.detach(info)) & FLIP_BIT) != 0, -n, n)
    p = m.Array3f(o) + t_att * m.Array3f(d)
    return t_att, p, n
