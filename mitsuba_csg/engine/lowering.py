"""Lowering: a `Model` becomes flat numpy arrays of a binary tree (the kernel's input).

Steps, all iterative (trees may be millions of nodes deep or wide):
1. Transforms and materials are multiplied down to the primitives (`Node.walk_leaves`).
2. Chains of one associative operation are flattened into n-ary nodes
   (`(a | b) | c` -> union(a, b, c), `(a - b) - c` -> difference(a, b, c)).
3. n-ary nodes become balanced binary subtrees in input order; a difference a - b - c
   becomes a - (b | c). With `positive=True` differences become intersections with
   complemented operands instead, and complements are pushed down to the leaves
   (the positive form of paper §4.1).
4. Bounds: exact world boxes for primitives; for operations, boxes of the general form.
   A node of a positive-form tree is either bounded (inside its box) or co-bounded
   (its complement is inside its box): `node_negative` says which.
Node ids are preorder, so every parent has a smaller id than its children.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from .. import memory
from ..errors import ModelError
from ..model.nodes import DIFFERENCE, INTERSECTION, UNION, Node, Operation
from . import layout as K
from . import mesh_bvh
from .shapes import primitive_bounds

KIND_CODE = {UNION: K.UNION, INTERSECTION: K.INTERSECTION, DIFFERENCE: K.DIFFERENCE}


@dataclass
class FlatTree:
    """A binary CSG tree and its primitives as structure-of-arrays (float64, int64)."""
    # per node (preorder ids, root = 0)
    node_kind: np.ndarray       # layout.UNION / INTERSECTION / DIFFERENCE / LEAF
    node_negative: np.ndarray   # leaf: complemented; operation: co-bounded
    node_left: np.ndarray       # operation: left child id; leaf: primitive index
    node_right: np.ndarray      # operation: right child id; leaf: -1
    node_parent: np.ndarray     # -1 for the root
    node_lower: np.ndarray      # (N, 3) world box of the general form
    node_upper: np.ndarray
    node_height: np.ndarray     # operation levels below and including the node; leaves 0
    # per primitive, in `Model.leaves()` order
    prim_shape: np.ndarray      # layout.SPHERE ... CONVEX
    prim_to_canonical: np.ndarray  # (P, 3, 4) world -> canonical affine
    prim_to_world: np.ndarray      # (P, 4, 4) canonical -> world
    prim_param: np.ndarray      # (P, 2): cone radii (bottom, top) / max; torus minor/major
    prim_plane_start: np.ndarray
    prim_plane_count: np.ndarray
    prim_lower: np.ndarray
    prim_upper: np.ndarray
    prim_material: list = field(default_factory=list)  # material name or None per primitive
    planes: np.ndarray = None   # (Q, 4) canonical unit-normal planes of convex primitives and mesh triangles
    plane_vertices: dict = field(default_factory=dict)  # plane start -> canonical vertices
    # Mesh leaves (engine.mesh_bvh): triangles parallel to `planes` (zero rows for convex
    # planes), and all meshes' BVH nodes; a mesh primitive's first param is its root node.
    triangles: np.ndarray = None    # (Q, 12)
    mesh_lower: np.ndarray = None   # (K, 3) node boxes, canonical frame
    mesh_upper: np.ndarray = None
    mesh_right: np.ndarray = None   # (K,) inner node: absolute index of the right child (the left is next)
    mesh_first: np.ndarray = None   # (K,) leaf: first triangle, relative to the mesh's plane start
    mesh_count: np.ndarray = None   # (K,) leaf: triangle count; 0: inner node
    root: int = 0
    # per node: a GROUP node (engine.grouping) joins separate solids: its hit is the nearer of
    # its children's; None where the tree has none
    node_group: np.ndarray = None

    @property
    def height(self) -> int:
        return int(self.node_height[self.root])

    @property
    def num_nodes(self) -> int:
        return len(self.node_kind)

    @property
    def num_prims(self) -> int:
        return len(self.prim_shape)


# ---- Step 1-2: primitives and the n-ary item tree ----

def item_tree(model: Node, prims: list):
    """Return the n-ary item tree: ('leaf', prim) or (kind, [items]); fills `prims`."""
    if not isinstance(model, Node):
        raise ModelError(f"expected a CSG model node, got {type(model).__name__}")
    memory.require(model.leaf_count * memory.BYTES_PER_PRIMITIVE, f"a model of {model.leaf_count} primitives")
    leaf_iter = model.walk_leaves()
    # Postorder over the model; the leaf walk yields primitives in the same DFS order.
    root_box = []
    stack = [(model, False, root_box)]
    while stack:
        node, expanded, out = stack.pop()
        if not isinstance(node, Operation):
            prim, matrix, material = next(leaf_iter)
            prims.append((prim, matrix, material))
            out.append(("leaf", len(prims) - 1))
            continue
        if not expanded:
            kids: list = []
            stack.append((node, kids, out))
            stack.extend((c, False, kids) for c in reversed(node.children))
            continue
        kids = expanded
        out.append(_flattened(node.kind, kids))
    return root_box[0]


def _flattened(kind: str, kids: list):
    if len(kids) == 1 and kind != DIFFERENCE:
        return kids[0]
    if kind == DIFFERENCE:
        first, rest = kids[0], []
        if first[0] == DIFFERENCE:            # (a - b) - c = a - b - c
            first, rest = first[1][0], list(first[1][1:])
        for k in kids[1:]:                    # a - (b | c) = a - b - c
            rest.extend(k[1] if k[0] == UNION else [k])
        return (DIFFERENCE, [first, *rest]) if rest else first
    merged = []
    for k in kids:
        merged.extend(k[1] if k[0] == kind else [k])
    return (kind, merged)


# ---- Step 3: binary emission in preorder ----

_FLIP = {UNION: INTERSECTION, INTERSECTION: UNION}


def positive_operands(item, negate: bool):
    """(operation, [(operand item, complemented)]) of an operation item, complemented if `negate`,
    with no difference left (paper §4.1): a - r = a & ~r, ~(a - r) = ~a | r, and De Morgan.
    """
    op, kids = item
    if op == DIFFERENCE:
        first, rest = kids[0], kids[1:]
        return (UNION if negate else INTERSECTION), [(first, negate)] + [(r, not negate) for r in rest]
    return (_FLIP[op] if negate else op), [(k, negate) for k in kids]


def _emit(root_item, positive: bool):
    kind, negative, left, right, parent = [], [], [], [], []
    # work: (spec, parent id, side); spec = ("item", item, neg) or ("range", op, [(item, neg)], lo, hi)
    work = [(("item", root_item, False), -1, 0)]
    while work:
        spec, par, side = work.pop()
        if spec[0] == "item":
            _, item, neg = spec
            if item[0] == "leaf":
                nid = new_node(kind, negative, left, right, parent, K.LEAF, neg, par, side)
                left[nid] = item[1]
                continue
            op, kids = item
            if op == DIFFERENCE and not (positive or neg):
                a, rest = kids[0], kids[1:]
                nid = new_node(kind, negative, left, right, parent, K.DIFFERENCE, False, par, side)
                right_spec = (("item", rest[0], False) if len(rest) == 1 else
                              ("range", UNION, [(r, False) for r in rest], 0, len(rest)))
                work.append((right_spec, nid, 1))
                work.append((("item", a, False), nid, 0))
                continue
            op, entries = positive_operands(item, neg) if (positive or neg) else (op, [(k, False) for k in kids])
            spec = ("range", op, entries, 0, len(entries))
        _, op, entries, lo, hi = spec
        if hi - lo == 1:
            work.append((("item", *entries[lo]), par, side))
            continue
        mid = (lo + hi) // 2
        nid = new_node(kind, negative, left, right, parent, KIND_CODE[op], False, par, side)
        work.append((("range", op, entries, mid, hi), nid, 1))
        work.append((("range", op, entries, lo, mid), nid, 0))
    return (np.array(kind, np.int64), np.array(negative, bool), np.array(left, np.int64),
            np.array(right, np.int64), np.array(parent, np.int64))


def new_node(kind, negative, left, right, parent, k, neg, par, side) -> int:
    nid = len(kind)
    kind.append(k)
    negative.append(neg)
    left.append(-1)
    right.append(-1)
    parent.append(par)
    if par >= 0:
        (left if side == 0 else right)[par] = nid
    return nid


# ---- Step 4: primitive arrays and bounds ----

def primitive_tree(prims) -> FlatTree:
    """A FlatTree with the primitive arrays of `prims` (from `item_tree`) and no nodes yet."""
    n = len(prims)
    shape = np.empty(n, np.int64)
    to_world = np.empty((n, 4, 4))
    param = np.zeros((n, 2))
    plane_start = np.zeros(n, np.int64)
    plane_count = np.zeros(n, np.int64)
    plane_sets: dict[int, tuple[int, np.ndarray]] = {}   # id(planes array) -> (start, vertices)
    mesh_sets: dict[int, tuple[int, int]] = {}            # id(faces array) -> (plane start, root)
    plane_chunks, triangle_chunks, bvhs, n_planes, n_mesh_nodes = [], [], [], 0, 0
    materials = []
    for i, (prim, matrix, material) in enumerate(prims):
        canon, prm, planes = prim.canonical()
        shape[i] = K.SHAPE_CODES[prim.canonical_shape]
        to_world[i] = matrix @ canon
        param[i] = prm
        materials.append(material)
        if shape[i] == K.MESH:
            key = id(prim.faces)
            if key not in mesh_sets:
                bvh = mesh_bvh.build(prim.vertices, prim.faces)
                mesh_sets[key] = (n_planes, n_mesh_nodes)
                plane_sets[key] = (n_planes, prim.vertices)
                plane_chunks.append(bvh.planes)
                triangle_chunks.append(bvh.triangles)
                bvhs.append((n_mesh_nodes, bvh))
                n_planes += len(bvh.planes)
                n_mesh_nodes += bvh.num_nodes
            plane_start[i], root = mesh_sets[key]
            param[i] = (root, 0)
        elif planes is not None:
            key = id(planes)
            if key not in plane_sets:
                plane_sets[key] = (n_planes, prim.vertices)
                plane_chunks.append(planes)
                triangle_chunks.append(np.zeros((len(planes), K.TRIANGLE_FLOATS)))
                n_planes += len(planes)
            plane_start[i] = plane_sets[key][0]
            plane_count[i] = len(planes)
    planes = np.vstack(plane_chunks) if plane_chunks else np.zeros((0, 4))
    triangles = np.vstack(triangle_chunks) if triangle_chunks else np.zeros((0, K.TRIANGLE_FLOATS))
    vertices = dict(plane_sets.values())
    mesh = _mesh_nodes(bvhs)
    lower, upper = primitive_bounds(shape, to_world, param, plane_start, vertices)
    check_float32_range(lower, upper, [p for p, _, _ in prims])
    to_canonical = _inverses(to_world, prims)
    return FlatTree(*_no_nodes(), shape, to_canonical, to_world, param, plane_start, plane_count, lower, upper,
                    materials, planes=planes, plane_vertices=vertices, triangles=triangles, **mesh)


# What the float32 kernel traces (docs/limits.md). The kernel works in the scene's own frame
# (engine.device: root box centred, half-side 1, unit ray directions), so the scene's absolute
# size does not matter; the rays reach it as float32 world coordinates, which bounds sizes and
# coordinates absolutely (MIN_LENGTH, MAX_COORDINATE). Relative to the scene, a primitive
# below UNREPRESENTABLE of its size overflows float32 in its own frame, and one below RESOLVED
# lies within the tie window of the scene's coordinates (docs/accuracy.md): rays may miss it
# or merge its faces. A scene far from the world origin for its size gets coarse float32 ray
# origins (FAR_FROM_ORIGIN).
MIN_LENGTH = 1e-30
MAX_COORDINATE = 1e30
UNREPRESENTABLE = 1e-15
RESOLVED = 2.0**-18
FAR_FROM_ORIGIN = 2.0**10


class PrecisionWarning(UserWarning):
    """Part of the model is too small, or too far from the origin, for float32 to trace reliably."""


def check_float32_range(lower: np.ndarray, upper: np.ndarray, prims: list | None = None) -> None:
    """Refuse primitives outside the range the float32 kernel traces; warn about those it
    cannot trace reliably. `prims` names them in messages."""
    def name(i):
        kind = type(prims[i]).__name__ if prims is not None else "primitive"
        return f"primitive {i} ({kind}, in leaves() order)"
    if not len(lower):
        return
    finite = np.all(np.isfinite(lower) & np.isfinite(upper), axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise ModelError(f"{name(i)}: its bounds are not finite (sizes or translations beyond float64's range)")
    size = np.max(upper - lower, axis=1)
    thickness = np.min(upper - lower, axis=1)      # a flat primitive is as unrepresentable as a tiny one
    reach = np.maximum(np.abs(lower), np.abs(upper)).max(axis=1)
    scene = float(np.max(upper.max(axis=0) - lower.min(axis=0)))
    for bad, what in ((reach > MAX_COORDINATE, f"reaches beyond {MAX_COORDINATE:g} from the origin"),
                      (thickness < MIN_LENGTH, f"is thinner than {MIN_LENGTH:g}, below float32 world coordinates"),
                      (thickness < UNREPRESENTABLE * scene,
                       f"is thinner than {UNREPRESENTABLE:g} of the scene's size {scene:.3g}, beyond float32 in "
                       f"its own frame")):
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ModelError(f"{name(i)}: its box ({thickness[i]:.3g} to {size[i]:.3g} across) {what} "
                             f"(docs/limits.md)")
    small = size < RESOLVED * scene
    if small.any():
        i = int(np.argmin(size))
        warnings.warn(f"{int(small.sum())} primitive(s) are smaller than 2^-18 of the scene's size {scene:.3g}, "
                      f"below what float32 traces reliably (the smallest: {name(i)}, size {size[i]:.3g}); rays may "
                      f"miss them or merge their faces (docs/limits.md)", PrecisionWarning, stacklevel=4)
    if reach.max() > FAR_FROM_ORIGIN * scene:
        warnings.warn(f"the model lies {reach.max():.3g} from the origin but is only {scene:.3g} across: float32 "
                      f"ray origins near it are {reach.max() * 2.0**-24:.3g} apart; move it nearer the origin "
                      f"(docs/limits.md)", PrecisionWarning, stacklevel=4)


def _inverses(to_world: np.ndarray, prims: list | None = None) -> np.ndarray:
    """World -> canonical rows (P, 3, 4); a singular map names its primitive."""
    try:
        return np.linalg.inv(to_world)[:, :3, :]
    except np.linalg.LinAlgError:
        i = int(np.argmin(np.abs(np.linalg.det(to_world[:, :3, :3]))))
        kind = type(prims[i][0]).__name__ if prims is not None else "primitive"
        raise ModelError(f"primitive {i} ({kind}, in leaves() order): its transform is singular") from None


def _mesh_nodes(bvhs) -> dict:
    """All meshes' BVH nodes in one set of arrays (child indices made absolute)."""
    if not bvhs:
        empty = np.zeros(0, np.int64)
        return dict(mesh_lower=np.zeros((0, 3)), mesh_upper=np.zeros((0, 3)), mesh_right=empty,
                    mesh_first=empty, mesh_count=empty)
    return dict(mesh_lower=np.vstack([b.lower for _, b in bvhs]), mesh_upper=np.vstack([b.upper for _, b in bvhs]),
                mesh_right=np.concatenate([b.right + offset for offset, b in bvhs]),
                mesh_first=np.concatenate([b.first for _, b in bvhs]),
                mesh_count=np.concatenate([b.count for _, b in bvhs]))


