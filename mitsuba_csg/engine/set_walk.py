"""The next event of a set: a union of leaves (or compound members) searched as one n-ary node.

The automaton (`engine.automaton`) asks every leaf for its first event after `t_start`
(`engine.leaf_events`). A subtree made only of unions of positive leaves (the Cheese's
holes, a city block's windows) is a *set* (`layout.SET_BIT` on its root): instead of walking it with the state
tables, which re-descend the looping child for every event, it is searched here as a BVH
over its own node boxes, nearer children first. (A lone leaf is a set of one, whose next
event is its own first event: the automaton intersects it without a walk.) The BVH is
4-wide (`engine.set_layout`: the set's binary subtree collapsed, four child boxes per record):
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
from .device import Untraversed, node_record, set_node
from .layout import ENTER, EXIT, MAX_SLOPE, MISS, NO_INDEX
from .leaf_events import leaf_hit, member_hit, no_hit, tie_window
from .neighbours import GRID_WORDS, NEIGHBOUR_REACH


def _neighbour_pass(tree, member, starting, near_enough):
    """(go, entry): a pass starting inside at `member`'s exit begins at its neighbour tree
    (`entry`) where `go`: it has one and the lane's tie window is within the tree's reach."""
    entry = dr.gather(tree.b.UInt32, tree.neighbour_entry, member, starting)
    return starting & near_enough & (entry != NO_INDEX), entry


def _cell_pass(tree, ray, root, t_c, entry_bound, fresh):
    """(go, entry): a pass that asks only the union's state at ray(t_c) (outside, its entries
    needed no further than the widest tie window) begins at the tree of that point's grid cell
    (engine.neighbours.cell_grids, `entry`) where `go`: the set has a grid, the cell is not
    crowded and the lane's window is within the cells' reach. Members not in the cell may be
    entered past the entry bound before an entry the pass finds there, so such an entry is not
    final: the pass counts the bound as culled."""
    b = tree.b
    width = dr.width(t_c)
    widest = tie_window(b, ray.tie, MAX_SLOPE)
    grid = dr.gather(b.UInt32, tree.set_grid, root, fresh)
    p = ray.o + t_c * ray.d
    go = fresh & (widest <= NEIGHBOUR_REACH) & (grid != NO_INDEX) & (entry_bound <= t_c + widest) & \
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
    entry = dr.gather(b.UInt32, tree.cell_entry, cell, go)
    return go & (entry != NO_INDEX), entry


@dr.syntax
def next_event(tree, ray, root, t_start, bounds, active, start_member=None):
    """(Hit, iterations) of the next event after t_start of the leaf or set at `root`.

    `bounds` = (entry_bound, exit_bound): outside at t_start, entries past `entry_bound` need
    not be found; inside, exits past `exit_bound` need not be found. Either way the result may
    then be provisional at the bound (where it is < ray.tmax): the state up to it. Lanes where
    `active` is false do nothing.

    `start_member` (a member leaf of this set per lane, or NO_INDEX) is a member the ray may
    start inside of: a ray leaving a hole's wall into the hole. Where its first event after
    t_start is an exit, the union is inside up to there whatever the other members do, and
    only members that hold that exit can take over: the walk starts as the next pass of a
    walk that ended inside there (one search around the exit instead of one along the whole
    chord). The result is the same, but for which member is reported where several exits
    coincide exactly.
    """
    b = tree.b
    entry_bound, exit_bound = bounds
    width = dr.width(t_start)
    tree = Untraversed(tree)
    start_node = dr.gather(b.UInt32, tree.walk_entry, root, active)     # a set's 4-wide root, or the leaf
    node = dr.select(active, start_node, NO_INDEX)
    t_c = b.Float(t_start)                       # this pass's start
    from_t = b.Float(t_start)                    # where the member at `node` is intersected from
    again = dr.zeros(b.Bool, width)              # `node` is a member re-intersected from its tie entry
    stack_node = dr.alloc_local(b.UInt32, tree.walk_stack_size)
    stack_near = dr.alloc_local(b.Float, tree.walk_stack_size)
    # `sp < walk_stack_size` never stops a lane, but puts the size into the kernel's IR (see
    # engine.automaton: Dr.Jit 1.5 leaves alloc_local sizes out of its kernel hash).
    walk_stack_size = tree.walk_stack_size
    sp = dr.zeros(b.UInt32, width)
    entry = no_hit(b, width)                     # nearest entry of a member outside at t_c
    reach = no_hit(b, width, -dr.inf)            # farthest exit of the members inside (this pass's reach)
    containing = dr.zeros(b.UInt32, width)
    non_convex_inside = dr.zeros(b.Bool, width)
    culled = dr.full(b.Float, dr.inf, width)     # nearest box not opened that may hold an entry that matters
    inside = dr.zeros(b.Bool, width)             # an earlier pass ended inside, at `out`: the union's exit
    out = b.Hit(b.Float(reach.t), b.UInt32(reach.leaf), b.UInt32(reach.info))   # unless a member takes over
    res = no_hit(b, width)
    # After an exit, only entries within the widest tie window of it matter (touching faces).
    widest = tie_window(b, ray.tie, MAX_SLOPE)
    done = ~b.Bool(active)
    iterations = dr.zeros(b.UInt32, width)
    # A pass inside at a member's exit may search that member's neighbours only (`local`,
    # engine.neighbours), where the ray's widest tie window is within what their trees cover.
    neighbours = tree.has_neighbours and tree.options.neighbour_passes
    cells = tree.has_grids and tree.options.cell_passes
    local = dr.zeros(b.Bool, width)
    near_enough = widest <= NEIGHBOUR_REACH
    if dr.hint(start_member is not None, mode="scalar"):
        hinted = b.Bool(active) & (start_member != NO_INDEX)
        if hinted:
            flags_h, prim_h, _, _ = node_record(b, tree, start_member, hinted)
            hit_h, _ = leaf_hit(tree, ray, start_member, flags_h, prim_h, t_start)
            holds = hinted & (K.info_class(hit_h.info) == EXIT) & dr.isfinite(hit_h.t)
            # Past the exit bound only the state matters: inside up to the bound, as a pass says.
            unsure = holds & (hit_h.t >= exit_bound) & (exit_bound < ray.tmax)
            res = dr.select(unsure, b.Hit(exit_bound, b.UInt32(root), b.UInt32(EXIT) | K.PROVISIONAL_BIT), res)
            done |= unsure
            held = holds & ~unsure
            inside |= held
            out = dr.select(held, hit_h, out)
            t_c, from_t = dr.select(held, hit_h.t, t_c), dr.select(held, hit_h.t, from_t)
            iterations += dr.select(hinted, 1, 0)
            if dr.hint(neighbours, mode="scalar"):
                go, tree_entry = _neighbour_pass(tree, start_member, held, near_enough)
                node, local = dr.select(go, tree_entry, node), local | go
    if dr.hint(cells, mode="scalar"):
        go, cell_entry = _cell_pass(tree, ray, root, t_c, entry_bound, b.Bool(active) & ~inside & ~done)
        node, local = dr.select(go, cell_entry, node), local | go
        culled = dr.select(go, dr.minimum(culled, entry_bound), culled)

    # Loop state is what the walk changes: the rays and bounds it only reads are left out
    # (Dr.Jit would otherwise record the body twice, once to find them unchanged).
    while dr.hint(~done & (sp < walk_stack_size), label="csg_set_walk",
                  exclude=[ray, entry_bound, exit_bound, widest, start_node, root, near_enough]):
        iterations += 1
        has_node = node != NO_INDEX
        wide = has_node & ((node & K.SET_NODE_TAG) != 0)
        is_leaf = has_node & ~wide

        # ---- A member: its first event after from_t ----
        again_now = dr.zeros(b.Bool, width)
        if dr.hint(is_leaf, exclude=[ray]):
            flags, prim, _, _ = node_record(b, tree, node, is_leaf)
            hit_m, odd_m, evaluated = member_hit(tree, ray, node, flags, prim, from_t, is_leaf)
            iterations += evaluated - 1       # a compound's leaf intersections count as steps
            cls_m = K.info_class(hit_m.info)
            # Once inside, the union's inside reaches at least `reach`: a member entered
            # before it (or within the tie window after it: a touching face) extends it. Its
            # exit comes from a second intersection from its entry; then it counts as containing.
            joined = inside | (containing > 0)
            reach_t = dr.select(joined, dr.maximum(reach.t, t_c), -dr.inf)
            w_m = tie_window(b, ray.tie, dr.minimum(K.info_slope(hit_m.info), K.info_slope(dr.select(
                containing > 0, reach.info, out.info))))
            again_now = joined & ~again & (cls_m == ENTER) & (hit_m.t <= reach_t + w_m)
            contains = ~again_now & (cls_m == EXIT)
            reach = dr.select(contains & (hit_m.t > reach.t), hit_m, reach)
            containing = dr.select(contains, containing + 1, containing)
            non_convex_inside |= contains & odd_m
            entry = dr.select(~again_now & (cls_m == ENTER) & (hit_m.t < entry.t), hit_m, entry)
            from_t = dr.select(again_now, hit_m.t, t_c)
        again = again_now
        next_node = dr.select(again_now, node, NO_INDEX)

        # ---- A 4-wide node: open the children whose boxes the ray meets in [t_c, cull] ----
        # Outside: up to the entry bound; inside: up to the reach and its tie window. The
        # nearest opened child is next; the others wait on the stack, nearer ones on top.
        joined = inside | (containing > 0)
        reach_window = dr.maximum(reach.t, t_c) + widest
        limit = dr.select(joined, reach_window, entry_bound)
        cull = dr.minimum(entry.t, limit)
        if dr.hint(wide, exclude=[ray]):
            refs, boxes = set_node(b, tree, node & (K.SET_NODE_TAG - 1), wide)
            keys, opened = [], []
            for ref, (lower, upper) in zip(refs, boxes):
                near, far = shapes.box_entry(lower, upper, ray.o, ray.inv_d)
                meets = (near <= far) & (far >= t_c)
                culled = dr.minimum(culled, dr.select(wide & meets & (near > limit), near, dr.inf))
                hit = meets & (near <= cull)
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
        pop = ~done & (next_node == NO_INDEX) & (sp > 0)
        top = dr.select(pop, sp - 1, 0)
        popped, popped_near = stack_node.read(top, pop), stack_near.read(top, pop)
        sp = dr.select(pop, sp - 1, sp)
        culled = dr.minimum(culled, dr.select(pop & (popped_near > limit), popped_near, dr.inf))
        next_node = dr.select(pop & (popped_near <= cull), popped, next_node)
        node = next_node

        # ---- End of a pass ----
        ended = ~done & (node == NO_INDEX) & (sp == 0)
        if dr.hint(ended, exclude=[ray, widest, entry_bound, exit_bound, root, start_node, near_enough]):
            found_inside = containing > 0
            window = tie_window(b, ray.tie, dr.minimum(K.info_slope(reach.info), K.info_slope(entry.info)))
            # Another member may take over at the farthest exit: one entered before it (or may
            # have been, in a box not opened), or a second containing one that may re-enter.
            take_over = (entry.t <= reach.t + window) | ((containing > 1) & non_convex_inside) | \
                (culled <= reach.t + widest)
            if dr.hint(neighbours or cells, mode="scalar"):
                take_over |= local        # a pass over neighbours (or a cell's members) saw only those
            # Past the exit bound the state is all that matters: inside up to the bound.
            unsure = found_inside & take_over & (reach.t >= exit_bound) & (exit_bound < ray.tmax)
            chain = found_inside & ~unsure & dr.isfinite(reach.t) & take_over
            exit_now = found_inside & ~unsure & ~chain
            exit_before = ~found_inside & inside
            entered = ~found_inside & ~inside & dr.isfinite(entry.t) & ((entry.t <= entry_bound) | (entry.t <= culled))
            outside_to_bound = ~found_inside & ~inside & ~entered & (culled < dr.inf) & (entry_bound < ray.tmax)
            t_res = dr.select(unsure, exit_bound, dr.select(outside_to_bound, entry_bound, dr.select(
                exit_now, reach.t, dr.select(exit_before, out.t, dr.select(entered, entry.t, dr.inf)))))
            leaf_res = dr.select(exit_now, reach.leaf, dr.select(exit_before, out.leaf,
                                                                 dr.select(entered, entry.leaf, b.UInt32(root))))
            info_res = dr.select(exit_now, reach.info, dr.select(exit_before, out.info,
                                                                 dr.select(entered, entry.info, MISS)))
            info_res = dr.select(unsure, b.UInt32(EXIT) | K.PROVISIONAL_BIT,
                                 dr.select(outside_to_bound, b.UInt32(ENTER) | K.PROVISIONAL_BIT, info_res))
            finish = ended & ~chain
            res = dr.select(finish, b.Hit(t_res, leaf_res, info_res), res)
            done |= finish
            # A new pass from the farthest exit.
            restart = ended & chain
            inside |= restart
            out = dr.select(restart, reach, out)
            t_c = dr.select(restart, reach.t, t_c)
            from_t = dr.select(restart, reach.t, from_t)
            node = dr.select(restart, start_node, node)
            if dr.hint(neighbours or cells, mode="scalar"):
                local &= ~restart
            if dr.hint(neighbours, mode="scalar"):
                onto_tree, onto_entry = _neighbour_pass(tree, reach.leaf, restart, near_enough)
                node, local = dr.select(onto_tree, onto_entry, node), local | onto_tree
            entry = dr.select(restart, no_hit(b, width), entry)
            reach = dr.select(restart, no_hit(b, width, -dr.inf), reach)
            containing = dr.select(restart, 0, containing)
            non_convex_inside &= ~restart
            culled = dr.select(restart, dr.inf, culled)
    return res, iterations
