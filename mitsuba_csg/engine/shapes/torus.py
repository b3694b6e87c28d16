"""The canonical torus: major radius 1 about z, minor radius param[0]. Face 0.

Root isolation by derivatives, then safeguarded Newton on each bracket: the quartic in
float32 has false roots otherwise."""
from __future__ import annotations

import drjit as dr
import numpy as np

from ..layout import MISS, TORUS
from .row import Shape, disc_support


# Newton-bisection steps per bracketed root of the torus quartic (and its derivative).
_TORUS_STEPS = 16


def _poly(coeffs, x):
    acc = coeffs[0]
    for c in coeffs[1:]:
        acc = dr.fma(acc, x, c)
    return acc


def _newton_step(f, df, x, lo, hi, lo_neg, done):
    """One safeguarded Newton step on a bracket [lo, hi] of a monotone polynomial; a lane
    that is done keeps its x."""
    fx = _poly(f, x)
    same_as_lo = (fx <= 0) == lo_neg
    lo = dr.select(same_as_lo, x, lo)
    hi = dr.select(same_as_lo, hi, x)
    step = x - fx / _poly(df, x)
    x_next = dr.select((step > lo) & (step < hi), step, 0.5 * (lo + hi))
    done = done | (fx == 0) | (dr.abs(x_next - x) <= 2e-7 * (dr.abs(x) + 1e-3))
    return dr.select(done, x, x_next), lo, hi, done


@dr.syntax
def _bracketed_roots(b, f, df, brackets, valid):
    """[(x, has_root)] of a monotone polynomial on each bracket (lo, hi) whose ends differ in
    sign; (midpoint, False) where they do not.

    Newton steps inside the bracket, bisection otherwise. Once a Newton step no longer moves
    x, x is frozen: at the float32 noise floor the sign of f is noise, and following it
    would walk the bracket away from the root. All brackets step together in one loop that
    ends when every lane's roots are frozen (at most _TORUS_STEPS steps; most converge in a
    few), so a packet whose lanes miss the torus, or converge early, does not pay for 16.
    """
    has_roots, negs, xs, los, his, dones = [], [], [], [], [], []
    for lo, hi in brackets:
        f_lo, f_hi = _poly(f, lo), _poly(f, hi)
        has_root = valid & (lo < hi) & ((f_lo <= 0) != (f_hi <= 0))
        has_roots.append(has_root)
        negs.append(f_lo <= 0)
        xs.append(0.5 * (lo + hi))
        los.append(b.Float(lo))
        his.append(b.Float(hi))
        dones.append(~has_root)
    steps = dr.zeros(b.UInt32, dr.width(valid))
    while dr.hint(_pending(dones) & (steps < _TORUS_STEPS), label="csg_torus_newton", exclude=[f, df, negs]):
        stepped = [_newton_step(f, df, *state) for state in zip(xs, los, his, negs, dones)]
        xs = [state[0] for state in stepped]
        los = [state[1] for state in stepped]
        his = [state[2] for state in stepped]
        dones = [state[3] for state in stepped]
        steps += 1
    return list(zip(xs, has_roots))


def _pending(dones):
    pending = ~dones[0]
    for done in dones[1:]:
        pending |= ~done
    return pending


