"""GDML loader: defines and units, every supported solid against analytic ray distances,
transform conventions against hand-computed positions, structure, and bad files."""
import math
import random
import warnings

import numpy as np
import pytest

import mitsuba_csg as csg
from mitsuba_csg.formats import gdml
from mitsuba_csg.formats.gdml.expressions import Expressions
from mitsuba_csg.errors import ModelError
from mitsuba_csg.formats.native_json import FormatError

S3 = math.sqrt(3.0)


def doc(solids="", structure=None, define="", world_solid="WorldBox"):
    """A GDML document; without `structure`, the world holds nothing."""
    if structure is None:
        structure = f'<volume name="World"><materialref ref="G4_AIR"/><solidref ref="{world_solid}"/></volume>'
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<gdml xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" xsi:noNamespaceSchemaLocation="gdml.xsd">
<define>{define}</define>
<materials><material name="Fe" Z="26"><D value="7.87"/><atom value="55.85"/></material></materials>
<solids><box name="WorldBox" x="1" y="1" z="1" lunit="m"/>
{solids}
</solids>
<structure>{structure}</structure>
<setup name="Default" version="1.0"><world ref="World"/></setup>
</gdml>"""


def solid(xml, name="S", define=""):
    return gdml.loads(doc(xml, define=define), "test.gdml", solid=name)


def boundaries(model, origin, direction, count=8):
    """Every boundary t along a ray: first hits, restarted just after each (same tmin: one kernel)."""
    d = np.array([direction], float)
    model = model if isinstance(model, csg.Prepared) else csg.prepare(model)
    out, start = [], 0.0
    for _ in range(count):
        h = csg.trace(model, np.array([origin], float) + start * d, d)
        t = float(h.t[0])
        if not math.isfinite(t):
            break
        out.append(start + t)
        start += t + 1e-4
    return out


def check_ray(model, origin, direction, expected, tol=2e-3):
    got = boundaries(model, origin, direction)
    assert len(got) == len(expected), (got, expected)
    np.testing.assert_allclose(got, expected, atol=tol)


def inside(model, points):
    return csg.contains(model, np.array(points, float))


# ---- Defines, expressions, units ----

def test_defines_expressions_and_units():
    define = """<constant name="a" value="2"/>
        <variable name="b" value="a^2 + 1"/>
        <quantity name="c" value="1" unit="cm"/>
        <expression name="d">sqrt(16) * mm + max(1, 2) - abs(-1)</expression>
        <constant name="ang" value="atan2(1, 1)"/>"""
    # x = 5 (b) * 1 mm, y = 10 mm (c), z = 4 + 2 - 1 = 5 mm times lunit cm = 50 mm
    m = solid('<box name="S" x="b" y="c" z="d" lunit="cm"/>', define=define)
    assert m.size == pytest.approx((50.0, 100.0, 50.0))
    m = solid('<box name="S" x="2*m/1000" y="-(-3)" z="10*um*1000 + pow(2,3)*cos(ang*4)/-8 + 1"/>', define=define)
    assert m.size == pytest.approx((2.0, 3.0, 12.0))
    # default angle unit rad, aunit deg, units inside the expression
    t1 = solid('<tube name="S" rmax="1" z="1" deltaphi="pi/2"/>')
    t2 = solid('<tube name="S" rmax="1" z="1" deltaphi="90" aunit="deg"/>')
    t3 = solid('<tube name="S" rmax="1" z="1" deltaphi="90*deg"/>')
    for t in (t1, t2, t3):
        assert list(inside(t, [[0.5, 0.5, 0], [-0.5, 0.5, 0]])) == [True, False]


def test_evaluator_whitelist():
    r = Expressions()
    r.scalars = {"x": 3.0}
    assert r.evaluate("2^3^2") == 2.0 ** 9          # right-associative power, above * and unary minus
    assert r.evaluate("-2^2") == -4.0
    assert r.evaluate("1 + 2^2 * 3") == 13.0
    assert r.evaluate("x*deg") == pytest.approx(3 * math.pi / 180)
    for bad in ("__import__('os')", "x.real", "[1]", "1 if 1 else 2", "'a'", "1 < 2", "x(1)", "1+", "1/0",
                "sqrt(-1)", "10^400", "lambda: 1", "True", "2**3", "1e999", "y", "sin(1, 2)", "1 % 2"):
        with pytest.raises(FormatError):
            r.evaluate(bad)


def test_leading_zeros_matrices_and_brackets():
    r = Expressions()
    assert r.evaluate("005") == 5.0                   # CLHEP reads leading zeros as decimals
    assert r.evaluate("1e05 + 2.005 + 0.5 + 0") == pytest.approx(1e5 + 2.505)
    r.define_matrix("m", 3, [1, 2, 3, 4, 5, 6])       # two rows of three: m_<row>_<col>
    r.define_matrix("v", 1, [7, 8, 9])                # a column: v_<i>
    r.scalars["i"] = 2.0
    assert r.evaluate("m[2,3] + m[1,i] + v[i+1]") == 6 + 2 + 9   # indices count from 1
    for bad in ("m[1", "m]1[", "m[1.5,1]", "m[3,1]"):
        with pytest.raises(FormatError):
            r.evaluate(bad)
    m = solid('<box name="S" x="k[2]" y="k[3]*2" z="1"/>',
              define='<matrix name="k" coldim="1" values="1 2*mm 3"/>')
    assert m.size == pytest.approx((2.0, 6.0, 1.0))


LOOPS = """<solids><box name="WorldBox" x="1" y="1" z="1" lunit="m"/>
  <loop for="i" from="1" to="n" step="1"><loop for="j" from="1" to="2" step="1">
    <box name="B[i][j]" x="i" y="j" z="0.5"/></loop></loop></solids>
