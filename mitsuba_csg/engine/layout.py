"""Codes and bit layouts shared by the lowering, the device upload and the kernel.

Everything that two stages must agree on bit for bit lives here, with named accessors, so
no other module writes a literal mask; so do the state tables, which the upload puts on the
device and the automaton reads. The accessors work on numpy arrays and on Dr.Jit
arrays alike (they only use integer operators).

Node flags word (one per flat-tree node)::

    bits 0-1  node kind: UNION, INTERSECTION, DIFFERENCE or LEAF
    bit  2    NEGATIVE: a complemented leaf, or a co-bounded operation of the positive form
    bits 3-4  ORDER axis of a union or intersection: the axis along which its children's
              boxes lie furthest apart (NO_ORDER: none); a ray searches first the child
              that lies first along its direction on that axis
    bit  5    LEFT_HIGH: the left child's box centre is the higher one on the ORDER axis
    bit  6    GROUP: a union node that joins separate solids (`engine.grouping`): its next
              event is the nearer of its children's, whatever their classes
    bit  7    SET: the root of a subtree of unions of positive leaves, searched as one n-ary
              node (`engine.set_walk`)
    bits 8-10 of an operation, its left child's CHILD_NEGATIVE, CHILD_LEAF and CHILD_SET bits
              (the child's own bits 2, kind == LEAF and 7), so that GoTo needs no child record
    bits 11-13 the same of its right child

Hit info word (one per returned hit)::

    bits 0-1  event class relative to the subtree that returned it: ENTER, EXIT or MISS
    bit  2    FLIP: the primitive's normal is reversed (complemented leaf, or the right side
              of a difference, an odd number of times)
    bit  3    PROVISIONAL: not an event but a bound: the subtree was not searched past t, and
              the class says its state before t (ENTER: outside, EXIT: inside)
    bits 4-7  SLOPE: k with 2^-(k+1) < |cos| <= 2^-k between the ray and the surface's normal
              (0 to MAX_SLOPE): the event's tie window is 2^(k+1) tie tolerances (see
              `engine.automaton`), as t errors grow like 1 / |cos|
    bits 8-31 face index within the primitive (see `engine.shapes`)

Primitive record: 16 floats per primitive (a power of two, so one gather fetches it)::

    0-11   rows of the world -> canonical affine map
    12-13  two shape parameters (cone radii, torus minor radius); a mesh: its BVH's root node
           (uint32 bits)
    14     first plane of a convex primitive or mesh (uint32 bits; a mesh's triangle k is
           plane and triangle row start + k)
    15     plane count | shape code << 16 (uint32 bits)
"""
from __future__ import annotations

import numpy as np

# ---- Node kinds ----
UNION, INTERSECTION, DIFFERENCE, LEAF = 0, 1, 2, 3
KIND_NAMES = {UNION: "union", INTERSECTION: "intersection", DIFFERENCE: "difference", LEAF: "leaf"}

# ---- Canonical shapes (model primitives name theirs; the kernel knows these codes) ----
SPHERE, BOX, CONE, TORUS, CONVEX, MESH, QUADRIC = 0, 1, 2, 3, 4, 5, 6
SHAPE_CODES = {"sphere": SPHERE, "box": BOX, "cone": CONE, "torus": TORUS, "convex": CONVEX, "mesh": MESH,
               "quadric": QUADRIC}
# Which are convex (one interval along a ray) their rows say: engine.shapes.CONVEX_CODES.
SHAPE_NAMES = {code: name for name, code in SHAPE_CODES.items()}

# ---- Event classes ----
ENTER, EXIT, MISS = 0, 1, 2

# The absent index, wherever a word holds a node, leaf, primitive, tree entry or literal:
# the leaf and primitive of a miss, no set, no neighbour tree, an unused literal slot.
NO_INDEX = 0xFFFFFFFF

