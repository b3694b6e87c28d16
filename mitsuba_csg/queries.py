"""The public ray queries: `prepare` a model once, then `trace_rays` (Dr.Jit arrays in and
out, for integrators) or `trace` / `contains` (numpy in and out).

Scene-free: the integrators call `trace_rays` with the ray arrays of their own variant;
`trace`, `contains` and `rays_to_device` convert numpy arrays at the edges only.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from .engine import layout as K
from .engine.automaton import traverse
from .engine.backend import Backend, default_backend, owned
from .engine.device import KernelTree, node_record, opaque, scene_rays, upload
from .engine.hit_geometry import hit_normal
from .engine.lowering import FlatTree, lower, with_primitive_transforms
from .engine.optimize import OptimizedModel
from .engine.optimize import optimize as optimize_tree
from .engine.options import TraversalOptions
from .engine.ray_order import coherent_order, root_box_mask, sort_keys
from .engine.shapes import inverse_direction
from .errors import CSGError
from .model.nodes import Node


class IterationLimitWarning(RuntimeWarning):
    """Some rays reached the kernel's iteration bound; their results are reported as NaN."""


@dataclass
class Prepared:
    """A model lowered and uploaded once, ready to trace many ray batches."""
    flat: FlatTree
    tree: KernelTree
    max_iterations: int | None = None   # the bound asked for (None: the tree's own, `engine.device.upload`)
    # Frozen `trace_rays` (dr.freeze) per (width, tmin, tmax), oldest first.
    replays: dict = field(default_factory=dict, repr=False, compare=False)


# The kernel counts iterations in a 32-bit word.
MAX_ITERATIONS = 2**31 - 1

# Frozen traces kept per prepared model: each holds its recorded kernel launches.
_MAX_REPLAYS = 4


def prepare(model, backend=None, *, optimize: bool = True, positive: bool = False,
            max_iterations: int | None = None, traversal: TraversalOptions | None = None) -> Prepared:
    """Optimize (or just lower) `model` and upload it for `backend` (default: Mitsuba's variant).

    `optimize=False` traces the input tree as written, chains of one operation balanced in
    input order; `positive=True` (with optimize=False) traces its positive form. `traversal`
    switches the automaton's mechanisms (`engine.options.TraversalOptions`; all on by default).
    """
    if isinstance(model, Prepared):
        return model
    if max_iterations is not None and (isinstance(max_iterations, bool) or not isinstance(max_iterations, int)
                                       or not 1 <= max_iterations <= MAX_ITERATIONS):
        raise CSGError(f"max_iterations: expected an integer in 1..{MAX_ITERATIONS} (or None for the "
                       f"model's own bound), got {max_iterations!r:.40}")
    if backend is None:
        backend = default_backend()
    if isinstance(model, FlatTree):
        flat = model
    elif isinstance(model, OptimizedModel):
        flat = model.flat
    elif not isinstance(model, Node):
        raise CSGError(f"expected a CSG model, got {type(model).__name__}")
    elif optimize:
        flat = optimize_tree(model)[0].flat
    else:
        flat = lower(model, positive=positive)
    return Prepared(flat, upload(flat, backend, max_iterations, traversal), max_iterations)


def moved(prepared: Prepared, to_world: np.ndarray) -> Prepared:
    """`prepared` with new canonical -> world matrices (P, 4, 4) for its primitives (a
    differentiable shape's parameter update): the same tree, backend, traversal options and
    iteration bound, boxes and records built anew from the new transforms."""
    flat = with_primitive_transforms(prepared.flat, to_world)
    tree = prepared.tree
    return Prepared(flat, upload(flat, tree.b, prepared.max_iterations, tree.options), prepared.max_iterations)


@dataclass
class RayHits:
    """Per-ray results on the device (detached Dr.Jit arrays)."""
    t: object          # Float: inf on a miss, NaN where the iteration bound was hit
    normal: object     # Array3f: outward unit normal of the CSG solid
    prim: object       # UInt32: index into Model.leaves(); NO_INDEX (0xFFFFFFFF) on a miss
    entering: object   # Bool: the ray enters the solid at the hit
    finished: object   # Bool: False where the iteration bound stopped the lane
    steps: object      # UInt32: automaton iterations plus set-walk iterations per lane
    info: object = None  # UInt32: class, flip bit and face of the hit (engine.layout)


