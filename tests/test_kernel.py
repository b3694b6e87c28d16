"""The automaton against analytic answers and the independent float64 reference."""
from __future__ import annotations

import itertools

import drjit as dr
import manifold3d
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import mitsuba_csg as csg
import reference as ref
from agreement import compare
from mitsuba_csg.engine.options import TraversalOptions
from mitsuba_csg.engine.grouping import group_trees
from mitsuba_csg.scenes import cheese
from strategies import make_points, make_rays, models, stacked_columns, unions_of_compounds, unions_of_leaves

pytestmark = pytest.mark.usefixtures("jit_variant")   # every test on every JIT backend here

# Each model is traced as lowered (general form), in positive form, and optimized.
FORMS = {
    "general": dict(optimize=False),
    "positive": dict(optimize=False, positive=True),
    "optimized": dict(optimize=True),
}


# Each traversal mechanism on (the default) and off, so that each is checked on its own.
TRAVERSALS = {
    "default": TraversalOptions(),
    "no_restart": TraversalOptions(restart_at_sibling=False),
    "no_skip": TraversalOptions(skip_to_sibling=False),
    "no_bound": TraversalOptions(bounded_search=False),
    "no_near_first": TraversalOptions(near_first=False),
    "no_sets": TraversalOptions(sets=False),
    "small_sets": TraversalOptions(min_set_size=2),      # unions of 2 and 3 leaves walked as sets too
    "no_compounds": TraversalOptions(compounds=False),   # set members are leaves only
    "no_neighbours": TraversalOptions(neighbour_passes=False),   # passes from inside start at the set's root
    "no_cells": TraversalOptions(cell_passes=False),    # passes asking a point's state start at the set's root
    "small_grids": TraversalOptions(min_grid_size=2),  # hole sets of any size get cell grids
    "no_pass_through": TraversalOptions(pass_through=False),
    "none": TraversalOptions(*[False] * 6),
}


def trace(model, o, d, form="general", traversal="default", **kw):
    prepared = csg.prepare(model, **FORMS[form], traversal=TRAVERSALS[traversal])
    return csg.trace(prepared, o, d, **kw)


def axis_rays(origin, direction, n=1):
    return np.tile(np.asarray(origin, float), (n, 1)), np.tile(np.asarray(direction, float), (n, 1))


# ---- Analytic answers, one primitive at a time ----

@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("model, origin, direction, t, normal", [
    (csg.Sphere(1.0), (0, 0, -5), (0, 0, 1), 4.0, (0, 0, -1)),
    (csg.Sphere(2.0).translate((1, 0, 0)), (1, -10, 0), (0, 2, 0), 4.0, (0, -1, 0)),
    (csg.Box((2, 4, 6)), (-10, 0.5, 0.5), (1, 0, 0), 9.0, (-1, 0, 0)),
    (csg.Box((2, 4, 6)), (0.2, 0.3, 10), (0, 0, -1), 7.0, (0, 0, 1)),
    (csg.Cylinder(1.0, 2.0), (5, 0, 0), (-1, 0, 0), 4.0, (1, 0, 0)),
    (csg.Cylinder(1.0, 2.0), (0.5, 0, 5), (0, 0, -1), 4.0, (0, 0, 1)),
    (csg.Cone(1.0, 0.0, 2.0), (0, 0, 5), (0, 0, -1), 4.0, (0, 0, 1)),            # apex
    (csg.Cone(1.0, 0.0, 2.0), (0, 0, -5), (0, 0, 1), 4.0, (0, 0, -1)),           # base
    (csg.Cone(0.0, 1.0, 2.0), (5, 0, 0), (-1, 0, 0), 4.5, (2 / 5 ** 0.5, 0, -1 / 5 ** 0.5)),
    (csg.Torus(2.0, 0.5), (-10, 0, 0), (1, 0, 0), 7.5, (-1, 0, 0)),
    (csg.Torus(2.0, 0.5), (0, 0, 0), (1, 0, 0), 1.5, (-1, 0, 0)),               # from the hole
    (csg.Torus(2.0, 0.5), (2, 0, 10), (0, 0, -1), 9.5, (0, 0, 1)),
    (csg.Prism(6, 1.0, 2.0), (-10, 0, 0), (1, 0, 0), 9.0, (-1, 0, 0)),
    (csg.ConvexPolyhedron([[1, 0, 0, 1], [-1, 0, 0, 1], [0, 1, 0, 1], [0, -1, 0, 1], [0, 0, 1, 1],
                           [0, 0, -1, 1], [1, 1, 1, 1.5]]), (5, 5, 5), (-1, -1, -1), 5 - 0.5, (1, 1, 1)),
])
def test_primitive_first_hit(model, origin, direction, t, normal, form):
    o, d = axis_rays(origin, direction)
    hits = trace(model, o, d, form)
    assert hits.t[0] == pytest.approx(t, rel=1e-5)
    assert hits.prim[0] == 0
    n = np.asarray(normal, float)
    np.testing.assert_allclose(hits.normal[0], n / np.linalg.norm(n), atol=1e-5)
    assert hits.entering[0]


@pytest.mark.parametrize("form", FORMS)
def test_boolean_analytic(form):
    a = csg.Sphere(1.0)
    b = csg.Sphere(1.0).translate((1.0, 0, 0))
    o, d = axis_rays((-5, 0, 0), (1, 0, 0))
    assert trace(a | b, o, d, form).t[0] == pytest.approx(4.0)
    assert trace(a & b, o, d, form).t[0] == pytest.approx(5.0)
    assert trace(b - a, o, d, form).t[0] == pytest.approx(6.0)            # exit of the subtracted sphere
    h = trace(b - a, o, d, form)
    np.testing.assert_allclose(h.normal[0], [-1, 0, 0], atol=1e-6)        # flipped: outward of the solid
    assert h.prim[0] == 1 and h.entering[0]
    # from inside: the first boundary is an exit
    h = trace(a | b, *axis_rays((0.5, 0, 0), (1, 0, 0)), form)
    assert h.t[0] == pytest.approx(1.5) and not h.entering[0] and h.prim[0] == 1


@pytest.mark.parametrize("form", FORMS)
def test_tmin_tmax(form):
    m = csg.Box(2.0) - csg.Sphere(0.5)
    o, d = axis_rays((-5, 0, 0), (1, 0, 0))
    assert trace(m, o, d, form).t[0] == pytest.approx(4.0)
    assert trace(m, o, d, form, tmin=4.0).t[0] == pytest.approx(4.5)     # strictly after tmin
    assert trace(m, o, d, form, tmin=4.2).t[0] == pytest.approx(4.5)
    assert trace(m, o, d, form, tmin=4.6).t[0] == pytest.approx(5.5)
    assert np.isinf(trace(m, o, d, form, tmax=3.9).t[0])
    assert trace(m, o, d, form, tmax=4.0).t[0] == pytest.approx(4.0)