def _no_nodes():
    empty = np.zeros(0, np.int64)
    return empty, np.zeros(0, bool), empty, empty, empty, np.zeros((0, 3)), np.zeros((0, 3)), empty


def with_nodes(prims: FlatTree, kind, negative, left, right, parent) -> FlatTree:
    """`prims`'s primitive arrays with the given binary tree (preorder, root 0), bounds computed."""
    lower_, upper_, height, negative = _node_bounds(kind, negative, left, right, prims.prim_lower, prims.prim_upper)
    return replace(prims, node_kind=kind, node_negative=negative, node_left=left, node_right=right,
                   node_parent=parent, node_lower=lower_, node_upper=upper_, node_height=height, root=0)


def with_primitive_transforms(flat: FlatTree, to_world: np.ndarray) -> FlatTree:
    """`flat` with new canonical -> world matrices (P, 4, 4): primitive and node bounds re-derived."""
    lower, upper = primitive_bounds(flat.prim_shape, to_world, flat.prim_param, flat.prim_plane_start,
                                    flat.plane_vertices)
    check_float32_range(lower, upper)
    prims = replace(flat, prim_to_world=to_world, prim_to_canonical=_inverses(to_world),
                    prim_lower=lower, prim_upper=upper)
    return with_nodes(prims, flat.node_kind, flat.node_negative, flat.node_left, flat.node_right,
                      flat.node_parent)


