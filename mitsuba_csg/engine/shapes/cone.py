"""The canonical cone: radius p0 at z = -1 and p1 at z = +1, capped, |z| <= 1 (cylinders
and cones). Faces: 0 side, 1 bottom, 2 top."""
from __future__ import annotations

import drjit as dr
import numpy as np

from ..layout import CONE
from .row import Shape, disc_support, revolution_uv


# Acceptance slack for cone side/cap candidates near the rim (canonical units).
_RIM_SLACK = 1e-5


def interval(b, o, d, param, plane_buf, start, count):
    # Side: x^2 + y^2 = r(z)^2 with r(z) = a + c z, |z| <= 1; caps at z = -1 (radius p0), +1 (p1).
    p0, p1 = param[0], param[1]
    a, c = 0.5 * (p0 + p1), 0.5 * (p1 - p0)
    # Solve the side's quadratic from the ray's closest approach to the origin: from a far
    # origin, o.x^2 + o.y^2 - r^2 cancels catastrophically in float32 (a ray 700 radii away
    # was off by a third of the radius).
    t_near = -dr.dot(o, d) / dr.squared_norm(d)
    oc = o + t_near * d
    r_o = a + c * oc.z
    qa = d.x * d.x + d.y * d.y - c * c * d.z * d.z
    qb = 2.0 * (oc.x * d.x + oc.y * d.y - c * d.z * r_o)
    qc = oc.x * oc.x + oc.y * oc.y - r_o * r_o
    disc = qb * qb - 4.0 * qa * qc
    # A ray through the apex has disc = 0 exactly; rounding must not turn it into a miss.
    real = disc >= -1e-5 * (qb * qb + dr.abs(4.0 * qa * qc))
    sq = dr.sqrt(dr.maximum(disc, 0.0))
    q = -0.5 * (qb + dr.copysign(sq, qb))          # stable roots; qa == 0 gives the linear root
    # disc <= 0 within rounding: one double root (its two formulas would disagree).
    roots = (t_near + q / qa, t_near + dr.select(disc > 0, qc / q, q / qa))
    near, far = dr.full(b.Float, dr.inf, dr.width(qa)), dr.full(b.Float, -dr.inf, dr.width(qa))
    near_face = dr.zeros(b.UInt32, dr.width(qa))
    far_face = dr.zeros(b.UInt32, dr.width(qa))
    candidates = []
    for t in roots:
        z = o.z + t * d.z
        ok = real & (dr.abs(z) <= 1.0 + _RIM_SLACK) & (a + c * z >= -_RIM_SLACK) & dr.isfinite(t)
        candidates.append((t, ok, 0))
    for face, zc, rc in ((1, -1.0, p0), (2, 1.0, p1)):
        t = (zc - o.z) / d.z
        x, y = o.x + t * d.x, o.y + t * d.y
        ok = (d.z != 0) & (x * x + y * y <= rc * rc * (1.0 + _RIM_SLACK) + _RIM_SLACK * _RIM_SLACK) & (rc > 0)
        candidates.append((t, ok, face))
    for t, ok, face in candidates:
        better_near, better_far = ok & (t < near), ok & (t > far)
        near = dr.select(better_near, t, near)
        near_face = dr.select(better_near, b.UInt32(face), near_face)
        far = dr.select(better_far, t, far)
        far_face = dr.select(better_far, b.UInt32(face), far_face)
    return near, far, near_face, far_face


def surface(m, face, param, plane, x):
    zero = dr.zeros(m.Float, dr.width(x.x))
    a, c = 0.5 * (param[0] + param[1]), 0.5 * (param[1] - param[0])   # side 0, bottom 1, top 2
    r = a + c * x.z
    side_g = x.x * x.x + x.y * x.y - r * r
    side_grad = m.Array3f(2.0 * x.x, 2.0 * x.y, -2.0 * c * r)
    cap_sign = dr.select(face == 1, -1.0, 1.0)
    return (dr.select(face == 0, side_g, cap_sign * x.z - 1.0),
            dr.select(face == 0, side_grad, m.Array3f(zero, zero, cap_sign + zero)))


def bounds(A, c, param, plane_start, plane_vertices):
    axis = A[:, :, 2]                                  # hull of the two cap discs
    bottom_c, top_c = c - axis, c + axis
    disc = disc_support(A)
    bottom_h, top_h = param[:, 0:1] * disc, param[:, 1:2] * disc
    return (np.minimum(bottom_c - bottom_h, top_c - top_h), np.maximum(bottom_c + bottom_h, top_c + top_h))


SHAPE = Shape(CONE, "cone", convex=True, interval=interval, surface=surface, bounds=bounds, uv=revolution_uv)
