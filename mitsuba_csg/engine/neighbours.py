"""Neighbour trees: where a set walk goes on from inside, at the exit of a member.

A set walk (`engine.set_walk.next_event`) is inside its union at a member M's exit in two
cases: a ray that starts on M's surface and leaves into M (a bounce off a hole's wall into
the hole, a hint from the integrators), and the next pass of a chain through overlapping
members (a ray crossing a Cheese's connected holes). What the pass asks there is which
members hold that point, or are entered within the tie window after it. Each of them comes
within the window of M's surface, so the pass needs only M's neighbours: a small 4-wide tree
over them, instead of a descent of the set's whole BVH from its root, which opens every box
that holds the point on the way down.

Members entered later in the pass, before the farthest exit found (the pass's reach), may
not be M's neighbours; a pass from a neighbour tree therefore hands on to a new pass from
that farthest exit whenever it ends inside, from that member's own neighbours.

The window depends on the ray (docs/accuracy.md: it grows with the origin's distance from
the scene), so the trees are built for windows up to `NEIGHBOUR_REACH`, and a lane with a
wider one walks from the set's root as before. Neighbours are members whose boxes meet M's
box widened by the reach and, where M or they are spheres, whose bounding balls come that
close to M's ball or box (on a Cheese of 1000 holes, about half the neighbours the boxes
alone give).

A pass that asks only the union's state at a point (the first pass of a walk from outside,
searched from its sibling's event: the Cheese's holes at the ray's entry into the block) has
the same need with no member to start from: which members hold the point, or are entered
within the tie window after it. Such a set also has a uniform grid of cells (`cell_grids`),
each with a 4-wide tree over the members that come within the reach of the cell, and the pass
walks the tree of the point's cell instead of descending from the set's root.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from . import layout as K

# How far past a member (scene frame: the root box's largest half-side is 1) its neighbours
# may lie: the widest tie window of a ray whose origin lies within ~7 of the scene's centre
# (TIE_TOLERANCE x 2^(MAX_SLOPE + 1) x (extent + |o|), engine.automaton).
NEIGHBOUR_REACH = 1.0 / 64.0
# A member with more neighbours than this walks from its set's root: its tree would cost
# about as many visits, and a tree stays within 21 records.
MAX_NEIGHBOURS = 64

# A set's cells are about this fraction of its members' median box size across: smaller
# cells hold fewer members each, and cost more memory.
CELL_PER_MEMBER = 0.5
MAX_CELLS = 1 << 18       # cells of one set's grid ...
CELLS_PER_MEMBER = 8      # ... and per member (a set of small members spread far: a city's windows)
GRID_WORDS = 8            # per grid: lower corner xyz and 1 / cell edge (float bits), cells per axis xyz,
                          # the index of its first cell's entry


def neighbour_trees(owner, box, balls, convex, first_record):
    """(records, entry): 4-wide set-node records (layout.SET_NODE_FLOATS each, numbered from
    `first_record`) holding each set member's neighbour tree, and per node where a pass from
    inside at that member's exit starts: SET_NODE_TAG | a record, a lone neighbour's node
    id, or NO_INDEX.

    `owner` gives per node the set it is a member of (a leaf or a compound; -1 for none),
    `box` holds the nodes' padded
    boxes (lower xyz, 0, upper xyz, 0; NaN if empty), `balls` per node a ball (centre,
    radius) that holds a sphere leaf (NaN radius for other nodes), `convex` the members whose
    inside along a ray is one interval: a convex member is not its own neighbour, since a
    ray that leaves it does not enter it again."""
    entry = np.full(len(owner), K.NO_INDEX, np.uint32)
    lower, upper = box[:, 0:3], box[:, 4:7]
    pairs = [_neighbour_pairs(members, lower, upper, balls) for members in _members_by_set(owner)]
    of = np.concatenate([p[0] for p in pairs]) if pairs else np.zeros(0, np.int64)    # each pair's member
    near = np.concatenate([p[1] for p in pairs]) if pairs else np.zeros(0, np.int64)
    keep = ~((of == near) & convex[of])
    of, near = of[keep], near[keep]
    with_list = np.unique(of)
    alone = np.setdiff1d(np.flatnonzero(owner >= 0), np.concatenate([with_list, _crowded(pairs)]))
    # Record 0 has no children: the entry of a member with no neighbours (a pass that opens nothing).
    entry[alone] = K.SET_NODE_TAG | first_record
    records, roots = _trees(of, near, lower, upper, first_record + 1)
    entry[with_list] = roots
    return np.concatenate([_empty_record(), records]), entry


def _empty_record():
    """A 4-wide record with no children: a pass that starts there opens nothing."""
    empty = np.full((1, K.SET_NODE_FLOATS), np.nan, np.float32)
    empty[0, :4] = np.full(4, K.NO_INDEX, np.uint32).view(np.float32)
    return empty


def _members_by_set(owner):
    """Each set's member node ids (sets of fewer than two members are skipped)."""
    ids = np.flatnonzero(owner >= 0)
    ids = ids[np.argsort(owner[ids], kind="stable")]
    for group in np.split(ids, np.flatnonzero(np.diff(owner[ids])) + 1):
        if len(group) > 1:
            yield group


