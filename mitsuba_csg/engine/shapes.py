"""Ray intersection of the canonical primitives, written once in Dr.Jit for every backend.

Each canonical solid is bounded, so along a full line its boundary events alternate
enter, exit, enter, ... starting with an enter. `first_event` therefore returns the
first event strictly after `t_start` and classifies it by the parity of its index.
Events are recomputed from the unchanged ray every time, so the same root gives the same
float bit for bit, and "strictly after" needs no epsilon and always makes progress.

Faces: sphere 0; box 2*axis + (1 on the + side); cone and quadric 0 side, 1 bottom, 2 top; torus 0;
convex polyhedron: the plane's index within the primitive; mesh: the triangle's index in
BVH order (its plane is plane start + face, as for a convex polyhedron).

The quadric x^2 + y^2 <= a z^2 + b z + c, |z| <= 1 (paraboloids, hyperboloids; params (a, b),
c = 1 - a - |b|, so that its widest cap has radius 1) is not convex either: along a line its
side region is up to two intervals, each clipped to the slab, and its events are those of
the two pieces in order (touching pieces merged), so enter and exit still alternate.

A mesh is not convex: its first crossing after t_start comes from a walk of its BVH
(`engine.mesh_bvh`, near child first) with a watertight ray/triangle test, and its class from the side
the ray crosses from. Crossings within `skip` of t_start are the event at t_start seen
again through a neighbouring triangle (an edge or vertex hit: float32 t differs by ulps
between the triangles), so they are not events.

`SHAPES` is the table of canonical shapes: for each, its interval along a ray (Dr.Jit),
its surface function (Dr.Jit, detached or AD) and its world bounds under an affine map
(numpy). A new primitive adds one row here, a code in `engine.layout`, and its tests.
"""
from __future__ import annotations

from typing import Callable

import drjit as dr
import numpy as np

from . import layout as K
from . import mesh_bvh
from .layout import BOX, CONE, CONVEX, ENTER, EXIT, MAX_SLOPE, MESH, MISS, QUADRIC, SPHERE, TORUS

# Acceptance slack for cone side/cap candidates near the rim (canonical units).
_RIM_SLACK = 1e-5
# Newton-bisection steps per bracketed root of the torus quartic (and its derivative).
_TORUS_STEPS = 16


def _interval_event(b, near, far, near_face, far_face, t_start):
    """First event after t_start of a convex interval [near, far] (empty if near >= far)."""
    hit = near < far
    take_near = hit & (near > t_start)
    take_far = hit & ~take_near & (far > t_start)
    t = dr.select(take_near, near, dr.select(take_far, far, dr.inf))
    face = dr.select(take_near, near_face, far_face)
    cls = dr.select(take_near, b.UInt32(ENTER), dr.select(take_far, b.UInt32(EXIT), b.UInt32(MISS)))
    return t, face, cls


# ---- Intervals: (near, far, near face, far face) of the ray inside the canonical solid ----

def _sphere(b, o, d, param, plane_buf, start, count):
    a = dr.squared_norm(d)
    tc = -dr.dot(o, d) / a
    pc = o + tc * d                      # closest approach: robust for far-away origins
    h2 = (1.0 - dr.squared_norm(pc)) / a
    h = dr.sqrt(dr.maximum(h2, 0.0))
    near = dr.select(h2 > 0, tc - h, dr.inf)
    far = dr.select(h2 > 0, tc + h, -dr.inf)
    face = dr.zeros(b.UInt32, dr.width(a))
    return near, far, face, face


def _box(b, o, d, param, plane_buf, start, count):
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


def _cone(b, o, d, param, plane_buf, start, count):
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


def _quadric_event(b, o, d, param, t_start):
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
    t, face, cls = _interval_event(b, n1, f1, face_n1, face_f1, t_start)
    t2, face2, cls2 = _interval_event(b, n2, f2, face_n2, face_f2, t_start)
    second = cls == MISS
    return dr.select(second, t2, t), dr.select(second, face2, face), dr.select(second, cls2, cls)


@dr.syntax
def _convex(b, o, d, param, plane_buf, start, count):
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


# ---- Mesh: ordered BVH walk, watertight triangle test (Woop, Benthin and Wald 2013) ----



