"""The flat tree on the device: structure-of-arrays buffers the kernel gathers from.

`upload` turns a `FlatTree` (numpy, float64) into float32/uint32 Dr.Jit buffers with one
fixed-size record per node (4 words: flags, children, parent; 8 floats: the padded box) and
per primitive (16 floats), gathered by index times record size. Word layouts are those of
`engine.layout`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from . import layout as K
from .backend import Backend, owned
from .lowering import FlatTree
from .neighbours import GRID_WORDS, NO_ENTRY, cell_grids, neighbour_trees
from ..errors import ModelError, TreeTooDeepError

MAX_STACK = 1024        # deepest tree the per-lane stacks are allocated for
MAX_NODES = 1 << 29     # a stack frame holds a node id above 3 bits of its own (engine.automaton)
MIN_SET_SIZE = 4
# Fewest members of a hole set given a cell grid: a smaller set's 4-wide tree is two levels
# deep, as shallow as a cell's, and City-343k's 34,300 sets of 8 windows took 620 MB of cell
# trees and 12 s to build.
MIN_GRID_SIZE = 64


class TraversalOptions:
    """Switches of the automaton's traversal mechanisms (all on by default; tests and
    benchmarks turn them off one at a time).

    A plain class: Dr.Jit's symbolic control flow walks dataclasses it finds in loop state
    (the KernelTree) and would try to assign to a frozen one.
    """

    __slots__ = ("restart_at_sibling", "skip_to_sibling", "bounded_search", "near_first", "sets", "pass_through",
                 "min_set_size", "compounds", "neighbour_passes", "cell_passes", "min_grid_size")

    def __init__(self, restart_at_sibling: bool = True, skip_to_sibling: bool = True, bounded_search: bool = True,
                 near_first: bool = True, sets: bool = True, pass_through: bool = True, *,
                 min_set_size: int = MIN_SET_SIZE, compounds: bool = True, neighbour_passes: bool = True,
                 cell_passes: bool = True, min_grid_size: int = MIN_GRID_SIZE):
        self.restart_at_sibling = restart_at_sibling   # a loop restarts the looping child at its sibling's event
        self.skip_to_sibling = skip_to_sibling         # a fresh second child starts at the first child's event
                                                       # when that child fixes the node's state
        self.bounded_search = bounded_search           # otherwise the second child is searched only up to the
                                                       # first child's event (provisional results beyond)
        self.near_first = near_first                   # a fresh union / intersection search starts with the
                                                       # child whose box the ray enters first
        self.sets = sets                               # unions of leaves are searched as n-ary nodes
                                                       # (engine.leaf_events)
        self.pass_through = pass_through               # an operation with a child the ray never meets
                                                       # after t_start is its other child, or a miss
        self.min_set_size = min_set_size               # fewest members of a union searched as a set
        self.compounds = compounds                     # set members may be small intersections and
                                                       # differences of convex leaves, not only leaves
        self.neighbour_passes = neighbour_passes       # a set walk inside at a member's exit searches
                                                       # that member's neighbours (engine.neighbours)
        self.cell_passes = cell_passes                 # a set walk that asks only the state at a point
                                                       # searches the members near its grid cell
        self.min_grid_size = min_grid_size             # fewest members of a set given a grid

    def __repr__(self) -> str:
        return (f"TraversalOptions(restart_at_sibling={self.restart_at_sibling}, "
                f"skip_to_sibling={self.skip_to_sibling}, bounded_search={self.bounded_search}, "
                f"near_first={self.near_first}, sets={self.sets}, pass_through={self.pass_through}, "
                f"min_set_size={self.min_set_size}, compounds={self.compounds}, "
                f"neighbour_passes={self.neighbour_passes}, cell_passes={self.cell_passes}, "
                f"min_grid_size={self.min_grid_size})")


@dataclass
class KernelTree:
    """A FlatTree on the device: structure-of-arrays with explicit strides."""
    b: Backend
    node_record: object     # UInt32, 4 per node: flags, left child or primitive index, right child, parent
    node_box: object        # Float, 8 per node: lower xyz, 0, upper xyz, 0 (padded outwards; NaN if empty)
    node_wide: object       # Float, 16 per node: its node_record words (as float bits), then an
                            # operation's children's boxes (left lower, upper, right lower, upper; xyz):
                            # one gather per visit where a traversal step tests both children
    set_nodes: object       # Float, 32 per 4-wide node of the sets (engine.leaf_events): four child refs
                            # (UInt32 bits: a leaf's node id, or SET_NODE_TAG | a 4-wide node), then
                            # their boxes (lower xyz, upper xyz each; NaN for an empty slot)
    walk_entry: object      # UInt32 per node: where a set walk from it starts (its 4-wide root, or
                            # the node itself for a leaf); a compound member's literal record
    neighbour_entry: object  # UInt32 per node: where a set walk inside at this member's exit starts
                             # (its neighbour tree in set_nodes, engine.neighbours; NO_ENTRY: the set's root);
                             # at a set's root, its cell grid in set_grids (NO_ENTRY: none); after
                             # the nodes, the entry of each grid cell's tree
    set_grids: object        # UInt32, GRID_WORDS per cell grid of a set (engine.neighbours.cell_grids)
    compound_literals: object  # UInt32, COMPOUND_RECORD_WORDS per compound set member: its literals
                               # (layout.LITERAL_COMPLEMENT | leaf node id; NO_LITERAL for none),
                               # then their primitives
    prim_start: object      # UInt32, 2 per primitive: its leaf node, and the set that leaf is a member
                            # of (NO_LEAF if none): where a ray starting on the primitive's surface
                            # starts inside a set member (engine.leaf_events.next_event's `start_member`)
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
    kind, neg = flat.node_kind.copy(), flat.node_negative.copy()
    left, right, parent = flat.node_left.copy(), flat.node_right.copy(), flat.node_parent.copy()
    lower, upper = flat.node_lower.copy(), flat.node_upper.copy()
    group = np.zeros(len(kind), bool) if flat.node_group is None else flat.node_group.copy()
    options = options or TraversalOptions()
    compound = _compound_roots(kind, neg, group, left, right, parent, flat) if options.compounds and options.sets \
        else np.zeros(len(kind), bool)
    sets = _set_roots(kind, neg, group, left, right, parent, flat.node_height, options.min_set_size, compound)
    compound &= _set_owners(sets, compound, kind, left, right) >= 0
    wrap = bool(kind[flat.root] == K.LEAF) or bool(sets[flat.root])
    if wrap:
        # The automaton starts at an operation and searches leaves and sets as its children:
        # root' = union(root, nothing), where the dummy leaf has an empty box, which the box
        # test rejects, so it is never intersected.
        n = len(kind)
        kind = np.concatenate([kind, [K.UNION, K.LEAF]])
        neg = np.concatenate([neg, [False, False]])
        group = np.concatenate([group, [False, False]])
        sets = np.concatenate([sets, [False, False]])
        compound = np.concatenate([compound, [False, False]])
        left = np.concatenate([left, [flat.root, 0]])
        right = np.concatenate([right, [n + 1, -1]])
        parent = np.concatenate([parent, [-1, n]])
        parent[flat.root] = n
        lower = np.vstack([lower, lower[flat.root], [np.inf] * 3])
        upper = np.vstack([upper, upper[flat.root], [-np.inf] * 3])
        root = n
    else:
        root = flat.root
    if len(kind) >= MAX_NODES:
        raise ModelError(f"the CSG tree has {len(kind)} nodes; the kernel addresses fewer than {MAX_NODES}")
    height = int(flat.node_height.max(initial=0)) + (1 if wrap else 0)
    if height > MAX_STACK:
        raise TreeTooDeepError(f"the CSG tree is {height} operations deep; the kernel allows {MAX_STACK}. "
                               "Optimize it (csg.optimize) or restructure it.")
    # The kernel works in the scene's own frame: the root box centred on the origin, its
    # largest half-side 1. Rays are mapped there on entry (`scene_rays`), hits keep their t,
    # and float32 then traces a scene of any size (a 1e22 mm "infinite" box as well as a
    # micrometre part) the same way (docs/limits.md).
    centre, inv_scale = _scene_frame(lower[root], upper[root])
    lower, upper = (lower - centre) * inv_scale, (upper - centre) * inv_scale
    pad = _box_pad(lower, upper)
    # An empty box (lower > upper on some axis: the dummy leaf, an intersection of disjoint
    # boxes) is stored as NaN: every slab comparison with NaN is false, so the box test
    # rejects it. The slab test alone accepts many empty boxes.
    empty = np.any(lower > upper, axis=1)
    zeros = np.zeros((len(lower), 1))
    box = np.hstack([lower - pad, zeros, upper + pad, zeros])
    box[empty] = np.nan
    order, left_high = _child_order(kind, left, right, lower, upper)
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
    set_nodes, walk_entry, pending = _wide_sets(sets, kind, left, right, lower, upper, box, compound)
    owner = _set_owners(sets, compound, kind, left, right)
    neighbour_entry = np.full(len(kind), NO_ENTRY, np.uint32)
    grids = np.zeros((0, GRID_WORDS), np.uint32)
    has_neighbours = False
    if options.sets and (options.neighbour_passes or options.cell_passes):
        leaf = kind == K.LEAF
        convex = leaf & ~np.isin(flat.prim_shape[np.where(leaf, left, 0)], K.NON_CONVEX_SHAPES)
        # Only where rays cross a set's inside outside the solid (holes: a subtracted or
        # complemented set) do its passes from inside matter; elsewhere the trees would cost
        # memory (a Satellites' parts: 23 MB more for 87,500 primitives) and save little.
        holes = sets & _subtracted(kind, neg, left, right, root)
        in_hole = np.where(holes[np.maximum(owner, 0)], owner, -1)
        balls = _sphere_balls(flat, kind, left, centre, inv_scale)
        if options.neighbour_passes:
            trees, neighbour_entry = neighbour_trees(in_hole, box, balls, convex, len(set_nodes))
            has_neighbours = bool(np.any(neighbour_entry != NO_ENTRY))
            if has_neighbours:
                set_nodes = np.concatenate([set_nodes, trees])
        if options.cell_passes:
            cell_records, grids, cells, grid_roots = cell_grids(in_hole, box, balls, len(set_nodes), len(kind),
                                                                options.min_grid_size)
            if len(grids):
                set_nodes = np.concatenate([set_nodes, cell_records])
                neighbour_entry[grid_roots] = np.arange(len(grids), dtype=np.uint32)
                neighbour_entry = np.concatenate([neighbour_entry, cells])
    compound_literals = _compound_literals(compound, kind, left, right, walk_entry)
    prim_start = _prim_start(flat.num_prims, len(flat.node_kind), owner, kind, left)
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
    n_nodes = len(kind)
    root_corners = np.abs(np.concatenate([lower[root], upper[root]]))
    extent = float(np.max(root_corners[np.isfinite(root_corners)], initial=0.0))
    if max_iterations is None:
        # Every loop step consumes a distinct primitive event; each event can be re-derived
        # once per ancestor. This bound is far above any real ray and only stops runaways.
        max_iterations = int(min(2**31 - 1, 64 + 8 * n_nodes * (height + 2)))
    tree = KernelTree(
        b=b, node_record=owned(b.UInt32, node_record.astype(np.uint32).ravel()),
        node_box=owned(b.Float, box.astype(np.float32).ravel()), node_wide=owned(b.Float, node_wide.ravel()),
        set_nodes=owned(b.Float, set_nodes.ravel()), walk_entry=owned(b.UInt32, walk_entry),
        neighbour_entry=owned(b.UInt32, neighbour_entry),
        set_grids=owned(b.UInt32, grids.ravel() if len(grids) else np.zeros(GRID_WORDS, np.uint32)),
        compound_literals=owned(b.UInt32, compound_literals.ravel()),
        prim_start=owned(b.UInt32, prim_start.ravel()),
        walk_stack_size=max(stack_size_class(height), stack_size_class(pending + 1), WALK_STACK_MIN),
        prim_record=owned(b.Float, prim_record.ravel()),
        planes=owned(b.Float, planes.astype(np.float32).ravel()),
        triangles=owned(b.Float, triangles.astype(np.float32).ravel()),
        mesh_nodes=owned(b.Float, mesh_nodes.ravel()),
        root=int(root), root_wrapped=wrap, stack_size=stack_size_class(height), num_nodes=n_nodes,
        num_prims=flat.num_prims, max_iterations=max_iterations, extent=extent,
        centre=tuple(float(c) for c in centre), inv_scale=float(inv_scale),
        has_meshes=bool(np.any(flat.prim_shape == K.MESH)), has_groups=bool(np.any(group)),
        has_compounds=bool(np.any(compound)), has_neighbours=has_neighbours,
        has_grids=bool(len(grids)),
        shape_kinds=frozenset(int(c) for c in np.unique(flat.prim_shape)), options=options)
    # Made now rather than at a first trace, which may be recorded by dr.freeze (queries.trace_rays).
    for dtype, value in ((b.UInt32, tree.root), (b.UInt32, tree.max_iterations), (b.UInt32, tree.num_prims),
                         (b.Float, tree.extent), (b.Float, tree.inv_scale), *((b.Float, c) for c in tree.centre)):
        opaque(tree, dtype, value)
    return tree


def _subtracted(kind, neg, left, right, root) -> np.ndarray:
    """Per node, whether its inside is outside the solid: an odd number of complements and
    differences' right sides on its way from the root."""
    odd = np.zeros(len(kind), bool)
    odd[root] = neg[root]
    frontier = np.array([root])
    while frontier.size:
        frontier = frontier[kind[frontier] != K.LEAF]
        flip_right = kind[frontier] == K.DIFFERENCE
        odd[left[frontier]] = odd[frontier] ^ neg[left[frontier]]
        odd[right[frontier]] = odd[frontier] ^ flip_right ^ neg[right[frontier]]
        frontier = np.concatenate([left[frontier], right[frontier]])
    return odd


