"""The OpenSCAD `.csg` loader: hand-written files for every node, modifier and error, OpenSCAD's
own examples (exported by `openscad` when it is installed) against its STL export, and a fuzz
test that only ever sees FormatError / ModelError.
"""
import itertools
import math
import os
import random
import re
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest

import mitsuba_csg as csg
from mitsuba_csg.formats import openscad
from mitsuba_csg.errors import ModelError
from mitsuba_csg.formats.openscad import FormatError, OpenSCADWarning


def load(text, **kw):
    return openscad.loads(text, "t.csg", **kw)


def inside(model, *points):
    return csg.contains(model, np.array(points, dtype=float)).tolist()


def bounds(model):
    lo, hi = model.bounds()
    return np.round(lo, 9).tolist(), np.round(hi, 9).tolist()


def mc_volume(model, lo, hi, n=200_000, seed=1):
    rng = np.random.default_rng(seed)
    p = rng.uniform(lo, hi, size=(n, 3))
    frac = csg.contains(model, p).mean()
    box = float(np.prod(np.asarray(hi) - lo))
    return frac * box, math.sqrt(max(frac * (1 - frac), 1e-12) / n) * box


# ---- Primitives and their conventions ----

def test_cube_has_its_corner_at_the_origin():
    m = load("cube(size = [2, 4, 6], center = false);")
    assert bounds(m) == ([0, 0, 0], [2, 4, 6])
    assert inside(m, (1, 2, 3), (-0.1, 2, 3), (1.9, 3.9, 5.9)) == [True, False, True]
    assert bounds(load("cube([2, 4, 6]);")) == ([0, 0, 0], [2, 4, 6])        # positional
    assert bounds(load("cube(2);")) == ([0, 0, 0], [2, 2, 2])                 # scalar size
    assert bounds(load("cube();")) == ([0, 0, 0], [1, 1, 1])                  # default 1


def test_centred_cube():
    m = load("cube(size = [2, 4, 6], center = true);")
    assert bounds(m) == ([-1, -2, -3], [1, 2, 3])
    assert isinstance(m, csg.Box) and m.size == (2, 4, 6)
    assert bounds(load("cube([2, 4, 6], true);")) == ([-1, -2, -3], [1, 2, 3])


def test_sphere_radius_and_diameter():
    m = load("sphere($fn = 0, $fa = 12, $fs = 2, r = 5);")
    assert isinstance(m, csg.Sphere) and m.radius == 5
    assert load("sphere(d = 4);").radius == 2
    assert load("sphere(3);").radius == 3
    assert load("sphere();").radius == 1
    t = csg.trace(m, [[0, 0, -10]], [[0, 0, 1]]).t
    assert t[0] == pytest.approx(5, abs=1e-5)


def test_cylinder_spans_zero_to_h_unless_centred():
    m = load("cylinder($fn = 0, $fa = 12, $fs = 2, h = 10, r1 = 2, r2 = 2, center = false);")
    assert bounds(m) == ([-2, -2, 0], [2, 2, 10])
    leaf = m.leaves()[0]
    assert (leaf.radius_bottom, leaf.radius_top, leaf.height) == (2, 2, 10)
    c = load("cylinder(h = 10, r1 = 2, r2 = 2, center = true);")
    assert bounds(c) == ([-2, -2, -5], [2, 2, 5])
    assert bounds(load("cylinder(h = 4, r = 1);")) == ([-1, -1, 0], [1, 1, 4])
    assert bounds(load("cylinder(h = 4, d = 1);")) == ([-0.5, -0.5, 0], [0.5, 0.5, 4])
    assert bounds(load("cylinder(4, 1, 1, true);")) == ([-1, -1, -2], [1, 1, 2])
    assert bounds(load("cylinder();")) == ([-1, -1, 0], [1, 1, 1])


def test_cone_with_a_zero_radius_end():
    m = load("cylinder(h = 10, r1 = 3, r2 = 0, center = false);")
    leaf = m.leaves()[0]
    assert (leaf.radius_bottom, leaf.radius_top) == (3, 0)
    # wide at z = 0, a point at z = 10
    assert inside(m, (2.9, 0, 0.05), (0, 0, 9.9), (1, 0, 9), (0.2, 0, 9)) == [True, True, False, True]
    up = load("cylinder(h = 10, r1 = 0, r2 = 3, center = true);")
    assert inside(up, (2.9, 0, 4.95), (2.9, 0, -4.95)) == [True, False]
    # a ray along x at z = 5 meets the cone at radius 1.5
    t = csg.trace(m, [[-10, 0, 5]], [[1, 0, 0]]).t
    assert t[0] == pytest.approx(10 - 1.5, abs=1e-4)


def test_multmatrix_rotation_and_translation():
    # rotate 90 degrees about z, then translate by (10, 0, 0): x' = -y + 10, y' = x
    m = load("""multmatrix([[6.12323e-17, -1, 0, 10], [1, 6.12323e-17, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) {
                    cube(size = [4, 1, 1], center = false);
                }""")
    lo, hi = m.bounds()
    np.testing.assert_allclose(lo, [9, 0, 0], atol=1e-6)
    np.testing.assert_allclose(hi, [10, 4, 1], atol=1e-6)
    # a 3x4 matrix and a single child without braces
    m = load("multmatrix(m = [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5]]) sphere(1);")
    lo, hi = m.bounds()
    np.testing.assert_allclose(lo, [-2, -1, 4], atol=1e-6)
    np.testing.assert_allclose(hi, [2, 1, 6], atol=1e-6)


def test_color_names_the_material():
    m = load("color([0.8, 0.2, 0.2, 1]) { cube(); }")
    assert m.leaves()[0].material == "color_0.8_0.2_0.2_1"
    assert load("color([0, 0.501961, 0]) cube();").leaves()[0].material == "color_0_0.501961_0_1"
    assert load('color("red") cube();').leaves()[0].material == "red"
    assert load('color(c = [1, 0, 0], alpha = 0.5) cube();').leaves()[0].material == "color_1_0_0_0.5"
    nested = load("color([1, 0, 0, 1]) { cube(); color([0, 0, 1, 1]) sphere(); }")
    assert [leaf.material for leaf in nested.leaves()] == ["color_1_0_0_1", "color_0_0_1_1"]   # inner wins


def test_booleans():
    text = """group() {
        difference() {
            cube(size = [2, 2, 2], center = true);
            sphere(r = 0.5);
            multmatrix([[1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) sphere(r = 0.5);
        }
    }"""
    m = load(text)
    assert inside(m, (0, 0, 0), (0.9, 0.9, 0.9), (0.9, 0, 0), (-0.7, 0, 0)) == [False, True, False, True]
    i = load("intersection() { cube(size = 2, center = true); sphere(r = 1.2); }")
    assert inside(i, (0, 0, 0), (0.95, 0.95, 0.95), (0.9, 0, 0)) == [True, False, True]
    u = load("union() { cube(size = 1); multmatrix([[1,0,0,3],[0,1,0,0],[0,0,1,0],[0,0,0,1]]) cube(size = 1); }")
    assert inside(u, (0.5, 0.5, 0.5), (3.5, 0.5, 0.5), (2, 0.5, 0.5)) == [True, True, False]
    r = load("render(convexity = 2) { sphere(1); }")
    assert isinstance(r, csg.Sphere)
    # a ray through the difference: enters the box at x=-1, leaves at the first hole
    t = csg.trace(m, [[-5, 0, 0]], [[1, 0, 0]]).t
    assert t[0] == pytest.approx(4, abs=1e-5)


