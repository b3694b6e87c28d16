"""An independent float64 reference for CSG ray tracing (tests only).

Nothing here shares code with the kernel or the lowering step: the model is read through its
public objects only (`Operation.kind/.children`, `Node.matrix`, the primitives' size
attributes), transforms are composed by our own walk, and every primitive is intersected
analytically in its own local frame (the primitive's frame, not the kernel's canonical one).

Conventions
-----------
* A ray is o + t d for t in (-inf, inf); d need not be unit length and t is never rescaled.
* Primitive indices are the leaves in depth-first, left-to-right input order.
* Normals are world-space outward unit normals *of the solid being described*: for a
  boundary contributed by a subtracted primitive the primitive's normal is flipped, so an
  interval entry has normal . d < 0 and an exit normal . d > 0 (generically).
* The Boolean result is regularized: zero-length intervals are dropped and touching ones
  merged (with a 1e-12 relative tolerance).

Public functions
----------------
intervals(model, origins, directions) -> list (per ray) of sorted lists of
    (t_enter, t_exit, prim_enter, prim_exit)
interval_arrays(model, origins, directions) -> Intervals (padded arrays, normals included)
first_hit(model, origins, directions, tmin=0.0, tmax=inf) -> (t, prim, normal, entering)
contains(model, points) -> (N,) bool
stable_mask(model, origins, directions, tmin=0.0, tmax=inf, ...) -> (N,) bool
leaf_list(model) -> [(primitive, world 4x4)] in prim-index order
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mitsuba_csg.model import Operation
from mitsuba_csg.model.mesh import Mesh
from mitsuba_csg.model.primitives import Box, Cone, ConvexPolyhedron, Hyperboloid, Paraboloid, Prism, Sphere, Torus

INF = np.inf
_REG_TOL = 1e-12   # regularization tolerance, relative to the ray's time scale


# ---------------------------------------------------------------------------------------------
# Model walk (our own; no Node.leaves / walk_leaves / lowering)
# ---------------------------------------------------------------------------------------------

def _postorder(model, leaf_fn, op_fn):
    """Evaluate the tree bottom-up, iteratively. leaf_fn(prim, world, index); op_fn(kind, values)."""
    stack = [(model, np.eye(4), False)]
    values = []
    counter = 0
    while stack:
        node, parent, expanded = stack.pop()
        if isinstance(node, Operation):
            if expanded:
                n = len(node.children)
                vals = values[len(values) - n:]
                del values[len(values) - n:]
                values.append(op_fn(node.kind, vals))
            else:
                world = parent @ np.asarray(node.matrix, dtype=np.float64)
                stack.append((node, world, True))
                for child in reversed(node.children):
                    stack.append((child, world, False))
        elif isinstance(node, (Sphere, Box, Cone, Torus, ConvexPolyhedron, Mesh, Paraboloid, Hyperboloid)):
            world = parent @ np.asarray(node.matrix, dtype=np.float64)
            values.append(leaf_fn(node, world, counter))
            counter += 1
        else:
            raise TypeError(f"reference: unsupported node type {type(node).__name__}")
    assert len(values) == 1
    return values[0]


def leaf_list(model):
    """[(primitive, world matrix)] in primitive-index (depth-first input) order."""
    out = []

    def leaf(prim, world, index):
        out.append((prim, world))
        return None

    _postorder(model, leaf, lambda kind, vals: None)
    return out


def _local_half_extent(prim):
    """Half sizes of a box around the primitive in its own frame (centred on its origin)."""
    if isinstance(prim, Sphere):
        return np.full(3, prim.radius)
    if isinstance(prim, Box):
        return 0.5 * np.asarray(prim.size, dtype=np.float64)
    if isinstance(prim, Cone):
        r = max(prim.radius_bottom, prim.radius_top)
        return np.array([r, r, 0.5 * prim.height])
    if isinstance(prim, Torus):
        r = prim.major_radius + prim.minor_radius
        return np.array([r, r, prim.minor_radius])
    if isinstance(prim, (Paraboloid, Hyperboloid)):
        a, b, c, h = _quadric_coefficients(prim)
        r = np.sqrt(max(a * h * h + abs(b) * h + c, c))
        return np.array([r, r, h])
    if isinstance(prim, Mesh):
        return np.abs(np.asarray(prim.vertices, dtype=np.float64)).max(axis=0)
    if isinstance(prim, Prism):
        r = prim.apothem / np.cos(np.pi / prim.sides)
        return np.array([r, r, 0.5 * prim.height])
    return np.abs(np.asarray(prim.vertices, dtype=np.float64)).max(axis=0)


def _extent(model):
    """An upper bound of the largest |coordinate| of the solid: the world corners of its leaves' boxes."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    best = 0.0
    for prim, world in leaf_list(model):
        pts = (corners * _local_half_extent(prim)) @ world[:3, :3].T + world[:3, 3]
        best = max(best, float(np.abs(pts).max()))
    return best


# The kernel's tie window (docs/accuracy.md): events of two children closer than
# 8 ulps of (extent + |o|_inf) / |d| times 2^(k+1) < 2 / |cos| are one event. Boundaries that
# close are ambiguous in float32 by design.
_KERNEL_TIE = 8 * 2.0 ** -23


