"""Rays against axis-aligned boxes: the slab test every traversal step uses."""
from __future__ import annotations

import drjit as dr


def inverse_direction(b, d):
    """1 / d per component for slab tests; a zero component becomes a huge number of its sign,
    so that the slab of a ray parallel to it is all or nothing."""
    return b.Array3f([dr.select(d[i] == 0, dr.copysign(1e30, d[i]), 1.0 / d[i]) for i in range(3)])


def box_entry(lower, upper, o, inv_d):
    """(near, far) of the ray's parameter inside the box (lower.xyz, upper.xyz).

    Comparisons and selects, not dr.minimum / dr.maximum: those propagate NaN, which costs
    several instructions each on a CPU. A box stored as NaN (empty) has NaN near and far
    either way, so `near <= far` rejects it.
    """
    near, far = [], []
    for i in range(3):
        t1, t2 = (lower[i] - o[i]) * inv_d[i], (upper[i] - o[i]) * inv_d[i]
        closer = t1 < t2
        near.append(dr.select(closer, t1, t2))
        far.append(dr.select(closer, t2, t1))
    return _larger(_larger(near[0], near[1]), near[2]), _smaller(_smaller(far[0], far[1]), far[2])


def _larger(a, c):
    return dr.select(a > c, a, c)


def _smaller(a, c):
    return dr.select(a < c, a, c)
