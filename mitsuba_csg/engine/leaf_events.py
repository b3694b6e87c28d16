"""The next event of a leaf, or of a set: a union of leaves searched as one n-ary node.

The automaton (`engine.automaton`) asks every leaf for its first event after `t_start`. A
subtree made only of unions of positive leaves (the Cheese's holes, a city block's
windows) is a *set* (`layout.SET_BIT` on its root): instead of walking it with the state
tables, which re-descend the looping child for every event, it is searched here as a BVH
over its own node boxes, nearer children first. (A lone leaf is a set of one, whose next
event is its own first event: the automaton intersects it without a walk.) The BVH is
4-wide (`engine.device`: the set's binary subtree collapsed, four child boxes per record):
half the visits of the binary one, each testing four boxes. The union:

* is inside at t+ exactly where some member is: a member whose first event after t is an
  exit *contains* the point. Containing members' boxes hold the point, so culling boxes by
  the ray's interval from t never drops them;
* outside, its next event is the nearest member entry (a closest-hit query: boxes past the
  nearest entry found so far, or past the caller's entry bound, stay closed);
* inside, it reaches at least the farthest exit of the members found inside (the *reach*).
  A member entered before the reach, or within the tie window after it (a touching face,
  as in the state tables), extends it once its exit is known (a second intersection from
  its entry), and boxes are opened up to the reach as it grows. Another pass, from the
  reach, follows where a member this pass could not see may take over there: one in a box
  it left closed, or a second containing member that is not convex (it may re-enter).

The caller says which event it needs (`entry_bound`, `exit_bound`: events past them cannot
change the parent's answer); past the bound the result is provisional, the state up to the
bound, as for a subtree whose box lies past it.
"""
from __future__ import annotations

import drjit as dr

from . import layout as K
from . import shapes
from .device import Untraversed, gather_prim, node_record, set_node
from .layout import ENTER, EXIT, FLIP_BIT, MAX_SLOPE, MISS, NO_LEAF
from .neighbours import GRID_WORDS, NEIGHBOUR_REACH, NO_ENTRY

_NO_NODE = 0xFFFFFFFF


def complement_class(cls):
    """The class of the same event for the complement: enter <-> exit, a miss is an exit at infinity."""
    return dr.select(cls == MISS, EXIT, cls ^ 1)


def tie_window(b, tie, slope):
    """How far in t two events may lie apart and still be one event, for a SLOPE exponent."""
    return tie * b.Float(b.UInt32(2) << slope)


def box_span(b, tree, node, o, inv_d, active):
    """(near, far) of the ray's parameter inside the node's box (NaN for an empty box)."""
    lo4 = dr.gather(b.Array4f, tree.node_box, node * 2, active)
    hi4 = dr.gather(b.Array4f, tree.node_box, node * 2 + 1, active)
    return shapes.box_entry(lo4, hi4, o, inv_d)


def leaf_hit(b, tree, flags, prim, o, d, t_start, tie):
    """(t, info) of a leaf node's first event after t_start, complement applied."""
    rows, shape, param, plane_start, plane_count = gather_prim(b, tree, prim)
    # A mesh's crossings within a tie window after t_start are the event at t_start again.
    mesh = (tree.triangles, tree.mesh_nodes, 2.0 * tie) if tree.has_meshes else None
    t, face, cls, slope = shapes.first_event(b, shape, rows, param, tree.planes, plane_start, plane_count, o, d,
                                             t_start, mesh, tree.shape_kinds)
    complemented = K.flags_negative(flags)
    # A complemented leaf swaps enter/exit; missing it means being inside it forever.
    cls = dr.select(complemented, complement_class(cls), cls)
    non_convex = dr.zeros(b.Bool, dr.width(t))
    for code in K.NON_CONVEX_SHAPES:
        if code in tree.shape_kinds:
            non_convex |= shape == code
    return t, K.hit_info(cls, dr.select(complemented, FLIP_BIT, 0), face, slope), non_convex