def _planes_of(prim):
    """(n (P,3) unit, d (P,)) half-spaces n.x <= d in the primitive's local frame."""
    if isinstance(prim, Prism):
        k = np.arange(prim.sides)
        ang = 2.0 * np.pi * k / prim.sides
        n = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
        d = np.full(prim.sides, float(prim.apothem))
        n = np.vstack([n, [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]])
        d = np.concatenate([d, [0.5 * prim.height, 0.5 * prim.height]])
        return n, d
    if isinstance(prim, ConvexPolyhedron):
        p = np.asarray(prim.planes, dtype=np.float64)
        norm = np.linalg.norm(p[:, :3], axis=1)
        return p[:, :3] / norm[:, None], p[:, 3] / norm
    if isinstance(prim, Box):
        h = 0.5 * np.asarray(prim.size, dtype=np.float64)
        n = np.vstack([np.eye(3), -np.eye(3)])
        return n, np.concatenate([h, h])
    raise TypeError(type(prim).__name__)


# ---------------------------------------------------------------------------------------------
# Interval lists: padded arrays
# ---------------------------------------------------------------------------------------------

@dataclass
class Intervals:
    """Per ray, up to K intervals, valid ones first (padding: t = inf, prim = -1).

    t (N,K,2) enter/exit parameters; prim (N,K,2); normal (N,K,2,3) outward unit normals of
    the described solid; margin (N,K,2) distance in t to the next competing constraint of the
    same primitive (edge proximity; inf when none).
    """
    t: np.ndarray
    prim: np.ndarray
    normal: np.ndarray
    margin: np.ndarray

    @property
    def valid(self):
        return np.isfinite(self.t[..., 0])

    @property
    def count(self):
        return self.valid.sum(axis=1)


def _empty(n, k=1):
    return Intervals(np.full((n, k, 2), INF), np.full((n, k, 2), -1, dtype=np.int64),
                     np.zeros((n, k, 2, 3)), np.full((n, k, 2), INF))


def _extract(t, inside, prim, normal, margin):
    """Intervals where `inside` (state after each event, events sorted by t) is true."""
    n, m = t.shape
    prev = np.concatenate([np.zeros((n, 1), bool), inside[:, :-1]], axis=1)
    start = inside & ~prev
    end = ~inside & prev
    # Every start has its end: the solids are bounded and the sweep ends outside.
    cnt_s = start.sum(1)
    cnt_e = end.sum(1)
    if np.any(cnt_s != cnt_e):
        raise AssertionError("reference: unbalanced interval sweep (unbounded set?)")
    k = max(int(cnt_s.max(initial=0)), 1)
    out = _empty(n, k)
    for mask, side in ((start, 0), (end, 1)):
        rows, cols = np.nonzero(mask)
        offsets = np.cumsum(cnt_s) - cnt_s
        rank = np.arange(len(rows)) - offsets[rows]
        out.t[rows, rank, side] = t[rows, cols]
        out.prim[rows, rank, side] = prim[rows, cols]
        out.normal[rows, rank, side] = normal[rows, cols]
        out.margin[rows, rank, side] = margin[rows, cols]
    return out


def _compact(L, keep):
    """Move the kept intervals (N,K mask) to the front, preserving order."""
    n = keep.shape[0]
    cnt = keep.sum(1)
    k = max(int(cnt.max(initial=0)), 1)
    out = _empty(n, k)
    rows, cols = np.nonzero(keep)
    rank = np.arange(len(rows)) - (np.cumsum(cnt) - cnt)[rows]
    out.t[rows, rank] = L.t[rows, cols]
    out.prim[rows, rank] = L.prim[rows, cols]
    out.normal[rows, rank] = L.normal[rows, cols]
    out.margin[rows, rank] = L.margin[rows, cols]
    return out


def _regularize(L, tscale):
    """Drop zero-length intervals, merge touching ones (tolerance relative to tscale (N,))."""
    t0, t1 = L.t[..., 0], L.t[..., 1]
    with np.errstate(invalid="ignore"):
        tol = _REG_TOL * (np.abs(np.where(np.isfinite(t0), t0, 0.0)) + tscale[:, None])
        keep = np.isfinite(t0) & (t1 - t0 > tol)
    L = _compact(L, keep)
    t0, t1 = L.t[..., 0], L.t[..., 1]
    valid = np.isfinite(t0)
    if L.t.shape[1] == 1:
        return L
    tol = _REG_TOL * (np.abs(np.where(valid, t0, 0.0)) + tscale[:, None])
    joins = np.zeros_like(valid)
    with np.errstate(invalid="ignore"):
        joins[:, 1:] = valid[:, 1:] & valid[:, :-1] & (t0[:, 1:] - t1[:, :-1] <= tol[:, 1:])
    if not joins.any():
        return L
    first = valid & ~joins
    nxt = np.zeros_like(valid)
    nxt[:, :-1] = joins[:, 1:]
    last = valid & ~nxt
    a = _compact(L, first)
    b = _compact(L, last)
    a.t[..., 1] = b.t[..., 1]
    a.prim[..., 1] = b.prim[..., 1]
    a.normal[:, :, 1] = b.normal[:, :, 1]
    a.margin[..., 1] = b.margin[..., 1]
    return a


