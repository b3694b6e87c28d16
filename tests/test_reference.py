"""Checks of the float64 test reference itself (tests/reference.py) against analytic answers,
point classification, Monte Carlo volumes and manifold3d meshes."""
from __future__ import annotations

import itertools
import math
import os
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import reference as ref  # noqa: E402
from strategies import aimed_rays, make_points, make_rays, models, seeds  # noqa: E402

from mitsuba_csg.model import difference, intersection, union  # noqa: E402
from mitsuba_csg.model.primitives import (Box, Cone, ConvexPolyhedron, Cylinder, Hyperboloid, Paraboloid, Prism, Sphere,  # noqa: E402
                                    Torus)

# The example count comes from the hypothesis profile (tests/conftest.py), when there is one.
FAST = settings(deadline=None, suppress_health_check=[HealthCheck.too_slow])
X = np.array([[1.0, 0.0, 0.0]])
Y = np.array([[0.0, 1.0, 0.0]])
Z = np.array([[0.0, 0.0, 1.0]])


def ivs(model, o, d):
    return ref.intervals(model, np.atleast_2d(o), np.atleast_2d(d))[0]


def assert_ivs(got, expected, prims=None, tol=1e-9):
    assert len(got) == len(expected), (got, expected)
    for g, e in zip(got, expected):
        assert g[0] == pytest.approx(e[0], abs=tol) and g[1] == pytest.approx(e[1], abs=tol), (got, expected)
    if prims is not None:
        assert [(g[2], g[3]) for g in got] == prims, got


def hit1(model, o, d, **kw):
    t, p, n, e = ref.first_hit(model, np.atleast_2d(o), np.atleast_2d(d), **kw)
    return t[0], p[0], n[0], e[0]


# ---------------------------------------------------------------------------------------------
# Primitives: analytic answers
# ---------------------------------------------------------------------------------------------

def test_sphere():
    s = Sphere(1.0)
    assert_ivs(ivs(s, [-5, 0, 0], [2, 0, 0]), [(2, 3)], [(0, 0)])
    t, p, n, e = hit1(s, [-5, 0, 0], [2, 0, 0])
    assert (t, p, e) == (2, 0, True) and np.allclose(n, [-1, 0, 0])
    t, p, n, e = hit1(s, [-5, 0, 0], [2, 0, 0], tmin=2.0)        # strictly after tmin
    assert (t, p, e) == (3, 0, False) and np.allclose(n, [1, 0, 0])
    t, p, n, e = hit1(s, [-5, 0, 0], [2, 0, 0], tmax=1.5)
    assert t == np.inf and p == -1 and not e
    assert_ivs(ivs(s, [-5, 0.6, 0], X), [(4.2, 5.8)])
    t, p, n, e = hit1(s, [-5, 0.6, 0], X)
    assert np.allclose(n, [-0.8, 0.6, 0])
    t, p, n, e = hit1(s, [0, 0, 0], [0, 0, -1])                  # from inside: an exit
    assert t == 1 and not e and np.allclose(n, [0, 0, -1])
    assert ivs(s, [-5, 1, 0], X) == []                           # exactly tangent: regularized away
    assert ivs(s, [-5, 1.01, 0], X) == []


def test_box_slabs():
    b = Box((2, 4, 6))
    assert_ivs(ivs(b, [0.3, -10, 0.2], Y), [(8, 12)])
    t, p, n, e = hit1(b, [0.3, -10, 0.2], Y)
    assert np.allclose(n, [0, -1, 0]) and e
    c = Box(2)
    assert_ivs(ivs(c, [-5, -4.5, -4], [1, 1, 1]), [(4, 5)])
    assert np.allclose(hit1(c, [-5, -4.5, -4], [1, 1, 1])[2], [-1, 0, 0])
    t, p, n, e = hit1(c, [-5, -4.5, -4], [1, 1, 1], tmin=4.5)
    assert t == pytest.approx(5) and np.allclose(n, [0, 0, 1]) and not e
    assert ivs(c, [-5, 2, 0], X) == []
    assert_ivs(ivs(c, [0.5, 0.5, 0.5], [0, 0, -0.5]), [(-1, 3)])


