"""Touching and coincident faces: one surface, never a phantom boundary (docs/accuracy.md).

Each primitive is intersected in its own frame in float32, so faces that coincide in the
model give events a few ulps apart; the automaton treats events of different primitives
within a tie window as one. The reproducers here once stopped rays at shared faces: stacked
boxes, two GDML boxes side by side (a calorimeter's layers), a flush-cut hole. Answers are
analytic (the union of the touching boxes is one box) or the float64 reference's.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import mitsuba_csg as csg
import reference as ref
from agreement import compare
from mitsuba_csg.formats import gdml, openscad
from strategies import make_rays, touching_models

pytestmark = pytest.mark.usefixtures("jit_variant")

N = 100_000           # rays per reproducer, one kernel launch (width N)
ALONE = 200           # of them, also traced one per launch (width 1)


def box_span(lo, hi, o, d):
    """(entry, exit) t of rays in the box [lo, hi] (entry < 0 for origins inside), and the
    |cos| of the ray with the face of each."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    near, far = np.minimum(t1, t2), np.maximum(t1, t2)
    rows = np.arange(len(o))
    cos_entry = np.abs(d[rows, np.nanargmax(near, axis=1)])
    cos_exit = np.abs(d[rows, np.nanargmin(far, axis=1)])
    return np.nanmax(near, axis=1), np.nanmin(far, axis=1), cos_entry, cos_exit


def trace_both_widths(model, o, d):
    """Hits of all rays at once, and of the first ALONE rays one at a time (same prepared tree)."""
    prepared = csg.prepare(model)
    wide = csg.trace(prepared, o, d)
    alone = np.array([csg.trace(prepared, o[i:i + 1], d[i:i + 1]).t[0] for i in range(ALONE)])
    return wide, alone


def assert_box_answers(model, lo, hi, o, d, atol):
    """Every ray: the box's exit from inside, its entry from outside (atol: float32 at this
    scale at normal incidence, growing as 1 / |cos| at the face; a phantom face is 1 mm off)."""
    entry, exit_, cos_entry, cos_exit = box_span(np.asarray(lo, float), np.asarray(hi, float), o, d)
    outside = entry > 0
    expected = np.where(outside, entry, exit_)
    expected = np.where(entry <= exit_, expected, np.inf)
    atol = atol / np.maximum(np.where(outside, cos_entry, cos_exit), 1e-3)
    wide, alone = trace_both_widths(model, o, d)
    assert wide.unfinished == 0
    wrong = ~(np.isclose(wide.t, expected, rtol=0, atol=atol) | (np.isinf(wide.t) & np.isinf(expected)))
    i = np.flatnonzero(wrong)[:3]
    assert not wrong.any(), f"{wrong.sum()} of {len(o)} rays wrong, e.g. o={o[i].tolist()} d={d[i].tolist()} " \
                            f"got {wide.t[i]} expected {expected[i]}"
    first = expected[:ALONE]
    assert np.all(np.isclose(alone, first, rtol=0, atol=atol[:ALONE]) | (np.isinf(alone) & np.isinf(first)))


def inside_and_outside_rays(lo, hi, inside_lo, inside_hi, seed):
    """Half the rays start inside [inside_lo, inside_hi], half outside the box, aimed at it."""
    rng = np.random.default_rng(seed)
    half = N // 2
    o_in = rng.uniform(inside_lo, inside_hi, (half, 3))
    d_in = rng.normal(size=(half, 3))
    centre, radius = (np.asarray(lo) + hi) / 2, np.linalg.norm(np.subtract(hi, lo))
    o_out = rng.normal(size=(N - half, 3))
    o_out = centre + radius * o_out / np.linalg.norm(o_out, axis=1)[:, None]
    d_out = rng.uniform(lo, hi, (N - half, 3)) - o_out
    o, d = np.vstack([o_in, o_out]), np.vstack([d_in, d_out])
    return o, d / np.linalg.norm(d, axis=1)[:, None]


