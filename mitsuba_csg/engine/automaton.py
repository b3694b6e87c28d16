"""The single-hit CSG automaton: Kensler's state tables, iterated as in Bogolepov et al. 2013.

`docs/algorithm.md` explains the algorithm; this module is its kernel and nothing else (the
buffers it reads are built by `engine.device`, the primitives are intersected by
`engine.shapes`, word layouts and the state tables are in `engine.layout`).

One symbolic Dr.Jit loop per ray batch walks the binary tree with two per-lane stacks of
the tree's height: a hit stack (t, leaf node, hit info) and a state stack (what to do when
a subtree's hit comes back). Each iteration does the GoTo steps of a descent (an inner
loop: one per operation node passed on the way down, each counted as a step), then at most
one search (a box test and one primitive intersection, or a set walk), one Classify step
(a state-table lookup) and one Return step (pop and hand the hit to the parent), so lanes
stay in step.

Registers: `node` (the operation whose children are in play), `t_start` (events must lie
strictly after it), `t_bound` (events of `node` past it do not matter), the left and right
hits (t, leaf, info) and the GoTo/Classify/Return state. Events of the two children closer
than their tie window (`_tie_window`, docs/accuracy.md) are one event: coincident faces.
The traversal mechanisms (restart and skip to the sibling's event, bounded search with
provisional hits, near-first order) are described in
`docs/algorithm.md` and switched by `engine.options.TraversalOptions`. A frame is pushed,
with the node's `t_bound` on a third stack, when GoTo descends into an operation child, and
popped when that child's subtree returns its hit (which then sits in both hit registers):

=========  ===========================  ===================================  ==============================
frame      pushed by                    hit stack entry holds                when popped
=========  ===========================  ===================================  ==============================
SAVE_L     GoTo left, fresh             the parent's `t_start`               the hit is the left child's:
                                        (leaf and info unused)               restore `t_start`, GoTo right
                                                                             fresh
LOAD_L     GoTo right (fresh or loop)   the left child's hit, which the      the hit is the right child's:
                                        right subtree overwrites             reload the left hit, Classify
LOAD_R     GoTo left after a loop       the right child's hit                the hit is the left child's:
                                                                             reload the right hit, Classify
=========  ===========================  ===================================  ==============================

"Left" and "right" in the table are the registers L and R: with near-first order L holds the
child searched first, which may be the node's right child (`swapped`, kept in the frame).
A frame also keeps the node that pushed it, which its child's hit returns to: with
pass-through an operation's only relevant child takes the operation's place without a
frame, and then the pushing node is not that child's parent.
A pop at stack depth 0 ends the lane (DONE) with the root's hit in the left register.
"""
from __future__ import annotations

import functools

import drjit as dr

from . import layout as K
from .device import KernelTree, Untraversed, node_record, node_with_child_boxes, opaque, scene_rays
from .layout import (DIFFERENCE, ENTER, EXIT, FLIP_BIT, INTERSECTION, LOOP_CLOSER, MAX_SLOPE, MISS, NO_INDEX,
                     RET_CLOSER, RET_L, RET_L_ELSE_LOOP_R, RET_R, RET_R_ELSE_LOOP_L, UNION)
from .leaf_events import box_meets, complement_class, leaf_hit, no_hit, tie_window
from .set_walk import next_event
from .shapes import box_entry, inverse_direction

# Events of different primitives closer than a tie window are one event for the state
# tables (docs/accuracy.md). The window is TIE_TOLERANCE x (the scene's extent + the ray
# origin's magnitude) / |d|, times 2^(k+1) >= 1 / |cos| of the event's slope: float32 maps
# into each primitive's own frame put coincident faces up to about 2 ulps of that magnitude
# apart across the surface (measured on rotated, translated and scaled touching solids), so
# at normal incidence the window is 16 ulps.
TIE_TOLERANCE = 8 * 2.0**-23

# Automaton states (GoTo states: bit 0 = right child, bit 1 = re-intersection after a loop).
GOTO_L_FRESH, GOTO_R_FRESH, GOTO_L_LOOP, GOTO_R_LOOP, CLASSIFY, RETURN, DONE = range(7)
# What a pushed frame does when the subtree's hit comes back (see the table above); the
# frame also keeps whether the parent's registers hold its children swapped (near_first).
SAVE_L, LOAD_L, LOAD_R = range(3)
SWAPPED_FRAME = 4
FRAME_NODE_SHIFT = 3     # above them, the node the frame returns to (not always the child's parent;
                         # device.MAX_NODES keeps node ids within the word)


