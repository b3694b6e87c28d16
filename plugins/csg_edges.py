"""The discontinuity curves of csg shapes, for the primarily visible boundary derivative.

Where a primitive's parameter moves a curve across which the image jumps (a silhouette, a
sharp edge of a leaf, the curve where two leaves' surfaces meet), the image changes by the
radiance difference across the curve times the curve's motion normal to itself in the
image. `csg_prb_projective` samples points on these curves and estimates that term; this
module lists the curves of a scene's csg shapes and evaluates points on them with Dr.Jit's
AD, so that a point moves with the shapes' `primitive_to_world`.

Curves, each a map u in [0, 1) -> a point (a parameter value slides the point along its
curve, never across it, so only the motion normal to the curve counts, as it must):

- SPHERE_SILHOUETTE: the contour of a sphere leaf (an ellipsoid after its transform) seen
  from the camera: in the leaf's canonical frame, the unit sphere's circle of contact of the
  cone from the camera.
- CONE_SILHOUETTE: the two contour lines of a cone or cylinder side (one curve per line).
- TORUS_SILHOUETTE: the contour of a torus seen from the camera, on two branches: at each
  angle about the axis, the points of the tube's circle where the normal is perpendicular
  to the line of sight, or at each angle about the tube, the two such points on its
  parallel circle (in closed form; both parametrizations, sampled as a mixture).
- QUADRIC_SILHOUETTE: the contour of a quadric leaf's side (paraboloid, hyperboloid) seen
  from the camera, on two branches: at each angle about the axis, the heights where the
  normal is perpendicular to the line of sight (the roots of a quadratic), or at each
  height the two such angles (both parametrizations, sampled as a mixture).
- CIRCLE: a fixed circle of a leaf's canonical frame: the rims of cones, cylinders and
  quadrics.
- SEGMENT: a box edge (corners of the canonical cube).
- POLY_EDGE: an edge of a convex polyhedron leaf (prisms, GDML polyhedra) or of a mesh
  leaf (where its two triangles are not coplanar), between two canonical vertices.
- SPHERE_PLANE: where a sphere leaf meets the plane of a box's, convex polyhedron's or mesh
  triangle's face (a CSG edge of holes cut into them), in the sphere's canonical frame.
- SPHERE_SPHERE: where two sphere leaves with uniform scales meet.
- PLANE_PLANE: where faces of two box, convex or mesh leaves meet (a notch cut by a box):
  the line of the two planes in world space over the overlap of the faces' boxes, or, for
  two meshes' triangles, over the segment where the two triangles cross.
- CONE_PLANE: where a cone or cylinder side meets the plane of such a face, in closed form
  in the cone's canonical frame (z as a function of the angle, or the angle as a function
  of z on two branches when the plane is nearer the axis's direction).
- CAP_PLANE: the chord where the plane of such a face crosses a cone or cylinder cap.
- SURFACE_PAIR: any other curve where a face of a sphere, cone, quadric or torus leaf meets
  a face of another such leaf, or a torus or quadric meets a box's or convex polyhedron's
  face or a mesh's triangle (a sphere cutting a cylinder, two cylinders, a torus sunk into
  a box, a paraboloid cut by a plane). No closed form:
  the host traces the curve on a grid over leaf a's surface (marching squares on leaf b's
  implicit function) into chords, one curve per chord; on the device a point of a chord is
  moved onto both leaves' attached surfaces by Newton steps, x - J^T (J J^T)^-1 F with J
  the surfaces' gradients, whose derivative is the curve's motion normal to itself (the
  implicit-function theorem), which is all the boundary term needs.

Each is listed where it may exist (the leaves' boxes overlap); the integrator drops points
the camera does not see, and whether a point is on the boundary of the CSG solid is left
to the radiance difference itself, which is zero across a curve inside the solid. Every
pair of leaf kinds has its curves listed (`docs/plugins.md` says which derivatives are
still missing).
"""
from __future__ import annotations

import weakref

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_csg.engine import layout as K
from mitsuba_csg.engine.backend import ad_module
from mitsuba_csg.engine.shapes import surface_function

(SPHERE_SILHOUETTE, CONE_SILHOUETTE, CIRCLE, SEGMENT, SPHERE_PLANE, SPHERE_SPHERE, CONE_PLANE, CAP_PLANE,
 POLY_EDGE, PLANE_PLANE, TORUS_SILHOUETTE, SURFACE_PAIR, QUADRIC_SILHOUETTE) = range(13)
DATA_FLOATS = 16
# `extra` of the plane curves: for CONE_PLANE whether the curve is parametrized by height
# (planes nearer the axis's direction; two branches) rather than by angle, for CAP_PLANE
# which cap. The plane itself is the curve's `data`: (normal, offset) in leaf b's frame.
BY_HEIGHT, BRANCH, TOP_CAP = 0x8, 0x10, 0x8
# `extra` of a torus's or quadric's contour: its branch (bit 0) and whether it is
# parametrized by the other parameter (the tube's angle, the height) rather than the angle
# about the axis.
OTHER_PARAMETER = 0x2

# Box edges: pairs of canonical corners (index bits = x, y, z sign).
_BOX_EDGES = [(a, a | (1 << axis)) for axis in range(3) for a in range(8) if not a & (1 << axis)]


def _polyhedron_edges(planes, vertices, tolerance=1e-9):
    """Canonical end points (E, 2, 3) of a convex polyhedron's edges: the vertices on two
    non-parallel face planes."""
    on = np.abs(vertices @ planes[:, :3].T - planes[:, 3]) <= tolerance * (1 + np.abs(planes[:, 3]))
    edges = []
    for i in range(len(planes)):
        for j in range(i + 1, len(planes)):
            if np.linalg.norm(np.cross(planes[i, :3], planes[j, :3])) <= 1e-9:
                continue
            both = vertices[on[:, i] & on[:, j]]
            if len(both) >= 2:
                axis = np.cross(planes[i, :3], planes[j, :3])
                position = both @ axis
                edges.append((both[np.argmin(position)], both[np.argmax(position)]))
    return np.array(edges).reshape(-1, 2, 3)


def _triangle_corners(triangles):
    """(T, 3, 3) corners of triangles stored as layout.TRIANGLE_FLOATS rows (a, b, c at 0, 4, 8)."""
    return np.stack([triangles[:, 0:3], triangles[:, 4:7], triangles[:, 8:11]], axis=1)


def _ranges(first, counts):
    """The indices first[k] + 0 ... counts[k] - 1 for every k, concatenated."""
    return np.repeat(first, counts) + np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)


def _mesh_edges(triangles, normals, tolerance=1e-9):
    """Canonical end points (E, 2, 3) of a closed mesh's edges whose two triangles are not
    coplanar."""
    return _bent_edges(_triangle_corners(triangles), normals, tolerance)


def _bent_edges(corners, normals, tolerance=1e-9, open_edges=False):
    """End points (E, 2, 3) of the edges of triangles (T, 3, 3) with unit normals (T, 3)
    where two triangles meet at an angle, and with `open_edges` also those of one triangle
    only (the boundary of an open mesh). Edges are matched by their end points, so meshes
    that repeat vertices per face (Mitsuba's cube) work alike."""
    ends = np.stack([corners, np.roll(corners, -1, axis=1)], axis=2).reshape(-1, 2, 3)   # (3T, 2, 3)
    # each edge's end points in lexicographic order, so that both its triangles list it alike
    greater, equal = ends[:, 0] > ends[:, 1], ends[:, 0] == ends[:, 1]
    swap = greater[:, 0] | (equal[:, 0] & (greater[:, 1] | (equal[:, 1] & greater[:, 2])))
    ends[swap] = ends[swap, ::-1]
    _, edge = np.unique(ends.reshape(-1, 6), axis=0, return_inverse=True)
    edge = edge.ravel()
    face = np.repeat(np.arange(len(corners)), 3)
    order = np.argsort(edge, kind="stable")
    edge, face = edge[order], face[order]
    pairs = np.flatnonzero(edge[1:] == edge[:-1])
    bent = np.einsum("ij,ij->i", normals[face[pairs]], normals[face[pairs + 1]]) < 1 - tolerance
    found = ends[order][pairs[bent]]
    if open_edges:
        alone = np.bincount(edge)[edge] == 1
        found = np.concatenate([found, ends[order][alone]])
    return found