def _combine(kind, lists):
    """Boolean combination of regularized interval lists by an event sweep (n-ary)."""
    ts, deltas, groups, prims, normals, margins = [], [], [], [], [], []
    for j, L in enumerate(lists):
        n, k = L.t.shape[:2]
        t = L.t.reshape(n, 2 * k)
        valid = np.isfinite(t)
        delta = np.where(valid, np.tile([1, -1], k)[None, :], 0)
        sign = -1.0 if (kind == "difference" and j > 0) else 1.0
        ts.append(t)
        deltas.append(delta)
        groups.append(np.full((n, 2 * k), j))
        prims.append(L.prim.reshape(n, 2 * k))
        normals.append(sign * L.normal.reshape(n, 2 * k, 3))
        margins.append(L.margin.reshape(n, 2 * k))
    t = np.concatenate(ts, 1)
    order = np.argsort(t, axis=1, kind="stable")
    take = lambda a: np.take_along_axis(a, order, axis=1)  # noqa: E731
    t = take(t)
    delta = take(np.concatenate(deltas, 1))
    group = take(np.concatenate(groups, 1))
    prim = take(np.concatenate(prims, 1))
    margin = take(np.concatenate(margins, 1))
    normal = np.take_along_axis(np.concatenate(normals, 1), order[..., None], axis=1)
    if kind == "union":
        inside = np.cumsum(delta, 1) > 0
    elif kind == "intersection":
        inside = np.cumsum(delta, 1) == len(lists)
    elif kind == "difference":
        ca = np.cumsum(np.where(group == 0, delta, 0), 1)
        co = np.cumsum(np.where(group > 0, delta, 0), 1)
        inside = (ca > 0) & (co == 0)
    else:
        raise ValueError(kind)
    return _extract(t, inside, prim, normal, margin)


# ---------------------------------------------------------------------------------------------
# Primitives, in their local frames. Each returns raw intervals (t0 <= t1, zero-length kept),
# local normals, margins; `grow` offsets the surface outwards (inwards if < 0) by about grow.
# ---------------------------------------------------------------------------------------------

def _convex(o, d, n, dd):
    num = dd[None, :] - o @ n.T            # (N,P)
    den = d @ n.T
    with np.errstate(divide="ignore", invalid="ignore"):
        tp = num / den
    entering = den < 0
    exiting = den > 0
    blocked = np.any((den == 0) & (num < 0), axis=1)
    te = np.where(entering, tp, -INF)
    tx = np.where(exiting, tp, INF)
    ie = np.argmax(te, 1)
    ix = np.argmin(tx, 1)
    rows = np.arange(len(o))
    t0 = te[rows, ie]
    t1 = tx[rows, ix]
    if te.shape[1] > 1:
        se = np.sort(te, 1)[:, -2]
        sx = np.sort(tx, 1)[:, 1]
    else:
        se = np.full(len(o), -INF)
        sx = np.full(len(o), INF)
    with np.errstate(invalid="ignore"):
        m0 = t0 - se
        m1 = sx - t1
    hit = ~blocked & (t0 <= t1) & np.isfinite(t0) & np.isfinite(t1)
    return hit, t0, t1, n[ie], n[ix], m0, m1


def _sphere(o, d, r):
    a = np.einsum("ij,ij->i", d, d)
    b = np.einsum("ij,ij->i", o, d)
    cr = np.cross(o, d)
    disc = a * r * r - np.einsum("ij,ij->i", cr, cr)   # = b^2 - a(|o|^2 - r^2), accurately
    c = np.einsum("ij,ij->i", o, o) - r * r
    hit = disc >= 0
    sq = np.sqrt(np.where(hit, disc, 0.0))
    q = -(b + np.copysign(sq, b))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(q != 0, q / a, 0.0)
        r2 = np.where(q != 0, c / q, 0.0)
    t0 = np.minimum(r1, r2)
    t1 = np.maximum(r1, r2)
    p0 = o + t0[:, None] * d
    p1 = o + t1[:, None] * d
    inf = np.full(len(o), INF)
    return hit, t0, t1, p0, p1, inf, inf


