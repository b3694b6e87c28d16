"""The flat tree on the device: structure-of-arrays buffers the kernel gathers from.

`upload` turns a `FlatTree` (numpy, float64) into float32/uint32 Dr.Jit buffers with one
fixed-size record per node (4 words: flags, children, parent; 8 floats: the padded box) and
per primitive (16 floats), gathered by index times record size, with the set walk's records
that `engine.set_layout` builds. Word layouts are those of `engine.layout`; the gathers at
the end of this module read them back in the kernel.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from . import layout as K
from .backend import Backend, owned
from .lowering import FlatTree
from .neighbours import GRID_WORDS
from .options import TraversalOptions
from .set_layout import NodeArrays, find_sets, set_records
from ..errors import ModelError, TreeTooDeepError

MAX_STACK = 1024        # deepest tree the per-lane stacks are allocated for
MAX_NODES = 1 << 29     # a stack frame holds a node id above 3 bits of its own (engine.automaton)


@dataclass
class KernelTree:
    """A FlatTree on the device: structure-of-arrays with explicit strides."""
    b: Backend
    node_record: object     # UInt32, 4 per node: flags, left child or primitive index, right child, parent
    node_box: object        # Float, 8 per node: lower xyz, 0, upper xyz, 0 (padded outwards; NaN if empty)
    node_wide: object       # Float, 16 per node: its node_record words (as float bits), then an
                            # operation's children's boxes (left lower, upper, right lower, upper; xyz):
                            # one gather per visit where a traversal step tests both children
    set_nodes: object       # Float, 32 per 4-wide node of the sets (engine.set_layout): four child refs
                            # (UInt32 bits: a leaf's node id, or SET_NODE_TAG | a 4-wide node), then
                            # their boxes (lower xyz, upper xyz each; NaN for an empty slot)
    walk_entry: object      # UInt32 per node: where a set walk from it starts (its 4-wide root, or
                            # the node itself for a leaf); a compound member's literal record
    neighbour_entry: object  # UInt32 per node: where a set walk inside at this member's exit starts
                             # (its neighbour tree in set_nodes, engine.neighbours; NO_INDEX: the set's root)
    set_grid: object         # UInt32 per node: a set root's cell grid in set_grids (NO_INDEX: none)
    set_grids: object        # UInt32, GRID_WORDS per cell grid of a set (engine.neighbours.cell_grids)
    cell_entry: object       # UInt32 per grid cell: where a pass from a point in it starts (its tree in
                             # set_nodes; NO_INDEX: the set's root)
    compound_literals: object  # UInt32, COMPOUND_RECORD_WORDS per compound set member: its literals
                               # (layout.LITERAL_COMPLEMENT | leaf node id; NO_INDEX for none),
                               # then their primitives
    prim_start: object      # UInt32, 2 per primitive: its leaf node, and the set that leaf is a member
                            # of (NO_INDEX if none): where a ray starting on the primitive's surface
                            # starts inside a set member (engine.set_walk.next_event's `start_member`)
    walk_stack_size: int    # per-lane entries of the set walk's stack (a size class, as stack_size)
    prim_record: object     # Float, 16 per primitive (layout.PRIM_*)
    planes: object          # Float, 4 per plane (convex faces and mesh triangles)
    triangles: object       # Float, 12 per plane row (mesh triangles; zeros for convex planes)
    mesh_nodes: object      # Float, 8 per mesh BVH node (layout.MESH_NODE_FLOATS)
    root: int
    root_wrapped: bool      # the root is a virtual union over a lone leaf or set
    stack_size: int
    num_nodes: int
    num_prims: int
    max_iterations: int
    extent: float           # largest |coordinate| of the root box (scene frame): the scene's magnitude for ties
    centre: tuple           # world -> scene frame: x' = (x - centre) * inv_scale
    inv_scale: float
    has_meshes: bool        # the kernel includes the mesh BVH walk only where there are mesh leaves
    has_groups: bool = False  # the kernel tests the GROUP flag only where there are group nodes
    has_compounds: bool = False  # the set walk evaluates compound members only where there are some
    has_neighbours: bool = False  # the set walk starts passes from neighbour trees only where there are some
    has_grids: bool = False       # ... and from cell trees
    shape_kinds: frozenset = frozenset(K.SHAPE_CODES.values())   # the leaves' shape codes: the kernel
                                                                  # intersects only these
    options: TraversalOptions = field(default_factory=TraversalOptions)
    # (Dr.Jit type, value) -> the value as an opaque scalar (`opaque`), made once per tree.
    opaque_scalars: dict = field(default_factory=dict, repr=False, compare=False)


def opaque(tree: KernelTree, dtype, value):
    """`value` as an opaque Dr.Jit scalar of `dtype`: a kernel input, not a literal compiled into
    the kernel (a second model, or another tmax, runs the same kernel). Each `dr.opaque` launches
    a memset kernel, a dozen per trace, so a tree keeps the ones it has made."""
    key = (dtype, value)
    scalar = tree.opaque_scalars.get(key)
    if scalar is None:
        scalar = dr.opaque(dtype, value)
        if value == value and len(tree.opaque_scalars) < _MAX_OPAQUE_SCALARS:    # NaN never matches its key
            tree.opaque_scalars[key] = scalar
    return scalar


# Opaque scalars a tree keeps: its own numbers and a few tmin / tmax values of its callers.
_MAX_OPAQUE_SCALARS = 32


def upload(flat: FlatTree, backend: Backend, max_iterations: int | None = None,
           options: TraversalOptions | None = None) -> KernelTree:
    """Copy a FlatTree to device arrays (float32). A lone leaf or set gets a virtual union root."""
    b = backend
    options = options or TraversalOptions()
    nodes = NodeArrays.of(flat)
    marks = find_sets(nodes, flat, options)
    # The automaton starts at an operation and searches leaves and sets as its children.
    wrap = bool(nodes.kind[flat.root] == K.LEAF) or bool(marks.is_set[flat.root])
    if wrap:
        nodes, marks, root = nodes.under_virtual_union(flat.root), marks.extended(2), len(nodes)
    else:
        root = flat.root
    n_nodes = len(nodes)
    if n_nodes >= MAX_NODES:
        raise ModelError(f"the CSG tree has {n_nodes} nodes; the kernel addresses fewer than {MAX_NODES}")
    height = int(flat.node_height.max(initial=0)) + (1 if wrap else 0)
    if height > MAX_STACK:
        raise TreeTooDeepError(f"the CSG tree is {height} operations deep; the kernel allows {MAX_STACK}. "
                               "Optimize it (csg.optimize) or restructure it.")
    # The kernel works in the scene's own frame: the root box centred on the origin, its
    # largest half-side 1. Rays are mapped there on entry (`scene_rays`), hits keep their t,
    # and float32 then traces a scene of any size (a 1e22 mm "infinite" box as well as a
    # micrometre part) the same way (docs/limits.md).
    centre, inv_scale = _scene_frame(nodes.lower[root], nodes.upper[root])
    nodes.lower, nodes.upper = (nodes.lower - centre) * inv_scale, (nodes.upper - centre) * inv_scale
    box = _padded_boxes(nodes.lower, nodes.upper)
    node_record, node_wide = _node_records(nodes, marks.is_set, box)
    walk = set_records(nodes, marks, box, flat, (centre, inv_scale), options, root)
    prim_record, planes, triangles, mesh_nodes = _prim_records(flat, centre, inv_scale)
    root_corners = np.abs(np.concatenate([nodes.lower[root], nodes.upper[root]]))
    extent = float(np.max(root_corners[np.isfinite(root_corners)], initial=0.0))
    if max_iterations is None:
        # Every loop step consumes a distinct primitive event; each event can be re-derived
        # once per ancestor. This bound is far above any real ray and only stops runaways.
        max_iterations = int(min(2**31 - 1, 64 + 8 * n_nodes * (height + 2)))
    tree = KernelTree(
        b=b, node_record=owned(b.UInt32, node_record.astype(np.uint32).ravel()),
        node_box=owned(b.Float, box.astype(np.float32).ravel()), node_wide=owned(b.Float, node_wide.ravel()),
        set_nodes=owned(b.Float, walk.set_nodes.ravel()), walk_entry=owned(b.UInt32, walk.walk_entry),
        neighbour_entry=owned(b.UInt32, walk.neighbour_entry), set_grid=owned(b.UInt32, walk.set_grid),
        set_grids=owned(b.UInt32, walk.grids.ravel() if len(walk.grids) else np.zeros(GRID_WORDS, np.uint32)),
        cell_entry=owned(b.UInt32, walk.cell_entry if len(walk.cell_entry) else np.full(1, K.NO_INDEX, np.uint32)),
        compound_literals=owned(b.UInt32, walk.compound_literals.ravel()),
        prim_start=owned(b.UInt32, walk.prim_start.ravel()),
        walk_stack_size=max(stack_size_class(height), stack_size_class(walk.walk_depth + 1), WALK_STACK_MIN),
        prim_record=owned(b.Float, prim_record.ravel()),
        planes=owned(b.Float, planes.astype(np.float32).ravel()),
        triangles=owned(b.Float, triangles.astype(np.float32).ravel()),
        mesh_nodes=owned(b.Float, mesh_nodes.ravel()),
        root=int(root), root_wrapped=wrap, stack_size=stack_size_class(height), num_nodes=n_nodes,
        num_prims=flat.num_prims, max_iterations=max_iterations, extent=extent,
        centre=tuple(float(c) for c in centre), inv_scale=float(inv_scale),
        has_meshes=bool(np.any(flat.prim_shape == K.MESH)), has_groups=bool(np.any(nodes.group)),
        has_compounds=bool(np.any(marks.is_compound)), has_neighbours=bool(np.any(walk.neighbour_entry != K.NO_INDEX)),
        has_grids=bool(len(walk.grids)),
        shape_kinds=frozenset(int(c) for c in np.unique(flat.prim_shape)), options=options)
    # Made now rather than at a first trace, which may be recorded by dr.freeze (queries.trace_rays).
    for dtype, value in ((b.UInt32, tree.root), (b.UInt32, tree.max_iterations), (b.UInt32, tree.num_prims),
                         (b.Float, tree.extent), (b.Float, tree.inv_scale), *((b.Float, c) for c in tree.centre)):
        opaque(tree, dtype, value)
    return tree


def _padded_boxes(lower, upper) -> np.ndarray:
    """(N, 8) boxes as the kernel stores them: lower xyz, 0, upper xyz, 0, padded outwards.

    An empty box (lower > upper on some axis: the dummy leaf, an intersection of disjoint
    boxes) is stored as NaN: every slab comparison with NaN is false, so the box test
    rejects it. The slab test alone accepts many empty boxes."""
    pad = _box_pad(lower, upper)
    zeros = np.zeros((len(lower), 1))
    box = np.hstack([lower - pad, zeros, upper + pad, zeros])
    box[np.any(lower > upper, axis=1)] = np.nan
    return box


def _node_records(nodes: NodeArrays, sets, box) -> tuple[np.ndarray, np.ndarray]:
    """(node_record (N, 4) uint32, node_wide (N, NODE_WIDE_FLOATS) float32) of the nodes
    (`KernelTree` has their words); `box` their padded boxes in the scene frame."""
    kind, neg, group, left, right, parent = nodes.kind, nodes.negative, nodes.group, nodes.left, nodes.right, \
        nodes.parent
    order, left_high = _child_order(kind, left, right, nodes.lower, nodes.upper)
    own = (neg * K.CHILD_NEGATIVE | (kind == K.LEAF) * K.CHILD_LEAF | sets * K.CHILD_SET).astype(np.uint32)
    ops = kind != K.LEAF
    children = np.zeros(len(kind), np.uint32)
    children[ops] = own[left[ops]] | own[right[ops]] << K.CHILD_BITS
    flags = K.node_flags(kind.astype(np.uint32), neg.astype(np.uint32), order, left_high, group.astype(np.uint32),
                         sets.astype(np.uint32), children)
    node_record = np.stack([flags, left, np.where(right < 0, 0, right), np.where(parent < 0, 0, parent)], 1)
    node_wide = np.zeros((len(kind), K.NODE_WIDE_FLOATS), np.float32)
    node_wide[:, :4] = node_record.astype(np.uint32).view(np.float32)
    for offset, child in ((4, left), (10, right)):
        node_wide[ops, offset:offset + 3] = box[child[ops], 0:3]
        node_wide[ops, offset + 3:offset + 6] = box[child[ops], 4:7]
    return node_record, node_wide


def _prim_records(flat: FlatTree, centre, inv_scale) -> tuple[np.ndarray, ...]:
    """(prim_record, planes, triangles, mesh_nodes): the primitives' records (layout.PRIM_*),
    their maps read from the scene frame, and the planes, triangles and mesh BVH nodes they
    point into (one dummy row where there are none)."""
    prim_record = np.zeros((flat.num_prims, K.PRIM_RECORD_FLOATS), np.float32)
    # world -> canonical after scene -> world (x = centre + x' / inv_scale)
    rows = flat.prim_to_canonical.copy()
    rows[:, :, 3] += rows[:, :, :3] @ centre
    rows[:, :, :3] /= inv_scale
    prim_record[:, K.PRIM_ROWS:K.PRIM_ROWS + 12] = rows.reshape(-1, 12)
    prim_record[:, K.PRIM_PARAMS:K.PRIM_PARAMS + 2] = flat.prim_param
    words = np.stack([flat.prim_plane_start, K.count_shape(flat.prim_plane_count, flat.prim_shape)], 1)
    prim_record[:, K.PRIM_PLANE_START:K.PRIM_COUNT_SHAPE + 1] = words.astype(np.uint32).view(np.float32)
    is_mesh = flat.prim_shape == K.MESH
    mesh_nodes, mesh_refs = _mesh_node_records(flat)
    # A mesh primitive's first param is its BVH root as a child ref (an inner node or a leaf).
    mesh_roots = mesh_refs[flat.prim_param[is_mesh, 0].astype(np.int64)]
    prim_record[is_mesh, K.PRIM_PARAMS] = mesh_roots.view(np.float32)
    prim_record[is_mesh, K.PRIM_PARAMS + 1] = 0
    planes = flat.planes if len(flat.planes) else np.zeros((1, 4))
    triangles = flat.triangles if flat.triangles is not None and len(flat.triangles) else \
        np.zeros((1, K.TRIANGLE_FLOATS))
    return prim_record, planes, triangles, mesh_nodes


def _scene_frame(lower, upper) -> tuple[np.ndarray, float]:
    """(centre, 1 / largest half-side) of the root box; the identity for an empty or unbounded box."""
    half = 0.5 * (np.asarray(upper, np.float64) - np.asarray(lower, np.float64))
    if not (np.all(np.isfinite(half)) and np.all(half >= 0) and half.max() > 0):
        return np.zeros(3), 1.0
    return 0.5 * (np.asarray(upper, np.float64) + np.asarray(lower, np.float64)), 1.0 / float(half.max())


def scene_rays(tree, o, d):
    """(origins, unit directions, k) of rays in the scene frame of `tree`: the point at t on
    a world ray is at t' = k t on the scene ray. Unit directions keep squared lengths inside
    float32 whatever the scene's size; the frame's numbers are opaque values, so a second
    model of another size runs the same kernel."""
    b = tree.b
    inv_scale = opaque(tree, b.Float, tree.inv_scale)
    centre = b.Array3f(*(opaque(tree, b.Float, c) for c in tree.centre))
    length = dr.norm(d)
    usable = length > 0
    unit = dr.select(usable, d / length, d)      # a zero direction stays zero (it misses)
    return (o - centre) * inv_scale, unit, dr.select(usable, length * inv_scale, 1.0)


def _box_pad(lower, upper):
    """How far to widen boxes (tree nodes, mesh BVH nodes) so that float32 rounding never
    culls a hit on the box boundary; 0 for empty or infinite boxes."""
    with np.errstate(invalid="ignore", over="ignore"):
        pad = 1e-5 * (upper - lower) + 1e-6 * np.maximum(np.abs(lower), np.abs(upper)) + 1e-30
    return np.where(np.isfinite(pad) & (upper >= lower), pad, 0.0)


def _mesh_node_records(flat: FlatTree) -> tuple[np.ndarray, np.ndarray]:
    """(inner node records (I, 16) float32, child ref of every BVH node (K,) uint32).

    The BVHs come in depth-first order (an inner node's left child is the next node); the
    kernel reads one record per inner node with both children's boxes (`engine.layout`),
    and a mesh primitive starts from its root's ref (one dummy record when there are no
    meshes)."""
    if flat.mesh_right is None or not len(flat.mesh_right):
        return np.zeros((1, K.MESH_NODE_FLOATS), np.float32), np.zeros(0, np.uint32)
    inner = flat.mesh_count == 0
    rank = np.cumsum(inner) - 1
    ref = np.where(inner, rank, K.mesh_leaf_ref(flat.mesh_first, flat.mesh_count)).astype(np.uint32)
    pad = _box_pad(flat.mesh_lower, flat.mesh_upper)
    lower, upper = flat.mesh_lower - pad, flat.mesh_upper + pad
    parents = np.flatnonzero(inner)
    left, right = parents + 1, flat.mesh_right[parents]
    record = np.zeros((len(parents), K.MESH_NODE_FLOATS), np.float32)
    record[:, 0:3], record[:, 4:7] = lower[left], upper[left]
    record[:, 8:11], record[:, 12:15] = lower[right], upper[right]
    record[:, 3] = ref[left].view(np.float32)
    record[:, 7] = ref[right].view(np.float32)
    if not len(record):                       # every mesh is a single leaf
        record = np.zeros((1, K.MESH_NODE_FLOATS), np.float32)
    return record, ref


def _child_order(kind, left, right, lower, upper):
    """Per node, the ORDER axis along which its children's box centres lie furthest apart
    and whether the left one is higher there (unions and intersections with finite,
    separated child boxes; NO_ORDER otherwise). A difference keeps its order."""
    n = len(kind)
    order = np.full(n, K.NO_ORDER, np.uint32)
    left_high = np.zeros(n, np.uint32)
    ops = np.flatnonzero((kind == K.UNION) | (kind == K.INTERSECTION))
    if len(ops) == 0:
        return order, left_high
    with np.errstate(invalid="ignore", over="ignore"):
        centre = 0.5 * (lower + upper)
        apart = centre[left[ops]] - centre[right[ops]]
    apart = np.where(np.isfinite(apart), apart, 0.0)
    axis = np.argmax(np.abs(apart), axis=1)
    gap = apart[np.arange(len(ops)), axis]
    order[ops] = np.where(gap != 0, axis, K.NO_ORDER)
    left_high[ops] = gap > 0
    return order, left_high


# The set walk's stack holds at least this many entries. Its deepest run of waiting entries
# depends on how SAH happened to shape a set (Cheeses of 200, 260 and 300 holes needed 15, 16
# and 15, hence classes 16, 32, 16), and each class is a kernel of its own: one class for all
# sets of up to some thousands of members lets such models share their kernel.
WALK_STACK_MIN = 32


def stack_size_class(height: int) -> int:
    """Per-lane stack entries for a tree of `height`, rounded up to a power of two (at least 8):
    the size is compiled into the kernel, so models of similar height share one kernel."""
    return max(8, 1 << max(0, int(height) - 1).bit_length())


class PrimRecord:
    """Primitives' records as gathered per lane (`gather_prim`): the rows of their world ->
    canonical maps, shape codes, two shape parameters, and first plane and plane count (convex
    shapes and meshes). A plain class: read by the shapes' functions, not carried in loops."""

    __slots__ = ("rows", "shape", "param", "plane_start", "plane_count")

    def __init__(self, rows, shape, param, plane_start, plane_count):
        self.rows, self.shape, self.param, self.plane_start, self.plane_count = rows, shape, param, plane_start, \
            plane_count


