"""Triangle mesh files as one-leaf models: `csg.load("part.stl")` is a `csg.Mesh`.

PLY and OBJ are read by Mitsuba's own loaders; STL (binary or ASCII) here, as Mitsuba 3 has
no STL reader. Vertices with the same position are welded, because STL repeats every vertex
per facet and OBJ/PLY may split them by normals or texture coordinates: the closedness
check of `Mesh` works on shared vertices.
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..model.mesh import Mesh, weld
from ..errors import ModelError
from .reading import FormatError, read_model_bytes


def load(path, **options) -> Mesh:
    data, source = read_model_bytes(path)
    suffix = Path(source).suffix.lower()
    if suffix == ".stl":
        vertices, faces = _read_stl(data, source)
    else:
        vertices, faces = _read_with_mitsuba(source, suffix[1:])
    vertices, faces = weld(vertices, faces)
    try:
        return Mesh(vertices, faces)
    except ModelError as e:
        raise FormatError(f"{source}: {e}") from e


def _read_with_mitsuba(path: str, kind: str):
    import mitsuba as mi
    try:
        mesh = mi.load_dict({"type": kind, "filename": path, "face_normals": True})
    except Exception as e:                                   # Mitsuba's parser errors
        raise FormatError(f"{path}: {str(e).splitlines()[0]}") from e
    params = mi.traverse(mesh)
    vertices = np.asarray(params["vertex_positions"], dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(params["faces"], dtype=np.int64).reshape(-1, 3)
    return vertices, faces


def _read_stl(data: bytes, path: str):
    if len(data) >= 84:
        (count,) = struct.unpack_from("<I", data, 80)
        if len(data) == 84 + 50 * count:
            record = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
            tris = np.frombuffer(data, record, count, 84)["v"].astype(np.float64)
            return tris.reshape(-1, 3), np.arange(3 * count).reshape(-1, 3)
    text = data.decode("ascii", errors="replace")
    if not text.lstrip().lower().startswith("solid"):
        raise FormatError(f"{path}: neither binary STL (size does not match its triangle count) nor ASCII STL")
    coords = []
    for number, line in enumerate(text.splitlines(), 1):
        words = line.split()
        if words and words[0].lower() == "vertex":
            try:
                xyz = [float(w) for w in words[1:]]
            except ValueError:
                xyz = []
            if len(xyz) != 3 or not all(np.isfinite(xyz)):
                raise FormatError(f"{path}:{number}: a vertex needs three finite numbers, got "
                                  f"{line.strip()[:80]!r}") from None
            coords.append(xyz)
    if not coords or len(coords) % 3:
        raise FormatError(f"{path}: ASCII STL with {len(coords)} vertices, not facets of three")
    vertices = np.array(coords)
    return vertices, np.arange(len(vertices)).reshape(-1, 3)
