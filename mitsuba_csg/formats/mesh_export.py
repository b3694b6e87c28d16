"""Mesh export: the ground-truth triangle mesh of a CSG model, and mesh files.

`to_mesh` evaluates a model with manifold3d's exact mesh Booleans. It is the reference the
kernel is tested against and the "mesh it, then trace triangles" baseline of the benchmarks.
It shares no code with the engine: primitives are meshed from their own parameters (not from
the canonical forms the kernel traces), and the tree is walked as the user wrote it.

Tessellation: every round primitive is approximated by a polyhedron *inscribed* in it
(vertices on the true surface), with `segments` edges around each full circle (sphere
great circles, cone and cylinder rims, both circles of a torus). Its volume is thus a little
below the analytic one, by a relative ~(2 pi / segments)^2 / 6 (0.04 % at 128 segments).
Boxes and convex polyhedra are exact up to float rounding.

`save_mesh` writes binary little-endian PLY, Wavefront OBJ or binary STL (by extension),
with numpy only. PLY and OBJ share vertices between triangles (as in the manifold), so
Mitsuba would interpolate vertex normals across the sharp CSG edges: load them with
`face_normals=True` for flat shading, e.g.
`mi.load_dict({"type": "ply", "filename": "out.ply", "face_normals": True})`.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

import manifold3d as m3

from ..errors import ModelError
from ..model.nodes import DIFFERENCE, INTERSECTION, UNION, Node, Operation

MESH_FORMATS = (".ply", ".obj", ".stl")

_OP_TYPE = {UNION: m3.OpType.Add, INTERSECTION: m3.OpType.Intersect, DIFFERENCE: m3.OpType.Subtract}


# ---- Model -> Manifold ----

def to_mesh(model: Node, segments: int = 64) -> m3.Manifold:
    """The ground-truth mesh of `model` as a `manifold3d.Manifold`, in world coordinates.

    `segments` is the number of edges around every full circle of a round primitive
    (sphere, cone, cylinder, torus tube and ring); spheres round it up to a multiple of 4.
    n-ary operations (and chains of one operation, `a | b | c`, `(a - b) - c`,
    `a - (b | c)`) are evaluated with one `Manifold.batch_boolean` each. The walk is
    iterative, so arbitrarily deep trees work. An empty result (e.g. the intersection of
    disjoint solids) is a valid, empty Manifold. Raises `ModelError` if manifold3d reports
    an error.
    """
    if not isinstance(model, Node):
        raise ModelError(f"to_mesh: expected a CSG model node, got {type(model).__name__}")
    segments = _checked_segments(segments)
    shapes = _ShapeCache(segments)

    result: list = [None]
    # Work items: ("node", node, parent world matrix, output list, slot) or
    # ("op", op kind, operand list, output list, slot). An "op" item is pushed below its
    # operands' items, so it runs after all of them (postorder).
    work: list = [("node", model, np.eye(4), result, 0)]
    while work:
        item = work.pop()
        if item[0] == "op":
            _, kind, operands, out, slot = item
            out[slot] = _boolean(operands, kind)
            continue
        if item[0] == "transform":
            _, matrix, local, out, slot = item
            out[slot] = local[0].transform(np.ascontiguousarray(matrix[:3, :]))
            continue
        _, node, parent, out, slot = item
        world = parent @ node.matrix
        if not isinstance(node, Operation):
            out[slot] = shapes.primitive(node, world)
            continue
        if np.linalg.det(world[:3, :3]) < 0:
            # A mirrored Boolean is evaluated unmirrored and mirrored afterwards: manifold3d's
            # Booleans of mirrored operands came out wrong on a real model (a 4-operand
            # difference gave 5 % more volume than its own pairwise intersections allow).
            local: list = [None]
            work.append(("transform", world, local, out, slot))
            work.append(("node", node, np.linalg.inv(node.matrix), local, 0))
            continue
        operands = _operands(node, world)
        if len(operands) == 1:                    # union(a), intersection(a), difference(a)
            work.append(("node", operands[0][0], operands[0][1], out, slot))
            continue
        values: list = [None] * len(operands)
        work.append(("op", node.kind, values, out, slot))
        work.extend(("node", child, child_parent, values, i)
                    for i, (child, child_parent) in enumerate(operands))

    mesh = result[0]
    _check_status(mesh, "the CSG result")
    return mesh


def _checked_segments(segments) -> int:
    if isinstance(segments, bool) or not isinstance(segments, (int, np.integer)):
        raise ModelError(f"segments: expected an integer >= 3, got {segments!r}")
    if not 3 <= int(segments) <= 100_000:
        raise ModelError(f"segments: expected an integer in 3..100000, got {segments}")
    return int(segments)


def _operands(op: Operation, world: np.ndarray) -> list[tuple[Node, np.ndarray]]:
    """Operands of `op` as (node, world matrix of the node's parent), chains flattened.

    Transforms are carried along, so merging a child operation into its parent is exact:
    union/intersection absorb children of the same kind; a difference absorbs a difference
    as its first operand ((a - b) - c = a - b - c) and unions among the subtracted ones
    (a - (b | c) = a - b - c).
    """
    if op.kind != DIFFERENCE:
        flat, stack = [], [(c, world) for c in reversed(op.children)]
        while stack:
            node, parent = stack.pop()
            if isinstance(node, Operation) and node.kind == op.kind:
                inner = parent @ node.matrix
                stack.extend((c, inner) for c in reversed(node.children))
            else:
                flat.append((node, parent))
        return flat

    # Difference: walk down the chain of first operands, collecting what is subtracted.
    head, head_parent = op.children[0], world
    subtracted = [(c, world) for c in op.children[1:]]
    while isinstance(head, Operation) and head.kind == DIFFERENCE:
        inner = head_parent @ head.matrix
        subtracted.extend((c, inner) for c in head.children[1:])   # order is irrelevant
        head, head_parent = head.children[0], inner
    flat, stack = [(head, head_parent)], list(reversed(subtracted))
    while stack:
        node, parent = stack.pop()
        if isinstance(node, Operation) and node.kind == UNION:
            inner = parent @ node.matrix
            stack.extend((c, inner) for c in reversed(node.children))
        else:
            flat.append((node, parent))
    return flat


def _boolean(operands: list, kind: str) -> m3.Manifold:
    try:
        return m3.Manifold.batch_boolean(operands, _OP_TYPE[kind])
    except Exception as exc:  # manifold3d raises plain RuntimeErrors
        raise ModelError(f"to_mesh: manifold3d failed on a {kind} of {len(operands)} operands: {exc}") from exc


def _check_status(mesh: m3.Manifold, what: str) -> None:
    status = mesh.status()
    if status != m3.Error.NoError:
        raise ModelError(f"to_mesh: manifold3d reports {status.name} for {what}")


class _ShapeCache:
    """Primitive meshes in their local frames, built once per call and shared (Manifolds are immutable).

    Each mesh is the primitive's own (`Primitive.tessellate`): made from its parameters
    (radius, size, sides, ...) with manifold3d's constructors, not from the canonical forms
    the kernel traces, so that the reference shares no geometry code with the engine.
    (Convex polyhedra use the vertices the model derives from their planes.)
    """

    def __init__(self, segments: int):
        self.segments = segments
        self.cache: dict = {}   # mesh key -> (mesh, the primitive it was made of)

    def primitive(self, prim: Node, world: np.ndarray) -> m3.Manifold:
        if not np.all(np.isfinite(world)) or np.linalg.det(world[:3, :3]) == 0:
            raise ModelError(f"to_mesh: singular or non-finite world transform on {prim!r}")
        # manifold3d flips the triangles of a mirroring (negative determinant) transform.
        return self.local(prim).transform(np.ascontiguousarray(world[:3, :]))

    def local(self, prim: Node) -> m3.Manifold:
        key = prim.mesh_key()
        entry = self.cache.get(key)
        if entry is None:
            mesh = prim.tessellate(self.segments)
            _check_status(mesh, repr(prim))
            if mesh.is_empty():
                raise ModelError(f"to_mesh: manifold3d built an empty mesh for {prim!r}")
            # The primitive is kept with its mesh: keys made of its arrays' ids stay its own.
            entry = self.cache[key] = (mesh, prim)
        return entry[0]


# ---- Mesh files ----

def mesh_arrays(mesh: m3.Manifold) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) float64, triangles (M, 3) int64, counter-clockwise seen from outside)."""
    m = mesh.to_mesh64()
    verts = np.asarray(m.vert_properties, dtype=np.float64)[:, :3]
    faces = np.asarray(m.tri_verts, dtype=np.int64).reshape(-1, 3)
    return np.ascontiguousarray(verts), faces


def save_mesh(mesh_or_model, path, segments: int = 64) -> Path:
    """Write a mesh (a `manifold3d.Manifold`, or a model meshed with `to_mesh`) to `path`.

    The format follows the extension (any case): `.ply` (binary little endian, float32
    positions, int32 indices), `.obj` (text, 1-based indices) or `.stl` (binary, float32,
    one facet normal per triangle). Returns the path written.
    """
    path = Path(os.fspath(path))
    ext = path.suffix.lower()
    if ext not in MESH_FORMATS:
        raise ModelError(f"save_mesh: unknown mesh format {path.suffix or '(no extension)'!r} in "
                         f"{str(path)!r}; supported: {', '.join(MESH_FORMATS)}")
    if isinstance(mesh_or_model, Node):
        mesh = to_mesh(mesh_or_model, segments)
    elif isinstance(mesh_or_model, m3.Manifold):
        mesh = mesh_or_model
        _check_status(mesh, "the mesh to save")
    else:
        raise ModelError(f"save_mesh: expected a manifold3d.Manifold or a CSG model node, "
                         f"got {type(mesh_or_model).__name__}")
    verts, faces = mesh_arrays(mesh)
    if not np.all(np.isfinite(verts)):
        raise ModelError("save_mesh: the mesh has NaN or infinite vertex positions")
    if len(verts) >= 2 ** 31:
        raise ModelError(f"save_mesh: {len(verts)} vertices is too many for 32-bit indices")
    writer = {".ply": _write_ply, ".obj": _write_obj, ".stl": _write_stl}[ext]
    writer(path, verts, faces)
    return path


def _write_ply(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    header = ("ply\n"
              "format binary_little_endian 1.0\n"
              "comment written by mitsuba-csg\n"
              f"element vertex {len(verts)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\n"
              "property list uchar int vertex_indices\n"
              "end_header\n")
    face_rows = np.empty(len(faces), dtype=np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
    face_rows["n"] = 3
    face_rows["v"] = faces
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(verts.astype("<f4").tobytes())
        f.write(face_rows.tobytes())


def _write_obj(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    # float32-exact text (9 significant digits), so OBJ and PLY load to the same positions.
    v = verts.astype(np.float32).astype(np.float64)
    with open(path, "w", encoding="ascii", newline="\n") as f:
        f.write(f"# written by mitsuba-csg: {len(verts)} vertices, {len(faces)} triangles\n")
        if len(v):
            np.savetxt(f, v, fmt="v %.9g %.9g %.9g")
        if len(faces):
            np.savetxt(f, faces + 1, fmt="f %d %d %d")


def _write_stl(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    tri = verts[faces]                                              # (M, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    rows = np.zeros(len(faces), dtype=np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)),
                                                ("attr", "<u2")]))
    rows["normal"] = normal
    rows["v"] = tri
    # The header must not start with "solid": readers would take the file for ASCII STL.
    header = b"binary STL written by mitsuba-csg".ljust(80, b" ")
    with open(path, "wb") as f:
        f.write(header)
        f.write(np.uint32(len(faces)).astype("<u4").tobytes())
        f.write(rows.tobytes())


def read_stl(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a binary STL: (vertices (N, 3) float64 with exact duplicates merged, triangles (M, 3) int64)."""
    data = Path(os.fspath(path)).read_bytes()
    if len(data) < 84:
        raise ModelError(f"read_stl: {str(path)!r} is too short for a binary STL ({len(data)} bytes)")
    count = int(np.frombuffer(data, "<u4", 1, 80)[0])
    if len(data) != 84 + 50 * count:
        raise ModelError(f"read_stl: {str(path)!r} says {count} triangles but has {len(data)} bytes "
                         f"(expected {84 + 50 * count}; ASCII STL is not supported)")
    rows = np.frombuffer(data, np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")]),
                         count, 84)
    corners = rows["v"].reshape(-1, 3)
    verts, inverse = np.unique(corners, axis=0, return_inverse=True)
    return verts.astype(np.float64), inverse.reshape(-1, 3).astype(np.int64)