def _sphere_balls(flat, kind, left, centre, inv_scale) -> np.ndarray:
    """(centre xyz, radius) per node in the scene frame: a ball holding a sphere leaf (an
    ellipsoid's largest semi-axis as the radius); NaN radius for every other node."""
    balls = np.full((len(kind), 4), np.nan)
    leaves = np.flatnonzero(kind == K.LEAF)
    leaves = leaves[(left[leaves] < flat.num_prims)]
    leaves = leaves[flat.prim_shape[left[leaves]] == K.SPHERE]
    to_world = flat.prim_to_world[left[leaves]]
    balls[leaves, :3] = (to_world[:, :3, 3] - centre) * inv_scale
    balls[leaves, 3] = np.linalg.norm(to_world[:, :3, :3], axis=1).max(axis=1) * inv_scale
    return balls


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


def _levels_bottom_up(kind, height) -> list:
    """The operation nodes in groups of equal height, lowest first: one vectorized step per
    level computes a per-node property from the children's."""
    ops = np.flatnonzero(kind != K.LEAF)
    ops = ops[np.argsort(height[ops], kind="stable")]
    return np.split(ops, np.flatnonzero(np.diff(height[ops])) + 1)


# Leaf shapes whose inside along a ray is one interval: compound members' literals.
_CONVEX_SHAPES = (K.SPHERE, K.BOX, K.CONE, K.CONVEX)