def gather_prim(b, tree, prim, active=True) -> PrimRecord:
    """The records (`PrimRecord`) of primitives."""
    rec = dr.gather(b.module.ArrayXf, tree.prim_record, prim, active, shape=(K.PRIM_RECORD_FLOATS, dr.width(prim)))
    rows = [b.Array4f(rec[4 * r], rec[4 * r + 1], rec[4 * r + 2], rec[4 * r + 3]) for r in range(3)]
    start = dr.reinterpret_array(b.UInt32, rec[K.PRIM_PLANE_START])
    word = dr.reinterpret_array(b.UInt32, rec[K.PRIM_COUNT_SHAPE])
    params = (rec[K.PRIM_PARAMS], rec[K.PRIM_PARAMS + 1])
    return PrimRecord(rows, K.record_shape(word), params, start, K.record_plane_count(word))


class Untraversed:
    """A KernelTree that Dr.Jit does not see into. A symbolic loop takes every local variable
    its body reads as loop state, and a dataclass's arrays with it: the tree's buffers, which no
    iteration changes, made Dr.Jit record each loop body a second time to drop them again.
    Read through this wrapper, the buffers are inputs of the loop, not its state."""
    __slots__ = ("_tree",)

    def __init__(self, tree):
        object.__setattr__(self, "_tree", tree._tree if isinstance(tree, Untraversed) else tree)

    def __getattr__(self, name):
        return getattr(self._tree, name)