def scene_mesh_edges(scene):
    """World end points (E, 2, 3) of the edges of the Mitsuba meshes in a scene (rectangles,
    cubes, loaded meshes) that may cast the edge of a shadow: creases and open boundaries.
    Area lights' shapes are not listed (the lamps themselves, lit from their own points only
    along their planes)."""
    found = [np.zeros((0, 2, 3))]
    for shape in scene.shapes():
        if not shape.is_mesh() or shape.is_emitter():
            continue
        vertices = np.array(shape.vertex_positions_buffer(), np.float64).reshape(-1, 3)
        corners = vertices[np.array(shape.faces_buffer(), np.int64).reshape(-1, 3)]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        size = np.linalg.norm(normals, axis=1)
        keep = size > 0
        found.append(_bent_edges(corners[keep], normals[keep] / size[keep, None], 1e-6, open_edges=True))
    return np.concatenate(found)


class StaticCurves:
    """The curves of a scene's Mitsuba shapes that may cast the edge of a shadow (they stand
    still: their points are not attached to anything), in the form `evaluate` takes, each
    row a kind, an extra int, a matrix and offset (canonical -> world) and DATA_FLOATS of
    data: the meshes' creases and open edges (`scene_mesh_edges`, POLY_EDGE rows with the
    identity), spheres' contours (SPHERE_SILHOUETTE), disks' rims (CIRCLE), and the open
    cylinders' contour lines and rims (CONE_SILHOUETTE, CIRCLE), mapped onto the canonical
    cone's frame (z from -1 to 1). `weight(viewpoint)`: the rows' sampling weights, about
    their length over their distance."""

    def __init__(self, scene):
        rows = []                                   # (kind, extra, to_world (3, 4), data, length)

        def add(kind, extra, to_world, data, length):
            row = np.zeros(DATA_FLOATS)
            row[:len(data)] = data
            rows.append((kind, extra, to_world, row, length))

        for a, b in scene_mesh_edges(scene):
            add(POLY_EDGE, 0, np.eye(3, 4), np.concatenate([[0.0, 0.0], a, b]), np.linalg.norm(b - a))
        for shape in scene.shapes():
            if shape.is_emitter() or shape.shape_type() not in (mi.ShapeType.Sphere, mi.ShapeType.Disk,
                                                               mi.ShapeType.Cylinder):
                continue
            m = np.array(mi.traverse(shape)["to_world"].matrix, np.float64).reshape(4, 4)[:3]
            size = np.linalg.norm(m[:, :3], axis=0).max()
            if shape.shape_type() == mi.ShapeType.Sphere:
                add(SPHERE_SILHOUETTE, 0, m, [], 2 * np.pi * size)
                continue
            # the object's z = 0 (disk; cylinder from z = 0 to 1) is the canonical z = -1
            stretch = 1.0 if shape.shape_type() == mi.ShapeType.Disk else 0.5
            cone = np.column_stack([m[:, 0], m[:, 1], stretch * m[:, 2], m[:, 3] + stretch * m[:, 2]])
            add(CIRCLE, 0, cone, [1.0, 1.0], 2 * np.pi * size)
            if shape.shape_type() == mi.ShapeType.Cylinder:
                add(CIRCLE, 1, cone, [1.0, 1.0], 2 * np.pi * size)
                for line in (0, 1):
                    add(CONE_SILHOUETTE, line, cone, [1.0, 1.0], np.linalg.norm(m[:, 2]))
        self.count = len(rows)
        if not rows:
            return
        kind, extra, to_world, data, length = zip(*rows)
        self.kind, self.extra = np.array(kind, np.uint32), np.array(extra, np.uint32)
        self.to_world, self.data, self.length = np.array(to_world), np.array(data), np.array(length)
        # where each curve is, for its distance: a segment's middle, a shape's centre
        self.centre = np.where((self.kind == POLY_EDGE)[:, None], 0.5 * (self.data[:, 2:5] + self.data[:, 5:8]),
                               self.to_world[:, :, 3])

    def weight(self, viewpoint):
        return self.length / np.maximum(np.linalg.norm(self.centre - viewpoint, axis=1), 1e-9)


# Curves of recently rendered shapes by the identity of their prepared trees, each with a weak
# reference that tells the tree it was listed for (an id may be reused once a tree is gone; the
# trees themselves are not kept alive). Views of one scene, and renders between parameter
# updates (which replace the prepared tree), list a shape's curves once.
_CURVES_CACHE: dict = {}
_CURVES_CACHE_SIZE = 8


def curves_of(shape) -> "Curves":
    """The `Curves` of a csg shape, listed once per prepared tree."""
    prepared = shape.prepared
    entry = _CURVES_CACHE.get(id(prepared))
    if entry is not None and entry[0]() is prepared:
        return entry[1]
    curves = Curves(shape)
    if len(_CURVES_CACHE) >= _CURVES_CACHE_SIZE:
        _CURVES_CACHE.pop(next(iter(_CURVES_CACHE)))
    _CURVES_CACHE[id(prepared)] = (weakref.ref(prepared), curves)
    return curves