# ---- Random trees against the reference ----

@pytest.mark.parametrize("traversal", TRAVERSALS)
@pytest.mark.parametrize("form", FORMS)
@given(model=models(max_leaves=8), seed=st.integers(0, 2**31))
def test_random_trees_agree_with_reference(model, seed, form, traversal):
    targets = [leaf.matrix[:3, 3] for leaf in model.leaves()]
    o, d = make_rays(seed, 96, targets=targets)
    hits = trace(model, o, d, form, traversal)
    compare(model, hits, o, d)


@pytest.mark.parametrize("traversal", ["default", "no_sets", "no_neighbours"])
@pytest.mark.parametrize("form", FORMS)
@given(model=unions_of_leaves(), seed=st.integers(0, 2**31))
def test_unions_of_many_leaves_agree_with_reference(model, seed, form, traversal):
    """Sets (unions of leaves searched as one n-ary node): overlapping, nested and disjoint
    members of every primitive, non-convex ones included, alone, cut from a box or cutting it."""
    targets = [leaf.matrix[:3, 3] for leaf in model.leaves()]
    o, d = make_rays(seed, 128, targets=targets)
    compare(model, trace(model, o, d, form, traversal), o, d)


@pytest.mark.parametrize("traversal", ["default", "no_compounds"])
@pytest.mark.parametrize("form", ["general", "optimized"])
@given(model=unions_of_compounds(), seed=st.integers(0, 2**31))
def test_unions_of_compounds_agree_with_reference(model, seed, form, traversal):
    """Compound set members (small intersections of convex solids and their complements,
    engine.leaf_events.compound_hit), cuts flush with faces among them; the same models with
    the automaton walking the compounds instead."""
    targets = [leaf.matrix[:3, 3] for leaf in model.leaves()]
    o, d = make_rays(seed, 128, targets=targets)
    prepared = csg.prepare(model, **FORMS[form], traversal=TRAVERSALS[traversal])
    compare(model, csg.trace(prepared, o, d), o, d, coincident=True)


def test_satellite_parts_are_compound_members():
    """A satellite's wings with their cut-outs and its dish are compound members of the
    satellites' union (one set), not subtrees the automaton descends into."""
    from mitsuba_csg import scenes
    tree = csg.prepare(scenes.satellites(8)).tree
    assert tree.has_compounds
    from mitsuba_csg.engine import layout as K
    literals = tree.compound_literals.numpy().reshape(-1, K.COMPOUND_RECORD_WORDS)[:, :K.MAX_COMPOUND_LITERALS]
    assert len(literals) == 8 * 3                          # two wings and a dish each
    assert sorted((literals != 0xFFFFFFFF).sum(axis=1).tolist()) == [3] * 24


@given(model=unions_of_leaves(), optimize=st.booleans())
def test_wide_set_nodes_hold_each_member_once_with_its_box(model, optimize):
    """The set walk's 4-wide nodes (engine.device): from each set's root they reach every leaf
    under it exactly once, each child's box is that child's own node box, and the deepest run
    of waiting entries (a visit pushes all the children it opens but one) fits the walk's stack."""
    from mitsuba_csg.engine import layout as K
    tree = csg.prepare(model, optimize=optimize).tree
    record = tree.node_record.numpy().reshape(-1, 4)
    boxes = tree.node_box.numpy().reshape(-1, 8)
    wide = tree.set_nodes.numpy().reshape(-1, K.SET_NODE_FLOATS)
    refs = wide[:, :4].view(np.uint32)
    entry = tree.walk_entry.numpy()
    kinds = K.flags_kind(record[:, 0])

    def leaves_under(node):
        found, todo = [], [node]
        while todo:
            n = todo.pop()
            if kinds[n] == K.LEAF:
                found.append(n)
            else:
                todo += [record[n, 1], record[n, 2]]
        return sorted(found)

    roots = np.flatnonzero(entry & K.SET_NODE_TAG)
    assert (entry[entry & K.SET_NODE_TAG == 0] == np.flatnonzero(entry & K.SET_NODE_TAG == 0)).all()
    for root in roots:
        found, deepest, todo = [], 0, [(int(entry[root] & (K.SET_NODE_TAG - 1)), 0)]
        while todo:
            index, waiting = todo.pop()
            children = [(j, int(r)) for j, r in enumerate(refs[index]) if r != 0xFFFFFFFF]
            assert 2 <= len(children) <= 4
            assert np.isnan(wide[index, 4 + 6 * len(children):28]).all()       # empty slots never open
            waiting += len(children) - 1
            deepest = max(deepest, waiting)
            for j, r in children:
                if r & K.SET_NODE_TAG:
                    todo.append((r & (K.SET_NODE_TAG - 1), waiting))
                else:
                    found.append(r)
                    child_box = np.concatenate([boxes[r, 0:3], boxes[r, 4:7]])
                    np.testing.assert_array_equal(wide[index, 4 + 6 * j:10 + 6 * j], child_box)
        assert sorted(found) == leaves_under(root)
        assert deepest < tree.walk_stack_size


@pytest.mark.parametrize("traversal", ["default", "no_sets"])
@given(model=stacked_columns(), seed=st.integers(0, 2**31))
def test_towers_of_touching_columns_have_no_inner_faces(model, seed, traversal):
    """A union of columns stacked face to face, each in its own frame: a ray along the tower
    passes from member to member through faces that are one event (a set's exit chain)."""
    o, d = make_rays(seed, 96, radius=6.0, target=1.5)
    prepared = csg.prepare(model, traversal=TRAVERSALS[traversal])
    compare(model, csg.trace(prepared, o, d), o, d, coincident=True)


@given(model=models(max_leaves=8), seed=st.integers(0, 2**31))
def test_normals_point_outward(model, seed):
    """Along the line through the hit point in the normal's direction, the reference sees the
    solid's boundary at the hit point, and it is an exit: inside before, outside after."""
    o, d = make_rays(seed, 64, targets=[leaf.matrix[:3, 3] for leaf in model.leaves()])
    hits = csg.trace(model, o, d)
    stable = ref.stable_mask(model, o, d)
    hit = np.flatnonzero(np.isfinite(hits.t) & stable)
    if not len(hit):
        return
    p = o[hit] + hits.t[hit, None].astype(np.float64) * d[hit]
    n = hits.normal[hit].astype(np.float64)
    for k, spans in enumerate(ref.intervals(model, p, n)):
        ends = [(abs(s), "enter") for s, _, _, _ in spans] + [(abs(e), "exit") for _, e, _, _ in spans]
        dist, kind = min(ends)
        assert dist < 1e-3, f"hit point {p[k]} is {dist} from the boundary along its normal"
        assert kind == "exit", f"normal {n[k]} at {p[k]} points into the solid"