def _neighbour_pairs(members, lower, upper, balls):
    """(member, neighbour, crowded): node-id pairs, each member with itself too, of the
    members with at most MAX_NEIGHBOURS neighbours; `crowded` lists the members with more.
    Candidates come from a k-d tree over the boxes' centres (bounded by the boxes'
    half-diagonals and the balls' radii), then the boxes and balls are tested."""
    none = np.zeros(0, np.int64)
    lo, hi = lower[members], upper[members]
    usable = np.flatnonzero(np.all(np.isfinite(lo) & np.isfinite(hi), axis=1))
    if len(usable) < 2:
        return none, none, members
    lo, hi, ball = lo[usable], hi[usable], balls[members[usable]]
    centre = 0.5 * (lo + hi)
    half = 0.5 * np.linalg.norm(hi - lo, axis=1)
    has_ball = np.isfinite(ball[:, 3])
    own = np.where(has_ball, ball[:, 3], half)
    radius = np.where(has_ball, own + own.max() + NEIGHBOUR_REACH,
                      half + half.max() + NEIGHBOUR_REACH * np.sqrt(3.0))
    index = cKDTree(centre)
    # Many candidates (a member among boxes of another size, or in a dense crowd): no tree.
    few = index.query_ball_point(centre, radius, return_length=True) <= 4 * MAX_NEIGHBOURS
    found = index.query_ball_point(centre[few], radius[few])
    i = np.repeat(np.flatnonzero(few), [len(f) for f in found])
    j = np.concatenate([np.asarray(f, np.int64) for f in found]) if len(found) else none
    meets = np.all((lo[j] <= hi[i] + NEIGHBOUR_REACH) & (lo[i] - NEIGHBOUR_REACH <= hi[j]), axis=1)
    # A ball: the neighbour's ball, or else its box, within the reach of it.
    gap = np.linalg.norm(np.clip(ball[i, :3], lo[j], hi[j]) - ball[i, :3], axis=1)
    with np.errstate(invalid="ignore"):
        gap = np.where(has_ball[j], np.maximum(gap, np.linalg.norm(ball[j, :3] - ball[i, :3], axis=1) - ball[j, 3]),
                       gap)
        meets &= ~has_ball[i] | (gap <= ball[i, 3] + NEIGHBOUR_REACH)
    # ... and the member's own box within the reach of the neighbour's ball.
    gap = np.linalg.norm(np.clip(ball[j, :3], lo[i], hi[i]) - ball[j, :3], axis=1)
    with np.errstate(invalid="ignore"):
        meets &= ~has_ball[j] | (gap <= ball[j, 3] + NEIGHBOUR_REACH)
    i, j = i[meets], j[meets]
    count = np.bincount(i, minlength=len(usable))
    listed = np.zeros(len(members), bool)
    listed[usable] = few & (count <= MAX_NEIGHBOURS)
    keep = listed[usable[i]]
    return members[usable[i[keep]]], members[usable[j[keep]]], members[~listed]