@functools.cache
def _goto_choice_type(module):
    class GotoChoice:
        """What GoTo decided at a node: which child is searched next, on which interval, and
        whether it is descended into or its hit is known in this step."""
        DRJIT_STRUCT = {
            "flags": module.UInt32,         # the node's flags word (its kind and group bit for Classify)
            "going": module.Bool,           # the lane is in a GoTo state and the node is not vacant
            "go_right": module.Bool,        # register R receives the child's hit
            "fresh_left": module.Bool,      # a fresh search of the node's first child
            "child": module.UInt32,         # the child searched
            "child_bits": module.UInt32,    # its CHILD_* bits
            "child_is_leaf": module.Bool,   # a leaf or a set: its next event is found in this step
            "child_bound": module.Float,    # the child's events past this do not matter
            "entry_bound": module.Float,    # ... its entries past this (a set walk's bounds)
            "exit_bound": module.Float,     # ... its exits past this
            "single": module.Bool,          # the node is its child in register L (pass-through)
            "vacant": module.Bool,          # the node misses: no child needs searching
            "in_box": module.Bool,          # the child's box lies (partly) within [t_start, child_bound]
            "provisional": module.Bool,     # the box lies past a bound short of tmax: a provisional hit
            "descend": module.Bool,         # an operation child in reach: descended into
        }

        def __init__(self, **fields):
            for name in self.DRJIT_STRUCT:
                setattr(self, name, fields.get(name))
    return GotoChoice


def _tie_tolerance(tree, o, d):
    """Per ray, the t distance below which events of different primitives are one event.

    Hits lie in the root box, so |o + t d| <= extent and every float32 rounding in the maps
    to the primitives' frames is relative to at most extent + |o| (docs/accuracy.md).
    """
    magnitude = opaque(tree, tree.b.Float, tree.extent) + dr.max(dr.abs(o))
    return TIE_TOLERANCE * magnitude / dr.norm(d)


