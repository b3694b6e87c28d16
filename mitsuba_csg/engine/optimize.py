"""The tree optimizer of paper §4: positive form, SAH treelets, height minimization, reverse.

    opt, stats = optimize(model)

`opt` is an `OptimizedModel`: the same solid as a balanced, spatially coherent binary tree
that `trace`, `contains` and the Mitsuba shape accept. Its primitives are the input's, in
the input's `leaves()` order, so hit primitive indices refer to the input model even where
a subtree was duplicated.

Phases:
1. Positive form: only union and intersection, negations pushed to the leaves; treelets
   (maximal groups of one operation) become n-ary nodes.
2. Spatial optimization: each treelet is rebuilt by a binned SAH builder (`sah.build`)
   over its operands, all treelets at once. Operand boxes are those of the general form;
   in an intersection, a complemented operand only matters inside the region the
   intersection can reach, so its box is clipped to it.
3. Height minimization: type-1 rotations inside a treelet while they lower the height,
   then type-2 distributions across interleaved operations (they duplicate a subtree),
   only where they lower the height and within a growth budget.
4. Reverse conversion to the general form (union, intersection, difference).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..model.nodes import Node
from . import layout as K
from . import lowering as L
from . import sah

_U, _I = K.UNION, K.INTERSECTION


@dataclass
class OptimizedModel:
    """An optimized tree over the primitives of `source` (trace it like a model)."""
    source: Node
    flat: L.FlatTree

    def leaves(self):
        return self.source.leaves()

    def bounds(self):
        return self.flat.node_lower[self.flat.root].copy(), self.flat.node_upper[self.flat.root].copy()

    def tree_height(self) -> int:
        return self.flat.height

    def __repr__(self):
        return (f"OptimizedModel({self.flat.num_prims} primitives, {self.flat.num_nodes} nodes, "
                f"height {self.flat.height})")


# ---- Phase 1: positive n-ary form ----

def _positive_nary(root_item):
    """Arrays of the positive n-ary tree: kind, prim (leaves), negated (leaves), children (CSR)."""
    kind, prim, neg, children = [], [], [], []

    def effective(item, negate):
        """(op code, [(operand, negate)]) of an item under an optional complement."""
        if item[0] == "leaf":
            return None, None
        op, operands = L.positive_operands(item, negate)
        return L.KIND_CODE[op], operands

    # Tasks: ("node", item, negate, parent); ("operand", item, negate, op, parent)
    tasks = [("node", root_item, False, -1)]
    while tasks:
        task = tasks.pop()
        if task[0] == "operand":
            _, item, negate, op, parent = task
            e_op, operands = effective(item, negate)
            if e_op == op:            # same operation: splice into the parent's treelet
                tasks.extend(("operand", k, n, op, parent) for k, n in reversed(operands))
                continue
            task = ("node", item, negate, parent)
        _, item, negate, parent = task
        nid = len(kind)
        if parent >= 0:
            children[parent].append(nid)
        e_op, operands = effective(item, negate)
        if e_op is None:
            kind.append(K.LEAF)
            prim.append(item[1])
            neg.append(negate)
            children.append(None)
            continue
        kind.append(e_op)
        prim.append(-1)
        neg.append(False)
        children.append([])
        tasks.extend(("operand", k, n, e_op, nid) for k, n in reversed(operands))
    return np.array(kind, np.int64), np.array(prim, np.int64), np.array(neg, bool), children


def _nary_bounds(kind, prim, neg, children, prim_lower, prim_upper):
    """Boxes, co-boundedness and leaf counts of the n-ary nodes (children have larger ids).

    One vectorized pass per level, deepest first, with the box rules of `lowering.operation_boxes`.
    """
    n = len(kind)
    lower, upper = np.empty((n, 3)), np.empty((n, 3))
    negative = neg.copy()
    leaves = np.zeros(n, np.int64)
    is_leaf = kind == K.LEAF
    lower[is_leaf], upper[is_leaf] = prim_lower[prim[is_leaf]], prim_upper[prim[is_leaf]]
    leaves[is_leaf] = 1
    depth = np.zeros(n, np.int64)
    for i in range(n):                       # parents come before their children
        if children[i] is not None:
            depth[children[i]] = depth[i] + 1
    for d in range(depth.max(initial=0), -1, -1):
        ids = np.flatnonzero((depth == d) & ~is_leaf)
        if not len(ids):
            continue
        kids = [np.asarray(children[i], np.int64) for i in ids]
        starts = np.concatenate([[0], np.cumsum([len(k) for k in kids])[:-1]]).astype(np.int64)
        c = np.concatenate(kids)
        lower[ids], upper[ids], negative[ids] = L.operation_boxes(kind[ids] == _U, lower[c], upper[c],
                                                                  negative[c], starts)
        leaves[ids] = np.add.reduceat(leaves[c], starts)
    return lower, upper, negative, leaves


# ---- Phase 2: SAH over every treelet ----

def _sah_treelets(kind, children, lower, upper, negative, leaves, spatial: bool = True):
    """Binary nodes (op, left, right) replacing every n-ary node; refs to n-ary ids are ~id.

    `spatial=False` keeps operand order (balanced in input order) instead of SAH.
    """
    ops = np.flatnonzero(kind != K.LEAF)
    counts = np.array([len(children[i]) for i in ops], np.int64)
    items = np.concatenate([np.asarray(children[i], np.int64) for i in ops]) if len(ops) else np.zeros(0, np.int64)
    owner = np.repeat(ops, counts)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    if spatial:
        item_lower, item_upper = lower[items].copy(), upper[items].copy()
        # Inside an intersection, a complemented operand only matters where the bounded ones reach.
        clip = (kind[owner] == _I) & negative[items] & ~negative[owner]
        item_lower[clip] = np.maximum(item_lower[clip], lower[owner[clip]])
        item_upper[clip] = np.minimum(item_upper[clip], upper[owner[clip]])
        weight = leaves[items]
    else:
        # Items on a line in input order: the builder's median split then keeps input order.
        item_lower = item_upper = np.arange(len(items), dtype=np.float64)[:, None].repeat(3, 1)
        weight = np.ones(len(items))
    left, right, roots = sah.build(item_lower, item_upper, weight, starts, counts)
    # Internal node i belongs to the set it was split from; find each node's operation.
    node_op = np.empty(len(left), np.int64)
    node_op[roots] = kind[ops]
    frontier = roots
    while len(frontier):
        kids = np.concatenate([left[frontier], right[frontier]])
        ops_of = np.concatenate([node_op[frontier], node_op[frontier]])
        internal = kids >= 0
        node_op[kids[internal]] = ops_of[internal]
        frontier = kids[internal]
    item_ref = lambda r: np.where(r >= 0, r, ~items[np.where(r < 0, -r - 1, 0)])  # noqa: E731
    treelet_root = np.full(len(kind), -1, np.int64)
    treelet_root[ops] = roots
    return node_op, item_ref(left), item_ref(right), treelet_root


# ---- Phase 3: height minimization on a mutable binary tree ----

class _Tree:
    """A mutable binary tree: op nodes and leaves in parallel Python lists."""

    def __init__(self):
        self.kind, self.left, self.right, self.prim, self.neg, self.height = [], [], [], [], [], []

    def add(self, kind, left=-1, right=-1, prim=-1, neg=False) -> int:
        self.kind.append(kind)
        self.left.append(left)
        self.right.append(right)
        self.prim.append(prim)
        self.neg.append(neg)
        h = 0 if kind == K.LEAF else 1 + max(self.height[left], self.height[right])
        self.height.append(h)
        return len(self.kind) - 1

    def update(self, i):
        self.height[i] = 1 + max(self.height[self.left[i]], self.height[self.right[i]])

    def heavy(self, i):
        """(heavy child, light child) of operation node i."""
        a, b = self.left[i], self.right[i]
        return (a, b) if self.height[a] >= self.height[b] else (b, a)

    def copy_subtree(self, i) -> tuple[int, int]:
        """Duplicate subtree i; returns (new root, leaves copied)."""
        order, stack = [], [i]
        while stack:
            j = stack.pop()
            order.append(j)
            if self.kind[j] != K.LEAF:
                stack.extend((self.left[j], self.right[j]))
        new = {}
        copied = 0
        for j in reversed(order):
            if self.kind[j] == K.LEAF:
                new[j] = self.add(K.LEAF, prim=self.prim[j], neg=self.neg[j])
                copied += 1
            else:
                new[j] = self.add(self.kind[j], new[self.left[j]], new[self.right[j]])
        return new[i], copied

    def postorder(self, root):
        out, stack = [], [(root, False)]
        while stack:
            j, done = stack.pop()
            if self.kind[j] == K.LEAF:
                continue
            if done:
                out.append(j)
            else:
                stack.extend(((j, True), (self.right[j], False), (self.left[j], False)))
        return out


def _rotate_type1(t: _Tree, n1: int) -> bool:
    """N1 = op(T1, N2), N2 = op(T2, T3), T3 heavy: N1 = op(op(T1, T2), T3). Lowers h(N1) by 1."""
    n2, t1 = t.heavy(n1)
    if t.kind[n2] != t.kind[n1]:
        return False
    t3, t2 = t.heavy(n2)
    if t.height[t3] <= t.height[t1] + 1 or t.height[t3] <= t.height[t2]:
        return False
    before = t.height[n1]
    # Reuse node n2 as op(T1, T2) and re-link n1 = op(n2, T3).
    t.left[n2], t.right[n2] = t1, t2
    t.update(n2)
    t.left[n1], t.right[n1] = n2, t3
    t.update(n1)
    if t.height[n1] >= before:    # cannot happen by the height condition; undo defensively
        raise AssertionError("type-1 rotation did not lower the height")
    return True


def _distribute_type2(t: _Tree, n1: int, budget: list) -> bool:
    """N1 = op(T1, N2), N2 = op'(T2, N3), N3 = op(T3, T4), T4 heavy:
    N1 = op'(op(T1, T2), op(op(T1, T3), T4)), duplicating T1. Lowers h(N1) by 1."""
    n2, t1 = t.heavy(n1)
    op = t.kind[n1]
    if t.kind[n2] == op or t.kind[n2] == K.LEAF:
        return False
    n3, t2 = t.heavy(n2)
    if t.kind[n3] != op:
        return False
    t4, t3 = t.heavy(n3)
    h1 = t.height[t1]
    if not (t.height[t4] > h1 + 2 and t.height[t4] > t.height[t2] + 1 and t.height[t4] > t.height[t3] + 1):
        return False
    size = _leaf_count(t, t1)
    if size > budget[0]:
        return False
    before = t.height[n1]
    t1_copy, copied = t.copy_subtree(t1)
    budget[0] -= copied
    budget[1] += copied
    # Reuse n2 as op(T1, T2), n3 as op(T1', T3), new node op(n3, T4); n1 becomes op'.
    t.kind[n2], t.left[n2], t.right[n2] = op, t1, t2
    t.update(n2)
    t.left[n3], t.right[n3] = t1_copy, t3
    t.update(n3)
    upper = t.add(op, n3, t4)
    t.kind[n1] = _other(op)
    t.left[n1], t.right[n1] = n2, upper
    t.update(n1)
    if t.height[n1] >= before:
        raise AssertionError("type-2 distribution did not lower the height")
    return True


