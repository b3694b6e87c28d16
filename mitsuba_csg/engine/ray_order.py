"""Reordering incoherent ray batches before traversal.

The automaton runs in SIMD packets (16 lanes with AVX-512, 32 on a GPU warp), and a packet
loops until its slowest lane is done. In a path tracer's bounce and shadow rays, a lane that
misses the model's box sits idle beside one crossing a hundred nodes, and neighbours start
from unrelated points in unrelated directions. Tracing only the rays that meet the root box,
grouped by where they start and where they go, fills the packets with rays that do similar
work (benchmarks/incoherent_rays.py).

The order is a counting sort on a key built from the ray's origin cell in the root box and
its direction cell on an octahedral map, with Dr.Jit's atomics: it runs on any backend and
needs evaluated inputs, so not inside a symbolic loop.
"""
from __future__ import annotations

import drjit as dr

from .leaf_events import box_meets
from .device import opaque

# Origin cells per axis of the root box (2^4) and direction cells per axis of the octahedral
# map (2^4): the key has 3 * 4 + 2 * 4 = 20 bits, the histogram 2^20 buckets. Measured on
# bounce-like rays and point-membership rays (City-3385, Cheese-1000): 3-5 bits per origin
# axis and 3-5 per direction axis are within ~10 % of each other; this was among the best.
ORIGIN_BITS = 4
DIRECTION_BITS = 4
KEY_BUCKETS = 1 << (3 * ORIGIN_BITS + 2 * DIRECTION_BITS)


def _spread(b, x, bits: int, stride: int):
    """The low `bits` bits of x, each moved to every `stride`-th bit (Morton interleave)."""
    out = dr.zeros(b.UInt32, dr.width(x))
    for i in range(bits):
        out |= ((x >> i) & 1) << (stride * i)
    return out


def _cell(b, x, bits: int):
    """x in [-1, 1] (clamped) to a cell index in [0, 2^bits)."""
    return b.UInt32(dr.clip((x + 1.0) * (0.5 * (1 << bits)), 0.0, float((1 << bits) - 1)))


def sort_keys(b, o, d):
    """Per ray, a key whose nearby values mean nearby origins, then similar directions.

    `o` in the scene frame (the root box within [-1, 1]^3; origins outside clamp to its
    faces), `d` unit directions."""
    origin = 0
    for axis in range(3):
        origin |= _spread(b, _cell(b, o[axis], ORIGIN_BITS), ORIGIN_BITS, 3) << axis
    # Octahedral map of the unit sphere onto [-1, 1]^2: cells of similar solid angle.
    norm1 = dr.abs(d[0]) + dr.abs(d[1]) + dr.abs(d[2])
    u, v = d[0] / norm1, d[1] / norm1
    lower = d[2] < 0
    u, v = (dr.select(lower, (1.0 - dr.abs(v)) * dr.sign(u), u),
            dr.select(lower, (1.0 - dr.abs(u)) * dr.sign(v), v))
    direction = (_spread(b, _cell(b, u, DIRECTION_BITS), DIRECTION_BITS, 2)
                 | (_spread(b, _cell(b, v, DIRECTION_BITS), DIRECTION_BITS, 2) << 1))
    return (origin << (2 * DIRECTION_BITS)) | direction


def root_box_mask(b, tree, o, inv_d, tmin, tmax, active):
    """Rays (scene frame) that meet the root box within [tmin, tmax]: the only ones with work."""
    root = opaque(tree, b.UInt32, tree.root)   # opaque: another model, the same kernel
    return b.Bool(active) & box_meets(tree, b.SceneRay(o=o, inv_d=inv_d, tmax=tmax), root, tmin)


def coherent_order(b, key, mask):
    """(order, rank): `order` lists the lanes where `mask` holds, sorted by `key`
    (< KEY_BUCKETS), lanes with equal keys in no particular order; `rank[lane]` is the
    lane's place in `order` (where `mask` holds). Evaluates its inputs.

    Every scatter runs over all lanes, masked, none over the selected lanes only: inside an
    evaluated loop Dr.Jit masks scatters with the loop's active lanes, and a narrower scatter
    there crashed (Dr.Jit 1.5, a loop with state compression)."""
    n = dr.width(key)
    histogram = dr.zeros(b.UInt32, KEY_BUCKETS)
    dr.scatter_reduce(dr.ReduceOp.Add, histogram, 1, key, mask)
    cursor = dr.prefix_sum(histogram)
    rank = dr.scatter_inc(cursor, key, mask)
    dr.eval(rank)                  # an atomic's result may be evaluated only once
    count = int(dr.count(mask)[0])
    order = dr.zeros(b.UInt32, count)
    if count:
        dr.scatter(order, dr.arange(b.UInt32, n), rank, mask)
    return order, rank
