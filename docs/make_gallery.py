"""Render the gallery in docs/images/ (and docs/gallery.md) with csg_path.

    ./run.sh -- python docs/make_gallery.py [--spp 64] [--size 640x360]

Generated scenes, five real GDML detectors (Geant4's and Celeritas' files copied into
tests/data/gdml) drawn as `mitsuba-csg render` draws them, and five of OpenSCAD's bundled
examples (CC0; read as .scad, so OpenSCAD must be installed: they are left out otherwise).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi

import mitsuba_csg as csg
from mitsuba_csg import scenes as generators
from mitsuba_csg import viewing
from mitsuba_csg.scene_setup import model_scene_dict, scene_dict
from mitsuba_csg.formats.openscad import tool as openscad_tool

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def detector():
    """A small GDML detector: a tube with a phi cut, a polyhedra barrel and a torus ring."""
    text = """<?xml version="1.0"?>
<gdml>
  <define><constant name="R" value="40"/></define>
  <solids>
    <box name="World" x="400" y="400" z="400"/>
    <tube name="Beam" rmin="8" rmax="12" z="160" deltaphi="270" aunit="deg"/>
    <polyhedra name="Barrel" startphi="0" deltaphi="360" numsides="8" aunit="deg">
      <zplane z="-50" rmin="25" rmax="R"/><zplane z="50" rmin="25" rmax="R"/>
    </polyhedra>
    <torus name="Ring" rmin="0" rmax="5" rtor="55" deltaphi="360" aunit="deg"/>
  </solids>
  <structure>
    <volume name="BeamV"><materialref ref="G4_Be"/><solidref ref="Beam"/></volume>
    <volume name="BarrelV"><materialref ref="G4_PbWO4"/><solidref ref="Barrel"/></volume>
    <volume name="RingV"><materialref ref="G4_Cu"/><solidref ref="Ring"/></volume>
    <volume name="WorldV"><materialref ref="G4_AIR"/><solidref ref="World"/>
      <physvol><volumeref ref="BeamV"/></physvol>
      <physvol><volumeref ref="BarrelV"/></physvol>
      <physvol><volumeref ref="RingV"/><position name="p" z="60"/></physvol>
    </volume>
  </structure>
  <setup name="Default" version="1.0"><world ref="WorldV"/></setup>
</gdml>"""
    from mitsuba_csg.formats import gdml
    return gdml.loads(text, "detector.gdml")


GDML = ROOT / "tests" / "data" / "gdml"
EXAMPLES = Path("/usr/share/openscad/examples")
# (name, caption, file, cut-aways)
FILES = [
    ("simple_cms", "Celeritas' simple CMS (GDML), cut away at y < 0", GDML / "simple-cms.gdml", ["y>0"]),
    ("testem3", "Geant4's TestEm3 calorimeter (GDML): 50 lead / liquid argon layers, cut at y < 0",
     GDML / "testem3.gdml", ["y>0"]),
    ("lht", "Geant4's ChargeExchangeMC target and calorimeter (GDML, replicas), mothers see-through",
     GDML / "lht.gdml", []),
    ("tes", "Geant4's X-ray TES detector (GDML, tessellated solids), its shield cut away at y < 0",
     GDML / "xray_TESdetector.gdml", ["y>0"]),
    ("par02", "Geant4's Par02 detector (GDML), cut away at y < 0", GDML / "Par02FullDetector.gdml", ["y>0"]),
    ("example001", "OpenSCAD's example001 (a sphere minus three cylinders)", EXAMPLES / "Old" / "example001.scad", []),
    ("example024", "OpenSCAD's example024 (a Menger sponge)", EXAMPLES / "Old" / "example024.scad", []),
    ("csg", "OpenSCAD's Basics/CSG", EXAMPLES / "Basics" / "CSG.scad", []),
    ("candle_stand", "OpenSCAD's Parametric/candleStand (rotate_extrude)", EXAMPLES / "Parametric" / "candleStand.scad",
     []),
    ("logo", "OpenSCAD's Basics/logo", EXAMPLES / "Basics" / "logo.scad", []),
]

ITEMS = [
    ("cheese", "The paper's Cheese: a cube minus 1000 spheres", lambda: generators.cheese(1000)),
    ("city", "A City of 3400 primitives (boxes, prisms, cones; windows subtracted)", lambda: generators.city(340)),
    ("satellites", "Satellites: 200 copies of a 14-primitive satellite", lambda: generators.satellites(200)),
    ("detector", "A GDML detector: a cut tube, an octagonal polyhedra barrel, a torus", detector),
]


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--size", default="640x360")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    lines = ["# Gallery", "", f"Rendered by `docs/make_gallery.py` with `csg_path`, {args.spp} spp, "
             f"{width}x{height}, on the machine of `docs/benchmarks.md`.", ""]
    work = [(name, caption, lambda make=make: [(make(), None, None)]) for name, caption, make in ITEMS]
    for name, caption, path, cuts in FILES:
        if not path.exists() or (path.suffix == ".scad" and openscad_tool.executable() is None):
            print(f"{name}: skipped ({path} or OpenSCAD is missing)")
            continue
        work.append((name, caption, lambda path=path, cuts=cuts: viewing.model_parts(
            path, [viewing.parse_cut(c) for c in cuts])))
    for name, caption, make in work:
        parts = make()
        if parts[0][1] is None:                 # a generated model: one colour
            model = parts[0][0]
            scene = mi.load_dict(model_scene_dict(mi, csg, model, width, height, args.spp, "csg_path"))
        else:
            model = csg.union(*[part[0] for part in parts])
            scene = mi.load_dict(scene_dict(mi, csg, parts, width, height, args.spp, "csg_path"))
        t0 = time.perf_counter()
        image = mi.render(scene)
        dr.eval(image)
        dr.sync_thread()          # kernels run asynchronously: wait before reading the clock
        seconds = time.perf_counter() - t0
        mi.util.write_bitmap(str(HERE / "images" / f"gallery_{name}.png"), image)
        lines += [f"## {caption}", "", f"![{name}](images/gallery_{name}.png)", "",
                  f"{len(model.leaves())} primitives, {seconds:.1f} s.", ""]
        print(f"{name}: {seconds:.1f} s", flush=True)
    (HERE / "gallery.md").write_text("\n".join(lines))


if __name__ == "__main__":
    main()
