"""Convex polyhedra as numpy geometry: planes -> vertices (with the checks a solid needs),
vertices -> planes, closed faces -> planes. Shared by the primitives and the file readers.
"""
from __future__ import annotations

import itertools

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from ..errors import ModelError

# Planes of one convex polyhedron: a GDML polyhedra of 10000 sides has 10002. Checking costs
# O(m log m) time and O(m) memory (qhull); tracing a ray costs O(m), so file readers turn
# hulls of many faces into meshes long before this.
MAX_PLANES = 16_384
# Readers that may choose (OpenSCAD's polyhedra and hulls) make a convex solid of more faces
# a mesh leaf: a ray tests every plane of a convex leaf, but only O(log) triangles of a mesh.
CONVEX_LEAF_PLANES = 256


def checked_polyhedron(planes, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Unit-normal planes and the vertices of a bounded convex polyhedron with volume, or ModelError."""
    p = np.asarray(planes, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 4:
        raise ModelError(f"{name}.planes: expected rows (nx, ny, nz, d), got shape {p.shape}")
    if not 4 <= len(p) <= MAX_PLANES:
        raise ModelError(f"{name}.planes: a closed convex solid needs 4..{MAX_PLANES} planes, "
                         f"got {len(p)}")
    if not np.all(np.isfinite(p)):
        raise ModelError(f"{name}.planes: NaN or infinite entries")
    norms = np.linalg.norm(p[:, :3], axis=1)
    if np.any(norms == 0):
        raise ModelError(f"{name}.planes: plane {int(np.argmin(norms))} has a zero normal")
    p = p / norms[:, None]
    n, d = p[:, :3], p[:, 3]
    scale = max(1.0, float(np.max(np.abs(d))))
    if not _normals_surround_origin(n):
        raise ModelError(f"{name}: the planes do not enclose a bounded solid (it extends to infinity)")
    centre = _chebyshev_centre(n, d, scale)
    if centre is None:
        raise ModelError(f"{name}: the planes enclose no solid (empty or flat intersection)")
    try:
        pts = HalfspaceIntersection(np.column_stack([n, -d]), centre, qhull_options=_QHULL).intersections
    except (QhullError, ValueError) as e:
        raise ModelError(f"{name}: the planes enclose a flat or empty set, not a solid ({str(e).splitlines()[0]})")
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 4 or np.linalg.matrix_rank(pts - pts.mean(axis=0), tol=1e-9 * scale) < 3:
        raise ModelError(f"{name}: the planes enclose a flat or empty set, not a solid")
    verts = np.unique(np.round(pts, 12), axis=0)
    p.setflags(write=False)
    verts.setflags(write=False)
    return p, verts


# Joggled input (about 1e-11 relative): the many coplanar inputs of a polyhedra's ring of
# sides took qhull seconds to merge exactly (3.4 s for 10000 sides), joggled 15 ms.
_QHULL = "QJ"


def _normals_surround_origin(n: np.ndarray) -> bool:
    """The intersection of the half-spaces n_i . x <= d_i is bounded for every d iff no
    direction y != 0 has n_i . y <= 0 for all i, iff the origin lies strictly inside the
    convex hull of the unit normals."""
    try:
        hull = ConvexHull(n, qhull_options=_QHULL)
    except (QhullError, ValueError):
        return False                         # coplanar normals: unbounded along their common normal
    # Facet equations a . x + b <= 0 inside: the origin is inside by a margin iff every b < 0.
    return bool(np.all(hull.equations[:, 3] < -1e-9))


def _chebyshev_centre(n: np.ndarray, d: np.ndarray, scale: float) -> np.ndarray | None:
    """The centre of the largest ball inside {x : n_i . x <= d_i} (unit normals), or None when
    that ball is too small to call the set a solid."""
    # Variables (x, y, z, r): maximize r subject to n_i . x + r <= d_i, 0 <= r <= scale.
    result = linprog(c=[0.0, 0.0, 0.0, -1.0], A_ub=np.column_stack([n, np.ones(len(n))]), b_ub=d,
                     bounds=[(None, None)] * 3 + [(0.0, scale)], method="highs")
    if result.status != 0 or result.x[3] <= 1e-9 * scale:
        return None
    return result.x[:3]


def hull_planes(vertices, max_faces: int | None = None) -> list[tuple]:
    """Outward unit planes (nx, ny, nz, d) of the convex hull of a few `vertices`.

    For small vertex sets (GDML's trd, trap, para: 8 vertices): every vertex triple spans a
    candidate plane, kept if all vertices lie on its inner side. `max_faces` refuses vertex
    sets whose "faces" are not planar (a twisted trap yields more candidate planes).
    """
    v = np.array(vertices, dtype=np.float64)
    scale = max(float(np.max(np.abs(v))), 1e-300)
    tol = 1e-9 * scale
    centre = v.mean(axis=0)
    planes = []
    for i, j, k in itertools.combinations(range(len(v)), 3):
        n = np.cross(v[j] - v[i], v[k] - v[i])
        norm = np.linalg.norm(n)
        if norm <= 1e-12 * scale * scale:
            continue
        n = n / norm
        d = float(n @ v[i])
        if n @ centre > d:
            n, d = -n, -d
        if np.all(v @ n <= d + tol) and not any(np.allclose(q[:3], n, atol=1e-9, rtol=0) and
                                                abs(q[3] - d) <= tol for q in planes):
            planes.append((*n, d))
    if max_faces is not None and len(planes) > max_faces:
        raise ModelError("the faces are not planar (twisted); the parameters are inconsistent")
    if len(planes) < 4:
        raise ModelError("the vertices do not enclose a solid")
    return planes


def convex_planes(points: np.ndarray, faces: list[list[int]]) -> tuple[np.ndarray | None, str | None]:
    """Outward planes (n, d) of a closed convex polyhedron given by faces, or (None, reason).

    Orientation-agnostic (OpenSCAD's faces are clockwise seen from outside, but the inside is
    found from the centroid). Tolerances allow for the 6 significant digits of `.csg` numbers.
    """
    used = np.unique(np.fromiter((i for f in faces for i in f), dtype=np.int64))
    p = points[used]
    scale = max(float(np.max(np.abs(p))), float(np.max(np.ptp(p, axis=0))), 1e-300)
    tol = 2e-5 * scale
    # Closed, consistently oriented surface: every directed edge once, its reverse once.
    edges: dict[tuple[int, int], int] = {}
    for f in faces:
        for a, b in zip(f, f[1:] + f[:1]):
            edges[(a, b)] = edges.get((a, b), 0) + 1
    for (a, b), n in edges.items():
        if n != 1 or edges.get((b, a), 0) != 1:
            return None, (f"a closed convex solid: its faces do not form a closed, consistently "
                          f"oriented surface (edge between points {a} and {b})")
    centre = p.mean(axis=0)
    planes = []
    for k, f in enumerate(faces):
        v = points[f]
        # Newell's normal: area-weighted, counter-clockwise positive.
        nxt = np.roll(v, -1, axis=0)
        normal = np.array([np.sum((v[:, 1] - nxt[:, 1]) * (v[:, 2] + nxt[:, 2])),
                           np.sum((v[:, 2] - nxt[:, 2]) * (v[:, 0] + nxt[:, 0])),
                           np.sum((v[:, 0] - nxt[:, 0]) * (v[:, 1] + nxt[:, 1]))])
        length = np.linalg.norm(normal)
        if length <= 1e-12 * scale * scale:
            continue                                   # zero-area face: no plane
        normal /= length
        offset = float(normal @ v.mean(axis=0))
        if np.max(np.abs(v @ normal - offset)) > tol:
            return None, f"convex: face {k} is not planar"
        if normal @ centre > offset:
            normal, offset = -normal, -offset
        if np.max(p @ normal - offset) > tol:
            return None, f"convex: points lie outside the plane of face {k}"
        planes.append(np.append(normal, offset))
    if not planes:
        return None, "a solid: no face has an area"
    planes = np.array(planes)
    unique = [planes[0]]
    for row in planes[1:]:
        u = np.array(unique)
        if not np.any((np.abs(u[:, :3] @ row[:3] - 1) < 1e-9) & (np.abs(u[:, 3] - row[3]) < tol)):
            unique.append(row)
    return np.array(unique), None
