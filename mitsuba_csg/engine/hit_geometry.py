"""Geometry of a found hit: its world normal (detached or differentiable) and its surface
coordinates (uv and tangents, detached).

The automaton finds the winning primitive and face with detached arithmetic. `hit_normal`
evaluates the face's surface gradient there; `attached_hit` recomputes t, position and
normal with Dr.Jit's AD types from the primitives' canonical-to-world matrices (which may
carry gradients), by one Newton step on the face's implicit function g(x(t)) = 0 at the
detached t: its value stays the detached t, and its derivative is the implicit-function
one, dt = -dg / (grad g . dx/dt). This gives interior derivatives; a change of the visible
primitive (silhouettes, CSG edges) is not differentiated.
"""
from __future__ import annotations

import drjit as dr

from . import layout as K
from .backend import ad_module
from .device import gather_prim, opaque, scene_rays
from .shapes import CanonicalHit, surface_coordinates_local, surface_function


def _normal_to_world(m, rows, n_local):
    """Normals transform with the inverse transpose of canonical -> world: n = M^T n_local,
    where `rows` are the rows of M = the linear part of world -> canonical."""
    return m.Array3f(*(rows[0][i] * n_local.x + rows[1][i] * n_local.y + rows[2][i] * n_local.z
                       for i in range(3)))


def _face_plane(m, planes, shape, plane_start, info, active):
    """The plane of the hit face of convex primitives and meshes (ignored for the other shapes)."""
    face = K.info_face(info)
    return face, dr.gather(m.Array4f, planes, plane_start + face, active & ((shape == K.CONVEX) | (shape == K.MESH)))


def _hit_in_primitive(tree, prim, info, o, d, t, active):
    """The hit at o + t d in primitive `prim`'s canonical frame: (rows of scene -> canonical,
    the hit there (`shapes.CanonicalHit`: point, shape, params, face, face plane, surface
    gradient, ...), the ray's unit direction in the scene frame, the face's implicit function
    there)."""
    b = tree.b
    record = gather_prim(b, tree, prim, active)
    rows, shape, param, plane_start = record.rows, record.shape, record.param, record.plane_start
    o, d, k = scene_rays(tree, o, d)
    p = o + (t * k) * d
    p4 = b.Array4f(p.x, p.y, p.z, 1.0)
    x = b.Array3f(dr.dot(rows[0], p4), dr.dot(rows[1], p4), dr.dot(rows[2], p4))
    face, plane = _face_plane(b.module, tree.planes, shape, plane_start, info, active)
    g, grad = surface_function(b.module, shape, face, param, plane, x)
    hit = CanonicalHit(b, x, shape, param, face, plane, grad, tree=tree, plane_start=plane_start, info=info,
                       active=active)
    return rows, hit, d, g


def _solid_normal(b, rows, n_local, info, d, active):
    """The world-space outward unit normal of the CSG solid from a face's canonical gradient."""
    n = _normal_to_world(b, rows, n_local)
    n = dr.select(K.info_flipped(info), -n, n) * dr.rsqrt(dr.squared_norm(n))
    # At a cone apex the surface has no normal: face the ray (outward for its hit class).
    facing = dr.normalize(dr.select(K.info_class(info) == K.ENTER, -d, d))
    n = dr.select(dr.isfinite(n.x) & dr.isfinite(n.y) & dr.isfinite(n.z), n, facing)
    return dr.select(active, n, 0.0)


def hit_normal(tree, prim, info, o, d, t, active):
    """World-space outward unit normal of the CSG solid at o + t d on primitive `prim`
    (zero where not `active`)."""
    def normal(prim, info, o, d, t, active):
        rows, hit, d_scene, _ = _hit_in_primitive(tree, prim, info, o, d, t, active)
        return _solid_normal(tree.b, rows, hit.grad, info, d_scene, active)

    def none(prim, info, o, d, t, active):
        return dr.zeros(tree.b.Array3f, dr.width(t))
    # A branch, not a masked evaluation: packets of rays that all missed (most camera rays
    # of a small model, the sky in a path tracer) skip the gathers and the surface gradient.
    # City-3385 primary rays: 1.3 ms of 17.7 ms a frame.
    return dr.if_stmt((prim, info, o, d, t, active), active, normal, none, mode="symbolic")