def _cone(o, d, r0, k, zlo, zhi):
    """Solid zlo <= z <= zhi, rho <= r0 + k z (r0 + k z >= 0 on the slab)."""
    ox, oy, oz = o.T
    dx, dy, dz = d.T
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (zlo - oz) / dz
        tb = (zhi - oz) / dz
    in_slab = (oz >= zlo) & (oz <= zhi)
    s_in = np.where(dz != 0, np.minimum(ta, tb), np.where(in_slab, -INF, INF))
    s_out = np.where(dz != 0, np.maximum(ta, tb), np.where(in_slab, INF, -INF))
    # Quadric Q(t) = A t^2 + 2 B t + C <= 0.
    rz = r0 + k * oz
    A = dx * dx + dy * dy - k * k * dz * dz
    B = ox * dx + oy * dy - k * rz * dz
    C = ox * ox + oy * oy - rz * rz
    disc = B * B - A * C
    sq = np.sqrt(np.maximum(disc, 0.0))
    q = -(B + np.copysign(sq, B))
    with np.errstate(divide="ignore", invalid="ignore"):
        ra = np.where(q != 0, q / A, 0.0)
        rb = np.where(q != 0, C / q, 0.0)
        lin = -C / (2 * B)
    lo_r = np.minimum(ra, rb)
    hi_r = np.maximum(ra, rb)
    # Up to two pieces [l1, h1], [l2, h2] of {Q <= 0}; empty pieces are (inf, -inf).
    pos = (A > 0) & (disc >= 0)              # one bounded piece
    negr = (A < 0) & (disc >= 0)             # two half-lines
    nega = (A < 0) & (disc < 0)              # everything
    zero = A == 0                            # linear: 2 B t + C <= 0
    up, down = zero & (B > 0), zero & (B < 0)
    allz = zero & (B == 0) & (C <= 0)
    l1 = np.select([pos, negr | nega | up | allz, down], [lo_r, -INF, lin], INF)
    h1 = np.select([pos, negr, nega | down | allz, up], [hi_r, lo_r, INF, lin], -INF)
    l2 = np.where(negr, hi_r, INF)
    h2 = np.where(negr, INF, -INF)
    # Intersect with the slab; keep the longer piece (the solid is convex).
    a0, a1 = np.maximum(l1, s_in), np.minimum(h1, s_out)
    b0, b1 = np.maximum(l2, s_in), np.minimum(h2, s_out)
    with np.errstate(invalid="ignore"):
        la = np.where(a1 >= a0, a1 - a0, -1.0)
        lb = np.where(b1 >= b0, b1 - b0, -1.0)
    use_b = lb > la
    t0 = np.where(use_b, b0, a0)
    t1 = np.where(use_b, b1, a1)
    side_lo = np.where(use_b, l2, l1)
    side_hi = np.where(use_b, h2, h1)
    hit = np.maximum(la, lb) >= 0
    t0 = np.where(hit, t0, INF)
    t1 = np.where(hit, t1, INF)

    def side_normal(t):
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        return np.stack([p[:, 0], p[:, 1], -k * (r0 + k * p[:, 2])], 1)

    cap0 = side_lo <= s_in          # the entry lies on a cap
    cap1 = side_hi >= s_out
    sgn = np.sign(dz)
    n0 = np.where(cap0[:, None], np.stack([0 * sgn, 0 * sgn, -sgn], 1), side_normal(t0))
    n1 = np.where(cap1[:, None], np.stack([0 * sgn, 0 * sgn, sgn], 1), side_normal(t1))
    with np.errstate(invalid="ignore"):
        m0 = np.abs(side_lo - s_in)
        m1 = np.abs(side_hi - s_out)
    m0 = np.where(np.isfinite(m0), m0, INF)
    m1 = np.where(np.isfinite(m1), m1, INF)
    return hit, t0, t1, n0, n1, m0, m1


def _torus_g(p, R, r):
    rho = np.hypot(p[..., 0], p[..., 1])
    return (rho - R) ** 2 + p[..., 2] ** 2 - r * r


def _torus_grad(p, R):
    rho = np.hypot(p[..., 0], p[..., 1])
    f = np.where(rho > 0, (rho - R) / np.where(rho > 0, rho, 1.0), 0.0)
    return np.stack([f * p[..., 0], f * p[..., 1], p[..., 2]], -1)


def _torus(o, d, R, r):
    """Up to two raw intervals: (N,2) t0, t1 and normals (N,2,3)."""
    n = len(o)
    os_, ds = o / R, d / R            # major radius 1; t unchanged
    rr = r / R
    dn = np.linalg.norm(ds, axis=1)
    u = ds / dn[:, None]
    s0 = -np.einsum("ij,ij->i", os_, u)
    c = os_ + s0[:, None] * u
    e = np.einsum("ij,ij->i", c, u)
    K = np.einsum("ij,ij->i", c, c) + 1.0 - rr * rr
    uxy = u[:, 0] ** 2 + u[:, 1] ** 2
    cu = c[:, 0] * u[:, 0] + c[:, 1] * u[:, 1]
    cxy = c[:, 0] ** 2 + c[:, 1] ** 2
    a3 = 4 * e
    a2 = 4 * e * e + 2 * K - 4 * uxy
    a1 = 4 * e * K - 8 * cu
    a0 = K * K - 4 * cxy
    comp = np.zeros((n, 4, 4))
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    comp[:, :, 3] = -np.stack([a0, a1, a2, a3], 1)
    roots = np.linalg.eigvals(comp) if n else np.zeros((0, 4), complex)
    re, im = roots.real, roots.imag
    s = np.where(np.abs(im) <= 1e-4 * (1.0 + np.abs(re)), re, np.nan)
    coef = (a3[:, None], a2[:, None], a1[:, None], a0[:, None])

    def poly(x):
        f = x + coef[0]
        fp = np.ones_like(x)
        for cc in coef[1:]:
            fp = fp * x + f
            f = f * x + cc
        return f, fp

    for _ in range(6):   # safeguarded Newton polishing
        f, fp = poly(s)
        with np.errstate(divide="ignore", invalid="ignore"):
            s_new = s - f / fp
        f_new, _ = poly(s_new)
        ok = np.isfinite(s_new) & (np.abs(f_new) <= np.abs(f))
        s = np.where(ok, s_new, s)
    s = np.sort(np.where(np.isnan(s), INF, s), axis=1)   # (N,4), inf last
    fin = np.isfinite(s)
    # Inside test on each segment between consecutive boundaries, with the geometric form.
    state = np.zeros((n, 4), bool)
    for j in range(3):
        seg = fin[:, j] & fin[:, j + 1]
        mid = np.where(seg, 0.5 * (s[:, j] + np.where(seg, s[:, j + 1], 0.0)), 0.0)
        p = c + mid[:, None] * u
        state[:, j] = seg & (_torus_g(p, 1.0, rr) < 0)
    t = np.where(fin, (s0[:, None] + s) / dn[:, None], INF)
    pts = c[:, None, :] + np.where(fin, s, 0.0)[..., None] * u[:, None, :]
    nrm = _torus_grad(pts, 1.0)
    return _extract(t, state, np.zeros((n, 4), np.int64), nrm, np.full((n, 4), INF))