def _crowded(pairs):
    return np.concatenate([p[2] for p in pairs]) if pairs else np.zeros(0, np.int64)


def _trees(owner, near, lower, upper, first_record):
    """(records, root per distinct owner, in sorted order): for each owner a 4-wide tree over
    its neighbours, built bottom up for all owners at once. Each list is ordered along the
    widest axis of its members' centres and cut into groups of four consecutive items,
    level after level, until one item is left: the root (a lone neighbour is its own root)."""
    if len(owner) == 0:
        return np.zeros((0, K.SET_NODE_FLOATS), np.float32), np.zeros(0, np.uint32)
    order = np.lexsort((near, owner))
    owner, near = owner[order], near[order]
    owners, start, sizes = np.unique(owner, return_index=True, return_counts=True)
    centres = 0.5 * (lower[near] + upper[near])
    span = np.maximum.reduceat(centres, start, axis=0) - np.minimum.reduceat(centres, start, axis=0)
    key = centres[np.arange(len(owner)), np.repeat(np.argmax(span, axis=1), sizes)]
    order = np.lexsort((key, owner))                # by owner, then along its widest axis
    group = np.repeat(np.arange(len(owners)), sizes)              # the list of each item
    refs = near[order].astype(np.uint32)
    lo, hi = lower[near[order]], upper[near[order]]
    records, count = [], 0
    while True:
        sizes = np.bincount(group, minlength=len(owners))
        if np.all(sizes <= 1):
            break
        firsts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        pos = np.arange(len(group)) - firsts[group]
        done = sizes[group] == 1                    # a list already down to its root stays as it is
        chunk = pos // 4
        # One record per (list, chunk) of the lists still being reduced.
        key = np.where(done, -1, group * (len(group) + 1) + chunk)
        parents, index = np.unique(key[~done], return_inverse=True)
        level = np.full((len(parents), K.SET_NODE_FLOATS), np.nan, np.float32)
        words = np.full((len(parents), 4), K.NO_INDEX, np.uint32)
        words[index, pos[~done] % 4] = refs[~done]
        level[:, :4] = words.view(np.float32)
        slots = (pos[~done] % 4)[:, None] * 6 + np.arange(4, 10)[None, :]
        level[index[:, None], slots] = np.concatenate([lo[~done], hi[~done]], axis=1)
        records.append(level)
        # The next level: each list's records, then the lists already done.
        firsts_of = np.flatnonzero(np.diff(np.concatenate([[-2], key[~done]])) != 0)
        p_group = group[~done][firsts_of]
        p_ref = K.SET_NODE_TAG | (first_record + count + np.arange(len(parents))).astype(np.uint32)
        p_lo = np.minimum.reduceat(lo[~done], firsts_of, axis=0)
        p_hi = np.maximum.reduceat(hi[~done], firsts_of, axis=0)
        count += len(parents)
        group = np.concatenate([group[done], p_group])
        refs = np.concatenate([refs[done], p_ref])
        lo, hi = np.concatenate([lo[done], p_lo]), np.concatenate([hi[done], p_hi])
        again = np.argsort(group, kind="stable")
        group, refs, lo, hi = group[again], refs[again], lo[again], hi[again]
    roots = np.full(len(owners), K.NO_INDEX, np.uint32)
    roots[group] = refs
    stacked = np.concatenate(records) if records else np.zeros((0, K.SET_NODE_FLOATS), np.float32)
    return stacked, roots