def _pick(v, k):
    return dr.select(k == 0, v.x, dr.select(k == 1, v.y, v.z))


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


@dr.syntax
def _mesh(b, o, d, param, plane_buf, start, mesh, t_start):
    """(t, face, class, plane normal) of a mesh's first crossing after t_start + skip."""
    triangles, nodes, skip = mesh
    width = dr.width(t_start)
    root = dr.reinterpret_array(b.UInt32, param[0])
    # The axis where |d| is largest becomes z; shear the others so the ray runs along z.
    ad = dr.abs(d)
    kz = dr.select((ad.x >= ad.y) & (ad.x >= ad.z), b.UInt32(0), dr.select(ad.y >= ad.z, b.UInt32(1), b.UInt32(2)))
    kx = dr.select(kz == 2, b.UInt32(0), kz + 1)
    ky = dr.select(kx == 2, b.UInt32(0), kx + 1)
    swap = _pick(d, kz) < 0                        # keep the projected triangles' winding
    kx, ky = dr.select(swap, ky, kx), dr.select(swap, kx, ky)
    dz = _pick(d, kz)
    sx, sy, sz = _pick(d, kx) / dz, _pick(d, ky) / dz, 1.0 / dz
    ox, oy, oz = _pick(o, kx), _pick(o, ky), _pick(o, kz)
    slope_scale = dr.norm(d) * dr.abs(sz)
    inv_d = inverse_direction(b, d)

    # The walk: `node` is an inner node whose children's boxes are still to be tested, [tri,
    # tri_end) the triangles of the leaf being tested; refs of boxes the ray reaches, with
    # their entry distances, wait on the stack (farther first), and one whose entry lies
    # beyond the nearest crossing found since is dropped when popped.
    root_leaf = K.mesh_ref_is_leaf(root)
    node = dr.select(root_leaf, K.NO_INDEX, root)
    tri = dr.select(root_leaf, K.mesh_tris_first(root), 0)
    tri_end = dr.select(root_leaf, K.mesh_tris_first(root) + K.mesh_tris_count(root), 0)
    stack_ref = dr.alloc_local(b.UInt32, mesh_bvh.STACK_SIZE)
    stack_near = dr.alloc_local(b.Float, mesh_bvh.STACK_SIZE)
    sp = dr.zeros(b.UInt32, width)
    t = dr.full(b.Float, dr.inf, width)
    face = dr.zeros(b.UInt32, width)
    enter = dr.zeros(b.Bool, width)
    # Loop state is what the walk changes (Dr.Jit would otherwise record the body twice, once
    # to find the ray's numbers unchanged).
    while dr.hint((node != K.NO_INDEX) | (tri < tri_end) | (sp > 0), label="csg_mesh_bvh",
                  exclude=[o, inv_d, triangles, nodes, skip, start, t_start, kx, ky, kz, sx, sy, sz, ox, oy, oz,
                           slope_scale]):
        # One triangle of the current leaf, or one inner node's two children.
        testing = tri < tri_end
        if dr.hint(testing, exclude=[triangles, skip, start, t_start, kx, ky, kz, sx, sy, sz, ox, oy, oz,
                                     slope_scale]):
            row = (start + tri) * 3
            va = dr.gather(b.Array4f, triangles, row, testing)
            vb = dr.gather(b.Array4f, triangles, row + 1, testing)
            vc = dr.gather(b.Array4f, triangles, row + 2, testing)
            # Projected vertices relative to the origin, each computed the same way in every
            # triangle that shares it.
            az, bz, cz = _pick(va, kz) - oz, _pick(vb, kz) - oz, _pick(vc, kz) - oz
            ax, ay = _pick(va, kx) - ox - sx * az, _pick(va, ky) - oy - sy * az
            bx, by = _pick(vb, kx) - ox - sx * bz, _pick(vb, ky) - oy - sy * bz
            cx, cy = _pick(vc, kx) - ox - sx * cz, _pick(vc, ky) - oy - sy * cz
            # Edge functions of the edges (a, b), (a, c), (b, c), lower vertex index first: a
            # shared edge gives the same value, negated, in both of its triangles.
            e_ab = ax * by - ay * bx
            e_ac = ax * cy - ay * cx
            e_bc = bx * cy - by * cx
            odd = va.w != 0                            # the sorted order reverses the winding
            u = dr.select(odd, e_bc, -e_bc)
            v = dr.select(odd, -e_ac, e_ac)
            w = dr.select(odd, e_ab, -e_ab)
            inside = ((u >= 0) & (v >= 0) & (w >= 0)) | ((u <= 0) & (v <= 0) & (w <= 0))
            det = u + v + w
            t_tri = (u * az + v * bz + w * cz) * sz / det
            # Neighbouring triangles' t for the same edge point differ like 1 / |cos|; the
            # sheared determinant is n . d / d_z for the triangle's normal n (|n| = twice its
            # area, word 7), so 1 / |cos| = |n| |d| / (|det| |d_z|).
            t_min = t_start + skip * dr.minimum(vb.w * slope_scale / dr.abs(det), 2.0**MAX_SLOPE)
            take = testing & inside & (det != 0) & (t_tri > t_min) & (t_tri < t)
            t = dr.select(take, t_tri, t)
            face = dr.select(take, tri, face)
            enter = dr.select(take, det > 0, enter)
            tri += 1

        # An inner node: test both children's boxes against [t_start, t]; go on with the
        # nearer one the ray reaches and push the other if it reaches both.
        expanding = ~testing & (node != K.NO_INDEX)
        next_ref = dr.full(b.UInt32, K.NO_INDEX, width)
        if dr.hint(expanding, exclude=[o, inv_d, nodes, t_start]):
            row = node * 4
            lower_l, upper_l = dr.gather(b.Array4f, nodes, row, expanding), dr.gather(b.Array4f, nodes, row + 1, expanding)
            near_l, far_l = box_entry(lower_l, upper_l, o, inv_d)
            near_r, far_r = box_entry(dr.gather(b.Array4f, nodes, row + 2, expanding),
                                       dr.gather(b.Array4f, nodes, row + 3, expanding), o, inv_d)
            hit_l = (near_l <= far_l) & (far_l > t_start) & (near_l <= t)
            hit_r = (near_r <= far_r) & (far_r > t_start) & (near_r <= t)
            ref_l = dr.reinterpret_array(b.UInt32, lower_l.w)
            ref_r = dr.reinterpret_array(b.UInt32, upper_l.w)
            right_first = hit_r & (~hit_l | (near_r < near_l))
            both = expanding & hit_l & hit_r
            stack_ref.write(dr.select(right_first, ref_l, ref_r), sp, both)
            stack_near.write(dr.select(right_first, near_l, near_r), sp, both)
            sp = dr.select(both, sp + 1, sp)
            next_ref = dr.select(hit_l | hit_r, dr.select(right_first, ref_r, ref_l), K.NO_INDEX)
            node = dr.full(b.UInt32, K.NO_INDEX, width)

        # Idle after this step: pop the nearest waiting box, unless it lies beyond t.
        pop = (next_ref == K.NO_INDEX) & (node == K.NO_INDEX) & (tri >= tri_end) & (sp > 0)
        top = dr.select(pop, sp - 1, 0)                 # an index in range on every lane
        popped_ref, popped_near = stack_ref.read(top, pop), stack_near.read(top, pop)
        sp = dr.select(pop, sp - 1, sp)
        next_ref = dr.select(pop & (popped_near <= t), popped_ref, next_ref)
        # Take the next ref: a leaf's triangles are tested next, an inner node is expanded.
        leaf = (next_ref != K.NO_INDEX) & K.mesh_ref_is_leaf(next_ref)
        tri = dr.select(leaf, K.mesh_tris_first(next_ref), tri)
        tri_end = dr.select(leaf, K.mesh_tris_first(next_ref) + K.mesh_tris_count(next_ref), tri_end)
        node = dr.select(leaf, K.NO_INDEX, dr.select(next_ref != K.NO_INDEX, next_ref, node))
    found = dr.isfinite(t)
    plane = dr.gather(b.Array4f, plane_buf, start + face, found)
    cls = dr.select(found, dr.select(enter, b.UInt32(ENTER), b.UInt32(EXIT)), b.UInt32(MISS))
    return t, face, cls, b.Array3f(plane.x, plane.y, plane.z)