def _quadric_coefficients(prim, g=0.0):
    """(a, b, c, h) of a paraboloid or hyperboloid: rho^2 <= a z^2 + b z + c, |z| <= h, in
    its own frame; `g` widens it by g at its widest circle and lengthens it by g at each end."""
    h = 0.5 * prim.height
    if isinstance(prim, Paraboloid):
        rb, rt = prim.radius_bottom, prim.radius_top
        a, b, c = 0.0, (rt * rt - rb * rb) / prim.height, 0.5 * (rt * rt + rb * rb)
        widest = max(rb, rt)
    else:
        a, b, c = (prim.radius_end ** 2 - prim.radius ** 2) / (h * h), 0.0, prim.radius ** 2
        widest = prim.radius_end
    s = max(widest + g, 1e-9 * widest) / widest
    return a * s * s, b * s * s, c * s * s, max(h + g, 1e-9 * h)


def _quadric(o, d, a, b, c, h):
    """Intervals of rho^2 <= a z^2 + b z + c, |z| <= h: every candidate boundary (two roots of
    the side, two cap planes) sorted, and each piece between two of them classified by its
    midpoint. Margins: the distance to the nearest other candidate."""
    n = len(o)
    ox, oy, oz = o.T
    dx, dy, dz = d.T
    A = dx * dx + dy * dy - a * dz * dz
    B = ox * dx + oy * dy - a * oz * dz - 0.5 * b * dz
    C = ox * ox + oy * oy - a * oz * oz - b * oz - c
    disc = B * B - A * C
    sq = np.sqrt(np.maximum(disc, 0.0))
    q = -(B + np.copysign(sq, B))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where((A != 0) & (disc >= 0), q / A, np.where((A == 0) & (B != 0), -C / (2 * B), INF))
        r2 = np.where((A != 0) & (disc > 0) & (q != 0), C / q, INF)
        p1, p2 = (-h - oz) / dz, (h - oz) / dz
    cand = np.stack([r1, r2, p1, p2], 1)
    cand = np.where(np.isfinite(cand), cand, INF)
    kind = np.tile(np.array([0, 0, 1, 2]), (n, 1))         # side, bottom, top
    order = np.argsort(cand, axis=1)
    t = np.take_along_axis(cand, order, 1)
    kind = np.take_along_axis(kind, order, 1)
    fin = np.isfinite(t)

    def inside_at(s):
        p = o + s[:, None] * d
        return (np.abs(p[:, 2]) <= h) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= a * p[:, 2] ** 2 + b * p[:, 2] + c)

    state = np.zeros((n, 4), bool)
    for j in range(3):
        seg = fin[:, j] & fin[:, j + 1]
        mid = np.where(seg, 0.5 * (t[:, j] + np.where(seg, t[:, j + 1], 0.0)), 0.0)
        state[:, j] = seg & inside_at(mid)
    p = o[:, None, :] + np.where(fin, t, 0.0)[..., None] * d[:, None, :]
    side = np.stack([p[..., 0], p[..., 1], -a * p[..., 2] - 0.5 * b], -1)
    cap = np.zeros_like(side)
    cap[..., 2] = np.where(kind == 1, -1.0, 1.0)
    normal = np.where((kind == 0)[..., None], side, cap)
    with np.errstate(invalid="ignore"):
        gaps = np.abs(t[:, :, None] - t[:, None, :]) + np.where(np.eye(4, dtype=bool), INF, 0.0)[None]
        margin = np.where(fin, np.nanmin(np.where(np.isnan(gaps), INF, gaps), axis=2), INF)
    return _extract(np.where(fin, t, INF), state, np.zeros((n, 4), np.int64), normal, margin)


def _mesh_grown(prim, g):
    """The mesh's vertices moved by g along their (area-weighted) vertex normals."""
    v, f = np.asarray(prim.vertices, dtype=np.float64), np.asarray(prim.faces)
    if not g:
        return v
    face_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], face_n)
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    return v + g * vn


