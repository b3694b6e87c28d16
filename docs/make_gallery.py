"""Render the gallery in docs/images/ (and docs/gallery.md) with csg_path.

    ./run.sh -- python docs/make_gallery.py [--spp 64] [--size 640x360]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi

import mitsuba_csg as csg
from mitsuba_csg import scenes as generators
from mitsuba_csg.cli import model_scene_dict

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
    for name, caption, make in ITEMS:
        model = make()
        scene = mi.load_dict(model_scene_dict(mi, csg, model, width, height, args.spp, "csg_path"))
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