# ---- Torus: root isolation by derivatives, then safeguarded Newton on each bracket ----

def _poly(coeffs, x):
    acc = coeffs[0]
    for c in coeffs[1:]:
        acc = dr.fma(acc, x, c)
    return acc


def _newton_step(f, df, x, lo, hi, lo_neg, done):
    """One safeguarded Newton step on a bracket [lo, hi] of a monotone polynomial; a lane
    that is done keeps its x."""
    fx = _poly(f, x)
    same_as_lo = (fx <= 0) == lo_neg
    lo = dr.select(same_as_lo, x, lo)
    hi = dr.select(same_as_lo, hi, x)
    step = x - fx / _poly(df, x)
    x_next = dr.select((step > lo) & (step < hi), step, 0.5 * (lo + hi))
    done = done | (fx == 0) | (dr.abs(x_next - x) <= 2e-7 * (dr.abs(x) + 1e-3))
    return dr.select(done, x, x_next), lo, hi, done


@dr.syntax
def _bracketed_roots(b, f, df, brackets, valid):
    """[(x, has_root)] of a monotone polynomial on each bracket (lo, hi) whose ends differ in
    sign; (midpoint, False) where they do not.

    Newton steps inside the bracket, bisection otherwise. Once a Newton step no longer moves
    x, x is frozen: at the float32 noise floor the sign of f is noise, and following it
    would walk the bracket away from the root. All brackets step together in one loop that
    ends when every lane's roots are frozen (at most _TORUS_STEPS steps; most converge in a
    few), so a packet whose lanes miss the torus, or converge early, does not pay for 16.
    """
    has_roots, negs, xs, los, his, dones = [], [], [], [], [], []
    for lo, hi in brackets:
        f_lo, f_hi = _poly(f, lo), _poly(f, hi)
        has_root = valid & (lo < hi) & ((f_lo <= 0) != (f_hi <= 0))
        has_roots.append(has_root)
        negs.append(f_lo <= 0)
        xs.append(0.5 * (lo + hi))
        los.append(b.Float(lo))
        his.append(b.Float(hi))
        dones.append(~has_root)
    steps = dr.zeros(b.UInt32, dr.width(valid))
    while dr.hint(_pending(dones) & (steps < _TORUS_STEPS), label="csg_torus_newton", exclude=[f, df, negs]):
        stepped = [_newton_step(f, df, *state) for state in zip(xs, los, his, negs, dones)]
        xs = [state[0] for state in stepped]
        los = [state[1] for state in stepped]
        his = [state[2] for state in stepped]
        dones = [state[3] for state in stepped]
        steps += 1
    return list(zip(xs, has_roots))