def _other(op):
    return _I if op == _U else _U


def _leaf_count(t: _Tree, i: int) -> int:
    count, stack = 0, [i]
    while stack:
        j = stack.pop()
        if t.kind[j] == K.LEAF:
            count += 1
        else:
            stack.extend((t.left[j], t.right[j]))
    return count


def _minimize_height(t: _Tree, root: int, max_growth: float) -> int:
    """Type-1 rotations everywhere, then type-2 distributions; returns leaves duplicated."""
    for n in t.postorder(root):
        t.update(n)
        while _rotate_type1(t, n):
            pass
    n_leaves = _leaf_count(t, root)
    budget = [int(max_growth * n_leaves), 0]
    changed = True
    while changed and budget[0] > 0:
        changed = False
        for n in t.postorder(root):
            t.update(n)
            while _rotate_type1(t, n) or _distribute_type2(t, n, budget):
                changed = True
    return budget[1]


# ---- Phase 4: reverse conversion to the general form ----

def _general_form(t: _Tree, root: int):
    """Preorder FlatTree arrays of the general form; complements survive only if unavoidable."""
    # value per node: (new-structure id, complemented?) built bottom-up into a second _Tree
    g = _Tree()
    value = {}
    for n in _all_postorder(t, root):
        if t.kind[n] == K.LEAF:
            value[n] = (g.add(K.LEAF, prim=t.prim[n]), t.neg[n])
            continue
        (a, na), (b, nb) = value[t.left[n]], value[t.right[n]]
        if t.kind[n] == _I:
            if not na and not nb:
                value[n] = (g.add(_I, a, b), False)
            elif not na and nb:
                value[n] = (g.add(K.DIFFERENCE, a, b), False)
            elif na and not nb:
                value[n] = (g.add(K.DIFFERENCE, b, a), False)
            else:                       # ~a & ~b = ~(a | b)
                value[n] = (g.add(_U, a, b), True)
        else:
            if not na and not nb:
                value[n] = (g.add(_U, a, b), False)
            elif not na and nb:         # a | ~b = ~(b - a)
                value[n] = (g.add(K.DIFFERENCE, b, a), True)
            elif na and not nb:
                value[n] = (g.add(K.DIFFERENCE, a, b), True)
            else:                       # ~a | ~b = ~(a & b)
                value[n] = (g.add(_I, a, b), True)
    g_root, complemented = value[root]
    if complemented:
        return None                     # an unbounded solid: keep the positive form
    return g, g_root


