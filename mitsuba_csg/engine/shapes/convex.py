"""The canonical convex polyhedron: an intersection of half-spaces (the primitive's planes).
Face: the plane's index within the primitive."""
from __future__ import annotations

import drjit as dr

from ..layout import CONVEX
from .row import Shape, plane_surface, plane_uv, vertex_bounds


@dr.syntax
def interval_normals(b, o, d, param, plane_buf, start, count):
    """The interval, and the planes' normals of its ends (for the events' slopes: tracking
    them here is cheaper than a second gather for every leaf event of every shape)."""
    near = dr.full(b.Float, -dr.inf, dr.width(start))
    far = dr.full(b.Float, dr.inf, dr.width(start))
    near_face = dr.zeros(b.UInt32, dr.width(start))
    far_face = dr.zeros(b.UInt32, dr.width(start))
    near_normal = dr.zeros(b.Array3f, dr.width(start))
    far_normal = dr.zeros(b.Array3f, dr.width(start))
    k = dr.zeros(b.UInt32, dr.width(start))
    while dr.hint(k < count, label="csg_convex_planes", exclude=[o, d, plane_buf, start, count]):
        plane = dr.gather(b.Array4f, plane_buf, start + k)
        n = b.Array3f(plane.x, plane.y, plane.z)
        denom = dr.dot(n, d)
        dist = plane.w - dr.dot(n, o)
        t = dist / denom
        entering, leaving = denom < 0, denom > 0
        better_near = entering & (t > near)
        near = dr.select(better_near, t, near)
        near_face = dr.select(better_near, k, near_face)
        near_normal = dr.select(better_near, n, near_normal)
        better_far = leaving & (t < far)
        far = dr.select(better_far, t, far)
        far_face = dr.select(better_far, k, far_face)
        far_normal = dr.select(better_far, n, far_normal)
        outside_parallel = (denom == 0) & (dist < 0)
        near = dr.select(outside_parallel, dr.inf, near)
        k += 1
    return near, far, near_face, far_face, near_normal, far_normal


SHAPE = Shape(CONVEX, "convex", convex=True, interval_normals=interval_normals, surface=plane_surface,
              bounds=vertex_bounds, uv=plane_uv)