def _events(b, o, d, param):
    """The up-to-four sorted boundary events of the canonical torus (major 1, minor param[0])."""
    k = param[0]
    width = dr.width(k)
    inv_len = dr.rsqrt(dr.squared_norm(d))
    dn = d * inv_len
    t0 = -dr.dot(o, dn) * inv_len          # ray parameter closest to the torus centre
    oc = o + t0 * d
    m = dr.squared_norm(oc)
    reach2 = (1.0 + k) * (1.0 + k) - m
    reach = dr.sqrt(dr.maximum(reach2, 0.0)) * 1.001 + 1e-3   # ends strictly outside the torus
    # The torus lies in the slab |z| <= k: a ray that crosses the bounding sphere outside it
    # has no root, and its lanes skip the root search (`_bracketed_roots`).
    slab = k * 1.001 + 1e-3
    z_lo, z_hi = (-slab - oc.z) / dn.z, (slab - oc.z) / dn.z
    in_slab = dr.select(dn.z == 0, dr.abs(oc.z) <= slab,
                        (dr.maximum(z_lo, z_hi) >= -reach) & (dr.minimum(z_lo, z_hi) <= reach))
    valid = (reach2 > 0) & in_slab
    bb = dr.dot(oc, dn)
    e = m + 1.0 - k * k
    u = dn.x * dn.x + dn.y * dn.y
    v = oc.x * dn.x + oc.y * dn.y
    w0 = oc.x * oc.x + oc.y * oc.y
    one = dr.full(b.Float, 1.0, width)
    f = [one, 4.0 * bb, 4.0 * bb * bb + 2.0 * e - 4.0 * u, 4.0 * bb * e - 8.0 * v, e * e - 4.0 * w0]
    df = [4.0 * one, 3.0 * f[1], 2.0 * f[2], f[3]]
    ddf = [12.0 * one, 6.0 * f[1], 2.0 * f[2]]
    # f'' roots (quadratic, monic up to 12): split [-reach, reach] into monotone pieces of f'.
    disc = ddf[1] * ddf[1] - 4.0 * ddf[0] * ddf[2]
    sq = dr.sqrt(dr.maximum(disc, 0.0))
    s1 = dr.clip((-ddf[1] - sq) / (2.0 * ddf[0]), -reach, reach)
    s2 = dr.clip((-ddf[1] + sq) / (2.0 * ddf[0]), -reach, reach)
    s1 = dr.select(disc > 0, s1, -reach)
    s2 = dr.select(disc > 0, s2, -reach)
    # f' roots: split points of f (a missing root leaves a harmless empty piece).
    pieces = ((-reach, s1), (s1, s2), (s2, reach))
    splits = [dr.select(ok, x, lo) for (x, ok), (lo, _) in zip(_bracketed_roots(b, df, ddf, pieces, valid), pieces)]
    ends = [-reach, *splits, reach]
    pieces = [(lo, dr.maximum(lo, hi)) for lo, hi in zip(ends[:-1], ends[1:])]
    events, oks = [], []
    for (x, ok), (lo, hi) in zip(_bracketed_roots(b, f, df, pieces, valid), pieces):
        # One Newton step on the geometric form (rho - 1)^2 + z^2 - k^2, which float32
        # evaluates without the quartic's cancellation (its roots were off by ~1e-5 of the
        # distance), kept inside the root's bracket so that the roots stay in order.
        p = oc + x * dn
        rho = dr.sqrt(p.x * p.x + p.y * p.y)
        g = (rho - 1.0) * (rho - 1.0) + p.z * p.z - k * k
        dg = 2.0 * (rho - 1.0) * (p.x * dn.x + p.y * dn.y) / rho + 2.0 * p.z * dn.z
        x = dr.select((dg != 0) & (rho > 0), dr.clip(x - g / dg, lo, hi), x)
        events.append(t0 + x * inv_len)
        oks.append(ok)
    return events, oks


def event(b, o, d, param, plane_buf, start, mesh, t_start):
    """(t, face, class) of the first root after t_start; its parity among the roots is its class."""
    width = dr.width(t_start)
    t = dr.full(b.Float, dr.inf, width)
    cls = dr.full(b.UInt32, MISS, width)
    events, oks = _events(b, o, d, param)
    seen = dr.zeros(b.UInt32, width)
    found = dr.zeros(b.Bool, width)
    for ev, ok in zip(events, oks):
        take = ok & ~found & (ev > t_start)
        t = dr.select(take, ev, t)
        cls = dr.select(take, seen & 1, cls)
        found |= take
        seen += dr.select(ok, 1, 0)
    return t, dr.zeros(b.UInt32, width), cls


def surface(m, face, param, plane, x):
    k = param[0]                                       # major radius 1, minor k
    s = dr.squared_norm(x) + 1.0 - k * k
    return (s * s - 4.0 * (x.x * x.x + x.y * x.y),
            m.Array3f(4.0 * s * x.x - 8.0 * x.x, 4.0 * s * x.y - 8.0 * x.y, 4.0 * s * x.z))


def bounds(A, c, param, plane_start, plane_vertices):
    half = disc_support(A) + param[:, 0:1] * np.linalg.norm(A, axis=2)
    return c - half, c + half


def uv(hit):
    """The two angles: u = phi / 2 pi about the axis, v = psi / 2 pi about the tube."""
    b, x, param = hit.b, hit.x, hit.param
    phi = hit.phi()
    psi = dr.atan2(x.z, hit.rho() - 1.0)
    psi = dr.select(psi < 0, psi + 2.0 * dr.pi, psi)
    dv = 2.0 * dr.pi * param[0] * b.Array3f(-dr.sin(psi) * dr.cos(phi), -dr.sin(psi) * dr.sin(phi), dr.cos(psi))
    return b.module.Array2f(phi / (2.0 * dr.pi), psi / (2.0 * dr.pi)), hit.around(), dv


SHAPE = Shape(TORUS, "torus", convex=False, event=event, surface=surface, bounds=bounds, uv=uv)
