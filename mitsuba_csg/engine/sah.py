"""Batched binned SAH: balanced, spatially coherent binary trees over many item sets at once.

All sets (the treelets of a CSG tree) are split level by level in one vectorized pass, so
a million small treelets cost no more Python calls than one big treelet.
"""
from __future__ import annotations

import numpy as np

BINS = 16
# Sets this small are split at the median of their widest axis: as good, and much cheaper.
MEDIAN_BELOW = 12


def _area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    e = np.clip(hi - lo, 0.0, None)
    e = np.where(np.isfinite(e), e, 0.0)
    return 2.0 * (e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0])


def build(item_lower, item_upper, item_weight, set_start, set_count, bins: int = BINS):
    """Binary trees over item sets (items of set s are set_start[s] .. + set_count[s], count >= 2).

    Returns (left, right, set_root): internal node children and each set's root, where a
    reference r >= 0 is an internal node and r < 0 is item -r - 1.
    """
    n_items = len(item_lower)
    lower = np.asarray(item_lower, np.float64)
    upper = np.asarray(item_upper, np.float64)
    centre = 0.5 * (np.where(np.isfinite(lower), lower, 0.0) + np.where(np.isfinite(upper), upper, 0.0))
    weight = np.asarray(item_weight, np.float64)
    order = np.arange(n_items)
    n_sets = len(set_start)
    left = np.empty(max(1, n_items), np.int64)
    right = np.empty(max(1, n_items), np.int64)
    set_root = np.arange(n_sets, dtype=np.int64)     # one internal node per set to begin with
    n_nodes = n_sets
    seg_start = np.asarray(set_start, np.int64).copy()
    seg_end = seg_start + np.asarray(set_count, np.int64)
    seg_node = set_root.copy()
    while len(seg_start):
        lengths = seg_end - seg_start
        offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        seg_of = np.repeat(np.arange(len(seg_start)), lengths)
        pos = np.arange(len(seg_of)) - offsets[seg_of] + seg_start[seg_of]
        items = order[pos]
        c = centre[items]
        cmin = np.minimum.reduceat(c, offsets)
        cmax = np.maximum.reduceat(c, offsets)
        extent = cmax - cmin
        scale = np.where(extent > 0, bins / np.where(extent > 0, extent, 1.0), 0.0)
        b = np.clip(((c - cmin[seg_of]) * scale[seg_of]).astype(np.int64), 0, bins - 1)
        # Per (segment, axis, bin): weight and box; then the SAH cost of every bin plane.
        n_seg = len(seg_start)
        best_cost = np.full(n_seg, np.inf)
        best_axis = np.zeros(n_seg, np.int64)
        best_split = np.zeros(n_seg, np.int64)
        big = np.flatnonzero(lengths >= MEDIAN_BELOW)
        in_big = (lengths >= MEDIAN_BELOW)[seg_of]
        big_index = np.full(n_seg, -1, np.int64)
        big_index[big] = np.arange(len(big))
        n_big = len(big)
        seg_big = big_index[seg_of[in_big]]
        lo_i, hi_i, w_i = lower[items[in_big]], upper[items[in_big]], weight[items[in_big]]
        for axis in range(3 if n_big else 0):
            key = seg_big * bins + b[in_big, axis]
            w = np.bincount(key, w_i, n_big * bins).reshape(n_big, bins)
            blo = np.full((n_big * bins, 3), np.inf)
            bhi = np.full((n_big * bins, 3), -np.inf)
            by_key = np.argsort(key, kind="stable")
            sorted_key = key[by_key]
            starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
            blo[sorted_key[starts]] = np.minimum.reduceat(lo_i[by_key], starts)
            bhi[sorted_key[starts]] = np.maximum.reduceat(hi_i[by_key], starts)
            blo, bhi = blo.reshape(n_big, bins, 3), bhi.reshape(n_big, bins, 3)
            l_lo = np.minimum.accumulate(blo, axis=1)[:, :-1]
            l_hi = np.maximum.accumulate(bhi, axis=1)[:, :-1]
            r_lo = np.minimum.accumulate(blo[:, ::-1], axis=1)[:, ::-1][:, 1:]
            r_hi = np.maximum.accumulate(bhi[:, ::-1], axis=1)[:, ::-1][:, 1:]
            l_w = np.cumsum(w, axis=1)[:, :-1]
            r_w = w.sum(axis=1, keepdims=True) - l_w
            cost = _area(l_lo, l_hi) * l_w + _area(r_lo, r_hi) * r_w
            cost = np.where((l_w > 0) & (r_w > 0), cost, np.inf)
            k = np.argmin(cost, axis=1)
            c_k = cost[np.arange(n_big), k]
            better = c_k < best_cost[big]
            best_cost[big] = np.where(better, c_k, best_cost[big])
            best_axis[big] = np.where(better, axis, best_axis[big])
            best_split[big] = np.where(better, k + 1, best_split[big])
        goes_right = b[np.arange(len(items)), best_axis[seg_of]] >= best_split[seg_of]
        # Small sets, and sets with no useful plane (all centres in one bin): split at the
        # median of the widest axis.
        stuck = ~np.isfinite(best_cost)
        if np.any(stuck):
            sel = stuck[seg_of]
            axis = np.argmax(extent, axis=1)[seg_of[sel]]
            coord = c[sel, axis]
            idx = np.flatnonzero(sel)
            ranked = idx[np.lexsort((coord, seg_of[sel]))]
            rank = np.empty(len(idx), np.int64)
            first = np.searchsorted(seg_of[ranked], seg_of[ranked], side="left")
            rank[np.searchsorted(idx, ranked)] = np.arange(len(ranked)) - first
            goes_right[sel] = rank >= (lengths[seg_of[sel]] // 2)
        # Stable partition inside each segment.
        perm = np.argsort(seg_of * 2 + goes_right, kind="stable")
        order[pos] = items[perm]
        n_left = lengths - np.bincount(seg_of, goes_right, n_seg).astype(np.int64)
        mid = seg_start + n_left
        # Children: a single item is referenced directly; larger halves become new nodes.
        next_start, next_end, next_node = [], [], []
        for side, (s0, s1) in enumerate(((seg_start, mid), (mid, seg_end))):
            single = (s1 - s0) == 1
            ref = np.empty(n_seg, np.int64)
            ref[single] = -order[s0[single]] - 1
            multi = np.flatnonzero(~single)
            ref[multi] = n_nodes + np.arange(len(multi))
            n_nodes += len(multi)
            (left if side == 0 else right)[seg_node] = ref
            next_start.append(s0[multi])
            next_end.append(s1[multi])
            next_node.append(ref[multi])
        seg_start = np.concatenate(next_start)
        seg_end = np.concatenate(next_end)
        seg_node = np.concatenate(next_node)
    return left[:n_nodes], right[:n_nodes], set_root