def _pending(dones):
    pending = ~dones[0]
    for done in dones[1:]:
        pending |= ~done
    return pending


def _torus_events(b, o, d, param):
    """The up-to-four sorted boundary events of the canonical torus (major 1, minor param[0])."""
    k = param[0]
    width = dr.width(k)
    inv_len = dr.rsqrt(dr.squared_norm(d))
    dn = d * inv_len
    t0 = -dr.dot(o, dn) * inv_len          # ray parameter closest to the torus centre
    oc = o + t0 * d
    m = dr.squared_norm(oc)
    reach2 = (1.0 + k) * (1.0 + k) - m
    reach = dr.sqrt(dr.maximum(reach2, 0.0)) * 1.001 + 1e-3   # ends strictly outside the torus
    # The torus lies in the slab |z| <= k: a ray that crosses the bounding sphere outside it
    # has no root, and its lanes skip the root search (`_bracketed_roots`).
    slab = k * 1.001 + 1e-3
    z_lo, z_hi = (-slab - oc.z) / dn.z, (slab - oc.z) / dn.z
    in_slab = dr.select(dn.z == 0, dr.abs(oc.z) <= slab,
                        (dr.maximum(z_lo, z_hi) >= -reach) & (dr.minimum(z_lo, z_hi) <= reach))
    valid = (reach2 > 0) & in_slab
    bb = dr.dot(oc, dn)
    e = m + 1.0 - k * k
    u = dn.x * dn.x + dn.y * dn.y
    v = oc.x * dn.x + oc.y * dn.y
    w0 = oc.x * oc.x + oc.y * oc.y
    one = dr.full(b.Float, 1.0, width)
    f = [one, 4.0 * bb, 4.0 * bb * bb + 2.0 * e - 4.0 * u, 4.0 * bb * e - 8.0 * v, e * e - 4.0 * w0]
    df = [4.0 * one, 3.0 * f[1], 2.0 * f[2], f[3]]
    ddf = [12.0 * one, 6.0 * f[1], 2.0 * f[2]]
    # f'' roots (quadratic, monic up to 12): split [-reach, reach] into monotone pieces of f'.
    disc = ddf[1] * ddf[1] - 4.0 * ddf[0] * ddf[2]
    sq = dr.sqrt(dr.maximum(disc, 0.0))
    s1 = dr.clip((-ddf[1] - sq) / (2.0 * ddf[0]), -reach, reach)
    s2 = dr.clip((-ddf[1] + sq) / (2.0 * ddf[0]), -reach, reach)
    s1 = dr.select(disc > 0, s1, -reach)
    s2 = dr.select(disc > 0, s2, -reach)
    # f' roots: split points of f (a missing root leaves a harmless empty piece).
    pieces = ((-reach, s1), (s1, s2), (s2, reach))
    splits = [dr.select(ok, x, lo) for (x, ok), (lo, _) in zip(_bracketed_roots(b, df, ddf, pieces, valid), pieces)]
    ends = [-reach, *splits, reach]
    pieces = [(lo, dr.maximum(lo, hi)) for lo, hi in zip(ends[:-1], ends[1:])]
    events, oks = [], []
    for (x, ok), (lo, hi) in zip(_bracketed_roots(b, f, df, pieces, valid), pieces):
        # One Newton step on the geometric form (rho - 1)^2 + z^2 - k^2, which float32
        # evaluates without the quartic's cancellation (its roots were off by ~1e-5 of the
        # distance), kept inside the root's bracket so that the roots stay in order.
        p = oc + x * dn
        rho = dr.sqrt(p.x * p.x + p.y * p.y)
        g = (rho - 1.0) * (rho - 1.0) + p.z * p.z - k * k
        dg = 2.0 * (rho - 1.0) * (p.x * dn.x + p.y * dn.y) / rho + 2.0 * p.z * dn.z
        x = dr.select((dg != 0) & (rho > 0), dr.clip(x - g / dg, lo, hi), x)
        events.append(t0 + x * inv_len)
        oks.append(ok)
    return events, oks