def operation_boxes(is_union, child_lower, child_upper, child_negative, starts):
    """Boxes and co-boundedness of operations from their operands' (positive form, paper §4.1).

    Operation i has operands starts[i] .. starts[i+1] - 1 (at least one). An intersection is
    bounded by the common box of its bounded operands, or, if all are co-bounded, co-bounded
    by the hull of their boxes (~a & ~b = ~(a | b)). A union is co-bounded by the common box
    of its co-bounded operands (~a | b = ~(a - b)), or, if all are bounded, bounded by the
    hull. Returns (lower, upper, negative) per operation.
    """
    counts = np.diff(np.append(starts, len(child_negative)))
    special = child_negative == np.repeat(is_union, counts)   # bounded in an intersection, co-bounded in a union
    has_special = np.add.reduceat(special.astype(np.int64), starts) > 0
    common_lo = np.maximum.reduceat(np.where(special[:, None], child_lower, -np.inf), starts)
    common_hi = np.minimum.reduceat(np.where(special[:, None], child_upper, np.inf), starts)
    hull_lo = np.minimum.reduceat(child_lower, starts)
    hull_hi = np.maximum.reduceat(child_upper, starts)
    lower = np.where(has_special[:, None], common_lo, hull_lo)
    upper = np.where(has_special[:, None], common_hi, hull_hi)
    negative = np.where(is_union, has_special, ~has_special)
    return lower, upper, negative


