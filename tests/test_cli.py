"""The command line, at small sizes: every subcommand and every error path."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from mitsuba_csg.cli import main

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "scenes" / "models" / "demo_cheese_small.json"


def run(*args):
    return main([str(a) for a in args])


def test_render_demo_writes_exr_and_png(tmp_path, capsys):
    out = tmp_path / "demo.exr"
    assert run("render", "--size", "32x18", "--spp", "2", "--passes", "2", "-o", out, "--png") == 0
    image = np.array(mi.Bitmap(str(out)))
    assert image.shape[:2] == (18, 32) and np.isfinite(image).all() and image.mean() > 0.01
    assert (tmp_path / "demo.png").exists()
    assert "built-in Cheese" in capsys.readouterr().out


def test_no_arguments_means_render(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert run("--size", "16x9", "--spp", "1") == 0
    assert (tmp_path / "cheese.exr").exists()


def test_render_model_and_scene(tmp_path):
    assert run("render", MODEL, "--size", "24x16", "--spp", "1", "-o", tmp_path / "m.exr") == 0
    assert run("render", ROOT / "scenes" / "cheese.xml", "--size", "24x16", "--spp", "1", "-o", tmp_path / "s.exr") == 0
    assert run("render", MODEL, "--integrator", "csg_aov", "--size", "8x8", "--spp", "1", "-o", tmp_path / "a.exr") == 0
    aov = mi.Bitmap(str(tmp_path / "a.exr"))
    assert "dd.y" in [c for c in aov.struct_()] or aov.channel_count() > 3


def test_render_and_bench_builtin_scenes(tmp_path, capsys):
    assert run("render", "city-3385", "--size", "24x16", "--spp", "1", "-o", tmp_path / "c.exr") == 0
    assert run("bench", "satellites-87.5k", "--size", "16x9", "--repeats", "1") == 0
    assert "87500 primitives" in capsys.readouterr().out


def test_python_m_entry_point(tmp_path):
    run_ = subprocess.run([sys.executable, "-m", "mitsuba_csg", "info", str(MODEL)], capture_output=True, text=True,
                          cwd=ROOT)
    assert run_.returncode == 0, run_.stderr
    assert "primitives   21: 1 Box, 20 Sphere" in run_.stdout


def test_info(capsys):
    assert run("info", MODEL) == 0
    out = capsys.readouterr().out
    assert "height" in out and "bounds" in out and "optimized" in out


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl", ".json"])
def test_convert(tmp_path, suffix):
    out = tmp_path / f"model{suffix}"
    assert run("convert", MODEL, "-o", out, "--segments", "16") == 0
    assert out.stat().st_size > 100


def test_bench(capsys):
    assert run("bench", MODEL, "--size", "32x18", "--repeats", "1") == 0
    assert "Mrays/s" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["render", "missing.json"], "missing.json: no such file"),
    (["render", "model.txt"], "expected a Mitsuba scene"),
    (["render", "city-12"], "built-in scene (cheese-500"),
    (["info", "missing.gdml"], "no such file"),
    (["--variant", "nope", "info", str(MODEL)], "unknown variant 'nope'"),
    (["--variant", "scalar_rgb", "info", str(MODEL)], "scalar variant"),
    (["convert", str(MODEL), "-o", "out.xyz"], "can write .ply"),
    (["render", "-o", "out.png", "--size", "8x8", "--spp", "1"], "OpenEXR"),
])
def test_errors_are_one_line(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "model.txt").write_text("nothing")
    assert run(*argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("mitsuba-csg: error:") and message in err and "\n" not in err


def test_bad_json_model_names_the_place(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "mitsuba-csg", "version": 1, "root": {"type": "sphere", "radius": -1}}')
    assert run("info", bad) == 2
    assert "root.radius" in capsys.readouterr().err


def test_bad_size_is_an_argument_error(capsys):
    with pytest.raises(SystemExit) as e:
        run("render", "--size", "ten")
    assert e.value.code == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err


def read_exr(path) -> dict:
    """Channels of an EXR file, read with OpenEXR (not Mitsuba's reader)."""
    import OpenEXR
    with OpenEXR.File(str(path), separate_channels=True) as f:
        return {name: np.array(channel.pixels) for name, channel in f.channels().items()}


def test_aov_layers_in_the_exr(tmp_path):
    """A sphere seen by the framing camera: the depth layer at the image centre is the camera's
    distance to the centre minus the radius, the normal faces the camera, the prim index is 0,
    and the colour channels are those Mitsuba's own reader sees."""
    from mitsuba_csg.camera import framing
    model = tmp_path / "ball.json"
    model.write_text('{"format": "mitsuba-csg", "version": 1, "root": {"type": "sphere", "radius": 1.5}}')
    out = tmp_path / "ball.exr"
    assert run("render", model, "--size", "33x19", "--spp", "4", "--aov", "-o", out) == 0
    layers = read_exr(out)
    assert {"R", "G", "B", "depth", "normal.x", "normal.y", "normal.z", "prim"} <= set(layers)
    origin, target = framing((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5), 40.0, 33 / 19)
    centre = (9, 16)
    assert layers["depth"][centre] == pytest.approx(np.linalg.norm(origin - target) - 1.5, rel=1e-3)
    normal = np.array([layers[f"normal.{c}"][centre] for c in "xyz"])
    towards_camera = (origin - target) / np.linalg.norm(origin - target)
    assert normal @ towards_camera > 0.99          # averaged over the pixel: ~4 degrees of sphere
    assert layers["prim"][centre] == 0.0 and layers["depth"][0, 0] == 0.0     # a corner sees no sphere
    mitsuba = np.array(mi.Bitmap(str(out)))
    np.testing.assert_array_equal(mitsuba[..., 0], layers["R"])


def test_aov_names_are_checked(capsys):
    with pytest.raises(SystemExit):
        run("render", "--aov", "depth,colour")
    assert "depth, normal, position, prim, shape" in capsys.readouterr().err


def test_global_options_around_an_implied_render(tmp_path, capsys):
    """`mitsuba-csg --variant V model` and `mitsuba-csg model ... --verbose` render, as `render` would."""
    out = tmp_path / "m.exr"
    assert run("--variant", "llvm_ad_rgb", MODEL, "--size", "8x8", "--spp", "1", "-o", out) == 0
    assert out.exists()
    assert run(MODEL, "--size", "8x8", "--spp", "1", "-o", out, "--verbose") == 0
    with pytest.raises(Exception):                  # --verbose after the command still re-raises
        run("info", tmp_path / "missing.json", "--verbose")


DETECTOR = """<?xml version="1.0"?>
<gdml><define/><materials>
  <material name="Fe" Z="26"><D value="7.87"/><atom value="55.85"/></material>
  <material name="Air" Z="7"><D value="0.0012"/><atom value="14.0"/></material></materials>
<solids><box name="W" x="200" y="200" z="200" lunit="m"/><box name="Hall" x="40" y="40" z="40" lunit="m"/>
  <box name="Shell" x="30" y="30" z="30" lunit="m"/><orb name="Core" r="8" lunit="m"/></solids>
<structure>
  <volume name="core"><materialref ref="Fe"/><solidref ref="Core"/></volume>
  <volume name="shell"><materialref ref="Fe"/><solidref ref="Shell"/>
    <physvol><volumeref ref="core"/></physvol></volume>
  <volume name="hall"><materialref ref="Air"/><solidref ref="Hall"/>
    <physvol><volumeref ref="shell"/></physvol></volume>
  <volume name="World"><materialref ref="Air"/><solidref ref="W"/>
    <physvol><volumeref ref="hall"/></physvol></volume>
</structure><setup name="Default" version="1.0"><world ref="World"/></setup></gdml>"""


def test_a_detector_renders_as_geant4_draws_it(tmp_path):
    """A 40 m detector in mm (beyond Mitsuba's default far clip): its air hall is not drawn, the
    shell holding the core is see-through, the core solid; a cut-away x > 0 halves them and its
    face has the volume's material; --hide and --depth drop volumes."""
    from mitsuba_csg import viewing
    from mitsuba_csg.formats import gdml
    path = tmp_path / "det.gdml"
    path.write_text(DETECTOR)
    view = viewing.DetectorView(gdml.volumes(path))
    mothers, solids = view.models([viewing.parse_cut("x>0")])
    assert [leaf.material for leaf in solids.leaves()] == ["Fe", "Fe"]            # the core and its cut box
    assert mothers is not None and "Air" not in {leaf.material for leaf in mothers.leaves()}
    inside = np.array([[1000.0, 0, 0], [-1000.0, 0, 0], [12000.0, 0, 0]])
    assert csg_contains(solids, inside).tolist() == [True, False, False]
    assert csg_contains(mothers, inside).tolist() == [True, False, True]
    out = tmp_path / "det.exr"
    assert run("render", path, "--size", "32x18", "--spp", "2", "--cut", "x>0", "--aov", "depth", "-o", out) == 0
    depth = read_exr(out)["depth"]
    assert 1e4 < depth[9, 16] < 2e5                  # the detector is there, tens of metres away (in mm)
    assert run("render", path, "--size", "16x9", "--spp", "1", "--hide", "shell", "--depth", "3",
               "-o", tmp_path / "h.exr") == 0


def csg_contains(model, points):
    import mitsuba_csg as csg
    return csg.contains(model, points)


@pytest.mark.parametrize("argv, message", [
    (["render", str(MODEL), "--depth", "2"], "--depth, --world and --hide apply to GDML"),
    (["render", str(MODEL), "--skip-unsupported"], "--skip-unsupported applies to GDML and OpenSCAD"),
    (["render", str(MODEL), "--cut", "w>0"], "expected AXIS>VALUE or AXIS<VALUE"),
])
def test_view_options_are_checked(argv, message, capsys):
    assert run(*argv, "--size", "8x8", "--spp", "1") == 2
    assert message in capsys.readouterr().err


def test_materials_get_distinct_colours():
    from mitsuba_csg import viewing
    import mitsuba_csg as csg
    model = csg.union(csg.Sphere(1, material="G4_Pb"), csg.Sphere(1, material="G4_lAr").translate((3, 0, 0)),
                      csg.Box(1, material="color_1_0_0_1").translate((6, 0, 0)))
    table = viewing.material_bsdfs(model)
    colours = [tuple(table[k]["reflectance"]["value"]) for k in ("G4_Pb", "G4_lAr")]
    assert colours[0] != colours[1] and max(abs(a - b) for a, b in zip(*colours)) > 0.2
    assert table["color_1_0_0_1"]["reflectance"]["value"] == [1.0, 0.0, 0.0]


@pytest.mark.parametrize("width, height", [(8, 4), (10, 7), (1, 1)])
def test_tile_order_is_a_permutation_into_blocks(width, height):
    """Every pixel once; consecutive runs of 16 are one 4x4 block where the image holds it."""
    from mitsuba_csg.camera import tile_order
    perm = tile_order(width, height)
    assert sorted(perm.tolist()) == list(range(width * height))
    y, x = np.divmod(perm, width)
    block = (y // 4) * ((width + 3) // 4) + x // 4
    assert np.all(np.diff(block) >= 0)        # blocks one after another, each contiguous
    full = np.flatnonzero(np.bincount(block) == 16)
    for b in full:
        members = perm[block == b]
        assert len(set(y[block == b])) == 4 and len(set(x[block == b])) == 4, members