def _compound_roots(kind, neg, group, left, right, parent, flat) -> np.ndarray:
    """Per node, whether it is a compound set member candidate: an intersection or difference
    under a plain union whose subtree is an intersection of at most MAX_COMPOUND_LITERALS
    literals, each a convex leaf or a complement of one (a difference's subtrahend, or a
    union of leaves subtracted: A - (B | C) = A & ~B & ~C). The set walk finds its next event in
    one member visit (`leaf_events.compound_hit`) where the automaton would descend into it,
    as Satellites' wings with their cut-outs made it do."""
    n = len(kind)
    # Literals of the node as an intersection (as_is), and of its complement (negated); -1: none.
    as_is, negated = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    leaves = np.flatnonzero(kind == K.LEAF)
    convex = leaves[np.isin(flat.prim_shape[left[leaves]], _CONVEX_SHAPES) & ~neg[leaves]]
    as_is[convex] = negated[convex] = 1
    limit = K.MAX_COMPOUND_LITERALS

    def total(a, c):
        return np.where((a > 0) & (c > 0) & (a + c <= limit), a + c, -1)
    for at in _levels_bottom_up(kind, flat.node_height):
        plain = ~neg[at] & ~group[at]
        l, r = left[at], right[at]
        as_is[at] = np.where(plain & (kind[at] == K.INTERSECTION), total(as_is[l], as_is[r]),
                             np.where(plain & (kind[at] == K.DIFFERENCE), total(as_is[l], negated[r]), -1))
        negated[at] = np.where(plain & (kind[at] == K.UNION), total(negated[l], negated[r]), -1)
    literals = as_is
    has_parent = parent >= 0
    under_union = np.zeros(n, bool)
    p = parent[has_parent]
    under_union[has_parent] = (kind[p] == K.UNION) & ~neg[p] & ~group[p]
    return (literals > 0) & (kind != K.LEAF) & under_union