def test_cylinder():
    c = Cylinder(1.0, 2.0)
    assert_ivs(ivs(c, [0, 0, -5], Z), [(4, 6)])
    assert_ivs(ivs(c, [-5, 0, 0.5], X), [(4, 6)])
    assert_ivs(ivs(c, [-5, 0, 0], [1, 0, 0.2]), [(4, 5)])
    t, p, n, e = hit1(c, [-5, 0, 0], [1, 0, 0.2], tmin=4.5)
    assert np.allclose(n, [0, 0, 1]) and not e
    assert_ivs(ivs(c, [0, -5, 0], [0, 1, 0]), [(4, 6)])
    assert np.allclose(hit1(c, [0.6, -5, 0], Y)[2], [0.6, -0.8, 0])
    assert ivs(c, [0, 0, 1.5], X) == []


def test_cone_and_apex():
    c = Cone(1.0, 0.0, 2.0)                       # apex at z = +1
    assert_ivs(ivs(c, [0, 0, -5], Z), [(4, 6)])
    assert_ivs(ivs(c, [-5, 0, 0], X), [(4.5, 5.5)])
    assert np.allclose(hit1(c, [-5, 0, 0], X)[2], np.array([-2, 0, 1]) / math.sqrt(5))
    assert_ivs(ivs(c, [0, 0, 3], [0, 0, -1]), [(2, 4)])           # in through the apex
    assert ivs(c, [-5, 0, 1], X) == []                           # touches the apex only
    assert ivs(c, [-5, 0, 0.999], X) != []
    inv = Cone(0.0, 1.0, 2.0)                     # apex at z = -1
    assert_ivs(ivs(inv, [0, 0, -5], Z), [(4, 6)])
    assert_ivs(ivs(inv, [-5, 0, 0], X), [(4.5, 5.5)])
    assert np.allclose(hit1(inv, [-5, 0, 0], X)[2], np.array([-2, 0, -1]) / math.sqrt(5))
    frustum = Cone(1.0, 0.5, 2.0)
    assert_ivs(ivs(frustum, [-5, 0, 1], X), [(4.5, 5.5)])        # top cap edge radius 0.5
    assert_ivs(ivs(frustum, [-5, 0, 0], X), [(4.25, 5.75)])
    # A ray steeper than the side, crossing the other nappe of the double cone outside the slab.
    assert_ivs(ivs(c, [0.2, 0, -5], [0, 0, 1]), [(4, 5.6)])


def test_torus_along_axes():
    t = Torus(2.0, 0.5)
    assert_ivs(ivs(t, [0, 0, 0], X), [(-2.5, -1.5), (1.5, 2.5)])
    assert_ivs(ivs(t, [-5, 0, 0], X), [(2.5, 3.5), (6.5, 7.5)])
    assert_ivs(ivs(t, [0, -5, 0], Y), [(2.5, 3.5), (6.5, 7.5)])
    assert_ivs(ivs(t, [2, 0, -5], Z), [(4.5, 5.5)])
    assert ivs(t, [0, 0, -5], Z) == []
    a, b = math.sqrt(2.25 - 1.96), math.sqrt(6.25 - 1.96)
    assert_ivs(ivs(t, [-5, 1.4, 0], X), [(5 - b, 5 - a), (5 + a, 5 + b)])
    a, b = math.sqrt(2.25 - 1), math.sqrt(6.25 - 1)
    assert_ivs(ivs(t, [-5, 1, 0], [0.5, 0, 0]), [(2 * (5 - b), 2 * (5 - a)), (2 * (5 + a), 2 * (5 + b))])
    t_, p, n, e = hit1(t, [-5, 0, 0], X)
    assert np.allclose(n, [-1, 0, 0]) and e
    t_, p, n, e = hit1(t, [2, 0, -5], Z, tmin=5)
    assert t_ == pytest.approx(5.5) and np.allclose(n, [0, 0, 1]) and not e
    r = Torus(2.0, 0.5).rotate("x", 90)           # axis along y now
    assert ivs(r, [0, -5, 0], Y) == []
    assert_ivs(ivs(r, [0, 0, -5], Z), [(2.5, 3.5), (6.5, 7.5)])
    # A far-away, oblique ray: the quartic must not produce false roots.
    o = np.array([[-40.0, 3.0, 1.0]])
    d = np.array([[1.0, -3.0 / 40, -1.0 / 40 + 1e-3]])
    got = ivs(t, o, d)
    ts = np.linspace(0, 80, 200001)
    pts = o + ts[:, None] * d
    inside = ref.contains(t, pts)
    assert abs(inside.mean() * 80 - sum(b - a for a, b, *_ in got)) < 1e-3


