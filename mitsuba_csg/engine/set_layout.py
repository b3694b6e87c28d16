"""Sets and their records: which unions of leaves the automaton searches as one n-ary node,
and the numpy records the set walk (`engine.set_walk`) reads.

A stage between the flat tree and the device (`engine.device.upload`): it decides, per node,

* the *sets*: maximal subtrees of plain unions of positive leaves or compounds, with at
  least `TraversalOptions.min_set_size` members (`find_sets`);
* the *compounds*: small intersections of convex leaves and complements of convex leaves
  under a union, walked as one set member (a satellite's wing with its cut-outs);

and builds (`set_records`) each set's binary subtree collapsed into a 4-wide BVH, the
compounds' literal records, the start records of rays leaving a member's surface, and, for
subtracted sets, the neighbour trees and cell grids of `engine.neighbours`. Word layouts
are those of `engine.layout`.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from . import layout as K
from .neighbours import GRID_WORDS, cell_grids, neighbour_trees
from .options import TraversalOptions
from .shapes import CONVEX_CODES, NON_CONVEX_CODES


@dataclass
class NodeArrays:
    """The flat tree's nodes as the upload works on them (numpy, one entry per node; a copy
    of the FlatTree's, since the upload may add a virtual root)."""
    kind: np.ndarray        # layout node kinds
    negative: np.ndarray    # bool: complemented leaf or co-bounded operation
    group: np.ndarray       # bool: a GROUP union (engine.grouping)
    left: np.ndarray        # left child, or a leaf's primitive
    right: np.ndarray       # right child (-1 for a leaf)
    parent: np.ndarray      # -1 for the root
    lower: np.ndarray       # (N, 3) box
    upper: np.ndarray

    @classmethod
    def of(cls, flat) -> "NodeArrays":
        group = np.zeros(len(flat.node_kind), bool) if flat.node_group is None else flat.node_group.copy()
        return cls(flat.node_kind.copy(), flat.node_negative.copy(), group, flat.node_left.copy(),
                   flat.node_right.copy(), flat.node_parent.copy(), flat.node_lower.copy(), flat.node_upper.copy())

    def __len__(self) -> int:
        return len(self.kind)

    def under_virtual_union(self, root: int) -> "NodeArrays":
        """These nodes and two more: root' = union(root, nothing), where the dummy leaf has an
        empty box, which the box test rejects, so it is never intersected."""
        n = len(self)
        parent = np.concatenate([self.parent, [-1, n]])
        parent[root] = n
        return NodeArrays(np.concatenate([self.kind, [K.UNION, K.LEAF]]),
                          np.concatenate([self.negative, [False, False]]),
                          np.concatenate([self.group, [False, False]]),
                          np.concatenate([self.left, [root, 0]]), np.concatenate([self.right, [n + 1, -1]]), parent,
                          np.vstack([self.lower, self.lower[root], [np.inf] * 3]),
                          np.vstack([self.upper, self.upper[root], [-np.inf] * 3]))


@dataclass
class SetMarks:
    """Per node: whether it roots a set, and whether it is a compound member of one."""
    is_set: np.ndarray
    is_compound: np.ndarray

    def extended(self, count: int) -> "SetMarks":
        """The marks with `count` more nodes that are neither (the virtual root's)."""
        more = np.zeros(count, bool)
        return replace(self, is_set=np.concatenate([self.is_set, more]),
                       is_compound=np.concatenate([self.is_compound, more]))


@dataclass
class SetRecords:
    """What the set walk reads, as numpy arrays (`engine.device.KernelTree` has their meaning)."""
    set_nodes: np.ndarray           # (R, SET_NODE_FLOATS) float32: 4-wide nodes, neighbour and cell trees
    walk_entry: np.ndarray          # (N,) uint32
    neighbour_entry: np.ndarray     # (N,) uint32
    set_grid: np.ndarray            # (N,) uint32
    cell_entry: np.ndarray          # (C,) uint32
    grids: np.ndarray               # (G, GRID_WORDS) uint32
    compound_literals: np.ndarray   # (M, COMPOUND_RECORD_WORDS) uint32
    prim_start: np.ndarray          # (P, 2) uint32
    walk_depth: int                 # most entries a walk's stack holds at once


def find_sets(nodes: NodeArrays, flat, options: TraversalOptions) -> SetMarks:
    """The sets and compound members of the flat tree's nodes."""
    compound = _compound_roots(nodes, flat) if options.compounds and options.sets else np.zeros(len(nodes), bool)
    sets = _set_roots(nodes, flat.node_height, options.min_set_size, compound)
    compound &= _set_owners(nodes, sets, compound) >= 0
    return SetMarks(sets, compound)