def _broadcast_opaque(tree: KernelTree, value: float, n: int):
    # One opaque value read by every lane: a width-n opaque array would be filled in memory
    # (a memset kernel per call), a literal would be compiled into the kernel.
    return opaque(tree, tree.b.Float, float(value)) + dr.zeros(tree.b.Float, n)


def trace_rays(prepared: Prepared, o, d, tmin=0.0, tmax=float("inf"), *, frozen: bool = False,
               active=None, reorder: bool = False, start_prim=None) -> RayHits:
    """First hit of each ray o + t d, t in (tmin, tmax], on the CSG solid (Dr.Jit arrays).

    `active` (a Bool per ray, optional) skips the lanes where it is false: they miss at no cost.

    `start_prim` (a UInt32 per ray, optional) names the primitive whose surface each ray
    starts on, as `RayHits.prim` gives it for the hit the ray continues from (NO_INDEX,
    NO_INDEX, 0xFFFFFFFF, for none): a hint, not a constraint. Hit distances and classes never depend
    on it; where the exits of several primitives coincide exactly (coincident faces), which
    of them is reported may. A ray leaving a hole's wall into the hole (a path tracer's
    bounce and shadow rays off a Cheese) then skips the search along its chord through the
    hole: 26.7 -> 19.9 steps per ray on the Cheese-1000 surface bounces of
    benchmarks/incoherent_rays.py.

    `reorder=True` traces only the rays that meet the model's box, sorted by origin and
    direction (`engine.ray_order`), and puts the results back in the input's order; results
    are the same bit for bit. It pays on incoherent batches (bounce-like rays, scattered
    points' rays: 1.1-1.9x, benchmarks/incoherent_rays.py) and costs ~10 % on camera rays,
    which are coherent already. It evaluates the inputs, so inside a symbolic loop (where
    nothing can be evaluated, as in the csg_* integrators) it is ignored.

    `frozen=True` records the call's kernels with `dr.freeze` the first time a batch of this
    width (and these tmin, tmax numbers) is traced, and replays them afterwards without
    tracing the kernel again in Python (2-4 ms a call): for repeated top-level calls on
    evaluated rays, such as an interactive preview or a benchmark, not inside a symbolic loop
    or an integrator. Results are the same bit for bit.
    """
    if frozen:
        if active is not None or start_prim is not None:
            raise CSGError("trace_rays(frozen=True): an active mask or start_prim is not supported; trace all "
                           "lanes from nowhere in particular")
        return _replay(prepared, o, d, tmin, tmax)
    if reorder and not dr.flag(dr.JitFlag.SymbolicScope):
        return _trace_reordered(prepared, o, d, tmin, tmax, active, start_prim)
    return _trace(prepared.tree, o, d, tmin, tmax, active, start_prim)


def _trace(tree: KernelTree, o, d, tmin, tmax, active, start_prim) -> RayHits:
    """trace_rays on the uploaded tree alone (what a frozen trace may capture, `_replay`)."""
    b = tree.b
    o, d = b.Array3f(dr.detach(o)), b.Array3f(dr.detach(d))
    # The widest input sets the batch: a camera's rays share one origin (width 1).
    n = max(dr.width(o), dr.width(d), dr.width(tmin), dr.width(tmax), dr.width(active),
            1 if start_prim is None else dr.width(start_prim))
    # Opaque: a literal would be compiled into the kernel, and every new value would recompile it.
    tmin = _broadcast_opaque(tree, tmin, n) if isinstance(tmin, (int, float)) else b.Float(dr.detach(tmin))
    tmax = _broadcast_opaque(tree, tmax, n) if isinstance(tmax, (int, float)) else b.Float(dr.detach(tmax))
    active = True if active is None else b.Bool(dr.detach(active))
    if start_prim is not None:
        start_prim = b.UInt32(dr.detach(start_prim))
    t, leaf, info, finished, steps = traverse(tree, o, d, tmin, tmax, active, start_prim)
    hit = leaf != K.NO_INDEX
    _, prim, _, _ = node_record(b, tree, leaf, hit)
    normal = hit_normal(tree, prim, info, o, d, dr.select(hit, t, 0.0), hit)
    t = dr.select(finished, t, dr.nan)
    return RayHits(t=t, normal=normal, prim=dr.select(hit, prim, K.NO_INDEX),
                   entering=hit & (K.info_class(info) == K.ENTER), finished=finished, steps=steps, info=info)


