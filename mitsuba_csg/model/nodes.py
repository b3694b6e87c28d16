"""The CSG model: small immutable trees of primitives and Boolean operations.

A node is a value. Transforms and materials return new nodes that share their children,
so building a cheese or a city is cheap, and trees can be shared between models.
Transforms stay on the node they were applied to; `leaves()` and the lowering step
multiply them down to the primitives.
"""
from __future__ import annotations

from typing import Iterator

import numpy as np

from ..errors import ModelError
from . import transform as tf

UNION, INTERSECTION, DIFFERENCE = "union", "intersection", "difference"
OPERATIONS = (UNION, INTERSECTION, DIFFERENCE)

# Primitives in one model once shared subtrees are expanded (each use of a shared subtree is
# a copy for the kernel): 10^7 leaves need several GB to lower and optimize (docs/limits.md).
MAX_LEAVES = 10_000_000


class Node:
    """Common base of primitives and operations: transforms, operators, queries."""

    __slots__ = ("matrix", "material")

    def __init__(self, matrix: np.ndarray = tf.IDENTITY, material: str | None = None):
        self.matrix = matrix      # local-to-parent 4x4, read-only
        self.material = material  # material name; inherited by leaves that have none

    # ---- Immutable updates ----
    def _with(self, **changes) -> "Node":
        clone = object.__new__(type(self))
        for cls in type(self).__mro__:
            for slot in getattr(cls, "__slots__", ()):
                setattr(clone, slot, changes.get(slot, getattr(self, slot)))
        return clone

    def transform(self, matrix) -> "Node":
        """Apply a 4x4 (or 3x4) affine matrix, in the parent frame."""
        return self._with(matrix=tf.compose(tf.affine(matrix), self.matrix))

    def translate(self, offset) -> "Node":
        return self._with(matrix=tf.compose(tf.translation(offset), self.matrix))

    def rotate(self, axis, degrees: float) -> "Node":
        """Right-handed rotation by `degrees` about `axis` ('x', 'y', 'z' or a vector) through the origin."""
        return self._with(matrix=tf.compose(tf.rotation(axis, degrees), self.matrix))

    def scale(self, factors) -> "Node":
        """Scale by a number or by (sx, sy, sz) about the origin; negative factors mirror."""
        return self._with(matrix=tf.compose(tf.scaling(factors), self.matrix))

    def with_material(self, name: str) -> "Node":
        """Name the material of this subtree; leaves with a material of their own keep it."""
        if not isinstance(name, str) or not name:
            raise ModelError(f"with_material: expected a non-empty string, got {name!r}")
        return self._with(material=name)

    # ---- Boolean operators ----
    def __or__(self, other: "Node") -> "Operation":
        return Operation(UNION, (self, other))

    def __and__(self, other: "Node") -> "Operation":
        return Operation(INTERSECTION, (self, other))

    def __sub__(self, other: "Node") -> "Operation":
        return Operation(DIFFERENCE, (self, other))

    # ---- Queries ----
    def leaves(self) -> list["Primitive"]:
        """The primitives in depth-first input order, each with its world transform and material.

        Hit primitive indices (`trace(...).prim`) index this list.
        """
        return [leaf._with(matrix=m, material=mat) for leaf, m, mat in self.walk_leaves()]

    def walk_leaves(self) -> Iterator[tuple["Primitive", np.ndarray, str | None]]:
        """(primitive, world matrix, resolved material) in depth-first input order, iteratively."""
        stack = [(self, tf.IDENTITY, None)]
        while stack:
            node, parent_matrix, inherited = stack.pop()
            matrix = tf.compose(parent_matrix, node.matrix)
            material = node.material if node.material is not None else inherited
            if isinstance(node, Operation):
                stack.extend((c, matrix, material) for c in reversed(node.children))
            else:
                yield node, matrix, material

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned box (lower, upper) of the solid, exact for primitives."""
        from ..engine.lowering import lower     # exact primitive boxes live with the engine's shapes
        flat = lower(self)
        return flat.node_lower[flat.root].copy(), flat.node_upper[flat.root].copy()

    @property
    def leaf_count(self) -> int:
        """Number of primitives in `leaves()` (shared subtrees counted once per use)."""
        return 1

    def tree_height(self) -> int:
        """Number of operation levels on the longest root-to-leaf path of the input tree."""
        heights: dict[int, int] = {}       # per shared operation node, so a DAG costs its size
        stack = [(self, False)]
        while stack:
            node, children_done = stack.pop()
            if not isinstance(node, Operation) or id(node) in heights:
                continue
            if children_done:
                heights[id(node)] = 1 + max(heights.get(id(c), 0) for c in node.children)
            else:
                stack.append((node, True))
                stack.extend((c, False) for c in node.children)
        return heights.get(id(self), 0)

    def _transform_repr(self) -> str:
        if self.matrix is tf.IDENTITY:
            return ""
        return ".transform(" + np.array2string(self.matrix, separator=", ", precision=6) + ")"


# Primitive classes by their name in native files, as they define themselves (`Primitive`).
PRIMITIVE_TYPES: dict[str, type] = {}


class Primitive(Node):
    """A closed analytic solid in its local frame (see `mitsuba_csg.model.primitives`).

    A primitive's class is where the project learns about it: its canonical form for the
    kernel (`canonical`, `canonical_shape`), its name and parameters in native files
    (`type_name`, `file_parameters`, `parameters`) and its reference mesh (`tessellate`,
    `mesh_key`). A class that names a `type_name` of its own is registered for the readers
    and writers (`PRIMITIVE_TYPES`); a subclass without one is written as its base.
    """

    __slots__ = ()
    type_name: str | None = None    # its node type in native files
    # Its parameters in native files, each with what a file must give: "positive",
    # "nonnegative", "size" (a number or three), "sides", "planes", "vertices" or "faces".
    file_parameters: dict = {}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        name = cls.__dict__.get("type_name")
        if name:
            PRIMITIVE_TYPES[name] = cls

    @classmethod
    def file_type(cls) -> str | None:
        """The node type this primitive is written as: its own class's or its nearest base's."""
        for klass in cls.__mro__:
            if klass.__dict__.get("type_name"):
                return klass.__dict__["type_name"]
        return None

    def parameters(self) -> dict:
        """Its `file_parameters` and their values, as a native file writes them."""
        return {name: getattr(self, name) for name in self.file_parameters}

    def mesh_key(self) -> tuple:
        """Primitives with equal keys have the same reference mesh (`tessellate`)."""
        return (type(self).file_type(), *(repr(v) for v in self.parameters().values()))

    def tessellate(self, segments: int):
        """The reference mesh (a `manifold3d.Manifold`) of the primitive in its local frame,
        made from its own parameters with manifold3d's constructors, so that it shares no
        geometry code with the engine; `segments` edges around a full circle."""
        raise ModelError(f"to_mesh: no mesh for the primitive {self!r}")


class Operation(Node):
    """An n-ary Boolean operation.

    `difference(a, b, c)` is a - b - c. Binary operators build binary nodes; the lowering
    step flattens chains of one associative operation, so `a | b | c | ...` costs no depth.
    """

    __slots__ = ("kind", "children", "_leaf_count")

    def __init__(self, kind: str, children, matrix: np.ndarray = tf.IDENTITY, material: str | None = None):
        super().__init__(matrix, material)
        if kind not in OPERATIONS:
            raise ModelError(f"unknown operation {kind!r}; expected one of {', '.join(OPERATIONS)}")
        children = tuple(children)
        if not children:
            raise ModelError(f"{kind}: needs at least one operand, got none (empty tree)")
        for i, c in enumerate(children):
            if not isinstance(c, Node):
                raise ModelError(f"{kind}: operand {i} is a {type(c).__name__}, not a CSG node")
        # Counted as the tree is built, so a small description of a huge tree (a subtree
        # used twice at every level) is refused before anything walks it.
        count = sum(c.leaf_count for c in children)
        if count > MAX_LEAVES:
            raise ModelError(f"{kind}: the model expands to {count:.3g} primitives (shared subtrees are copied "
                             f"for each use), more than the limit of {MAX_LEAVES:.0e}")
        self.kind = kind
        self.children = children
        self._leaf_count = count

    @property
    def leaf_count(self) -> int:
        return self._leaf_count

    def __repr__(self) -> str:
        inner = ", ".join(repr(c) for c in self.children[:4])
        more = f", ... ({len(self.children)} operands)" if len(self.children) > 4 else ""
        return f"{self.kind}({inner}{more}){self._transform_repr()}"


def union(*nodes: Node) -> Operation:
    """The union of all operands (at least one)."""
    return Operation(UNION, _operands(nodes))


def intersection(*nodes: Node) -> Operation:
    """The intersection of all operands (at least one)."""
    return Operation(INTERSECTION, _operands(nodes))


def difference(first: Node, *others: Node) -> Operation:
    """`first` minus every other operand."""
    return Operation(DIFFERENCE, (first, *_operands(others, allow_empty=True)))


def _operands(nodes, allow_empty: bool = False) -> tuple:
    # Accept union(a, b, c) as well as union([a, b, c]) or union(generator).
    if len(nodes) == 1 and not isinstance(nodes[0], Node):
        nodes = tuple(nodes[0])
    if not nodes and not allow_empty:
        raise ModelError("an operation needs at least one operand, got none (empty tree)")
    return tuple(nodes)