def set_records(nodes: NodeArrays, marks: SetMarks, box: np.ndarray, flat, frame, options: TraversalOptions,
                root: int) -> SetRecords:
    """The set walk's records for `nodes` (in the scene frame; `box` their padded boxes, as
    `engine.device.upload` stores them; `frame` the scene frame's (centre, inv_scale))."""
    kind, left = nodes.kind, nodes.left
    set_nodes, walk_entry, walk_depth = _wide_sets(nodes, marks, box)
    owner = _set_owners(nodes, marks.is_set, marks.is_compound)
    neighbour_entry = np.full(len(nodes), K.NO_INDEX, np.uint32)
    set_grid = np.full(len(nodes), K.NO_INDEX, np.uint32)
    cell_entry = np.zeros(0, np.uint32)
    grids = np.zeros((0, GRID_WORDS), np.uint32)
    if options.sets and (options.neighbour_passes or options.cell_passes):
        leaf = kind == K.LEAF
        convex = leaf & ~np.isin(flat.prim_shape[np.where(leaf, left, 0)], NON_CONVEX_CODES)
        # Only where rays cross a set's inside outside the solid (holes: a subtracted or
        # complemented set) do its passes from inside matter; elsewhere the trees would cost
        # memory (a Satellites' parts: 23 MB more for 87,500 primitives) and save little.
        holes = marks.is_set & _subtracted(nodes, root)
        in_hole = np.where(holes[np.maximum(owner, 0)], owner, -1)
        balls = _sphere_balls(flat, nodes, *frame)
        if options.neighbour_passes:
            trees, neighbour_entry = neighbour_trees(in_hole, box, balls, convex, len(set_nodes))
            if np.any(neighbour_entry != K.NO_INDEX):
                set_nodes = np.concatenate([set_nodes, trees])
        if options.cell_passes:
            cell_records, grids, cell_entry, grid_roots = cell_grids(in_hole, box, balls, len(set_nodes),
                                                                     options.min_grid_size)
            if len(grids):
                set_nodes = np.concatenate([set_nodes, cell_records])
                set_grid[grid_roots] = np.arange(len(grids), dtype=np.uint32)
    compound_literals = _compound_literals(nodes, marks.is_compound, walk_entry)
    prim_start = _prim_start(flat.num_prims, len(flat.node_kind), owner, nodes)
    return SetRecords(set_nodes, walk_entry, neighbour_entry, set_grid, cell_entry, grids, compound_literals,
                      prim_start, walk_depth)


def levels_bottom_up(kind, height) -> list:
    """The operation nodes in groups of equal height, lowest first: one vectorized step per
    level computes a per-node property from the children's."""
    ops = np.flatnonzero(kind != K.LEAF)
    ops = ops[np.argsort(height[ops], kind="stable")]
    return np.split(ops, np.flatnonzero(np.diff(height[ops])) + 1)


def _compound_roots(nodes: NodeArrays, flat) -> np.ndarray:
    """Per node, whether it is a compound set member candidate: an intersection or difference
    under a plain union whose subtree is an intersection of at most MAX_COMPOUND_LITERALS
    literals, each a convex leaf or a complement of one (a difference's subtrahend, or a
    union of leaves subtracted: A - (B | C) = A & ~B & ~C). The set walk finds its next event in
    one member visit (`leaf_events.compound_hit`) where the automaton would descend into it,
    as Satellites' wings with their cut-outs made it do."""
    kind, neg, group, left, right, parent = nodes.kind, nodes.negative, nodes.group, nodes.left, nodes.right, \
        nodes.parent
    n = len(kind)
    # Literals of the node as an intersection (as_is), and of its complement (negated); -1: none.
    as_is, negated = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    leaves = np.flatnonzero(kind == K.LEAF)
    convex = leaves[np.isin(flat.prim_shape[left[leaves]], CONVEX_CODES) & ~neg[leaves]]
    as_is[convex] = negated[convex] = 1
    limit = K.MAX_COMPOUND_LITERALS

    def total(a, c):
        return np.where((a > 0) & (c > 0) & (a + c <= limit), a + c, -1)
    for at in levels_bottom_up(kind, flat.node_height):
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


def _compound_literals(nodes: NodeArrays, compound, walk_entry) -> np.ndarray:
    """Literal records (layout.COMPOUND_RECORD_WORDS words each: the literals, then their leaves'
    primitives, so that a literal's intersection reads no node record) of the compound members,
    whose walk_entry becomes their record's index."""
    kind, left, right = nodes.kind, nodes.left, nodes.right
    roots = np.flatnonzero(compound)
    records = np.full((max(len(roots), 1), K.COMPOUND_RECORD_WORDS), K.NO_INDEX, np.uint32)
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