def first_event(b, shape, xf_rows, param, plane_buf, plane_start, plane_count, o_world, d_world, t_start,
                mesh=None, kinds=None):
    """(t, face, class, slope) of the first boundary event of one primitive after t_start (per lane).

    `slope` is the event's SLOPE exponent (`engine.layout`): how steeply the ray meets the
    surface there, which scales how far in t float32 rounding can move the event. `mesh` is
    (triangle buffer, mesh node buffer, skip) for mesh leaves (see the module docstring).
    """
    o = b.Array3f(dr.dot(xf_rows[0], b.Array4f(o_world.x, o_world.y, o_world.z, 1.0)),
                  dr.dot(xf_rows[1], b.Array4f(o_world.x, o_world.y, o_world.z, 1.0)),
                  dr.dot(xf_rows[2], b.Array4f(o_world.x, o_world.y, o_world.z, 1.0)))
    d = b.Array3f(dr.dot(b.Array3f(xf_rows[0].x, xf_rows[0].y, xf_rows[0].z), d_world),
                  dr.dot(b.Array3f(xf_rows[1].x, xf_rows[1].y, xf_rows[1].z), d_world),
                  dr.dot(b.Array3f(xf_rows[2].x, xf_rows[2].y, xf_rows[2].z), d_world))
    t, face, cls, plane_normal = _first_event_local(b, shape, param, plane_buf, plane_start, plane_count, o, d,
                                                    t_start, mesh, kinds)
    # A miss has no surface point: its slope is never read (a miss's t is inf wherever a tie
    # window meets it), and packets whose lanes all missed skip the surface function.
    slope = dr.if_stmt((b, shape, face, param, plane_normal, o, d, t, xf_rows, d_world, kinds), dr.isfinite(t),
                       _event_slope, _no_slope, label="csg_event_slope")
    return t, face, cls, slope