def _goto(tree, ray, node, state, t_start, t_bound, swapped, hit_l):
    """(GotoChoice, t_start, swapped): GoTo's choice at `node` in `state`, where the search
    starts (later than t_start where skip_to_sibling allows) and which child register L holds."""
    b = tree.b
    o, d, inv_d, tie = ray.o, ray.d, ray.inv_d, ray.tie
    n = dr.width(node)
    # The node's record serves GoTo (children) and Classify (kind).
    flags, node_left, node_right, box_l, box_r = node_with_child_boxes(b, tree, node)
    kind = K.flags_kind(flags)
    going = state < CLASSIFY
    go_right = (state & 1) == 1
    # The second child of a fresh search: while the first child's state fixes the node's
    # (union: inside; intersection, difference: outside), the second child's events before
    # the first child's event cannot matter (skip_to_sibling: search it from there);
    # otherwise its events after the first child's event cannot change what the node
    # returns next (bounded_search: search it only up to there).
    second = state == GOTO_R_FRESH
    cls_first = K.info_class(hit_l.info)
    fixes = dr.select(kind == UNION, cls_first == EXIT, cls_first != EXIT)
    if tree.has_groups:
        # A group's children are separate solids: none fixes what the other shows.
        fixes &= ~K.flags_group(flags)
    if tree.options.skip_to_sibling:
        t_start = dr.select(second & fixes, dr.maximum(t_start, hit_l.t), t_start)
    child_bound = t_bound
    if tree.options.bounded_search:
        # Up to the first child's event and its tie window, so that a coincident event of
        # the second child is seen as the tie it is.
        reach = hit_l.t + tie_window(b, tie, K.info_slope(hit_l.info))
        child_bound = dr.select(second & ~fixes, dr.minimum(t_bound, reach), t_bound)
    entry_bound = exit_bound = child_bound
    if tree.options.skip_to_sibling and tree.options.bounded_search:
        # Searched from the first child's event because that child fixed the node until
        # then, the second child decides what the node does there by its state alone; its
        # next event matters only where that state keeps the node's state (union and
        # difference: the second child inside, so its exit; intersection: outside, so its
        # entry). The other kind of event is searched only for ties (engine.set_walk).
        near_tie = hit_l.t + tie_window(b, tie, MAX_SLOPE)
        state_only = second & fixes
        wants_entry = kind == INTERSECTION
        entry_bound = dr.select(state_only & ~wants_entry, dr.minimum(child_bound, near_tie), child_bound)
        exit_bound = dr.select(state_only & wants_entry, dr.minimum(child_bound, near_tie), child_bound)
    fresh_left = state == GOTO_L_FRESH
    if tree.options.near_first:
        # A fresh search of a union or intersection takes first the child that lies first
        # along the ray on the node's ORDER axis (as a BVH's ordered traversal does), so
        # that its event bounds the other. Registers L and R then hold the right and the
        # left child (`swapped`); the state tables of both operations are symmetric.
        axis = K.flags_order(flags)
        d_axis = dr.select(axis == 0, d.x, dr.select(axis == 1, d.y, d.z))
        right_first = (axis != K.NO_ORDER) & ((d_axis < 0) ^ K.flags_left_high(flags))
    else:
        right_first = dr.zeros(b.Bool, n)
    # Both children's boxes, and what the node's flags say of them (a leaf, a set, co-bounded).
    bits_l, bits_r = K.flags_children(flags)
    near_l, far_l = box_entry(*box_l, o, inv_d)
    near_r, far_r = box_entry(*box_r, o, inv_d)
    swapped = dr.select(fresh_left, right_first, swapped)
    single = dr.zeros(b.Bool, n)       # the node is its child in register L
    vacant = dr.zeros(b.Bool, n)       # the node misses: no child needs searching
    if tree.options.pass_through:
        # A positive child whose box the ray does not meet after t_start is outside from
        # there on. A union with such a child, or a difference with such a subtrahend, is
        # then its other child: that child takes the node's place in the parent's frame
        # (no frame is pushed), or, a leaf or set, is searched with its sibling's miss
        # known (Classify in the same step). A union of two such children, an
        # intersection with one, a difference with such a minuend: a miss.
        gone_l = ((bits_l & K.CHILD_NEGATIVE) == 0) & ~((near_l <= far_l) & (far_l >= t_start))
        gone_r = ((bits_r & K.CHILD_NEGATIVE) == 0) & ~((near_r <= far_r) & (far_r >= t_start))
        is_union = kind == UNION
        only_l = fresh_left & gone_r & ~gone_l & (is_union | (kind == DIFFERENCE))
        only_r = fresh_left & gone_l & ~gone_r & is_union
        vacant = fresh_left & dr.select(is_union, gone_l & gone_r,
                                        dr.select(kind == INTERSECTION, gone_l | gone_r, gone_l))
        single = only_l | only_r
        swapped = dr.select(only_l, False, dr.select(only_r, True, swapped))
    use_r = go_right ^ swapped
    child = dr.select(use_r, node_right, node_left)
    near, far = dr.select(use_r, near_r, near_l), dr.select(use_r, far_r, far_l)
    child_bits = dr.select(use_r, bits_r, bits_l)
    # A set (a union of leaves) is searched as one node, like a leaf (engine.set_walk).
    child_is_leaf = (child_bits & K.CHILD_LEAF) != 0
    if tree.options.sets:
        child_is_leaf |= (child_bits & K.CHILD_SET) != 0
    going &= ~vacant
    reaches = going & (near <= far) & (far >= t_start)      # the box lies (partly) after t_start
    in_box = reaches & (near <= child_bound)
    # Past a bound short of tmax, the subtree's state is known (outside if bounded, inside
    # if co-bounded) but not its next event: a provisional hit at the bound.
    provisional = reaches & ~in_box & (child_bound < ray.tmax)
    # An operation child in reach is descended into.
    descend = in_box & ~child_is_leaf
    choice = _goto_choice_type(b.module)(
        flags=flags, going=going, go_right=go_right, fresh_left=fresh_left, child=child, child_bits=child_bits,
        child_is_leaf=child_is_leaf, child_bound=child_bound, entry_bound=entry_bound, exit_bound=exit_bound,
        single=single, vacant=vacant, in_box=in_box, provisional=provisional, descend=descend)
    return choice, t_start, swapped


