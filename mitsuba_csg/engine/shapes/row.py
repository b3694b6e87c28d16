"""The row of one canonical shape (`Shape`) and the helpers several rows share."""
from __future__ import annotations

from typing import Callable

import drjit as dr
import numpy as np

from ..layout import ENTER, EXIT, MISS


class Shape:
    """One canonical shape: everything the engine knows of it, in the shape's own module.

    A plain class on purpose: Dr.Jit's symbolic `if` treats dataclasses and tuples it reads
    as loop state (PyTrees), and a row is constant.
    """

    __slots__ = ("code", "name", "convex", "interval", "interval_normals", "event", "event_normal", "surface",
                 "bounds", "uv")

    def __init__(self, code: int, name: str, *, convex: bool, surface: Callable, bounds: Callable, uv: Callable,
                 interval: Callable | None = None, interval_normals: Callable | None = None,
                 event: Callable | None = None, event_normal: bool = False):
        self.code = code              # engine.layout shape code
        self.name = name              # the canonical shape's name (Primitive.canonical_shape)
        self.convex = convex          # its inside along a ray is one interval
        # How the kernel finds its first event after t_start (`first_event`), one of:
        self.interval = interval      # (b, o, d, param, planes, start, count) -> (near, far, near face, far face)
        self.interval_normals = interval_normals   # ... and the two faces' plane normals
        self.event = event            # (b, o, d, param, planes, start, mesh, t_start) -> (t, face, class[, normal])
        self.event_normal = event_normal   # `event` also returns the face's plane normal
        self.surface = surface        # (m, face, param, plane, x) -> (g, grad g), Dr.Jit detached or AD
        self.bounds = bounds          # (A, c, param, plane_start, plane_vertices) -> (lower, upper), numpy
        self.uv = uv                  # (hit: CanonicalHit) -> (uv, dx/du, dx/dv) in the canonical frame


class CanonicalHit:
    """Hits in their primitives' canonical frames, as the rows' `uv` read them: the point
    `x`, the primitive's `shape` code and `param`, the `face`, the face's `plane` (convex
    shapes and meshes), the surface gradient `grad` there, and what a mesh needs: the `tree`,
    the primitive's `plane_start`, the hit's `info`, and `active`."""

    __slots__ = ("b", "x", "shape", "param", "face", "plane", "grad", "tree", "plane_start", "info", "active")

    def __init__(self, b, x, shape, param, face, plane, grad, *, tree, plane_start, info, active):
        self.b, self.x, self.shape, self.param, self.face, self.plane, self.grad = b, x, shape, param, face, plane, grad
        self.tree, self.plane_start, self.info, self.active = tree, plane_start, info, active

    def zero(self):
        return dr.zeros(self.b.Float, dr.width(self.x.x))

    def phi(self):
        """The angle about the z axis, in [0, 2 pi)."""
        phi = dr.atan2(self.x.y, self.x.x)
        return dr.select(phi < 0, phi + 2.0 * dr.pi, phi)

    def around(self):
        """d/du of a point turning about the z axis once as u goes from 0 to 1."""
        return 2.0 * dr.pi * self.b.Array3f(-self.x.y, self.x.x, self.zero())

    def rho(self):
        return dr.sqrt(self.x.x * self.x.x + self.x.y * self.x.y)


def interval_event(b, near, far, near_face, far_face, t_start):
    """First event after t_start of a convex interval [near, far] (empty if near >= far)."""
    hit = near < far
    take_near = hit & (near > t_start)
    take_far = hit & ~take_near & (far > t_start)
    t = dr.select(take_near, near, dr.select(take_far, far, dr.inf))
    face = dr.select(take_near, near_face, far_face)
    cls = dr.select(take_near, b.UInt32(ENTER), dr.select(take_far, b.UInt32(EXIT), b.UInt32(MISS)))
    return t, face, cls


def disc_support(A):
    """Support of the unit disc in z = 0 under A, per world axis."""
    return np.sqrt(A[:, :, 0] ** 2 + A[:, :, 1] ** 2)


def revolution_uv(hit: CanonicalHit):
    """(uv, dx/du, dx/dv) of a surface of revolution about z (cone and quadric sides as
    Mitsuba's `cylinder`: u = phi / 2 pi, v up the axis from 0 to 1) and its planar caps
    ([-1, 1]^2 -> [0, 1]^2)."""
    b, x, grad = hit.b, hit.x, hit.grad
    m = b.module
    phi, zero = hit.phi(), hit.zero()
    cos_phi, sin_phi = dr.cos(phi), dr.sin(phi)
    # Up the profile, d rho / dz = -g_z / g_rho.
    g_rho = grad.x * cos_phi + grad.y * sin_phi
    slope = dr.select(g_rho != 0, -grad.z / g_rho, 0.0)
    up_profile = 2.0 * b.Array3f(slope * cos_phi, slope * sin_phi, 1.0)       # z = 2 v - 1
    uv_cap = m.Array2f(0.5 * (x.x + 1.0), 0.5 * (x.y + 1.0))
    du_cap, dv_cap = b.Array3f(2.0, 0.0, 0.0) + zero, b.Array3f(0.0, 2.0, 0.0) + zero
    side = hit.face == 0
    uv_side = m.Array2f(phi / (2.0 * dr.pi), 0.5 * (x.z + 1.0))
    return (dr.select(side, uv_side, uv_cap), dr.select(side, hit.around(), du_cap),
            dr.select(side, up_profile, dv_cap))


def plane_uv(hit: CanonicalHit):
    """(uv, dx/du, dx/dv) on a planar face: a frame in the face's plane, its first axis from
    the least aligned axis."""
    b, x, plane = hit.b, hit.x, hit.plane
    zero = hit.zero()
    n_f = b.Array3f(plane.x, plane.y, plane.z)
    helper = dr.select(dr.abs(n_f.x) < 0.9, b.Array3f(1.0, 0.0, 0.0) + zero, b.Array3f(0.0, 1.0, 0.0) + zero)
    du = dr.normalize(dr.cross(helper, n_f))
    dv = dr.cross(n_f, du)
    return b.module.Array2f(dr.dot(x, du), dr.dot(x, dv)), du, dv


def vertex_bounds(A, c, param, plane_start, plane_vertices):
    """World boxes of polyhedra (convex shapes, meshes) from their canonical vertices."""
    lower, upper = np.empty_like(c), np.empty_like(c)
    for start, verts in plane_vertices.items():
        m = plane_start == start
        world = np.einsum("nij,vj->nvi", A[m], verts) + c[m][:, None, :]
        lower[m], upper[m] = world.min(axis=1), world.max(axis=1)
    return lower, upper


def plane_surface(m, face, param, plane, x):
    """(g, grad g) of a planar face (convex shapes, mesh triangles)."""
    n = m.Array3f(plane.x, plane.y, plane.z)           # the face's plane
    return dr.dot(n, x) - plane.w, n
