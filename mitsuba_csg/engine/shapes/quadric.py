"""The canonical quadric of revolution x^2 + y^2 <= a z^2 + b z + c, |z| <= 1 (paraboloids,
hyperboloids; params (a, b), c = 1 - a - |b|, so that its widest cap has radius 1). Not
convex: along a line its side region is up to two intervals, each clipped to the slab, and
its events are those of the two pieces in order (touching pieces merged), so enter and exit
still alternate. Faces: 0 side, 1 bottom, 2 top."""
from __future__ import annotations

import drjit as dr
import numpy as np

from ..layout import MISS, QUADRIC
from .row import Shape, disc_support, interval_event, revolution_uv


def _event(b, o, d, param, t_start):
    """(t, face, class) of the canonical quadric's first event after t_start."""
    a, c_lin = param[0], param[1]
    c0 = 1.0 - a - dr.abs(c_lin)
    width = dr.width(a)
    inf = dr.full(b.Float, dr.inf, width)
    # The side's quadratic from the ray's closest approach to the origin (as for the cone).
    t_near = -dr.dot(o, d) / dr.squared_norm(d)
    oc = o + t_near * d
    qa = d.x * d.x + d.y * d.y - a * d.z * d.z
    qb = 2.0 * (oc.x * d.x + oc.y * d.y - a * oc.z * d.z) - c_lin * d.z
    qc = oc.x * oc.x + oc.y * oc.y - a * oc.z * oc.z - c_lin * oc.z - c0
    disc = qb * qb - 4.0 * qa * qc
    real = disc >= 0.0
    sq = dr.sqrt(dr.maximum(disc, 0.0))
    q = -0.5 * (qb + dr.copysign(sq, qb))
    ra = t_near + q / qa
    rb = t_near + dr.select(disc > 0, qc / q, q / qa)
    lo, hi = dr.minimum(ra, rb), dr.maximum(ra, rb)
    linear_root = t_near - qc / qb
    # The side region {f <= 0} along the line: [l1, h1] and [l2, h2] (empty: l > h).
    bounded = (qa > 0) & real
    split = (qa < 0) & real                       # two half-lines
    everywhere = ((qa < 0) & ~real) | ((qa == 0) & (qb == 0) & (qc <= 0))
    rising = (qa == 0) & (qb > 0)                 # f grows along the ray: inside before the root
    falling = (qa == 0) & (qb < 0)
    l1 = dr.select(bounded, lo, dr.select(split | everywhere | rising, -dr.inf, dr.select(falling, linear_root, inf)))
    h1 = dr.select(bounded, hi, dr.select(split, lo, dr.select(everywhere | falling, inf,
                                                             dr.select(rising, linear_root, -dr.inf))))
    l2 = dr.select(split, hi, inf)
    h2 = dr.select(split, inf, -dr.inf)
    # The slab |z| <= 1 and the caps through which the ray enters and leaves it.
    flat = d.z == 0
    inv_dz = 1.0 / dr.select(flat, 1.0, d.z)
    ta, tb = (-1.0 - o.z) * inv_dz, (1.0 - o.z) * inv_dz
    in_slab = dr.abs(o.z) <= 1.0
    s_in = dr.select(flat, dr.select(in_slab, -dr.inf, inf), dr.minimum(ta, tb))
    s_out = dr.select(flat, dr.select(in_slab, inf, -dr.inf), dr.maximum(ta, tb))
    up = d.z > 0
    cap_in, cap_out = dr.select(up, b.UInt32(1), b.UInt32(2)), dr.select(up, b.UInt32(2), b.UInt32(1))
    n1, f1 = dr.maximum(l1, s_in), dr.minimum(h1, s_out)
    n2, f2 = dr.maximum(l2, s_in), dr.minimum(h2, s_out)
    face_n1, face_f1 = dr.select(l1 > s_in, b.UInt32(0), cap_in), dr.select(h1 < s_out, b.UInt32(0), cap_out)
    face_n2, face_f2 = dr.select(l2 > s_in, b.UInt32(0), cap_in), dr.select(h2 < s_out, b.UInt32(0), cap_out)
    # Pieces that touch (a ray tangent inside the side) are one piece: no exit-enter pair.
    touch = (n1 < f1) & (n2 < f2) & (n2 <= f1)
    f1 = dr.select(touch, f2, f1)
    face_f1 = dr.select(touch, face_f2, face_f1)
    n2 = dr.select(touch, inf, n2)
    t, face, cls = interval_event(b, n1, f1, face_n1, face_f1, t_start)
    t2, face2, cls2 = interval_event(b, n2, f2, face_n2, face_f2, t_start)
    second = cls == MISS
    return dr.select(second, t2, t), dr.select(second, face2, face), dr.select(second, cls2, cls)


def event(b, o, d, param, plane_buf, start, mesh, t_start):
    return _event(b, o, d, param, t_start)


def surface(m, face, param, plane, x):
    zero = dr.zeros(m.Float, dr.width(x.x))
    a, c_lin = param[0], param[1]                      # side 0, bottom 1, top 2
    c0 = 1.0 - a - dr.abs(c_lin)
    side_g = x.x * x.x + x.y * x.y - a * x.z * x.z - c_lin * x.z - c0
    side_grad = m.Array3f(2.0 * x.x, 2.0 * x.y, -2.0 * a * x.z - c_lin)
    cap_sign = dr.select(face == 1, -1.0, 1.0)
    return (dr.select(face == 0, side_g, cap_sign * x.z - 1.0),
            dr.select(face == 0, side_grad, m.Array3f(zero, zero, cap_sign + zero)))


def bounds(A, c, param, plane_start, plane_vertices):
    # Per world axis, the support max_z (p z + w rho(z)) over |z| <= 1, with p the axis' z
    # weight and w the norm of its xy weights: rho = sqrt(a z^2 + b z + c) bulges past the
    # hull of the cap circles (a paraboloid's does), so the maximum may lie between the caps,
    # where p rho = -w rho' (squared: a quadratic in z). Its real roots in [-1, 1] and the ends
    # are the candidates; extra roots from squaring are harmless (any z gives a lower bound).
    a, b = param[:, 0:1], param[:, 1:2]
    c0 = 1.0 - a - np.abs(b)
    w = disc_support(A)                               # (n, 3)

    def support(p):
        qa = 4.0 * a * (p * p - w * w * a)
        qb = 4.0 * b * (p * p - w * w * a)
        qc = 4.0 * p * p * c0 - w * w * b * b
        disc = qb * qb - 4.0 * qa * qc
        sq = np.sqrt(np.maximum(disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            linear = np.where(qb != 0, -qc / qb, 0.0)
            z1 = np.where(qa != 0, (-qb - sq) / (2.0 * qa), linear)
            z2 = np.where(qa != 0, (-qb + sq) / (2.0 * qa), linear)
        best = np.full(p.shape, -np.inf)
        for z in (np.full(p.shape, -1.0), np.full(p.shape, 1.0), z1, z2):
            z = np.clip(np.nan_to_num(z), -1.0, 1.0)
            best = np.maximum(best, p * z + w * np.sqrt(np.maximum(a * z * z + b * z + c0, 0.0)))
        return best

    p = A[:, :, 2]
    return c - support(-p), c + support(p)


SHAPE = Shape(QUADRIC, "quadric", convex=False, event=event, surface=surface, bounds=bounds, uv=revolution_uv)