def _classify(tree, ray, flags, state, t_start, t_bound, hit_l, hit_r):
    """Classify: apply the state table of the node (of `flags`) to its children's hits in
    registers L and R. Returns `state` (RETURN, a loop's GoTo, or unchanged), `t_start`
    (where a loop restarts) and the registers L and R."""
    b = tree.b
    t_l, t_r = hit_l.t, hit_r.t
    kind = K.flags_kind(flags)
    classify = state == CLASSIFY
    is_diff = kind == DIFFERENCE
    cls_l = K.info_class(hit_l.info)
    cls_r = K.info_class(hit_r.info)
    # L - R = L & ~R: complement R's class (a miss of R is an exit at infinity)
    cls_r = dr.select(is_diff, complement_class(cls_r), cls_r)
    table_op = dr.select(kind == UNION, 0, 1)
    if tree.has_groups:
        table_op = dr.select(K.flags_group(flags), K.GROUP_ROW, table_op)
    row = dr.select(table_op == 0, K.TABLE_WORDS[0], dr.select(table_op == 1, K.TABLE_WORDS[1], K.TABLE_WORDS[2]))
    action = (row >> (3 * (cls_l * 3 + cls_r))) & 7
    # Ties: a return needs its hit closer by more than the tie window, except
    # RET_CLOSER. Where an enter of one child meets an exit of the other within it
    # (touching or coincident faces, each computed in its own primitive's frame), the
    # solid does not change there, so the tie loops instead of reporting a false boundary.
    l_closer = t_l <= t_r
    # The narrower of the two windows: a coincident pair meets the ray at one slope, and
    # a steep event next to a grazing one is not widened by it.
    window = tie_window(b, ray.tie, dr.minimum(K.info_slope(hit_l.info), K.info_slope(hit_r.info)))
    apart = dr.abs(t_l - t_r) > window        # false for inf vs inf (NaN)
    l_strictly, r_strictly = (t_l < t_r) & apart, (t_r < t_l) & apart
    ret_l = (action == RET_L) | ((action == RET_CLOSER) & l_closer) | ((action == RET_L_ELSE_LOOP_R) & l_strictly)
    ret_r = (action == RET_R) | ((action == RET_CLOSER) & ~l_closer) | ((action == RET_R_ELSE_LOOP_L) & r_strictly)
    loop_l = ((action == RET_R_ELSE_LOOP_L) & ~r_strictly) | ((action == LOOP_CLOSER) & l_closer)
    loop_r = ((action == RET_L_ELSE_LOOP_R) & ~l_strictly) | ((action == LOOP_CLOSER) & ~l_closer)
    # Nothing lies beyond infinity: a loop from t = inf (inside both forever) returns.
    ret_l = classify & (ret_l | (loop_l & (t_l == dr.inf)))
    ret_r = classify & ~ret_l & (ret_r | (loop_r & (t_r == dr.inf)))
    loop_l = classify & loop_l & (t_l != dr.inf)
    loop_r = classify & ~loop_l & loop_r & (t_r != dr.inf)
    # A provisional hit before the node's own bound is not the node's answer: search that
    # child again from its bound (redo), which finds its real next event.
    redo_l = ret_l & K.info_provisional(hit_l.info) & (t_l < t_bound)
    redo_r = ret_r & K.info_provisional(hit_r.info) & (t_r < t_bound)
    ret_l, ret_r = ret_l & ~redo_l, ret_r & ~redo_r
    # A loop whose restart lies at or past the node's bound: the node keeps its state up
    # to the bound (union: inside, the sibling is; otherwise outside), a provisional hit.
    t_loop = dr.maximum(t_l, t_r)
    past = (loop_l | loop_r) & (t_loop >= t_bound) & (t_bound < ray.tmax)
    loop_l, loop_r = (loop_l & ~past) | redo_l, (loop_r & ~past) | redo_r
    ret_miss = classify & ~(ret_l | ret_r | loop_l | loop_r | past)
    # A returned right hit of a difference changes class and flips its normal.
    flip = dr.select(is_diff, FLIP_BIT, 0)
    info_r_out = K.with_class(hit_r.info, cls_r, flip)
    # The returned hit goes into both registers (the parent's frame picks the slot).
    res_t = dr.select(ret_r, t_r, dr.select(ret_l, t_l, dr.select(past, t_bound, dr.inf)))
    res_leaf = dr.select(ret_r, hit_r.leaf, dr.select(ret_l, hit_l.leaf, NO_INDEX))
    past_info = dr.select(kind == UNION, b.UInt32(EXIT), b.UInt32(ENTER)) | K.PROVISIONAL_BIT
    res_info = dr.select(ret_r, info_r_out, dr.select(ret_l, hit_l.info, dr.select(past, past_info, MISS)))
    returning = ret_l | ret_r | ret_miss | past
    # A loop advances the child X whose event comes first; until the sibling Y's event the
    # parent's state is fixed by Y (union: Y inside; intersection: Y outside), so X's events
    # before t_Y cannot matter. Restarting X at t_Y skips them; the class of X's next event
    # after t_Y still says X's state from t_Y on. Without the option X restarts at t_X.
    # A redo restarts at the provisional hit's own bound.
    if tree.options.restart_at_sibling:
        t_start = dr.select(loop_l | loop_r, t_loop, t_start)
    else:
        t_start = dr.select(loop_l, t_l, dr.select(loop_r, t_r, t_start))
    t_start = dr.select(redo_l, t_l, dr.select(redo_r, t_r, t_start))
    returned = b.Hit(res_t, res_leaf, res_info)
    hit_l, hit_r = dr.select(returning, returned, hit_l), dr.select(returning, returned, hit_r)
    state = dr.select(returning, RETURN, dr.select(loop_l, GOTO_L_LOOP, dr.select(loop_r, GOTO_R_LOOP, state)))
    return state, t_start, hit_l, hit_r