# ---- Node flags ----
KIND_MASK = 0x3
NEGATIVE_BIT = 0x4
ORDER_SHIFT = 3
ORDER_MASK = 0x3
NO_ORDER = 3
LEFT_HIGH_BIT = 0x20
GROUP_BIT = 0x40
SET_BIT = 0x80
# What an operation's GoTo needs to know of each child without reading the child's record:
# CHILD_BITS bits per child, the left child's at CHILD_SHIFT, the right child's above them.
CHILD_SHIFT = 8
CHILD_BITS = 3
CHILD_NEGATIVE, CHILD_LEAF, CHILD_SET = 0x1, 0x2, 0x4


def node_flags(kind, negative, order=NO_ORDER, left_high=0, group=0, set_root=0, children=0):
    """The flags word of nodes (numpy integer and bool arrays); `children` is the left
    child's CHILD_* bits | the right child's << CHILD_BITS."""
    return (kind | (negative << 2) | (order << ORDER_SHIFT) | (left_high << 5) | (group << 6) | (set_root << 7)
            | (children << CHILD_SHIFT))


def flags_children(flags):
    """(left, right): the CHILD_* bits of an operation's two children."""
    mask = (1 << CHILD_BITS) - 1
    return (flags >> CHILD_SHIFT) & mask, (flags >> (CHILD_SHIFT + CHILD_BITS)) & mask


def flags_set(flags):
    return (flags & SET_BIT) != 0


def flags_group(flags):
    return (flags & GROUP_BIT) != 0


def flags_order(flags):
    """The ORDER axis (0-2) of an operation, or NO_ORDER."""
    return (flags >> ORDER_SHIFT) & ORDER_MASK


def flags_left_high(flags):
    return (flags & LEFT_HIGH_BIT) != 0


def flags_kind(flags):
    return flags & KIND_MASK


def flags_negative(flags):
    """True where a leaf is complemented or an operation is co-bounded."""
    return (flags & NEGATIVE_BIT) != 0


# ---- Hit info ----
CLASS_MASK = 0x3
FLIP_BIT = 0x4
PROVISIONAL_BIT = 0x8
SLOPE_SHIFT = 4
SLOPE_MASK = 0xF
MAX_SLOPE = 10            # |cos| below 2^-10 gets the window of 2^-10: grazing rays may still tie wrongly
FACE_SHIFT = 8
_KEEP_OTHERS = 0xFFFFFFFF ^ (CLASS_MASK | FLIP_BIT)    # a literal: Dr.Jit's UInt32 takes no negative ~mask


def hit_info(cls, flip, face, slope=0):
    """The info word of hits: `flip` is 0 or FLIP_BIT, `slope` the SLOPE exponent."""
    return cls | flip | (slope << SLOPE_SHIFT) | (face << FACE_SHIFT)


def info_class(info):
    return info & CLASS_MASK


def info_flipped(info):
    return (info & FLIP_BIT) != 0


def info_face(info):
    return info >> FACE_SHIFT


def info_slope(info):
    return (info >> SLOPE_SHIFT) & SLOPE_MASK


def info_provisional(info):
    return (info & PROVISIONAL_BIT) != 0


def with_class(info, cls, flip):
    """`info` with its class replaced by `cls` and its flip bit toggled where `flip` is FLIP_BIT."""
    return (info & _KEEP_OTHERS) | cls | ((info & FLIP_BIT) ^ flip)


# ---- Primitive record ----
PRIM_RECORD_FLOATS = 16
NODE_WIDE_FLOATS = 16      # engine.device.node_with_child_boxes
SET_NODE_FLOATS = 32       # engine.set_layout: a 4-wide node of a set
SET_NODE_TAG = 1 << 31     # a set walk's reference to a 4-wide node (else a member's node id)

# A compound set member (engine.set_layout, engine.leaf_events.compound_hit): an intersection of
# convex leaves and complements of convex leaves, listed in a record of literal words, then
# the literals' primitives (one word each).
MAX_COMPOUND_LITERALS = 4
COMPOUND_RECORD_WORDS = 2 * MAX_COMPOUND_LITERALS
LITERAL_COMPLEMENT = 1 << 31   # the literal is the leaf's complement (the leaf node id below)
PRIM_ROWS, PRIM_PARAMS, PRIM_PLANE_START, PRIM_COUNT_SHAPE = 0, 12, 14, 15
SHAPE_SHIFT = 16
PLANE_COUNT_MASK = 0xFFFF