def _mesh_crossings(o, d, v, f):
    """Per ray and triangle (Moeller-Trumbore, float64, edges inclusive): t (inf where the
    ray misses the triangle), unit outward normals, and the t distance to the nearest edge."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    n = np.cross(e1, e2)
    area2 = np.linalg.norm(n, axis=1)
    longest = np.max(np.stack([np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1),
                               np.linalg.norm(c - b, axis=1)]), axis=0)
    p = np.cross(d[:, None, :], e2[None])                      # (N, T, 3)
    det = np.einsum("tk,ntk->nt", e1, p)
    s = o[:, None, :] - a[None]
    q = np.cross(s, e1[None])
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.einsum("ntk,ntk->nt", s, p) / det
        w = np.einsum("nk,ntk->nt", d, q) / det
        t = np.einsum("tk,ntk->nt", e2, q) / det
    hit = (det != 0) & (u >= 0) & (w >= 0) & (u + w <= 1)
    t = np.where(hit, t, INF)
    bary = np.minimum(np.minimum(u, w), 1.0 - u - w)
    margin = np.where(hit, bary * (area2 / longest)[None] / np.linalg.norm(d, axis=1)[:, None], INF)
    return t, n / area2[:, None], margin


def _mesh(o, d, prim, grow):
    """Intervals of a closed mesh: state after each crossing from the side it is crossed from."""
    v = _mesh_grown(prim, grow)
    t, n, margin = _mesh_crossings(o, d, v, np.asarray(prim.faces))
    order = np.argsort(t, axis=1)
    t = np.take_along_axis(t, order, 1)
    normal = n[order]
    margin = np.take_along_axis(margin, order, 1)
    inside = np.einsum("ntk,nk->nt", normal, d) < 0
    # An edge or vertex crossing is seen by several triangles at (nearly) one t: one event.
    with np.errstate(invalid="ignore"):
        repeat = np.zeros_like(inside)
        repeat[:, 1:] = (np.abs(np.diff(t, axis=1)) <= 1e-12 * np.maximum(1.0, np.abs(t[:, 1:]))) & \
            (inside[:, 1:] == inside[:, :-1])
    t = np.where(repeat, INF, t)
    order = np.argsort(t, axis=1)
    t, normal = np.take_along_axis(t, order, 1), normal[np.arange(len(o))[:, None], order]
    inside, margin = np.take_along_axis(inside, order, 1), np.take_along_axis(margin, order, 1)
    inside = inside & np.isfinite(t)
    return _extract(t, inside, np.zeros(t.shape, np.int64), normal, margin)


def _leaf_raw(prim, world, index, o, d, grow=0.0):
    """Raw (unregularized) world-frame intervals of one primitive. grow is in world units."""
    n = len(o)
    winv = np.linalg.inv(world)
    lin_inv = winv[:3, :3]
    ol = o @ lin_inv.T + winv[:3, 3]
    dl = d @ lin_inv.T
    g = grow * np.linalg.norm(lin_inv, 2) if grow else 0.0
    if isinstance(prim, Torus):
        minor = max(prim.minor_radius + g, 1e-9 * prim.minor_radius)
        L = _torus(ol, dl, prim.major_radius, minor)
    elif isinstance(prim, Mesh):
        L = _mesh(ol, dl, prim, g)
    elif isinstance(prim, (Paraboloid, Hyperboloid)):
        L = _quadric(ol, dl, *_quadric_coefficients(prim, g))
    else:
        if isinstance(prim, Sphere):
            hit, t0, t1, n0, n1, m0, m1 = _sphere(ol, dl, max(prim.radius + g, 0.0))
        elif isinstance(prim, Cone):
            rb, rt, h = prim.radius_bottom, prim.radius_top, prim.height
            k = (rt - rb) / h
            r0 = 0.5 * (rb + rt)
            r0g = r0 + g * np.hypot(1.0, k)
            zlo, zhi = -0.5 * h - g, 0.5 * h + g
            # Keep the radius non-negative on the slab (matters when shrinking a pointed cone).
            if r0g + k * zlo < 0:
                zlo = -r0g / k
            if r0g + k * zhi < 0:
                zhi = -r0g / k
            hit, t0, t1, n0, n1, m0, m1 = _cone(ol, dl, r0g, k, zlo, zhi)
        else:
            nn, dd = _planes_of(prim)
            hit, t0, t1, n0, n1, m0, m1 = _convex(ol, dl, nn, dd + g)
        L = _empty(n, 1)
        L.t[:, 0, 0] = np.where(hit, t0, INF)
        L.t[:, 0, 1] = np.where(hit, t1, INF)
        L.normal[:, 0, 0] = n0
        L.normal[:, 0, 1] = n1
        L.margin[:, 0, 0] = m0
        L.margin[:, 0, 1] = m1
    valid = np.isfinite(L.t)
    L.prim = np.where(valid, index, -1).astype(np.int64)
    # Local normals to world: inverse transpose of the linear part, then normalize.
    nw = L.normal @ lin_inv
    norm = np.linalg.norm(nw, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        nw = np.where(norm > 0, nw / np.where(norm > 0, norm, 1.0), 0.0)
    L.normal = np.where(valid[..., None], nw, 0.0)
    L.margin = np.where(valid, L.margin, INF)
    return L


# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------

def _rays(origins, directions):
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if o.shape != d.shape:
        raise ValueError(f"origins {o.shape} and directions {d.shape} differ")
    return o, d


def _time_scale(o, d):
    """Per ray: a length scale over |d| (t units), for relative tolerances."""
    length = np.maximum(1.0, np.linalg.norm(o, axis=1))
    return length / np.linalg.norm(d, axis=1)


def _trace(model, o, d, keep_raw=False, grow=0.0):
    tscale = _time_scale(o, d)
    raws = []

    def leaf(prim, world, index):
        raw = _leaf_raw(prim, world, index, o, d, grow)
        if keep_raw:
            raws.append(raw)
        return _regularize(raw, tscale)

    def op(kind, vals):
        return _regularize(_combine(kind, vals), tscale)

    return _postorder(model, leaf, op), raws


def interval_arrays(model, origins, directions) -> Intervals:
    """The regularized interval lists as padded arrays (see `Intervals`)."""
    o, d = _rays(origins, directions)
    return _trace(model, o, d)[0]


def intervals(model, origins, directions):
    """Per ray, the sorted list of (t_enter, t_exit, prim_enter, prim_exit) inside the solid."""
    L = interval_arrays(model, origins, directions)
    out = []
    for i in range(L.t.shape[0]):
        row = []
        for k in range(L.t.shape[1]):
            if not np.isfinite(L.t[i, k, 0]):
                break
            row.append((float(L.t[i, k, 0]), float(L.t[i, k, 1]),
                        int(L.prim[i, k, 0]), int(L.prim[i, k, 1])))
        out.append(row)
    return out


def _first(L, tmin, tmax):
    n, k = L.t.shape[:2]
    t = L.t.reshape(n, 2 * k)
    tmin = np.broadcast_to(np.asarray(tmin, dtype=np.float64), (n,))
    tmax = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (n,))
    cand = np.where(t > tmin[:, None], t, INF)
    idx = np.argmin(cand, 1)
    rows = np.arange(n)
    tb = cand[rows, idx]
    hit = np.isfinite(tb) & (tb <= tmax)
    prim = np.where(hit, L.prim.reshape(n, 2 * k)[rows, idx], -1)
    normal = np.where(hit[:, None], L.normal.reshape(n, 2 * k, 3)[rows, idx], 0.0)
    entering = hit & (idx % 2 == 0)
    return np.where(hit, tb, INF), prim.astype(np.int64), normal, entering


def first_hit(model, origins, directions, tmin=0.0, tmax=INF):
    """First boundary of the solid with tmin < t <= tmax.

    Returns (t (N,) float64, inf on miss; prim (N,) int64, -1 on miss; normal (N,3) outward
    unit normal of the CSG solid, zeros on miss; entering (N,) bool, True when the ray enters
    the solid there). tmin/tmax may be scalars or (N,) arrays.
    """
    o, d = _rays(origins, directions)
    L = _trace(model, o, d)[0]
    return _first(L, tmin, tmax)


def _contains_leaf(prim, world, p):
    winv = np.linalg.inv(world)
    q = p @ winv[:3, :3].T + winv[:3, 3]
    x, y, z = q.T
    if isinstance(prim, Sphere):
        return x * x + y * y + z * z <= prim.radius ** 2
    if isinstance(prim, Torus):
        return (np.hypot(x, y) - prim.major_radius) ** 2 + z * z <= prim.minor_radius ** 2
    if isinstance(prim, Cone):
        h = prim.height
        rz = prim.radius_bottom + (prim.radius_top - prim.radius_bottom) * (z / h + 0.5)
        return (np.abs(z) <= 0.5 * h) & (np.hypot(x, y) <= rz)
    if isinstance(prim, (Paraboloid, Hyperboloid)):
        a, b, c, h = _quadric_coefficients(prim)
        return (np.abs(z) <= h) & (x * x + y * y <= a * z * z + b * z + c)
    if isinstance(prim, Box):
        hs = 0.5 * np.asarray(prim.size)
        return np.all(np.abs(q) <= hs, axis=1)
    if isinstance(prim, Mesh):
        # Parity of the crossings of a ray in a fixed, generic direction.
        ray = np.broadcast_to(np.array([0.5214, 0.3331, 0.7856]), q.shape)
        t, _, _ = _mesh_crossings(q, ray, np.asarray(prim.vertices, dtype=np.float64), np.asarray(prim.faces))
        return np.sum(np.isfinite(t) & (t > 0), axis=1) % 2 == 1
    nn, dd = _planes_of(prim)
    return np.all(q @ nn.T <= dd, axis=1)


def contains(model, points):
    """(N,) bool: the points inside the (closed) solid, by direct classification."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)

    def op(kind, vals):
        if kind == "union":
            return np.logical_or.reduce(vals)
        if kind == "intersection":
            return np.logical_and.reduce(vals)
        rest = np.logical_or.reduce(vals[1:]) if len(vals) > 1 else np.zeros(len(p), bool)
        return vals[0] & ~rest

    return _postorder(model, lambda prim, world, index: _contains_leaf(prim, world, p), op)