def _trace_reordered(prepared: Prepared, o, d, tmin, tmax, active, start_prim=None) -> RayHits:
    b = prepared.tree.b
    o, d = b.Array3f(dr.detach(o)), b.Array3f(dr.detach(d))
    n = max(dr.width(o), dr.width(d), dr.width(tmin), dr.width(tmax), dr.width(active),
            1 if start_prim is None else dr.width(start_prim))
    o, d = o + dr.zeros(b.Array3f, n), d + dr.zeros(b.Array3f, n)
    tmin = b.Float(dr.detach(tmin)) + dr.zeros(b.Float, n)
    tmax = b.Float(dr.detach(tmax)) + dr.zeros(b.Float, n)
    scene_o, scene_d, k = scene_rays(prepared.tree, o, d)
    mask = root_box_mask(b, prepared.tree, scene_o, inverse_direction(b, scene_d), tmin * k, tmax * k,
                         True if active is None else b.Bool(dr.detach(active)))
    order, rank = coherent_order(b, sort_keys(b, scene_o, scene_d), mask)
    misses = RayHits(t=dr.full(b.Float, dr.inf, n), normal=dr.zeros(b.Array3f, n),
                     prim=dr.full(b.UInt32, K.NO_INDEX, n), entering=dr.zeros(b.Bool, n),
                     finished=dr.full(b.Bool, True, n), steps=dr.zeros(b.UInt32, n),
                     info=dr.full(b.UInt32, K.MISS, n))
    if dr.width(order) == 0:
        return misses
    if start_prim is not None:
        start_prim = dr.gather(b.UInt32, b.UInt32(dr.detach(start_prim)) + dr.zeros(b.UInt32, n), order)
    traced = trace_rays(prepared, dr.gather(b.Array3f, o, order), dr.gather(b.Array3f, d, order),
                        dr.gather(b.Float, tmin, order), dr.gather(b.Float, tmax, order), start_prim=start_prim)
    fields = ("t", "normal", "prim", "entering", "finished", "steps", "info")
    dr.eval(*(getattr(traced, name) for name in fields))   # one traversal kernel for all outputs
    # Gathered back rather than scattered: see coherent_order.
    back = {name: dr.select(mask, dr.gather(type(getattr(traced, name)), getattr(traced, name), rank, mask),
                            getattr(misses, name))
            for name in fields}
    return RayHits(**back)


def _replay(prepared: Prepared, o, d, tmin, tmax) -> RayHits:
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (tmin, tmax)):
        raise CSGError("trace_rays(frozen=True): tmin and tmax must be numbers (one per call, not per ray)")
    b = prepared.tree.b
    o, d = b.Array3f(dr.detach(o)), b.Array3f(dr.detach(d))
    # A frozen function replays its kernels at the width it recorded, so each width gets its own.
    key = (dr.width(o), float(tmin), float(tmax))
    replay = prepared.replays.get(key)
    if replay is None:
        if len(prepared.replays) >= _MAX_REPLAYS:
            prepared.replays.pop(next(iter(prepared.replays)))
        for value in key[1:]:     # made outside the recording, which replays without making them
            opaque(prepared.tree, b.Float, value)
        # The recording captures the uploaded tree only: dr.freeze inspects what a frozen
        # function captures on every call, and the model's numpy arrays (FlatTree) took it 29 ms
        # a call on City-343k, as long as the traversal kernel itself.
        tree = prepared.tree
        replay = prepared.replays[key] = dr.freeze(lambda o, d: _trace(tree, o, d, key[1], key[2], None, None))
    return replay(o, d)


# ---- numpy helpers ----

@dataclass
class Hits:
    """First hits as numpy arrays (see `trace`)."""
    t: np.ndarray          # (N,) float32; inf on a miss
    normal: np.ndarray     # (N, 3) outward unit normal of the CSG solid; 0 on a miss
    prim: np.ndarray       # (N,) int64 index into model.leaves(); -1 on a miss
    entering: np.ndarray   # (N,) bool
    unfinished: int        # rays stopped by the iteration bound (their t is NaN)
    steps: np.ndarray      # (N,) automaton iterations plus set-walk iterations (engine.set_walk)