def test_prisms_and_polyhedra():
    h = Prism(6, 1.0, 2.0)
    assert_ivs(ivs(h, [-5, 0, 0], X), [(4, 6)])
    assert_ivs(ivs(h, [0, -5, 0], Y), [(5 - 2 / math.sqrt(3), 5 + 2 / math.sqrt(3))])
    assert_ivs(ivs(h, [0.3, 0.2, -5], Z), [(4, 6)])
    tri = Prism(3, 1.0, 2.0)
    assert_ivs(ivs(tri, [5, 0, 0], [-1, 0, 0]), [(4, 7)])
    # Prism(4) is a box; a cube from unnormalized planes is a box too.
    o, d = make_rays(1, 300, radius=4.0, target=1.2)
    cube = ConvexPolyhedron([[2, 0, 0, 2], [-1, 0, 0, 1], [0, 3, 0, 3], [0, -1, 0, 1], [0, 0, 1, 1], [0, 0, -1, 1]])
    for m in (Prism(4, 1.0, 2.0), cube):
        a = ref.interval_arrays(m, o, d)
        b = ref.interval_arrays(Box(2.0), o, d)
        assert np.allclose(a.t, b.t, equal_nan=True)
        hit = np.isfinite(a.t)
        assert np.allclose(a.normal[hit], b.normal[hit], atol=1e-12)
    n = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) / math.sqrt(3)
    tet = ConvexPolyhedron(np.hstack([n, np.ones((4, 1))]))
    assert_ivs(ivs(tet, 5 * n[0], -n[0]), [(4, 8)])
    assert np.allclose(hit1(tet, 5 * n[0], -n[0])[2], n[0])


def test_transforms():
    e = Sphere(1.0).scale((2, 1, 1))
    assert_ivs(ivs(e, [-5, 0, 0], X), [(3, 7)])
    assert_ivs(ivs(e, [0, -5, 0], Y), [(4, 6)])
    t, p, n, _ = hit1(e, [-5, 0.5, 0], X)
    x = -math.sqrt(3)
    assert t == pytest.approx(5 + x)
    g = np.array([x / 4, 0.5, 0])
    assert np.allclose(n, g / np.linalg.norm(g))
    r = Box((4, 2, 2)).rotate("z", 90)
    assert_ivs(ivs(r, [0, -5, 0], Y), [(3, 7)])
    assert_ivs(ivs(r, [-5, 0, 0], X), [(4, 6)])
    c = Cone(1.0, 0.0, 2.0).rotate("x", 90)      # right-handed: +z goes to -y
    assert_ivs(ivs(c, [0, -5, 0], Y), [(4, 6)])
    t, p, n, e_ = hit1(c, [0, -5, 0], Y, tmin=5)
    assert np.allclose(n, [0, 1, 0]) and not e_
    m = Cone(1.0, 0.0, 2.0).scale((1, 1, -1))    # mirrored: apex at z = -1
    assert_ivs(ivs(m, [0.25, 0, -5], Z), [(4.5, 6)])
    t, p, n, e_ = hit1(m, [0.25, 0, -5], Z)
    g = np.array([0.25, 0, -0.125])
    assert np.allclose(n, g / np.linalg.norm(g)) and e_
    u = (Sphere(1.0) | Box(1.0)).translate((3, 0, 0))
    assert_ivs(ivs(u, [-5, 0, 0], X), [(7, 9)])
    s = union(Sphere(1.0), Sphere(1.0).translate((3, 0, 0))).scale(2).translate((0, 0, 1))
    assert_ivs(ivs(s, [-5, 0, 1], X), [(3, 7), (9, 13)], [(0, 0), (1, 1)])
    sh = np.eye(4)
    sh[0, 1] = 1.0                                # x' = x + y
    b = Box(2.0).transform(sh)
    assert_ivs(ivs(b, [-5, 0.5, 0], X), [(4.5, 6.5)])