class Curves:
    """The curves of one csg shape: per curve its kind, leaves a and b, an extra int (edge,
    branch) and DATA_FLOATS of data (the cone radii of leaf a, then a face plane of leaf b, an
    edge's end points, or two face planes and the line's parameter range). Listed once per
    prepared tree of the shape (`curves_of`): only `weight(viewpoint)`, the sampling weights
    (about each curve's length in the image), depends on where the curves are seen from."""

    def __init__(self, shape):
        flat = shape.prepared.flat
        to_world = flat.prim_to_world
        self._centre = to_world[:, :3, 3]
        scale = np.linalg.norm(to_world[:, :3, :3], axis=1)           # column lengths per primitive
        spheres = np.flatnonzero(flat.prim_shape == K.SPHERE)
        boxes = np.flatnonzero(flat.prim_shape == K.BOX)
        cones = np.flatnonzero(flat.prim_shape == K.CONE)
        tori = np.flatnonzero(flat.prim_shape == K.TORUS)
        convex = np.flatnonzero(flat.prim_shape == K.CONVEX)
        quadrics = np.flatnonzero(flat.prim_shape == K.QUADRIC)
        r = flat.prim_param
        parts = []                                  # (kind, a, b, extra, length, data)

        def add_edges(p, ends):
            """A polyhedron's or mesh's edges, canonical end points (E, 2, 3)."""
            world = np.einsum("ij,ekj->eki", to_world[p, :3, :3], ends)
            add(POLY_EDGE, np.full(len(ends), p), p, 0, np.linalg.norm(world[:, 1] - world[:, 0], axis=1),
                ends.reshape(-1, 6))

        def add(kind, a, b, extra, length, data=None, head=None):
            """`head`: the first two data floats where not leaf a's parameters."""
            a = np.atleast_1d(a)
            rows = np.zeros((len(a), DATA_FLOATS))
            rows[:, :2] = r[a] if head is None else head
            if data is not None:
                rows[:, 2:2 + np.shape(data)[-1]] = data
            parts.append((np.full(len(a), kind), a, np.broadcast_to(b, a.shape), np.broadcast_to(extra, a.shape),
                          np.broadcast_to(length, a.shape), rows))

        # Face planes (canonical normal, offset) of boxes, convex polyhedra and mesh triangles,
        # one row each, with a world box per face (its leaf's, or the triangle's own).
        face_prim, face_plane, face_lower, face_upper, mesh_corners = [], [], [], [], {}
        for p in boxes:
            for face in range(6):
                normal = np.zeros(3)
                normal[face >> 1] = 1.0 if face & 1 else -1.0
                face_prim.append(p)
                face_plane.append(np.append(normal, 1.0))
        for p in convex:
            start, count = flat.prim_plane_start[p], flat.prim_plane_count[p]
            for plane in flat.planes[start:start + count]:
                face_prim.append(p)
                face_plane.append(plane)
            add_edges(p, _polyhedron_edges(flat.planes[start:start + count], flat.plane_vertices[start]))
        meshes = np.flatnonzero(flat.prim_shape == K.MESH)
        # A mesh's triangles run from its plane start to the next chunk's (engine.lowering).
        chunk_starts = np.unique(np.append(flat.prim_plane_start[np.isin(flat.prim_shape, (K.CONVEX, K.MESH))],
                                           len(flat.planes)))
        for p in meshes:
            start = flat.prim_plane_start[p]
            end = chunk_starts[np.searchsorted(chunk_starts, start, side="right")]
            add_edges(p, _mesh_edges(flat.triangles[start:end], flat.planes[start:end, :3]))
            triangles = flat.triangles[start:end]
            corners = np.einsum("ij,tkj->tki", to_world[p, :3, :3], _triangle_corners(triangles))
            corners += to_world[p, :3, 3]
            mesh_corners[p] = (len(face_prim), corners)            # (first face row, world corners)
            face_prim.extend([p] * len(triangles))
            face_plane.extend(flat.planes[start:end])
            face_lower.extend(corners.min(axis=1))
            face_upper.extend(corners.max(axis=1))
        face_prim = np.array(face_prim, np.int64)
        face_plane = np.array(face_plane).reshape(-1, 4)
        face_lower = np.concatenate([flat.prim_lower[face_prim[:len(face_prim) - len(face_lower)]],
                                     np.reshape(face_lower, (-1, 3))])
        face_upper = np.concatenate([flat.prim_upper[face_prim[:len(face_prim) - len(face_upper)]],
                                     np.reshape(face_upper, (-1, 3))])
        face_size = np.linalg.norm(face_upper - face_lower, axis=1)

        add(SPHERE_SILHOUETTE, spheres, spheres, 0, 2 * np.pi * scale[spheres].max(axis=1))
        for extra in (0, 1, OTHER_PARAMETER, OTHER_PARAMETER | 1):   # equal weights: the mixture's
            add(TORUS_SILHOUETTE, tori, tori, extra, np.pi * (1 + r[tori, 0]) * scale[tori].max(axis=1))
        for k in (0, 1):
            side = np.linalg.norm(np.einsum("pij,pj->pi", to_world[cones, :3, :3],
                                            np.column_stack([r[cones, 1] - r[cones, 0], 0 * cones, 2 + 0 * cones])),
                                  axis=1)
            add(CONE_SILHOUETTE, cones, cones, k, side)
            rim = cones[r[cones, k] > 0]
            add(CIRCLE, rim, rim, k, 2 * np.pi * r[rim, k] * scale[rim, :2].max(axis=1))
        for extra in (0, 1, OTHER_PARAMETER, OTHER_PARAMETER | 1):
            add(QUADRIC_SILHOUETTE, quadrics, quadrics, extra, np.pi * scale[quadrics].max(axis=1))
        rim_radii = np.sqrt(np.maximum(_quadric_cap_squares(r[quadrics]), 0.0))      # (Q, 2) bottom, top
        for k in (0, 1):
            rim = rim_radii[:, k] > 0
            add(CIRCLE, quadrics[rim], quadrics[rim], k,
                2 * np.pi * rim_radii[rim, k] * scale[quadrics[rim], :2].max(axis=1), head=rim_radii[rim])
        corners = np.stack([_box_corners(to_world[p]) for p in boxes]) if len(boxes) else np.zeros((0, 8, 3))
        for e, (i, j) in enumerate(_BOX_EDGES):
            add(SEGMENT, boxes, boxes, e, np.linalg.norm(corners[:, i] - corners[:, j], axis=1))

        def overlapping(first, second):
            """Pairs (i, j) of indices into the two primitive lists whose boxes overlap."""
            if not len(first) or not len(second):
                return np.zeros(0, np.int64), np.zeros(0, np.int64)
            lo, hi = flat.prim_lower, flat.prim_upper
            return np.nonzero(np.all((lo[first, None] <= hi[None, second]) & (lo[None, second] <= hi[first, None]),
                                     axis=2))

        # Faces of the leaves in `second` order: prims with faces, their first face and count.
        with_faces, face_first, face_count = np.unique(face_prim, return_index=True, return_counts=True)

        def near_faces(first, later_and_not_both_meshes=False):
            """Pairs (i, face) of an index into `first` and a face of another leaf whose box
            overlaps leaf first[i]'s (boxes tested per leaf, then expanded to its faces);
            optionally only leaves after first[i] and not two meshes (face pairs: each once,
            and not the triangle pairs of two meshes, which are not listed)."""
            i, k = overlapping(first, with_faces)
            keep = first[i] != with_faces[k]
            if later_and_not_both_meshes:
                mesh = flat.prim_shape == K.MESH
                keep &= (first[i] < with_faces[k]) & ~(mesh[first[i]] & mesh[with_faces[k]])
            i, k = i[keep], k[keep]
            i, f = np.repeat(i, face_count[k]), _ranges(face_first[k], face_count[k])
            # a mesh's triangles only where their own boxes reach the leaf's
            near = np.all((face_lower[f] <= flat.prim_upper[first[i]]) & (flat.prim_lower[first[i]] <= face_upper[f]),
                          axis=1)
            return i[near], f[near]

        i, j = near_faces(spheres)
        p, q = spheres[i], face_prim[j]
        # (a triangle holds at most about pi times its box's diagonal of the circle)
        add(SPHERE_PLANE, p, q, 0, np.minimum(2 * np.pi * scale[p].max(axis=1), np.pi * face_size[j]), face_plane[j])
        i, j = overlapping(spheres, spheres)
        p, q = spheres[i], spheres[j]
        uniform = np.ptp(scale, axis=1) <= 1e-6 * scale.max(axis=1)
        keep = (q > p) & uniform[p] & uniform[q]
        p, q = p[keep], q[keep]
        add(SPHERE_SPHERE, p, q, 0, 2 * np.pi * np.minimum(scale[p].max(axis=1), scale[q].max(axis=1)))
        i, j = near_faces(cones)
        p, q, plane = cones[i], face_prim[j], face_plane[j]
        size = np.minimum(scale[p].max(axis=1), 0.5 * face_size[j])   # (a triangle holds less of the curve)
        # the face's normal in the cone's frame: nearer the axis's direction, parametrize by angle
        normal = np.einsum("pk,pkj->pj", np.einsum("pk,pkj->pj", plane[:, :3], flat.prim_to_canonical[q, :, :3]),
                           to_world[p, :3, :3])
        flat_ish = np.abs(normal[:, 2]) >= np.linalg.norm(normal[:, :2], axis=1)
        add(CONE_PLANE, p[flat_ish], q[flat_ish], 0, 2 * np.pi * size[flat_ish], plane[flat_ish])
        for branch in (0, BRANCH):
            add(CONE_PLANE, p[~flat_ish], q[~flat_ish], BY_HEIGHT | branch, 2 * size[~flat_ish], plane[~flat_ish])
        for cap, k in ((0, 0), (TOP_CAP, 1)):
            crossing = (r[p, k] > 0) & (np.linalg.norm(normal[:, :2], axis=1) > 1e-9 * np.abs(normal[:, 2]))
            add(CAP_PLANE, p[crossing], q[crossing], cap, 2 * r[p[crossing], k] * size[crossing], plane[crossing])
        # Faces of two different box or convex leaves: the line where their planes meet,
        # clipped to the overlap of the leaves' boxes (where the CSG edge can be).
        f, j = near_faces(with_faces, later_and_not_both_meshes=True)
        i = _ranges(face_first[f], face_count[f])             # each face of leaf with_faces[f] ...
        j = np.repeat(j, face_count[f])                       # ... against each nearby face
        keep = np.all((face_lower[i] <= face_upper[j]) & (face_lower[j] <= face_upper[i]), axis=1)
        i, j = i[keep], j[keep]
        if len(i):
            p, q = face_prim[i], face_prim[j]
            normal_p, e_p = _world_planes(flat, p, face_plane[i])
            normal_q, e_q = _world_planes(flat, q, face_plane[j])
            foot, unit, crossing = _plane_line(normal_p, e_p, normal_q, e_q)
            with np.errstate(divide="ignore", invalid="ignore"):
                lo = np.maximum(face_lower[i], face_lower[j])
                hi = np.minimum(face_upper[i], face_upper[j])
                margin = 1e-3 * np.max(hi - lo, axis=1, keepdims=True)
                t1, t2 = (lo - margin - foot) / unit, (hi + margin - foot) / unit
                near = np.max(np.where(np.abs(unit) > 1e-12, np.minimum(t1, t2), -np.inf), axis=1)
                far = np.min(np.where(np.abs(unit) > 1e-12, np.maximum(t1, t2), np.inf), axis=1)
                inside = np.all((np.abs(unit) > 1e-12) | ((foot >= lo - margin) & (foot <= hi + margin)), axis=1)
            crossing &= inside & (near < far) & np.isfinite(near) & np.isfinite(far)
            data = np.column_stack([face_plane[i], face_plane[j], near, far])[crossing]
            add(PLANE_PLANE, p[crossing], q[crossing], 0, (far - near)[crossing], data)
        mesh_list = sorted(mesh_corners)
        for m_i, p in enumerate(mesh_list):
            for q in mesh_list[m_i + 1:]:
                rows = _crossing_triangles(flat, p, q, mesh_corners[p], mesh_corners[q], face_plane)
                if rows is not None:
                    add(PLANE_PLANE, *rows)
        for rows in _surface_pair_curves(flat, overlapping, uniform, mesh_corners):
            add(SURFACE_PAIR, *rows)
        kind, a, b, extra, length, data = (np.concatenate(column) for column in zip(*parts))
        self.count = len(kind)
        self.kind, self.a, self.b = kind.astype(np.uint32), a.astype(np.uint32), b.astype(np.uint32)
        self.extra = extra.astype(np.uint32)
        self.data = data.astype(np.float32)
        self.length = length

    def weight(self, viewpoint: np.ndarray) -> np.ndarray:
        """Each curve's length over its leaf's distance from `viewpoint`."""
        distance = np.maximum(np.linalg.norm(self._centre - viewpoint, axis=1), 1e-9)
        return self.length / distance[self.a]