def _no_slope(b, shape, face, param, plane_normal, o, d, t, xf_rows, d_world, kinds):
    return dr.full(b.UInt32, MAX_SLOPE, dr.width(t))


def _event_slope(b, shape, face, param, plane_normal, o, d, t, xf_rows, d_world, kinds):
    """The SLOPE exponent of the event at t (engine.layout)."""
    plane = b.Array4f(plane_normal.x, plane_normal.y, plane_normal.z, 0.0)
    _, grad = surface_function(b.module, shape, face, param, plane, o + t * d, kinds)
    # The world normal is M^T grad for the rows M of world -> canonical; grad . d is the same
    # in both frames.
    normal = b.Array3f(*(xf_rows[0][i] * grad.x + xf_rows[1][i] * grad.y + xf_rows[2][i] * grad.z
                         for i in range(3)))
    cos = dr.abs(dr.dot(grad, d)) * dr.rsqrt(dr.squared_norm(normal) * dr.squared_norm(d_world))
    return _slope_exponent(b, cos)


def _slope_exponent(b, cos):
    """k with 2^-(k+1) < cos <= 2^-k, clamped to [0, MAX_SLOPE] (NaN, e.g. a cone's apex: MAX_SLOPE)."""
    biased = dr.reinterpret_array(b.module.Int32, dr.minimum(cos, 1.0)) >> 23     # IEEE exponent + 127
    k = dr.clip(126 - biased, 0, MAX_SLOPE)
    return b.UInt32(dr.select(cos > 0, k, MAX_SLOPE))


@dr.syntax
def _first_event_local(b, shape, param, plane_buf, plane_start, plane_count, o, d, t_start, mesh, kinds):
    width = dr.width(t_start)
    near = dr.full(b.Float, dr.inf, width)
    far = dr.full(b.Float, -dr.inf, width)
    near_face = dr.zeros(b.UInt32, width)
    far_face = dr.zeros(b.UInt32, width)
    near_normal = dr.zeros(b.Array3f, width)
    far_normal = dr.zeros(b.Array3f, width)
    t = dr.full(b.Float, dr.inf, width)
    face = dr.zeros(b.UInt32, width)
    cls = dr.full(b.UInt32, MISS, width)
    present = _present(kinds)
    for kind in _INTERVAL_SHAPES:
        if dr.hint(kind.code in present, mode="scalar"):
            if shape == kind.code:
                near, far, near_face, far_face = kind.interval(b, o, d, param, plane_buf, plane_start, plane_count)
    if dr.hint(CONVEX in present, mode="scalar"):
        if shape == CONVEX:
            near, far, near_face, far_face, near_normal, far_normal = _convex(b, o, d, param, plane_buf, plane_start,
                                                                              plane_count)
    if dr.hint(mesh is not None and MESH in present, mode="scalar"):
        if shape == MESH:
            t, face, cls, near_normal = _mesh(b, o, d, param, plane_buf, plane_start, mesh, t_start)
            far_normal = b.Array3f(near_normal)
    if dr.hint(QUADRIC in present, mode="scalar"):
        if shape == QUADRIC:
            t, face, cls = _quadric_event(b, o, d, param, t_start)
    own = (shape == MESH) | (shape == QUADRIC)
    if dr.hint(TORUS in present, mode="scalar"):
        own |= shape == TORUS
        if shape == TORUS:
            # Pick the first root after t_start; its parity among the roots is its class.
            events, oks = _torus_events(b, o, d, param)
            seen = dr.zeros(b.UInt32, width)
            found = dr.zeros(b.Bool, width)
            for ev, ok in zip(events, oks):
                take = ok & ~found & (ev > t_start)
                t = dr.select(take, ev, t)
                cls = dr.select(take, seen & 1, cls)
                found |= take
                seen += dr.select(ok, 1, 0)
    t_i, face_i, cls_i = _interval_event(b, near, far, near_face, far_face, t_start)
    t, face, cls = dr.select(own, t, t_i), dr.select(own, face, face_i), dr.select(own, cls, cls_i)
    return t, face, cls, dr.select(cls == ENTER, near_normal, far_normal)


