"""Mesh leaves: primary rays on a lone mesh leaf against Embree on the same triangles, and a
Cheese whose holes are triangle meshes against the analytic Cheese, measured in one run.

    ./run.sh bench mesh_leaves.py [--triangles 70000] [--holes 500] [--size 1280x720]

The lone mesh is a blob (a sphere warped by three waves, non-convex), made by manifold3d
at about `--triangles` triangles. The mesh Cheese replaces every spherical hole by a
geodesic-like sphere mesh of `--hole-segments` segments (manifold3d's sphere).

CSG frames are timed twice: traced (each call builds the kernel in Python, then runs the
cached compiled kernel) and frozen (`trace_rays(frozen=True)`: the recorded kernels
replayed, as a render loop of fixed size would); Embree's Mitsuba call traces almost nothing.
"""
from __future__ import annotations

import argparse

import numpy as np

import common
from mesh_route import embree_primary, mitsuba_mesh
from trace_throughput import measure, rays_for


def blob(triangles: int):
    import manifold3d as m3

    # manifold3d's sphere of n segments has about n^2 / 2 triangles.
    n = max(8, int(round(np.sqrt(2.0 * triangles))))

    def wave(p):
        x, y, z = p
        r = 1.0 + 0.18 * np.sin(3.0 * x) * np.cos(2.0 * y) + 0.12 * np.sin(4.0 * z + 1.0)
        return (r * x, r * y, r * z)
    return m3.Manifold.sphere(1.0, n).warp(wave)


def mesh_cheese(holes: int, segments: int):
    import manifold3d as m3

    import mitsuba_csg as csg
    from mitsuba_csg import scenes
    centres, radii = scenes.cheese_holes(holes)
    unit = csg.Mesh.from_manifold(m3.Manifold.sphere(1.0, segments))
    return csg.difference(csg.Box(2.0), *(unit.scale(float(r)).translate(c) for c, r in zip(centres, radii)))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--triangles", type=int, default=70000)
    parser.add_argument("--holes", type=int, default=500)
    parser.add_argument("--hole-segments", type=int, default=12)
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--name", default="mesh_leaves")
    args = common.parse_args(parser, argv)
    import mitsuba_csg as csg
    from mitsuba_csg import scenes
    from mitsuba_csg.formats.mesh_export import mesh_arrays
    width, height = (int(v) for v in args.size.split("x"))
    rows = []

    manifold = blob(args.triangles)
    lone = csg.Mesh.from_manifold(manifold)
    o, d = rays_for(lone, width, height)
    prepared = csg.prepare(lone)
    timing, info = measure(prepared, o, d, args.repeats)
    frozen, _ = measure(prepared, o, d, args.repeats, frozen=True)
    embree = embree_primary(mitsuba_mesh(*mesh_arrays(manifold)), o, d, args.repeats)
    rows.append(dict(scene=f"lone mesh ({len(lone.faces)} tris)", csg_s=timing["min_s"], embree_s=embree,
                     ratio=timing["min_s"] / embree, csg_frozen_s=frozen["min_s"],
                     frozen_ratio=frozen["min_s"] / embree, **info))
    print(f"  {rows[-1]['scene']} done", flush=True)

    analytic = scenes.cheese(args.holes)
    meshed = mesh_cheese(args.holes, args.hole_segments)
    o, d = rays_for(analytic, width, height)
    base = None
    for label, model in ((f"cheese-{args.holes}, sphere holes", analytic),
                         (f"cheese-{args.holes}, mesh holes ({args.hole_segments} segments)", meshed)):
        timing, info = measure(csg.prepare(model), o, d, args.repeats)
        base = base or timing["min_s"]
        rows.append(dict(scene=label, csg_s=timing["min_s"], vs_analytic=timing["min_s"] / base, **info))
        print(f"  {label} done", flush=True)
    columns = [("scene", "scene", "s"), ("csg_s", "CSG s/frame", ".3f"), ("embree_s", "Embree s/frame", ".3f"),
               ("ratio", "CSG/Embree", ".1f"), ("csg_frozen_s", "frozen s/frame", ".3f"),
               ("frozen_ratio", "frozen/Embree", ".1f"), ("vs_analytic", "vs sphere holes", ".2f"),
               ("mean_steps", "steps/ray", ".1f"), ("hit_fraction", "hit fraction", ".2f"),
               ("unfinished", "unfinished", "d")]
    print(f"{width}x{height} primary rays, {common.machine()['cpu']}, {common.machine()['variant']}")
    print(common.table(rows, columns))
    print(f"wrote {common.write(args.name, {'machine': common.machine(), 'args': vars(args), 'rows': rows})}")


if __name__ == "__main__":
    main()
