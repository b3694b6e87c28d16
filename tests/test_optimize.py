"""The optimizer keeps the solid and the primitive indices, and makes trees shallow."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import mitsuba_csg as csg
import reference as ref
from agreement import compare
from mitsuba_csg.scenes import cheese, city
from strategies import make_points, make_rays, models

STAT_KEYS = {"height_before", "height_after", "nodes_before", "nodes_after", "leaves_duplicated", "seconds"}


def _check_same_solid(model, opt, seed, n_rays=96, n_points=300):
    targets = [leaf.matrix[:3, 3] for leaf in model.leaves()]
    o, d = make_rays(seed, n_rays, targets=targets)
    compare(model, csg.trace(opt, o, d), o, d)
    p = make_points(seed, n_points)
    expected = ref.contains(model, p)
    rng = np.random.default_rng(seed)
    robust = np.ones(len(p), bool)
    for _ in range(4):
        robust &= ref.contains(model, p + rng.normal(scale=2e-4, size=p.shape)) == expected
    assert np.array_equal(csg.contains(opt, p)[robust], expected[robust])


@given(model=models(max_leaves=10), seed=st.integers(0, 2**31),
       variant=st.sampled_from(["default", "positive", "no_sah", "no_height"]))
def test_optimized_model_is_the_same_solid(model, seed, variant):
    kw = {"default": {}, "positive": dict(general_form=False), "no_sah": dict(spatial=False),
          "no_height": dict(minimize_height=False)}[variant]
    opt, stats = csg.optimize(model, **kw)
    assert STAT_KEYS <= set(stats)
    assert opt.flat.num_prims == len(model.leaves())
    _check_same_solid(model, opt, seed)


def _chain(kind, n, seed=0, spread=6.0, disjoint=False):
    rng = np.random.default_rng(seed)
    if disjoint:   # spheres on a line, never touching: the union Exit/Exit case
        centres = np.stack([np.arange(n) * 1.0 - n / 2, np.zeros(n), np.zeros(n)], 1)
        radii = np.full(n, 0.4)
    else:
        centres = rng.uniform(-spread / 2, spread / 2, (n, 3))
        radii = rng.uniform(0.2, 0.6, n)
    parts = [csg.Sphere(float(r)).translate(c) for c, r in zip(centres, radii)]
    if kind == "left_union":
        m = parts[0]
        for p in parts[1:]:
            m = m | p
    elif kind == "right_union":
        m = parts[-1]
        for p in reversed(parts[:-1]):
            m = p | m
    elif kind == "left_difference":
        m = csg.Box(spread)
        for p in parts:
            m = m - p
    elif kind == "alternating":
        m = csg.Box(spread)
        for i, p in enumerate(parts):
            m = (m | p) if i % 2 else (m - p.scale(0.5))
    return m


@pytest.mark.parametrize("kind", ["left_union", "right_union", "left_difference", "alternating"])
def test_chains(kind):
    model = _chain(kind, 40, seed=3)
    opt, stats = csg.optimize(model)
    _check_same_solid(model, opt, seed=5)
    if kind != "alternating":
        assert stats["height_after"] <= 2 * math.ceil(math.log2(41)) + 2


def test_disjoint_union_chain():
    model = _chain("left_union", 30, disjoint=True)
    opt, _ = csg.optimize(model)
    o = np.array([[-20.0, 0.0, 0.0]] * 3 + [[-20.0, 0.1, 0.05]])
    d = np.array([[1.0, 0.0, 0.0]] * 4)
    hits = csg.trace(opt, o, d, tmin=0.0)
    assert hits.t[0] == pytest.approx(-15 + 20 - 0.4, rel=1e-5)
    # walking through the chain: every sphere boundary is a real boundary
    t = 0.0
    for k in range(6):
        h = csg.trace(opt, o[:1], d[:1], tmin=t)
        expected = 20 - 15 + (k // 2) + (-0.4 if k % 2 == 0 else 0.4)
        assert h.t[0] == pytest.approx(expected, rel=1e-5)
        assert h.prim[0] == k // 2
        t = float(h.t[0])


@pytest.mark.parametrize("n", [100, 1000, 10000])
def test_left_deep_union_becomes_logarithmic(n):
    model = _chain("left_union", n, seed=1, spread=20.0)
    opt, stats = csg.optimize(model)
    assert stats["height_before"] >= 1
    assert model.tree_height() == n - 1
    assert stats["height_after"] <= 2 * math.ceil(math.log2(n)) + 2, stats


def _interleaved(n=24, seed=8):
    """T1 | (T2 & (T3 | (T4 & ...))): interleaved operations cannot be flattened."""
    rng = np.random.default_rng(seed)
    parts = [csg.Sphere(float(r)).translate(c) for c, r in zip(rng.uniform(-1, 1, (n, 3)), rng.uniform(0.6, 1.2, n))]
    m = parts[-1]
    for i, p in enumerate(reversed(parts[:-1])):
        m = (p & m) if i % 2 else (p | m)
    return m


def test_type2_distribution_duplicates_and_keeps_indices():
    m = _interleaved()
    opt, stats = csg.optimize(m, max_growth=2.0)
    assert stats["leaves_duplicated"] > 0
    assert stats["height_after"] < stats["height_before"]
    assert stats["nodes_after"] > stats["nodes_before"]
    _check_same_solid(m, opt, seed=9, n_rays=200)
    # every primitive index still names the input's leaf
    prims = opt.flat.node_left[opt.flat.node_kind == 3]
    assert set(prims.tolist()) == set(range(len(m.leaves())))


def test_growth_budget_is_respected():
    m = _interleaved()
    _, none = csg.optimize(m, max_growth=0.0)
    assert none["leaves_duplicated"] == 0
    _, some = csg.optimize(m, max_growth=0.1)
    assert some["leaves_duplicated"] <= int(0.1 * 24)


def test_paper_scenes_reach_paper_depths():
    # Table 2 of the paper: City 3385 -> depth 14, Cheese 1002 -> 11 (we allow a little slack).
    _, s = csg.optimize(city(340))
    assert s["height_after"] <= 16, s
    _, s = csg.optimize(cheese(1000))
    assert s["height_after"] <= 14, s


def test_optimized_cheese_traces_like_the_input():
    model = cheese(300, seed=2)
    opt, _ = csg.optimize(model)
    o, d = make_rays(4, 300, radius=5.0, target=1.0)
    a = csg.trace(opt, o, d)
    b = csg.trace(model, o, d, optimize=False)
    both = np.isfinite(a.t) & np.isfinite(b.t)
    assert np.array_equal(np.isfinite(a.t), np.isfinite(b.t))
    np.testing.assert_allclose(a.t[both], b.t[both], rtol=1e-5)
    assert np.mean(a.prim == b.prim) > 0.99


def test_optimize_accepts_its_own_output_and_single_primitives():
    opt, _ = csg.optimize(csg.Sphere(1.0))
    assert csg.trace(opt, [[0, 0, -5]], [[0, 0, 1]]).t[0] == pytest.approx(4.0)
    again, stats = csg.optimize(opt)
    assert stats["nodes_after"] == 1
    lo, hi = opt.bounds()
    np.testing.assert_allclose(lo, [-1, -1, -1])
    np.testing.assert_allclose(hi, [1, 1, 1])


def test_subtracted_unions_become_one_set():
    """A box minus many spheres comes out of the optimizer as box - (one union of every
    sphere), which the kernel searches as one set; the solid is the same."""
    from mitsuba_csg.engine import layout as K
    from mitsuba_csg.engine.backend import default_backend
    from mitsuba_csg.engine.device import upload
    model = cheese(300, seed=3)
    opt, stats = csg.optimize(model)
    assert stats["set_chains_merged"] >= 1
    flat = opt.flat
    assert np.count_nonzero(flat.node_kind == K.DIFFERENCE) == 1
    tree = upload(flat, default_backend())
    flags = np.asarray(tree.node_record.numpy()).reshape(-1, 4)[:, 0]
    roots = np.flatnonzero(K.flags_set(flags))
    assert len(roots) == 1 and flat.node_right[flat.root] == roots[0]
    _check_same_solid(model, opt, seed=5, n_rays=300)