# ---- Two meshes' triangles ----

# Triangle pairs tested for crossing per numpy block (their boxes first).
_PAIR_BLOCK = 1 << 22


def _world_planes(flat, prim, plane):
    """(q, e) of canonical face planes n . y = d of leaves `prim` (one per plane, or one for
    all) in world space, q . x = e (q = M^-T n unnormalized, as the device's PLANE_PLANE
    evaluation has them)."""
    prim = np.broadcast_to(prim, plane.shape[:1])
    q = np.einsum("fk,fkj->fj", plane[:, :3], flat.prim_to_canonical[prim, :, :3])
    return q, plane[:, 3] + np.einsum("fk,fk->f", q, flat.prim_to_world[prim, :3, 3])


def _plane_line(q_a, e_a, q_b, e_b):
    """(foot, unit, crossing) of the lines where world planes q_a . x = e_a and q_b . x = e_b
    meet: the point nearest the origin, the unit direction q_a x q_b, and whether they cross."""
    direction = np.cross(q_a, q_b)
    d2 = np.einsum("pk,pk->p", direction, direction)
    crossing = d2 > 1e-12 * (np.linalg.norm(q_a, axis=1) * np.linalg.norm(q_b, axis=1)) ** 2
    ab = np.einsum("pk,pk->p", q_a, q_b)
    with np.errstate(divide="ignore", invalid="ignore"):
        foot = (((e_a * np.einsum("pk,pk->p", q_b, q_b) - e_b * ab)[:, None] * q_a
                 + (e_b * np.einsum("pk,pk->p", q_a, q_a) - e_a * ab)[:, None] * q_b) / d2[:, None])
        unit = direction / np.sqrt(d2)[:, None]
    return foot, unit, crossing


def _span_on_line(corners, q, e, foot, unit):
    """(lo, hi) of where triangles (P, 3, 3) cross the planes q . x = e, as positions along
    the lines (foot, unit) in those planes: the crossings of their edges (and their corners on
    the plane); lo > hi where a triangle does not reach its plane."""
    s = np.einsum("pvk,pk->pv", corners, q) - e[:, None]
    tolerance = 1e-9 * np.abs(s).max(axis=1, keepdims=True)
    s = np.where(np.abs(s) <= tolerance, 0.0, s)
    nxt = np.roll(corners, -1, axis=1)
    s_next = np.roll(s, -1, axis=1)
    cuts = s * s_next < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(cuts, s / (s - s_next), 0.0)
    points = corners + w[..., None] * (nxt - corners)
    at = np.einsum("pvk,pk->pv", points - foot[:, None], unit)
    on = np.einsum("pvk,pk->pv", corners - foot[:, None], unit)
    lo = np.minimum(np.where(cuts, at, np.inf).min(axis=1), np.where(s == 0, on, np.inf).min(axis=1))
    hi = np.maximum(np.where(cuts, at, -np.inf).max(axis=1), np.where(s == 0, on, -np.inf).max(axis=1))
    return lo, hi