def stable_mask(model, origins, directions, tmin=0.0, tmax=INF, *, sep=1e-5, cos_min=1e-2,
                jitter=1e-6, trials=2, seed=0, return_reasons=False, same=0.0):
    """(N,) bool: rays whose first hit (or miss) is well-conditioned.

    Distances are relative to L = max(1, |origin|) per ray. A ray is unstable when, among the
    raw primitive boundaries with tmin - sep*L <= t*|d| <= t_hit + sep*L (t_hit = the first
    hit, or tmax on a miss):
      * a boundary grazes (|n . d|/|d| < cos_min) or lies within sep*L of an edge/apex of its
        primitive, or two boundaries (of any primitives) lie within sep*L of each other (or
        within twice the kernel's tie window for their slope, where events are one by design),
        or one lies within sep*L of tmin;
      * a primitive's silhouette passes within sep*L of the ray there (the primitive grown and
        shrunk by sep*L has different interval counts);
    or when the first boundary after tmin lies within sep*L of tmax, or when `trials` rays
    jittered by jitter*L disagree on hit/miss, prim, t (> sep*L) or normal (dot < 0.9).
    With return_reasons=True, also returns a dict of the individual (N,) failure masks.
    Boundaries within same*L of each other are one (coincident faces, which the kernel must
    answer as one surface), not a reason to call the ray unstable.
    """
    o, d = _rays(origins, directions)
    n = len(o)
    if n == 0:
        empty = np.zeros(0, bool)
        return (empty, {}) if return_reasons else empty
    dlen = np.linalg.norm(d, axis=1)
    length = np.maximum(1.0, np.linalg.norm(o, axis=1))
    sep_t = sep * length / dlen
    tmin_a = np.broadcast_to(np.asarray(tmin, dtype=np.float64), (n,))
    tmax_a = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (n,))
    final, raws = _trace(model, o, d, keep_raw=True)
    t_hit, prim, normal, _ = _first(final, tmin_a, tmax_a)
    t_free = _first(final, tmin_a, INF)[0]
    t_end = np.minimum(t_hit, tmax_a)
    lo = tmin_a - sep_t
    hi = t_end + sep_t

    rt = np.concatenate([r.t.reshape(n, -1) for r in raws], 1)
    rn = np.concatenate([r.normal.reshape(n, -1, 3) for r in raws], 1)
    rm = np.concatenate([r.margin.reshape(n, -1) for r in raws], 1)
    with np.errstate(invalid="ignore"):
        win = np.isfinite(rt) & (rt >= lo[:, None]) & (rt <= hi[:, None])
    cosang = np.abs(np.einsum("nkj,nj->nk", rn, d)) / dlen[:, None]
    reasons = {}
    reasons["grazing"] = np.any(win & (cosang < cos_min), 1)
    reasons["edge"] = np.any(win & (rm <= sep_t[:, None]), 1)
    reasons["near_tmin"] = np.any(win & (np.abs(rt - tmin_a[:, None]) <= sep_t[:, None]), 1)
    order = np.argsort(np.where(win, rt, INF), 1)
    ts = np.take_along_axis(np.where(win, rt, INF), order, 1)
    cos_sorted = np.take_along_axis(cosang, order, 1)
    tie_t = _KERNEL_TIE * (_extent(model) + np.abs(o).max(axis=1)) / dlen
    with np.errstate(invalid="ignore", divide="ignore"):
        gaps = np.diff(ts, axis=1)
        # Twice the window of the steeper event of each neighbouring pair (the kernel takes that one).
        window = 4.0 * tie_t[:, None] / np.maximum(np.maximum(cos_sorted[:, 1:], cos_sorted[:, :-1]), 2.0 ** -10)
        close = gaps <= np.maximum(sep_t[:, None], window)
        if same > 0:
            close &= gaps > (same * length / dlen)[:, None]
    reasons["close_boundaries"] = np.any(np.isfinite(ts[:, 1:]) & close, 1)
    with np.errstate(invalid="ignore"):
        reasons["near_tmax"] = np.isfinite(t_free) & (np.abs(t_free - tmax_a) <= sep_t)

    # Silhouettes: grow and shrink every primitive by sep*L (world units, per ray -> use max).
    g = sep * float(length.max(initial=1.0))
    sil = np.zeros(n, bool)
    for (prim_obj, world), idx in zip(leaf_list(model), range(len(raws))):
        big = _leaf_raw(prim_obj, world, idx, o, d, +g)
        small = _leaf_raw(prim_obj, world, idx, o, d, -g)
        differ = big.count != small.count
        bt = big.t.reshape(n, -1)
        with np.errstate(invalid="ignore"):
            near = np.any(np.isfinite(bt) & (bt >= lo[:, None]) & (bt <= hi[:, None]), 1)
        sil |= differ & near
    reasons["silhouette"] = sil

    rng = np.random.default_rng(seed)
    pert = np.zeros(n, bool)
    for _ in range(trials):
        jo = rng.normal(size=(n, 3))
        jo *= (jitter * length / np.linalg.norm(jo, axis=1))[:, None]
        jd = rng.normal(size=(n, 3))
        jd *= (jitter * dlen / np.linalg.norm(jd, axis=1))[:, None]
        t2, p2, n2, _ = _first(_trace(model, o + jo, d + jd)[0], tmin_a, tmax_a)
        h1, h2 = np.isfinite(t_hit), np.isfinite(t2)
        bad = (h1 != h2)
        both = h1 & h2
        with np.errstate(invalid="ignore"):
            bad |= both & ((p2 != prim) | (np.abs(t2 - t_hit) > sep_t)
                           | (np.einsum("ij,ij->i", n2, normal) < 0.9))
        pert |= bad
    reasons["perturbation"] = pert

    unstable = np.zeros(n, bool)
    for v in reasons.values():
        unstable |= v
    if return_reasons:
        return ~unstable, reasons
    return ~unstable


stable = stable_mask