def _compound_literals(compound, kind, left, right, walk_entry) -> np.ndarray:
    """Literal records (layout.COMPOUND_RECORD_WORDS words each: the literals, then their leaves'
    primitives, so that a literal's intersection reads no node record) of the compound members,
    whose walk_entry becomes their record's index."""
    roots = np.flatnonzero(compound)
    records = np.full((max(len(roots), 1), K.COMPOUND_RECORD_WORDS), K.NO_LITERAL, np.uint32)
    for index, root in enumerate(roots):
        found, pending = [], [(int(root), False)]
        while pending:
            node, complement = pending.pop()      # complement: the node's complement is wanted
            if kind[node] == K.LEAF:
                found.append(node | (K.LITERAL_COMPLEMENT if complement else 0))
            else:                                 # A & B, A & ~B, or under a complement ~A & ~B
                pending.append((int(right[node]), complement or kind[node] == K.DIFFERENCE))
                pending.append((int(left[node]), complement))
        records[index, :len(found)] = found
        leaves = np.asarray(found, np.int64) & (K.LITERAL_COMPLEMENT - 1)
        records[index, K.MAX_COMPOUND_LITERALS:K.MAX_COMPOUND_LITERALS + len(found)] = left[leaves]
        walk_entry[root] = index
    return records