def test_leaf_order_matches_model_leaves():
    m = difference(Box(4.0).rotate("z", 30),
                   union(Sphere(0.5).translate((1, 0, 0)), Torus(1.0, 0.2)).scale(1.5),
                   Cylinder(0.3, 5).rotate("x", 90) & Prism(5, 1, 1)).translate((0, 1, 0))
    mine = ref.leaf_list(m)
    theirs = m.leaves()
    assert [type(p) for p, _ in mine] == [type(p) for p in theirs]
    for (_, w), leaf in zip(mine, theirs):
        assert np.allclose(w, leaf.matrix)


# ---------------------------------------------------------------------------------------------
# Booleans: analytic answers
# ---------------------------------------------------------------------------------------------

A = Sphere(1.0).translate((-0.5, 0, 0))
B = Sphere(1.0).translate((0.5, 0, 0))
O5 = [-5, 0, 0]


def test_two_spheres():
    assert_ivs(ivs(A | B, O5, X), [(3.5, 6.5)], [(0, 1)])
    assert_ivs(ivs(A & B, O5, X), [(4.5, 5.5)], [(1, 0)])
    assert_ivs(ivs(A - B, O5, X), [(3.5, 4.5)], [(0, 1)])
    assert_ivs(ivs(B - A, O5, X), [(5.5, 6.5)], [(1, 0)])
    t, p, n, e = hit1(A - B, O5, X, tmin=4)
    assert (t, p, e) == (4.5, 1, False) and np.allclose(n, [1, 0, 0])
    t, p, n, e = hit1(B - A, O5, X)
    assert (t, p, e) == (5.5, 1, True) and np.allclose(n, [-1, 0, 0])   # leaves of B - A: B, A
    # Off-axis: the lens A & B and its normals.
    t, p, n, e = hit1(A & B, [-5, 0.3, 0], X)
    x = 0.5 - math.sqrt(1 - 0.09)
    assert t == pytest.approx(5 + x) and np.allclose(n, [x - 0.5, 0.3, 0])


def test_nested_and_nary():
    m = Box(4.0) - (Box(2.0) - Sphere(0.5))
    assert_ivs(ivs(m, O5, X), [(3, 4), (4.5, 5.5), (6, 7)], [(0, 1), (2, 2), (1, 0)])
    t, p, n, e = hit1(m, O5, X, tmin=4.2)
    assert (p, e) == (2, True) and np.allclose(n, [-1, 0, 0])      # flipped twice
    t, p, n, e = hit1(m, O5, X, tmin=3.5)
    assert (t, p, e) == (4, 1, False) and np.allclose(n, [1, 0, 0])
    nd = difference(Box(4.0), Sphere(0.5).translate((-1, 0, 0)), Sphere(0.5).translate((1, 0, 0)))
    assert_ivs(ivs(nd, O5, X), [(3, 3.5), (4.5, 5.5), (6.5, 7)], [(0, 1), (1, 2), (2, 0)])
    assert ivs(difference(Box(4.0)), O5, X) == ivs(Box(4.0), O5, X)
    nu = union(Sphere(0.5).translate((-1, 0, 0)), Sphere(0.5), Sphere(0.5).translate((1, 0, 0)))
    assert_ivs(ivs(nu, O5, X), [(3.5, 6.5)], [(0, 2)])                 # touching: merged
    ni = intersection(Box(4.0), Sphere(1.5), Cylinder(1.0, 10).rotate("y", 90))
    assert_ivs(ivs(ni, O5, X), [(3.5, 6.5)], [(1, 1)])
    assert_ivs(ivs(ni, [0, 0, -5], Z), [(4, 6)], [(2, 2)])