def _crossing_triangles(flat, p, q, mesh_p, mesh_q, face_plane):
    """PLANE_PLANE rows (a, b, extra, length, data) for the triangles of mesh leaves p and q
    that cross each other: the line of their planes over the segment both triangles hold.
    Candidate pairs by their boxes, in blocks; None where none cross."""
    (first_p, corners_p), (first_q, corners_q) = mesh_p, mesh_q
    lo_p, hi_p = corners_p.min(axis=1), corners_p.max(axis=1)
    lo_q, hi_q = corners_q.min(axis=1), corners_q.max(axis=1)
    near_q = np.flatnonzero(np.all((lo_q <= hi_p.max(axis=0)) & (lo_p.min(axis=0) <= hi_q), axis=1))
    if not len(near_q):
        return None
    step = max(1, _PAIR_BLOCK // len(near_q))
    i_all, j_all = [], []
    for start in range(0, len(corners_p), step):
        block = slice(start, start + step)
        overlap = np.all((lo_p[block, None] <= hi_q[None, near_q]) & (lo_q[None, near_q] <= hi_p[block, None]), axis=2)
        i, j = np.nonzero(overlap)
        i_all.append(i + start)
        j_all.append(near_q[j])
    i, j = np.concatenate(i_all), np.concatenate(j_all)
    if not len(i):
        return None
    plane_i, plane_j = face_plane[first_p + i], face_plane[first_q + j]
    q_i, e_i = _world_planes(flat, p, plane_i)
    q_j, e_j = _world_planes(flat, q, plane_j)
    foot, unit, crossing = _plane_line(q_i, e_i, q_j, e_j)
    lo_a, hi_a = _span_on_line(corners_p[i], q_j, e_j, foot, unit)
    lo_b, hi_b = _span_on_line(corners_q[j], q_i, e_i, foot, unit)
    near, far = np.maximum(lo_a, lo_b), np.minimum(hi_a, hi_b)
    keep = crossing & (near < far) & np.isfinite(near) & np.isfinite(far)
    if not keep.any():
        return None
    data = np.column_stack([plane_i, plane_j, near, far])[keep]
    count = int(keep.sum())
    return np.full(count, p), np.full(count, q), 0, (far - near)[keep], data


# ---- SURFACE_PAIR: curves traced on the host ----

# Grid over leaf a's face on which leaf b's implicit function is sampled (angles get more
# points); a chord's sagitta on a circle of n segments is ~5 / n^2 of its radius.
_GRID_ANGLE, _GRID_OTHER = 96, 40
_CONE_FACES = (0, 1, 2)            # side, bottom cap (z = -1), top cap (z = +1)


def _quadric(param):
    """(a, b, c) of a quadric leaf's side rho^2 = q(z) = a z^2 + b z + c from its params
    (..., 2): c = 1 - a - |b| (engine.shapes)."""
    a, b = np.asarray(param, float)[..., 0], np.asarray(param, float)[..., 1]
    return a, b, 1.0 - a - np.abs(b)


def _quadric_cap_squares(param):
    """Squared radii (..., 2) of a quadric leaf's bottom and top caps, q(-1) and q(+1)."""
    a, b, c = _quadric(param)
    return np.stack([a - b + c, a + b + c], axis=-1)


def _face_grid(shape, face, param):
    """(n1, n2, 3) canonical points covering a face of a sphere, cone, quadric or torus leaf;
    rows and columns wrap where the face does (endpoints repeated)."""
    angle = np.linspace(0.0, 2 * np.pi, _GRID_ANGLE + 1)
    if shape == K.SPHERE:
        theta = np.linspace(0.0, np.pi, _GRID_OTHER + 1)[:, None]
        return np.stack(np.broadcast_arrays(np.sin(theta) * np.cos(angle), np.sin(theta) * np.sin(angle),
                                            np.cos(theta)), axis=-1)
    if shape == K.TORUS:
        tube = np.linspace(0.0, 2 * np.pi, _GRID_OTHER + 1)[:, None]
        ring = 1.0 + param[0] * np.cos(tube)
        return np.stack(np.broadcast_arrays(ring * np.cos(angle), ring * np.sin(angle), param[0] * np.sin(tube)),
                        axis=-1)
    if shape == K.QUADRIC:
        a, b, c = _quadric(param)
        if face == 0:
            z = np.linspace(-1.0, 1.0, _GRID_OTHER + 1)[:, None]
            radius = np.sqrt(np.maximum(a * z * z + b * z + c, 0.0))
        else:
            z = -1.0 if face == 1 else 1.0
            radius = np.linspace(0.0, np.sqrt(max(a + b * z + c, 0.0)), _GRID_OTHER + 1)[:, None]
        return np.stack(np.broadcast_arrays(radius * np.cos(angle), radius * np.sin(angle), z + 0 * angle), axis=-1)
    a, c = 0.5 * (param[0] + param[1]), 0.5 * (param[1] - param[0])
    if face == 0:
        z = np.linspace(-1.0, 1.0, _GRID_OTHER + 1)[:, None]
        radius = a + c * z
    else:
        z = -1.0 if face == 1 else 1.0
        radius = np.linspace(0.0, param[face - 1], _GRID_OTHER + 1)[:, None]
    return np.stack(np.broadcast_arrays(radius * np.cos(angle), radius * np.sin(angle), z + 0 * angle), axis=-1)


def _implicit(flat, prim, face, y):
    """(f, on_face) of a leaf's face at canonical points y (..., 3): f = 0 on its surface,
    and whether the point lies within the face (a cone's side between its caps, a cap's disc,
    a box face's square, a convex face's polygon, a mesh's triangle)."""
    shape, param = flat.prim_shape[prim], flat.prim_param[prim]
    x, yy, z = y[..., 0], y[..., 1], y[..., 2]
    slack = 1e-6
    if shape == K.SPHERE:
        return x * x + yy * yy + z * z - 1.0, np.ones(x.shape, bool)
    if shape == K.TORUS:
        s = x * x + yy * yy + z * z + 1.0 - param[0] ** 2
        return s * s - 4.0 * (x * x + yy * yy), np.ones(x.shape, bool)
    if shape == K.CONE:
        a, c = 0.5 * (param[0] + param[1]), 0.5 * (param[1] - param[0])
        if face == 0:
            return x * x + yy * yy - (a + c * z) ** 2, np.abs(z) <= 1 + slack
        cap = -1.0 if face == 1 else 1.0
        return cap * z - 1.0, x * x + yy * yy <= param[face - 1] ** 2 * (1 + slack)
    if shape == K.QUADRIC:
        a, b, c = _quadric(param)
        if face == 0:
            q = a * z * z + b * z + c
            return x * x + yy * yy - q, (np.abs(z) <= 1 + slack) & (q >= -slack)
        cap = -1.0 if face == 1 else 1.0
        return cap * z - 1.0, x * x + yy * yy <= (a + b * cap + c) * (1 + slack)
    if shape == K.BOX:
        axis, sign = face // 2, 1.0 if face & 1 else -1.0
        others = [k for k in range(3) if k != axis]
        return sign * y[..., axis] - 1.0, np.all(np.abs(y[..., others]) <= 1 + slack, axis=-1)
    if shape == K.MESH:                     # triangle `face`: inside its three edges
        row = flat.prim_plane_start[prim] + face
        plane, corners = flat.planes[row], _triangle_corners(flat.triangles[row:row + 1])[0]
        sides = []
        for k in range(3):
            edge = corners[(k + 1) % 3] - corners[k]
            sides.append(np.cross(edge, y - corners[k]) @ plane[:3] / np.dot(edge, edge))
        sides = np.stack(sides)                         # same sign on all three: inside (any winding)
        return y @ plane[:3] - plane[3], np.all(sides >= -slack, axis=0) | np.all(sides <= slack, axis=0)
    start, count = flat.prim_plane_start[prim], flat.prim_plane_count[prim]   # convex
    planes = flat.planes[start:start + count]
    values = y @ planes[:, :3].T - planes[:, 3]
    others = np.delete(values, face, axis=-1)
    return values[..., face], np.all(others <= slack * (1 + np.abs(np.delete(planes[:, 3], face))), axis=-1)


def _chords(points, f):
    """Chords (M, 2, 3) of the zero set of f (n1, n2) sampled at points (n1, n2, 3): the
    crossings on the grid's edges, joined in each cell (marching squares; a cell crossed on
    all four edges gets two chords, paired in edge order)."""
    s = f >= 0

    def crossing(f1, f2, p1, p2):
        with np.errstate(divide="ignore", invalid="ignore"):
            w = f1 / (f1 - f2)
        return p1 + np.nan_to_num(w)[..., None] * (p2 - p1)
    along = crossing(f[:, :-1], f[:, 1:], points[:, :-1], points[:, 1:])      # (n1, n2-1)
    across = crossing(f[:-1], f[1:], points[:-1], points[1:])                 # (n1-1, n2)
    cut_along, cut_across = s[:, :-1] != s[:, 1:], s[:-1] != s[1:]
    # a cell's edges in order: bottom, right, top, left
    cut = np.stack([cut_along[:-1], cut_across[:, 1:], cut_along[1:], cut_across[:, :-1]], axis=-1)
    at = np.stack([along[:-1], across[:, 1:], along[1:], across[:, :-1]], axis=-2)
    cut, at = cut.reshape(-1, 4), at.reshape(-1, 4, 3)
    count = cut.sum(axis=1)
    two = count == 2
    first = np.argsort(~cut[two], axis=1, kind="stable")[:, :2]
    pairs = [np.take_along_axis(at[two], first[:, :, None], axis=1)]
    four = count == 4
    pairs += [at[four][:, 0:2], at[four][:, 2:4]]
    return np.concatenate(pairs)


def _surface_pair_curves(flat, overlapping, uniform, mesh_corners):
    """Rows for `Curves.add` (a, b, extra, length, data) of the SURFACE_PAIR chords: faces of
    sphere, cone, quadric and torus leaves against faces of other such leaves, and tori and
    quadrics against box and convex faces and mesh triangles (those whose boxes reach the
    leaf's); pairs the closed forms cover are left to them (`uniform`: which leaves have
    uniform scales, whose sphere pairs SPHERE_SPHERE lists; `mesh_corners`: per mesh leaf its
    triangles' world corners)."""
    shape = flat.prim_shape
    curved = np.flatnonzero(np.isin(shape, (K.SPHERE, K.CONE, K.TORUS, K.QUADRIC)))
    faced = np.flatnonzero(np.isin(shape, (K.SPHERE, K.CONE, K.TORUS, K.QUADRIC, K.BOX, K.CONVEX, K.MESH)))
    capped = (K.CONE, K.QUADRIC)
    i, j = overlapping(curved, faced)
    rows = []
    for p, q in zip(curved[i], faced[j]):
        if p == q:
            continue
        sp, sq = shape[p], shape[q]
        flat_q = sq in (K.BOX, K.CONVEX, K.MESH)
        if flat_q and sp not in (K.TORUS, K.QUADRIC):
            continue                      # SPHERE_PLANE, CONE_PLANE, CAP_PLANE
        if sp == K.SPHERE and sq == K.SPHERE and uniform[p] and uniform[q]:
            continue                      # SPHERE_SPHERE
        if not flat_q and p > q:
            continue                      # two curved leaves: once, every face against every face
        faces_p = _CONE_FACES if sp in capped else (0,)
        faces_q = (_CONE_FACES if sq in capped else range(6) if sq == K.BOX
                   else range(flat.prim_plane_count[q]) if sq == K.CONVEX else (0,))
        if sq == K.MESH:
            corners = mesh_corners[q][1]
            faces_q = np.flatnonzero(np.all((corners.min(axis=1) <= flat.prim_upper[p])
                                            & (flat.prim_lower[p] <= corners.max(axis=1)), axis=1))
        for fp in faces_p:
            if fp > 0 and _cap_radius(flat, p, fp) <= 0:
                continue                  # a tip has no cap
            grid = _face_grid(sp, fp, flat.prim_param[p])
            world = grid @ flat.prim_to_world[p, :3, :3].T + flat.prim_to_world[p, :3, 3]
            y_q = world @ flat.prim_to_canonical[q, :, :3].T + flat.prim_to_canonical[q, :, 3]
            for fq in faces_q:
                if sq in capped and fq > 0 and _cap_radius(flat, q, fq) <= 0:
                    continue
                f, _ = _implicit(flat, q, fq, y_q)
                chords = _chords(world, f)
                if not len(chords):
                    continue
                ends_q = chords @ flat.prim_to_canonical[q, :, :3].T + flat.prim_to_canonical[q, :, 3]
                on = np.all(_implicit(flat, q, fq, ends_q)[1], axis=1)
                length = np.linalg.norm(chords[on, 1] - chords[on, 0], axis=1)
                chords, length = chords[on][length > 0], length[length > 0]
                if not len(chords):
                    continue
                plane = np.zeros(4)
                if sq in (K.CONVEX, K.MESH):
                    plane = flat.planes[flat.prim_plane_start[q] + fq]
                data = np.zeros((len(chords), 12))
                data[:, 0:6] = chords.reshape(-1, 6)
                data[:, 6:8] = flat.prim_param[q]
                data[:, 8:12] = plane
                # (a flat face's plane is in the data: its index, which may not fit, is not needed)
                extra = fp | ((0 if flat_q and sq != K.BOX else int(fq)) << 8) | (int(sp) << 16) | (int(sq) << 24)
                rows.append((np.full(len(chords), p), q, extra, length, data))
    return rows


def _cap_radius(flat, prim, face):
    """The radius of a cone's or quadric's cap (face 1 bottom, 2 top) in its canonical frame."""
    if flat.prim_shape[prim] == K.QUADRIC:
        return float(np.sqrt(max(_quadric_cap_squares(flat.prim_param[prim])[face - 1], 0.0)))
    return float(flat.prim_param[prim, face - 1])


def _box_corners(m):
    signs = np.array([[1 if i & 1 else -1, 1 if i & 2 else -1, 1 if i & 4 else -1] for i in range(8)], float)
    return signs @ m[:3, :3].T + m[:3, 3]


def leaf_rows(to_world, prim, active):
    """(M, t) of canonical -> world for primitives, with AD: `to_world` holds 12 per primitive."""
    rows = [dr.gather(mi.Vector4f, to_world, prim * 3 + r, active) for r in range(3)]
    m = mi.Matrix3f(rows[0].x, rows[0].y, rows[0].z, rows[1].x, rows[1].y, rows[1].z,
                    rows[2].x, rows[2].y, rows[2].z)
    return m, mi.Vector3f(rows[0].w, rows[1].w, rows[2].w)


def _basis(w):
    """Two unit vectors orthogonal to unit `w` and to each other (AD-attached to w)."""
    helper = dr.select(dr.abs(w.x) < 0.9, mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0))
    u1 = dr.normalize(dr.cross(w, helper))
    return u1, dr.cross(w, u1)