def count_shape(plane_count, shape):
    return plane_count | (shape << SHAPE_SHIFT)


def record_shape(word):
    return word >> SHAPE_SHIFT


def record_plane_count(word):
    return word & PLANE_COUNT_MASK


# ---- Mesh leaves: BVH node and triangle records ----
# Node: one record per inner node of a mesh BVH, holding both children's boxes, so that one
# visit tests both and descends only into those the ray reaches (16 words): left lower xyz +
# left child ref, left upper xyz + right child ref, right lower xyz + pad, right upper xyz +
# pad. A child ref is an inner node's record index, or MESH_LEAF_BIT | first triangle <<
# MESH_COUNT_BITS | count for a leaf (first relative to the mesh's plane start).
# Triangle: 12 floats, sorted vertices a, b, c (xyz + pad), parity in word 3, twice the
# triangle's area in word 7.
MESH_NODE_FLOATS = 16
TRIANGLE_FLOATS = 12
MESH_COUNT_BITS = 4
MESH_LEAF_BIT = 1 << 31


def mesh_leaf_ref(first, count):
    return MESH_LEAF_BIT | (first << MESH_COUNT_BITS) | count


def mesh_ref_is_leaf(ref):
    return (ref & MESH_LEAF_BIT) != 0


def mesh_tris_first(ref):
    return (ref & (MESH_LEAF_BIT - 1)) >> MESH_COUNT_BITS


def mesh_tris_count(ref):
    return ref & ((1 << MESH_COUNT_BITS) - 1)


# ---- State tables (compiled into the automaton as constants, TABLE_WORDS) ----
# Actions of the state tables.
RET_L, RET_R, RET_CLOSER, RET_L_ELSE_LOOP_R, RET_R_ELSE_LOOP_L, LOOP_CLOSER, RET_MISS = range(7)
_E, _X, _M = ENTER, EXIT, MISS
# Kensler's tables as refined by Bogolepov et al.; union Exit/Exit loops the closer child
# (returning the farther exit is wrong once a child is non-convex or disjoint). A difference
# uses the intersection table with the right child's class complemented.
STATE_TABLE = {
    UNION: {(_E, _E): RET_CLOSER, (_E, _X): RET_R_ELSE_LOOP_L, (_E, _M): RET_L,
            (_X, _E): RET_L_ELSE_LOOP_R, (_X, _X): LOOP_CLOSER, (_X, _M): RET_L,
            (_M, _E): RET_R, (_M, _X): RET_R, (_M, _M): RET_MISS},
    INTERSECTION: {(_E, _E): LOOP_CLOSER, (_E, _X): RET_L_ELSE_LOOP_R, (_E, _M): RET_MISS,
                   (_X, _E): RET_R_ELSE_LOOP_L, (_X, _X): RET_CLOSER, (_X, _M): RET_MISS,
                   (_M, _E): RET_MISS, (_M, _X): RET_MISS, (_M, _M): RET_MISS},
}
# A group's next event is its nearer child's: separate solids do not combine (a miss is at
# infinity, so the closer of a hit and a miss is the hit). Row 2 of the flat table.
GROUP_TABLE = {(cl, cr): RET_CLOSER for cl in (_E, _X, _M) for cr in (_E, _X, _M)}
GROUP_ROW = 2
TABLE_ARRAY = np.array([[table[(cl, cr)] for cl in range(3) for cr in range(3)]
                        for table in (STATE_TABLE[UNION], STATE_TABLE[INTERSECTION], GROUP_TABLE)],
                       dtype=np.uint32).ravel()
# The same tables as one 32-bit word per row, 3 bits per action (entry cl * 3 + cr): the
# automaton shifts its action out of a constant instead of gathering it from memory.
TABLE_WORDS = tuple(int(sum(int(a) << (3 * i) for i, a in enumerate(row))) for row in TABLE_ARRAY.reshape(3, 9))