def _merge_subtracted_sets(t: _Tree, root: int, prim_lower, prim_upper) -> int:
    """Rewrite chains (((A - B1) - B2) - ...) - Bk, where the B are unions of leaves, as
    A - B with B one SAH union of all their leaves: the kernel searches a union of leaves as
    one n-ary set (`engine.set_walk`), so one set of all the holes costs one BVH query
    where k sets cost k. Returns the number of chains merged."""
    pure = {}
    for j in _all_postorder(t, root):
        pure[j] = t.kind[j] == K.LEAF or (t.kind[j] == _U and pure[t.left[j]] and pure[t.right[j]])
    merged = 0
    stack = [root]
    while stack:
        n = stack.pop()
        if t.kind[n] == K.LEAF:
            continue
        subtrahends, minuend = [], n
        while t.kind[minuend] == K.DIFFERENCE and pure[t.right[minuend]]:
            subtrahends.append(t.right[minuend])
            minuend = t.left[minuend]
        if len(subtrahends) >= 2:
            leaves = [leaf for b in subtrahends for leaf in _leaves_under(t, b)]
            prims = [t.prim[leaf] for leaf in leaves]
            left, right, roots = sah.build(prim_lower[prims], prim_upper[prims], np.ones(len(prims)),
                                           np.array([0]), np.array([len(prims)]))
            joined = _add_built(t, left, right, int(roots[0]), leaves)
            # SAH alone may build a deep tree over clustered leaves; the chain is kept where
            # the merge would deepen the tree past a balanced one's height (and the chain's).
            allowed = max(t.height[n], int(np.ceil(np.log2(len(prims)))) + 4)
            if 1 + max(t.height[minuend], t.height[joined]) <= allowed:
                t.left[n], t.right[n] = minuend, joined
                merged += 1
            stack.append(minuend)
        else:
            stack.extend((t.left[n], t.right[n]))
    for j in _all_postorder(t, root):
        if t.kind[j] != K.LEAF:
            t.update(j)
    return merged