def face_at(tree, prim, info, o, d, t, active):
    """(normal, residual) of face `info` of primitive `prim` at o + t d: the normal as
    `hit_normal` gives it, and how far the point lies off the face's surface, |g| / |grad g|
    of its implicit function in the primitive's canonical frame (about the distance from the
    surface there, in units of the canonical shape, near it). Tells whether a face found
    along one ray passes through a point of another (the point of an edge)."""
    rows, hit, d, g = _hit_in_primitive(tree, prim, info, o, d, t, active)
    residual = dr.select(active, dr.abs(g) * dr.rsqrt(dr.squared_norm(hit.grad)), dr.inf)
    return _solid_normal(tree.b, rows, hit.grad, info, d, active), residual


def attached_hit(to_world, tree, prim, info, t, o, d, active):
    """(t, p, n) with AD: `to_world` holds 12 floats per primitive (canonical -> world rows).

    `prim`, `info` and `t` come from the detached traversal; o and d are the (AD) rays.
    """
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
    record = gather_prim(b, tree, b.UInt32(dr.detach(prim)), b.Bool(dr.detach(active)))
    shape, plane_start = m.UInt32(record.shape), m.UInt32(record.plane_start)
    param = (m.Float(record.param[0]), m.Float(record.param[1]))
    info = m.UInt32(dr.detach(info))
    face, plane = _face_plane(m, m.Float(tree.planes), shape, plane_start, info, active)
    t_det = m.Float(dr.detach(t))
    x = o_c + t_det * d_c
    g, grad = surface_function(m, shape, face, param, plane, x)
    slope = dr.dot(grad, d_c)
    step = g / slope
    t_att = dr.select(dr.isfinite(step) & (slope != 0), t_det - step, t_det)
    x = o_c + t_att * d_c
    _, grad = surface_function(m, shape, face, param, plane, x)
    n = _normal_to_world(m, inv, grad)
    n = dr.select(K.info_flipped(info), -n, n) * dr.rsqrt(dr.squared_norm(n))
    p = m.Array3f(o) + t_att * m.Array3f(d)
    return t_att, p, n


def surface_coordinates(tree, prim, info, o, d, t, active):
    """(uv, dp_du, dp_dv) of the hit at o + t d on primitive `prim`, derivatives in world space.

    Each canonical shape has a parameterization (its row's `uv` in `engine.shapes`;
    docs/plugins.md): spheres as Mitsuba's `sphere` (u = phi / 2 pi, v = theta / pi), the
    sides of cylinders, cones and quadrics as Mitsuba's `cylinder` (u = phi / 2 pi, v up the
    axis from 0 to 1), box faces as Mitsuba's `cube`, caps planar from 0 to 1 across, the torus
    by its two angles, convex faces by a frame in their plane, mesh triangles by barycentric
    coordinates as Mitsuba's meshes without texture coordinates. Shading frames follow dp_du,
    so anisotropic BSDFs and normal maps have a tangent.
    """
    b = tree.b
    m = b.module
    rows, hit, _, _ = _hit_in_primitive(tree, prim, info, o, d, t, active)
    uv, du, dv = surface_coordinates_local(hit)
    # Tangents map with canonical -> world: the inverse of the rows' linear part, then the
    # scene frame's scale.
    A = m.Matrix3f(rows[0].x, rows[0].y, rows[0].z, rows[1].x, rows[1].y, rows[1].z,
                   rows[2].x, rows[2].y, rows[2].z)
    to_world = dr.rcp(A) * (1.0 / opaque(tree, b.Float, tree.inv_scale))
    dp_du, dp_dv = to_world @ du, to_world @ dv
    return (dr.select(active, uv, 0.0), dr.select(active, dp_du, 0.0), dr.select(active, dp_dv, 0.0))
