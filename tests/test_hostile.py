"""Hostile and extreme inputs (small files that describe huge models, pathological sizes):
each ends in the package's error naming the place, within a time and memory budget, in a
subprocess so that a regression cannot take the test run down with it."""
from __future__ import annotations

import math
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_isolated(code: str, timeout: float = 120.0) -> tuple[str, float, float]:
    """(output, seconds, peak resident MB) of `code` run by a fresh Python."""
    code = textwrap.dedent(code) + (
        "\nimport resource\nprint('peak_mb', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)\n")
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"did not finish within {timeout} s")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    return out, time.perf_counter() - start, float(out.rsplit("peak_mb", 1)[1].split()[0])


def _gdml(solids: str, structure: str) -> str:
    return (f'<?xml version="1.0"?>\n<gdml>\n<solids>\n<box name="b" x="1" y="1" z="1"/>\n{solids}\n</solids>\n'
            f'<structure>\n{structure}\n</structure>\n'
            '<setup name="Default" version="1.0"><world ref="World"/></setup>\n</gdml>\n')


def doubling_booleans(levels: int) -> str:
    """s_i = s_(i-1) | s_(i-1): 2^levels boxes from a few kilobytes."""
    solids = "\n".join(f'<union name="s{i}"><first ref="s{i - 1}"/><second ref="s{i - 1}"/>'
                       f'<position name="p{i}" x="0.1"/></union>' for i in range(1, levels + 1))
    structure = (f'<volume name="V"><materialref ref="G4_AIR"/><solidref ref="s{levels}"/></volume>\n'
                 '<volume name="World"><materialref ref="G4_AIR"/><solidref ref="w"/>'
                 '<physvol><volumeref ref="V"/></physvol></volume>')
    return _gdml('<box name="s0" x="1" y="1" z="1"/>\n<box name="w" x="100" y="100" z="100"/>\n' + solids, structure)


def doubling_placements(levels: int) -> str:
    """Volume L_i places L_(i-1) twice: 2^levels placed volumes."""
    volumes = ['<volume name="L0"><materialref ref="G4_AIR"/><solidref ref="b"/></volume>']
    volumes += [f'<volume name="L{i}"><materialref ref="G4_AIR"/><solidref ref="b"/>'
                f'<physvol><volumeref ref="L{i - 1}"/></physvol>'
                f'<physvol><volumeref ref="L{i - 1}"/><position name="q{i}" x="0.01"/></physvol></volume>'
                for i in range(1, levels + 1)]
    volumes.append(f'<volume name="World"><materialref ref="G4_AIR"/><solidref ref="b"/>'
                   f'<physvol><volumeref ref="L{levels}"/></physvol></volume>')
    return _gdml("", "\n".join(volumes))


def test_shared_subtrees_that_double_are_refused_as_they_are_built():
    """A subtree used twice at each of 40 levels is 2^40 primitives for the kernel: the
    operation that passes the limit refuses, at once, instead of anything walking it."""
    out, seconds, peak = run_isolated("""
        import mitsuba_csg as csg
        a = csg.Sphere(1.0)
        try:
            for i in range(40):
                a = a | a.translate((0.1, 0, 0))
        except csg.ModelError as e:
            print("refused at", i, ":", e)
        b = csg.Sphere(1.0)
        for i in range(20):
            b = b - b.rotate('z', 10)
        print("height", b.tree_height(), "leaves", b.leaf_count)
    """)
    assert "refused at 23 : union: the model expands to 1.68e+07 primitives" in out, out
    assert "more than the limit of 1e+07" in out
    assert "height 20 leaves 1048576" in out, out
    assert seconds < 30 and peak < 2000, (seconds, peak)


@pytest.mark.parametrize("maker, levels, pattern", [
    (doubling_booleans, 40, r'line \d+: <union name="s24">: union: the model expands to 1.68e\+07 primitives'),
    (doubling_placements, 40, r"line \d+: <physvol>: the hierarchy places 2.1e\+06 volumes or more"),
])
def test_gdml_that_describes_a_huge_model_is_refused_early(tmp_path, maker, levels, pattern):
    import re
    path = tmp_path / "huge.gdml"
    path.write_text(maker(levels))
    out, seconds, peak = run_isolated(f"""
        import time
        import mitsuba_csg as csg
        t0 = time.perf_counter()
        try:
            csg.load({str(path)!r})
            print("loaded")
        except csg.CSGError as e:
            print(type(e).__name__, e)
        print("load seconds", time.perf_counter() - t0)
    """)
    assert re.search("FormatError huge.gdml: " + pattern, out), out
    load_seconds = float(out.rsplit("load seconds", 1)[1].split()[0])
    assert load_seconds < 2.0 and peak < 2000, (load_seconds, peak)


def test_many_placements_within_the_limit_load_in_seconds(tmp_path):
    """2^18 doubled placements (524287 volumes) are within the limit: the walk reads each
    volume's solid and each placement's copies once, and validates transforms cheaply."""
    import mitsuba_csg as csg
    path = tmp_path / "many.gdml"
    path.write_text(doubling_placements(18))
    t0 = time.perf_counter()
    model = csg.load(str(path))
    assert model.leaf_count == 2**19 - 1
    assert time.perf_counter() - t0 < 60