@given(model=models(max_leaves=8), seed=st.integers(0, 2**31))
def test_contains_agrees_with_reference(model, seed):
    p = make_points(seed, 300)
    got = csg.contains(model, p)
    expected = ref.contains(model, p)
    # points within 1e-4 of the boundary may go either way: test with jittered copies
    rng = np.random.default_rng(seed)
    robust = np.ones(len(p), bool)
    for _ in range(4):
        robust &= ref.contains(model, p + rng.normal(scale=2e-4, size=p.shape)) == expected
    assert np.array_equal(got[robust], expected[robust])


@given(model=models(max_leaves=8), seed=st.integers(0, 2**31))
def test_reordered_rays_agree_with_reference_and_with_rays_as_given(model, seed):
    """trace_rays(reorder=True) traces only the rays that meet the root box, sorted, and puts
    the results back: the same results bit for bit, with a camera-like shared origin,
    per-ray tmin and tmax, an active mask, rays from inside and rays that miss the box."""
    from mitsuba_csg.queries import trace_rays
    rng = np.random.default_rng(seed)
    o, d = make_rays(seed, 96, targets=[leaf.matrix[:3, 3] for leaf in model.leaves()])
    o[:16] = make_points(seed, 16, 1.0)                      # from inside or near the model
    o[16:24], d[16:24] = [40.0, 0, 0], [1.0, 0, 0]          # away from the box: no work
    compare(model, csg.trace(model, o, d, reorder=True), o, d)

    prepared = csg.prepare(model)
    b = prepared.tree.b
    O, D = csg.rays_to_device(o, b), csg.rays_to_device(d, b)
    tmin, tmax = b.Float(rng.uniform(0, 0.5, 96)), b.Float(rng.uniform(2, 12, 96))
    active = b.Bool(rng.random(96) < 0.8)
    fields = ("t", "normal", "prim", "entering", "finished", "steps", "info")
    for args in ((O, D, tmin, tmax), (b.Array3f(0.0, 0.0, -6.0), D, 0.0, float("inf"))):
        plain = trace_rays(prepared, *args, active=active)
        reordered = trace_rays(prepared, *args, active=active, reorder=True)
        for name in fields:
            assert np.array_equal(np.asarray(getattr(plain, name).numpy()),
                                  np.asarray(getattr(reordered, name).numpy()), equal_nan=True), name
    none = trace_rays(prepared, O, D, active=dr.zeros(b.Bool, 96), reorder=True)
    assert np.all(np.isinf(none.t.numpy())) and not np.any(none.steps.numpy())


@given(model=models(max_leaves=8), seed=st.integers(0, 2**31))
def test_start_prim_changes_no_result(model, seed):
    """Rays that continue from hits (a path tracer's bounce and shadow rays: from either side
    of the surface, in any direction) traced with the hit's primitive as `start_prim`, and
    with a wrong one, give the results of the rays traced without it bit for bit, as given
    and reordered, and agree with the float64 reference. The one freedom: where set members'
    exits coincide exactly (coincident faces), which of them is reported (found with
    Sphere(1) | Sphere(1))."""
    from types import SimpleNamespace

    from mitsuba_csg.queries import trace_rays
    rng = np.random.default_rng(seed)
    o, d = make_rays(seed, 128, targets=[leaf.matrix[:3, 3] for leaf in model.leaves()])
    first = csg.trace(model, o, d)
    hit = np.flatnonzero(np.isfinite(first.t))
    if not len(hit):
        return
    unit = d[hit] / np.linalg.norm(d[hit], axis=1, keepdims=True)
    n = first.normal[hit]
    side = rng.choice([-1.0, 1.0], len(hit))                # the empty side (+n) or into the solid
    origin = o[hit] + first.t[hit, None] * d[hit] + side[:, None] * 1e-4 * n
    direction = rng.normal(size=origin.shape)
    direction *= np.sign(np.einsum("ij,ij->i", direction, n) * side)[:, None]
    direction[::5] = np.where(side[::5, None] > 0, -unit[::5] + 2 * n[::5] * np.einsum("ij,ij->i", unit[::5], n[::5])[:, None],
                              unit[::5])                  # mirror reflections, and straight on into the solid
    start = first.prim[hit].astype(np.uint32)
    wrong = rng.random(len(hit)) < 0.25
    start[wrong] = rng.integers(0, len(model.leaves()), int(wrong.sum()))
    start[::7] = 0xFFFFFFFF
    prepared = csg.prepare(model)
    b = prepared.tree.b
    O, D, S = csg.rays_to_device(origin, b), csg.rays_to_device(direction, b), b.UInt32(start)
    plain = trace_rays(prepared, O, D)
    for reorder in (False, True):
        hinted = trace_rays(prepared, O, D, start_prim=S, reorder=reorder)
        for name in ("t", "entering", "finished", "info"):
            assert np.array_equal(np.asarray(getattr(plain, name).numpy()),
                                  np.asarray(getattr(hinted, name).numpy()), equal_nan=True), (name, reorder)
        other = plain.prim.numpy() != hinted.prim.numpy()
        # The same surface (another of coincident faces where the primitive differs); the
        # reordered kernel's normals may differ in the last bits.
        hit = np.isfinite(plain.t.numpy())
        assert np.all(np.einsum("ij,ij->j", plain.normal.numpy(), hinted.normal.numpy())[hit] > 0.9999), reorder
    got = SimpleNamespace(t=hinted.t.numpy(), prim=hinted.prim.numpy().astype(np.int64),
                          normal=np.asarray(hinted.normal.numpy()).T, entering=hinted.entering.numpy(),
                          unfinished=int(np.sum(~hinted.finished.numpy())))
    got.prim[~np.isfinite(got.t)] = -1
    compare(model, got, origin, direction, check_prim=not np.any(other))


def test_a_compound_literal_under_a_union_gives_no_start_hint():
    """A compound cut by a union, C - (S1 | S2), has its literals S1, S2 under a union inside
    the set: a ray starting on S1 must not be walked as if it started inside a set member
    (found by test_neighbour_passes_change_no_result: a hit where the reference has none)."""
    from mitsuba_csg.queries import trace_rays
    shift = np.eye(4)
    shift[0, 3] = -0.214713
    shift[:3, :3] *= 0.991207
    model = csg.union(csg.Sphere(0.781508), csg.Sphere(0.3) - csg.Sphere(0.95), csg.Sphere(0.667453),
                      csg.Cylinder(0.767058, 1.9).transform(shift) - (csg.Sphere(0.967631) | csg.Sphere(0.3)))
    o = np.array([[-0.09745904000258288, -0.6017817626049867, 0.7513168434815128]])
    d = np.array([[2.2035098806466507, -0.05202897425988651, -0.6836861907765345]])
    assert np.isinf(ref.first_hit(model, o, d)[0][0])
    prepared = csg.prepare(model, optimize=False)
    b = prepared.tree.b
    for prim in range(len(model.leaves())):
        hits = trace_rays(prepared, csg.rays_to_device(o, b), csg.rays_to_device(d, b), start_prim=b.UInt32([prim]))
        assert np.isinf(hits.t.numpy()[0]), prim