def test_regularization():
    L, R = Box(2.0), Box(2.0).translate((2, 0, 0))
    o = [-5, 0.3, 0.1]
    assert_ivs(ivs(L | R, o, X), [(4, 8)], [(0, 1)])               # touching: merged
    t, p, n, e = hit1(L | R, o, X)
    assert (t, p, e) == (4, 0, True) and np.allclose(n, [-1, 0, 0])
    t, p, n, e = hit1(L | R, o, X, tmin=5)
    assert (t, p, e) == (8, 1, False) and np.allclose(n, [1, 0, 0])
    assert ivs(L & R, o, X) == []                                  # touching: empty
    assert_ivs(ivs(L - R, o, X), [(4, 6)])                         # coincident face
    assert_ivs(ivs(L | L, o, X), [(4, 6)])
    assert ivs(L - L, o, X) == []
    assert_ivs(ivs(L & L, o, X), [(4, 6)])
    assert_ivs(ivs(Box(4.0) - Box(2.0).translate((1, 0, 0)), o, X), [(3, 5)])


# ---------------------------------------------------------------------------------------------
# Random models: the reference agrees with itself (intervals, first hits, point membership)
# ---------------------------------------------------------------------------------------------

@FAST
@given(models(), seeds())
def test_contains_matches_intervals(model, seed):
    o, d = aimed_rays(model, seed, 48)
    L = ref.interval_arrays(model, o, d)
    dl = np.linalg.norm(d, axis=1)
    rng = np.random.default_rng(seed)
    ts = (np.linspace(0.0, 12.0, 40)[None, :] + rng.uniform(0, 0.3, (len(o), 40))) / dl[:, None]
    t0, t1 = L.t[..., 0], L.t[..., 1]
    inside = np.any((ts[:, :, None] >= t0[:, None, :]) & (ts[:, :, None] <= t1[:, None, :]), axis=2)
    bounds = L.t.reshape(len(o), -1)
    with np.errstate(invalid="ignore"):
        dist = np.min(np.abs(ts[:, :, None] - bounds[:, None, :]), axis=2) * dl[:, None]
    far = ~(dist < 1e-7)
    pts = o[:, None, :] + ts[..., None] * d[:, None, :]
    got = ref.contains(model, pts.reshape(-1, 3)).reshape(inside.shape)
    assert np.array_equal(got[far], inside[far])


@FAST
@given(models(), seeds())
def test_first_hit_properties(model, seed):
    o, d = aimed_rays(model, seed, 48)
    rng = np.random.default_rng(seed)
    dl = np.linalg.norm(d, axis=1)
    tmin = np.where(rng.random(len(o)) < 0.5, 0.0, rng.uniform(0, 8, len(o)) / dl)
    t, prim, n, entering = ref.first_hit(model, o, d, tmin=tmin)
    L = ref.interval_arrays(model, o, d)
    b = L.t.reshape(len(o), -1)
    expected = np.min(np.where(b > tmin[:, None], b, np.inf), axis=1)
    assert np.array_equal(t, expected)
    hit = np.isfinite(t)
    assert np.all((prim >= 0) == hit)
    assert np.allclose(np.linalg.norm(n[hit], axis=1), 1.0)
    ok = hit & ref.stable_mask(model, o, d, tmin=tmin)
    cosn = np.einsum("ij,ij->i", n, d) / dl
    assert np.all(cosn[ok & entering] < 0) and np.all(cosn[ok & ~entering] > 0)
    p = o + t[:, None] * d
    eps = 1e-7 * np.maximum(1.0, np.linalg.norm(o, axis=1))[:, None]
    assert not ref.contains(model, (p + eps * n)[ok]).any()
    assert ref.contains(model, (p - eps * n)[ok]).all()
    u = d / dl[:, None]
    assert np.array_equal(ref.contains(model, (p + eps * u)[ok]), entering[ok])
    assert np.array_equal(ref.contains(model, (p - eps * u)[ok]), ~entering[ok])


