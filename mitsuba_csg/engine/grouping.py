"""Several CSG solids in one flat tree, so that one kernel finds a ray's nearest surface among them.

A scene with k `csg` shapes would otherwise run k traversals per ray, each from its own root,
each to the end of the ray. Here the shapes' trees are concatenated under a binary tree of
GROUP nodes built by SAH over the shapes' root boxes (`engine.sah`). A GROUP node is not a
set operation: its children are separate solids, and its next event is simply the nearer of
its children's (the automaton's group table returns the closer hit whatever the classes,
and never skips ahead to a sibling's event). With bounded search and near-first order the
group nodes then act as a top-level BVH: the second child is searched only up to the first
child's hit.

Group nodes come first (ids 0 .. G-1, the root 0, parents before children), then each
shape's nodes, primitives, planes and mesh BVH nodes with their indices offset.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import layout as K
from . import sah
from .lowering import FlatTree


@dataclass
class GroupedTree:
    """The combined tree and where each solid's primitives lie in it."""
    flat: FlatTree
    prim_offset: np.ndarray     # (k + 1,): solid s has primitives prim_offset[s] .. prim_offset[s + 1] - 1

    def solid_of_prim(self) -> np.ndarray:
        """Per primitive of the combined tree, the index of its solid."""
        return np.repeat(np.arange(len(self.prim_offset) - 1), np.diff(self.prim_offset))


def _concatenated(parts: list, empty) -> np.ndarray:
    return np.concatenate(parts) if parts else empty


