"""The canonical shapes, one module each, and the kernel's dispatch over them.

Every primitive reaches the kernel as one of a few canonical solids (`engine.layout`
shape codes) under a matrix. Each canonical shape's module holds everything the engine
knows of it, as one row (`row.Shape`): how a ray finds its first event after t_start
(Dr.Jit, for every backend), its surface function (Dr.Jit, detached or AD), its exact world
bounds under an affine map (numpy), its surface coordinates, and whether it is convex.
A module of this package with a `SHAPE` row is a canonical shape: adding one is adding
its module and its code in `engine.layout`.

Each canonical solid is bounded, so along a full line its boundary events alternate
enter, exit, enter, ... starting with an enter. `first_event` therefore returns the
first event strictly after `t_start` and classifies it by the parity of its index.
Events are recomputed from the unchanged ray every time, so the same root gives the same
float bit for bit, and "strictly after" needs no epsilon and always makes progress.
"""
from __future__ import annotations

import importlib
import pkgutil

import drjit as dr
import numpy as np

from ..layout import ENTER, MAX_SLOPE, MESH, MISS, SHAPE_CODES
from .boxes import box_entry, inverse_direction
from .row import CanonicalHit, Shape, interval_event

__all__ = ["SHAPES", "CONVEX_CODES", "NON_CONVEX_CODES", "CanonicalHit", "Shape", "box_entry", "first_event",
           "inverse_direction", "primitive_bounds", "surface_coordinates_local", "surface_function"]


def _rows() -> tuple[Shape, ...]:
    rows = []
    for info in pkgutil.iter_modules(__path__):
        row = getattr(importlib.import_module(f"{__name__}.{info.name}"), "SHAPE", None)
        if isinstance(row, Shape):
            rows.append(row)
    rows.sort(key=lambda row: row.code)
    if {row.name: row.code for row in rows} != SHAPE_CODES or len(rows) != len(SHAPE_CODES):
        raise RuntimeError(f"engine.shapes: the rows {[(row.name, row.code) for row in rows]} are not "
                           f"engine.layout.SHAPE_CODES {SHAPE_CODES}")
    return tuple(rows)


SHAPES = _rows()
# Shapes whose inside along a ray is one interval, and those whose inside may be several.
CONVEX_CODES = tuple(row.code for row in SHAPES if row.convex)
NON_CONVEX_CODES = tuple(row.code for row in SHAPES if not row.convex)
_INTERVAL_ROWS = tuple(row for row in SHAPES if row.interval is not None)
_INTERVAL_NORMAL_ROWS = tuple(row for row in SHAPES if row.interval_normals is not None)
_EVENT_ROWS = tuple(row for row in SHAPES if row.event is not None)


def first_event(b, prim, plane_buf, o_world, d_world, t_start, mesh=None, kinds=None):
    """(t, face, class, slope) of the first boundary event of one primitive after t_start (per lane).

    `prim` is the primitives' records (`engine.device.PrimRecord`), `plane_buf` the planes
    they point into. `slope` is the event's SLOPE exponent (`engine.layout`): how steeply the
    ray meets the surface there, which scales how far in t float32 rounding can move the
    event. `mesh` is (triangle buffer, mesh node buffer, skip) for mesh leaves (`mesh.event`).
    """
    xf_rows, shape, param = prim.rows, prim.shape, prim.param
    o = b.Array3f(dr.dot(xf_rows[0], b.Array4f(o_world.x, o_world.y, o_world.z, 1.0)),
                  dr.dot(xf_rows[1], b.Array4f(o_world.x, o_world.y, o_world.z, 1.0)),
                  dr.dot(xf_rows[2], b.Array4f(o_world.x, o_world.y, o_world.z, 1.0)))
    d = b.Array3f(dr.dot(b.Array3f(xf_rows[0].x, xf_rows[0].y, xf_rows[0].z), d_world),
                  dr.dot(b.Array3f(xf_rows[1].x, xf_rows[1].y, xf_rows[1].z), d_world),
                  dr.dot(b.Array3f(xf_rows[2].x, xf_rows[2].y, xf_rows[2].z), d_world))
    t, face, cls, plane_normal = _first_event_local(b, prim, plane_buf, o, d, t_start, mesh, kinds)
    # A miss has no surface point: its slope is never read (a miss's t is inf wherever a tie
    # window meets it), and packets whose lanes all missed skip the surface function.
    slope = dr.if_stmt((b, shape, face, param, plane_normal, o, d, t, xf_rows, d_world, kinds), dr.isfinite(t),
                       _event_slope, _no_slope, label="csg_event_slope")
    return t, face, cls, slope


def _no_slope(b, shape, face, param, plane_normal, o, d, t, xf_rows, d_world, kinds):
    return dr.full(b.UInt32, MAX_SLOPE, dr.width(t))


def _event_slope(b, shape, face, param, plane_normal, o, d, t, xf_rows, d_world, kinds):
    """The SLOPE exponent of the event at t (engine.layout)."""
    plane = b.Array4f(plane_normal.x, plane_normal.y, plane_normal.z, 0.0)
    _, grad = surface_function(b.module, shape, face, param, plane, o + t * d, kinds)
    # The world normal is M^T grad for the rows M of world -> canonical; grad . d is the same
    # in both frames.
    normal = b.Array3f(*(xf_rows[0][i] * grad.x + xf_rows[1][i] * grad.y + xf_rows[2][i] * grad.z
                         for i in range(3)))
    cos = dr.abs(dr.dot(grad, d)) * dr.rsqrt(dr.squared_norm(normal) * dr.squared_norm(d_world))
    return _slope_exponent(b, cos)