@FAST
@given(models(), seeds())
def test_stable_rays_are_robust(model, seed):
    """Rays the mask calls stable keep their first hit under float32 rounding of the ray."""
    o, d = aimed_rays(model, seed, 48)
    ok = ref.stable_mask(model, o, d)
    t, prim, n, entering = ref.first_hit(model, o, d)
    o32, d32 = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    t2, prim2, n2, entering2 = ref.first_hit(model, o32, d32)
    assert np.array_equal(prim[ok], prim2[ok]) and np.array_equal(entering[ok], entering2[ok])
    hit = ok & np.isfinite(t)
    scale = np.maximum(1.0, np.linalg.norm(o, axis=1)) / np.linalg.norm(d, axis=1)
    assert np.all(np.abs(t2[hit] - t[hit]) <= 1e-5 * scale[hit])
    assert np.all(np.einsum("ij,ij->i", n, n2)[hit] > 0.999)


def test_stable_mask_flags_ill_conditioned_rays():
    s = Sphere(1.0)
    o = np.array([[-5, 1 - 1e-9, 0], [-5, 1 + 1e-9, 0], [-5, 0.3, 0]])
    assert ref.stable_mask(s, o, np.repeat(X, 3, 0)).tolist() == [False, False, True]
    b = Box(2.0)
    o = np.array([[-5, 1 - 1e-8, 0.3], [-5, 1 - 1e-8, 1 - 1e-8], [-5, 0.2, 0.3]])
    assert ref.stable_mask(b, o, np.repeat(X, 3, 0)).tolist() == [False, False, True]
    t = Torus(2.0, 0.5)
    o = np.array([[-5, 2.5 - 1e-9, 0], [-5, 1.5 + 1e-9, 0], [-5, 1.0, 0]])
    assert ref.stable_mask(t, o, np.repeat(X, 3, 0)).tolist() == [False, False, True]
    # Coincident faces, a boundary at tmin, one at tmax.
    assert not ref.stable_mask(Box(2.0) | Box(2.0), [[-5, 0.2, 0.1]], X)[0]
    touching = Box(2.0) - Box(2.0).translate((2, 0, 0))
    assert ref.stable_mask(touching, [[-5, 0.2, 0.1]], X)[0]            # coincidence after the hit
    assert not ref.stable_mask(touching, [[-5, 0.2, 0.1]], X, tmin=5.0)[0]
    assert not ref.stable_mask(Box(2.0), [[-5, 0.2, 0.1]], X, tmin=4.0)[0]
    assert not ref.stable_mask(Box(2.0), [[-5, 0.2, 0.1]], X, tmax=4.0)[0]
    assert ref.stable_mask(Box(2.0), [[-5, 0.2, 0.1]], X, tmin=4.5)[0]
    # A cone's apex.
    assert not ref.stable_mask(Cone(1, 0, 2), [[-1e-9, 0, -5]], Z, tmin=5)[0]
    # Ordinary rays at an ordinary model are almost all stable.
    m = (Box(2.0).rotate([1, 2, 3], 20) - Sphere(1.2)) | Torus(1.5, 0.3).rotate("x", 30)
    o, d = make_rays(3, 2000)
    assert ref.stable_mask(m, o, d).mean() > 0.97


# ---------------------------------------------------------------------------------------------
# Volumes: Monte Carlo (point classification) and ray integration vs analytic
# ---------------------------------------------------------------------------------------------

def _hex_area(a):
    return 2.0 * math.sqrt(3.0) * a * a