def rays_leaving_holes(model, seed, n, spread):
    """(origins, directions, start primitives) of rays from the walls of a Cheese's holes into
    them: the hits of `n` random rays on holes, each leaving about its normal."""
    o, d = make_rays(seed, n)
    first = csg.trace(model, o, d)
    on_hole = np.flatnonzero(np.isfinite(first.t) & (first.prim > 0))      # leaf 0 is the cube
    normal = first.normal[on_hole]
    origin = o[on_hole] + first.t[on_hole, None] * d[on_hole] + 1e-4 * normal
    direction = normal + spread * np.random.default_rng(seed).normal(size=normal.shape)
    direction *= np.sign(np.einsum("ij,ij->i", direction, normal))[:, None]
    return origin, direction, first.prim[on_hole].astype(np.uint32)


def test_start_prim_saves_steps_on_rays_leaving_a_hole():
    """The case the hint is for: rays from the inside of a Cheese's hole's wall into the hole
    take fewer steps (the same hits: test_start_prim_changes_no_result)."""
    from mitsuba_csg.queries import trace_rays
    model = cheese(40)
    prepared = csg.prepare(model)
    b = prepared.tree.b
    origin, direction, start = rays_leaving_holes(model, 4, 2000, 0.5)
    O, D = csg.rays_to_device(origin, b), csg.rays_to_device(direction, b)
    plain = trace_rays(prepared, O, D)
    hinted = trace_rays(prepared, O, D, start_prim=b.UInt32(start))
    assert np.array_equal(plain.t.numpy(), hinted.t.numpy(), equal_nan=True)
    assert hinted.steps.numpy().mean() < 0.9 * plain.steps.numpy().mean()


@pytest.mark.parametrize("mechanism", ["neighbour_passes", "cell_passes"])
@given(model=st.one_of(unions_of_leaves(), unions_of_compounds()), seed=st.integers(0, 2**31),
       optimize=st.booleans())
def test_local_passes_change_no_result(mechanism, model, seed, optimize):
    """A set walk inside at a member's exit that searches only that member's neighbours
    (engine.neighbours: a ray leaving a member's surface into it, a chain through overlapping
    members), and a walk asking only the set's state at a point that searches only the
    members near the point's grid cell (the holes at a ray's entry into a Cheese), find what
    the walk from the set's root finds, for rays from anywhere and for rays continuing from
    hits with the hit's primitive as `start_prim`; and agree with the float64 reference."""
    from types import SimpleNamespace

    from mitsuba_csg.queries import trace_rays
    targets = [leaf.matrix[:3, 3] for leaf in model.leaves()]
    o, d = make_rays(seed, 128, targets=targets)
    first = csg.trace(model, o, d)
    hit = np.flatnonzero(np.isfinite(first.t))
    rng = np.random.default_rng(seed)
    side = rng.choice([-1.0, 1.0], len(hit))
    n = first.normal[hit]
    origin = np.concatenate([o, o[hit] + first.t[hit, None] * d[hit] + side[:, None] * 1e-4 * n])
    turned = rng.normal(size=n.shape)
    turned *= np.sign(np.einsum("ij,ij->i", turned, n) * side)[:, None]
    direction = np.concatenate([d, turned])
    start = np.concatenate([np.full(len(o), 0xFFFFFFFF), first.prim[hit]]).astype(np.uint32)
    results = []
    for on in (True, False):
        # Grids for sets of any size, not only those of MIN_GRID_SIZE members or more.
        prepared = csg.prepare(model, optimize=optimize, traversal=TraversalOptions(**{mechanism: on}, min_grid_size=2))
        b = prepared.tree.b
        results.append(trace_rays(prepared, csg.rays_to_device(origin, b), csg.rays_to_device(direction, b),
                                  start_prim=b.UInt32(start)))
    local, rooted = results
    for name in ("t", "entering", "finished", "info"):
        assert np.array_equal(np.asarray(getattr(local, name).numpy()), np.asarray(getattr(rooted, name).numpy()),
                              equal_nan=True), name
    got = SimpleNamespace(t=local.t.numpy(), prim=local.prim.numpy().astype(np.int64),
                          normal=np.asarray(local.normal.numpy()).T, entering=local.entering.numpy(),
                          unfinished=int(np.sum(~local.finished.numpy())))
    got.prim[~np.isfinite(got.t)] = -1
    compare(model, got, origin, direction, check_prim=bool(np.all(local.prim.numpy() == rooted.prim.numpy())),
            coincident=True)


def test_neighbour_passes_save_steps_in_connected_holes():
    """The case neighbour trees are for: rays from a hole's wall into a Cheese whose holes
    overlap (each pass at a hole's exit looks among that hole's neighbours, not down the
    whole set) take fewer steps, to the same hits."""
    from mitsuba_csg.queries import trace_rays
    model = cheese(300, seed=2)
    origin, direction, start = rays_leaving_holes(model, 5, 3000, 0.7)
    steps, t = [], []
    for neighbours in (True, False):
        prepared = csg.prepare(model, traversal=TraversalOptions(neighbour_passes=neighbours))
        assert prepared.tree.has_neighbours == neighbours
        b = prepared.tree.b
        hits = trace_rays(prepared, csg.rays_to_device(origin, b), csg.rays_to_device(direction, b),
                          start_prim=b.UInt32(start))
        steps.append(hits.steps.numpy().mean())
        t.append(hits.t.numpy())
    assert np.array_equal(t[0], t[1], equal_nan=True)
    assert steps[0] < 0.85 * steps[1]


def test_cell_passes_save_steps_entering_a_cheese():
    """The case cell grids are for: rays from outside a Cheese, where the holes' set is asked
    only whether the point where a ray enters the block lies in a hole (its first pass walks
    the tree of that point's cell, not down the whole set), take fewer steps, to the same hits."""
    model = cheese(300, seed=2)
    o, d = make_rays(7, 3000)
    steps, t = [], []
    for cells in (True, False):
        prepared = csg.prepare(model, traversal=TraversalOptions(cell_passes=cells))
        assert prepared.tree.has_grids == cells
        hits = csg.trace(prepared, o, d)
        entered = np.isfinite(hits.t) | (hits.steps > 2)
        steps.append(hits.steps[entered].mean())
        t.append(hits.t)
    assert np.array_equal(t[0], t[1], equal_nan=True)
    assert steps[0] < 0.85 * steps[1], steps


