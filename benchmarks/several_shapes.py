"""A scene of several csg shapes: one traversal of their group against one traversal per shape.

    ./run.sh bench several_shapes.py [--counts 4,16,64] [--holes 60] [--size 1280x720]

The scene is a grid of `count` small Cheeses (each a cube minus `holes` spheres), framed by
the benchmark camera. Primary rays at SIZE, all measured in this run:
- per shape: one traversal per shape, each up to the nearest hit so far (what the csg_*
  integrators did before shapes were grouped),
- grouped: one traversal of the shapes' group (`engine.grouping`: GROUP nodes over the shapes'
  roots; what the integrators do now),
- one union: the same geometry as a single optimized model (one shape),
and a 1-spp `csg_path` frame (floor, sky, sun) of the grid as `count` shapes and as one shape,
with Mitsuba's `path` on the manifold3d mesh of the union as the mesh route.
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

import common
from trace_throughput import rays_for


def grid_of_cheeses(count: int, holes: int):
    from mitsuba_csg.scenes import cheese
    side = int(np.ceil(np.sqrt(count)))
    return [cheese(holes, seed=k).translate((2.6 * (k % side), 2.6 * (k // side), 0.0)) for k in range(count)]


def kernel_frames(solids, o, d, repeats) -> dict:
    """Best seconds and mean steps per ray of the three ways to trace the primary rays."""
    import drjit as dr

    import mitsuba_csg as csg
    from mitsuba_csg.engine.grouping import group_trees
    from mitsuba_csg.queries import rays_to_device, trace_rays
    shapes = [csg.prepare(s) for s in solids]
    grouped = csg.prepare(group_trees([p.flat for p in shapes]).flat)
    union = csg.prepare(csg.union(*solids))
    b = grouped.tree.b
    O, D = rays_to_device(o, b), rays_to_device(d, b)
    dr.eval(O, D)
    out, steps = {}, {}

    def per_shape():
        t = dr.full(b.Float, dr.inf, dr.width(O.x))
        total = dr.zeros(b.UInt32, dr.width(O.x))
        for prepared in shapes:
            h = trace_rays(prepared, O, D, 0.0, t)
            t = dr.minimum(t, h.t)
            total += h.steps
            dr.eval(t, total, h.normal, h.prim)     # as the integrators' selects would
        dr.sync_thread()
        steps["per_shape"] = total

    def single(prepared, key):
        def run():
            h = trace_rays(prepared, O, D)
            dr.eval(h.t, h.normal, h.prim, h.steps)
            dr.sync_thread()
            steps[key] = h.steps
        return run

    for key, run in (("per_shape", per_shape), ("grouped", single(grouped, "grouped")),
                     ("union", single(union, "union"))):
        out[f"{key}_s"] = common.best_of(run, repeats)["min_s"]
        out[f"{key}_steps"] = float(np.asarray(steps[key]).mean())
    out["per_shape_over_grouped"] = out["per_shape_s"] / out["grouped_s"]
    out["grouped_over_union"] = out["grouped_s"] / out["union_s"]
    return out


def path_frames(solids, width, height, repeats, directory: Path) -> dict:
    """Seconds of a 1-spp csg_path frame with the solids as separate shapes and as one, and
    of Mitsuba's path on the mesh of their union."""
    import drjit as dr
    import mitsuba as mi

    import mitsuba_csg as csg
    from mitsuba_csg.formats.mesh_export import save_mesh
    from mitsuba_csg.scene_setup import scene_dict
    colour = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.6, 0.2]}}
    union = csg.union(*solids)
    separate = scene_dict(mi, csg, [(s, {}, colour) for s in solids], width, height, 1, "csg_path")
    one = scene_dict(mi, csg, [(union, {}, colour)], width, height, 1, "csg_path")
    mesh = scene_dict(mi, csg, [(union, {}, colour)], width, height, 1, "path")
    ply = directory / "union.ply"
    save_mesh(csg.to_mesh(union, segments=48), ply)
    mesh["model"] = {"type": "ply", "filename": str(ply), "bsdf": colour}
    out = {}
    for key, d in (("csg_path_shapes_s", separate), ("csg_path_union_s", one), ("mesh_path_s", mesh)):
        scene = mi.load_dict(d)

        def run():
            dr.eval(mi.render(scene, spp=1))
            dr.sync_thread()
        out[key] = common.best_of(run, repeats)["min_s"]
    out["shapes_over_union"] = out["csg_path_shapes_s"] / out["csg_path_union_s"]
    out["shapes_over_mesh"] = out["csg_path_shapes_s"] / out["mesh_path_s"]
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--counts", default="4,16,64", help="comma-separated numbers of shapes")
    parser.add_argument("--holes", type=int, default=60, help="holes per Cheese")
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-path", action="store_true", help="skip the csg_path frames")
    args = common.parse_args(parser, argv)
    import mitsuba_csg as csg
    width, height = (int(v) for v in args.size.split("x"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for count in (int(c) for c in args.counts.split(",")):
            solids = grid_of_cheeses(count, args.holes)
            o, d = rays_for(csg.union(*solids), width, height)
            row = {"shapes": count, "holes": args.holes, **kernel_frames(solids, o, d, args.repeats)}
            if not args.no_path:
                row.update(path_frames(solids, width, height, args.repeats, Path(tmp)))
            for key in ("per_shape_s", "grouped_s", "union_s"):
                row[key[:-2] + "_ms"] = 1e3 * row[key]
            rows.append(row)
            print(f"{count} shapes done", flush=True)
    columns = [("shapes", "shapes", "d"), ("per_shape_ms", "per shape ms", ".1f"), ("grouped_ms", "grouped ms", ".1f"),
               ("union_ms", "one union ms", ".1f"), ("per_shape_over_grouped", "per shape/grouped", ".2f"),
               ("per_shape_steps", "steps per shape", ".1f"), ("grouped_steps", "steps grouped", ".1f"),
               ("union_steps", "steps union", ".1f"), ("csg_path_shapes_s", "csg_path shapes s", ".3f"),
               ("csg_path_union_s", "csg_path union s", ".3f"), ("mesh_path_s", "path mesh s", ".3f")]
    print(f"Primary rays at {args.size} (kernel) and 1-spp frames; {args.holes} holes per Cheese")
    print(common.table(rows, columns))
    path = common.write("several_shapes", {"machine": common.machine(), "size": args.size, "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