VOLUME_CASES = [
    (Sphere(0.8), 4 / 3 * math.pi * 0.8 ** 3),
    (Box((0.5, 1.0, 1.5)), 0.75),
    (Cylinder(0.6, 1.3), math.pi * 0.36 * 1.3),
    (Cone(0.9, 0.0, 1.2), math.pi * 1.2 / 3 * 0.81),
    (Cone(0.3, 0.8, 1.0), math.pi / 3 * (0.09 + 0.24 + 0.64)),
    (Torus(1.2, 0.4), 2 * math.pi ** 2 * 1.2 * 0.16),
    (Prism(6, 0.7, 1.1), _hex_area(0.7) * 1.1),
    (Prism(5, 0.7, 1.1), 5 * 0.49 * math.tan(math.pi / 5) * 1.1),
    (ConvexPolyhedron(np.hstack([np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) / math.sqrt(3),
                                 0.4 * np.ones((4, 1))])), 8 * math.sqrt(3) * 0.4 ** 3),
]


def _bounding_radius(prim):
    if isinstance(prim, Sphere):
        return prim.radius
    if isinstance(prim, Box):
        return 0.5 * float(np.linalg.norm(prim.size))
    if isinstance(prim, Cone):
        return math.hypot(max(prim.radius_bottom, prim.radius_top), 0.5 * prim.height)
    if isinstance(prim, Torus):
        return prim.major_radius + prim.minor_radius
    if isinstance(prim, (Paraboloid, Hyperboloid)):
        widest = max(prim.radius_bottom, prim.radius_top) if isinstance(prim, Paraboloid) else prim.radius_end
        return math.hypot(widest, 0.5 * prim.height)
    n, d = ref._planes_of(prim)
    return float(np.max(np.linalg.norm(_convex_vertices(n, d), axis=1)))