def _set_roots(nodes: NodeArrays, height, min_size=2, compound=None):
    """Per node, whether it roots a maximal subtree of unions of members, positive leaves or
    compounds (a set, `engine.set_walk`), with at least `min_size` members; co-bounded
    (positive-form) unions and group nodes are not set members."""
    kind, left, right, parent = nodes.kind, nodes.left, nodes.right, nodes.parent
    compound = np.zeros(len(kind), bool) if compound is None else compound
    member = ((kind == K.LEAF) & ~nodes.negative) | compound
    pure = member.copy()
    plain_union = (kind == K.UNION) & ~nodes.negative & ~nodes.group
    members = member.astype(np.int64)
    for at in levels_bottom_up(kind, height):
        pure[at] = compound[at] | (plain_union[at] & pure[left[at]] & pure[right[at]])
        members[at] = np.where(compound[at], 1, members[left[at]] + members[right[at]])
    parent_pure = np.zeros(len(kind), bool)
    has_parent = parent >= 0
    parent_pure[has_parent] = pure[parent[has_parent]]
    return pure & ~member & ~parent_pure & (members >= min_size)


def _prim_start(num_prims, n_real, owner, nodes: NodeArrays) -> np.ndarray:
    """(leaf node, set root or NO_INDEX) per primitive: the set a ray starting on the
    primitive's surface may start inside a member of (`owner`: per node, the set it is a
    member of, as `_set_owners` gives it). A compound's literals are no members (a cut by a
    union, A - (B | C), has literals under a union too): their set cannot take a hint from
    them. Nodes from `n_real` on are the virtual root's (no primitive of their own)."""
    kind, left = nodes.kind, nodes.left
    out = np.full((max(num_prims, 1), 2), K.NO_INDEX, np.uint32)
    leaves = np.flatnonzero(kind[:n_real] == K.LEAF)
    out[left[leaves], 0] = leaves
    member = leaves[owner[leaves] >= 0]
    out[left[member], 1] = owner[member]
    return out


def _set_owners(nodes: NodeArrays, sets, compound) -> np.ndarray:
    """Per node, the set root it is a member (a leaf or a compound) of; -1 for the others."""
    kind, left, right = nodes.kind, nodes.left, nodes.right
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


def _wide_sets(nodes: NodeArrays, marks: SetMarks, box) -> tuple[np.ndarray, np.ndarray, int]:
    """Each set's binary subtree collapsed into 4-wide nodes for the set walk (fewer, wider
    visits: a node's four boxes are tested in one step from one record). A node takes its two
    children, then twice splits its inner child of largest box area into that child's two
    children (while it has one). Built level by level for all sets at once. Returns the records
    (layout.SET_NODE_FLOATS each), the walk entry of every node, and the most entries the
    walk's stack can hold at once."""
    kind, left, right, lower, upper = nodes.kind, nodes.left, nodes.right, nodes.lower, nodes.upper
    sets, compound = marks.is_set, marks.is_compound
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
    refs = np.where(wide, K.SET_NODE_TAG | id_of[safe], np.where(present, children, K.NO_INDEX)).astype(np.uint32)
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


def _subtracted(nodes: NodeArrays, root) -> np.ndarray:
    """Per node, whether its inside is outside the solid: an odd number of complements and
    differences' right sides on its way from the root."""
    kind, neg, left, right = nodes.kind, nodes.negative, nodes.left, nodes.right
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


def _sphere_balls(flat, nodes: NodeArrays, centre, inv_scale) -> np.ndarray:
    """(centre xyz, radius) per node in the scene frame: a ball holding a sphere leaf (an
    ellipsoid's largest semi-axis as the radius); NaN radius for every other node."""
    kind, left = nodes.kind, nodes.left
    balls = np.full((len(kind), 4), np.nan)
    leaves = np.flatnonzero(kind == K.LEAF)
    leaves = leaves[(left[leaves] < flat.num_prims)]
    leaves = leaves[flat.prim_shape[left[leaves]] == K.SPHERE]
    to_world = flat.prim_to_world[left[leaves]]
    balls[leaves, :3] = (to_world[:, :3, 3] - centre) * inv_scale
    balls[leaves, 3] = np.linalg.norm(to_world[:, :3, :3], axis=1).max(axis=1) * inv_scale
    return balls
