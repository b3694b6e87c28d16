"""Closed triangle meshes as CSG leaves.

A `Mesh` is any closed, consistently oriented triangle surface with volume: the automaton
only needs a leaf's next boundary crossing and whether it enters or exits, which a
watertight ray/triangle test over the mesh's own BVH gives (`engine.mesh_bvh`,
`engine.shapes`). Validation happens here, once, in float64.
"""
from __future__ import annotations

import warnings

import numpy as np

from ..errors import ModelError
from . import transform as tf
from .nodes import Primitive

MAX_TRIANGLES = 1 << 24        # the hit info word keeps 24 bits of face index
MAX_COORDINATE = 1e15          # float32 products of coordinates stay finite below this


class MeshOrientationWarning(UserWarning):
    """An inside-out mesh was flipped."""


def weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with identical positions (faces re-indexed)."""
    unique, inverse = np.unique(vertices, axis=0, return_inverse=True)
    return unique, inverse.reshape(-1)[faces]


def ruled_mesh(rings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of the solid swept by a polygon through z: `rings` (K, M, 3) holds the
    polygon (the same M corners, in the same order, at K >= 2 heights); neighbouring rings are
    joined by quads split into two triangles and the end rings are capped. Corners that
    coincide (a collapsed edge, a tip) are merged, and the outside found by the volume's sign."""
    import manifold3d as m3
    rings = np.asarray(rings, dtype=np.float64)
    k, m = rings.shape[:2]
    x, y = rings[:, :, 0], rings[:, :, 1]
    areas = (x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y).sum(axis=1)
    if areas[np.argmax(np.abs(areas))] < 0:
        rings = rings[:, ::-1]              # counter-clockwise seen from +z: the sides face out
        areas = -areas
    i = np.arange(m)
    j = (i + 1) % m
    faces = []
    for s in range(k - 1):
        lo, hi = s * m, (s + 1) * m
        faces += [np.column_stack([lo + i, lo + j, hi + j]), np.column_stack([lo + i, hi + j, hi + i])]
    scale = max(float(np.ptp(rings[:, :, :2].reshape(-1, 2), axis=0).max()), 1e-300)
    for end, flip in ((0, True), (k - 1, False)):
        if areas[end] <= 1e-14 * scale * scale:
            continue                       # the polygon collapsed to a line or a point
        cap = np.asarray(m3.triangulate([rings[end, :, :2]]), dtype=np.int64)
        faces.append(end * m + (cap[:, ::-1] if flip else cap))
    vertices, faces = weld(rings.reshape(-1, 3), np.vstack(faces))
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
    if signed_volume(vertices, faces) < 0:
        faces = faces[:, ::-1]
    return vertices, faces


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The volume a closed mesh encloses, negative when its triangles face inward."""
    v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces)
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def orient_consistently(faces: np.ndarray) -> tuple[np.ndarray, bool]:
    """Faces turned so that neighbours agree (each edge used once in each direction), and
    whether any was turned. Formats whose readers accept facets in either order (Geant4's
    tessellated solids) need this; the result's outside is then fixed by `Mesh`'s volume sign.
    Edges not shared by exactly two faces are left for `Mesh` to report."""
    f = np.asarray(faces, dtype=np.int64).copy()
    m = len(f)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    owner = np.tile(np.arange(m), 3)
    key = np.sort(edges, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner, edges = key[order], owner[order], edges[order]
    pair = np.flatnonzero(np.all(key[1:] == key[:-1], axis=1))
    neighbours: list[list[tuple[int, bool]]] = [[] for _ in range(m)]
    for k in pair:
        if (k > 0 and np.all(key[k - 1] == key[k])) or (k + 2 < len(key) and np.all(key[k + 2] == key[k])):
            continue                       # more than two faces at the edge
        a, b = int(owner[k]), int(owner[k + 1])
        same = bool(edges[k, 0] == edges[k + 1, 0])     # both use the edge in the same direction
        neighbours[a].append((b, same))
        neighbours[b].append((a, same))
    flip = np.zeros(m, dtype=bool)
    seen = np.zeros(m, dtype=bool)
    for start in range(m):
        if seen[start]:
            continue
        seen[start] = True
        queue = [start]
        while queue:
            a = queue.pop()
            for b, same in neighbours[a]:
                if not seen[b]:
                    seen[b] = True
                    flip[b] = flip[a] ^ same
                    queue.append(b)
    f[flip] = f[flip][:, ::-1]
    return f, bool(flip.any())


def _checked(vertices, faces, name: str) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
        raise ModelError(f"{name}.vertices: expected an (N, 3) array with N >= 4, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        bad = int(np.flatnonzero(~np.isfinite(v).all(1))[0])
        raise ModelError(f"{name}.vertices: vertex {bad} has NaN or infinite coordinates")
    if np.abs(v).max() > MAX_COORDINATE:
        bad = int(np.argmax(np.abs(v).max(axis=1)))
        raise ModelError(f"{name}.vertices: vertex {bad} lies {np.abs(v[bad]).max():.3g} from the origin; "
                         f"coordinates beyond {MAX_COORDINATE:g} cannot be traced in float32")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
        raise ModelError(f"{name}.faces: expected an (M, 3) array of vertex indices with M >= 4, got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        if not np.all(np.isfinite(f)) or np.any(f != np.round(f)):
            raise ModelError(f"{name}.faces: vertex indices must be integers")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        bad = int(np.flatnonzero((f < 0).any(1) | (f >= len(v)).any(1))[0])
        raise ModelError(f"{name}.faces: triangle {bad} refers to vertex {f[bad].tolist()}, "
                         f"but there are {len(v)} vertices")
    # A triangle with a repeated vertex bounds nothing, and dropping it keeps the surface
    # closed (its two edges cancel). Slivers of three distinct collinear vertices stay: their
    # edges are shared with their neighbours, and the ray test never hits them.
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    if len(f) > MAX_TRIANGLES:
        raise ModelError(f"{name}: {len(f)} triangles; a mesh leaf holds at most {MAX_TRIANGLES}")
    if len(f) < 4:
        raise ModelError(f"{name}: fewer than 4 non-degenerate triangles; a closed solid needs at least 4")
    _check_closed(f, name)
    volume = signed_volume(v, f)
    scale = float(np.ptp(v, axis=0).max()) ** 3
    if abs(volume) <= 1e-12 * scale:
        raise ModelError(f"{name}: the mesh encloses no volume")
    if volume < 0:
        warnings.warn(f"{name}: the triangles are oriented inward (negative volume); flipped them",
                      MeshOrientationWarning, stacklevel=4)
        f = f[:, ::-1].copy()
    return v, f


def _check_closed(f, name: str) -> None:
    """Every directed edge once and its reverse once: closed, manifold along edges, and
    consistently oriented (an inconsistent pair repeats a directed edge)."""
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1
    key = directed[:, 0] * n + directed[:, 1]
    unique, counts = np.unique(key, return_counts=True)
    if np.any(counts > 1):
        a, b = divmod(int(unique[np.argmax(counts > 1)]), n)
        raise ModelError(f"{name}: edge ({a}, {b}) is used twice in the same direction: the triangles are not "
                         "consistently oriented, or more than two meet at the edge")
    reverse = directed[:, 1] * n + directed[:, 0]
    missing = ~np.isin(reverse, unique)
    if np.any(missing):
        a, b = directed[np.argmax(missing)]
        raise ModelError(f"{name}: edge ({int(a)}, {int(b)}) has no opposite triangle: the mesh is not closed")


class Mesh(Primitive):
    """A closed, consistently oriented triangle mesh (outward normals by the right-hand rule).

    `vertices` is (N, 3), `faces` (M, 3) vertex indices. Triangles with a repeated vertex are dropped; a
    mesh oriented inward is flipped with a `MeshOrientationWarning`; an open, non-manifold or
    inconsistently oriented mesh, or one without volume, is a `ModelError` naming the edge.
    """

    __slots__ = ("vertices", "faces")
    canonical_shape = "mesh"
    type_name = "mesh"
    file_parameters = {"vertices": "vertices", "faces": "faces"}

    def __init__(self, vertices, faces, *, material: str | None = None):
        super().__init__(material=material)
        self.vertices, self.faces = _checked(vertices, faces, "Mesh")
        self.vertices.setflags(write=False)
        self.faces.setflags(write=False)

    @classmethod
    def from_manifold(cls, manifold, *, material: str | None = None) -> "Mesh":
        """The triangles of a `manifold3d.Manifold` (its first three vertex properties)."""
        mesh = manifold.to_mesh64()
        vertices = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
        faces = np.asarray(mesh.tri_verts, dtype=np.int64).reshape(-1, 3)
        try:
            return cls(vertices, faces, material=material)
        except ModelError:
            # manifold3d may keep copies of a vertex (property seams): weld them by position.
            return cls(*weld(vertices, faces), material=material)

    def canonical(self):
        # The mesh is its own canonical solid; the kernel reads its triangles and BVH.
        return tf.IDENTITY, (0.0, 0.0), None

    def parameters(self) -> dict:
        return {"vertices": self.vertices.tolist(), "faces": self.faces.tolist()}

    def mesh_key(self) -> tuple:
        return ("mesh", id(self.faces))

    def tessellate(self, segments: int):
        import manifold3d as m3
        return m3.Manifold(m3.Mesh(vert_properties=np.asarray(self.vertices, np.float32),
                                   tri_verts=np.asarray(self.faces, np.uint32)))

    def __repr__(self):
        return f"Mesh(<{len(self.vertices)} vertices, {len(self.faces)} triangles>){self._transform_repr()}"
