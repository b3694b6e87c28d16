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
from .shapes import surface_function


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
    shape, params, plane start, canonical point, face, face plane, surface gradient there,
    the ray's unit direction in the scene frame, the face's implicit function there)."""
    b = tree.b
    rows, shape, param, plane_start, _ = gather_prim(b, tree, prim, active)
    o, d, k = scene_rays(tree, o, d)
    p = o + (t * k) * d
    p4 = b.Array4f(p.x, p.y, p.z, 1.0)
    x = b.Array3f(dr.dot(rows[0], p4), dr.dot(rows[1], p4), dr.dot(rows[2], p4))
    face, plane = _face_plane(b.module, tree.planes, shape, plane_start, info, active)
    g, grad = surface_function(b.module, shape, face, param, plane, x)
    return rows, shape, param, plane_start, x, face, plane, grad, d, g


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
        rows, _, _, _, _, _, _, n_local, d_scene, _ = _hit_in_primitive(tree, prim, info, o, d, t, active)
        return _solid_normal(tree.b, rows, n_local, info, d_scene, active)

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
    rows, _, _, _, _, _, _, grad, d, g = _hit_in_primitive(tree, prim, info, o, d, t, active)
    residual = dr.select(active, dr.abs(g) * dr.rsqrt(dr.squared_norm(grad)), dr.inf)
    return _solid_normal(tree.b, rows, grad, info, d, active), residual


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
    _, shape, param, plane_start, _ = gather_prim(b, tree, b.UInt32(dr.detach(prim)), b.Bool(dr.detach(active)))
    shape, plane_start = m.UInt32(shape), m.UInt32(plane_start)
    param = (m.Float(param[0]), m.Float(param[1]))
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

    Each canonical shape has a parameterization (docs/plugins.md): spheres as Mitsuba's
    `sphere` (u = phi / 2 pi, v = theta / pi), the sides of cylinders, cones and quadrics as
    Mitsuba's `cylinder` (u = phi / 2 pi, v up the axis from 0 to 1), box faces as Mitsuba's
    `cube`, caps planar from 0 to 1 across, the torus by its two angles, convex faces by a frame in their
    plane, mesh triangles by barycentric coordinates as Mitsuba's meshes without texture
    coordinates. Shading frames follow dp_du, so anisotropic BSDFs and normal maps have a
    tangent.
    """
    b = tree.b
    m = b.module
    rows, shape, param, plane_start, x, face, plane, grad, _, _ = _hit_in_primitive(tree, prim, info, o, d, t, active)
    zero = dr.zeros(b.Float, dr.width(x.x))
    two_pi, pi = 2.0 * dr.pi, dr.pi

    # Angle around the z axis, and d/du of a point turning about it.
    phi = dr.atan2(x.y, x.x)
    phi = dr.select(phi < 0, phi + two_pi, phi)
    around = two_pi * b.Array3f(-x.y, x.x, zero)
    rho = dr.sqrt(x.x * x.x + x.y * x.y)
    cos_phi, sin_phi = dr.cos(phi), dr.sin(phi)
    # A surface of revolution (cone, quadric side): up the profile, d rho / dz = -g_z / g_rho.
    g_rho = grad.x * cos_phi + grad.y * sin_phi
    slope = dr.select(g_rho != 0, -grad.z / g_rho, 0.0)
    up_profile = 2.0 * b.Array3f(slope * cos_phi, slope * sin_phi, 1.0)       # z = 2 v - 1

    # Sphere (Mitsuba's sphere).
    theta = dr.acos(dr.clip(x.z, -1.0, 1.0))
    uv_sphere = m.Array2f(phi / two_pi, theta / pi)
    dv_sphere = pi * b.Array3f(x.z * cos_phi, x.z * sin_phi, -dr.sin(theta))
    # Planar caps of cones and quadrics: [-1, 1]^2 -> [0, 1]^2.
    uv_cap = m.Array2f(0.5 * (x.x + 1.0), 0.5 * (x.y + 1.0))
    du_cap, dv_cap = b.Array3f(2.0, 0.0, 0.0) + zero, b.Array3f(0.0, 2.0, 0.0) + zero
    side = face == 0
    uv_side = m.Array2f(phi / two_pi, 0.5 * (x.z + 1.0))
    # Box faces as Mitsuba's `cube` lays its texture out: per face (-x, +x, -y, +y, -z, +z),
    # u and v run along these signed canonical axes.
    ex, ey, ez = (b.Array3f(2.0, 0.0, 0.0) + zero, b.Array3f(0.0, 2.0, 0.0) + zero,
                  b.Array3f(0.0, 0.0, 2.0) + zero)

    def per_face(values):
        out = values[5]
        for k in range(4, -1, -1):
            out = dr.select(face == k, values[k], out)
        return out
    u_box = per_face([x.y, x.y, x.z, -x.x, -x.y, x.y])
    v_box = per_face([x.z, -x.z, x.x, -x.z, x.x, x.x])
    du_box = per_face([ey, ey, ez, -ex, -ey, ey])
    dv_box = per_face([ez, -ez, ex, -ez, ex, ex])
    uv_box = m.Array2f(0.5 * (u_box + 1.0), 0.5 * (v_box + 1.0))
    # Torus: major angle phi, minor angle psi (minor radius k = param[0]).
    psi = dr.atan2(x.z, rho - 1.0)
    psi = dr.select(psi < 0, psi + two_pi, psi)
    uv_torus = m.Array2f(phi / two_pi, psi / two_pi)
    dv_torus = two_pi * param[0] * b.Array3f(-dr.sin(psi) * cos_phi, -dr.sin(psi) * sin_phi, dr.cos(psi))
    # Convex faces: a frame in the face's plane (its first axis from the least aligned axis).
    n_f = b.Array3f(plane.x, plane.y, plane.z)
    helper = dr.select(dr.abs(n_f.x) < 0.9, b.Array3f(1.0, 0.0, 0.0) + zero, b.Array3f(0.0, 1.0, 0.0) + zero)
    du_flat = dr.normalize(dr.cross(helper, n_f))
    dv_flat = dr.cross(n_f, du_flat)
    uv_flat = m.Array2f(dr.dot(x, du_flat), dr.dot(x, dv_flat))
    # Mesh triangles: barycentric coordinates over the stored (index-sorted) vertices.
    row = (plane_start + K.info_face(info)) * 3
    is_mesh = active & (shape == K.MESH)
    va = dr.gather(b.Array4f, tree.triangles, row, is_mesh)
    vb = dr.gather(b.Array4f, tree.triangles, row + 1, is_mesh)
    vc = dr.gather(b.Array4f, tree.triangles, row + 2, is_mesh)
    a3, e1 = b.Array3f(va.x, va.y, va.z), b.Array3f(vb.x - va.x, vb.y - va.y, vb.z - va.z)
    e2 = b.Array3f(vc.x - va.x, vc.y - va.y, vc.z - va.z)
    rel = x - a3
    d11, d12, d22 = dr.dot(e1, e1), dr.dot(e1, e2), dr.dot(e2, e2)
    r1, r2 = dr.dot(rel, e1), dr.dot(rel, e2)
    det = d11 * d22 - d12 * d12
    uv_mesh = m.Array2f((d22 * r1 - d12 * r2) / det, (d11 * r2 - d12 * r1) / det)

    def pick(sphere, side_or_cap, box, torus, flat, mesh):
        return dr.select(shape == K.SPHERE, sphere, dr.select((shape == K.CONE) | (shape == K.QUADRIC), side_or_cap,
                         dr.select(shape == K.BOX, box, dr.select(shape == K.TORUS, torus,
                                   dr.select(shape == K.MESH, mesh, flat)))))
    uv = pick(uv_sphere, dr.select(side, uv_side, uv_cap), uv_box, uv_torus, uv_flat, uv_mesh)
    du = pick(around, dr.select(side, around, du_cap), du_box, around, du_flat, e1)
    dv = pick(dv_sphere, dr.select(side, up_profile, dv_cap), dv_box, dv_torus, dv_flat, e2)
    # Tangents map with canonical -> world: the inverse of the rows' linear part, then the
    # scene frame's scale.
    A = m.Matrix3f(rows[0].x, rows[0].y, rows[0].z, rows[1].x, rows[1].y, rows[1].z,
                   rows[2].x, rows[2].y, rows[2].z)
    to_world = dr.rcp(A) * (1.0 / opaque(tree, b.Float, tree.inv_scale))
    dp_du, dp_dv = to_world @ du, to_world @ dv
    return (dr.select(active, uv, 0.0), dr.select(active, dp_du, 0.0), dr.select(active, dp_dv, 0.0))