<structure>
  <loop for="i" from="1" to="n" step="1"><loop for="j" from="1" to="2" step="1">
    <volume name="v[i][j]"><materialref ref="Fe"/><solidref ref="B[i][j]"/></volume></loop></loop>
  <volume name="World"><materialref ref="G4_AIR"/><solidref ref="WorldBox"/>
    <loop for="i" from="1" to="n" step="1"><loop for="j" from="1" to="2" step="1">
      <physvol><volumeref ref="v[i][j]"/><position name="p[i][j]" x="10*i" y="10*j"/></physvol>
    </loop></loop>
    <physvol><volumeref ref="v_0_0"/><position name="q" z="i*100"/></physvol>
  </volume></structure>"""


def loops_doc(define='<variable name="i" value="7"/><variable name="j" value="0"/><constant name="n" value="3"/>',
              body=LOOPS):
    return (f'<?xml version="1.0"?><gdml><define>{define}</define><materials/>{body}'
            '<setup name="Default" version="1.0"><world ref="World"/></setup></gdml>')


def test_loops_repeat_their_contents_as_geant4_reads_them():
    m = gdml.loads(loops_doc(), "loops.gdml")
    leaves = m.leaves()
    assert len(leaves) == 3 * 2 + 1
    # Box B[i][j] (named B_<i-1>_<j-1>) is i by j mm, placed at (10 i, 10 j)
    centres = [np.round(tf_offset(leaf), 6) for leaf in leaves[:6]]
    assert [tuple(c) for c in centres] == [(10 * i, 10 * j, 0) for i in (1, 2, 3) for j in (1, 2)]
    assert [tuple(leaf.size) for leaf in leaves[:6]] == [(i, j, 0.5) for i in (1, 2, 3) for j in (1, 2)]
    # after the loops the variable has its own value again (7): z = 700
    assert tuple(np.round(tf_offset(leaves[6]), 6)) == (0, 0, 700)


def tf_offset(leaf):
    return leaf.matrix[:3, 3]


def test_bad_loops_each_raise_one_clear_error():
    body = LOOPS
    # Names are solved only inside loops (Geant4's GenerateName): outside, v[1][1] is a literal.
    _expect(loops_doc(body=body.replace('<volumeref ref="v_0_0"/>', '<volumeref ref="v[1][1]"/>')),
            "undefined volume 'v\\[1\\]\\[1\\]'")
    _expect(loops_doc(define='<constant name="i" value="0"/><variable name="j" value="0"/>'
                             '<constant name="n" value="3"/>'), r"<loop>: for='i': the loop variable must be")
    _expect(loops_doc(body=body.replace('to="n" step="1"', 'to="n" step="0"', 1)), "endless loop")
    _expect(loops_doc(body=body.replace('from="1" to="n"', 'from="1.5" to="n"', 1)), "must have a whole value")
    _expect(loops_doc(body=body.replace('<loop for="j" from="1" to="2" step="1">\n    <box',
                                        '<loop for="i" from="1" to="2" step="1">\n    <box', 1)),
            "the variable of an enclosing loop")
    big = body.replace('to="n"', 'to="1000000"', 1)
    _expect(loops_doc(body=big), "loops make more than")


def test_copies_place_their_volume_many_times(tmp_path):
    vols = ('<volume name="c"><materialref ref="Cu"/><solidref ref="Small"/></volume>'
            '<volume name="row"><materialref ref="Fe"/><solidref ref="Row"/>{}</volume>')
    row = '<box name="Row" x="4" y="1" z="1"/>' + BAR
    replica = ('<replicavol number="4"><volumeref ref="c"/><replicate_along_axis><direction x="1"/>'
               '<width value="1" unit="mm"/><offset value="0" unit="mm"/></replicate_along_axis></replicavol>')
    m = gdml.loads(world('<physvol><volumeref ref="row"/></physvol>', vols.format(replica), row), "r.gdml")
    assert [tuple(np.round(leaf.matrix[:3, 3], 9)) for leaf in m.leaves()[1:]] == \
        [(-1.5, 0, 0), (-0.5, 0, 0), (0.5, 0, 0), (1.5, 0, 0)]
    division = '<divisionvol axis="kXAxis" number="2" offset="1" unit="mm"><volumeref ref="c"/></divisionvol>'
    m = gdml.loads(world('<physvol><volumeref ref="row"/></physvol>', vols.format(division), row), "d.gdml")
    # two slices of (4 - 1) / 2 = 1.5 mm from x = -2 + 1: centres -0.25 and 1.25, the mother's other sides
    assert [(tuple(np.round(leaf.matrix[:3, 3], 9)), tuple(leaf.size)) for leaf in m.leaves()[1:]] == \
        [((-0.25, 0, 0), (1.5, 1, 1)), ((1.25, 0, 0), (1.5, 1, 1))]
    params = ('<paramvol ncopies="2"><volumeref ref="c"/><parameterised_position_size>'
              '<parameters number="1"><position name="p1" x="-1"/><box_dimensions x="1" y="0.5" z="0.5"/></parameters>'
              '<parameters number="2"><position name="p2" x="1"/><rotation name="r2" z="90" unit="deg"/>'
              '<tube_dimensions InR="0" OutR="0.4" hz="1" DeltaPhi="360" aunit="deg"/></parameters>'
              '</parameterised_position_size></paramvol>')
    path = tmp_path / "p.gdml"
    path.write_text(world('<physvol><volumeref ref="row"/></physvol>', vols.format(params), row))
    placed = gdml.volumes(path)
    assert [v.level for v in placed] == [1, 2, 2] and [v.name for v in placed] == ["row", "c", "c"]
    m = csg.union(*[v.node for v in placed if v.level == 2])     # the copies, without their mother
    assert list(inside(m, [[-1.45, 0, 0], [-0.9, 0.3, 0], [1.0, 0.35, 0.45], [1.0, 0.45, 0]])) == \
        [True, False, True, False]
    for bad, pattern in ((replica.replace('x="1"/>', 'rho="1"/>'), "radial replicas"),
                         (division.replace("kXAxis", "kPhi"), "division of a <box> along kPhi"),
                         (params.replace('ncopies="2"', 'ncopies="3"'), "ncopies=3 but 2"),
                         (params.replace("box_dimensions", "hype_dimensions"), "<hype_dimensions> is not supported"),
                         (replica.replace('number="4"', 'number="-1"'), "number: expected 0..")):
        _expect(world('<physvol><volumeref ref="row"/></physvol>', vols.format(bad), row), pattern)


def test_simple_extension_root_and_colours():
    text = doc("").replace("<gdml ", "<gdml_simple_extension ", 1).replace("</gdml>", "</gdml_simple_extension>")
    text = text.replace("<define>", '<extension><color name="red" R="1" G="0" B="0" A="1"/></extension><define>')
    m = gdml.loads(text, "ext.gdml")          # a world alone: shown (as a file of one volume is that volume)
    assert [leaf.material for leaf in m.leaves()] == ["G4_AIR"]
    _expect(text.replace('R="1"', 'R="2"'), r"<color name=\"red\">: colour components must lie in \[0, 1\]")
    with pytest.raises(FormatError, match="nothing to show"):
        gdml.loads(text, "ext.gdml", show_world=False)


def test_inconsistent_facets_are_turned_to_agree():
    from mitsuba_csg.model.mesh import orient_consistently, signed_volume
    box = csg.to_mesh(csg.Box((2, 3, 4))).to_mesh()
    v, f = np.asarray(box.vert_properties)[:, :3], np.asarray(box.tri_verts).astype(np.int64)
    rng = np.random.default_rng(3)
    flipped = f.copy()
    turn = rng.random(len(f)) < 0.5
    flipped[turn] = flipped[turn][:, ::-1]
    fixed, turned = orient_consistently(flipped)
    assert turned
    assert abs(signed_volume(v, fixed)) == pytest.approx(24.0)
    csg.Mesh(v, fixed if signed_volume(v, fixed) > 0 else fixed[:, ::-1])     # closed, consistent
    assert not orient_consistently(f)[1]


# ---- Solids against analytic ray distances ----

def test_box_and_orb():
    check_ray(solid('<box name="S" x="2" y="4" z="6"/>'), (-10, 0.5, 0.5), (1, 0, 0), [9, 11])
    check_ray(solid('<box name="S" x="2" y="4" z="6"/>'), (0, 0, -10), (0, 0, 1), [7, 13])
    check_ray(solid('<orb name="S" r="3"/>'), (-10, 0, 0), (1, 0, 0), [7, 13])


def test_tube_with_hole_and_phi_segments():
    m = solid('<tube name="S" rmin="2" rmax="5" z="4"/>')
    check_ray(m, (-10, 0, 0), (1, 0, 0), [5, 8, 12, 15])                 # -rmax, -rmin, rmin, rmax
    check_ray(m, (3, 0, -10), (0, 0, 1), [8, 12])                        # z is the full length
    # a quarter: phi in [0, 90 deg]; a ray along x at y = 1 enters at x = 0 and leaves at sqrt(25 - 1)
    q = solid('<tube name="S" rmax="5" z="4" startphi="0" deltaphi="90" aunit="deg"/>')
    check_ray(q, (-10, 1, 0), (1, 0, 0), [10, 10 + math.sqrt(24)])
    assert not inside(q, [[1, -1, 0]])[0]
    # 270 degrees starting at 90: only the quadrant x > 0, y > 0 is missing
    t = solid('<tube name="S" rmin="1" rmax="5" z="4" startphi="90" deltaphi="270" aunit="deg"/>')
    assert list(inside(t, [[3, -1, 0], [3, 1, 0], [-3, -1, 0], [-3, 1, 0], [0.5, 0.5, 0]])) == \
        [True, False, True, True, False]
    check_ray(t, (-10, 3, 0), (1, 0, 0), [10 - 4, 10])                  # leaves the solid at x = 0
    # startphi 30, deltaphi 60: the wedge between 30 and 90 deg
    w = solid('<tube name="S" rmax="5" z="4" startphi="30" deltaphi="60" aunit="deg"/>')
    check_ray(w, (-0.5, 2, 0), (1, 0, 0), [0.5, 0.5 + 2 * S3])            # the 90-deg plane, then the 30-deg one


def test_cone_sections():
    c = solid('<cone name="S" rmin1="0" rmax1="4" rmin2="1" rmax2="2" z="6"/>')
    # at z = 0: rmax = 3, rmin = 0.5
    check_ray(c, (-10, 0, 0), (1, 0, 0), [7, 9.5, 10.5, 13])
    # at z = -3: rmax = 4, no hole; at z = +2: rmax = 2 + 2*(-1/3)... radius(z) = 3 - z/3
    check_ray(c, (-10, 0, 2), (1, 0, 0), [10 - (3 - 2 / 3), 10 - (0.5 + 2 / 6), 10 + (0.5 + 2 / 6), 10 + 3 - 2 / 3])
    half = solid('<cone name="S" rmax1="4" rmax2="2" z="6" startphi="0" deltaphi="180" aunit="deg"/>')
    assert list(inside(half, [[0, 1, 0], [0, -1, 0]])) == [True, False]


def test_sphere_shell_and_cuts():
    s = solid('<sphere name="S" rmin="2" rmax="5" deltaphi="2*pi" deltatheta="pi"/>')
    check_ray(s, (-10, 0, 0), (1, 0, 0), [5, 8, 12, 15])
    # theta in [0, 60 deg]: at height z = 3 the solid is rho < 3 tan 60
    cap = solid('<sphere name="S" rmax="10" starttheta="0" deltatheta="60" aunit="deg"/>')
    check_ray(cap, (-20, 0, 3), (1, 0, 0), [20 - 3 * S3, 20 + 3 * S3])
    check_ray(cap, (0.5, 0, -20), (0, 0, 1), [20 + 0.5 / S3, 20 + math.sqrt(99.75)])   # the cone, the sphere
    # theta in [60, 120 deg]: a band around the equator, outside the double cone
    band = solid('<sphere name="S" rmax="10" starttheta="60" deltatheta="60" aunit="deg"/>')
    # theta >= 60 deg at z = 3 means rho >= 3 tan 60; the sphere ends at rho = sqrt(100 - 9)
    check_ray(band, (-20, 0, 3), (1, 0, 0), [20 - math.sqrt(91), 20 - 3 * S3, 20 + 3 * S3, 20 + math.sqrt(91)])
    # theta in [90, 180]: the lower half, and a phi quarter
    low = solid('<sphere name="S" rmax="10" starttheta="90" deltatheta="90" deltaphi="90" aunit="deg"/>')
    assert list(inside(low, [[2, 2, -2], [2, 2, 2], [-2, 2, -2]])) == [True, False, False]


def test_torus():
    t = solid('<torus name="S" rmin="0.5" rmax="1" rtor="4" deltaphi="360" aunit="deg"/>')
    check_ray(t, (-10, 0, 0), (1, 0, 0), [5, 5.5, 6.5, 7, 13, 13.5, 14.5, 15])
    half = solid('<torus name="S" rmax="1" rtor="4" startphi="0" deltaphi="180" aunit="deg"/>')
    check_ray(half, (-10, 0.01, 0), (1, 0, 0), [5, 7, 13, 15], tol=5e-3)
    check_ray(half, (-10, -0.01, 0), (1, 0, 0), [])


def test_polyhedra_rmax_is_the_apothem():
    # numsides 6, startphi 0: vertices at k * 60 deg, faces centred at 30 + k * 60 deg.
    p = solid('<polyhedra name="S" startphi="0" deltaphi="360" numsides="6" aunit="deg">'
              '<zplane z="-2" rmin="0" rmax="10"/><zplane z="2" rmin="0" rmax="10"/></polyhedra>')
    check_ray(p, (0, -20, 0), (0, 1, 0), [10, 30])                       # 90 deg: a face, at the apothem
    check_ray(p, (-20, 0, 0), (1, 0, 0), [20 - 20 / S3, 20 + 20 / S3])   # 0 deg: a vertex, apothem / cos 30
    # a frustum section with a hole: apothem 10 -> 5 over z 0..10, hole apothem 2 everywhere
    f = solid('<polyhedra name="S" numsides="4" startphi="45" deltaphi="360" aunit="deg">'
              '<zplane z="0" rmin="2" rmax="10"/><zplane z="10" rmin="2" rmax="5"/></polyhedra>')
    # startphi 45, 4 sides: faces at 90, 180, 270, 360 deg -> axis-aligned square
    check_ray(f, (-20, 0, 4), (1, 0, 0), [20 - 8, 18, 22, 28])
    # a half polyhedra (deltaphi 180, 3 sides of 60 deg each): faces at 30, 90, 150
    h = solid('<polyhedra name="S" numsides="3" startphi="0" deltaphi="180" aunit="deg">'
              '<zplane z="-1" rmin="1" rmax="4"/><zplane z="1" rmin="1" rmax="4"/></polyhedra>')
    check_ray(h, (0, -5, 0), (0, 1, 0), [6, 9])                         # cut at y = 0 by the hole? no: x = 0 crosses hole
    assert list(inside(h, [[0, -1, 0], [3, 0.5, 0], [0, 3.9, 0], [0, 4.1, 0]])) == [False, True, True, False]
    # 3/4 segment of 6 sides (45 deg each): missing quadrant x > 0, y < 0
    g = solid('<polyhedra name="S" numsides="6" startphi="0" deltaphi="270" aunit="deg">'
              '<zplane z="-1" rmin="0" rmax="4"/><zplane z="1" rmin="0" rmax="4"/></polyhedra>')
    assert list(inside(g, [[2, -1, 0], [2, 1, 0], [-2, -1, 0], [-1, 1, 0]])) == [False, True, True, True]


def test_polycone():
    p = solid('<polycone name="S" startphi="0" deltaphi="360" aunit="deg">'
              '<zplane z="-5" rmin="0" rmax="2"/><zplane z="0" rmin="1" rmax="4"/><zplane z="5" rmin="1" rmax="4"/>'
              '</polycone>')
    check_ray(p, (-10, 0, 2), (1, 0, 0), [6, 9, 11, 14])
    check_ray(p, (-10, 0, -2.5), (1, 0, 0), [7, 9.5, 10.5, 13])       # rmax 3, rmin 0.5 at z = -2.5
    check_ray(p, (3, 0, -20), (0, 0, 1), [17.5, 25])                     # r = 3 reached at z = -2.5; crosses z = 0


def test_trd_trap_para():
    trd = solid('<trd name="S" x1="4" x2="2" y1="6" y2="6" z="10"/>')
    check_ray(trd, (-10, 0, 0), (1, 0, 0), [10 - 1.5, 10 + 1.5])         # half width (x1 + x2) / 4 at z = 0
    check_ray(trd, (0, 0, -10), (0, 0, 1), [5, 15])
    # trap with theta = phi = 0, alpha 0: a trd-like solid with different x at +-y
    trap = solid('<trap name="S" z="10" theta="0" phi="0" y1="4" x1="2" x2="6" alpha1="0" '
                 'y2="4" x3="2" x4="6" alpha2="0" aunit="deg"/>')
    check_ray(trap, (-10, 0, 0), (1, 0, 0), [8, 12])                     # x half width 2 at y = 0
    check_ray(trap, (-10, 1, 0), (1, 0, 0), [7.5, 12.5])                 # 2.5 at y = 1
    # para with alpha 45 deg: x shifts by y
    para = solid('<para name="S" x="2" y="4" z="2" alpha="45" theta="0" phi="0" aunit="deg"/>')
    check_ray(para, (-10, 1.5, 0), (1, 0, 0), [10 + 1.5 - 1, 10 + 1.5 + 1])
    # para with theta: the centre moves along (tan theta cos phi) z
    tilted = solid('<para name="S" x="2" y="2" z="4" alpha="0" theta="45" phi="0" aunit="deg"/>')
    check_ray(tilted, (-10, 0, 1.5), (1, 0, 0), [10 + 1.5 - 1, 10 + 1.5 + 1])
    twisted = doc('<trap name="S" z="10" theta="0" phi="0" y1="4" x1="2" x2="6" alpha1="0" '
                  'y2="4" x3="6" x4="2" alpha2="0"/>')
    with pytest.raises(FormatError, match="not planar"):
        gdml.loads(twisted, "t.gdml", solid="S")


def test_paraboloid_and_hype():
    m = solid('<paraboloid name="S" rlo="1" rhi="3" dz="2"/>')
    check_ray(m, (0, 0, -10), (0, 0, 1), [8, 12])
    # rho^2 = k1 z + k2 with k1 = (9 - 1) / 4 = 2, k2 = 5: at z = 0.5 the radius is sqrt(6)
    check_ray(m, (-10, 0, 0.5), (1, 0, 0), [10 - math.sqrt(6), 10 + math.sqrt(6)])
    m = solid('<hype name="S" rmin="1" rmax="2" inst="0.3" outst="0.6" z="4"/>')
    check_ray(m, (-10, 0, 0), (1, 0, 0), [8, 9, 11, 12])              # the waist: rmin and rmax
    r_out, r_in = math.hypot(2, math.tan(0.6) * 1.5), math.hypot(1, math.tan(0.3) * 1.5)
    check_ray(m, (-10, 0, 1.5), (1, 0, 0), [10 - r_out, 10 - r_in, 10 + r_in, 10 + r_out])
    cone2 = solid('<hype name="S" rmin="0" rmax="2" inst="0.5" outst="0.6" z="4"/>')   # inner double cone
    check_ray(cone2, (0, 0, -10), (0, 0, 1), [])                        # the axis lies in the hole
    assert list(inside(cone2, [[0.1, 0, 0.0], [0.1, 0, 1.0], [1.9, 0, 0]])) == [True, False, True]


def test_swept_and_revolved_solids():
    from mitsuba_csg.model.mesh import signed_volume
    # arb8 without twist: the exact convex polyhedron; with twist: a swept mesh (volume kept)
    flat = solid('<arb8 name="S" dz="1" v1x="-2" v1y="-2" v2x="-2" v2y="2" v3x="2" v3y="2" v4x="2" v4y="-2" '
                 'v5x="-1" v5y="-1" v6x="-1" v6y="1" v7x="1" v7y="1" v8x="1" v8y="-1"/>')
    assert isinstance(flat, csg.ConvexPolyhedron)
    check_ray(flat, (-10, 0, 0), (1, 0, 0), [8.5, 11.5])                   # half width 1.5 at z = 0
    twisted = solid('<arb8 name="S" dz="1" v1x="-2" v1y="-2" v2x="-2" v2y="2" v3x="2" v3y="2" v4x="2" v4y="-2" '
                    'v5x="-2" v5y="-2" v6x="-2" v6y="2" v7x="2" v7y="2" v8x="2" v8y="1"/>')
    assert isinstance(twisted, csg.Mesh)
    # cross-sections of area 16, 13, 10 at z = -1, 0, 1 (quadratic in z): Simpson's rule is exact
    assert signed_volume(twisted.vertices, twisted.faces) == pytest.approx(2 * (16 + 4 * 13 + 10) / 6, rel=1e-4)
    # a twisted box keeps its cross-section: volume x y z; a quarter turn about z maps it onto itself
    box = solid('<twistedbox name="S" PhiTwist="0.8" x="2" y="3" z="4"/>')
    assert signed_volume(box.vertices, box.faces) == pytest.approx(24.0, rel=1e-3)
    check_ray(box, (0, 0, -10), (0, 0, 1), [8, 12])
    c, s_ = math.cos(0.4), math.sin(0.4)                                   # the top turned by +0.4 rad
    assert list(inside(box, [[0.99 * c - 1.49 * s_, 0.99 * s_ + 1.49 * c, 1.99],
                             [0.99 * c + 1.49 * s_, -0.99 * s_ + 1.49 * c, 1.99]])) == [True, False]  # turned back
    tubs = solid('<twistedtubs name="S" twistedangle="40" endinnerrad="3" endouterrad="5" zlen="8" phi="60" '
                 'aunit="deg"/>')
    ri, ro, kappa = 3 * math.cos(math.radians(20)), 5 * math.cos(math.radians(20)), math.tan(math.radians(20)) / 4
    exact = math.radians(60) / 2 * (ro * ro - ri * ri) * (8 + 2 * kappa ** 2 * 4 ** 3 / 3)
    assert signed_volume(tubs.vertices, tubs.faces) == pytest.approx(exact, rel=2e-3)
    # a generic polycone of two stacked frusta and a hole: exact cones
    gp = solid('<genericPolycone name="S" startphi="0" deltaphi="360" aunit="deg">'
               '<rzpoint r="1" z="-2"/><rzpoint r="3" z="-2"/><rzpoint r="2" z="2"/><rzpoint r="1" z="2"/>'
               '</genericPolycone>')
    check_ray(gp, (-10, 0, 0), (1, 0, 0), [7.5, 9, 11, 12.5])
    mirrored = solid('<box name="B" x="2" y="2" z="2"/><reflectedSolid name="S" solid="B" sx="-1" sy="1" sz="1" '
                     'dx="5" rz="90" aunit="deg"/>')
    check_ray(mirrored, (0, 0, 0), (1, 0, 0), [4, 6])


def test_vector_units_are_read_as_geant4_reads_them():
    # Geant4 reads only unit= on <rotation>/<position>: aunit="deg" there leaves radians (with a warning)
    text = world('<physvol><volumeref ref="bar"/><rotation name="r" z="90" aunit="deg"/></physvol>',
                 '<volume name="bar"><materialref ref="Fe"/><solidref ref="Bar"/></volume>', BAR)
    with pytest.warns(UserWarning, match='aunit="deg" is not read on a <rotation>'):
        m = gdml.loads(text, "u.gdml")
    c, s_ = math.cos(-90.0), math.sin(-90.0)                   # 90 rad; the frame rotation's inverse
    assert list(inside(m, [[4.5 * c, 4.5 * s_, 0]])) == [True]


def test_ellipsoid_eltube_elcone():
    e = solid('<ellipsoid name="S" ax="2" by="3" cz="4" zcut1="-1" zcut2="2"/>')
    check_ray(e, (0, 0, -10), (0, 0, 1), [9, 12])
    check_ray(e, (-10, 0, 0), (1, 0, 0), [8, 12])
    full = solid('<ellipsoid name="S" ax="2" by="3" cz="4"/>')
    check_ray(full, (0, 0, -10), (0, 0, 1), [6, 14])
    t = solid('<eltube name="S" dx="2" dy="3" dz="4"/>')                 # half lengths
    check_ray(t, (-10, 0, 0), (1, 0, 0), [8, 12])
    check_ray(t, (0, -10, 0), (0, 1, 0), [7, 13])
    check_ray(t, (0, 0, -10), (0, 0, 1), [6, 14])
    c = solid('<elcone name="S" dx="0.5" dy="1" zmax="10" zcut="5"/>')    # semi-axes dx (zmax - z)
    check_ray(c, (-20, 0, 0), (1, 0, 0), [15, 25])
    check_ray(c, (0, -20, 2), (0, 1, 0), [12, 28])


def test_cut_tube():
    c = solid('<cutTube name="S" rmax="5" z="10" lowX="0" lowY="0" lowZ="-1" highX="1" highY="0" highZ="1"/>')
    # high plane: x + z = 5 through (0, 0, 5); along z at x = 2 the top is z = 3
    check_ray(c, (2, 0, -10), (0, 0, 1), [5, 13])
    check_ray(c, (-2, 0, -10), (0, 0, 1), [5, 17])


# ---- Booleans and the transform conventions ----

def test_boolean_second_moves_by_R_then_t():
    # second = a bar along x, rotated +30 deg about z (x' = R x + t): it points at +30 deg, moved by t
    define = '<position name="p" x="1" y="0" z="0"/><rotation name="r" z="30" unit="deg"/>'
    body = ('<box name="A" x="1" y="1" z="1"/><box name="B" x="10" y="0.4" z="0.4"/>'
            '<union name="S"><first ref="A"/><second ref="B"/><positionref ref="p"/><rotationref ref="r"/></union>')
    u = solid(body, define=define)
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    assert list(inside(u, [[1 + 4 * c, 4 * s, 0], [1 + 4 * c, -4 * s, 0], [1 - 4 * c, -4 * s, 0]])) == \
        [True, False, True]
    inline = solid('<box name="A" x="1" y="1" z="1"/><box name="B" x="10" y="0.4" z="0.4"/>'
                   '<union name="S"><first ref="A"/><second ref="B"/><position name="q" x="1"/>'
                   '<rotation name="rr" z="pi/6"/></union>')
    assert list(inside(inline, [[1 + 4 * c, 4 * s, 0], [1 + 4 * c, -4 * s, 0]])) == [True, False]
    # rotation order: x then y then z (R = Rz Ry Rx). A bar along y, x = 90 deg puts it along z,
    # then z = 90 deg leaves it along z; the other order would give x.
    order = solid('<box name="A" x="0.5" y="0.5" z="0.5"/><box name="B" x="0.4" y="10" z="0.4"/>'
                  '<union name="S"><first ref="A"/><second ref="B"/><rotation name="o" x="90" z="90" unit="deg"/>'
                  '</union>')
    assert list(inside(order, [[0, 0, 4], [4, 0, 0], [0, 4, 0]])) == [True, False, False]
    # subtraction with firstposition and intersection
    sub = solid('<box name="A" x="4" y="4" z="4"/><orb name="B" r="1"/>'
                '<subtraction name="S"><first ref="A"/><second ref="B"/><position name="q" x="2"/>'
                '<firstposition name="f" x="1"/></subtraction>')
    check_ray(sub, (-10, 0, 0), (1, 0, 0), [9, 11])                      # box -1..3 minus ball at 2 (1..3)
    inter = solid('<box name="A" x="4" y="4" z="4"/><orb name="B" r="3"/>'
                  '<intersection name="S"><first ref="A"/><second ref="B"/><position name="q" x="2"/></intersection>')
    check_ray(inter, (-10, 0, 0), (1, 0, 0), [9, 12])


def test_multiunion_and_scaled_solid():
    m = solid('<orb name="B" r="1"/><multiUnion name="S">'
              '<multiUnionNode name="n1"><solid ref="B"/><position name="p1" x="-3"/></multiUnionNode>'
              '<multiUnionNode name="n2"><solid ref="B"/><position name="p2" x="3"/></multiUnionNode></multiUnion>')
    check_ray(m, (-10, 0, 0), (1, 0, 0), [6, 8, 12, 14])
    s = solid('<orb name="B" r="1"/><scaledSolid name="S"><solidref ref="B"/><scale name="k" x="2" y="1" z="1"/>'
              '</scaledSolid>')
    check_ray(s, (-10, 0, 0), (1, 0, 0), [8, 12])


# ---- Structure ----

def world(daughters, extra_volumes="", solids=""):
    return doc(solids=solids, structure=extra_volumes +
               f'<volume name="World"><materialref ref="G4_AIR"/><solidref ref="WorldBox"/>{daughters}</volume>')


BAR = '<box name="Bar" x="10" y="0.4" z="0.4"/><box name="Small" x="1" y="1" z="1"/>'


def test_physvol_rotation_is_inverse():
    # physvol: x' = R^-1 x + t. A bar along x with rotation z = +30 deg ends up pointing at -30 deg.
    text = world('<physvol name="pv"><volumeref ref="bar"/><position name="p" x="100" unit="mm"/>'
                 '<rotation name="r" z="30" unit="deg"/></physvol>',
                 '<volume name="bar"><materialref ref="Fe0x55d1"/><solidref ref="Bar"/></volume>', BAR)
    m = gdml.loads(text, "w.gdml")
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    assert list(inside(m, [[100 + 4 * c, -4 * s, 0], [100 + 4 * c, 4 * s, 0]])) == [True, False]
    assert [leaf.material for leaf in m.leaves()] == ["Fe"]              # 0x pointer suffix stripped
    # world hidden: a ray from outside the world box meets only the bar
    start = np.array([100.0, 0, 0]) - 10 * np.array([c, -s, 0])
    check_ray(m, start, (c, -s, 0), [5, 15])                              # along the bar: its two ends
    shown = gdml.loads(text, "w.gdml", show_world=True)
    check_ray(shown, (-1000, 0, 0), (1, 0, 0), [500, 1500])
    assert sorted(leaf.material for leaf in shown.leaves()) == ["Fe", "G4_AIR"]


def test_nested_placement_scale_and_depth():
    vols = ('<volume name="small"><materialref ref="Lead"/><solidref ref="Small"/></volume>'
            '<volume name="mother"><materialref ref="Fe"/><solidref ref="Bar"/>'
            '<physvol><volumeref ref="small"/><position name="a" x="2"/></physvol></volume>')
    text = world('<physvol><volumeref ref="mother"/><position name="b" y="50"/>'
                 '<rotation name="r" z="-90" unit="deg"/><scale name="s" x="1" y="1" z="2"/></physvol>', vols, BAR)
    m = gdml.loads(text, "n.gdml")
    # mother rotated by R^-1 = Rz(+90): the bar lies along y around (0, 50); its daughter at (0, 52)
    assert [leaf.material for leaf in m.leaves()] == ["Fe", "Lead"]
    assert list(inside(m, [[0, 54, 0], [4, 50, 0], [0, 52, 0.9], [0, 52, 1.1]])) == [True, False, True, False]
    shallow = gdml.loads(text, "n.gdml", depth=1)
    assert [leaf.material for leaf in shallow.leaves()] == ["Fe"]


def test_assembly_places_its_contents():
    vols = ('<volume name="v"><materialref ref="Cu"/><solidref ref="Small"/></volume>'
            '<assembly name="pair"><physvol><volumeref ref="v"/><position name="a1" x="-2"/></physvol>'
            '<physvol><volumeref ref="v"/><position name="a2" x="2"/></physvol></assembly>')
    text = world('<physvol><volumeref ref="pair"/><position name="p" y="10"/></physvol>'
                 '<physvol><volumeref ref="pair"/><position name="q" y="-10"/>'
                 '<rotation name="r" z="90" unit="deg"/></physvol>', vols, BAR)
    m = gdml.loads(text, "a.gdml")
    assert [leaf.material for leaf in m.leaves()] == ["Cu"] * 4
    assert list(inside(m, [[2, 10, 0], [-2, 10, 0], [0, -8, 0], [0, -12, 0], [2, -10, 0]])) == \
        [True, True, True, True, False]
    assert len(gdml.loads(text, "a.gdml", depth=1).leaves()) == 4      # an assembly adds no level


def test_external_entity_beside_the_file(tmp_path):
    (tmp_path / "solids.xml").write_text('<orb name="S" r="2"/>')
    text = doc("&solids;").replace('<gdml ', '<!DOCTYPE gdml [ <!ENTITY solids SYSTEM "solids.xml"> ]>\n<gdml ', 1)
    path = tmp_path / "e.gdml"
    path.write_text(text)
    check_ray(gdml.load(path, solid="S"), (-10, 0, 0), (1, 0, 0), [8, 12])
    with pytest.raises(FormatError, match="only for documents loaded from a file"):
        gdml.loads(text, "e.gdml", solid="S")


# ---- Bad files ----

def _expect(text, pattern, **kw):
    with pytest.raises(FormatError, match=pattern) as info:
        gdml.loads(text, "bad.gdml", **kw)
    assert str(info.value).startswith("bad.gdml")
    return info.value


def test_bad_files_each_raise_one_clear_error(tmp_path):
    _expect("<gdml><solids>", "line 1: malformed XML")
    _expect("<notgdml/>", "root element")
    _expect(doc('<union name="S"><first ref="A"/><second ref="nope"/></union><box name="A" x="1" y="1" z="1"/>'),
            "undefined solid 'nope'", solid="S")
    _expect(world('<physvol><volumeref ref="ghost"/></physvol>'), "undefined volume 'ghost'")
    _expect(doc('<union name="S"><first ref="T"/><second ref="S"/></union>'
                '<union name="T"><first ref="S"/><second ref="S"/></union>'), "cycle", solid="S")
    _expect(world('<physvol><volumeref ref="a"/></physvol>',
                  '<volume name="a"><solidref ref="Small"/><physvol><volumeref ref="b"/></physvol></volume>'
                  '<volume name="b"><solidref ref="Small"/><physvol><volumeref ref="a"/></physvol></volume>', BAR),
            "placement cycle")
    _expect(doc('<blob name="S" r="1"/>'), r"unknown solid <blob>", solid="S")
    _expect(doc('<gencone name="S"/>'), r"<gencone name=\"S\">.*cannot be represented", solid="S")
    _expect(doc('<reflectedSolid name="S" solid="nope" sx="-1"/>'), "undefined solid 'nope'", solid="S")
    _expect(doc('<paraboloid name="S" rlo="2" rhi="1" dz="1"/>'), "needs rlo < rhi", solid="S")
    _expect(doc('<hype name="S" rmin="1" rmax="2" inst="1.2" outst="0.1" z="4"/>'), "must lie inside the outer",
            solid="S")
    _expect(doc('<tessellated name="S"/>'), r"<tessellated name=\"S\">: a <tessellated> solid needs facets", solid="S")
    _expect(doc('<tessellated name="S"><triangular vertex1="a" vertex2="b" vertex3="c"/></tessellated>'),
            r"<triangular.*vertex1: refers to undefined position 'a'", solid="S")
    _expect(doc('<box name="S" x="abc" y="1" z="1"/>'), r"x=\"abc\": .*undefined name 'abc'", solid="S")
    _expect(doc('<box name="S" x="1+" y="1" z="1"/>'), "bad expression", solid="S")
    _expect(doc('<box name="S" x="1/0" y="1" z="1"/>'), "division by zero", solid="S")
    _expect(doc('<box name="S" x="-1" y="1" z="1"/>'), "must be > 0", solid="S")
    _expect(doc('<box name="S" x="__import__(\'os\').getcwd()" y="1" z="1"/>'), "not allowed", solid="S")
    _expect(doc('<box name="S" x="a" y="1" z="1"/>', define='<constant name="a" value="b"/>'
                '<constant name="b" value="a"/>'), "'a' could not be evaluated", solid="S")
    _expect(doc('<box name="S" x="1" y="1" z="1"/>'), "no solid named 'T'", solid="T")
    _expect(doc('<box name="S" x="1" y="1" z="1"/><box name="S" x="1" y="1" z="1"/>'), "defined twice")
    bomb = ('<?xml version="1.0"?><!DOCTYPE gdml [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;">'
            '<!ENTITY c "&b;&b;&b;&b;&b;&b;">]><gdml>&c;</gdml>')
    _expect(bomb, "entity-expansion bomb")
    _expect('<!DOCTYPE gdml [<!ENTITY x SYSTEM "http://example.com/x.xml">]><gdml>&x;</gdml>', "never URLs")
    (tmp_path / "sub").mkdir()
    outside = '<!DOCTYPE gdml [<!ENTITY x SYSTEM "../secret.xml">]><gdml>&x;</gdml>'
    (tmp_path / "secret.xml").write_text("<solids/>")
    with pytest.raises(FormatError, match="outside the document's directory"):
        gdml.loads(outside, "bad.gdml", base_dir=str(tmp_path / "sub"))
    _expect('<!DOCTYPE gdml [<!ENTITY % p "x">]><gdml/>', "parameter entity")
    with pytest.raises(FormatError, match="missing.gdml: no such file"):
        gdml.load(tmp_path / "missing.gdml")


def test_unsupported_skip_option():
    text = world('<physvol><volumeref ref="t"/></physvol><physvol><volumeref ref="o"/></physvol>',
                 '<volume name="t"><materialref ref="Fe"/><solidref ref="X"/></volume>'
                 '<volume name="o"><materialref ref="Cu"/><solidref ref="O"/></volume>',
                 '<gencone name="X"/><orb name="O" r="1"/><union name="U"><first ref="X"/><second ref="O"/></union>')
    _expect(text, r"<gencone name=\"X\">.*on_unsupported='skip'")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = gdml.loads(text, "bad.gdml", on_unsupported="skip")
    assert [leaf.material for leaf in m.leaves()] == ["Cu"]
    assert any("gencone" in str(w.message) for w in caught)
    with pytest.raises(FormatError, match="bad option|on_unsupported must be"):
        gdml.loads(text, "bad.gdml", on_unsupported="maybe")


def test_fuzzed_documents_raise_only_format_errors():
    base = world('<physvol><volumeref ref="v"/><position name="p" x="L"/><rotation name="r" z="30" unit="deg"/>'
                 '</physvol><physvol><volumeref ref="asm"/></physvol>',
                 '<volume name="v"><materialref ref="Fe"/><solidref ref="U"/></volume>'
                 '<assembly name="asm"><physvol><volumeref ref="v"/><positionref ref="pp"/></physvol></assembly>',
                 '<tube name="T" rmin="1" rmax="L/2" z="4" deltaphi="270" aunit="deg"/>'
                 '<polyhedra name="P" numsides="5" deltaphi="2*pi"><zplane z="-1" rmax="3"/><zplane z="1" rmax="2"/>'
                 '</polyhedra><sphere name="Sp" rmin="1" rmax="3" deltatheta="1"/>'
                 '<union name="U"><first ref="T"/><second ref="P"/><positionref ref="pp"/></union>'
                 '<subtraction name="D"><first ref="U"/><second ref="Sp"/></subtraction>')
    base = base.replace("<define></define>", '<define><constant name="L" value="10"/>'
                        '<position name="pp" x="L*2" unit="mm"/></define>')
    assert gdml.loads(base, "fuzz.gdml").leaves()
    tokens = ['"', "<", ">", "/", "=", "0", "-1", "1e308", "nan", "&", "&amp;", "ref", "name", "x", "L",
              "^", "(", "*", "deg", "]]>", "<!--", "zplane", "physvol", "\x00", "é", " "]
    rng = random.Random(1234)
    accepted = 0
    for _ in range(400):
        text = list(base)
        for _ in range(rng.randint(1, 4)):
            i = rng.randrange(len(text))
            op = rng.random()
            if op < 0.4:
                del text[i:i + rng.randint(1, 8)]
            elif op < 0.8:
                text.insert(i, rng.choice(tokens))
            else:
                j = rng.randrange(len(text))
                text[i], text[j] = text[j], text[i]
        try:
            model = gdml.loads("".join(text), "fuzz.gdml", on_unsupported=rng.choice(["error", "skip"]))
        except ModelError:
            continue
        accepted += 1
        model.leaves()
    assert accepted > 0


def test_planar_solids_as_meshes():
    """<xtru> (a non-convex L through three sections), <tessellated> (a cube of quads,
    positions in cm times lunit="mm" as Geant4 reads them) and <tet> have the analytic
    answers: the L's area times height, the cube's and the tetrahedron's volume and hits."""
    xtru = ('<xtru name="L" lunit="mm">' + "".join(f'<twoDimVertex x="{x}" y="{y}"/>' for x, y in
            [(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)]) +
            '<section zOrder="0" zPosition="-1" xOffset="0" yOffset="0" scalingFactor="1"/>'
            '<section zOrder="1" zPosition="0" xOffset="0" yOffset="0" scalingFactor="1"/>'
            '<section zOrder="2" zPosition="2" xOffset="0" yOffset="0" scalingFactor="1"/></xtru>')
    corners = {f"c{i}": ((i >> 2 & 1) * 2 - 1, (i >> 1 & 1) * 2 - 1, (i & 1) * 2 - 1) for i in range(8)}
    define = "".join(f'<position name="{n}" unit="cm" x="{x}" y="{y}" z="{z}"/>' for n, (x, y, z) in corners.items())
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tess = ('<tessellated name="C" lunit="mm">' + "".join(
        f'<quadrangular vertex1="c{a}" vertex2="c{b}" vertex3="c{c}" vertex4="c{d}"/>' for a, b, c, d in quads) +
        '</tessellated>')
    tet = '<tet name="T" lunit="mm" vertex1="c0" vertex2="c1" vertex3="c2" vertex4="c4"/>'
    text = doc(solids=xtru + tess + tet, define=define)
    L = gdml.loads(text, "x.gdml", solid="L")
    assert csg.to_mesh(L).volume() == pytest.approx(3.0 * 3.0)
    hits = csg.trace(L, [[1.5, 1.5, -5.0], [0.5, 1.5, -5.0]], [[0, 0, 1.0]] * 2)
    assert np.isinf(hits.t[0]) and hits.t[1] == pytest.approx(4.0)        # the notch, then the L
    cube = gdml.loads(text, "x.gdml", solid="C")
    box_hits = csg.trace(csg.Box(20.0), [[3.0, 2.0, -50.0]], [[0, 0, 1.0]])
    assert csg.trace(cube, [[3.0, 2.0, -50.0]], [[0, 0, 1.0]]).t[0] == pytest.approx(box_hits.t[0])
    assert csg.to_mesh(gdml.loads(text, "x.gdml", solid="T")).volume() == pytest.approx(20.0**3 / 6.0)
