"""OpenSCAD's 2D geometry and extrusions, with OpenSCAD's own facets (manifold3d).

A 2D subtree (`square`, `circle`, `polygon`, their unions, differences, intersections and
`multmatrix` placements) becomes a `manifold3d.CrossSection`; `linear_extrude` and
`rotate_extrude` turn it into a closed triangle mesh, a `Mesh` leaf. Unlike the 3D primitives,
which we trace exactly, a 2D circle *is* a polygon in OpenSCAD: its `$fn`, `$fa`, `$fs`
decide the facets of the extrusion, so we use OpenSCAD's fragment rule and vertex placement,
and the mesh we trace is the solid OpenSCAD renders.
"""
from __future__ import annotations

import math

import numpy as np

from ...model.mesh import Mesh

GRID_FINE = 0.00000095367431640625      # OpenSCAD's smallest radius with more than 3 fragments


def fragments(r: float, fn: float, fs: float, fa: float) -> int:
    """OpenSCAD's number of segments of a circle of radius r (Calc::get_fragments_from_r)."""
    if r < GRID_FINE:
        return 3
    if fn > 0.0:
        return int(fn) if fn >= 3 else 3
    return int(math.ceil(max(min(360.0 / fa, r * 2.0 * math.pi / fs), 5)))


class Shape2D:
    """A 2D result of the evaluation: a manifold3d CrossSection (possibly empty)."""

    __slots__ = ("section",)

    def __init__(self, section):
        self.section = section


def square(size, center: bool) -> Shape2D:
    import manifold3d as m3
    return Shape2D(m3.CrossSection.square(tuple(size), center=center))


def circle(r: float, fn: float, fs: float, fa: float) -> Shape2D:
    import manifold3d as m3
    n = fragments(r, fn, fs, fa)
    phi = 2.0 * np.pi * np.arange(n) / n
    return Shape2D(m3.CrossSection([np.column_stack([r * np.cos(phi), r * np.sin(phi)])]))


def polygon(points: np.ndarray, paths) -> Shape2D:
    """Paths as OpenSCAD fills them: every path an outline, overlaps by the even-odd rule."""
    import manifold3d as m3
    contours = [points[list(p)] for p in paths] if paths else [points]
    return Shape2D(m3.CrossSection(contours, m3.FillRule.EvenOdd))


def combine(kind: str, shapes: list[Shape2D]) -> Shape2D:
    import manifold3d as m3
    sections = [s.section for s in shapes]
    op = {"union": m3.OpType.Add, "difference": m3.OpType.Subtract, "intersection": m3.OpType.Intersect}[kind]
    return Shape2D(m3.CrossSection.batch_boolean(sections, op) if len(sections) > 1 else sections[0])


def transform(shape: Shape2D, matrix: np.ndarray) -> Shape2D:
    """The xy part of a 3D multmatrix, as OpenSCAD applies it to 2D children."""
    m = np.array([[matrix[0, 0], matrix[0, 1], matrix[0, 3]], [matrix[1, 0], matrix[1, 1], matrix[1, 3]]])
    return Shape2D(shape.section.transform(m))


def offset(shape: Shape2D, r: float | None, delta: float | None, chamfer: bool, fn: float, fs: float,
           fa: float) -> Shape2D:
    """OpenSCAD's offset(): by `r` with round corners of OpenSCAD's fragments for |r|, or by
    `delta` with sharp (mitred) corners, cut square when `chamfer` (Clipper's joins, as
    OpenSCAD uses them)."""
    import manifold3d as m3
    if r is not None:
        n = fragments(abs(r), fn, fs, fa)
        return Shape2D(shape.section.offset(r, m3.JoinType.Round, 2.0, n))
    join = m3.JoinType.Square if chamfer else m3.JoinType.Miter
    return Shape2D(shape.section.offset(delta, join, 1e6, 0))


def scaled(shape: Shape2D, sx: float, sy: float) -> Shape2D:
    return Shape2D(shape.section.scale((sx, sy)))


def is_empty(shape: Shape2D) -> bool:
    return shape.section.is_empty() or shape.section.area() <= 0.0


def linear_extrude(shape: Shape2D, height: float, center: bool, twist: float, slices: int | None,
                   scale, fn: float, fs: float, fa: float) -> Mesh:
    """OpenSCAD's linear_extrude: positive twist turns clockwise seen from +z (left-handed)."""
    import manifold3d as m3
    if slices is None:
        slices = 1 if twist == 0.0 else helix_slices(_largest_radius(shape), height, twist, fn, fs, fa)
    solid = m3.Manifold.extrude(shape.section, height, n_divisions=max(1, slices), twist_degrees=-twist,
                                scale_top=tuple(scale))
    if center:
        solid = solid.translate((0.0, 0.0, -0.5 * height))
    return Mesh.from_manifold(solid)