def _add_built(t: _Tree, left, right, node: int, items) -> int:
    """Add the binary union that `sah.build` made over `items` (node ids of t); returns its root."""
    order, stack = [], [node]
    while stack:                        # parents before children
        j = stack.pop()
        order.append(j)
        stack.extend(r for r in (int(left[j]), int(right[j])) if r >= 0)
    ids = {}
    for j in reversed(order):           # children before parents
        a, b = (items[-r - 1] if r < 0 else ids[r] for r in (int(left[j]), int(right[j])))
        ids[j] = t.add(_U, a, b)
    return ids[node]


def _leaves_under(t: _Tree, i: int) -> list:
    out, stack = [], [i]
    while stack:
        j = stack.pop()
        if t.kind[j] == K.LEAF:
            out.append(j)
        else:
            stack.extend((t.left[j], t.right[j]))
    return out


def _all_postorder(t: _Tree, root: int):
    out, stack = [], [(root, False)]
    while stack:
        j, done = stack.pop()
        if done or t.kind[j] == K.LEAF:
            out.append(j)
        else:
            stack.extend(((j, True), (t.right[j], False), (t.left[j], False)))
    return out


def _to_flat(t: _Tree, root: int, base: L.FlatTree) -> L.FlatTree:
    """Renumber `t` in preorder and attach the primitive arrays of `base`."""
    kind, neg, left, right, parent = [], [], [], [], []
    stack = [(root, -1, 0)]
    while stack:
        j, par, side = stack.pop()
        nid = L.new_node(kind, neg, left, right, parent, t.kind[j], t.neg[j], par, side)
        if t.kind[j] == K.LEAF:
            left[nid] = t.prim[j]
        else:
            stack.append((t.right[j], nid, 1))
            stack.append((t.left[j], nid, 0))
    arrays = (np.array(kind, np.int64), np.array(neg, bool), np.array(left, np.int64),
              np.array(right, np.int64), np.array(parent, np.int64))
    return L.with_nodes(base, *arrays)