def _rays(a, what: str) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as e:        # strings, ragged rows, objects
        raise CSGError(f"{what}: expected an (N, 3) array of numbers ({str(e).splitlines()[0][:120]})") from None
    if arr.ndim == 1 and arr.shape == (3,):
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise CSGError(f"{what}: expected an (N, 3) array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CSGError(f"{what}: contains NaN or infinite values (first at row "
                       f"{int(np.flatnonzero(~np.isfinite(arr).all(1))[0])})")
    return arr


def rays_to_device(array, backend: Backend | None = None):
    """An (N, 3) numpy array as a Dr.Jit Array3f (float32) of `backend` (default: Mitsuba's variant)."""
    b = backend or default_backend()
    a32 = np.ascontiguousarray(np.asarray(array, dtype=np.float64).reshape(-1, 3).T, dtype=np.float32)
    return b.Array3f(*(owned(b.Float, a32[k]) for k in range(3)))


def trace(model, origins, directions, tmin: float = 0.0, tmax: float = np.inf, *,
          optimize: bool = True, max_iterations: int | None = None, reorder: bool = False) -> Hits:
    """First hit of each ray on the CSG solid; numpy (N, 3) arrays in, `Hits` out.

    `model` is a Node, an optimized model or the result of `prepare`. Rays are o + t d with
    t in (tmin, tmax]; d need not be unit length and t is in units of d. The tree is
    optimized first unless `optimize=False` (see `prepare`). `reorder=True` suits rays in no
    particular order, such as scattered points' rays (see `trace_rays`); results are the same.
    """
    o, d = _rays(origins, "origins"), _rays(directions, "directions")
    if len(o) != len(d):
        raise CSGError(f"origins and directions differ in length ({len(o)} vs {len(d)})")
    # float32 carries the rays: a direction that rounds to zero there would silently miss.
    tiny = np.max(np.abs(d), axis=1) < np.finfo(np.float32).tiny
    if np.any(tiny):
        raise CSGError(f"directions: row {int(np.flatnonzero(tiny)[0])} is the zero vector, or rounds to it in "
                       f"float32 (components below {np.finfo(np.float32).tiny:.3g})")
    tmin, tmax = _ray_parameter(tmin, "tmin"), _ray_parameter(tmax, "tmax")
    if np.isnan(tmin) or np.isnan(tmax) or tmin > tmax:
        raise CSGError(f"need tmin <= tmax, got tmin={tmin}, tmax={tmax}")
    prepared = prepare(model, optimize=optimize, max_iterations=max_iterations)
    b = prepared.tree.b
    if len(o) == 0:
        return Hits(np.zeros(0, np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                    np.zeros(0, bool), 0, np.zeros(0, np.uint32))
    hits = trace_rays(prepared, rays_to_device(o, b), rays_to_device(d, b), float(tmin), float(tmax),
                      reorder=reorder)
    dr.eval(hits.t, hits.normal, hits.prim, hits.entering, hits.finished, hits.steps)
    prim = hits.prim.numpy().astype(np.int64)
    prim[prim == K.NO_INDEX] = -1
    unfinished = int(np.count_nonzero(~hits.finished.numpy()))
    if unfinished:
        warnings.warn(f"{unfinished} of {len(o)} rays reached the iteration bound "
                      f"({prepared.tree.max_iterations}); their t is NaN", IterationLimitWarning, stacklevel=2)
    return Hits(hits.t.numpy(), hits.normal.numpy().T.copy(), prim, hits.entering.numpy(),
                unfinished, hits.steps.numpy())


def _ray_parameter(value, what: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise CSGError(f"{what}: expected a number, got {type(value).__name__} {value!r:.40}")
    try:
        return float(value)
    except OverflowError:
        raise CSGError(f"{what}: an integer beyond the float range") from None


# A direction with no special relation to axes or common angles, so that membership rays
# rarely graze edges of axis-aligned or symmetric models.
_PROBE = np.array([0.5773502691896257, 0.5773502691896257, 0.5773502691896257]) + \
    np.array([0.0912, -0.0513, 0.0231])
_PROBE /= np.linalg.norm(_PROBE)


def contains(model, points, *, optimize: bool = True) -> np.ndarray:
    """(N,) bool: which points lie inside the solid.

    A ray from each point finds the first boundary after it: an exit means the point is
    inside. Points on the boundary itself may go either way.
    """
    p = _rays(points, "points")
    # Points come in any order: their rays are traced grouped by where they start.
    hits = trace(model, p, np.broadcast_to(_PROBE, p.shape), 0.0, np.inf, optimize=optimize, reorder=True)
    return (hits.prim >= 0) & ~hits.entering