def _slope_exponent(b, cos):
    """k with 2^-(k+1) < cos <= 2^-k, clamped to [0, MAX_SLOPE] (NaN, e.g. a cone's apex: MAX_SLOPE)."""
    biased = dr.reinterpret_array(b.module.Int32, dr.minimum(cos, 1.0)) >> 23     # IEEE exponent + 127
    k = dr.clip(126 - biased, 0, MAX_SLOPE)
    return b.UInt32(dr.select(cos > 0, k, MAX_SLOPE))


@dr.syntax
def _first_event_local(b, prim, plane_buf, o, d, t_start, mesh, kinds):
    """Each present shape in a branch of its own: an interval (its first event after t_start
    taken once for all of them), an interval with its faces' normals, or an event of its own."""
    shape, param, plane_start, plane_count = prim.shape, prim.param, prim.plane_start, prim.plane_count
    width = dr.width(t_start)
    near = dr.full(b.Float, dr.inf, width)
    far = dr.full(b.Float, -dr.inf, width)
    near_face = dr.zeros(b.UInt32, width)
    far_face = dr.zeros(b.UInt32, width)
    near_normal = dr.zeros(b.Array3f, width)
    far_normal = dr.zeros(b.Array3f, width)
    t = dr.full(b.Float, dr.inf, width)
    face = dr.zeros(b.UInt32, width)
    cls = dr.full(b.UInt32, MISS, width)
    present = _present(kinds)
    for row in _INTERVAL_ROWS:
        if dr.hint(row.code in present, mode="scalar"):
            if shape == row.code:
                near, far, near_face, far_face = row.interval(b, o, d, param, plane_buf, plane_start, plane_count)
    for row in _INTERVAL_NORMAL_ROWS:
        if dr.hint(row.code in present, mode="scalar"):
            if shape == row.code:
                near, far, near_face, far_face, near_normal, far_normal = row.interval_normals(
                    b, o, d, param, plane_buf, plane_start, plane_count)
    own = dr.zeros(b.Bool, width)
    for row in _EVENT_ROWS:
        # A mesh's event walks its BVH: only trees with meshes pass their buffers.
        if dr.hint(row.code in present and (mesh is not None or row.code != MESH), mode="scalar"):
            own |= shape == row.code
            if shape == row.code:
                if dr.hint(row.event_normal, mode="scalar"):
                    t, face, cls, near_normal = row.event(b, o, d, param, plane_buf, plane_start, mesh, t_start)
                    far_normal = b.Array3f(near_normal)
                else:
                    t, face, cls = row.event(b, o, d, param, plane_buf, plane_start, mesh, t_start)
    t_i, face_i, cls_i = interval_event(b, near, far, near_face, far_face, t_start)
    t, face, cls = dr.select(own, t, t_i), dr.select(own, face, face_i), dr.select(own, cls, cls_i)
    return t, face, cls, dr.select(cls == ENTER, near_normal, far_normal)


def _present(kinds):
    """The shape codes a kernel must handle: all of them unless the tree says which."""
    return frozenset(row.code for row in SHAPES) if kinds is None else kinds


def surface_function(m, shape, face, param, plane, x, kinds=None):
    """(g, grad g) of a primitive's `face` at canonical point x; g = 0 on the surface, < 0 inside.

    `m` is a Dr.Jit module (detached or AD) and `plane` the face's plane for convex primitives.
    grad g is the outward (unnormalized) normal: the hit normal and its derivatives use it.
    """
    g = grad = None
    present = _present(kinds)
    for row in SHAPES:
        if row.code not in present:
            continue
        g_k, grad_k = row.surface(m, face, param, plane, x)
        g = g_k if g is None else dr.select(shape == row.code, g_k, g)
        grad = grad_k if grad is None else dr.select(shape == row.code, grad_k, grad)
    return g, grad


def surface_coordinates_local(hit: CanonicalHit):
    """(uv, dx/du, dx/dv) of hits in their primitives' canonical frames, each by its shape's
    parameterization (`Shape.uv`)."""
    uv = du = dv = None
    for row in reversed(SHAPES):
        uv_k, du_k, dv_k = row.uv(hit)
        if uv is None:
            uv, du, dv = uv_k, du_k, dv_k
        else:
            mine = hit.shape == row.code
            uv, du, dv = dr.select(mine, uv_k, uv), dr.select(mine, du_k, du), dr.select(mine, dv_k, dv)
    return uv, du, dv


def primitive_bounds(shape, to_world, param, plane_start, plane_vertices):
    """Exact world boxes (lower, upper) of primitives: support functions under canonical -> world."""
    A, c = to_world[:, :3, :3], to_world[:, :3, 3]
    lower, upper = c.copy(), c.copy()
    for row in SHAPES:
        m = shape == row.code
        if np.any(m):
            lower[m], upper[m] = row.bounds(A[m], c[m], param[m], plane_start[m], plane_vertices)
    return lower, upper