def optimize(model, *, spatial: bool = True, minimize_height: bool = True, general_form: bool = True,
             max_growth: float = 0.25):
    """Optimize `model` (paper §4). Returns (OptimizedModel, stats dict).

    `max_growth` caps the leaves that type-2 distributions may duplicate, as a fraction of
    the primitive count. Stats: heights, node counts, leaves duplicated, seconds per phase.
    """
    if isinstance(model, OptimizedModel):
        model = model.source
    seconds = {}
    t0 = time.perf_counter()
    prims: list = []
    root_item = L.item_tree(model, prims)
    base = L.primitive_tree(prims)     # primitive arrays only; no node arrays yet
    seconds["lower"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    kind, prim, neg, children = _positive_nary(root_item)
    seconds["positive_form"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    lower, upper, negative, leaves = _nary_bounds(kind, prim, neg, children, base.prim_lower, base.prim_upper)
    tree = _Tree()
    if kind[0] == K.LEAF:
        root = tree.add(K.LEAF, prim=int(prim[0]), neg=bool(neg[0]))
    else:
        node_op, b_left, b_right, treelet_root = _sah_treelets(kind, children, lower, upper, negative, leaves,
                                                               spatial)
        root = _assemble(tree, kind, prim, neg, node_op, b_left, b_right, treelet_root)
    seconds["spatial"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    duplicated = _minimize_height(tree, root, max_growth) if minimize_height else 0
    seconds["height"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    general = _general_form(tree, root) if general_form else None
    merged = _merge_subtracted_sets(*general, base.prim_lower, base.prim_upper) if general is not None else 0
    flat = _to_flat(*general, base) if general is not None else _to_flat(tree, root, base)
    seconds["reverse"] = time.perf_counter() - t0

    stats = {
        "primitives": base.num_prims,
        "height_input": model.tree_height(),
        "height_before": L.lowered_height(root_item),   # the tree `lower` would trace
        "height_after": flat.height,
        "nodes_before": 2 * base.num_prims - 1,
        "nodes_after": flat.num_nodes,
        "leaves_duplicated": duplicated,
        "set_chains_merged": merged,
        "positive_form": general is None,
        "seconds": seconds,
        "seconds_total": sum(seconds.values()),
    }
    return OptimizedModel(model, flat), stats


def _assemble(tree: _Tree, kind, prim, neg, node_op, b_left, b_right, treelet_root) -> int:
    """Copy the SAH binary nodes and n-ary leaves into `tree`; returns the root id."""
    # ids: binary internal node i -> i; n-ary leaf j -> offset + rank
    n_int = len(node_op)
    leaf_ids = np.flatnonzero(kind == K.LEAF)
    leaf_new = np.full(len(kind), -1, np.int64)
    leaf_new[leaf_ids] = n_int + np.arange(len(leaf_ids))

    def resolve(ref):
        # ref >= 0: internal node; ref < 0: n-ary node ~ref (a leaf, or another treelet's root)
        nary = ~ref
        target = np.where(kind[np.where(ref < 0, nary, 0)] == K.LEAF, leaf_new[np.where(ref < 0, nary, 0)],
                          treelet_root[np.where(ref < 0, nary, 0)])
        return np.where(ref >= 0, ref, target)

    lefts, rights = resolve(b_left), resolve(b_right)
    # heights bottom-up need children first: insert leaves, then internal nodes in reverse
    # topological order (children before parents).
    tree.kind = list(node_op) + [K.LEAF] * len(leaf_ids)
    tree.left = list(lefts) + [-1] * len(leaf_ids)
    tree.right = list(rights) + [-1] * len(leaf_ids)
    tree.prim = [-1] * n_int + list(prim[leaf_ids])
    tree.neg = [False] * n_int + list(neg[leaf_ids])
    tree.height = [0] * (n_int + len(leaf_ids))
    root = int(treelet_root[0])
    for j in _all_postorder(tree, root):
        if tree.kind[j] != K.LEAF:
            tree.update(j)
    tree.kind = [int(k) for k in tree.kind]
    tree.left = [int(v) for v in tree.left]
    tree.right = [int(v) for v in tree.right]
    tree.prim = [int(v) for v in tree.prim]
    tree.neg = [bool(v) for v in tree.neg]
    return root