def test_reorder_inside_a_symbolic_loop_is_ignored():
    """Nothing can be evaluated while a symbolic loop is recorded (the integrators' path
    loops): there trace_rays(reorder=True) traces the rays as given."""
    from mitsuba_csg.queries import trace_rays
    model = csg.Box(2.0) - csg.Sphere(1.2)
    prepared = csg.prepare(model)
    b = prepared.tree.b
    o, d = make_rays(3, 64)
    O, D = csg.rays_to_device(o, b), csg.rays_to_device(d, b)

    def body(total, k):
        t = trace_rays(prepared, O, D, reorder=True).t
        return total + dr.select(dr.isfinite(t), t, 0.0), k + 1
    total, _ = dr.while_loop((dr.zeros(b.Float, 64), dr.zeros(b.UInt32, 64)), lambda total, k: k < 2, body,
                             mode="symbolic")
    expected = csg.trace(model, o, d).t
    assert np.allclose(total.numpy(), 2 * np.where(np.isfinite(expected), expected, 0.0))


# ---- Robustness ----

def test_rays_starting_inside_and_on_surface():
    m = csg.Box(2.0) - csg.Sphere(0.5)
    o, d = axis_rays((0.75, 0, 0), (1, 0, 0))
    h = csg.trace(m, o, d)
    assert h.t[0] == pytest.approx(0.25) and not h.entering[0]
    h = csg.trace(m, *axis_rays((-1.0, 0, 0), (1, 0, 0)))          # starts on the face: next is the hole
    assert h.t[0] == pytest.approx(0.5)


def test_tangent_and_edge_rays():
    """Grazing and edge rays end with the analytic answer; the random ones agree with the reference."""
    m = (csg.Sphere(1.0) | csg.Box(1.0).translate((1.5, 0, 0))) - csg.Cylinder(0.3, 4.0)
    # Grazes the sphere at (0, 1, 0), t = 5 (the box's y extent is 0.5, the hole's radius 0.3):
    # a miss, or a touch at the tangent point, are both right.
    h = csg.trace(m, *axis_rays((-5.0, 1.0, 0.0), (1, 0, 0), 8))
    assert h.unfinished == 0
    assert np.all(np.isinf(h.t) | (np.abs(h.t - 5.0) < 1e-3))
    # Along the box edge y = z = 0.5: enters the sphere first, at x = -sqrt(1 - 0.5).
    h = csg.trace(m, *axis_rays((-5.0, 0.5, 0.5), (1, 0, 0), 8))
    np.testing.assert_allclose(h.t, 5.0 - np.sqrt(0.5), rtol=1e-6)
    assert np.all(h.entering) and np.all(h.prim == 0)
    rng = np.random.default_rng(1)
    o, d = rng.uniform(-3, 3, (200, 3)), rng.normal(size=(200, 3))
    stable, total = compare(m, csg.trace(m, o, d), o, d)
    assert stable > 0.9 * total


def test_coincident_faces():
    """Shared, touching and identical faces: the reference on stable rays, analytic answers on the faces."""
    slab = csg.Box((2, 2, 2))
    half = slab - csg.Box((1, 2, 2)).translate((0.5, 0, 0))          # x in [-1, 0]: shares three faces
    pair = slab | csg.Box((2, 2, 2)).translate((2, 0, 0))            # touching at x = 1
    overlap = slab & csg.Box((2, 2, 2)).translate((1, 0, 0))         # x in [0, 1]
    rng = np.random.default_rng(2)
    o, d = rng.uniform(-4, 4, (500, 3)), rng.normal(size=(500, 3))
    along_x = axis_rays((-5, 0.25, -0.5), (1, 0, 0))
    for form, traversal in itertools.product(FORMS, TRAVERSALS):
        for m in (half, pair, overlap):
            compare(m, trace(m, o, d, form, traversal), o, d)
        assert np.all(np.isinf(trace(slab - slab, o, d, form).t))
        assert trace(half, *along_x, form).t[0] == pytest.approx(4.0)
        assert trace(half, *axis_rays((-0.5, 0, 0), (1, 0, 0)), form).t[0] == pytest.approx(0.5)
        assert trace(pair, *along_x, form).t[0] == pytest.approx(4.0)
        assert trace(overlap, *along_x, form).t[0] == pytest.approx(5.0)


@pytest.mark.parametrize("scale", [1e-4, 1.0, 1e5])
def test_huge_and_tiny_scales(scale):
    """Scaling the scene and the rays (o' = s o + c, d' = s d) leaves every t unchanged."""
    m = csg.Box(2.0) - csg.Sphere(0.6).translate((1, 0, 0)) | csg.Torus(1.0, 0.3).translate((0, 0, 2))
    shift = np.array([3.0, -1.0, 0.5]) * scale
    scaled = m.scale(scale).translate(shift)
    o, d = make_rays(7, 300, radius=6.0, target=1.5)
    hits = csg.trace(scaled, o * scale + shift, d * scale)
    stable, total = compare(m, hits, o, d)
    assert stable > 0.8 * total


def test_axis_parallel_rays_on_slab_planes():
    m = csg.Box(2.0) | csg.Box(2.0).translate((2, 0, 0))
    # rays inside the plane y = 1 (a face plane), parallel to x and z
    o = np.array([[-5.0, 1.0, 0.0], [-5.0, 0.999, 0.0], [0.5, 1.0, -5.0], [0.5, -1.0, -5.0]])
    d = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0], [0, 0, 1.0]])
    h = csg.trace(m, o, d)
    assert h.unfinished == 0
    assert h.t[1] == pytest.approx(4.0)


def test_iteration_bound_is_reported():
    m = cheese(50, seed=3)
    o, d = make_rays(3, 200, radius=4.0, target=0.8)
    with pytest.warns(csg.IterationLimitWarning):
        h = csg.trace(m, o, d, max_iterations=5)
    assert h.unfinished > 0
    assert np.count_nonzero(np.isnan(h.t)) == h.unfinished      # exactly the stopped lanes are NaN
    done = ~np.isnan(h.t)
    full = csg.trace(m, o[done], d[done])
    np.testing.assert_array_equal(h.t[done], full.t)              # the others finished as usual