def test_convex_polyhedron():
    # example011.scad: a square pyramid (faces clockwise seen from outside)
    text = ("polyhedron(points = [[10, 0, 0], [0, 10, 0], [-10, 0, 0], [0, -10, 0], [0, 0, 10]], "
            "faces = [[0, 1, 2, 3], [4, 1, 0], [4, 2, 1], [4, 3, 2], [4, 0, 3]], convexity = 1);")
    m = load(text)
    assert isinstance(m, csg.ConvexPolyhedron) and len(m.planes) == 5
    assert inside(m, (0, 0, 1), (0, 0, 9.5), (6, 6, 1), (0, 0, -0.1)) == [True, True, False, False]
    vol, err = mc_volume(m, (-10, -10, 0), (10, 10, 10), n=100_000)
    assert vol == pytest.approx(200 * 10 / 3, abs=4 * err)
    # the same with the faces reversed (counter-clockwise) and a cube split into triangles
    rev = text.replace("[0, 1, 2, 3], [4, 1, 0], [4, 2, 1], [4, 3, 2], [4, 0, 3]",
                       "[3, 2, 1, 0], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]")
    assert len(load(rev).planes) == 5
    tri_cube = ("polyhedron(points = [[0,0,0],[1,0,0],[1,1,0],[0,1,0],[0,0,1],[1,0,1],[1,1,1],[0,1,1]], "
                "triangles = [[0,1,2],[0,2,3],[4,6,5],[4,7,6],[0,4,5],[0,5,1],[1,5,6],[1,6,2],"
                "[2,6,7],[2,7,3],[3,7,4],[3,4,0]]);")
    cube = load(tri_cube)
    assert len(cube.planes) == 6
    assert bounds(cube) == ([0, 0, 0], [1, 1, 1])


def test_non_convex_polyhedra_are_mesh_leaves_and_open_ones_are_skipped():
    # a cube with a dent: the top centre vertex pushed down (faces clockwise seen from outside)
    dented = """group() {
polyhedron(points = [[0,0,0],[2,0,0],[2,2,0],[0,2,0],[0,0,2],[2,0,2],[2,2,2],[0,2,2],[1,1,1]],
  faces = [[0,1,2,3],[5,4,8],[6,5,8],[7,6,8],[4,7,8],[0,4,5,1],[1,5,6,2],[2,6,7,3],[3,7,4,0]]);
}"""
    m = load(dented)
    assert isinstance(m, csg.Mesh)
    hits = csg.trace(m, [[1.0, 1.0, 5.0], [0.25, 0.25, 5.0], [1.0, 1.0, -5.0]], [[0, 0, -1.0], [0, 0, -1.0], [0, 0, 1.0]])
    assert np.allclose(hits.t, [4.0, 3.25, 5.0]) and hits.entering.all()     # the dent's tip, its slope, the base
    assert csg.to_mesh(m).volume() == pytest.approx(8.0 - 4.0 / 3.0)
    open_box = ("polyhedron(points = [[0,0,0],[1,0,0],[1,1,0],[0,1,0],[0,0,1],[1,0,1],[1,1,1],[0,1,1]], "
                "faces = [[0,1,2,3],[0,4,5,1],[1,5,6,2],[2,6,7,3],[3,7,4,0]]);")
    # Malformed polyhedra: OpenSCAD reports them and renders the rest of the file; so do we.
    for bad, pattern in ((open_box, r"line 1, column 20: polyhedron: neither a closed convex solid nor a closed, "
                                    r"consistently oriented mesh .*not closed"),
                         ("polyhedron(points = [[0,0,0],[1,0,0],[0,1,0],[0,0,1]], faces = [[0,1,9]]);", "refers to point 9"),
                         ("polyhedron(points = [[0,0,0],[1,0,0],[0,1,0],[0,0,1]], faces = [[0,1,2.5]]);",
                          "integer point indices"),
                         ("polyhedron(points = [[0,0],[1,0,0]], faces = [[0,1,2]]);", "points must be")):
        with pytest.warns(OpenSCADWarning, match=pattern):
            assert isinstance(load(f"union() {{ cube(1); {bad} }}"), csg.Box)


# ---- 2D outlines and extrusions (mesh leaves with OpenSCAD's facets) ----

def test_linear_extrude_of_a_square_is_the_box():
    m = load("linear_extrude(height = 3, center = true, convexity = 1, scale = [1, 1], $fn = 0, $fa = 12, $fs = 2) "
             "{ square(size = [2, 1], center = true); }")
    assert isinstance(m, csg.Mesh)
    rng = np.random.default_rng(0)
    o, d = rng.uniform(-4, 4, (500, 3)), rng.uniform(-1, 1, (500, 3))
    d -= o
    a, b = csg.trace(m, o, d), csg.trace(csg.Box((2.0, 1.0, 3.0)), o, d)
    assert np.array_equal(np.isfinite(a.t), np.isfinite(b.t))
    assert np.allclose(a.t[np.isfinite(a.t)], b.t[np.isfinite(b.t)], atol=1e-5)


def test_circles_have_openscads_fragments():
    """$fn = 6: a hexagon; the defaults ($fa = 12, $fs = 2) give r = 1 five segments and r = 20
    thirty (OpenSCAD's get_fragments_from_r); rotate_extrude uses the rule on the outline's
    largest x."""
    def volume(text):
        return csg.to_mesh(load(text)).volume()
    hexagon = 3 * math.sqrt(3) / 2
    assert volume("linear_extrude(height = 2) circle(r = 1, $fn = 6);") == pytest.approx(2 * hexagon)
    polygon_area = lambda n, r: 0.5 * n * r * r * math.sin(2 * math.pi / n)           # noqa: E731
    assert volume("linear_extrude(height = 1) circle(r = 1, $fn = 0, $fa = 12, $fs = 2);") == \
        pytest.approx(polygon_area(5, 1.0))
    assert volume("linear_extrude(height = 1) circle(r = 20, $fn = 0, $fa = 12, $fs = 2);") == \
        pytest.approx(polygon_area(30, 20.0))
    ring = volume("rotate_extrude($fn = 64) multmatrix([[1, 0, 0, 2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) "
                  "square(1);")
    # A polygonal ring: the square swept by 64 flat sectors (Pappus on the inscribed polygon).
    assert ring == pytest.approx(64 * math.sin(2 * math.pi / 64) / 2 * (3**2 - 2**2) * 1.0, rel=1e-6)   # float32 vertices


def test_polygon_paths_and_2d_booleans():
    frame = ("linear_extrude(height = 1) polygon(points = [[0,0],[4,0],[4,4],[0,4],[1,1],[3,1],[3,3],[1,3]], "
             "paths = [[0,1,2,3],[4,5,6,7]]);")
    assert csg.to_mesh(load(frame)).volume() == pytest.approx(16 - 4)
    cut = ("linear_extrude(height = 2) difference() { square(4); "
           "multmatrix([[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1]]) square(2); }")
    assert csg.to_mesh(load(cut)).volume() == pytest.approx(2 * 12)
    with pytest.warns(OpenSCADWarning, match="ignoring its 3D children"):
        m = load("linear_extrude(height = 1) { square(1); cube(5); }")
    assert csg.to_mesh(m).volume() == pytest.approx(1.0)
    with pytest.raises(FormatError, match="the model is 2D"):
        load("square(2);")
    with pytest.warns(OpenSCADWarning, match="both sides of the axis"):
        with pytest.raises(FormatError, match="the model is empty"):
            load("rotate_extrude() square(1, center = true);")