def _set_roots(kind, neg, group, left, right, parent, height, min_size=2, compound=None):
    """Per node, whether it roots a maximal subtree of unions of members, positive leaves or
    compounds (a set, `engine.leaf_events`), with at least `min_size` members; co-bounded
    (positive-form) unions and group nodes are not set members."""
    compound = np.zeros(len(kind), bool) if compound is None else compound
    member = ((kind == K.LEAF) & ~neg) | compound
    pure = member.copy()
    plain_union = (kind == K.UNION) & ~neg & ~group
    members = member.astype(np.int64)
    for at in _levels_bottom_up(kind, height):
        pure[at] = compound[at] | (plain_union[at] & pure[left[at]] & pure[right[at]])
        members[at] = np.where(compound[at], 1, members[left[at]] + members[right[at]])
    parent_pure = np.zeros(len(kind), bool)
    has_parent = parent >= 0
    parent_pure[has_parent] = pure[parent[has_parent]]
    return pure & ~member & ~parent_pure & (members >= min_size)


def _prim_start(num_prims, n_real, owner, kind, left) -> np.ndarray:
    """(leaf node, set root or NO_LEAF) per primitive: the set a ray starting on the
    primitive's surface may start inside a member of (`owner`: per node, the set it is a
    member of, as `_set_owners` gives it). A compound's literals are no members (a cut by a
    union, A - (B | C), has literals under a union too): their set cannot take a hint from
    them. Nodes from `n_real` on are the virtual root's (no primitive of their own)."""
    out = np.full((max(num_prims, 1), 2), K.NO_LEAF, np.uint32)
    leaves = np.flatnonzero(kind[:n_real] == K.LEAF)
    out[left[leaves], 0] = leaves
    member = leaves[owner[leaves] >= 0]
    out[left[member], 1] = owner[member]
    return out


def _set_owners(sets, compound, kind, left, right) -> np.ndarray:
    """Per node, the set root it is a member (a leaf or a compound) of; -1 for the others."""
    owner = np.full(len(kind), -1, np.int64)
    frontier = np.flatnonzero(sets)
    roots = frontier
    while frontier.size:
        children = np.concatenate([left[frontier], right[frontier]])
        roots = np.concatenate([roots, roots])
        ends = (kind[children] == K.LEAF) | compound[children]
        owner[children[ends]] = roots[ends]
        frontier, roots = children[~ends], roots[~ends]
    return owner


