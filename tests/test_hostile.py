"""Hostile and extreme inputs (small files that describe huge models, pathological sizes):
each ends in the package's error naming the place, within a time and memory budget, in a
subprocess so that a regression cannot take the test run down with it."""
from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_isolated(code: str, timeout: float = 120.0, memory_cap_gb: float = 4.0) -> tuple[str, float, float]:
    """(output, seconds, peak resident MB) of `code` run by a fresh Python whose address space
    is capped, so that a regression fails there instead of taking the machine down."""
    cap = int(memory_cap_gb * 2**30)
    code = f"import resource\nresource.setrlimit(resource.RLIMIT_AS, ({cap}, {cap}))\n" + textwrap.dedent(code) + (
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


@pytest.mark.parametrize("exponent", [-24, -12, 0, 12, 24])
def test_the_kernel_traces_a_scene_of_any_size(exponent):
    """The kernel works in the scene's own frame (root box centred, half-side 1, unit ray
    directions): a sphere with a spherical bite taken out, at any scale from 1e-24 to 1e24
    and far from the origin, gives the analytic first hit (a sphere of radius 1e-20 or 1e20
    used to miss every ray)."""
    import numpy as np

    import mitsuba_csg as csg
    s = 10.0 ** exponent
    shift = np.array([3.0, -2.0, 1.0]) * s
    model = (csg.Sphere(1.0) - csg.Sphere(0.5).translate((0, 0, -1))).scale(s).translate(shift)
    rng = np.random.default_rng(exponent + 100)
    xy = rng.uniform(-0.9, 0.9, (400, 2))
    xy = xy[np.hypot(*xy.T) < 0.95]
    rho2 = (xy ** 2).sum(1)
    z_enter = -np.sqrt(1 - rho2)                         # unit sphere, entered from below
    bitten = rho2 + (z_enter + 1) ** 2 < 0.25
    z_hit = np.where(bitten, -1 + np.sqrt(np.maximum(0.25 - rho2, 0)), z_enter)
    o = np.column_stack([xy, np.full(len(xy), -5.0)]) * s + shift
    hits = csg.trace(model, o, np.tile([0, 0, 2.0], (len(xy), 1)))
    expected = (z_hit + 5.0) / 2.0 * s                   # t along a direction of length 2
    np.testing.assert_allclose(hits.t, expected, rtol=2e-5)
    normals = np.where(bitten[:, None], -(np.column_stack([xy, z_hit + 1]) / 0.5), np.column_stack([xy, z_hit]))
    np.testing.assert_allclose(hits.normal, normals, atol=1e-3)


@pytest.mark.parametrize("model, message", [
    ("csg.Sphere(1e-31)", r"primitive 0 \(Sphere, in leaves\(\) order\): its box \(2e-31 to 2e-31 across\) is thinner than 1e-30"),
    ("csg.Sphere(1e31)", r"its box \(2e\+31 to 2e\+31 across\) reaches beyond 1e\+30 from the origin"),
    ("csg.Sphere(1.0).translate((1e300, 0, 0))", r"reaches beyond 1e\+30 from the origin"),
    ("csg.Box(5e-324)", r"primitive 0 \(Box, in leaves\(\) order\): its box \(0 to 0 across\) is thinner than 1e-30"),
    ("csg.Box(1e308) | csg.Box(1.0)", r"primitive 0 \(Box.*reaches beyond 1e\+30"),
    ("csg.Box([1.0, 1.0, 5e-324]) - csg.Sphere(0.5)", r"primitive 0 \(Box.*0 to 1 across\) is thinner than 1e-30"),
    ("csg.Box(1.0) - csg.Sphere(1e-16)", r"primitive 1 \(Sphere.*thinner than 1e-15 of the scene's size 1"),
])
def test_sizes_float32_cannot_trace_are_refused_by_name(model, message):
    import numpy as np

    import mitsuba_csg as csg
    with pytest.raises(csg.ModelError, match=message):
        csg.trace(eval(model), np.zeros((1, 3)), np.array([[0, 0, 1.0]]))
    with pytest.raises(csg.ModelError, match=message):
        eval(model).bounds()


def test_parts_too_small_or_too_far_for_float32_are_warned_about():
    import numpy as np

    import mitsuba_csg as csg
    with pytest.warns(csg.PrecisionWarning, match=r"1 primitive\(s\) are smaller than 2\^-18 of the scene's size"):
        csg.prepare(csg.Box(1.0) - csg.Sphere(1e-7).translate((0.5, 0, 0)))
    with pytest.warns(csg.PrecisionWarning, match="lies 1e\\+05 from the origin but is only 2 across"):
        csg.prepare(csg.Sphere(1.0).translate((1e5, 0, 0)))
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        csg.prepare(csg.Box(1.0) - csg.Sphere(1e-4).translate((0.5, 0, 0)))
        # an "infinite" medium as Geant4 users write it: a 1e22 mm box, traced from inside
        hits = csg.trace(csg.Box(1e22), np.zeros((1, 3)), np.array([[1.0, 0, 0]]))
    assert abs(hits.t[0] - 5e21) < 1e-5 * 5e21 and not hits.entering[0]


def test_a_gdml_scale_that_makes_a_placement_singular_names_the_element(tmp_path):
    import mitsuba_csg as csg
    structure = ('<volume name="V"><materialref ref="G4_AIR"/><solidref ref="b"/></volume>\n'
                 '<volume name="World"><materialref ref="G4_AIR"/><solidref ref="w"/>'
                 '<physvol name="pv1"><volumeref ref="V"/><scale name="s" x="1e30" y="1" z="1"/></physvol></volume>')
    path = tmp_path / "scaled.gdml"
    path.write_text(_gdml('<box name="w" x="100" y="100" z="100"/>', structure))
    with pytest.raises(csg.CSGError, match=r'scaled.gdml: line \d+: <physvol name="pv1">: transform: singular'):
        csg.load(str(path))


def test_files_that_are_not_regular_files_are_refused_without_blocking(tmp_path):
    """A FIFO as the model file, or as a GDML external entity, blocked forever."""
    import mitsuba_csg as csg
    for suffix in ("json", "gdml", "csg", "stl", "scad"):
        fifo = tmp_path / f"pipe.{suffix}"
        os.mkfifo(fifo)
        with pytest.raises(csg.CSGError, match=f"pipe.{suffix}: not a regular file"):
            csg.load(str(fifo))
    os.mkfifo(tmp_path / "entity.xml")
    (tmp_path / "doc.gdml").write_text(
        '<?xml version="1.0"?>\n<!DOCTYPE gdml [<!ENTITY solids SYSTEM "entity.xml">]>\n'
        '<gdml><solids>&solids;</solids></gdml>\n')
    with pytest.raises(csg.CSGError, match=r"external entity .*is not a regular file"):
        csg.load(str(tmp_path / "doc.gdml"))


def test_messages_never_echo_a_megabyte():
    import json

    import mitsuba_csg as csg
    from mitsuba_csg.formats import gdml, native_json
    big = "x" * 1_000_000
    sphere = {"type": "sphere", "radius": 1}
    documents = [{"root": {**sphere, big: 2}}, {"root": {**sphere, "type": big}},
                 {"materials": {"m": {"type": "diffuse"}}, "root": {**sphere, "material": big}}]
    for document in documents:
        with pytest.raises(csg.CSGError) as info:
            native_json.loads(json.dumps({"format": "mitsuba-csg", "version": 1, **document}))
        assert len(str(info.value)) < 400 and "(1000000 characters)" in str(info.value), str(info.value)[:300]
    with pytest.raises(csg.CSGError) as info:
        gdml.loads(_gdml(f'<box name="{big}" x="-1" y="1" z="1"/>', ""), "x.gdml")
    assert len(str(info.value)) < 2100
    text = '{"format": "mitsuba-csg", "version": 1, "root": {"type": "sphere", "radius": %s}}' % ("1" * 5000)
    with pytest.raises(csg.CSGError, match=r"root\.radius: must be finite, got a 5000-digit integer"):
        native_json.loads(text)


@pytest.mark.parametrize("call, message", [
    ("csg.trace(S, o, d, max_iterations=-1)", "max_iterations: expected an integer in 1..2147483647"),
    ("csg.trace(S, o, d, max_iterations=10**12)", "max_iterations: expected an integer in 1..2147483647"),
    ("csg.trace(S, o, d, max_iterations='3')", "max_iterations: expected an integer"),
    ("csg.trace(S, o, d, tmin='0')", "tmin: expected a number, got str"),
    ("csg.trace(S, o, d, tmax=10**400)", "tmax: an integer beyond the float range"),
    ("csg.trace(S, [['a', 'b', 'c']], d[:1])", r"origins: expected an \(N, 3\) array of numbers"),
    ("csg.trace(S, [[0, 0], [1, 2, 3]], d)", r"origins: expected an \(N, 3\) array of numbers"),
    ("csg.contains(S, [[0, 0], [1]])", r"points: expected an \(N, 3\) array of numbers"),
    ("csg.trace(S, o[:1], np.array([[0, 0, 1e-320]]))", "row 0 is the zero vector, or rounds to it in float32"),
    ("csg.Sphere(10**400)", "Sphere.radius: must be finite, got an integer beyond the float range"),
    ("csg.Box(True)", "Box.size: expected a number, got True"),
    ("csg.Box('1')", "Box.size: expected a number, got '1'"),
    ("csg.Box([1, 2])", "Box.size: expected a number or 3 numbers, got 2 items"),
])
def test_api_arguments_raise_the_packages_errors(call, message):
    import numpy as np

    import mitsuba_csg as csg
    S = csg.Sphere(1.0)
    o, d = np.array([[0, 0, -5.0], [0.5, 0, -5]]), np.array([[0, 0, 1.0], [0, 0, 1]])
    with pytest.raises(csg.CSGError, match=message):
        eval(call)


SCENE_WITHOUT_PARAMETERS = """<scene version="3.0.0">
  <integrator type="csg_path"/>
  <sensor type="perspective"><transform name="to_world"><lookat origin="0, 0, 6" target="0, 0, 0" up="0, 1, 0"/>
  </transform><film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/></film></sensor>
  <emitter type="constant"/>
  <shape type="csg"><string name="filename" value="{model}"/></shape>
</scene>
"""


def test_cli_render_errors_name_the_reason_and_come_before_the_render(tmp_path, capsys):
    """A bad csg shape in a scene showed only Mitsuba's first line ("Traceback ..."); a scene
    that does not use $spp/$width/$height was refused for unused parameters; an unwritable
    output was found after the render; an unusable variant was an internal ImportError."""
    from mitsuba_csg.cli import main
    bad = tmp_path / "bad.xml"
    bad.write_text(SCENE_WITHOUT_PARAMETERS.format(model="nope.json"))
    assert main(["render", str(bad), "-o", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err
    assert 'failed to instantiate shape plugin of type "csg": FormatError: nope.json: no such file' in err, err
    assert "Traceback" not in err
    good = tmp_path / "good.xml"
    good.write_text(SCENE_WITHOUT_PARAMETERS.format(model=ROOT / "scenes" / "models" / "demo_cheese_small.json"))
    assert main(["render", str(good), "-o", str(tmp_path / "good.exr")]) == 0
    assert (tmp_path / "good.exr").stat().st_size > 0
    t0 = time.perf_counter()
    assert main(["render", "--size", "640x360", "--spp", "64", "-o", "/proc/no/such/place.exr"]) == 2
    assert "cannot write there" in capsys.readouterr().err
    assert time.perf_counter() - t0 < 5                  # refused before rendering
    import mitsuba as mi
    if "cuda_ad_rgb" in mi.variants():
        code = main(["render", "--variant", "cuda_ad_rgb", "--size", "8x8", "--spp", "1", "-o",
                     str(tmp_path / "cuda.exr")])
        err = capsys.readouterr().err
        assert code == 0 or "cannot start on this machine" in err, err
        mi.set_variant("llvm_ad_rgb")


def test_an_image_that_was_not_written_whole_is_an_error(tmp_path, monkeypatch):
    """A full disk left a short file and "rendered ... -> out.exr" with exit 0: the image is
    read back before it takes the real name."""
    import numpy as np
    import OpenEXR

    from mitsuba_csg import images

    class Truncating(OpenEXR.File):
        def write(self, path):
            open(path, "wb").close()                     # what ENOSPC leaves behind
    monkeypatch.setattr(images.OpenEXR, "File", Truncating)
    out = tmp_path / "out.exr"
    with pytest.raises(OSError, match="not written completely"):
        images.write_exr(out, np.zeros((4, 4, 3)), ["R", "G", "B"])
    assert list(tmp_path.iterdir()) == []                # neither the image nor a partial file


@pytest.mark.parametrize("extra, message", [
    ({"optimise": False}, "unknown property 'optimise'; a csg shape takes filename or model, optimize, to_world"),
    ({"optimize": "false"}, "'optimize' must be a boolean"),
    ({"to_world": "translate(1, 0, 0)"}, "'to_world' must be a transform"),
    ({"inner": {"type": "sphere"}}, "cannot hold other shapes ('inner')"),
    ({"fog": {"type": "homogeneous"}}, "a medium goes in 'interior' or 'exterior', not 'fog'"),
])
def test_the_csg_shape_refuses_properties_it_would_ignore(extra, message):
    """Misspelt or mistyped properties were silently ignored or misread ("false" was true)."""
    import mitsuba as mi

    import mitsuba_csg as csg
    with pytest.raises(Exception) as info:
        mi.load_dict({"type": "csg", "model": csg.model_ref(csg.Sphere(1.0)), **extra})
    assert message in str(info.value), str(info.value)[-300:]
    shape = mi.load_dict({"type": "csg", "model": csg.model_ref(csg.Sphere(1.0)), "optimize": False,
                          "bsdf": {"type": "diffuse"}})
    assert shape.optimize is False


def test_models_too_big_for_the_memory_are_refused_up_front(tmp_path, monkeypatch):
    """The memory a model needs is estimated from its counts (and a JSON file's size) and
    compared with what the machine has available, so a model that cannot fit is refused
    with the numbers instead of dying with a MemoryError. The machine here is made small."""
    import json

    import mitsuba_csg as csg
    from mitsuba_csg import memory
    monkeypatch.setattr(memory, "available_bytes", lambda: 512 * 2**20)
    model = csg.Sphere(1.0)
    for _ in range(20):                                  # 2^20 primitives from 21 nodes
        model = model | model.translate((0.5, 0, 0))
    t0 = time.perf_counter()
    with pytest.raises(csg.ModelError, match=r"a model of 1048576 primitives needs about 2.0 GiB of memory, "
                                             r"and 512 MiB are available"):
        csg.prepare(model)
    assert time.perf_counter() - t0 < 1
    path = tmp_path / "big.json"
    spheres = [{"type": "sphere", "radius": 1.0, "transform": [{"translate": [i, 0, 0]}]} for i in range(50_000)]
    path.write_text(json.dumps({"format": "mitsuba-csg", "version": 1,
                                "root": {"type": "union", "children": spheres}}))
    monkeypatch.setattr(memory, "available_bytes", lambda: 16 * 2**20)
    with pytest.raises(csg.ModelError, match=r"big.json: reading \d+ bytes of JSON \(50001 nodes\) needs about \d+ MiB of memory, and 16 MiB"):
        csg.load(str(path))
    monkeypatch.undo()
    assert memory.available_bytes() is None or memory.available_bytes() > 2**20


def test_a_tree_past_the_node_limit_is_refused_by_name(monkeypatch):
    """The kernel's stack frames hold node ids in 29 bits; a tree with more nodes (here: the
    limit lowered to 4) is refused with both counts, not traced with ids cut short."""
    import mitsuba_csg as csg
    from mitsuba_csg.engine import device
    monkeypatch.setattr(device, "MAX_NODES", 4)
    model = csg.Sphere(1.0) | csg.Box(1.0).translate((3, 0, 0)) | csg.Sphere(0.5).translate((0, 3, 0))
    with pytest.raises(csg.ModelError, match=r"has \d+ nodes; the kernel addresses fewer than 4"):
        csg.prepare(model)
