"""A closed triangle mesh leaf, in its own canonical frame. Not convex: its first crossing
after t_start comes from a walk of its BVH (`engine.mesh_bvh`, near child first) with a
watertight ray/triangle test (Woop, Benthin and Wald 2013), and its class from the side the
ray crosses from. Crossings within `skip` of t_start are the event at t_start seen again
through a neighbouring triangle (an edge or vertex hit: float32 t differs by ulps between the
triangles), so they are not events. Face: the triangle's index in BVH order (its plane is
plane start + face, as for a convex polyhedron)."""
from __future__ import annotations

import drjit as dr

from .. import layout as K
from .. import mesh_bvh
from ..layout import ENTER, EXIT, MAX_SLOPE, MESH, MISS
from .boxes import box_entry, inverse_direction
from .row import Shape, plane_surface, vertex_bounds


def _pick(v, k):
    return dr.select(k == 0, v.x, dr.select(k == 1, v.y, v.z))


@dr.syntax
def event(b, o, d, param, plane_buf, start, mesh, t_start):
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
            lower_l = dr.gather(b.Array4f, nodes, row, expanding)
            upper_l = dr.gather(b.Array4f, nodes, row + 1, expanding)
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


def uv(hit):
    """Barycentric coordinates over the stored (index-sorted) vertices, as Mitsuba's meshes
    without texture coordinates."""
    b, x, tree = hit.b, hit.x, hit.tree
    row = (hit.plane_start + K.info_face(hit.info)) * 3
    is_mesh = hit.active & (hit.shape == MESH)
    va = dr.gather(b.Array4f, tree.triangles, row, is_mesh)
    vb = dr.gather(b.Array4f, tree.triangles, row + 1, is_mesh)
    vc = dr.gather(b.Array4f, tree.triangles, row + 2, is_mesh)
    a3, e1 = b.Array3f(va.x, va.y, va.z), b.Array3f(vb.x - va.x, vb.y - va.y, vb.z - va.z)
    e2 = b.Array3f(vc.x - va.x, vc.y - va.y, vc.z - va.z)
    rel = x - a3
    d11, d12, d22 = dr.dot(e1, e1), dr.dot(e1, e2), dr.dot(e2, e2)
    r1, r2 = dr.dot(rel, e1), dr.dot(rel, e2)
    det = d11 * d22 - d12 * d12
    return b.module.Array2f((d22 * r1 - d12 * r2) / det, (d11 * r2 - d12 * r1) / det), e1, e2


SHAPE = Shape(MESH, "mesh", convex=False, event=event, event_normal=True, surface=plane_surface,
              bounds=vertex_bounds, uv=uv)