def test_torus_has_no_false_roots():
    """Grazing and far-away rays: every kernel hit is a real boundary, every miss a real miss."""
    m = csg.Torus(1.0, 0.25)
    rng = np.random.default_rng(5)
    n = 4000
    target = rng.uniform(-1.3, 1.3, (n, 3)) * [1, 1, 0.3]
    o = rng.normal(size=(n, 3))
    o *= (rng.choice([3.0, 30.0, 300.0], n) / np.linalg.norm(o, axis=1))[:, None]
    d = target - o
    hits = csg.trace(m, o, d)
    t_ref = ref.first_hit(m, o, d)[0]
    hit = np.isfinite(hits.t)
    p = o[hit] + hits.t[hit, None].astype(np.float64) * d[hit]
    # a hit lies on the torus surface (distance from the tube's core circle == minor radius)
    dist = np.hypot(np.hypot(p[:, 0], p[:, 1]) - 1.0, p[:, 2])
    assert np.max(np.abs(dist - 0.25)) < 1e-3 * np.max(np.linalg.norm(o[hit], axis=1))
    # and agrees with the reference except within a whisker of tangency
    stable = ref.stable_mask(m, o, d)
    np.testing.assert_array_equal(np.isfinite(hits.t[stable]), np.isfinite(t_ref[stable]))
    assert stable.mean() > 0.95


# ---- Large and deep trees ----

def _sphere_union_reference(centres, radii, o, d):
    """First hit on a union of spheres from outside: the nearest sphere entry."""
    oc = o[:, None, :] - centres[None]
    a = np.einsum("ij,ij->i", d, d)[:, None]
    b = np.einsum("nkj,nj->nk", oc, d)
    c = np.einsum("nkj,nkj->nk", oc, oc) - radii[None] ** 2
    disc = b * b - a * c
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
    t = np.where(t > 0, t, np.inf)
    return t.min(1), t.argmin(1)