def _circle(centre, radius, w, phi):
    """Point and tangent (d/dphi) of the circle about unit axis w."""
    u1, u2 = _basis(w)
    c, s = dr.cos(phi), dr.sin(phi)
    return centre + radius * (c * u1 + s * u2), radius * (c * u2 - s * u1)


class _CurvePoint:
    """What every curve's point at u is computed from: the curves' `kind`, `extra` and
    `data` (`Curves`), the matrices (m, t) of their leaves a and b (attached), the `camera`,
    `u`, and what several kinds share: phi = 2 pi u and the camera in leaf a's canonical
    frame. A plain class: it is read by the kinds' functions, not carried through loops."""

    __slots__ = ("kind", "extra", "m_a", "t_a", "m_b", "t_b", "data", "camera", "u", "phi", "cam")

    def __init__(self, kind, extra, m_a, t_a, m_b, t_b, data, camera, u):
        self.kind, self.extra, self.data, self.camera, self.u = kind, extra, data, camera, u
        self.m_a, self.t_a, self.m_b, self.t_b = m_a, t_a, m_b, t_b
        self.phi = dr.two_pi * u
        self.cam = dr.rcp(m_a) @ (camera - t_a)    # the camera in leaf a's canonical frame

    def cone(self):
        """(a, b) of a cone side's radius a + b z from leaf a's radii (data 0, 1)."""
        r0, r1 = self.data[0], self.data[1]
        return 0.5 * (r0 + r1), 0.5 * (r1 - r0)

    def face_plane(self):
        """(n', d'): the plane of a face of leaf b (data 2-5: n . y = d in b's frame) as
        n' . x = d' in leaf a's canonical frame."""
        data = self.data
        q = dr.rcp(self.m_b).T @ mi.Vector3f(data[2], data[3], data[4])
        return self.m_a.T @ q, data[5] - dr.dot(q, self.t_a - self.t_b)

    def branch(self):
        """+1 or -1: the branch of a two-branch curve (bit 0 of `extra`)."""
        return dr.select((self.extra & 1) == 0, 1.0, -1.0)


# ---- Each kind's point, tangent dx/du (dx/dphi for circles) and validity ----

def _sphere_silhouette(c):
    """|x| = 1 and x . cam = 1: centre cam / |cam|^2, radius sqrt(1 - 1 / |cam|^2)."""
    s2 = dr.squared_norm(c.cam)
    x, dx = _circle(c.cam / s2, dr.safe_sqrt(1 - dr.rcp(s2)), dr.normalize(c.cam), c.phi)
    return x, dx, s2 > 1


def _cone_silhouette(c):
    """cos(phi - phi0) = (a + b cam_z) / |cam_xy| at r(z) = a + b z."""
    cam = c.cam
    a_, b_ = c.cone()
    rho = dr.sqrt(cam.x * cam.x + cam.y * cam.y)
    cos_d = (a_ + b_ * cam.z) / rho
    ang = dr.atan2(cam.y, cam.x) + dr.select(c.extra == 0, 1.0, -1.0) * dr.safe_acos(cos_d)
    z = 2 * c.u - 1
    radial = mi.Vector3f(dr.cos(ang), dr.sin(ang), 0)
    return (radial * (a_ + b_ * z) + mi.Vector3f(0, 0, z), radial * (2 * b_) + mi.Vector3f(0, 0, 2),
            (rho > 0) & (dr.abs(cos_d) < 1))


def _torus_silhouette(c):
    """Major radius 1, minor k = data[0]: at angle w about the axis the tube point at v has
    normal n = (cos v cos w, cos v sin w, sin v) and n . x = cos v + k, so n . (x - cam) = 0
    reads F(w, v) = A cos v + B sin v + k = 0 with A = 1 - (cam_x cos w + cam_y sin w), B =
    -cam_z. Each branch is listed twice, parametrized by w = phi (v = atan2(B, A) +- acos(-k /
    |(A, B)|)) and by v = phi (w = w0 +- acos((cos v + k - cam_z sin v) / (|cam_xy| cos v))):
    near a fold of one parametrization (where the contour runs along a meridian, or along a
    parallel) its speed diverges and so would the weights of points sampled there, so the two
    are combined (the balance heuristic, as the host lists them with equal weights): the
    tangent returned is the contour's direction D = x_w F_v - x_v F_w over |F_v| + |F_w|, the
    speed of neither but that of their mixture, bounded."""
    cam, phi = c.cam, c.phi
    k_t = c.data[0]
    by_tube = (c.extra & OTHER_PARAMETER) != 0
    side_t = c.branch()
    cos_p, sin_p = dr.cos(phi), dr.sin(phi)
    A_p, B_t = 1 - (cam.x * cos_p + cam.y * sin_p), -cam.z
    R_t = dr.sqrt(A_p * A_p + B_t * B_t)
    v_of_w = dr.atan2(B_t, A_p) + side_t * dr.safe_acos(-k_t / R_t)
    rho_cam = dr.sqrt(cam.x * cam.x + cam.y * cam.y)
    c_v = (cos_p + k_t - cam.z * sin_p) / (rho_cam * cos_p)
    w_of_v = dr.atan2(cam.y, cam.x) + side_t * dr.safe_acos(c_v)
    w_t = dr.select(by_tube, w_of_v, phi)
    v_t = dr.select(by_tube, phi, v_of_w)
    c_w, s_w, cv, sv = dr.cos(w_t), dr.sin(w_t), dr.cos(v_t), dr.sin(v_t)
    A_t = 1 - (cam.x * c_w + cam.y * s_w)
    f_w = (cam.x * s_w - cam.y * c_w) * cv
    f_v = -A_t * sv + B_t * cv
    ring = 1 + k_t * cv
    x_tor = mi.Vector3f(ring * c_w, ring * s_w, k_t * sv)
    x_w = mi.Vector3f(-ring * s_w, ring * c_w, 0)
    x_v = mi.Vector3f(-k_t * sv * c_w, -k_t * sv * s_w, k_t * cv)
    mixture = dr.abs(f_v) + dr.abs(f_w)
    dx_tor = (x_w * f_v - x_v * f_w) / mixture
    valid = dr.select(by_tube, (dr.abs(c_v) <= 1) & (rho_cam * cos_p != 0), R_t > k_t) & (mixture > 0)
    return x_tor, dx_tor, valid