def member_hit(b, tree, node, flags, prim, o, d, t_start, tie, active):
    """(t, info, non-convex, leaf node, leaf intersections) of a set member's first event
    after t_start: a leaf's own, or a compound's (`compound_hit`, compiled in only for trees
    that have compounds)."""
    if not tree.has_compounds:
        t, info, non_convex = leaf_hit(b, tree, flags, prim, o, d, t_start, tie)
        return t, info, non_convex, b.UInt32(node), 1
    return compound_hit(b, tree, node, flags, prim, o, d, t_start, tie, active)


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
def compound_hit(b, tree, node, flags, prim, o, d, t_start, tie, active):
    """(t, info, non-convex, leaf node, leaf intersections) of the first event after t_start of a compound set
    member: an intersection of up to MAX_COMPOUND_LITERALS convex leaves and complements of
    convex leaves (a satellite's wing with its cut-outs, `engine.device`).

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
    width = dr.width(t_start)
    plain = b.Bool(active) & (K.flags_kind(flags) == K.LEAF)
    record = dr.gather(b.UInt32, tree.walk_entry, node, active & ~plain)
    words = dr.gather(b.module.ArrayXu, tree.compound_literals, record, active & ~plain,
                      shape=(K.COMPOUND_RECORD_WORDS, width))
    # A plain leaf member is a compound of one literal: itself.
    literals = [dr.select(plain, b.UInt32(node), words[0])] + \
        [dr.select(plain, K.NO_LITERAL, words[i]) for i in range(1, K.MAX_COMPOUND_LITERALS)]
    prims = [dr.select(plain, prim, words[K.MAX_COMPOUND_LITERALS])] + \
        [words[K.MAX_COMPOUND_LITERALS + i] for i in range(1, K.MAX_COMPOUND_LITERALS)]
    count = dr.zeros(b.UInt32, width)
    non_convex = dr.zeros(b.Bool, width)
    for slot in range(K.MAX_COMPOUND_LITERALS):
        present = literals[slot] != K.NO_LITERAL
        count += dr.select(present, 1, 0)
        non_convex |= present & ((literals[slot] & K.LITERAL_COMPLEMENT) != 0)
    cur = b.Float(t_start)
    cand_t, cand_leaf, cand_info = b.Float(t_start), dr.full(b.UInt32, NO_LEAF, width), dr.full(b.UInt32, MISS, width)
    res_t, res_leaf, res_info = dr.full(b.Float, dr.inf, width), dr.full(b.UInt32, NO_LEAF, width), \
        dr.full(b.UInt32, MISS, width)
    # This round's accumulators: all inside so far; the nearest exit; the latest entry (or tied
    # exit) of the literals outside; a literal outside for good.
    all_in = dr.full(b.Bool, True, width)
    exit_t, exit_leaf, exit_info = dr.full(b.Float, dr.inf, width), dr.full(b.UInt32, NO_LEAF, width), \
        dr.full(b.UInt32, MISS, width)
    late_t, late_leaf, late_info = dr.full(b.Float, -dr.inf, width), dr.full(b.UInt32, NO_LEAF, width), \
        dr.full(b.UInt32, MISS, width)
    never = dr.zeros(b.Bool, width)
    k = dr.zeros(b.UInt32, width)
    rounds = dr.zeros(b.UInt32, width)
    evaluated = dr.zeros(b.UInt32, width)
    done = ~b.Bool(active)
    while dr.hint(~done, label="csg_compound", exclude=[o, d, tie, literals, prims, count]):
        literal, prim = _slot(k, literals), _slot(k, prims)
        leaf = literal & ~b.UInt32(K.LITERAL_COMPLEMENT)
        # Literal leaves are positive (engine.device): the literal's own bit is the complement.
        flags = dr.select((literal & K.LITERAL_COMPLEMENT) != 0, b.UInt32(K.NEGATIVE_BIT), 0)
        t_k, info_k, odd_k = leaf_hit(b, tree, flags, prim, o, d, cur, tie)
        evaluated += 1
        cls_k = K.info_class(info_k)
        window = tie_window(b, tie, dr.minimum(K.info_slope(info_k), K.info_slope(cand_info)))
        # (Not the literal that entered at cur: a thin slab's own exit is no tie.)
        tied = (cls_k == EXIT) & (rounds > 0) & (leaf != cand_leaf) & (t_k <= cur + window)
        inside = (cls_k == EXIT) & ~tied
        all_in &= inside
        nearer = inside & (t_k < exit_t)
        exit_t, exit_leaf, exit_info = dr.select(nearer, t_k, exit_t), dr.select(nearer, leaf, exit_leaf), \
            dr.select(nearer, info_k, exit_info)
        never |= ~inside & (cls_k == MISS)
        later = ~inside & (cls_k != MISS) & (t_k > late_t)
        late_t, late_leaf, late_info = dr.select(later, t_k, late_t), dr.select(later, leaf, late_leaf), \
            dr.select(later, info_k, late_info)
        last = k + 1 >= count
        exits = last & all_in & (rounds == 0)
        enters = last & all_in & (rounds > 0)
        misses = never | (last & ~all_in & (rounds + 1 >= _COMPOUND_ROUNDS))
        res_t = dr.select(exits, exit_t, dr.select(enters, cand_t, res_t))
        res_leaf = dr.select(exits, exit_leaf, dr.select(enters, cand_leaf, res_leaf))
        res_info = dr.select(exits, exit_info, dr.select(enters, cand_info, res_info))
        # A plain leaf's event is its own, whatever its class.
        res_t, res_leaf, res_info = dr.select(plain, t_k, res_t), dr.select(plain, leaf, res_leaf), \
            dr.select(plain, info_k, res_info)
        non_convex |= plain & odd_k
        done |= exits | enters | misses | plain
        advance = last & ~done
        cur = dr.select(advance, late_t, cur)
        cand_t, cand_leaf, cand_info = dr.select(advance, late_t, cand_t), dr.select(advance, late_leaf, cand_leaf), \
            dr.select(advance, late_info, cand_info)
        rounds = dr.select(advance, rounds + 1, rounds)
        all_in |= last
        never &= ~last
        exit_t = dr.select(last, dr.inf, exit_t)
        late_t = dr.select(last, -dr.inf, late_t)
        k = dr.select(last, 0, k + 1)
    return res_t, res_info, non_convex, res_leaf, evaluated


def _neighbour_pass(b, tree, member, starting, near_enough, node, local):
    """(node, local): a pass starting inside at `member`'s exit begins at its neighbour tree,
    where it has one and the lane's tie window is within the tree's reach."""
    entry = dr.gather(b.UInt32, tree.neighbour_entry, member, starting)
    go = starting & near_enough & (entry != NO_ENTRY)
    return dr.select(go, entry, node), local | go


def _cell_pass(b, tree, root, o, d, t_c, entry_bound, widest, near_enough, fresh, node, local, culled):
    """(node, local, culled): a pass that asks only the union's state at ray(t_c) (outside, its
    entries needed no further than the widest tie window) begins at the tree of that point's
    grid cell (engine.neighbours.cell_grids), where the set has a grid, the cell is not crowded
    and the lane's window is within the cells' reach. Members not in the cell may be entered
    past the entry bound before an entry the pass finds there, so such an entry is not final:
    the pass counts the bound as culled."""
    width = dr.width(t_c)
    grid = dr.gather(b.UInt32, tree.neighbour_entry, root, fresh)
    p = o + t_c * d
    go = fresh & near_enough & (grid != NO_ENTRY) & (entry_bound <= t_c + widest) & \
        dr.isfinite(p.x) & dr.isfinite(p.y) & dr.isfinite(p.z)
    words = dr.gather(b.module.ArrayXu, tree.set_grids, grid, go, shape=(GRID_WORDS, width))
    inv_edge = dr.reinterpret_array(b.Float, words[3])
    cell = b.UInt32(words[7])
    stride = b.UInt32(1)
    for axis in range(3):
        lower = dr.reinterpret_array(b.Float, words[axis])
        index = dr.clip(dr.floor((p[axis] - lower) * inv_edge), 0.0, b.Float(words[4 + axis] - 1))
        cell += b.UInt32(index) * stride
        stride *= words[4 + axis]
    entry = dr.gather(b.UInt32, tree.neighbour_entry, cell, go)
    go &= entry != NO_ENTRY
    return dr.select(go, entry, node), local | go, dr.select(go, dr.minimum(culled, entry_bound), culled)


@dr.syntax
def next_event(b, tree, root, o, d, inv_d, t_start, entry_bound, exit_bound, tmax, tie, active,
               start_member=None):
    """(t, leaf node, info, iterations) of the next event after t_start of the leaf or set at `root`.

    Outside at t_start, entries past `entry_bound` need not be found; inside, exits past
    `exit_bound` need not be found. Either way the result may then be provisional at the
    bound (where it is < tmax): the state up to it. Lanes where `active` is false do nothing.

    `start_member` (a member leaf of this set per lane, or NO_LEAF) is a member the ray may
    start inside of: a ray leaving a hole's wall into the hole. Where its first event after
    t_start is an exit, the union is inside up to there whatever the other members do, and
    only members that hold that exit can take over: the walk starts as the next pass of a
    walk that ended inside there (one search around the exit instead of one along the whole
    chord). The result is the same, but for which member is reported where several exits
    coincide exactly.
    """
    width = dr.width(t_start)
    tree = Untraversed(tree)
    start_node = dr.gather(b.UInt32, tree.walk_entry, root, active)     # a set's 4-wide root, or the leaf
    node = dr.select(active, start_node, _NO_NODE)
    t_c = b.Float(t_start)                       # this pass's start
    from_t = b.Float(t_start)                    # where the member at `node` is intersected from
    again = dr.zeros(b.Bool, width)              # `node` is a member re-intersected from its tie entry
    stack_node = dr.alloc_local(b.UInt32, tree.walk_stack_size)
    stack_near = dr.alloc_local(b.Float, tree.walk_stack_size)
    # `sp < walk_stack_size` never stops a lane, but puts the size into the kernel's IR (see
    # engine.automaton: Dr.Jit 1.5 leaves alloc_local sizes out of its kernel hash).
    walk_stack_size = tree.walk_stack_size
    sp = dr.zeros(b.UInt32, width)
    en_t, en_leaf, en_info = dr.full(b.Float, dr.inf, width), dr.full(b.UInt32, NO_LEAF, width), \
        dr.full(b.UInt32, MISS, width)           # nearest entry of a member outside at t_c
    ex_t, ex_leaf, ex_info = dr.full(b.Float, -dr.inf, width), dr.full(b.UInt32, NO_LEAF, width), \
        dr.full(b.UInt32, MISS, width)           # farthest exit of the members inside (this pass's reach)
    containing = dr.zeros(b.UInt32, width)
    non_convex_inside = dr.zeros(b.Bool, width)
    culled = dr.full(b.Float, dr.inf, width)     # nearest box not opened that may hold an entry that matters
    inside = dr.zeros(b.Bool, width)             # an earlier pass ended inside, at out_*: the union's exit
    out_t, out_leaf, out_info = b.Float(ex_t), b.UInt32(ex_leaf), b.UInt32(ex_info)   # unless a member takes over
    res_t, res_leaf, res_info = dr.full(b.Float, dr.inf, width), dr.full(b.UInt32, NO_LEAF, width), \
        dr.full(b.UInt32, MISS, width)
    # After an exit, only entries within the widest tie window of it matter (touching faces).
    widest = tie_window(b, tie, MAX_SLOPE)
    done = ~b.Bool(active)
    iterations = dr.zeros(b.UInt32, width)
    # A pass inside at a member's exit may search that member's neighbours only (`local`,
    # engine.neighbours), where the ray's widest tie window is within what their trees cover.
    neighbours = tree.has_neighbours and tree.options.neighbour_passes
    cells = tree.has_grids and tree.options.cell_passes
    local = dr.zeros(b.Bool, width)
    near_enough = widest <= NEIGHBOUR_REACH
    if dr.hint(start_member is not None, mode="scalar"):
        hinted = b.Bool(active) & (start_member != NO_LEAF)
        if hinted:
            flags_h, prim_h, _, _ = node_record(b, tree, start_member, hinted)
            t_h, info_h, _ = leaf_hit(b, tree, flags_h, prim_h, o, d, t_start, tie)
            holds = hinted & (K.info_class(info_h) == EXIT) & dr.isfinite(t_h)
            # Past the exit bound only the state matters: inside up to the bound, as a pass says.
            unsure = holds & (t_h >= exit_bound) & (exit_bound < tmax)
            res_t = dr.select(unsure, exit_bound, res_t)
            res_leaf = dr.select(unsure, b.UInt32(root), res_leaf)
            res_info = dr.select(unsure, b.UInt32(EXIT) | K.PROVISIONAL_BIT, res_info)
            done |= unsure
            held = holds & ~unsure
            inside |= held
            out_t, out_leaf, out_info = dr.select(held, t_h, out_t), dr.select(held, start_member, out_leaf), \
                dr.select(held, info_h, out_info)
            t_c, from_t = dr.select(held, t_h, t_c), dr.select(held, t_h, from_t)
            iterations += dr.select(hinted, 1, 0)
            if dr.hint(neighbours, mode="scalar"):
                node, local = _neighbour_pass(b, tree, start_member, held, near_enough, node, local)
    if dr.hint(cells, mode="scalar"):
        node, local, culled = _cell_pass(b, tree, root, o, d, t_c, entry_bound, widest, near_enough,
                                         b.Bool(active) & ~inside & ~done, node, local, culled)

    # Loop state is what the walk changes: the rays and bounds it only reads are left out
    # (Dr.Jit would otherwise record the body twice, once to find them unchanged).
    while dr.hint(~done & (sp < walk_stack_size), label="csg_set_walk",
                  exclude=[o, d, inv_d, tie, entry_bound, exit_bound, tmax, widest, start_node, root, near_enough]):
        iterations += 1
        has_node = node != _NO_NODE
        wide = has_node & ((node & K.SET_NODE_TAG) != 0)
        is_leaf = has_node & ~wide

        # ---- A member: its first event after from_t ----
        again_now = dr.zeros(b.Bool, width)
        if dr.hint(is_leaf, exclude=[o, d, tie]):
            flags, prim, _, _ = node_record(b, tree, node, is_leaf)
            t_m, info_m, odd_m, leaf_m, evaluated = member_hit(b, tree, node, flags, prim, o, d, from_t, tie, is_leaf)
            iterations += evaluated - 1       # a compound's leaf intersections count as steps
            cls_m = K.info_class(info_m)
            # Once inside, the union's inside reaches at least `reach`: a member entered
            # before it (or within the tie window after it: a touching face) extends it. Its
            # exit comes from a second intersection from its entry; then it counts as containing.
            joined = inside | (containing > 0)
            reach = dr.select(joined, dr.maximum(ex_t, t_c), -dr.inf)
            w_m = tie_window(b, tie, dr.minimum(K.info_slope(info_m), K.info_slope(dr.select(
                containing > 0, ex_info, out_info))))
            again_now = joined & ~again & (cls_m == ENTER) & (t_m <= reach + w_m)
            contains = ~again_now & (cls_m == EXIT)
            farther = contains & (t_m > ex_t)
            ex_t, ex_leaf, ex_info = dr.select(farther, t_m, ex_t), dr.select(farther, leaf_m, ex_leaf), \
                dr.select(farther, info_m, ex_info)
            containing = dr.select(contains, containing + 1, containing)
            non_convex_inside |= contains & odd_m
            nearer = ~again_now & (cls_m == ENTER) & (t_m < en_t)
            en_t, en_leaf, en_info = dr.select(nearer, t_m, en_t), dr.select(nearer, leaf_m, en_leaf), \
                dr.select(nearer, info_m, en_info)
            from_t = dr.select(again_now, t_m, t_c)
        again = again_now
        next_node = dr.select(again_now, node, _NO_NODE)

        # ---- A 4-wide node: open the children whose boxes the ray meets in [t_c, cull] ----
        # Outside: up to the entry bound; inside: up to the reach and its tie window. The
        # nearest opened child is next; the others wait on the stack, nearer ones on top.
        joined = inside | (containing > 0)
        reach_window = dr.maximum(ex_t, t_c) + widest
        limit = dr.select(joined, reach_window, entry_bound)
        cull = dr.minimum(en_t, limit)
        if dr.hint(wide, exclude=[o, inv_d]):
            refs, boxes = set_node(b, tree, node & (K.SET_NODE_TAG - 1), wide)
            keys, opened = [], []
            for ref, (lower, upper) in zip(refs, boxes):
                near, far = shapes.box_entry(lower, upper, o, inv_d)
                reach = (near <= far) & (far >= t_c)
                culled = dr.minimum(culled, dr.select(wide & reach & (near > limit), near, dr.inf))
                hit = reach & (near <= cull)
                keys.append(dr.select(hit, near, dr.inf))
                opened.append(hit)
            refs = list(refs)
            for i, j in ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2)):     # sort by entry distance
                swap = keys[j] < keys[i]
                keys[i], keys[j] = dr.select(swap, keys[j], keys[i]), dr.select(swap, keys[i], keys[j])
                refs[i], refs[j] = dr.select(swap, refs[j], refs[i]), dr.select(swap, refs[i], refs[j])
                opened[i], opened[j] = opened[i] ^ (swap & (opened[i] ^ opened[j])), \
                    opened[j] ^ (swap & (opened[i] ^ opened[j]))
            for i in (3, 2, 1):
                push = wide & opened[i]
                if push:
                    stack_node.write(refs[i], sp, push)
                    stack_near.write(keys[i], sp, push)
                    sp = dr.select(push, sp + 1, sp)
            next_node = dr.select(wide & opened[0], refs[0], next_node)

        # ---- Nothing to do next: pop the nearest waiting box, unless it lies past cull ----
        pop = ~done & (next_node == _NO_NODE) & (sp > 0)
        top = dr.select(pop, sp - 1, 0)
        popped, popped_near = stack_node.read(top, pop), stack_near.read(top, pop)
        sp = dr.select(pop, sp - 1, sp)
        culled = dr.minimum(culled, dr.select(pop & (popped_near > limit), popped_near, dr.inf))
        next_node = dr.select(pop & (popped_near <= cull), popped, next_node)
        node = next_node

        # ---- End of a pass ----
        ended = ~done & (node == _NO_NODE) & (sp == 0)
        if dr.hint(ended, exclude=[tie, widest, entry_bound, exit_bound, tmax, root, start_node, near_enough]):
            found_inside = containing > 0
            window = tie_window(b, tie, dr.minimum(K.info_slope(ex_info), K.info_slope(en_info)))
            # Another member may take over at the farthest exit: one entered before it (or may
            # have been, in a box not opened), or a second containing one that may re-enter.
            take_over = (en_t <= ex_t + window) | ((containing > 1) & non_convex_inside) | (culled <= ex_t + widest)
            if dr.hint(neighbours or cells, mode="scalar"):
                take_over |= local        # a pass over neighbours (or a cell's members) saw only those
            # Past the exit bound the state is all that matters: inside up to the bound.
            unsure = found_inside & take_over & (ex_t >= exit_bound) & (exit_bound < tmax)
            chain = found_inside & ~unsure & dr.isfinite(ex_t) & take_over
            exit_now = found_inside & ~unsure & ~chain
            exit_before = ~found_inside & inside
            entry = ~found_inside & ~inside & dr.isfinite(en_t) & ((en_t <= entry_bound) | (en_t <= culled))
            outside_to_bound = ~found_inside & ~inside & ~entry & (culled < dr.inf) & (entry_bound < tmax)
            t_res = dr.select(unsure, exit_bound, dr.select(outside_to_bound, entry_bound, dr.select(
                exit_now, ex_t, dr.select(exit_before, out_t, dr.select(entry, en_t, dr.inf)))))
            leaf_res = dr.select(exit_now, ex_leaf, dr.select(exit_before, out_leaf,
                                                              dr.select(entry, en_leaf, b.UInt32(root))))
            info_res = dr.select(exit_now, ex_info, dr.select(exit_before, out_info, dr.select(entry, en_info, MISS)))
            info_res = dr.select(unsure, b.UInt32(EXIT) | K.PROVISIONAL_BIT,
                                 dr.select(outside_to_bound, b.UInt32(ENTER) | K.PROVISIONAL_BIT, info_res))
            finish = ended & ~chain
            res_t, res_leaf, res_info = dr.select(finish, t_res, res_t), dr.select(finish, leaf_res, res_leaf), \
                dr.select(finish, info_res, res_info)
            done |= finish
            # A new pass from the farthest exit.
            restart = ended & chain
            inside |= restart
            out_t, out_leaf, out_info = dr.select(restart, ex_t, out_t), dr.select(restart, ex_leaf, out_leaf), \
                dr.select(restart, ex_info, out_info)
            t_c = dr.select(restart, ex_t, t_c)
            from_t = dr.select(restart, ex_t, from_t)
            node = dr.select(restart, start_node, node)
            if dr.hint(neighbours or cells, mode="scalar"):
                local &= ~restart
            if dr.hint(neighbours, mode="scalar"):
                node, local = _neighbour_pass(b, tree, ex_leaf, restart, near_enough, node, local)
            en_t, en_leaf, en_info = dr.select(restart, dr.inf, en_t), dr.select(restart, NO_LEAF, en_leaf), \
                dr.select(restart, MISS, en_info)
            ex_t, ex_leaf, ex_info = dr.select(restart, -dr.inf, ex_t), dr.select(restart, NO_LEAF, ex_leaf), \
                dr.select(restart, MISS, ex_info)
            containing = dr.select(restart, 0, containing)
            non_convex_inside &= ~restart
            culled = dr.select(restart, dr.inf, culled)
    return res_t, res_leaf, res_info, iterations
