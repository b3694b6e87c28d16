"""The BVH of a mesh leaf, built once in numpy, and its triangles as the kernel reads them.

Nodes are stored in depth-first order (an inner node's left child is the next node) with the
index of the right child; the upload (`engine.device`) turns them into one record per inner
node holding both children's boxes, which the kernel tests together, visiting the nearer
child first and keeping the other on a small per-lane stack: the nearest crossing found
early culls the boxes behind it. Each triangle is stored with its vertices sorted by vertex
index, so that the edge functions of an edge shared by two triangles are computed from the
same operands in the same order, hence equal and opposite bit for bit (the watertight test, `engine.shapes`): a ray
through an edge or a vertex is never missed. A parity flag says whether the sorted order
reverses the triangle's orientation.
"""
from __future__ import annotations

import numpy as np

LEAF_SIZE = 4           # triangles per BVH leaf at most (the kernel's count field has 4 bits)
STACK_SIZE = 32         # the kernel's per-lane stack: deeper than any BVH built here


class MeshBVH:
    """One mesh's BVH in depth-first order and its triangles in BVH order (float64)."""

    __slots__ = ("lower", "upper", "right", "first", "count", "triangles", "planes")

    def __init__(self, lower, upper, right, first, count, triangles, planes):
        self.lower, self.upper = lower, upper      # (K, 3) node boxes
        self.right = right                         # inner nodes: right child (the left is the next node)
        self.first, self.count = first, count      # leaf triangle range in BVH order; count 0: inner node
        self.triangles = triangles                 # (T, 12): sorted vertices a, b, c as xyz + pad; parity at 3, twice the area at 7
        self.planes = planes                       # (T, 4) outward unit normal and offset per triangle

    @property
    def num_nodes(self) -> int:
        return len(self.right)


def _sah_split(ids, centroid, t_lower, t_upper):
    """(ids in split order, left count) minimizing the surface area heuristic over the
    three axes' centroid orders (area(left) * n_left + area(right) * n_right)."""
    best = None
    n = len(ids)
    for axis in range(3):
        order = ids[np.argsort(centroid[ids, axis], kind="stable")]
        lo, hi = t_lower[order], t_upper[order]
        left = _areas(np.minimum.accumulate(lo), np.maximum.accumulate(hi))
        right = _areas(np.minimum.accumulate(lo[::-1])[::-1], np.maximum.accumulate(hi[::-1])[::-1])
        k = np.arange(1, n)
        cost = left[:-1] * k + right[1:] * (n - k)
        i = int(np.argmin(cost))
        if best is None or cost[i] < best[0]:
            best = (cost[i], order, i + 1)
    return best[1], best[2]


def _areas(lower, upper):
    e = upper - lower
    return e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]


def build(vertices: np.ndarray, faces: np.ndarray) -> MeshBVH:
    """SAH BVH over triangle boxes (centroid orders); median splits deep down, so that no
    path is longer than the kernel's stack."""
    tri = vertices[faces]                                  # (T, 3, 3)
    centroid = tri.mean(axis=1)
    t_lower, t_upper = tri.min(axis=1), tri.max(axis=1)
    order = np.arange(len(faces))
    lower, upper, right, first, count = [], [], [], [], []

    def emit(start: int, end: int, depth: int) -> None:
        index = len(right)
        ids = order[start:end]
        lower.append(t_lower[ids].min(axis=0))
        upper.append(t_upper[ids].max(axis=0))
        right.append(0)
        if end - start <= LEAF_SIZE:
            first.append(start)
            count.append(end - start)
        else:
            if depth >= STACK_SIZE - 1:
                raise ValueError("mesh BVH deeper than the kernel's stack")
            halvings = int(np.ceil(np.log2(max(1.0, (end - start) / LEAF_SIZE))))
            if depth + halvings + 1 < STACK_SIZE - 1:
                order[start:end], mid = _sah_split(ids, centroid, t_lower, t_upper)
            else:                           # median splits always finish within the stack
                c = centroid[ids]
                axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
                mid = (end - start) // 2
                order[start:end] = ids[np.argpartition(c[:, axis], mid)]
            first.append(0)
            count.append(0)
            emit(start, start + mid, depth + 1)
            right[index] = len(right)
            emit(start + mid, end, depth + 1)

    emit(0, len(faces), 0)
    faces = faces[order]
    # Sorted vertex order and its parity against the triangle's own (cyclic) order.
    sort = np.argsort(faces, axis=1)
    sorted_faces = np.take_along_axis(faces, sort, axis=1)
    parity = _odd(sort)
    triangles = np.zeros((len(faces), 12))
    for k in range(3):
        triangles[:, 4 * k:4 * k + 3] = vertices[sorted_faces[:, k]]
    triangles[:, 3] = parity
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    normal = np.cross(b - a, c - a)
    triangles[:, 7] = np.linalg.norm(normal, axis=1)     # twice the area: the kernel's slope
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    planes = np.column_stack([normal, np.einsum("ij,ij->i", normal, a)])
    return MeshBVH(np.array(lower), np.array(upper), np.array(right, np.int64),
                   np.array(first, np.int64), np.array(count, np.int64), triangles, planes)


def _odd(permutation: np.ndarray) -> np.ndarray:
    """1.0 where a permutation of (0, 1, 2) (rows) is odd."""
    p = permutation
    inversions = (p[:, 0] > p[:, 1]).astype(int) + (p[:, 0] > p[:, 2]) + (p[:, 1] > p[:, 2])
    return (inversions % 2).astype(np.float64)