def cell_grids(owner, box, balls, first_record, min_members=2):
    """(records, grids, cells, grid_roots): for each set of `owner` (as in `neighbour_trees`),
    a uniform grid over its members' boxes widened by NEIGHBOUR_REACH, each cell with a 4-wide
    tree over the members whose boxes (and, for spheres, balls) come within the reach of the
    cell. `records`: the trees (numbered from `first_record`; the first has no children, the
    entry of an empty cell); `grids`: GRID_WORDS uint32 words per grid; `cells`: the entry of
    each cell (a record, a lone member's node id, or NO_INDEX where
    more than MAX_NEIGHBOURS members crowd the cell: its point walks from the set's root);
    `grid_roots`: the set root of each grid."""
    lower, upper = box[:, 0:3], box[:, 4:7]
    grids, roots, cell_of, member_of, crowded, count = [], [], [], [], [], 0
    sets, size = np.unique(owner[owner >= 0], return_counts=True)
    owner = np.where(np.isin(owner, sets[size >= min_members]), owner, -1)    # the small sets skipped at once
    for members in _members_by_set(owner):
        lo, hi = lower[members], upper[members]
        usable = np.all(np.isfinite(lo) & np.isfinite(hi), axis=1)
        members, lo, hi = members[usable], lo[usable], hi[usable]
        if len(members) < max(min_members, 2):
            continue
        g_lo = lo.min(axis=0) - NEIGHBOUR_REACH
        span = hi.max(axis=0) + NEIGHBOUR_REACH - g_lo
        edge = max(CELL_PER_MEMBER * float(np.median((hi - lo).max(axis=1))), float(span.max()) / 1024.0, 1e-6)
        while True:
            res = np.maximum(np.ceil(span / edge), 1).astype(np.int64)
            if res.prod() <= min(MAX_CELLS, CELLS_PER_MEMBER * len(members)):
                break
            edge *= 1.25
        first = np.clip(np.floor((lo - NEIGHBOUR_REACH - g_lo) / edge), 0, res - 1).astype(np.int64)
        last = np.clip(np.floor((hi + NEIGHBOUR_REACH - g_lo) / edge), 0, res - 1).astype(np.int64)
        sizes = last - first + 1
        per = sizes.prod(axis=1)
        i = np.repeat(np.arange(len(members)), per)
        k = np.arange(len(i)) - np.repeat(np.cumsum(per) - per, per)
        cx = first[i, 0] + k % sizes[i, 0]
        cy = first[i, 1] + (k // sizes[i, 0]) % sizes[i, 1]
        cz = first[i, 2] + k // (sizes[i, 0] * sizes[i, 1])
        cell = np.stack([cx, cy, cz], axis=1)
        # A sphere: its ball within the reach of the cell.
        ball = balls[members[i]]
        c_lo = g_lo + cell * edge
        gap = np.linalg.norm(np.clip(ball[:, :3], c_lo, c_lo + edge) - ball[:, :3], axis=1)
        with np.errstate(invalid="ignore"):
            keep = ~np.isfinite(ball[:, 3]) | (gap <= ball[:, 3] + NEIGHBOUR_REACH)
        flat = count + cx + res[0] * (cy + res[1] * cz)
        flat, near = flat[keep], members[i[keep]]
        full = np.bincount(flat - count, minlength=int(res.prod())) > MAX_NEIGHBOURS
        crowded.append(count + np.flatnonzero(full))
        listed = ~full[flat - count]
        cell_of.append(flat[listed])
        member_of.append(near[listed])
        words = np.zeros(GRID_WORDS, np.uint32)
        words[0:4] = np.array([*g_lo, 1.0 / edge], np.float32).view(np.uint32)
        words[4:7] = res
        words[7] = count
        grids.append(words)
        roots.append(owner[members[0]])
        count += int(res.prod())
    if not grids:
        return np.zeros((0, K.SET_NODE_FLOATS), np.float32), np.zeros((0, GRID_WORDS), np.uint32), \
            np.zeros(0, np.uint32), np.zeros(0, np.int64)
    cells = np.full(count, K.SET_NODE_TAG | first_record, np.uint32)     # empty cells: the empty record
    cells[np.concatenate(crowded)] = K.NO_INDEX
    of, near = np.concatenate(cell_of), np.concatenate(member_of)
    records, tree_roots = _trees(of, near, lower, upper, first_record + 1)
    cells[np.unique(of)] = tree_roots
    return np.concatenate([_empty_record(), records]), np.stack(grids), cells, np.asarray(roots, np.int64)