def _present(kinds):
    """The shape codes a kernel must handle: all of them unless the tree says which."""
    return frozenset(kind.code for kind in SHAPES) if kinds is None else kinds


def surface_function(m, shape, face, param, plane, x, kinds=None):
    """(g, grad g) of a primitive's `face` at canonical point x; g = 0 on the surface, < 0 inside.

    `m` is a Dr.Jit module (detached or AD) and `plane` the face's plane for convex primitives.
    grad g is the outward (unnormalized) normal: the hit normal and its derivatives use it.
    """
    g = grad = None
    present = _present(kinds)
    for kind in SHAPES:
        if kind.code not in present:
            continue
        g_k, grad_k = kind.surface(m, face, param, plane, x)
        g = g_k if g is None else dr.select(shape == kind.code, g_k, g)
        grad = grad_k if grad is None else dr.select(shape == kind.code, grad_k, grad)
    return g, grad


# ---- Surface functions: (g, grad g) at a canonical point x on `face` ----

def _sphere_surface(m, face, param, plane, x):
    return dr.squared_norm(x) - 1.0, 2.0 * x


def _box_surface(m, face, param, plane, x):
    zero = dr.zeros(m.Float, dr.width(x.x))
    axis, plus = face // 2, (face & 1) == 1           # face 2*axis + side
    sign = dr.select(plus, 1.0, -1.0)
    coord = dr.select(axis == 0, x.x, dr.select(axis == 1, x.y, x.z))
    unit = m.Array3f(dr.select(axis == 0, sign, zero), dr.select(axis == 1, sign, zero),
                     dr.select(axis == 2, sign, zero))
    return sign * coord - 1.0, unit


def _cone_surface(m, face, param, plane, x):
    zero = dr.zeros(m.Float, dr.width(x.x))
    a, c = 0.5 * (param[0] + param[1]), 0.5 * (param[1] - param[0])   # side 0, bottom 1, top 2
    r = a + c * x.z
    side_g = x.x * x.x + x.y * x.y - r * r
    side_grad = m.Array3f(2.0 * x.x, 2.0 * x.y, -2.0 * c * r)
    cap_sign = dr.select(face == 1, -1.0, 1.0)
    return (dr.select(face == 0, side_g, cap_sign * x.z - 1.0),
            dr.select(face == 0, side_grad, m.Array3f(zero, zero, cap_sign + zero)))


def _quadric_surface(m, face, param, plane, x):
    zero = dr.zeros(m.Float, dr.width(x.x))
    a, c_lin = param[0], param[1]                      # side 0, bottom 1, top 2
    c0 = 1.0 - a - dr.abs(c_lin)
    side_g = x.x * x.x + x.y * x.y - a * x.z * x.z - c_lin * x.z - c0
    side_grad = m.Array3f(2.0 * x.x, 2.0 * x.y, -2.0 * a * x.z - c_lin)
    cap_sign = dr.select(face == 1, -1.0, 1.0)
    return (dr.select(face == 0, side_g, cap_sign * x.z - 1.0),
            dr.select(face == 0, side_grad, m.Array3f(zero, zero, cap_sign + zero)))


def _torus_surface(m, face, param, plane, x):
    k = param[0]                                       # major radius 1, minor k
    s = dr.squared_norm(x) + 1.0 - k * k
    return (s * s - 4.0 * (x.x * x.x + x.y * x.y),
            m.Array3f(4.0 * s * x.x - 8.0 * x.x, 4.0 * s * x.y - 8.0 * x.y, 4.0 * s * x.z))


def _convex_surface(m, face, param, plane, x):
    n = m.Array3f(plane.x, plane.y, plane.z)           # the face's plane
    return dr.dot(n, x) - plane.w, n


# ---- World bounds: exact boxes of the canonical solids under x -> A x + c (numpy) ----

def _sphere_bounds(A, c, param, plane_start, plane_vertices):
    half = np.linalg.norm(A, axis=2)                   # |A_i.|: support of the unit ball
    return c - half, c + half