def _node_bounds(kind, negative, left, right, prim_lower, prim_upper):
    """Boxes and heights bottom-up, one vectorized pass per tree depth."""
    n = len(kind)
    depth = np.zeros(n, np.int64)
    frontier = np.array([0])
    level = 0
    while len(frontier):
        depth[frontier] = level
        f_ops = frontier[kind[frontier] != K.LEAF]
        frontier = np.concatenate([left[f_ops], right[f_ops]])
        level += 1
    lower = np.empty((n, 3))
    upper = np.empty((n, 3))
    height = np.zeros(n, np.int64)
    leaves = kind == K.LEAF
    lower[leaves] = prim_lower[left[leaves]]
    upper[leaves] = prim_upper[left[leaves]]
    for d in range(depth.max(initial=0), -1, -1):
        ids = np.flatnonzero((depth == d) & ~leaves)
        if not len(ids):
            continue
        l, r, k = left[ids], right[ids], kind[ids]
        height[ids] = 1 + np.maximum(height[l], height[r])
        # A difference is an intersection with the complement of its right child.
        children = np.stack([l, r], 1).ravel()
        child_negative = np.stack([negative[l], negative[r] ^ (k == K.DIFFERENCE)], 1).ravel()
        lower[ids], upper[ids], negative[ids] = operation_boxes(
            k == K.UNION, lower[children], upper[children], child_negative, np.arange(0, 2 * len(ids), 2))
    return lower, upper, height, negative


def lowered_height(root_item) -> int:
    """Height of the binary tree `lower` emits for an item tree (general form)."""
    def balanced(hs, lo, hi):
        if hi - lo == 1:
            return hs[lo]
        mid = (lo + hi) // 2
        return 1 + max(balanced(hs, lo, mid), balanced(hs, mid, hi))

    heights = []
    stack = [(root_item, False)]
    while stack:
        item, done = stack.pop()
        if item[0] == "leaf":
            heights.append(0)
            continue
        op, kids = item
        if not done:
            stack.append((item, True))
            stack.extend((k, False) for k in reversed(kids))
            continue
        hs = heights[len(heights) - len(kids):]
        del heights[len(heights) - len(kids):]
        if op == DIFFERENCE:
            rest = hs[1:]
            heights.append(1 + max(hs[0], balanced(rest, 0, len(rest))))
        else:
            heights.append(balanced(hs, 0, len(hs)))
    return heights[0]


def lower(model: Node, positive: bool = False) -> FlatTree:
    """Flatten `model` into a FlatTree; `positive=True` gives the positive form."""
    prims: list = []
    root_item = item_tree(model, prims)
    return with_nodes(primitive_tree(prims), *_emit(root_item, positive))