def test_stacked_boxes_have_no_inner_face():
    m = csg.Box((600, 600, 600)).translate((0, 0, -200)) | csg.Box((600, 600, 300)).translate((0, 0, 250))
    lo, hi = (-300, -300, -500), (300, 300, 400)
    # The rays: straight down from z in (101, 150), which once stopped at z = 100.
    rng = np.random.default_rng(1)
    o = np.column_stack([rng.uniform(-290, 290, N), rng.uniform(-290, 290, N), rng.uniform(101, 150, N)])
    d = np.tile([0.0, 0.0, -1.0], (N, 1))
    assert_box_answers(m, lo, hi, o, d, atol=2e-3)
    o, d = inside_and_outside_rays(lo, hi, (-290, -290, 101), (290, 290, 150), seed=2)
    assert_box_answers(m, lo, hi, o, d, atol=2e-3)


def test_gdml_boxes_side_by_side_have_no_inner_face():
    """Two layers 2.3 mm and 5.7 mm wide sharing the face x = -197.7, as placed by GDML."""
    text = """<?xml version="1.0"?>
<gdml><define/><materials/>
<solids><box name="W" x="1" y="1" z="1" lunit="m"/>
  <box name="gap" x="2.3" y="400" z="400" lunit="mm"/><box name="absorber" x="5.7" y="400" z="400" lunit="mm"/></solids>
<structure>
  <volume name="G"><materialref ref="lAr"/><solidref ref="gap"/></volume>
  <volume name="A"><materialref ref="Pb"/><solidref ref="absorber"/></volume>
  <volume name="World"><materialref ref="G4_AIR"/><solidref ref="W"/>
    <physvol><volumeref ref="G"/><position name="p1" x="-198.85" y="0" z="0" unit="mm"/></physvol>
    <physvol><volumeref ref="A"/><position name="p2" x="-194.85" y="0" z="0" unit="mm"/></physvol>
  </volume>
</structure>
<setup name="Default" version="1.0"><world ref="World"/></setup></gdml>"""
    m = gdml.loads(text, "layers.gdml")
    lo, hi = (-200, -200, -200), (-192, 200, 200)
    o, d = inside_and_outside_rays(lo, hi, (-199.99, -190, -190), (-197.71, 190, 190), seed=3)
    assert_box_answers(m, lo, hi, o, d, atol=2e-3)
    # Along the layers' normal, from inside the first: out at x = -192, as Geant4 says.
    rng = np.random.default_rng(4)
    o = np.column_stack([rng.uniform(-199.99, -197.71, N), rng.uniform(-190, 190, (N, 2))])
    d = np.tile([1.0, 0.0, 0.0], (N, 1))
    assert_box_answers(m, lo, hi, o, d, atol=2e-3)


FLUSH_CUTS = {
    "cylinder": "difference() { cube([10, 10, 10]); multmatrix([[1,0,0,5],[0,1,0,5],[0,0,1,0],[0,0,0,1]]) "
                "cylinder(h = 10, r1 = 2, r2 = 2, center = false); }",
    "cone": "difference() { cube([10, 10, 10]); multmatrix([[1,0,0,5],[0,1,0,5],[0,0,1,0],[0,0,0,1]]) "
            "cylinder(h = 10, r1 = 2, r2 = 1, center = false); }",
    "prism": None,
    "cylinder minus box": None,
}


def flush_cut(name):
    """A solid with a hole cut flush through it (top and bottom faces shared), the hole's
    axis point, and the radii of discs inside the opening at z = 0 and z = 10."""
    if name == "cylinder":
        return openscad.loads(FLUSH_CUTS[name], "hole.csg"), (5.0, 5.0), (2.0, 2.0)
    if name == "cone":
        return openscad.loads(FLUSH_CUTS[name], "hole.csg"), (5.0, 5.0), (2.0, 1.0)
    if name == "prism":
        cube = csg.Box(10.0).translate((5, 5, 5))
        return cube - csg.Prism(6, 2.0, 10.0).rotate("z", 17).translate((5, 5, 5)), (5.0, 5.0), (1.7, 1.7)
    drum = csg.Cylinder(5.0, 10.0).translate((5, 5, 5))
    return drum - csg.Box((2, 2, 10)).rotate("z", 30).translate((5, 5, 5)), (5.0, 5.0), (1.0, 1.0)