# ---- hull() and minkowski(): of OpenSCAD's faceted solids ----

def test_hull_and_minkowski_of_faceted_solids():
    """The hull of a cube is the box; the Minkowski sum of a cube and a four-sided cylinder
    and the 2D hull of two octagons have the volumes manifold3d computes for the same facets."""
    import manifold3d as m3
    box = load("hull() { cube(size = [2, 2, 2], center = true); }")
    rng = np.random.default_rng(0)
    o, d = rng.uniform(-3, 3, (300, 3)), rng.uniform(-1, 1, (300, 3))
    d -= o
    a, b = csg.trace(box, o, d), csg.trace(csg.Box(2.0), o, d)
    assert np.array_equal(np.isfinite(a.t), np.isfinite(b.t))
    rounded = load("minkowski() { cube(size = [2, 2, 2], center = true); "
                   "cylinder(h = 1, r1 = 1, r2 = 1, center = true, $fn = 4, $fa = 12, $fs = 2); }")
    expected = m3.Manifold.minkowski_sum(m3.Manifold.cube([2, 2, 2], center=True),
                                         m3.Manifold.cylinder(1.0, 1.0, 1.0, 4, center=True)).volume()
    assert csg.to_mesh(rounded).volume() == pytest.approx(expected)
    hull2d = load("linear_extrude(height = 1) hull() { circle(r = 1, $fn = 8); "
                  "multmatrix([[1, 0, 0, 3], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) circle(r = 1, $fn = 8); }")
    octagon = m3.CrossSection.circle(1.0, 8)
    expected = m3.CrossSection.batch_hull([octagon, octagon.translate((3.0, 0.0))]).area()
    assert csg.to_mesh(hull2d).volume() == pytest.approx(expected)
    # a union operand is no longer refused: manifold3d sums OpenSCAD's facets (see below)
    assert isinstance(load("minkowski() { union() { cube(1); sphere(1); } sphere(1); }"), csg.Mesh)


# ---- Modifiers ----

def test_modifiers():
    base = "cube(size = 2, center = true);"
    m = load("group() { %sphere(r = 5); " + base + " }")
    assert isinstance(m, csg.Box)                     # background: dropped
    m = load("group() { *sphere(r = 5); " + base + " }")
    assert isinstance(m, csg.Box)                     # disabled: dropped
    m = load("difference() { " + base + " #sphere(r = 0.5); }")
    assert inside(m, (0, 0, 0), (0.8, 0.8, 0.8)) == [False, True]     # highlight: kept
    m = load("difference() { " + base + " multmatrix([[1,0,0,9],[0,1,0,0],[0,0,1,0],[0,0,0,1]]) { !sphere(r = 0.5); } }")
    assert isinstance(m, csg.Sphere) and bounds(m) == ([-0.5] * 3, [0.5] * 3)   # root: alone, untransformed
    # a background subtree is not evaluated: its unsupported nodes are no error
    assert isinstance(load("group() { %linear_extrude(height = 1) square(1); " + base + " }"), csg.Box)
    # a background first operand is no operand of a difference (OpenSCAD skips it)
    m = load("difference() { %cube(10); " + base + " sphere(0.5); }")
    assert inside(m, (0, 0, 0), (0.8, 0.8, 0.8)) == [False, True]


# ---- Nothing: degenerate solids and empty groups ----

def test_degenerate_solids_produce_nothing():
    with pytest.warns(OpenSCADWarning, match="line 1.*cylinder.*no volume"):
        m = load("group() { cylinder(h = 1, r1 = 0, r2 = 0); sphere(1); }")
    assert isinstance(m, csg.Sphere)
    for text in ("cube(size = [1, 0, 1]);", "sphere(r = 0);", "cylinder(h = 0, r = 1);", "cube(-1);"):
        with pytest.warns(OpenSCADWarning):
            with pytest.raises(FormatError, match="the model is empty"):
                load(text)
    with pytest.warns(OpenSCADWarning, match="singular"):
        m = load("group() { multmatrix([[1,0,0,0],[0,1,0,0],[0,0,0,0],[0,0,0,1]]) cube(1); sphere(1); }")
    assert isinstance(m, csg.Sphere)


def test_empty_operands_follow_openscad():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OpenSCADWarning)
        # difference with an empty first operand is empty
        with pytest.raises(FormatError, match="empty"):
            load("difference() { sphere(r = 0); cube(1); }")
        # an empty later operand removes nothing
        assert isinstance(load("difference() { cube(1); sphere(r = 0); }"), csg.Box)
        # an intersection with an empty operand is empty
        with pytest.raises(FormatError, match="empty"):
            load("intersection() { cube(1); cube(0); }")
        # ... but a group with no children at all is no operand
        assert isinstance(load("difference() { group(); cube(1); }"), csg.Box)
        assert isinstance(load("intersection() { group(); cube(1); }"), csg.Box)
        m = load("group() { difference() { cube(0); cube(1); } sphere(1); }")
        assert isinstance(m, csg.Sphere)
    with pytest.raises(FormatError, match="empty"):
        load("group();")
    with pytest.raises(FormatError, match="empty"):
        load("// nothing here\n")


# ---- Unsupported nodes ----

@pytest.mark.parametrize("name", sorted(openscad.UNSUPPORTED_NODES))
def test_unsupported_nodes_are_refused_by_name(name):
    text = f"group() {{\n  cube(1);\n  {name}(convexity = 1) {{ square(size = [1, 1], center = false); }}\n}}"
    with pytest.raises(FormatError, match=rf"t\.csg: line 3, column 3: {name} \(.*\) is not supported"):
        load(text)
    with pytest.warns(OpenSCADWarning, match=rf"line 3, column 3: {name} .*skipped"):
        m = load(text, on_unsupported="skip")
    assert isinstance(m, csg.Box)


def test_unknown_node():
    with pytest.raises(FormatError, match=r"line 2, column 3: unknown node 'frobnicate'"):
        load("group() {\n  frobnicate(x = 1);\n}")
    with pytest.warns(OpenSCADWarning, match="frobnicate"):
        with pytest.raises(FormatError, match="empty"):
            load("frobnicate();", on_unsupported="skip")
    with pytest.raises(ModelError, match="on_unsupported"):
        load("cube();", on_unsupported="maybe")


def test_skipped_first_operand_empties_a_difference():
    with pytest.warns(OpenSCADWarning):
        with pytest.raises(FormatError, match="empty"):
            load("difference() { surface(file = \"h.dat\"); cube(1); }", on_unsupported="skip")