def helix_slices(r: float, height: float, twist: float, fn: float, fs: float, fa: float) -> int:
    """OpenSCAD's slice count of a twisted extrusion (Calc::get_helix_slices): at least one
    slice per 120 degrees; with $fn, $fn slices per turn; otherwise the fewer of one per
    $fa degrees and one per $fs of the outermost vertex's helix length."""
    twist = abs(twist)
    least = max(int(math.ceil(twist / 120.0)), 1)
    if r < GRID_FINE:
        return least
    if fn > 0.0:
        return max(int(math.ceil(twist / 360.0 * fn)), least)
    turn = math.radians(twist)
    rise = height / turn
    helix = turn * math.sqrt(r * r + rise * rise)
    return max(min(int(math.ceil(twist / fa)), int(math.ceil(helix / fs))), least)


def _largest_radius(shape: Shape2D) -> float:
    polygons = shape.section.to_polygons()
    return float(max((np.linalg.norm(np.asarray(p), axis=1).max() for p in polygons if len(p)), default=0.0))


def rotate_extrude(shape: Shape2D, angle: float, fn: float, fs: float, fa: float) -> Mesh:
    """The xy outline (x >= 0) swept about z from +x by `angle` degrees (right-handed)."""
    import manifold3d as m3
    (_, _), (x1, _) = np.reshape(shape.section.bounds(), (2, 2))
    n = fragments(x1, fn, fs, fa)
    solid = m3.Manifold.revolve(shape.section, n, abs(angle))
    if angle < 0:
        solid = solid.mirror((0.0, 1.0, 0.0))
    return Mesh.from_manifold(solid)


# ---- OpenSCAD's facets of 3D primitives, for hull() and minkowski() ----
# OpenSCAD computes hulls and Minkowski sums of its faceted solids; their vertices are what
# matters for convex operands, so only the points are built here.

def circle_points(r: float, n: int) -> np.ndarray:
    phi = 2.0 * np.pi * np.arange(n) / n
    return np.column_stack([r * np.cos(phi), r * np.sin(phi)])


def sphere_points(r: float, fn: float, fs: float, fa: float) -> np.ndarray:
    """OpenSCAD's sphere: (fragments + 1) // 2 rings at polar angles pi (i + 1/2) / rings."""
    n = fragments(r, fn, fs, fa)
    rings = (n + 1) // 2
    polar = np.pi * (np.arange(rings) + 0.5) / rings
    return np.vstack([np.column_stack([circle_points(r * math.sin(p), n), np.full(n, r * math.cos(p))])
                      for p in polar])


def cylinder_points(h: float, r1: float, r2: float, center: bool, fn: float, fs: float, fa: float) -> np.ndarray:
    n = fragments(max(r1, r2), fn, fs, fa)
    z0 = -0.5 * h if center else 0.0
    ends = []
    for r, z in ((r1, z0), (r2, z0 + h)):
        ends.append(np.array([[0.0, 0.0, z]]) if r == 0 else np.column_stack([circle_points(r, n), np.full(n, z)]))
    return np.vstack(ends)


def cube_points(size, center: bool) -> np.ndarray:
    corners = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)]) * np.asarray(size)
    return corners - 0.5 * np.asarray(size) if center else corners


def convex_solid(points: np.ndarray):
    """The convex hull of points as a ConvexPolyhedron (a Mesh beyond CONVEX_LEAF_PLANES faces)."""
    import manifold3d as m3

    from ...model.polyhedra import CONVEX_LEAF_PLANES, convex_planes
    from ...model.primitives import ConvexPolyhedron
    hull = m3.Manifold.hull_points(np.ascontiguousarray(points, dtype=np.float64))
    if hull.is_empty() or hull.volume() <= 0:
        return None
    mesh = hull.to_mesh64()
    verts = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    tris = np.asarray(mesh.tri_verts, dtype=np.int64).reshape(-1, 3)
    planes, problem = convex_planes(verts, [list(t[::-1]) for t in tris])
    if problem is None and len(planes) <= CONVEX_LEAF_PLANES:
        return ConvexPolyhedron(planes)
    return Mesh.from_manifold(hull)


def hull_2d(shapes: list[Shape2D]) -> Shape2D:
    import manifold3d as m3
    return Shape2D(m3.CrossSection.batch_hull([s.section for s in shapes]))


def minkowski_2d_convex(point_sets: list[np.ndarray]) -> Shape2D:
    import manifold3d as m3
    total = point_sets[0]
    for pts in point_sets[1:]:
        total = (total[:, None, :] + pts[None, :, :]).reshape(-1, 2)
    return Shape2D(m3.CrossSection.hull_points(np.ascontiguousarray(total)))