@dr.syntax
def traverse(tree: KernelTree, o, d, tmin, tmax, active=True, start_prim=None):
    """Run the automaton. Returns (t, leaf node, info, finished, steps) per lane, all detached;
    steps are automaton steps (iterations, and the further GoTo steps of descents) plus set-walk
    iterations (the work done).

    Lanes where `active` is false do no work and miss (an integrator's finished paths, or
    shadow rays it does not need, would otherwise be traced in full). `start_prim` (per lane,
    or NO_INDEX) is the primitive whose surface the ray starts on, a hint for the set walk
    (`engine.set_walk.next_event`) that changes no hit distance or class.
    """
    b = tree.b
    tree = Untraversed(tree)
    # Every lane's registers must be full width, whichever input is widest: with a width-1
    # origin (a camera's rays share theirs) the loop state would be width 1, and Dr.Jit 1.5's
    # LLVM backend then mixes lanes' per-lane stacks (tests/test_drjit_workarounds.py).
    n = max(dr.width(o.x), dr.width(d.x), dr.width(tmin), dr.width(tmax), dr.width(active),
            1 if start_prim is None else dr.width(start_prim))
    o, d, k = scene_rays(tree, o, d)
    tmin, tmax = tmin * k, tmax * k
    ray = b.SceneRay(o, d, inverse_direction(b, d), _tie_tolerance(tree, o, d), tmax)
    if dr.hint(start_prim is not None, mode="scalar"):
        # The start primitive's leaf, if it is a set member, and the set.
        known = b.UInt32(start_prim) < opaque(tree, b.UInt32, tree.num_prims)
        start_leaf, start_set = dr.gather(b.module.Array2u, tree.prim_start, b.UInt32(start_prim), known)
        start_set = dr.select(known, start_set, NO_INDEX)

    # ---- Loop state (all full width: a width-1 literal stack index misbehaved in Dr.Jit 1.5,
    #      see tests/test_drjit_workarounds.py) ----
    # Model-dependent numbers enter as opaque values, not literals: a literal is compiled into
    # the kernel, and every new model would compile a new one.
    node = opaque(tree, b.UInt32, tree.root) + dr.zeros(b.UInt32, n)   # operation node whose children are in play
    max_iterations = opaque(tree, b.UInt32, tree.max_iterations)
    t_start = b.Float(tmin)                         # re-intersection starts strictly after this
    hit_l, hit_r = no_hit(b, n), no_hit(b, n)       # registers L and R: the children's hits
    state = dr.full(b.UInt32, GOTO_L_FRESH, n)
    t_bound = b.Float(tmax)                         # events of `node` past this do not matter
    swapped = dr.zeros(b.Bool, n)                   # registers L / R hold `node`'s right / left child
    sp = dr.zeros(b.UInt32, n)                      # shared depth of both stacks
    steps = dr.zeros(b.UInt32, n)                  # automaton steps
    walked = dr.zeros(b.UInt32, n)                 # set-walk iterations (engine.set_walk); a walk runs to
                                                   # its end, the iteration bound is tested between steps
    hit_t = dr.alloc_local(b.Float, tree.stack_size)       # hit stack: t (or a saved t_start)
    hit_leaf = dr.alloc_local(b.UInt32, tree.stack_size)   #            leaf node
    hit_info = dr.alloc_local(b.UInt32, tree.stack_size)   #            info word
    frame = dr.alloc_local(b.UInt32, tree.stack_size)      # state stack: SAVE_L / LOAD_L / LOAD_R
    bound = dr.alloc_local(b.Float, tree.stack_size)       #              the parent's t_bound

    # Rays that miss the root box are done before the loop starts.
    state = dr.select(b.Bool(active) & box_meets(tree, ray, node, t_start), state, DONE)

    # `sp < stack_size` never stops a lane (no tree descends deeper than its height), but it
    # puts the stack size into the kernel's IR: Dr.Jit 1.5 leaves the sizes of `alloc_local`
    # arrays out of its kernel hash, and without it a kernel compiled for a shallower tree
    # would run with stacks too small for this one (memory corruption, crashes).
    stack_size = tree.stack_size
    # Loop state is what the automaton changes: the rays and bounds it only reads are left out
    # (Dr.Jit would otherwise record the body twice, once to find them unchanged).
    while dr.hint((state != DONE) & (steps + walked < max_iterations) & (sp < stack_size), mode="symbolic",
                  label="csg_traverse",
                  exclude=[ray, tmin, tmax, max_iterations, start_prim, start_leaf, start_set]):
        steps += 1
        # Register updates use dr.select rather than nested symbolic ifs: they are cheap, and
        # a literal assigned in two sibling branches misbehaved in Dr.Jit 1.5's LLVM backend
        # (tests/test_drjit_workarounds.py).

        # ---- GoTo: one child of `node`, from t_start ----
        # A descent into an operation child is followed, in the same step, by GoTo at that
        # child (each counted as a step), so that a step's Classify and Return are not
        # paid on every level of a descent.
        choice, t_start, swapped = _goto(tree, ray, node, state, t_start, t_bound, swapped, hit_l)
        choosing = choice.descend & (steps + walked < max_iterations) & (sp < stack_size)
        while dr.hint(choosing, label="csg_descend",
                      exclude=[ray, tmin, tmax, max_iterations, walked, t_start, hit_l, hit_r, start_prim, start_leaf,
                               start_set]):
            # Push what to do with the child's hit when it comes back, and where (unless the
            # child takes this node's place).
            push = ~choice.single
            if dr.hint(push, exclude=[t_start, hit_l, hit_r]):
                hit_t.write(dr.select(choice.fresh_left, t_start, dr.select(choice.go_right, hit_l.t, hit_r.t)),
                            sp, push)
                hit_leaf.write(dr.select(choice.go_right, hit_l.leaf, hit_r.leaf), sp, push)
                hit_info.write(dr.select(choice.go_right, hit_l.info, hit_r.info), sp, push)
                frame.write(dr.select(choice.fresh_left, SAVE_L, dr.select(choice.go_right, LOAD_L, LOAD_R))
                            | dr.select(swapped, SWAPPED_FRAME, 0) | (node << FRAME_NODE_SHIFT), sp, push)
                bound.write(t_bound, sp, push)
            sp = dr.select(push, sp + 1, sp)
            node = b.UInt32(choice.child)
            t_bound = dr.select(push, choice.child_bound, t_bound)
            state = dr.select(choosing, GOTO_L_FRESH, state)
            steps += 1
            # At the child, a fresh search: a literal state, so that what only other states
            # need folds away (t_start among them: it stays).
            choice, _, swapped = _goto(tree, ray, node, dr.full(b.UInt32, GOTO_L_FRESH, n), t_start, t_bound,
                                       swapped, hit_l)
            choosing = choice.descend & (steps + walked < max_iterations) & (sp < stack_size)
        # A leaf, or a subtree whose box the ray misses from here on: its hit is known now.
        co_bounded = (choice.child_bits & K.CHILD_NEGATIVE) != 0
        t_c = dr.select(choice.provisional, choice.child_bound, dr.inf)
        info_c = dr.select(co_bounded, b.UInt32(EXIT), b.UInt32(MISS))   # co-bounded: inside forever
        info_c = dr.select(choice.provisional,
                           dr.select(co_bounded, b.UInt32(EXIT), b.UInt32(ENTER)) | K.PROVISIONAL_BIT, info_c)
        found = b.Hit(t_c, b.UInt32(choice.child), info_c)
        searching = choice.in_box & choice.child_is_leaf
        # A lone leaf's next event is its first event after t_start, whatever the bounds
        # (a set of one: no other member can take over), so it skips the set walk's loop.
        lone = searching & ((choice.child_bits & K.CHILD_LEAF) != 0)
        if dr.hint(lone, exclude=[ray]):
            leaf_flags, prim, _, _ = node_record(b, tree, choice.child, lone)
            found, _ = leaf_hit(tree, ray, choice.child, leaf_flags, prim, t_start)
        walking = searching & ~lone
        if dr.hint(walking, exclude=[ray, tmin, tmax, start_prim, start_leaf, start_set]):
            member = None
            if dr.hint(start_prim is not None, mode="scalar"):
                # Only the ray's first search from its own start is inside the start member.
                member = dr.select(walking & (start_set == choice.child) & (t_start == tmin), start_leaf, NO_INDEX)
            found, iterations = next_event(tree, ray, choice.child, t_start, (choice.entry_bound, choice.exit_bound),
                                           walking, member)
            walked += iterations
        # `descend` is still set only where the iteration bound stopped the descent: that
        # lane ends unfinished.
        known = choice.going & ~choice.descend
        hit_r = dr.select(known & choice.go_right, found, hit_r)
        hit_l = dr.select(known & ~choice.go_right, found, hit_l)
        # The sibling of a single known child, and both children of a vacant node, miss.
        hit_r = dr.select((known & choice.single) | choice.vacant, no_hit(b, n), hit_r)
        hit_l = dr.select(choice.vacant, no_hit(b, n), hit_l)
        state = dr.select(choice.descend, GOTO_L_FRESH, dr.select(
            known, dr.select(choice.fresh_left & ~choice.single, GOTO_R_FRESH, CLASSIFY),
            dr.select(choice.vacant, CLASSIFY, state)))

        # ---- Classify: apply the state table of `node` ----
        state, t_start, hit_l, hit_r = _classify(tree, ray, choice.flags, state, t_start, t_bound, hit_l, hit_r)

        # ---- Return: hand the hit (in both registers) to the parent's frame ----
        at_root = (state == RETURN) & (sp == 0)
        popping = (state == RETURN) & (sp > 0)
        sp = dr.select(popping, sp - 1, sp)
        if popping:
            what = frame.read(sp, popping)
            node = dr.select(popping, what >> FRAME_NODE_SHIFT, node)
            swapped = dr.select(popping, (what & SWAPPED_FRAME) != 0, swapped)
            what = what & (SWAPPED_FRAME - 1)
            t_bound = dr.select(popping, bound.read(sp, popping), t_bound)
            saved = b.Hit(hit_t.read(sp, popping), hit_leaf.read(sp, popping), hit_info.read(sp, popping))
            load_l = popping & (what == LOAD_L)      # the hit is the right child's; reload the left
            load_r = popping & (what == LOAD_R)      # the hit is the left child's; reload the right
            save_l = popping & (what == SAVE_L)      # the hit is the left child's; now go right
            t_start = dr.select(save_l, saved.t, t_start)
            hit_l = dr.select(load_l, saved, hit_l)
            hit_r = dr.select(load_r, saved, hit_r)
            state = dr.select(save_l, GOTO_R_FRESH, dr.select(popping, CLASSIFY, state))
        state = dr.select(at_root, DONE, state)

    finished = state == DONE
    # A provisional hit at the root can only sit at tmax: nothing before it.
    hit = finished & (K.info_class(hit_l.info) != MISS) & (hit_l.t <= tmax) & ~K.info_provisional(hit_l.info)
    t = dr.select(hit, hit_l.t / k, dr.inf)
    return t, dr.select(hit, hit_l.leaf, NO_INDEX), hit_l.info, finished, steps + walked