def test_offset_and_resize():
    def area(text):
        m = load(f"linear_extrude(height = 1) {{ {text} }}")
        return csg.to_mesh(m).volume()
    # offset(delta) of a square keeps sharp corners; r rounds them (OpenSCAD's fragments)
    assert area("offset(delta = 1) square(size = [2, 2]);") == pytest.approx(16.0)
    # a chamfer cuts each corner square at distance delta from the corner (Clipper's square join)
    assert area("offset(delta = 1, chamfer = true) square(size = [2, 2]);") == \
        pytest.approx(16.0 - 4 * (math.sqrt(2) - 1) ** 2)
    n = 30                                       # fragments of r = 1 with $fn = 30
    rounded = 4 + 4 * 2 + n * math.sin(2 * math.pi / n) / 2
    assert area("offset(r = 1, $fn = 30) square(size = [2, 2]);") == pytest.approx(rounded, rel=2e-3)
    assert area("offset(delta = -0.5) square(size = [2, 2]);") == pytest.approx(1.0)
    # resize: new sizes scale their axes; auto takes the largest one's scale for the zero ones
    m = load("resize(newsize = [4, 0, 0], auto = [false, true, false]) cube(size = [2, 1, 3]);")
    lo, hi = m.bounds()
    assert np.allclose(hi - lo, [4, 2, 3])
    m = load("resize(newsize = [0, 0, 6]) sphere(r = 1);")
    assert np.allclose(np.subtract(*m.bounds()[::-1]), [2, 2, 6])
    m = load("linear_extrude(height = 1) resize(newsize = [10, 5]) circle(r = 1, $fn = 64);")
    assert np.allclose(np.subtract(*m.bounds()[::-1])[:2], [10, 5], rtol=1e-6)


@pytest.mark.skipif(shutil.which("openscad") is None, reason="text() is drawn by OpenSCAD, which is not installed")
def test_text_is_the_outline_openscad_draws():
    m = load('linear_extrude(height = 2) text(text = "Hi", size = 10, font = "Liberation Sans", $fn = 16);')
    assert isinstance(m, csg.Mesh)
    lo, hi = m.bounds()
    assert 8 < hi[1] - lo[1] < 11 and hi[2] - lo[2] == pytest.approx(2.0)    # cap height of size 10
    # a quote and a backslash in the text are written back to OpenSCAD escaped
    m = load('linear_extrude(height = 1) text(text = "a\\"b\\\\", size = 5);')
    assert csg.to_mesh(m).volume() > 1
    with pytest.raises(FormatError, match="empty"):
        load('linear_extrude(height = 1) text(text = "   ");')


def test_text_without_openscad_says_how_to_install(monkeypatch):
    from mitsuba_csg.formats.openscad import tool as openscad_tool
    monkeypatch.setenv("MITSUBA_CSG_OPENSCAD", "/nonexistent/openscad")
    monkeypatch.setattr(openscad_tool, "_TEXT_CACHE", {})
    with pytest.raises(FormatError, match=r"line 1, column 28: text\(\) needs OpenSCAD .* apt-get install openscad"):
        load('linear_extrude(height = 1) text(text = "x");')
    with pytest.warns(OpenSCADWarning, match="text: skipped"):
        assert isinstance(load('union() { cube(1); linear_extrude(height = 1) text(text = "x"); }',
                               on_unsupported="skip"), csg.Box)


def test_hull_and_minkowski_of_any_solid():
    # the hull of a cube minus a sphere is the cube; of an extrusion, its corners' hull
    m = load("hull() { difference() { cube(size = [2, 2, 2], center = true); sphere(r = 0.5, $fn = 24); } }")
    assert isinstance(m, csg.ConvexPolyhedron)
    assert csg.to_mesh(m).volume() == pytest.approx(8.0)
    m = load("hull() { linear_extrude(height = 1) polygon(points = [[0, 0], [2, 0], [1, 0.5], [1, 2]]); }")
    assert csg.to_mesh(m).volume() == pytest.approx(2.0)            # triangle (0,0) (2,0) (1,2), height 1
    # Minkowski sum of a non-convex L-shape and a cube: manifold3d's sum, a mesh leaf
    m = load("minkowski() { union() { cube(size = [3, 1, 1]); cube(size = [1, 3, 1]); } "
             "cube(size = [1, 1, 1], center = true); }")
    assert isinstance(m, csg.Mesh)
    # (3 + 1) x 2 x 2 for the bar plus 2 x 2 x 2 for the rest of the other arm
    assert csg.to_mesh(m).volume() == pytest.approx(4 * 2 * 2 + 2 * 2 * 2, rel=1e-9)
    lo, hi = m.bounds()
    assert np.allclose(lo, [-0.5, -0.5, -0.5]) and np.allclose(hi, [3.5, 3.5, 1.5])
    inside = csg.contains(m, np.array([[2.9, 2.9, 0.5], [0.5, 3.2, 0.5], [3.2, 0.5, 0.5]]))
    assert inside.tolist() == [False, True, True]                      # the L's notch stays open


def test_rotate_extrude_of_an_outline_at_negative_x():
    # OpenSCAD sweeps an outline wholly at x <= 0 like its mirror, and drops one across the axis
    a = load("rotate_extrude($fn = 32) multmatrix([[1, 0, 0, -3], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) "
             "square(size = [1, 1]);")
    b = load("rotate_extrude($fn = 32) multmatrix([[1, 0, 0, 2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) "
             "square(size = [1, 1]);")
    assert csg.to_mesh(a).volume() == pytest.approx(csg.to_mesh(b).volume(), rel=1e-6)
    with pytest.warns(OpenSCADWarning, match="both sides of the axis"):
        m = load("union() { cube(1); rotate_extrude() multmatrix([[1, 0, 0, -1], [0, 1, 0, 0], [0, 0, 1, 0], "
                 "[0, 0, 0, 1]]) square(size = [2, 1]); }")
    assert isinstance(m, csg.Box)


# ---- Syntax and values ----

def test_syntax_details():
    text = """/* a block comment */
    // a line comment
    group() {
        ;
        { sphere(r = 1); }
        multmatrix(m = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1],]) cube(size = [.5, 5e-1, 0.5e0]);
        sphere(r = +2, $fn = 8, $fa = 12, $fs = 2, $t = [0 : 1 : 10], label = undef);
    }"""
    with pytest.warns(OpenSCADWarning, match="unknown argument 'label'"):
        m = load(text)
    # (the last sphere sets $fn = 8: OpenSCAD's faceted sphere)
    assert [type(leaf).__name__ for leaf in m.leaves()] == ["Sphere", "Box", "ConvexPolyhedron"]
    assert m.leaves()[1].size == (0.5, 0.5, 0.5)
    assert load(b"\xef\xbb\xbfsphere(r = 2);").radius == 2           # bytes with a BOM
    # undef means the default
    assert load("sphere(r = undef);").radius == 1