def _quadric_silhouette(c):
    """rho^2 = q(z) = qa z^2 + qb z + qc: at angle phi about the axis, with w = cam_x cos phi +
    cam_y sin phi, (x - cam) . grad g = 0 reads F = L(z) - 2 w rho(z) = 0, L(z) = alpha z +
    beta = (qb + 2 qa cam_z) z + 2 qc + qb cam_z. Listed twice, as the torus's contour: by phi
    (z a root of L^2 = 4 w^2 q(z), a quadratic, where L and w agree in sign) and by the
    height z = 2 u - 1 (phi = phi0 +- acos(L / (2 rho |cam_xy|))), and mixed: the tangent D =
    x_phi F_z - x_z F_phi over |F_z| + pi |F_phi| (z's range is 2, phi's 2 pi)."""
    cam, phi, u = c.cam, c.phi, c.u
    qa, qb = c.data[0], c.data[1]
    qc = 1 - qa - dr.abs(qb)
    alpha, beta = qb + 2 * qa * cam.z, 2 * qc + qb * cam.z
    by_height = (c.extra & OTHER_PARAMETER) != 0
    first = (c.extra & 1) == 0
    w_p = cam.x * dr.cos(phi) + cam.y * dr.sin(phi)
    w4 = 4 * w_p * w_p
    c2, c1, c0 = alpha * alpha - w4 * qa, 2 * alpha * beta - w4 * qb, beta * beta - w4 * qc
    root = dr.safe_sqrt(c1 * c1 - 4 * c2 * c0)
    pivot = -0.5 * (c1 + dr.select(c1 >= 0, root, -root))     # the roots pivot / c2 and c0 / pivot
    z_of_phi = dr.select(first, pivot / c2, c0 / pivot)
    agree = (alpha * z_of_phi + beta) * w_p
    valid_phi = (c1 * c1 >= 4 * c2 * c0) & ((agree > 0) | ((agree == 0) & first))
    z_h = 2 * u - 1
    rho_h = dr.safe_sqrt(qa * z_h * z_h + qb * z_h + qc)
    rho_cam = dr.sqrt(cam.x * cam.x + cam.y * cam.y)
    cos_h = (alpha * z_h + beta) / (2 * rho_h * rho_cam)
    phi_of_z = dr.atan2(cam.y, cam.x) + c.branch() * dr.safe_acos(cos_h)
    valid_z = (dr.abs(cos_h) <= 1) & (rho_h > 0) & (rho_cam > 0)
    z_q = dr.select(by_height, z_h, z_of_phi)
    phi_q = dr.select(by_height, phi_of_z, phi)
    c_q, s_q = dr.cos(phi_q), dr.sin(phi_q)
    q_z = qa * z_q * z_q + qb * z_q + qc
    rho_q = dr.safe_sqrt(q_z)
    slope_q = (2 * qa * z_q + qb) / (2 * rho_q)                # d rho / dz
    f_z = alpha - 2 * (cam.x * c_q + cam.y * s_q) * slope_q
    f_phi = -2 * (cam.y * c_q - cam.x * s_q) * rho_q
    x_quad = mi.Vector3f(rho_q * c_q, rho_q * s_q, z_q)
    x_phi = mi.Vector3f(-rho_q * s_q, rho_q * c_q, 0)
    x_z = mi.Vector3f(slope_q * c_q, slope_q * s_q, 1)
    mixture_q = dr.abs(f_z) + dr.pi * dr.abs(f_phi)
    dx_quad = (x_phi * f_z - x_z * f_phi) / mixture_q
    valid = dr.select(by_height, valid_z, valid_phi) & (dr.abs(z_q) <= 1) & (q_z > 0) & (mixture_q > 0)
    return x_quad, dx_quad, valid


def _rim(c):
    """A cone's rim: the circle z = -1 (extra 0, radius data 0) or +1 (extra 1, data 1)."""
    rim_z = dr.select(c.extra == 0, -1.0, 1.0)
    x, dx = _circle(mi.Vector3f(0, 0, rim_z), dr.select(c.extra == 0, c.data[0], c.data[1]), mi.Vector3f(0, 0, 1),
                    c.phi)
    return x, dx, True


def _box_edge(c):
    """A box edge: between two canonical corners. (Masked: other kinds' `extra` is no edge
    index, and an unmasked gather past the table's end reads whatever memory lies there.)"""
    segment = c.kind == SEGMENT
    corner_i = dr.gather(mi.UInt32, mi.UInt32([i for i, _ in _BOX_EDGES]), c.extra, segment)
    corner_j = dr.gather(mi.UInt32, mi.UInt32([j for _, j in _BOX_EDGES]), c.extra, segment)

    def corner(k):
        return mi.Vector3f(dr.select((k & 1) != 0, 1.0, -1.0), dr.select((k & 2) != 0, 1.0, -1.0),
                           dr.select((k & 4) != 0, 1.0, -1.0))
    ci, cj = corner(corner_i), corner(corner_j)
    return dr.lerp(ci, cj, c.u), cj - ci, True


def _poly_edge(c):
    """A convex polyhedron's or mesh's edge: between the two canonical end points in the data."""
    data = c.data
    end_0, end_1 = mi.Vector3f(data[2], data[3], data[4]), mi.Vector3f(data[5], data[6], data[7])
    return dr.lerp(end_0, end_1, c.u), end_1 - end_0, True


def _sphere_plane(c):
    """A sphere meets the plane of a face of leaf b: n . y = d in b's frame (y = M_b^-1 (x_w -
    t_b)), that is q . (x_w - t_b) = d with q = M_b^-T n; n' . x = d' in a's frame."""
    n_plane, d_plane = c.face_plane()
    n2 = dr.squared_norm(n_plane)
    x, dx = _circle(n_plane * (d_plane / n2), dr.safe_sqrt(1 - d_plane * d_plane / n2), dr.normalize(n_plane), c.phi)
    return x, dx, d_plane * d_plane < n2


def _cone_plane(c):
    """A cone side meets the same plane (in the cone's frame, leaf a): a point at angle phi and
    height z has radius a + b z, so n . x = d' is linear in z for a given phi; by height,
    |n_xy| cos(phi - phi0) = (d' - n_z z) / (a + b z), on two branches."""
    n_plane, d_plane = c.face_plane()
    a_, b_ = c.cone()
    phi, extra = c.phi, c.extra
    by_height = (extra & BY_HEIGHT) != 0
    c_phi = n_plane.x * dr.cos(phi) + n_plane.y * dr.sin(phi)
    dc_phi = -n_plane.x * dr.sin(phi) + n_plane.y * dr.cos(phi)
    denom = b_ * c_phi + n_plane.z
    z_a = (d_plane - a_ * c_phi) / denom
    dz_a = (-a_ * dc_phi * denom - (d_plane - a_ * c_phi) * b_ * dc_phi) / (denom * denom)
    radial_a = mi.Vector3f(dr.cos(phi), dr.sin(phi), 0)
    x_ca = radial_a * (a_ + b_ * z_a) + mi.Vector3f(0, 0, z_a)
    dx_ca = dr.two_pi * (mi.Vector3f(-dr.sin(phi), dr.cos(phi), 0) * (a_ + b_ * z_a)
                         + radial_a * (b_ * dz_a) + mi.Vector3f(0, 0, dz_a))
    n_xy = dr.sqrt(n_plane.x * n_plane.x + n_plane.y * n_plane.y)
    z_h = 2 * c.u - 1
    cos_h = (d_plane - n_plane.z * z_h) / ((a_ + b_ * z_h) * n_xy)
    side = dr.select((extra & BRANCH) != 0, -1.0, 1.0)
    ang_h = dr.atan2(n_plane.y, n_plane.x) + side * dr.safe_acos(cos_h)
    radial_h = mi.Vector3f(dr.cos(ang_h), dr.sin(ang_h), 0)
    x_ch = radial_h * (a_ + b_ * z_h) + mi.Vector3f(0, 0, z_h)
    # d(cos_h)/dz, then d(angle)/dz = -side * dcos / sin(angle - phi0)
    dcos = (-n_plane.z * (a_ + b_ * z_h) - (d_plane - n_plane.z * z_h) * b_) / ((a_ + b_ * z_h) ** 2 * n_xy)
    dang = -side * dcos * dr.rsqrt(dr.maximum(1 - cos_h * cos_h, 1e-12))
    dx_ch = 2 * (mi.Vector3f(-dr.sin(ang_h), dr.cos(ang_h), 0) * ((a_ + b_ * z_h) * dang)
                 + radial_h * b_ + mi.Vector3f(0, 0, 1))
    return (dr.select(by_height, x_ch, x_ca), dr.select(by_height, dx_ch, dx_ca),
            dr.select(by_height, dr.abs(cos_h) < 1, (dr.abs(z_a) <= 1) & (denom != 0)))