@pytest.mark.parametrize("name", FLUSH_CUTS)
def test_flush_cut_hole_has_no_film(name):
    m, (cx, cy), (r_bottom, r_top) = flush_cut(name)
    radius = min(r_bottom, r_top)
    rng = np.random.default_rng(5)
    half = N // 2
    # From above (the ray among them) into the opening, and from inside the hole.
    o_top = np.tile([5.0, -4.0, 26.0], (half, 1)) + rng.normal(scale=3.0, size=(half, 3))
    aim = np.column_stack([cx + rng.uniform(-radius, radius, half), cy + rng.uniform(-radius, radius, half),
                           np.full(half, 10.0)])
    r, phi = 0.9 * radius * np.sqrt(rng.random(N - half)), rng.uniform(0, 2 * np.pi, N - half)
    o_hole = np.column_stack([cx + r * np.cos(phi), cy + r * np.sin(phi), rng.uniform(0.5, 9.5, N - half)])
    d_hole = rng.normal(size=(N - half, 3)) * [0.2, 0.2, 1.0]
    o = np.vstack([[5.0, -4.0, 26.0], o_top[1:], o_hole])
    d = np.vstack([[0.0074546309, 0.49190256, -0.87061834], aim[1:] - o_top[1:], d_hole])
    d /= np.linalg.norm(d, axis=1)[:, None]
    wide, alone = trace_both_widths(m, o, d)
    # No hit inside the opening on the shared planes z = 0 and z = 10.
    p = o + np.where(np.isfinite(wide.t), wide.t, 0.0)[:, None] * d
    off_axis = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
    film = np.isfinite(wide.t) & (((np.abs(p[:, 2]) < 1e-3) & (off_axis < 0.8 * r_bottom))
                                  | ((np.abs(p[:, 2] - 10) < 1e-3) & (off_axis < 0.8 * r_top)))
    assert not film.any(), f"{film.sum()} film hits, e.g. o={o[film][0].tolist()} d={d[film][0].tolist()}"
    assert wide.t[0] > 19.0             # the ray passes the opening (z = 10 at t = 18.38) to the wall
    # And the float64 reference agrees everywhere it is well-conditioned, at both widths.
    some = slice(0, None, 5)
    compare(m, csg.trace(m, o[some], d[some]), o[some], d[some], coincident=True)
    t_ref = ref.first_hit(m, o[:ALONE], d[:ALONE])[0]
    stable = ref.stable_mask(m, o[:ALONE], d[:ALONE], same=1e-9)
    np.testing.assert_allclose(alone[stable], t_ref[stable], rtol=1e-4, atol=1e-4)


def test_thin_features_above_the_tolerance_are_seen():
    """A gap between two boxes and a box's wall, 1e-4 of the scene thick (tens of tie
    windows at normal incidence), bounded by faces of different primitives."""
    size, thin = 100.0, 1e-2
    half = size / 2 - thin / 2
    gap = csg.Box((half, size, size)).translate((-(thin + half) / 2, 0, 0)) | \
        csg.Box((half, size, size)).translate(((thin + half) / 2, 0, 0))
    shell = csg.Box(size) - csg.Box(size - 2 * thin)
    rng = np.random.default_rng(6)
    yz = rng.uniform(-40, 40, (1000, 2))
    d = np.tile([1.0, 0.0, 0.0], (1000, 1))
    inside_left = np.column_stack([np.full(1000, -25.0), yz])
    np.testing.assert_allclose(csg.trace(gap, inside_left, d).t, 25 - thin / 2, atol=1e-4)
    outside = np.column_stack([np.full(1000, -100.0), yz])
    np.testing.assert_allclose(csg.trace(shell, outside, d).t, 50.0, atol=1e-4)
    cavity = np.column_stack([np.zeros(1000), yz])
    h = csg.trace(shell, cavity, d)
    np.testing.assert_allclose(h.t, size / 2 - thin, atol=1e-4)
    assert np.all(h.entering)


@given(model=touching_models(), seed=st.integers(0, 2**31))
def test_touching_copies_in_different_frames_agree_with_reference(model, seed):
    """Rotated, translated and scaled solids placed face to face, nested in random trees."""
    o, d = make_rays(seed, 96, radius=6.0, target=2.0)
    compare(model, csg.trace(model, o, d), o, d, coincident=True)