BAD = [
    ("cube(size = [1, 2, 3]", r"line 1, column 22: expected ',' or '\)'"),
    ("cube(size = [1, 2, 3);", r"line 1, column 21: expected ',' or '\]'"),
    ("group() {\n cube(1);\n", r"line 3, column 1: unexpected end of file: the block of group at line 1"),
    ("cube(1); }", r"line 1, column 10: unexpected '}'"),
    ("cube(size = 1.2.3);", r"line 1, column 13: malformed number '1\.2\.3'"),
    ("cube(size = 1e);", r"malformed number '1e'"),
    ("cube(size = foo);", r"unknown name 'foo'"),
    ("cube(size = 1) @", r"line 1, column 16: unexpected character '@'"),
    ('color("red) cube();', r"unterminated string"),
    ("/* cube();", r"unterminated comment"),
    ("sphere(r = inf);", r"line 1, column 8: sphere: r must be a finite number, got inf"),
    ("sphere(r = -inf);", r"must be a finite number, got -inf"),
    ("sphere(r = nan);", r"must be a finite number, got nan"),
    ("sphere(r = 1e999);", r"must be a finite number, got inf"),
    ('sphere(r = "big");', r'sphere: r must be a number, got "big"'),
    ("sphere(r = [1, 2]);", r"sphere: r must be a number, got \[1, 2\]"),
    ("cube(size = [1, 2]);", r"cube: size must be a number or \[x, y, z\]"),
    ("cube(size = [1, inf, 2]);", r"cube: size must be finite"),
    ("cube(size = 1, center = 1);", r"cube: center must be true or false"),
    ("cylinder(h = true, r = 1);", r"cylinder: h must be a number, got true"),
    ("multmatrix(m = [[1, 0], [0, 1]]) cube();", r"multmatrix: m must be a 4x4"),
    ("multmatrix(m = [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,1,1]]) cube();", r"projective"),
    ("multmatrix(m = [[1,0,0,0],[0,1,0,0],[0,0,1,nan],[0,0,0,1]]) cube();", r"inf or nan"),
    ("color(c = 7) cube();", r"color: c must be"),
    ("cube(size = -true);", r"unary - needs a number"),
    ("true();", r"expected a node name, got the keyword 'true'"),
    ("cube(size = );", r"expected a value, got '\)'"),
    ("= cube();", r"expected a statement"),
    ("cube(size = [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]);",
     r"nested more than 64 deep"),
]


@pytest.mark.parametrize("text, message", BAD, ids=[b[0][:30] for b in BAD])
def test_bad_files_raise_one_clear_error(text, message):
    with pytest.raises(FormatError, match=r"^t\.csg: .*" + message):
        load(text)


def test_bounds_on_depth_and_size(monkeypatch, tmp_path):
    deep = 3000
    m = load("multmatrix([[1,0,0,1],[0,1,0,0],[0,0,1,0],[0,0,0,1]]) {" * deep + "sphere(1);" + "}" * deep)
    lo, hi = m.bounds()
    np.testing.assert_allclose(lo, [deep - 1, -1, -1], atol=1e-6)
    monkeypatch.setattr(openscad.limits, "MAX_DEPTH", 100)
    with pytest.raises(FormatError, match="nested more than 100 deep"):
        load("group() {" * 200 + "sphere(1);" + "}" * 200)
    monkeypatch.setattr(openscad.limits, "MAX_FILE_BYTES", 100)
    with pytest.raises(FormatError, match="larger than the limit"):
        load("group() {" * 20 + "}" * 20)
    path = tmp_path / "big.csg"
    path.write_text("sphere(1);" * 20)
    with pytest.raises(FormatError, match=r"big\.csg: 200 bytes is larger than the limit of 100"):
        openscad.load(path)


def test_load_files(tmp_path):
    path = tmp_path / "m.csg"
    path.write_text("group() {\n\tcube(size = [1, 2, 3], center = true);\n}\n")
    assert isinstance(openscad.load(path), csg.Box)
    assert isinstance(openscad.load(str(path)), csg.Box)
    with pytest.raises(FormatError, match="no such file"):
        openscad.load(tmp_path / "missing.csg")
    with pytest.raises(FormatError, match="is a directory"):
        openscad.load(tmp_path)
    bad = tmp_path / "bad.csg"
    bad.write_bytes(b"cube();\n\xff\xfe")
    with pytest.raises(FormatError, match=r"bad\.csg: not UTF-8 text \(invalid byte at offset 8, line 2\)"):
        openscad.load(bad)
    (tmp_path / "err.csg").write_text("group() {\n  sphere(r = inf);\n}\n")
    with pytest.raises(FormatError, match=r"err\.csg: line 2, column 10: sphere: r must be a finite number"):
        openscad.load(tmp_path / "err.csg")


# ---- Fuzz ----

SEEDS = [
    """group() {
\tmultmatrix([[1, 0, 0, -24], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) {
\t\tunion() {
\t\t\tcube(size = [15, 15, 15], center = true);
\t\t\tsphere($fn = 0, $fa = 12, $fs = 2, r = 10);
\t\t}
\t}
\tintersection() {
\t\tcube(size = [15, 15, 15], center = true);
\t\t%sphere($fn = 0, $fa = 12, $fs = 2, r = 10);
\t}
\tcolor([1, 0, 0, 1]) {
\t\tdifference() {
\t\t\tcylinder($fn = 0, $fa = 12, $fs = 2, h = 10, r1 = 5, r2 = 0, center = false);
\t\t\t#cube(size = 2);
\t\t}
\t}
}
""",
    """polyhedron(points = [[10, 0, 0], [0, 10, 0], [-10, 0, 0], [0, -10, 0], [0, 0, 10]], faces = [[0, 1, 2, 3], [4, 1, 0], [4, 2, 1], [4, 3, 2], [4, 0, 3]], convexity = 1);
render(convexity = 1) { color("red", 0.5) multmatrix([[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]]) cylinder(h = 62.5, r1 = 12.5, r2 = 12.5, center = true); }
""",
]
JUNK = ["", "{", "}", "(", ")", "[", "]", ";", ",", "=", "#", "%", "!", "*", "-", ":", '"', "/*", "//", "\n",
        "inf", "-inf", "nan", "undef", "true", "1e999", "0", "-1", "1.2.3", "cube", "square(1);", "group() {",
        "[[1,0],[0,1]]", "\x00", "é", "$fn", "x"]


def _mutate(text: str, rng: random.Random) -> str:
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(5)
        i = rng.randrange(len(text) + 1)
        if op == 0 and text:                               # delete a span
            text = text[:i] + text[i + rng.randint(1, 6):]
        elif op == 1:                                      # insert junk
            text = text[:i] + rng.choice(JUNK) + text[i:]
        elif op == 2:                                      # swap a number for something else
            nums = list(re.finditer(r"-?[0-9.]+(?:e-?[0-9]+)?", text))
            if nums:
                m = rng.choice(nums)
                text = text[:m.start()] + rng.choice(JUNK + ["0", "1e-300", "-0", "1e30", "3.5"]) + text[m.end():]
        elif op == 3:                                      # truncate
            text = text[:i]
        else:                                              # duplicate a span
            j = min(len(text), i + rng.randint(1, 40))
            text = text[:j] + text[i:j] + text[j:]
    return text


def test_fuzz_only_format_errors():
    rng = random.Random(1234)
    outcomes = {"ok": 0, "error": 0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OpenSCADWarning)
        for k in range(1500):
            text = _mutate(rng.choice(SEEDS), rng)
            for mode in ("error", "skip"):
                try:
                    model = load(text, on_unsupported=mode)
                    model.bounds()                          # the model is usable
                    outcomes["ok"] += 1
                except ModelError as e:                     # FormatError is a ModelError
                    assert str(e).startswith("t.csg: "), (text, e)
                    outcomes["error"] += 1
                except Exception as e:                      # pragma: no cover - the failure report
                    raise AssertionError(f"{type(e).__name__}: {e}\n--- input ---\n{text}") from e
    assert outcomes["ok"] > 100 and outcomes["error"] > 100, outcomes


