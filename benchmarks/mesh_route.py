"""mitsuba-csg versus the mesh route a user would take today, measured in one run:
manifold3d booleans -> Mitsuba scene build -> Embree primary rays, against
optimize + upload -> CSG primary rays, at 1280x720.

    ./run.sh bench mesh_route.py [--scenes cheese-500,cheese-1000,city-3385] [--segments 48]

`segments` is the circle subdivision of round primitives in the mesh (48: a sphere spanning
~100 pixels shows no facets at 1280x720 in a diffuse render; raise it for close-ups).
`--compose` meshes the children of a top-level union one by one and puts them side by side
instead of evaluating the union (`composed_mesh`): the Satellites' union Boolean ran out of
memory here, e.g. `--scenes satellites-87.5k --compose --no-path`.

Unless `--no-path`, it also renders one 1-spp frame of the same scene (the command line's
model scene: floor, sky, sun, max_depth 6, one diffuse BSDF) both ways: `csg_path` with the
CSG shape, and Mitsuba's own `path` with the mesh in its place.

CSG frames are timed twice: traced (each call builds the kernel in Python, then runs the
cached compiled kernel) and frozen (`trace_rays(frozen=True)`: the recorded kernels
replayed, as a render loop of fixed size would); Embree's Mitsuba call traces almost nothing.
The traced, frozen and Embree frames (and the csg_path and path frames) run in turn, round
after round (`common.alternating`): on a shared machine whose speed drifts over minutes, a
ratio of frames timed minutes apart drifted with it.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import common
from trace_throughput import primary_frame, scenes_with_rays


def mitsuba_mesh(verts, tris):
    """A Mitsuba mesh of vertex (N, 3) and triangle (M, 3) arrays."""
    import mitsuba as mi
    mesh = mi.Mesh("csg-mesh", len(verts), len(tris))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(verts, np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(tris, np.uint32).ravel())
    params.update()
    return mesh


def embree_frame(mesh, o, d, timings=None):
    """A function that traces Embree primary rays (t, normal, primitive) on a Mitsuba mesh;
    the seconds of the scene build (Embree's BVH) go into `timings["bvh_s"]`."""
    import drjit as dr
    import mitsuba as mi
    t0 = time.perf_counter()
    scene = mi.load_dict({"type": "scene", "mesh": mesh})
    dr.sync_thread()
    if timings is not None:
        timings["bvh_s"] = time.perf_counter() - t0
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(o[:, i].astype(np.float32)) for i in range(3))),
                   mi.Vector3f(*(mi.Float(d[:, i].astype(np.float32)) for i in range(3))))
    dr.eval(ray)

    def run():
        si = scene.ray_intersect(ray)
        dr.eval(si.t, si.n, si.prim_index)
        dr.sync_thread()
    return run


def embree_primary(mesh, o, d, repeats, timings=None) -> float:
    """Best seconds of Embree primary rays on a Mitsuba mesh (`embree_frame`)."""
    return common.best_of(embree_frame(mesh, o, d, timings), repeats)["min_s"]


def composed_mesh(model, segments):
    """(vertices, triangles) of a top-level union of separate objects without the union's
    Boolean: each child meshed on its own (its own Booleans), its arrays put side by side.
    Where children overlap the result keeps their inner faces, which a ray from outside the
    solid never meets first, so first hits match the union's. For scenes whose union Boolean
    does not fit in memory (the Satellites': OOM-killed at 24 GB here, and so was composing
    their 6250 manifolds with `Manifold.compose`)."""
    import mitsuba_csg as csg
    from mitsuba_csg.formats.mesh_export import mesh_arrays
    from mitsuba_csg.model.nodes import UNION, Operation
    if not (isinstance(model, Operation) and model.kind == UNION):
        return mesh_arrays(csg.to_mesh(model, segments=segments))
    verts, tris, offset = [], [], 0
    for child in model.children:
        v, f = mesh_arrays(csg.to_mesh(child, segments=segments))
        verts.append((v @ model.matrix[:3, :3].T + model.matrix[:3, 3]).astype(np.float32))
        tris.append((f + offset).astype(np.uint32))
        offset += len(v)
    return np.concatenate(verts), np.concatenate(tris)


def mesh_route(model, o, d, segments, compose=False):
    """(Mitsuba mesh, its row: triangles and set-up seconds, a function tracing its Embree
    primary-ray frame)."""
    import mitsuba_csg as csg
    from mitsuba_csg.formats.mesh_export import mesh_arrays
    t0 = time.perf_counter()
    verts, tris = composed_mesh(model, segments) if compose else mesh_arrays(csg.to_mesh(model, segments=segments))
    boolean_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    mesh = mitsuba_mesh(verts, tris)
    build_s = time.perf_counter() - t0
    timings = {}
    embree = embree_frame(mesh, o, d, timings)
    # The scene build: the Mitsuba mesh and Embree's BVH over it.
    return mesh, dict(triangles=len(tris), boolean_s=boolean_s, scene_build_s=build_s + timings["bvh_s"]), embree