def _wide_sets(sets, kind, left, right, lower, upper, box, compound) -> tuple[np.ndarray, np.ndarray, int]:
    """Each set's binary subtree collapsed into 4-wide nodes for the set walk (fewer, wider
    visits: a node's four boxes are tested in one step from one record). A node takes its two
    children, then twice splits its inner child of largest box area into that child's two
    children (while it has one). Built level by level for all sets at once. Returns the records
    (layout.SET_NODE_FLOATS each), the walk entry of every node, and the most entries the
    walk's stack can hold at once."""
    walk_entry = np.arange(len(kind), dtype=np.uint32)
    extent = np.nan_to_num(upper - lower, nan=0.0, posinf=1e30, neginf=0.0).clip(0.0, 1e30)
    area = extent[:, 0] * extent[:, 1] + extent[:, 1] * extent[:, 2] + extent[:, 2] * extent[:, 0]
    inner_node = (kind != K.LEAF) & ~compound      # a set's own unions; its members are leaves and compounds
    id_of = np.full(len(kind), -1, np.int64)
    levels = []                           # per level: its 4-wide nodes' children (tree ids, -1: none)
    frontier, count = np.flatnonzero(sets), 0
    while frontier.size:
        id_of[frontier] = count + np.arange(frontier.size)
        count += frontier.size
        children = np.full((frontier.size, 4), -1, np.int64)
        children[:, 0], children[:, 1] = left[frontier], right[frontier]
        rows = np.arange(frontier.size)
        for used in (2, 3):
            candidates = children[:, :used]
            splittable = (candidates >= 0) & inner_node[np.maximum(candidates, 0)]
            widest = np.argmax(np.where(splittable, area[candidates], -1.0), axis=1)
            split = splittable[rows, widest]
            node = candidates[rows, widest]
            children[split, widest[split]] = left[node[split]]
            children[split, used] = right[node[split]]
        levels.append(children)
        present = children >= 0
        frontier = children[present & inner_node[np.maximum(children, 0)]]
    walk_entry[sets] = K.SET_NODE_TAG | id_of[sets].astype(np.uint32)
    children = np.concatenate(levels) if levels else np.full((1, 4), -1, np.int64)
    present = children >= 0
    safe = np.maximum(children, 0)
    wide = present & inner_node[safe]
    refs = np.where(wide, K.SET_NODE_TAG | id_of[safe], np.where(present, children, 0xFFFFFFFF)).astype(np.uint32)
    boxes = np.concatenate([box[safe][..., 0:3], box[safe][..., 4:7]], axis=-1).astype(np.float32)
    boxes[~present] = np.nan
    # A visit pushes all but one of the children it opens, and goes on into one of them: the
    # most entries waiting at once is the largest sum of (children - 1) down a path. Deeper
    # levels have larger ids, so one backward pass over the levels sees children first.
    pending = np.zeros(len(children), np.int64)
    start = count
    for level in reversed(levels):
        start -= len(level)
        here = slice(start, start + len(level))
        below = np.where(wide[here], pending[id_of[safe[here]]], 0).max(axis=1)
        pending[here] = present[here].sum(axis=1) - 1 + below
    records = np.zeros((len(children), K.SET_NODE_FLOATS), np.float32)
    records[:, :4] = refs.view(np.float32)
    records[:, 4:28] = boxes.reshape(-1, 24)
    return records, walk_entry, int(pending.max(initial=0)) if levels else 0


# The set walk's stack holds at least this many entries. Its deepest run of waiting entries
# depends on how SAH happened to shape a set (Cheeses of 200, 260 and 300 holes needed 15, 16
# and 15, hence classes 16, 32, 16), and each class is a kernel of its own: one class for all
# sets of up to some thousands of members lets such models share their kernel.
WALK_STACK_MIN = 32


def stack_size_class(height: int) -> int:
    """Per-lane stack entries for a tree of `height`, rounded up to a power of two (at least 8):
    the size is compiled into the kernel, so models of similar height share one kernel."""
    return max(8, 1 << max(0, int(height) - 1).bit_length())


def gather_prim(b, tree, prim, active=True):
    """(rows of world -> canonical, shape, params, plane start, plane count) of primitives."""
    rec = dr.gather(b.module.ArrayXf, tree.prim_record, prim, active, shape=(K.PRIM_RECORD_FLOATS, dr.width(prim)))
    rows = [b.Array4f(rec[4 * r], rec[4 * r + 1], rec[4 * r + 2], rec[4 * r + 3]) for r in range(3)]
    start = dr.reinterpret_array(b.UInt32, rec[K.PRIM_PLANE_START])
    word = dr.reinterpret_array(b.UInt32, rec[K.PRIM_COUNT_SHAPE])
    params = (rec[K.PRIM_PARAMS], rec[K.PRIM_PARAMS + 1])
    return rows, K.record_shape(word), params, start, K.record_plane_count(word)


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