# ---- OpenSCAD's own examples, against its STL export ----

EXAMPLES = Path("/usr/share/openscad/examples")
OPENSCAD = shutil.which("openscad")
# Examples that use only supported nodes and export quickly (OpenSCAD 2021.01; seconds of CGAL each).
COMPARED = ["Basics/CSG.scad", "Basics/logo.scad", "Old/example001.scad", "Old/example002.scad",
            "Old/example003.scad", "Old/example004.scad", "Old/example005.scad", "Old/example011.scad",
            "Old/example014.scad",
            # 2D outlines extruded: the same facets as OpenSCAD's (its fragment rule), as mesh leaves
            # (example020's twisted screws and springs load too, but fewer than half of the test's
            # rays are away from silhouettes there, so it is not compared)
            "Basics/linear_extrude.scad", "Old/example017.scad", "Old/example018.scad", "Old/example019.scad",
            "Old/example022.scad", "Old/example024.scad", "Parametric/candleStand.scad"]
needs_openscad = pytest.mark.skipif(OPENSCAD is None or not EXAMPLES.is_dir(),
                                    reason="needs the `openscad` program and its examples (apt-get install openscad)")


def _export(scad: Path, out: Path, fmt: str | None = None) -> Path:
    cmd = [OPENSCAD, "-o", str(out)] + (["--export-format", fmt] if fmt else []) + [str(scad)]
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    try:
        res = subprocess.run(cmd, cwd=scad.parent, capture_output=True, text=True, timeout=180, env=env)
    except subprocess.TimeoutExpired:
        pytest.skip(f"openscad took too long exporting {scad.name}")
    if res.returncode != 0 or not out.is_file():
        pytest.skip(f"openscad could not export {scad.name} headless: {res.stderr[-300:]}")
    return out


@pytest.fixture(scope="module")
def exported_csg(tmp_path_factory):
    out = tmp_path_factory.mktemp("openscad_csg")
    files = {}
    for scad in sorted(EXAMPLES.glob("*/*.scad")):
        rel = f"{scad.parent.name}/{scad.name}"
        files[rel] = _export(scad, out / (scad.stem + ".csg"))
    return files


@needs_openscad
def test_examples_load_or_refuse_by_name(exported_csg):
    loaded, refused = [], []
    for rel, path in exported_csg.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", OpenSCADWarning)
            try:
                openscad.load(path)
                loaded.append(rel)
            except FormatError as e:
                msg = str(e)
                assert msg.startswith(str(path)), msg
                assert re.search(r"is not supported|unknown node|the model is empty|the model is 2D", msg), msg
                refused.append((rel, msg))
    assert set(COMPARED) <= set(loaded), (loaded, refused)
    assert len(loaded) >= 10
    # skipping unsupported nodes loads everything that has 3D geometry left (a 2D drawing stays 2D)
    for rel, msg in refused:
        if "is not supported" in msg:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", OpenSCADWarning)
                try:
                    openscad.load(exported_csg[rel], on_unsupported="skip")
                except FormatError as e:
                    assert "empty" in str(e) or "the model is 2D" in str(e)


def _stl_scene(path):
    import mitsuba as mi
    from mitsuba_csg.formats.mesh_export import read_stl
    verts, faces = read_stl(path)
    tri = verts[faces]
    volume = float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6)
    area = float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum() / 2)
    shape = mi.Mesh("openscad", len(verts), len(faces))
    params = mi.traverse(shape)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(verts.astype(np.float32).ravel()))
    params["faces"] = mi.UInt32(np.ascontiguousarray(faces.astype(np.uint32).ravel()))
    params.update()
    return mi.load_dict({"type": "scene", "m": shape}), volume, area


def _aimed_rays(rng, lo, hi, n):
    """n rays from a sphere around the box [lo, hi] towards uniform points inside it (unit d)."""
    centre, radius = 0.5 * (lo + hi), 1.5 * float(np.linalg.norm(hi - lo))
    o = rng.normal(size=(n, 3))
    o = centre + o * (radius / np.linalg.norm(o, axis=1, keepdims=True))
    d = rng.uniform(lo, hi, size=(n, 3)) - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _mesh_hits(scene, o, d):
    import mitsuba as mi
    ray = mi.Ray3f(mi.Point3f(*np.ascontiguousarray(o.T, np.float32)),
                   mi.Vector3f(*np.ascontiguousarray(d.T, np.float32)))
    si = scene.ray_intersect(ray)
    t = np.array(si.t, dtype=np.float64)
    t[~np.array(si.is_valid(), dtype=bool)] = np.inf
    return t