@pytest.mark.slow
@pytest.mark.parametrize("optimize", [False, True])
def test_left_deep_union_of_10k_spheres(optimize):
    rng = np.random.default_rng(11)
    centres = rng.uniform(-5, 5, (10000, 3))
    radii = rng.uniform(0.05, 0.3, 10000)
    model = csg.Sphere(float(radii[0])).translate(centres[0])
    for c, r in zip(centres[1:], radii[1:]):
        model = model | csg.Sphere(float(r)).translate(c)
    assert model.tree_height() == 9999
    o, d = make_rays(12, 400, radius=12.0, target=5.0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hits = csg.trace(model, o, d, optimize=optimize)
    t_ref, prim_ref = _sphere_union_reference(centres, radii, o, d)
    assert hits.unfinished == 0
    np.testing.assert_array_equal(np.isfinite(hits.t), np.isfinite(t_ref))
    hit = np.isfinite(t_ref)
    np.testing.assert_allclose(hits.t[hit], t_ref[hit], rtol=1e-4, atol=1e-5)
    assert np.mean(hits.prim[hit] == prim_ref[hit]) > 0.999   # ties between overlapping entries aside


@pytest.mark.slow
@pytest.mark.parametrize("optimize", [False, True])
def test_cheese_1000(optimize):
    model = cheese(1000, seed=4)
    o, d = make_rays(13, 150, radius=5.0, target=1.0)
    hits = csg.trace(model, o, d, optimize=optimize)
    stable, total = compare(model, hits, o, d)
    assert stable > 0.7 * total


# ---- Bad input ----

def test_bad_rays_are_refused():
    m = csg.Sphere(1.0)
    with pytest.raises(csg.CSGError, match="origins"):
        csg.trace(m, [[np.nan, 0, 0]], [[1, 0, 0]])
    with pytest.raises(csg.CSGError, match="zero vector"):
        csg.trace(m, [[0, 0, 0]], [[0, 0, 0]])
    with pytest.raises(csg.CSGError, match="differ in length"):
        csg.trace(m, np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(csg.CSGError, match="shape"):
        csg.trace(m, np.zeros((2, 2)), np.ones((2, 2)))
    with pytest.raises(csg.CSGError, match="tmin"):
        csg.trace(m, [[0, 0, 0]], [[1, 0, 0]], tmin=2.0, tmax=1.0)
    assert len(csg.trace(m, np.zeros((0, 3)), np.zeros((0, 3))).t) == 0


def test_tree_too_deep_is_refused():
    from mitsuba_csg.engine import device as kernel
    m = csg.Sphere(1.0)
    for i in range(kernel.MAX_STACK + 5):           # alternating operations cannot be flattened
        m = (m | csg.Sphere(0.5).translate((i * 0.01, 0, 0))) if i % 2 else (m - csg.Box(0.1).translate((0, i * 0.01, 3)))
    with pytest.raises(csg.TreeTooDeepError, match="optimize"):
        csg.prepare(m, optimize=False)


def test_ray_through_a_cone_apex_from_inside():
    # Along the axis the side quadratic has a double root at the apex; rounding made it a miss.
    cone = csg.Cone(0.0, 34.64, 20.0)
    for z in (-9.99, -9.0, -5.0):
        h = csg.trace(cone, [[0, 0, z]], [[0, 0, 1.0]])
        assert h.t[0] == pytest.approx(10.0 - z, rel=1e-5) and not h.entering[0]
    h = csg.trace(cone, [[0, 0, -30.0]], [[0, 0, 1.0]])
    assert h.t[0] == pytest.approx(20.0, rel=1e-5) and h.entering[0]


def test_new_tmin_values_do_not_recompile():
    import drjit as dr
    prepared = csg.prepare(csg.Sphere(1.0) - csg.Box(0.5))
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    csg.trace(prepared, [[0, 0, -5]], [[0, 0, 1.0]], tmin=0.01)
    dr.kernel_history()                                   # clear
    for k in range(4):
        csg.trace(prepared, [[0, 0, -5]], [[0, 0, 1.0]], tmin=0.1 + 0.1 * k)
    history = [h for h in dr.kernel_history() if h.get("operation_count", 0) > 500]
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    # One traversal kernel per call, all one kernel: a value baked into the kernel would give
    # each call its own hash (compared by hash: Dr.Jit's cache-hit flag is also set for a
    # kernel an earlier run left in the disk cache).
    assert len(history) == 4 and len({h["hash"] for h in history}) == 1, [
        {k: h.get(k) for k in ("hash", "cache_hit", "cache_disk", "operation_count", "size")} for h in history]


def test_each_loop_body_is_recorded_once(capfd):
    """Dr.Jit records a symbolic loop's body a second time when its state holds variables the
    body never changes, and a nested loop is then recorded once per recording of the loop
    around it: every trace paid that in Python. Dr.Jit's debug log names each re-recording;
    a trace with every kind of loop (sets, convex planes, a torus, a mesh, a start hint) has none."""
    import drjit as dr
    import manifold3d as m3
    holes = csg.union(*(csg.Sphere(0.3).translate((0.5 * i - 1, 0, 0)) for i in range(5)))
    model = ((csg.Box(3.0) - holes) | csg.Torus(1.0, 0.2).translate((0, 0, 2)) | csg.Prism(6, 0.5, 1.0).translate((0, 2, 0))
             | csg.Mesh.from_manifold(m3.Manifold.sphere(0.5, 16)).translate((2.5, 0, 0)))
    prepared = csg.prepare(model)
    rng = np.random.default_rng(2)
    o, d = rng.uniform(-4, 4, (64, 3)), rng.normal(size=(64, 3))
    b = prepared.tree.b
    O, D = csg.rays_to_device(o, b), csg.rays_to_device(d, b)
    first = csg.trace_rays(prepared, O, D)
    dr.eval(first.prim)
    capfd.readouterr()
    level = dr.log_level()
    dr.set_log_level(dr.LogLevel.Debug)
    try:
        again = csg.trace_rays(prepared, O, D, start_prim=first.prim)
    finally:
        dr.set_log_level(level)
    captured = capfd.readouterr()        # Dr.Jit logs to stderr, or to stdout through Python's
    log = captured.out + captured.err     # print where a Python callback took the log over
    assert "created a loop" in log, "Dr.Jit's debug log was not captured"
    assert "re-recording" not in log, [line for line in log.splitlines() if "re-recording" in line]
    np.testing.assert_array_equal(again.t.numpy(), first.t.numpy())


def test_box_test_rejects_empty_boxes():
    """The lone leaf's dummy sibling and an intersection of disjoint boxes have empty boxes;
    the slab test alone would accept rays through them (so a lone primitive was intersected
    twice). Every ray, from every direction, must be rejected."""
    import drjit as dr

    from mitsuba_csg.engine import leaf_events

    lone = csg.prepare(csg.Sphere(1.0))
    disjoint = csg.prepare((csg.Box(1.0) & csg.Box(1.0).translate((3, 0, 0))) | csg.Sphere(0.5).translate((9, 0, 0)),
                           optimize=False)
    empty_node = int(np.flatnonzero(np.any(disjoint.flat.node_lower > disjoint.flat.node_upper, axis=1))[0])
    rng = np.random.default_rng(4)
    o, d = rng.uniform(-6, 6, (256, 3)), rng.normal(size=(256, 3))
    d[:6] = np.vstack([np.eye(3), -np.eye(3)])
    for prepared, node in ((lone, lone.tree.num_nodes - 1), (disjoint, empty_node)):
        b = prepared.tree.b
        O, D = csg.rays_to_device(o, b), csg.rays_to_device(d, b)
        inv_d = b.Array3f([1.0 / D[i] for i in range(3)])
        ray = b.SceneRay(o=O, inv_d=inv_d, tmax=b.Float(1e30))
        hit = leaf_events.box_meets(prepared.tree, ray, dr.full(b.UInt32, node, 256), b.Float(-1e30))
        assert not np.any(hit.numpy())
    h = csg.trace(lone, o, d)
    compare(csg.Sphere(1.0), h, o, d)


@pytest.mark.parametrize("shape", ["cylinder", "cone", "thin_mast"])
def test_rays_from_far_away(shape):
    """Rays from 700 sizes away (the Satellites camera): the cone side's quadratic used to
    cancel in float32 there (a third of the radius off, phantom hits on a thin mast)."""
    model = {"cylinder": csg.Cylinder(0.5, 1.4),
             "cone": csg.Cone(0.5, 0.1, 1.0),
             "thin_mast": csg.Cylinder(0.05, 2.6).rotate("y", 90)}[shape]
    model = model.rotate((0.3, 0.8, 0.5), 37.0).translate((28.8, 61.9, 39.1))
    rng = np.random.default_rng(5)
    origin = np.array([321.6, -514.7, 289.4])
    targets = np.array([28.8, 61.9, 39.1]) + rng.uniform(-0.7, 0.7, (400, 3))
    d = targets - origin
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(origin, d.shape).copy()
    hits = csg.trace(model, o, d)
    stable, total = compare(model, hits, o, d)
    assert stable > 0.8 * total and np.isfinite(hits.t).sum() > 20


def test_a_second_model_of_the_same_size_class_compiles_no_kernel():
    """Model-dependent numbers are opaque and the buffers Dr.Jit's own (aligned), so tracing
    a second cheese of similar size runs the first one's kernels (Dr.Jit's kernel history)."""
    import drjit as dr
    rng = np.random.default_rng(0)
    o = np.column_stack([rng.uniform(-1, 1, (500, 2)), np.full(500, -5.0)])
    d = np.tile([0.0, 0.0, 1.0], (500, 1))
    models = [csg.prepare(cheese(200, seed=1)), csg.prepare(cheese(260, seed=2))]
    # The SAH shapes of these two sets need different walk stacks (15 and 16 waiting entries):
    # both must still fall in one size class.
    assert len({(p.tree.stack_size, p.tree.walk_stack_size) for p in models}) == 1
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()                                   # reading it clears it
        hits, kernels = [], []
        for prepared in models:
            hits.append(csg.trace(prepared, o, d))
            kernels.append({k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT})
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert all(np.isfinite(h.t).any() for h in hits)
    # Compared by hash, not by Dr.Jit's cache-hit flag: a kernel compiled by an earlier run
    # and read from the disk cache counts as a hit, so the flag passes on a warm machine only.
    new = kernels[1] - kernels[0]
    assert not new, f"{len(new)} new kernels for the second cheese"


def test_a_deeper_tree_after_a_shallow_one_gets_its_own_stacks():
    """Dr.Jit 1.5's kernel hash leaves out the sizes of `alloc_local` arrays, so a kernel
    compiled for a lone primitive (8-entry stacks) used to be reused for a 40-deep chain:
    wrong hits or a crash. The stack size is now part of the kernel (its loop condition)."""
    rng = np.random.default_rng(3)
    centres, radii = rng.uniform(-3, 3, (40, 3)), rng.uniform(0.5, 1.5, 40)
    chain = csg.Sphere(2.0)
    for i, (c, r) in enumerate(zip(centres, radii)):      # alternating: no chain to balance
        sphere = csg.Sphere(float(r)).translate(c)
        chain = chain | sphere if i % 2 else chain - sphere
    targets = np.array([leaf.matrix[:3, 3] for leaf in chain.leaves()])
    o = rng.uniform(-8, 8, (400, 3))
    d = targets[rng.integers(0, len(targets), 400)] + rng.normal(0, 0.1, (400, 3)) - o
    csg.trace(csg.Sphere(1.0), o, d)
    prepared = csg.prepare(chain, optimize=False)
    assert prepared.tree.stack_size >= 40
    hits = csg.trace(prepared, o, d)
    assert hits.unfinished == 0
    compare(chain, hits, o, d)


def test_frozen_traces_replay_the_same_hits():
    """`trace_rays(frozen=True)` replays recorded kernels (dr.freeze): new rays of a recorded
    width, and a new width, give the hits of an ordinary trace bit for bit, for an analytic
    Cheese and for a mesh leaf, and the second call of a width records nothing new."""
    import drjit as dr
    import manifold3d as m3
    from mitsuba_csg.queries import rays_to_device, trace_rays
    rng = np.random.default_rng(5)
    blob = csg.Mesh.from_manifold(m3.Manifold.sphere(1.0, 24)).scale((1.0, 0.7, 0.5))
    for model in (cheese(120, seed=4), blob - csg.Box(0.8).translate((0.6, 0, 0))):
        prepared = csg.prepare(model)
        b = prepared.tree.b
        for width in (300, 300, 77):
            o = rays_to_device(np.column_stack([rng.uniform(-1.2, 1.2, (width, 2)), np.full(width, -5.0)]), b)
            d = rays_to_device(rng.normal([0, 0, 1], 0.05, (width, 3)), b)
            frozen, plain = trace_rays(prepared, o, d, frozen=True), trace_rays(prepared, o, d)
            for name in ("t", "normal", "prim", "steps"):
                np.testing.assert_array_equal(np.asarray(getattr(frozen, name)), np.asarray(getattr(plain, name)))
            assert np.isfinite(np.asarray(plain.t)).any()
        assert len(prepared.replays) == 2
        assert all(replay.n_recordings == 1 for replay in prepared.replays.values())
    with pytest.raises(csg.CSGError, match="tmin and tmax must be numbers"):
        trace_rays(prepared, o, d, tmin=dr.zeros(b.Float, 77), frozen=True)


def test_inactive_lanes_do_no_work_and_miss():
    """`trace_rays(..., active=mask)`: the integrators pass their live lanes, so finished
    paths and unneeded shadow rays cost nothing (a csg_path frame at max_depth 1 traced every
    lane's unused shadow ray through the model: 1.30 s -> 0.41 s for Cheese-1000)."""
    import drjit as dr
    from mitsuba_csg.queries import rays_to_device, trace_rays
    rng = np.random.default_rng(9)
    prepared = csg.prepare(cheese(80, seed=3))
    b = prepared.tree.b
    n = 500
    o = rays_to_device(np.column_stack([rng.uniform(-1.2, 1.2, (n, 2)), np.full(n, -5.0)]), b)
    d = rays_to_device(np.tile([0.0, 0.0, 1.0], (n, 1)), b)
    mask = rng.random(n) < 0.5
    full = trace_rays(prepared, o, d)
    part = trace_rays(prepared, o, d, active=b.Bool(mask))
    t_full, t_part = np.asarray(full.t), np.asarray(part.t)
    np.testing.assert_array_equal(t_part[mask], t_full[mask])
    assert np.all(np.isinf(t_part[~mask])) and np.all(np.asarray(part.steps)[~mask] == 0)
    assert np.all(np.asarray(part.prim)[~mask] == 0xFFFFFFFF) and np.isfinite(t_full[~mask]).any()


# ---- Several solids in one tree (engine.grouping) ----

@pytest.mark.parametrize("traversal", TRAVERSALS)
@given(solids=st.lists(models(max_leaves=5), min_size=2, max_size=4), seed=st.integers(0, 2**31),
       optimized=st.booleans())
def test_grouped_solids_give_the_nearest_surface_of_any(solids, seed, optimized, traversal):
    """One traversal of the group finds, per ray, the nearest first hit among the solids, as
    the reference traced solid by solid says: which solid, t, normal and entering."""
    flats = [csg.prepare(m, optimize=optimized).flat for m in solids]
    grouped = group_trees(flats)
    hits = csg.trace(csg.prepare(grouped.flat, traversal=TRAVERSALS[traversal]), *make_rays(seed, 96))
    o, d = make_rays(seed, 96)
    firsts = [ref.first_hit(m, o, d) for m in solids]
    t_all = np.stack([f[0] for f in firsts])
    stable = np.all([ref.stable_mask(m, o, d) for m in solids], axis=0)
    # The nearest solid must be clear: the runner-up's surface lies further than the tolerance.
    ranked = np.sort(t_all, axis=0)
    length = np.maximum(1.0, np.linalg.norm(o, axis=1)) / np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore"):         # inf - inf where two solids are missed
        stable &= ~np.isfinite(ranked[0]) | (ranked[1] - ranked[0] > 1e-4 * length)
    assert hits.unfinished == 0
    nearest = np.argmin(t_all, axis=0)
    t_ref = t_all[nearest, np.arange(len(o))]
    hit = np.isfinite(t_ref)
    assert np.array_equal(np.isfinite(hits.t[stable]), hit[stable])
    s = np.flatnonzero(stable & hit)
    np.testing.assert_allclose(hits.t[s], t_ref[s], rtol=1e-4, atol=1e-4 * length[s].max(initial=1.0))
    solid = np.searchsorted(grouped.prim_offset, hits.prim[s], side="right") - 1
    assert np.array_equal(solid, nearest[s])
    local = hits.prim[s] - grouped.prim_offset[solid]
    for k, (_, prim_ref, n_ref, enter_ref) in enumerate(firsts):
        on_k = solid == k
        assert np.array_equal(local[on_k], prim_ref[s][on_k])
        assert np.all(np.einsum("ij,ij->i", hits.normal[s][on_k], n_ref[s][on_k]) > 0.999)
        assert np.array_equal(hits.entering[s][on_k], enter_ref[s][on_k])


def test_a_group_of_cheeses_with_mesh_leaves_agrees_with_each_alone():
    """Solids of every kind of record (meshes with their BVHs, convex planes) keep their own
    planes and BVH nodes once concatenated: the group's hits on rays that see one solid only
    are that solid's own hits."""
    mesh = csg.Mesh.from_manifold(manifold3d.Manifold.cylinder(1.0, 0.4, 0.4, 24)).translate((0, 0, -0.5))
    solids = [cheese(40, seed=1), csg.Prism(6, 0.6, 1.0).translate((3, 0, 0)) - mesh.translate((3, 0, 0)),
              mesh.translate((0, 3, 0)) | csg.Box(0.5).translate((0, 3, 0.8)), cheese(30, seed=2).translate((3, 3, 0))]
    grouped = group_trees([csg.prepare(m).flat for m in solids])
    prepared = csg.prepare(grouped.flat)
    rng = np.random.default_rng(4)
    for k, (m, centre) in enumerate(zip(solids, [(0, 0), (3, 0), (0, 3), (3, 3)])):
        # Straight down onto solid k only: no other solid lies under these rays.
        o = np.column_stack([rng.uniform(-0.7, 0.7, (300, 2)) + centre, np.full(300, 5.0)])
        d = np.tile([0.0, 0.0, -1.0], (300, 1))
        alone, group = csg.trace(m, o, d), csg.trace(prepared, o, d)
        hit = np.isfinite(alone.t)
        assert hit.mean() > 0.2
        np.testing.assert_allclose(group.t, alone.t, rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(group.prim[hit] - grouped.prim_offset[k], alone.prim[hit])
