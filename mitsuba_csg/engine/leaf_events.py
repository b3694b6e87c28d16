"""The next event of a leaf, or of a compound set member: what the automaton and the set walk
ask of the primitives.

An event is a leaf's first boundary crossing after `t_start` (`engine.shapes.first_event`)
classified as ENTER, EXIT or MISS for the leaf as the tree sees it: a complemented leaf
swaps enter and exit, and a miss of it is an exit at infinity. A compound member (an
intersection of a few convex leaves and complements of convex leaves, `engine.set_layout`)
has its next event found in rounds over its literals (`compound_hit`).
"""
from __future__ import annotations

import drjit as dr

from . import layout as K
from . import shapes
from .device import gather_prim
from .layout import EXIT, FLIP_BIT, MISS, NO_INDEX


def no_hit(b, width, t=dr.inf):
    """A Hit per lane that is no event: no leaf, class MISS, at `t` (inf unless given; a
    number or a Float of the lanes)."""
    t = dr.full(b.Float, t, width) if isinstance(t, (int, float)) else b.Float(t)
    return b.Hit(t, dr.full(b.UInt32, NO_INDEX, width), dr.full(b.UInt32, MISS, width))


def complement_class(cls):
    """The class of the same event for the complement: enter <-> exit, a miss is an exit at infinity."""
    return dr.select(cls == MISS, EXIT, cls ^ 1)


def tie_window(b, tie, slope):
    """How far in t two events may lie apart and still be one event, for a SLOPE exponent."""
    return tie * b.Float(b.UInt32(2) << slope)


def box_span(tree, ray, node, active):
    """(near, far) of the ray's parameter inside the node's box (NaN for an empty box)."""
    b = tree.b
    lo4 = dr.gather(b.Array4f, tree.node_box, node * 2, active)
    hi4 = dr.gather(b.Array4f, tree.node_box, node * 2 + 1, active)
    return shapes.box_entry(lo4, hi4, ray.o, ray.inv_d)


def box_meets(tree, ray, node, t_start, active=True):
    """Whether the ray meets the node's box within [t_start, ray.tmax]."""
    near, far = box_span(tree, ray, node, active)
    return (near <= far) & (far >= t_start) & (near <= ray.tmax)


def leaf_hit(tree, ray, node, flags, prim, t_start):
    """(Hit, non-convex) of a leaf node's first event after t_start, complement applied
    (`flags`, `prim`: the leaf's node record)."""
    b = tree.b
    record = gather_prim(b, tree, prim)
    # A mesh's crossings within a tie window after t_start are the event at t_start again.
    mesh = (tree.triangles, tree.mesh_nodes, 2.0 * ray.tie) if tree.has_meshes else None
    t, face, cls, slope = shapes.first_event(b, record, tree.planes, ray.o, ray.d, t_start, mesh, tree.shape_kinds)
    complemented = K.flags_negative(flags)
    # A complemented leaf swaps enter/exit; missing it means being inside it forever.
    cls = dr.select(complemented, complement_class(cls), cls)
    non_convex = dr.zeros(b.Bool, dr.width(t))
    for code in shapes.NON_CONVEX_CODES:
        if code in tree.shape_kinds:
            non_convex |= record.shape == code
    info = K.hit_info(cls, dr.select(complemented, FLIP_BIT, 0), face, slope)
    return b.Hit(t, b.UInt32(node), info), non_convex


def member_hit(tree, ray, node, flags, prim, t_start, active):
    """(Hit, non-convex, leaf intersections) of a set member's first event after t_start: a
    leaf's own, or a compound's (`compound_hit`, compiled in only for trees that have
    compounds)."""
    if not tree.has_compounds:
        hit, non_convex = leaf_hit(tree, ray, node, flags, prim, t_start)
        return hit, non_convex, 1
    return compound_hit(tree, ray, node, flags, prim, t_start, active)


def _slot(k, values):
    """values[k] per lane (k < len(values))."""
    value = values[-1]
    for slot in range(len(values) - 2, -1, -1):
        value = dr.select(k == slot, values[slot], value)
    return value


# Rounds of `compound_hit` before it gives up (each passes at least one of the literals' at
# most two events, so 2 x MAX_COMPOUND_LITERALS + 1 suffice).
_COMPOUND_ROUNDS = 2 * K.MAX_COMPOUND_LITERALS + 2