def _box_pairs(b, rec, offsets):
    """(lower, upper) Array3f boxes stored as six floats each at `offsets` of a gathered record."""
    return tuple((b.Array3f(rec[k], rec[k + 1], rec[k + 2]), b.Array3f(rec[k + 3], rec[k + 4], rec[k + 5]))
                 for k in offsets)


def node_with_child_boxes(b, tree, node, active=True):
    """(flags, left or primitive, right, left child's box, right child's box) of nodes; a box is
    (lower, upper) as Array3f, meaningful for operation nodes only."""
    rec = dr.gather(b.module.ArrayXf, tree.node_wide, node, active, shape=(K.NODE_WIDE_FLOATS, dr.width(node)))
    words = [dr.reinterpret_array(b.UInt32, rec[i]) for i in range(3)]
    return (*words, *_box_pairs(b, rec, (4, 10)))


def set_node(b, tree, index, active=True):
    """(four child refs, four child boxes as (lower, upper) Array3f) of 4-wide set nodes."""
    rec = dr.gather(b.module.ArrayXf, tree.set_nodes, index, active, shape=(K.SET_NODE_FLOATS, dr.width(index)))
    refs = tuple(dr.reinterpret_array(b.UInt32, rec[i]) for i in range(4))
    return refs, _box_pairs(b, rec, range(4, 28, 6))


def node_record(b, tree, node, active=True):
    """(flags, left or primitive, right, parent) of nodes."""
    rec = dr.gather(b.module.Array4u, tree.node_record, node, active)
    return rec[0], rec[1], rec[2], rec[3]