@pytest.mark.slow
@needs_openscad
@pytest.mark.parametrize("rel", COMPARED)
def test_example_agrees_with_openscad_stl(rel, tmp_path):
    scad = EXAMPLES / rel
    model = openscad.load(_export(scad, tmp_path / "m.csg"))
    scene, mesh_volume, mesh_area = _stl_scene(_export(scad, tmp_path / "m.stl", "binstl"))
    lo, hi = (np.asarray(b, float) for b in model.bounds())
    size = float(np.max(hi - lo))
    # OpenSCAD's default facets ($fa = 12 degrees, $fs = 2): at most 30 segments per circle, a
    # sagitta of r (1 - cos 6 deg) = 0.55 % of r; small circles get as few as 5 segments.
    tol = 0.03 * size

    rng = np.random.default_rng(7)
    n = 2000
    o, d = _aimed_rays(rng, lo, hi, n)
    hits = csg.trace(model, o, d)
    t_exact = hits.t.astype(np.float64)
    # Skip rays near silhouettes and edges: jittered copies must see the same thing.
    helper = np.where(np.abs(d[:, :1]) < 0.6, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(d, u)
    stable = np.ones(n, bool)
    for shift in (u, -u, v, -v):
        t_j = csg.trace(model, o + 0.02 * size * shift, d).t.astype(np.float64)
        same = (np.isinf(t_j) == np.isinf(t_exact)) & \
               (np.isinf(t_exact) | (np.abs(np.where(np.isinf(t_j), 0, t_j) - np.where(np.isinf(t_exact), 0, t_exact)) < 2 * tol))
        stable &= same
    cos = np.abs(np.einsum("ij,ij->i", hits.normal.astype(np.float64), d))
    stable &= np.isinf(t_exact) | (cos > 0.2)
    t_mesh = _mesh_hits(scene, o, d)
    both_miss = np.isinf(t_exact) & np.isinf(t_mesh)
    close = np.isfinite(t_exact) & np.isfinite(t_mesh) & \
        (np.abs(t_exact - t_mesh) <= tol / np.maximum(cos, 0.2))
    agree = both_miss | close
    compared = int(stable.sum())
    assert compared >= 0.5 * n, f"{rel}: only {compared} of {n} rays away from silhouettes"
    assert np.isfinite(t_exact[stable]).sum() >= 0.2 * compared, f"{rel}: too few hits to compare"
    rate = agree[stable].mean()
    assert rate >= 0.97, (f"{rel}: {rate:.3f} of {compared} stable rays agree with OpenSCAD's STL "
                          f"(tol {tol:g}); first disagreements t_exact/t_mesh: "
                          f"{list(zip(t_exact[stable & ~agree][:5], t_mesh[stable & ~agree][:5]))}")

    # Volumes differ by at most the surface area times the gap between the exact and the
    # faceted surface: 30 segments per circle leave a sagitta of 0.55 % of r <= size / 2;
    # OpenSCAD's sphere rings are offset from the poles, so allow twice that.
    volume, err = mc_volume(model, lo, hi)
    gap = 0.0055 * size
    assert mesh_volume > 0
    assert abs(volume - mesh_volume) <= mesh_area * gap + 4 * err, \
        f"{rel}: exact volume {volume:g} +- {err:g} vs OpenSCAD's facets {mesh_volume:g} (area {mesh_area:g})"
    print(f"{rel}: rays {rate:.3f} of {compared}; volume exact {volume:.6g} +- {err:.2g}, facets {mesh_volume:.6g}, "
          f"allowed {mesh_area * gap + 4 * err:.3g}")


# ---- Real models written by others (../shared/data/openscad), against OpenSCAD's round mesh ----

SHARED_MODELS = Path(__file__).resolve().parents[2] / "shared" / "data" / "openscad"
# The models of that corpus the loader reads and that agree with OpenSCAD (the others need extrusions, hulls,
# Minkowski sums or non-convex polyhedra); not copied here: their licences do not allow it.
LOADING_MODELS = [
    "github/Enclosure.scad", "github/stage_knob.scad", "mcad/bitmap/alphabet_block.scad",
    "mcad/bitmap/test_name_tag.scad", "mcad/hardware.scad", "openscad-tests/cube-tests.scad",
    "openscad-tests/cylinder-tests.scad", "openscad-tests/edge-cases.scad", "openscad-tests/render-tests.scad",
    "openscad-tests/sphere-tests.scad", "openscad-tests/transform-tests.scad", "prusa-mendel/bar-clamp.scad",
    "thingiverse/thing-1937473-moneySpinner02-customizer.scad", "thingiverse/thing-2003965-spice.scad",
    "thingiverse/thing-2443095-cuvette-holder.scad", "thingiverse/thing-2570852-StairGateMount.scad",
    "thingiverse/thing-2799861-customizable-cylinder.scad", "thingiverse/thing-2891299-HDD-Holder-HP-ThinPC-T610.scad",
    "thingiverse/thing-3646982-Customizable-cylinder-adapter.scad", "thingiverse/thing-464376-kabelball.scad",
    "thingiverse/thing-47278-stretchy-band-v1-0.scad", "thingiverse/thing-651077-bedLevelAid.scad",
    "thingiverse/thing-691867-strap-sclip.scad", "thingiverse/thing-746644-schroefdopje.scad",
    "thingiverse/thing-797089-card-tray.scad",
    # extrusions of 2D outlines and non-convex polyhedra, as mesh leaves
    "gears/examples/bevel_gear.scad", "gears/examples/spur_gear.scad", "mcad/trochoids.scad",
    # (openscad-tests/linear_extrude-tests.scad loads, but its twisted extrusions split each side
    # quad along another diagonal than OpenSCAD 2021.01 does: 98.8 % of rays agree)
    "openscad-tests/difference-tests.scad", "prusa-i3-mk3/bearing.scad",
    "prusa-i3-mk3/x-end.scad", "prusa-mendel/frame-vertex.scad", "thingiverse/thing-280075-bezier-lathe.scad",
    "thingiverse/thing-3184263-a3pro-wireguide.scad",
    # hulls and Minkowski sums of OpenSCAD's faceted solids (convex polyhedra). Not listed:
    # openscad-tests/intersection-tests.scad (loads; 95.3 % of rays agree, not yet explained)
    # and thing-2092829-heart-hex-gen (loads; not compared yet)
    "thingiverse/thing-1188098-CandleHat.scad",
    "thingiverse/thing-1342838-Boxx-Insert-v2-Divisions.scad", "thingiverse/thing-1902773-SimpleModularFrame-v1.0.scad",
    "thingiverse/thing-236144-fan-duct-v0.2.scad",
    "thingiverse/thing-2496733-RialzoPiede.scad", "thingiverse/thing-3068796-involute-pump.scad",
    "thingiverse/thing-3767106-square-nut-to-ALU.scad", "thingiverse/thing-510700-test1.scad",
    # text (drawn by OpenSCAD), offset, resize, hulls and Minkowski sums of any solid, rotate_extrude
    # of outlines at x <= 0, malformed polyhedra dropped as OpenSCAD drops them
    "github/rugged-box.scad", "prusa-i3-mk3/lcd-supports.scad", "prusa-i3-mk3/x-end-idler.scad",
    "prusa-i3-mk3/z-axis-bottom.scad", "keyv2/customizer.scad", "thingiverse/thing-1892322-outlet2.scad",
    "openscad-tests/hull3-tests.scad", "openscad-tests/minkowski3-tests.scad",
    "thingiverse/thing-3413835-Support-Foot-Adapter.scad", "thingiverse/thing-46887-MultiStand.scad",
    "openscad-tests/polyhedron-tests.scad", "openscad-tests/rotate_extrude-tests.scad",
    "prusa-i3-mk3/z-axis-top.scad", "thingiverse/thing-2104049-CableTie2.scad",
    "thingiverse/thing-2940792-bohr20180601.scad", "thingiverse/thing-3600965-FlaskofBubbles.scad",
]
FINE_FN = 96


@pytest.fixture(scope="module")
def fine_exports(tmp_path_factory):
    """Each model's .csg and STL from a copy of the corpus where every `$fn` (top level, per
    call, in included files) is 96, so OpenSCAD's mesh is round everywhere: this compares the
    exact solid, holes and touching faces included, not OpenSCAD's low-$fn facets (whose
    fragment rule is the loader's business). Exported two at a time."""
    if OPENSCAD is None or not SHARED_MODELS.is_dir():
        pytest.skip("needs the `openscad` program and ../shared/data/openscad (not copied: licences)")
    from concurrent.futures import ThreadPoolExecutor
    work = tmp_path_factory.mktemp("openscad_corpus") / "corpus"
    shutil.copytree(SHARED_MODELS, work)
    for scad in work.rglob("*.scad"):
        text = scad.read_text(encoding="utf-8", errors="replace")
        scad.write_text(re.sub(r"\$fn\s*=\s*[^,;)\n]+", f"$fn={FINE_FN}", text), encoding="utf-8")

    def export(rel):
        scad = work / rel
        cmd = [OPENSCAD, "-D", f"$fn={FINE_FN}"]
        env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
        outs = {}
        for suffix, fmt in ((".csg", []), (".stl", ["--export-format", "binstl"])):
            out = scad.with_suffix(suffix)
            res = subprocess.run(cmd + fmt + ["-o", str(out), str(scad)], cwd=scad.parent, capture_output=True,
                                 text=True, timeout=600, env=env)
            outs[suffix] = out if res.returncode == 0 and out.is_file() else res.stderr[-300:]
        return rel, outs

    with ThreadPoolExecutor(2) as pool:
        return dict(pool.map(export, LOADING_MODELS))


@pytest.mark.slow
@pytest.mark.parametrize("rel", LOADING_MODELS)
def test_real_model_agrees_with_openscad_round_mesh(rel, fine_exports):
    """No film over flush-cut holes, no face where touching solids meet: 4000 rays aimed into
    the model's box, and 6000 in six orthographic views, each agree with OpenSCAD's 96-facet
    mesh on at least 99.7 % (both miss, or the hits agree within 2e-3 of the model's size over
    the cosine, for the facets' sagitta), and the volumes agree within 0.5 %."""
    outs = fine_exports[rel]
    for suffix in (".csg", ".stl"):
        assert isinstance(outs[suffix], Path), f"openscad could not export {rel} as {suffix}: {outs[suffix]}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OpenSCADWarning)
        model = openscad.load(outs[".csg"])
    scene, stl_volume, _ = _stl_scene(outs[".stl"])
    lo, hi = (np.asarray(b, float) for b in model.bounds())
    size = float(np.max(hi - lo))
    # Volumes within 0.5 %: our mesh of the exact solid at OpenSCAD's 96 segments per circle.
    ours = csg.to_mesh(model, segments=FINE_FN).volume()
    print(f"{rel}: volume {ours:.6g} (ours, {FINE_FN} segments) vs {stl_volume:.6g} (OpenSCAD)")
    assert ours == pytest.approx(stl_volume, rel=5e-3)
    rng = np.random.default_rng(7)
    n = 4000
    o, d = _aimed_rays(rng, lo, hi, n)
    # And six orthographic views along the axes, as renders of holes are: 1000 rays each.
    views_o, views_d = [], []
    for axis, sign in itertools.product(range(3), (1.0, -1.0)):
        start = rng.uniform(lo, hi, (1000, 3))
        start[:, axis] = (lo if sign > 0 else hi)[axis] - sign * 0.1 * size
        views_o.append(start)
        views_d.append(np.tile(np.eye(3)[axis] * sign, (1000, 1)))
    for label, (o, d) in (("aimed", (o, d)), ("orthographic", (np.vstack(views_o), np.vstack(views_d)))):
        hits = csg.trace(model, o, d)
        assert hits.unfinished == 0
        t_exact, t_mesh = hits.t.astype(np.float64), _mesh_hits(scene, o, d)
        cos = np.abs(np.einsum("ij,ij->i", hits.normal.astype(np.float64), d))
        with np.errstate(invalid="ignore"):                      # inf - inf where both miss
            agree = (np.isinf(t_exact) & np.isinf(t_mesh)) | \
                (np.abs(t_exact - t_mesh) <= 2e-3 * size / np.maximum(cos, 0.2))
        print(f"{rel}: {agree.mean():.4%} of {len(o)} {label} rays agree with OpenSCAD's mesh")
        assert agree.mean() >= 0.997, (f"{rel}: {agree.mean():.4%} of {label} rays agree; first disagreements "
                                       f"(ours, mesh): {list(zip(t_exact[~agree][:5], t_mesh[~agree][:5]))}")


@pytest.mark.skipif(shutil.which("openscad") is None, reason="needs the `openscad` program")
def test_scad_sources_are_evaluated_by_openscad(tmp_path, monkeypatch):
    src = tmp_path / "part.scad"
    src.write_text("module part(s) { difference() { cube(s, center = true); sphere(r = s / 2 + 0.2); } }\n"
                   "translate([1, 0, 0]) part(2);\n")
    m = csg.load(src)
    hits = csg.trace(m, [[1.0, 0.0, 5.0]], [[0.0, 0.0, -1.0]])
    assert np.isinf(hits.t[0])                       # the sphere (r = 1.2) takes the cube's middle
    assert csg.contains(m, [[1.95, 0.95, 0.95]])[0]  # a corner is left
    monkeypatch.setenv("MITSUBA_CSG_OPENSCAD", str(tmp_path / "no-openscad-here"))
    with pytest.raises(csg.CSGError, match=r"part.scad: an OpenSCAD source .*`openscad -o part.csg part.scad`.*"
                                           r"apt-get install openscad"):
        csg.load(src)


def test_explicit_low_fn_makes_openscads_polygon_solids():
    """A cylinder with $fn = 6 is a nut trap: OpenSCAD's hexagonal prism, corners on +x; with
    $fn = 0 (OpenSCAD's $fa/$fs default) or a large $fn, the round cylinder."""
    nut = load("cylinder($fn = 6, $fa = 12, $fs = 2, h = 2, r = 3, center = true);")
    assert isinstance(nut, csg.ConvexPolyhedron)
    assert csg.to_mesh(nut).volume() == pytest.approx(3 * math.sqrt(3) / 2 * 9 * 2)     # hexagon area x h
    hits = csg.trace(nut, [[10.0, 0, 0], [0, 10.0, 0]], [[-1.0, 0, 0], [0, -1.0, 0]])
    assert np.allclose(hits.t, [7.0, 10.0 - 3 * math.sqrt(3) / 2])                      # a corner, an edge
    for text in ("cylinder($fn = 0, $fa = 12, $fs = 2, h = 2, r = 3);", "cylinder($fn = 64, h = 2, r = 3);"):
        assert isinstance(load(text).leaves()[0], csg.Cone)
    ball = load("sphere($fn = 8, r = 2);")
    assert isinstance(ball, csg.ConvexPolyhedron)
    assert csg.to_mesh(ball).volume() < 4 / 3 * math.pi * 8
    assert isinstance(load("sphere($fn = 8, r = 2);", facets="exact"), csg.Sphere)
    assert isinstance(load("sphere($fn = 0, r = 2);", facets="openscad"), csg.ConvexPolyhedron)
    with pytest.raises(ModelError, match="facets"):
        load("sphere(r = 1);", facets="round")


def test_an_error_lists_every_unsupported_node_kind():
    text = ("group() {\n  cube(1);\n  import(file = \"a.stl\");\n  roof() square(1);\n"
            "  import(file = \"b.stl\");\n  surface(file = \"h.dat\");\n}")
    with pytest.raises(FormatError) as info:
        load(text)
    message = str(info.value)
    assert message.startswith("t.csg: line 3, column 3: import (imported geometry) is not supported")
    assert "in all: import x2, roof x1 (first at line 4), surface x1 (first at line 6)" in message
    assert message.count("line 3") == 1


def test_projection_of_the_faceted_solid():
    # the shadow of a unit cube turned 45 degrees about x: 1 x sqrt(2); its cut at z = 0: 1 x sqrt(2) too
    cube = "multmatrix([[1, 0, 0, 0], [0, 0.70710678, -0.70710678, 0], [0, 0.70710678, 0.70710678, 0], [0, 0, 0, 1]]) " \
           "cube(size = [1, 1, 1], center = true);"
    shadow = load(f"linear_extrude(height = 1) projection() {cube}")
    assert csg.to_mesh(shadow).volume() == pytest.approx(math.sqrt(2), rel=1e-6)
    section = load(f"linear_extrude(height = 1) projection(cut = true) {cube}")
    assert csg.to_mesh(section).volume() == pytest.approx(math.sqrt(2), rel=1e-6)
    ball = load("linear_extrude(height = 1) projection(cut = true) "
                "multmatrix([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.6], [0, 0, 0, 1]]) sphere(r = 1, $fn = 64);")
    assert csg.to_mesh(ball).volume() == pytest.approx(math.pi * (1 - 0.36), rel=0.02)   # a circle of r 0.8