@dr.syntax
def compound_hit(tree, ray, node, flags, prim, t_start, active):
    """(Hit, non-convex, leaf intersections) of the first event after t_start of a compound set
    member: an intersection of up to MAX_COMPOUND_LITERALS convex leaves and complements of
    convex leaves (a satellite's wing with its cut-outs, `engine.set_layout`).

    Rounds from `cur` (t_start first): every literal's first event after cur. All inside:
    the compound is inside past cur, so its next event is the nearest exit (the first round)
    or its entry at cur (later rounds: cur is the latest entry of the round before). Some
    literal outside for good: no event. Otherwise the next round starts at the latest entry
    of the literals outside. A literal whose exit lies within the tie window after an entry
    at cur leaves as another enters (touching faces, as in the state tables): it counts as
    outside, its exit as an entry to wait for. A literal outside for good (a miss) ends the
    search at once.

    A plain leaf member (`flags`, `prim`: the member's node record) is a compound of one literal,
    itself: its event is its first. A packet whose lanes hold members of both kinds then
    runs one leaf intersection per round, instead of the rounds and then the plain leaves'.
    """
    b = tree.b
    width = dr.width(t_start)
    plain = b.Bool(active) & (K.flags_kind(flags) == K.LEAF)
    record = dr.gather(b.UInt32, tree.walk_entry, node, active & ~plain)
    words = dr.gather(b.module.ArrayXu, tree.compound_literals, record, active & ~plain,
                      shape=(K.COMPOUND_RECORD_WORDS, width))
    # A plain leaf member is a compound of one literal: itself.
    literals = [dr.select(plain, b.UInt32(node), words[0])] + \
        [dr.select(plain, K.NO_INDEX, words[i]) for i in range(1, K.MAX_COMPOUND_LITERALS)]
    prims = [dr.select(plain, prim, words[K.MAX_COMPOUND_LITERALS])] + \
        [words[K.MAX_COMPOUND_LITERALS + i] for i in range(1, K.MAX_COMPOUND_LITERALS)]
    count = dr.zeros(b.UInt32, width)
    non_convex = dr.zeros(b.Bool, width)
    for slot in range(K.MAX_COMPOUND_LITERALS):
        present = literals[slot] != K.NO_INDEX
        count += dr.select(present, 1, 0)
        non_convex |= present & ((literals[slot] & K.LITERAL_COMPLEMENT) != 0)
    cur = b.Float(t_start)
    cand = no_hit(b, width, t_start)            # the latest entry of the round before
    res = no_hit(b, width)
    # This round's accumulators: all inside so far; the nearest exit; the latest entry (or tied
    # exit) of the literals outside; a literal outside for good.
    all_in = dr.full(b.Bool, True, width)
    exit_hit = no_hit(b, width)
    late = no_hit(b, width, -dr.inf)
    never = dr.zeros(b.Bool, width)
    k = dr.zeros(b.UInt32, width)
    rounds = dr.zeros(b.UInt32, width)
    evaluated = dr.zeros(b.UInt32, width)
    done = ~b.Bool(active)
    while dr.hint(~done, label="csg_compound", exclude=[ray, literals, prims, count]):
        literal, prim = _slot(k, literals), _slot(k, prims)
        leaf = literal & ~b.UInt32(K.LITERAL_COMPLEMENT)
        # Literal leaves are positive (engine.set_layout): the literal's own bit is the complement.
        flags = dr.select((literal & K.LITERAL_COMPLEMENT) != 0, b.UInt32(K.NEGATIVE_BIT), 0)
        hit_k, odd_k = leaf_hit(tree, ray, leaf, flags, prim, cur)
        evaluated += 1
        cls_k = K.info_class(hit_k.info)
        window = tie_window(b, ray.tie, dr.minimum(K.info_slope(hit_k.info), K.info_slope(cand.info)))
        # (Not the literal that entered at cur: a thin slab's own exit is no tie.)
        tied = (cls_k == EXIT) & (rounds > 0) & (leaf != cand.leaf) & (hit_k.t <= cur + window)
        inside = (cls_k == EXIT) & ~tied
        all_in &= inside
        exit_hit = dr.select(inside & (hit_k.t < exit_hit.t), hit_k, exit_hit)
        never |= ~inside & (cls_k == MISS)
        late = dr.select(~inside & (cls_k != MISS) & (hit_k.t > late.t), hit_k, late)
        last = k + 1 >= count
        exits = last & all_in & (rounds == 0)
        enters = last & all_in & (rounds > 0)
        misses = never | (last & ~all_in & (rounds + 1 >= _COMPOUND_ROUNDS))
        res = dr.select(exits, exit_hit, dr.select(enters, cand, res))
        # A plain leaf's event is its own, whatever its class.
        res = dr.select(plain, hit_k, res)
        non_convex |= plain & odd_k
        done |= exits | enters | misses | plain
        advance = last & ~done
        cur = dr.select(advance, late.t, cur)
        cand = dr.select(advance, late, cand)
        rounds = dr.select(advance, rounds + 1, rounds)
        all_in |= last
        never &= ~last
        exit_hit.t = dr.select(last, dr.inf, exit_hit.t)
        late.t = dr.select(last, -dr.inf, late.t)
        k = dr.select(last, 0, k + 1)
    return res, non_convex, evaluated