def _box_bounds(A, c, param, plane_start, plane_vertices):
    half = np.abs(A).sum(axis=2)
    return c - half, c + half


def _disc_support(A):
    """Support of the unit disc in z = 0 under A, per world axis."""
    return np.sqrt(A[:, :, 0] ** 2 + A[:, :, 1] ** 2)


def _cone_bounds(A, c, param, plane_start, plane_vertices):
    axis = A[:, :, 2]                                  # hull of the two cap discs
    bottom_c, top_c = c - axis, c + axis
    disc = _disc_support(A)
    bottom_h, top_h = param[:, 0:1] * disc, param[:, 1:2] * disc
    return (np.minimum(bottom_c - bottom_h, top_c - top_h), np.maximum(bottom_c + bottom_h, top_c + top_h))


def _quadric_bounds(A, c, param, plane_start, plane_vertices):
    # Per world axis, the support max_z (p z + w rho(z)) over |z| <= 1, with p the axis' z
    # weight and w the norm of its xy weights: rho = sqrt(a z^2 + b z + c) bulges past the
    # hull of the cap circles (a paraboloid's does), so the maximum may lie between the caps,
    # where p rho = -w rho' (squared: a quadratic in z). Its real roots in [-1, 1] and the ends
    # are the candidates; extra roots from squaring are harmless (any z gives a lower bound).
    a, b = param[:, 0:1], param[:, 1:2]
    c0 = 1.0 - a - np.abs(b)
    w = _disc_support(A)                               # (n, 3)

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


def _torus_bounds(A, c, param, plane_start, plane_vertices):
    half = _disc_support(A) + param[:, 0:1] * np.linalg.norm(A, axis=2)
    return c - half, c + half


def _convex_bounds(A, c, param, plane_start, plane_vertices):
    lower, upper = np.empty_like(c), np.empty_like(c)
    for start, verts in plane_vertices.items():
        m = plane_start == start
        world = np.einsum("nij,vj->nvi", A[m], verts) + c[m][:, None, :]
        lower[m], upper[m] = world.min(axis=1), world.max(axis=1)
    return lower, upper


class Shape:
    """One canonical shape as the engine sees it.

    A plain class on purpose: Dr.Jit's symbolic `if` treats dataclasses and tuples it reads
    as loop state (PyTrees), and this table is constant.
    """

    __slots__ = ("code", "interval", "surface", "bounds")

    def __init__(self, code: int, interval: Callable | None, surface: Callable, bounds: Callable):
        self.code = code              # engine.layout shape code
        self.interval = interval      # (b, o, d, param, planes, start, count) -> (near, far, faces); None: own
                                      # search in _first_event_local
        self.surface = surface        # (m, face, param, plane, x) -> (g, grad g)
        self.bounds = bounds          # (A, c, param, plane_start, plane_vertices) -> (lower, upper)


SHAPES = (
    Shape(SPHERE, _sphere, _sphere_surface, _sphere_bounds),
    Shape(BOX, _box, _box_surface, _box_bounds),
    Shape(CONE, _cone, _cone_surface, _cone_bounds),
    Shape(TORUS, None, _torus_surface, _torus_bounds),     # four roots: _torus_events
    Shape(QUADRIC, None, _quadric_surface, _quadric_bounds),  # two pieces: _quadric_event
    Shape(CONVEX, None, _convex_surface, _convex_bounds),  # also the faces' normals: _convex
    Shape(MESH, None, _convex_surface, _convex_bounds),    # a triangle's plane; bounds of the vertices
)
_INTERVAL_SHAPES = tuple(kind for kind in SHAPES if kind.interval is not None)


def primitive_bounds(shape, to_world, param, plane_start, plane_vertices):
    """Exact world boxes (lower, upper) of primitives: support functions under canonical -> world."""
    A, c = to_world[:, :3, :3], to_world[:, :3, 3]
    lower, upper = c.copy(), c.copy()
    for kind in SHAPES:
        m = shape == kind.code
        if np.any(m):
            lower[m], upper[m] = kind.bounds(A[m], c[m], param[m], plane_start[m], plane_vertices)
    return lower, upper