def _cap_plane(c):
    """A cap (z = -1 or +1, radius data 0 or 1) crossed by the plane: a chord."""
    n_plane, d_plane = c.face_plane()
    top = (c.extra & TOP_CAP) != 0
    cap_z = dr.select(top, 1.0, -1.0)
    cap_r = dr.select(top, c.data[1], c.data[0])
    n_xy = dr.sqrt(n_plane.x * n_plane.x + n_plane.y * n_plane.y)
    e = d_plane - n_plane.z * cap_z
    foot = mi.Vector3f(n_plane.x, n_plane.y, 0) * (e / (n_xy * n_xy)) + mi.Vector3f(0, 0, cap_z)
    along = mi.Vector3f(-n_plane.y, n_plane.x, 0) / n_xy
    half = dr.safe_sqrt(cap_r * cap_r - e * e / (n_xy * n_xy))
    return (foot + along * (half * (2 * c.u - 1)), along * (2 * half),
            (cap_r * cap_r * n_xy * n_xy > e * e) & (n_xy > 0))


def _sphere_sphere(c):
    """Two spheres with uniform scales meet in a circle, in world space."""
    m_a, m_b, t_a, t_b = c.m_a, c.m_b, c.t_a, c.t_b
    r_a, r_b = dr.norm(mi.Vector3f(m_a[0][0], m_a[1][0], m_a[2][0])), dr.norm(mi.Vector3f(m_b[0][0], m_b[1][0],
                                                                                       m_b[2][0]))
    between = t_b - t_a
    dist = dr.norm(between)
    h = (dist * dist + r_a * r_a - r_b * r_b) / (2 * dist)
    x, dx = _circle(t_a + between * (h / dist), dr.safe_sqrt(r_a * r_a - h * h), between / dist, c.phi)
    return x, dx, (dist < r_a + r_b) & (dist > dr.abs(r_a - r_b))


def _plane_plane(c):
    """Two face planes, each q . x = e in world space (q = M^-T n, e = d + q . t): their line,
    from its point nearest the origin along the unit direction over [near, far] of the data."""
    data = c.data
    q_a = dr.rcp(c.m_a).T @ mi.Vector3f(data[2], data[3], data[4])
    q_b = dr.rcp(c.m_b).T @ mi.Vector3f(data[6], data[7], data[8])
    e_a, e_b = data[5] + dr.dot(q_a, c.t_a), data[9] + dr.dot(q_b, c.t_b)
    line = dr.cross(q_a, q_b)
    ab = dr.dot(q_a, q_b)
    foot = ((e_a * dr.squared_norm(q_b) - e_b * ab) * q_a + (e_b * dr.squared_norm(q_a) - e_a * ab) * q_b) \
        / dr.squared_norm(line)
    unit = dr.normalize(line)
    return foot + unit * dr.lerp(data[10], data[11], c.u), unit * (data[11] - data[10]), True


def _surface_pair(c):
    """A chord listed on the host (SURFACE_PAIR), moved onto both leaves' attached surfaces."""
    return _newton_on_pair(c.kind == SURFACE_PAIR, c.extra, c.m_a, c.t_a, c.m_b, c.t_b, c.data, c.u)


# kind -> (its function, whether it gives world points (else leaf a's canonical ones), and
# whether it is a circle, whose tangent is per phi = 2 pi u)
_KINDS = {
    SPHERE_SILHOUETTE: (_sphere_silhouette, False, True),
    CONE_SILHOUETTE: (_cone_silhouette, False, False),
    CIRCLE: (_rim, False, True),
    SEGMENT: (_box_edge, False, False),
    SPHERE_PLANE: (_sphere_plane, False, True),
    CONE_PLANE: (_cone_plane, False, False),
    CAP_PLANE: (_cap_plane, False, False),
    POLY_EDGE: (_poly_edge, False, False),
    TORUS_SILHOUETTE: (_torus_silhouette, False, True),
    QUADRIC_SILHOUETTE: (_quadric_silhouette, False, True),
    SPHERE_SPHERE: (_sphere_sphere, True, True),
    PLANE_PLANE: (_plane_plane, True, False),
    SURFACE_PAIR: (_surface_pair, True, False),
}


def evaluate(kind, extra, m_a, t_a, m_b, t_b, data, camera, u):
    """(world point, world tangent dx/du, valid) of curves at u in [0, 1), attached to the
    matrices (m, t) of the curves' leaves; `data` the curves' DATA_FLOATS floats (`Curves.data`).

    Every lane computes every kind's point (`_KINDS`) and keeps its own: a packet of mixed
    kinds pays for all of them, and no branch is taken."""
    c = _CurvePoint(kind, extra, m_a, t_a, m_b, t_b, data, camera, u)
    zero = mi.Vector3f(0)
    x_c, dx_c, x_w, dx_w = zero, zero, zero, zero
    valid, world, circle = mi.Bool(True), mi.Bool(False), mi.Bool(False)
    for k, (function, in_world, is_circle) in _KINDS.items():
        x_k, dx_k, valid_k = function(c)
        mine = kind == k
        if in_world:
            x_w, dx_w = dr.select(mine, x_k, x_w), dr.select(mine, dx_k, dx_w)
            world |= mine
        else:
            x_c, dx_c = dr.select(mine, x_k, x_c), dr.select(mine, dx_k, dx_c)
        if valid_k is not True:
            valid &= dr.select(mine, valid_k, True)
        if is_circle:
            circle |= mine
    x = dr.select(world, x_w, m_a @ x_c + t_a)
    dx = dr.select(world, dx_w, m_a @ dx_c)
    dx = dr.select(circle, dr.two_pi * dx, dx)
    return x, dx, valid


# Newton steps from a chord's point onto the curve: the chords' sagitta at the host's grid
# is ~1e-3 of the leaf's size, and each step squares the relative error.
NEWTON_STEPS = 2


def _world_surface(m, matrix, offset, shape, face, param, plane, x):
    """(f, grad f) of a leaf's face at world point x: f = g(M^-1 (x - t)), grad f = M^-T grad g."""
    inverse = dr.rcp(matrix)
    g, grad = surface_function(m, shape, face, param, plane, m.Array3f(inverse @ (x - offset)))
    return g, inverse.T @ mi.Vector3f(grad)


def _newton_on_pair(active, extra, m_a, t_a, m_b, t_b, data, u):
    """(world point, dx/du, valid) of SURFACE_PAIR curves: the point at u on the chord
    (data 2-7, world space, detached) moved by Newton steps x -= J^T (J J^T)^-1 F onto
    f_a = 0 and f_b = 0, F attached to the leaves' matrices, J = (grad f_a, grad f_b)
    detached. At F = 0 the step's derivative is -J^T (J J^T)^-1 dF/dparameter: the motion
    of the curve normal to itself."""
    m = ad_module(u)
    face_a, face_b = extra & 0xFF, (extra >> 8) & 0xFF
    shape_a, shape_b = (extra >> 16) & 0xFF, extra >> 24
    start, end = mi.Vector3f(data[2], data[3], data[4]), mi.Vector3f(data[5], data[6], data[7])
    x = dr.lerp(start, end, u)
    no_plane = m.Array4f(0.0)
    plane_b = m.Array4f(data[10], data[11], data[12], data[13])
    valid = mi.Bool(active)
    for _ in range(NEWTON_STEPS):
        f_a, g_a = _world_surface(m, m_a, t_a, shape_a, face_a, (data[0], data[1]), no_plane, x)
        f_b, g_b = _world_surface(m, m_b, t_b, shape_b, face_b, (data[8], data[9]), plane_b, x)
        g_a, g_b = dr.detach(g_a), dr.detach(g_b)
        aa, ab, bb = dr.dot(g_a, g_a), dr.dot(g_a, g_b), dr.dot(g_b, g_b)
        det = aa * bb - ab * ab
        # surfaces that touch (parallel gradients) have no transversal curve there
        valid &= det > 1e-6 * aa * bb
        det = dr.select(valid, det, 1.0)
        lam_a, lam_b = (bb * f_a - ab * f_b) / det, (aa * f_b - ab * f_a) / det
        x = x - dr.select(valid, lam_a * g_a + lam_b * g_b, 0.0)
    # a point the steps carried off its chord's neighbourhood did not converge
    valid &= dr.norm(dr.detach(x) - dr.lerp(start, end, u)) <= dr.norm(end - start) + 1e-3 * dr.norm(start)
    return x, end - start, valid