def polyhedra_file(sides: int, zplanes) -> str:
    z = "".join(f'<zplane z="{zz}" rmin="0" rmax="{r}"/>' for zz, r in zplanes)
    solids = (f'<polyhedra name="p" startphi="0" deltaphi="360" numsides="{sides}" aunit="deg" lunit="mm">{z}'
              '</polyhedra>\n<box name="w" x="1000" y="1000" z="1000"/>')
    structure = ('<volume name="V"><materialref ref="G4_AIR"/><solidref ref="p"/></volume>\n'
                 '<volume name="World"><materialref ref="G4_AIR"/><solidref ref="w"/>'
                 '<physvol><volumeref ref="V"/></physvol></volume>')
    return _gdml(solids, structure)


@pytest.mark.parametrize("sides, zplanes", [
    (254, [(-10, 10), (10, 5)]),                                    # a tapered section: 256 planes
    (200, [(-100 + 10 * i, 20 + i % 3) for i in range(20)]),        # 19 sections of 202 planes
    (10_000, [(-10, 10), (10, 5)]),                                  # GDML's documented maximum
])
def test_polyhedra_with_many_sides_load_and_trace_fast(tmp_path, sides, zplanes):
    """The vertex check of a convex polyhedron used every plane triple against every plane
    (254 sides: 6.5 GB); a half-space intersection needs memory linear in the planes. The
    ray along -x at z = 0 meets the ring of sides at a corner (G4Polyhedra puts one on
    phi = 180 degrees for an even count), at the corner radius r / cos(pi / sides)."""
    path = tmp_path / "poly.gdml"
    path.write_text(polyhedra_file(sides, zplanes))
    out, seconds, peak = run_isolated(f"""
        import math, time
        import numpy as np
        import mitsuba_csg as csg
        t0 = time.perf_counter()
        model = csg.load({str(path)!r})
        t = csg.trace(model, np.array([[-500.0, 0, 0]]), np.array([[1.0, 0, 0]])).t[0]
        print("seconds", time.perf_counter() - t0, "t", t)
    """)
    (z0, r0), (z1, r1) = [(z, r) for z, r in zplanes if z <= 0][-1], [(z, r) for z, r in zplanes if z > 0][0]
    apothem = r0 + (r1 - r0) * (0 - z0) / (z1 - z0)
    corner = apothem / math.cos(math.pi / sides)
    t = float(out.split(" t ", 1)[1].split()[0])
    assert abs(t - (500.0 - corner)) < 1e-4 * 500, (t, 500.0 - corner)
    assert float(out.split("seconds", 1)[1].split()[0]) < 10 and peak < 1500, (out, peak)


def test_convex_polyhedron_planes_are_checked_in_linear_memory():
    """The documented limits agree with the code: 4..16384 planes of a ConvexPolyhedron,
    prisms of up to 1000 sides; unbounded, empty and flat sets are refused by name."""
    import numpy as np

    import mitsuba_csg as csg
    from mitsuba_csg.model.polyhedra import MAX_PLANES
    angles = 2 * np.pi * np.arange(MAX_PLANES - 2) / (MAX_PLANES - 2)
    ring = np.column_stack([np.cos(angles), np.sin(angles), np.full_like(angles, 0.2), np.ones_like(angles)])
    caps = [[0, 0, 1, 1], [0, 0, -1, 1]]
    t0 = time.perf_counter()
    solid = csg.ConvexPolyhedron(np.vstack([ring, caps]))
    assert time.perf_counter() - t0 < 5
    assert len(solid.vertices) == 2 * (MAX_PLANES - 2)
    with pytest.raises(csg.ModelError, match=f"needs 4..{MAX_PLANES} planes, got {MAX_PLANES + 1}"):
        csg.ConvexPolyhedron(np.vstack([ring, caps, [[1, 0, 0, 5]]]))
    assert len(csg.Prism(1000, 1.0, 1.0).vertices) == 2000
    slab_ring = [[1, 0, 0, 1], [-1, 0, 0, 1], [0, 1, 0, 1], [0, -1, 0, 1]]
    for planes, message in ((slab_ring, "extends to infinity"),
                            (slab_ring + [[0, 0, 1, 1], [0, 0, -1, -2]], "enclose no solid"),
                            (slab_ring + [[0, 0, 1, 0], [0, 0, -1, 0]], "enclose no solid")):
        with pytest.raises(csg.ModelError, match=message):
            csg.ConvexPolyhedron(planes)


@pytest.mark.parametrize("text, expected", [
    ("';' * 60_000_000", "FormatError x.csg: line 1, column 10000001: more than 10000000 statements"),
    ("'#' * 1_000_000 + 'cube(2);'", "loaded 1"),
    ("'cube(size=' + '-' * 1001 + '1);'", "cube: size [-1, -1, -1] has no volume"),
    ("'cube(size=[0:1:2]);'", "cube: size must be a number or [x, y, z], got [0 : 1 : 2]"),
])
def test_openscad_reader_is_bounded_in_memory_and_time(text, expected):
    """Tokens are read as the parser goes (60 MB of ';' held every token: more than 4 GB);
    repeated modifiers count once (a million '#' were quadratic); signs in a row are read in a
    loop (a thousand raised RecursionError); a range argument is shown as OpenSCAD writes it."""
    out, seconds, peak = run_isolated(f"""
        import mitsuba_csg as csg
        from mitsuba_csg.formats import openscad
        try:
            model = openscad.loads({text}, "x.csg")
            print("loaded", model.leaf_count)
        except csg.CSGError as e:
            print(type(e).__name__, e)
    """)
    assert expected in out, out
    assert seconds < 30 and peak < 1000, (seconds, peak)