def path_frames(model, mesh, width, height, repeats, directory) -> dict:
    """Seconds of a 1-spp frame: csg_path on the CSG shape and Mitsuba's path on its mesh."""
    import drjit as dr
    import mitsuba as mi

    import mitsuba_csg as csg
    from mitsuba_csg.scene_setup import model_scene_dict
    csg_dict = model_scene_dict(mi, csg, model, width, height, 1, "csg_path")
    mesh_dict = model_scene_dict(mi, csg, model, width, height, 1, "path")
    ply = str(directory / "mesh.ply")
    mesh.write_ply(ply)
    mesh_dict["model"] = {"type": "ply", "filename": ply, "bsdf": mesh_dict["model"]["bsdf"]}
    def frame(scene_dict):
        scene = mi.load_dict(scene_dict)

        def run():
            dr.eval(mi.render(scene, spp=1))
            dr.sync_thread()
        return run
    times = common.alternating({"csg_path_s": frame(csg_dict), "mesh_path_s": frame(mesh_dict)}, repeats)
    out = {key: timing["min_s"] for key, timing in times.items()}
    out["path_ratio"] = out["csg_path_s"] / out["mesh_path_s"]
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="cheese-500,cheese-1000,cheese-8000,city-3385,city-343k")
    parser.add_argument("--segments", type=int, default=48)
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-path", action="store_true", help="skip the csg_path / path frames")
    parser.add_argument("--compose", action="store_true",
                        help="mesh a top-level union's children one by one and compose them (no union Boolean)")
    parser.add_argument("--name", default="mesh_route")
    args = common.parse_args(parser, argv)
    import mitsuba_csg as csg
    rows = []
    for scene, model, o, d, width, height in scenes_with_rays(args.scenes.split(","), args.size):
        t0 = time.perf_counter()
        prepared = csg.prepare(model)
        prepare_s = time.perf_counter() - t0
        mesh, mesh_row, embree = mesh_route(model, o, d, args.segments, args.compose)
        # The three frames in turn, round after round: their ratios do not drift with the machine.
        times = common.alternating({"traced": primary_frame(prepared, o, d), "frozen": primary_frame(
            prepared, o, d, frozen=True), "embree": embree}, args.repeats)
        row = dict(scene=scene, primitives=prepared.flat.num_prims, csg_prepare_s=prepare_s,
                   csg_trace_s=times["traced"]["min_s"], csg_mrays_s=width * height / times["traced"]["min_s"] / 1e6,
                   csg_frozen_s=times["frozen"]["min_s"], embree_s=times["embree"]["min_s"])
        mesh_row["composed"] = args.compose
        row.update(mesh_row)
        if not args.no_path:
            with tempfile.TemporaryDirectory() as directory:
                row.update(path_frames(model, mesh, width, height, args.repeats, Path(directory)))
        row["embree_mrays_s"] = width * height / row["embree_s"] / 1e6
        row["csg_first_frame_s"] = row["csg_prepare_s"] + row["csg_trace_s"]
        row["mesh_first_frame_s"] = row["boolean_s"] + row["scene_build_s"] + row["embree_s"]
        row["trace_ratio"] = row["csg_trace_s"] / row["embree_s"]
        row["frozen_ratio"] = row["csg_frozen_s"] / row["embree_s"]
        rows.append(row)
        # Written after every scene: a later scene's booleans may exhaust the memory (the
        # Satellites' did here) and take the process with them.
        path = common.write(args.name, {'machine': common.machine(), 'args': vars(args), 'rows': rows})
        print(f"  {scene} done", flush=True)
    columns = [("scene", "scene", "s"), ("primitives", "prims", "d"), ("triangles", "mesh tris", "d"),
               ("boolean_s", "booleans s", ".2f"), ("scene_build_s", "build s", ".2f"),
               ("embree_s", "Embree s", ".3f"), ("csg_prepare_s", "optimize s", ".2f"), ("csg_trace_s", "CSG s", ".3f"),
               ("trace_ratio", "CSG/Embree", ".1f"), ("csg_frozen_s", "frozen s", ".3f"),
               ("frozen_ratio", "frozen/Embree", ".1f"), ("mesh_first_frame_s", "mesh 1st frame s", ".2f"),
               ("csg_first_frame_s", "CSG 1st frame s", ".2f"), ("mesh_path_s", "path s", ".2f"),
               ("csg_path_s", "csg_path s", ".2f"), ("path_ratio", "csg_path/path", ".1f")]
    print(f"{width}x{height} primary rays, segments={args.segments}")
    print(common.table(rows, columns))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
