"""Where a `csg_path` frame's time goes, by path depth: `csg_path` on the CSG shape against
Mitsuba's `path` on its manifold3d mesh, and both again on a bare stand-in (a box of the
model's bounds), measured in one run.

    ./run.sh bench path_depths.py [--scenes cheese-1000,city-3385] [--depths 1,2,3,6]
                                  [--size 1280x720] [--variant cuda_ad_rgb]

The scene is mesh_route.py's (`scene_setup.model_scene_dict`: floor, sky, sun, one diffuse
BSDF), one sample per pixel, with `max_depth` set per row. The stand-in scene costs each
integrator what it spends besides tracing the model (camera, floor, emitters, BSDFs, paths
that leave), so `csg_path - csg_path on the box` is what the CSG traversal adds at that depth,
and `path - path on the box` what Embree's traversal of the model's mesh adds: their ratio
(`traversal ratio`) is the kernel's cost against Embree's on the rays a path tracer really
traces (camera, shadow and bounce rays, many of them starting on the model).
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import common


def frame_seconds(scene_dict, repeats) -> float:
    import drjit as dr
    import mitsuba as mi
    scene = mi.load_dict(scene_dict)

    def run():
        dr.eval(mi.render(scene, spp=1))
        dr.sync_thread()
    run()          # compiles the kernel: not timed
    return common.best_of(run, repeats)["min_s"]


def scene_pair(model, mesh_file, width, height, depth):
    """(csg_path scene dict, path scene dict with the mesh in the model's place)."""
    import mitsuba as mi

    import mitsuba_csg as csg
    from mitsuba_csg.scene_setup import model_scene_dict
    csg_dict = model_scene_dict(mi, csg, model, width, height, 1, "csg_path")
    mesh_dict = model_scene_dict(mi, csg, model, width, height, 1, "path")
    mesh_dict["model"] = {"type": "ply", "filename": mesh_file, "bsdf": mesh_dict["model"]["bsdf"]}
    for scene_dict in (csg_dict, mesh_dict):
        scene_dict["integrator"]["max_depth"] = depth
    return csg_dict, mesh_dict


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="cheese-1000,city-3385")
    parser.add_argument("--depths", default="1,2,3,6")
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--segments", type=int, default=48)
    parser.add_argument("--name", default="path_depths")
    args = common.parse_args(parser, argv)
    import numpy as np

    import mitsuba_csg as csg
    from mesh_route import composed_mesh, mitsuba_mesh
    from mitsuba_csg import scenes
    width, height = (int(v) for v in args.size.split("x"))
    depths = [int(v) for v in args.depths.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as directory:
        for name in args.scenes.split(","):
            model = scenes.named(name)
            lo, hi = (np.asarray(v, np.float64) for v in model.bounds())
            bare = csg.Box(tuple((hi - lo).tolist())).translate(tuple((0.5 * (lo + hi)).tolist()))
            files = {}
            for key, solid in (("model", model), ("bare", bare)):
                files[key] = str(Path(directory) / f"{name}-{key}.ply")
                mitsuba_mesh(*composed_mesh(solid, args.segments)).write_ply(files[key])
            for depth in depths:
                row = dict(scene=name, max_depth=depth)
                for key, solid in (("model", model), ("bare", bare)):
                    csg_dict, mesh_dict = scene_pair(solid, files[key], width, height, depth)
                    suffix = "" if key == "model" else "_bare"
                    row["csg_path_s" + suffix] = frame_seconds(csg_dict, args.repeats)
                    row["path_s" + suffix] = frame_seconds(mesh_dict, args.repeats)
                row["ratio"] = row["csg_path_s"] / row["path_s"]
                row["csg_traversal_s"] = row["csg_path_s"] - row["csg_path_s_bare"]
                row["embree_traversal_s"] = row["path_s"] - row["path_s_bare"]
                row["traversal_ratio"] = (row["csg_traversal_s"] / row["embree_traversal_s"]
                                          if row["embree_traversal_s"] > 0 else float("nan"))
                rows.append(row)
                print(f"  {name} max_depth {depth}: csg_path {row['csg_path_s']:.3f} s, path {row['path_s']:.3f} s",
                      flush=True)
    columns = [("scene", "scene", "s"), ("max_depth", "max_depth", "d"), ("csg_path_s", "csg_path s", ".3f"),
               ("path_s", "path s", ".3f"), ("ratio", "csg_path/path", ".2f"),
               ("csg_path_s_bare", "csg_path box s", ".3f"), ("path_s_bare", "path box s", ".3f"),
               ("csg_traversal_s", "CSG traversal s", ".3f"), ("embree_traversal_s", "Embree traversal s", ".3f"),
               ("traversal_ratio", "traversal ratio", ".1f")]
    print(f"{args.size}, 1 spp, {common.machine()['cpu']}, {common.machine()['variant']}")
    print(common.table(rows, columns))
    print(f"wrote {common.write(args.name, {'machine': common.machine(), 'args': vars(args), 'rows': rows})}")


if __name__ == "__main__":
    main()