def group_trees(flats: list[FlatTree]) -> GroupedTree:
    """One tree whose hits are the nearest surface of any of `flats` (at least two solids)."""
    if len(flats) < 2:
        raise ValueError("group_trees needs at least two trees")
    k = len(flats)
    roots_lower = np.array([f.node_lower[f.root] for f in flats], np.float64)
    roots_upper = np.array([f.node_upper[f.root] for f in flats], np.float64)
    weight = np.array([max(1, f.num_nodes) for f in flats], np.float64)
    g_left, g_right, _ = sah.build(roots_lower, roots_upper, weight, np.array([0]), np.array([k]))
    n_groups = len(g_left)

    node_offset = n_groups + np.concatenate([[0], np.cumsum([f.num_nodes for f in flats])])
    prim_offset = np.concatenate([[0], np.cumsum([f.num_prims for f in flats])]).astype(np.int64)
    plane_counts = [0 if f.planes is None else len(f.planes) for f in flats]
    plane_offset = np.concatenate([[0], np.cumsum(plane_counts)]).astype(np.int64)
    mesh_counts = [0 if f.mesh_right is None else len(f.mesh_right) for f in flats]
    mesh_offset = np.concatenate([[0], np.cumsum(mesh_counts)]).astype(np.int64)

    # ---- Nodes: the groups, then each solid's tree ----
    def shifted_nodes(s, f):
        ops = f.node_kind != K.LEAF
        left = np.where(ops, f.node_left + node_offset[s], f.node_left + prim_offset[s])
        right = np.where(ops, f.node_right + node_offset[s], -1)
        parent = np.where(f.node_parent >= 0, f.node_parent + node_offset[s], -1)
        return left, right, parent

    shifted = [shifted_nodes(s, f) for s, f in enumerate(flats)]
    solid_roots = node_offset[:-1] + np.array([f.root for f in flats])

    def ref_id(r):
        """A group child reference (r >= 0: group node r; r < 0: solid -r - 1) as a node id."""
        out = r.copy()
        out[r < 0] = solid_roots[-r[r < 0] - 1]
        return out

    group_left, group_right = ref_id(g_left), ref_id(g_right)
    kind = np.concatenate([np.full(n_groups, K.UNION)] + [f.node_kind for f in flats]).astype(np.int64)
    negative = np.concatenate([np.zeros(n_groups, bool)] + [f.node_negative for f in flats])
    is_group = np.concatenate([np.ones(n_groups, bool)] + [np.zeros(f.num_nodes, bool) for f in flats])
    left = np.concatenate([group_left] + [sh[0] for sh in shifted]).astype(np.int64)
    right = np.concatenate([group_right] + [sh[1] for sh in shifted]).astype(np.int64)
    parent = np.concatenate([np.full(n_groups, -1)] + [sh[2] for sh in shifted]).astype(np.int64)
    parent[group_left] = np.arange(n_groups)
    parent[group_right] = np.arange(n_groups)
    lower = np.vstack([np.zeros((n_groups, 3))] + [f.node_lower for f in flats])
    upper = np.vstack([np.zeros((n_groups, 3))] + [f.node_upper for f in flats])
    height = np.concatenate([np.zeros(n_groups, np.int64)] + [f.node_height for f in flats]).astype(np.int64)
    # Bottom-up over the groups (a group's children have larger ids). A group's box holds
    # its solids' surfaces, whichever side of them is inside: the union of the children's
    # boxes (a co-bounded solid's box bounds its surface too).
    for g in range(n_groups - 1, -1, -1):
        a, b = left[g], right[g]
        lower[g] = np.minimum(lower[a], lower[b])
        upper[g] = np.maximum(upper[a], upper[b])
        height[g] = 1 + max(height[a], height[b])

    # ---- Primitives, planes and mesh BVHs ----
    prim_param = np.vstack([f.prim_param for f in flats]).copy()
    for s, f in enumerate(flats):
        mesh = np.flatnonzero(f.prim_shape == K.MESH) + prim_offset[s]
        prim_param[mesh, 0] += mesh_offset[s]        # a mesh primitive's first param is its BVH root
    plane_vertices = {}
    for s, f in enumerate(flats):
        plane_vertices.update({start + int(plane_offset[s]): v for start, v in f.plane_vertices.items()})
    triangles = [f.triangles if f.triangles is not None and len(f.triangles) == n
                 else np.zeros((n, K.TRIANGLE_FLOATS)) for f, n in zip(flats, plane_counts)]
    with_meshes = [f for f in flats if f.mesh_right is not None and len(f.mesh_right)]
    mesh_right = [f.mesh_right + mesh_offset[s] for s, f in enumerate(flats)
                  if f.mesh_right is not None and len(f.mesh_right)]
    no_ints = np.zeros(0, np.int64)
    flat = FlatTree(
        node_kind=kind, node_negative=negative, node_left=left, node_right=right, node_parent=parent,
        node_lower=lower, node_upper=upper, node_height=height,
        prim_shape=np.concatenate([f.prim_shape for f in flats]),
        prim_to_canonical=np.concatenate([f.prim_to_canonical for f in flats]),
        prim_to_world=np.concatenate([f.prim_to_world for f in flats]),
        prim_param=prim_param,
        prim_plane_start=np.concatenate([f.prim_plane_start + plane_offset[s] for s, f in enumerate(flats)]),
        prim_plane_count=np.concatenate([f.prim_plane_count for f in flats]),
        prim_lower=np.concatenate([f.prim_lower for f in flats]),
        prim_upper=np.concatenate([f.prim_upper for f in flats]),
        prim_material=[m for f in flats for m in f.prim_material],
        planes=_concatenated([f.planes for f in flats if f.planes is not None], np.zeros((0, 4))),
        plane_vertices=plane_vertices,
        triangles=_concatenated(triangles, np.zeros((0, K.TRIANGLE_FLOATS))),
        mesh_lower=_concatenated([f.mesh_lower for f in with_meshes], np.zeros((0, 3))),
        mesh_upper=_concatenated([f.mesh_upper for f in with_meshes], np.zeros((0, 3))),
        mesh_right=_concatenated(mesh_right, no_ints),
        mesh_first=_concatenated([f.mesh_first for f in with_meshes], no_ints),
        mesh_count=_concatenated([f.mesh_count for f in with_meshes], no_ints),
        root=0, node_group=is_group)
    return GroupedTree(flat, prim_offset)