def _placed(prim, seed):
    rng = np.random.default_rng(seed)
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + rng.uniform(-0.3, 0.3, (3, 3))
    m[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    return prim.rotate(rng.normal(size=3), rng.uniform(0, 360)).transform(m), abs(np.linalg.det(m[:3, :3]))


@pytest.mark.parametrize("case", range(len(VOLUME_CASES)))
def test_volume_monte_carlo(case):
    prim, vol = VOLUME_CASES[case]
    model, det = _placed(prim, case)
    vol *= det
    world = ref.leaf_list(model)[0][1]
    half = _bounding_radius(prim) * np.linalg.norm(world[:3, :3], 2)
    n = 200_000
    pts = world[:3, 3] + make_points(case, n, half)
    inside = ref.contains(model, pts)
    mc = inside.mean() * (2 * half) ** 3
    sigma = math.sqrt(max(inside.mean() * (1 - inside.mean()), 1e-12) / n) * (2 * half) ** 3
    assert abs(mc - vol) < 4 * sigma, (mc, vol, sigma)
    ext = half + float(np.max(np.abs(world[:3, 3])))
    assert _ray_volume(model, ext, 150, case) == pytest.approx(vol, rel=0.01)


def _ray_volume(model, ext, n, seed):
    """Volume by integrating interval lengths along z over a jittered grid of n x n rays."""
    rng = np.random.default_rng(seed)
    cell = 2 * ext / n
    ij = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
    xy = -ext + (ij + rng.random(ij.shape)) * cell
    o = np.hstack([xy, np.full((len(xy), 1), -ext - 1.0)])
    d = np.repeat(Z, len(o), 0)
    L = ref.interval_arrays(model, o, d)
    lengths = np.where(L.valid, L.t[..., 1] - np.where(L.valid, L.t[..., 0], 0.0), 0.0)
    return lengths.sum() * cell * cell


# ---------------------------------------------------------------------------------------------
# Random models vs manifold3d meshes of the same solid (volume)
# ---------------------------------------------------------------------------------------------

def _convex_vertices(n, d):
    pts = []
    for i, j, k in itertools.combinations(range(len(n)), 3):
        m = n[[i, j, k]]
        if abs(np.linalg.det(m)) < 1e-9:
            continue
        p = np.linalg.solve(m, d[[i, j, k]])
        if np.all(n @ p <= d + 1e-9):
            pts.append(p)
    return np.array(pts)


def _revolved(prim, segments):
    """Our own profile of a paraboloid or hyperboloid (rho^2 = a z^2 + b z + c), densely sampled
    near a tip or apex (z spaced as the square of an even step from it), revolved."""
    import manifold3d as mf
    a, b, c, h = ref._quadric_coefficients(prim)
    u = np.linspace(0.0, 1.0, 4 * segments + 1)
    if isinstance(prim, Paraboloid) and prim.radius_bottom > prim.radius_top:
        z = h - 2 * h * u ** 2                            # from the tip at the top down
    elif isinstance(prim, Paraboloid):
        z = -h + 2 * h * u ** 2
    else:
        z = np.concatenate([-h * u[::-1] ** 2, h * u[1:] ** 2])   # both ways from the waist
    z = np.unique(z)
    rho = np.sqrt(np.maximum(a * z * z + b * z + c, 0.0))
    pts = [(0.0, -h)] + [(r, zz) for r, zz in zip(rho, z) if r > 1e-12] + [(0.0, h)]
    return mf.Manifold.revolve(mf.CrossSection([pts]), segments)


def _mesh(model, segments=96):
    import manifold3d as mf

    def leaf(prim, world, index):
        if isinstance(prim, Sphere):
            m = mf.Manifold.sphere(prim.radius, segments)
        elif isinstance(prim, Box):
            m = mf.Manifold.cube(tuple(prim.size), True)
        elif isinstance(prim, Cone):
            m = mf.Manifold.cylinder(prim.height, prim.radius_bottom, prim.radius_top, segments, True)
        elif isinstance(prim, Torus):
            circle = mf.CrossSection.circle(prim.minor_radius, segments // 2).translate((prim.major_radius, 0))
            m = circle.revolve(segments)
        elif isinstance(prim, (Paraboloid, Hyperboloid)):
            m = _revolved(prim, segments)
        else:
            n, d = ref._planes_of(prim)
            m = mf.Manifold.hull_points(_convex_vertices(n, d))
        return m.transform(world[:3, :4]), _volume_of(prim) * abs(np.linalg.det(world[:3, :3]))

    def op(kind, vals):
        meshes = [v[0] for v in vals]
        total = sum(v[1] for v in vals)
        out = meshes[0]
        for m in meshes[1:]:
            out = out + m if kind == "union" else (out ^ m if kind == "intersection" else out - m)
        return out, total

    return ref._postorder(model, leaf, op)


def _volume_of(prim):
    if isinstance(prim, Sphere):
        return 4 / 3 * math.pi * prim.radius ** 3
    if isinstance(prim, Box):
        return float(np.prod(prim.size))
    if isinstance(prim, Cone):
        a, b = prim.radius_bottom, prim.radius_top
        return math.pi * prim.height / 3 * (a * a + a * b + b * b)
    if isinstance(prim, Torus):
        return 2 * math.pi ** 2 * prim.major_radius * prim.minor_radius ** 2
    if isinstance(prim, Paraboloid):
        return math.pi * prim.height * (prim.radius_bottom ** 2 + prim.radius_top ** 2) / 2
    if isinstance(prim, Hyperboloid):
        return math.pi * prim.height * (prim.radius ** 2 + (prim.radius_end ** 2 - prim.radius ** 2) / 3)
    n, d = ref._planes_of(prim)
    v = _convex_vertices(n, d)
    import manifold3d as mf
    return mf.Manifold.hull_points(v).volume()


@pytest.mark.slow
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(models(max_leaves=6))
def test_volume_matches_manifold3d(model):
    mesh, total = _mesh(model)
    box = np.array(mesh.bounding_box())
    ext = float(np.max(np.abs(box))) + 0.1 if not mesh.is_empty() else 1.0
    vol = _ray_volume(model, ext, 128, 0)
    assert vol == pytest.approx(mesh.volume(), abs=0.01 * total + 2e-3 * ext ** 2)
