"""Primary-ray throughput of `trace` at 1280x720: Mrays/s, automaton steps, compile time.

    ./run.sh bench trace_throughput.py [--scenes cheese-1000,city-3385] [--size 1280x720]

For each scene: the unoptimized tree ('-': input chains balanced in input order) and the
optimized one ('+'), both measured in this run; their ratio is the optimizer's speed-up.
Kernel compile time is measured cold in a fresh process with an empty Dr.Jit kernel cache.
Cheese scenes also report their solid fraction and the holes a ray crosses before its hit
(`cheese_statistics`).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

import cheese_statistics
import common

# An unoptimized frame slower than this (estimated from a small frame) is reported as N/A.
SLOW_FRAME_S = 60.0


def scenes_with_rays(names, size):
    """(name, model, origins, directions, width, height) per named scene, with the benchmark
    camera at `size` ("WIDTHxHEIGHT")."""
    from mitsuba_csg import scenes
    width, height = (int(v) for v in size.split("x"))
    for name in names:
        model = scenes.named(name)
        yield (name, model, *rays_for(model, width, height), width, height)


def rays_for(model, width, height):
    """The benchmark camera's rays, in `common.ray_order` (4x4 tiles unless --ray-order rows)."""
    from mitsuba_csg.camera import framing, look_at_rays, tile_order
    lo, hi = model.bounds()
    origin, target = framing(lo, hi, 40.0, width / height)
    o, d = look_at_rays(origin, target, fov_degrees=40.0, width=width, height=height)
    if common.ray_order == "tiles":
        perm = tile_order(width, height)
        o, d = o[perm], d[perm]
    return o, d


def primary_frame(prepared, o, d, frozen=False, reorder=False, hits=None, start_prim=None):
    """A function that traces one primary-ray frame (hits, normals, steps) of rays o, d
    (numpy): `frozen` replays the recorded kernels (trace_rays(frozen=True)) instead of
    tracing them, `reorder` sorts the rays first (trace_rays(reorder=True)), `start_prim`
    (numpy, per ray) passes trace_rays the primitive each ray starts on. Each run's RayHits
    go into `hits["h"]` when a dict is given."""
    import drjit as dr

    from mitsuba_csg.queries import rays_to_device, trace_rays
    b = prepared.tree.b
    O, D = rays_to_device(o, b), rays_to_device(d, b)
    start = None if start_prim is None else b.UInt32(np.asarray(start_prim, np.uint32))
    dr.eval(O, D, start)
    out = {} if hits is None else hits

    def run():
        h = trace_rays(prepared, O, D, frozen=frozen, reorder=reorder, start_prim=start)
        dr.eval(h.t, h.normal, h.prim, h.steps, h.finished)
        dr.sync_thread()
        out["h"] = h
    return run


def measure(prepared, o, d, repeats, frozen=False, reorder=False, hits=None, start_prim=None):
    """Best seconds of a primary-ray frame (`primary_frame`) and its statistics. The last
    run's RayHits go into `hits["h"]` when a dict is given."""
    out = {} if hits is None else hits
    timing = common.best_of(primary_frame(prepared, o, d, frozen, reorder, out, start_prim), repeats)
    h = out["h"]
    steps = h.steps.numpy()
    return timing, {"mean_steps": float(steps.mean()), "max_steps": int(steps.max()),
                    "hit_fraction": float(np.isfinite(h.t.numpy()).mean()),
                    "unfinished": int((~h.finished.numpy()).sum())}


def path_frame(model, width, height, repeats) -> float:
    """Seconds of a full csg_path frame at 1 spp (floor, sky and sun; warm kernels)."""
    import drjit as dr
    import mitsuba as mi

    import mitsuba_csg as csg
    from mitsuba_csg.scene_setup import model_scene_dict
    scene = mi.load_dict(model_scene_dict(mi, csg, model, width, height, 1, "csg_path"))

    def run():
        image = mi.render(scene, spp=1)
        dr.eval(image)
        dr.sync_thread()
    return common.best_of(run, repeats)["min_s"]


def cold_compile(scene: str, size: str, variant: str | None = None) -> dict:
    """First trace in a fresh process with an empty Dr.Jit kernel cache, then with a warm one.

    Reports the LLVM compile time of the traversal kernel from Dr.Jit's kernel history,
    and the wall time of the first trace (Python tracing of the kernel included).
    """
    code = ("import sys; sys.path.insert(0, {root!r}); sys.path.insert(0, {bench!r});"
            "import common; common.select_variant({variant!r});"
            "import trace_throughput as tt; tt._first_trace({scene!r}, {size!r})")
    code = code.format(root=str(common.ROOT), bench=str(common.ROOT / "benchmarks"), scene=scene, size=size,
                       variant=variant)
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, DRJIT_CACHE_DIR=cache)
        for label in ("cold", "warm_cache"):
            run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
            wall, compile_ms, ops = run.stdout.split()[-3:]
            out[f"first_trace_{label}_s"] = float(wall)
            out[f"kernel_compile_{label}_s"] = float(compile_ms) / 1e3
            out["kernel_ops"] = int(ops)
    out["compile_s"] = out["kernel_compile_cold_s"]
    return out


def _first_trace(scene: str, size: str) -> None:
    import drjit as dr

    import mitsuba_csg as csg
    from mitsuba_csg import scenes
    from mitsuba_csg.queries import rays_to_device, trace_rays
    width, height = (int(v) for v in size.split("x"))
    model = scenes.named(scene)
    prepared = csg.prepare(model)
    o, d = rays_for(model, width, height)
    O, D = rays_to_device(o, prepared.tree.b), rays_to_device(d, prepared.tree.b)
    dr.eval(O, D)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    t0 = time.perf_counter()
    h = trace_rays(prepared, O, D)
    dr.eval(h.t, h.normal, h.prim, h.steps, h.finished)
    dr.sync_thread()
    wall = time.perf_counter() - t0
    kernels = [k for k in dr.kernel_history() if "backend_time" in k]
    biggest = max(kernels, key=lambda k: k["operation_count"])
    compile_ms = sum(k["codegen_time"] + k["backend_time"] for k in kernels)
    print(wall, compile_ms, biggest["operation_count"])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="cheese-1000,city-3385", help="comma-separated, or 'paper' for Table 2")
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-compile", action="store_true", help="skip the cold-compile measurement")
    parser.add_argument("--no-path", action="store_true", help="skip the csg_path frame")
    parser.add_argument("--name", default="trace_throughput")
    args = common.parse_args(parser, argv)
    import mitsuba_csg as csg
    from mitsuba_csg import scenes
    rows = []
    names = list(scenes.PAPER_TABLE_2) if args.scenes == "paper" else args.scenes.split(",")
    for scene, model, o, d, width, height in scenes_with_rays(names, args.size):
        results = {}
        for label, optimize in (("-", False), ("+", True)):
            t0 = time.perf_counter()
            prepared = csg.prepare(model, optimize=optimize)
            prep_s = time.perf_counter() - t0
            # Estimate from a 1/16 frame first; skip hopeless frames as the paper's N/A.
            so, sd = rays_for(model, width // 4, height // 4)
            probe, _ = measure(prepared, so, sd, 1)
            if probe["min_s"] * 16 > SLOW_FRAME_S:
                rows.append(dict(scene=scene, tree=label, primitives=prepared.flat.num_prims,
                                 depth=prepared.flat.height, prepare_s=prep_s, note="N/A (> 60 s/frame)"))
                results[label] = rows[-1]
                continue
            timing, info = measure(prepared, o, d, args.repeats)
            n = width * height
            results[label] = dict(scene=scene, tree=label, primitives=prepared.flat.num_prims,
                                  depth=prepared.flat.height, prepare_s=prep_s,
                                  mrays_s=n / timing["min_s"] / 1e6, fps=1.0 / timing["min_s"],
                                  median_mrays_s=n / timing["median_s"] / 1e6, **timing, **info)
            rows.append(results[label])
        results["+"].update(cheese_statistics.statistics(scene, prepared, o, d))   # the optimized tree
        if "min_s" in results["-"] and "min_s" in results["+"]:
            results["+"]["speedup"] = results["-"]["min_s"] / results["+"]["min_s"]
        if not args.no_path:
            results["+"]["path_1spp_s"] = path_frame(model, width, height, max(1, args.repeats - 1))
        print(f"  {scene}: - {results['-'].get('mrays_s', 0):.2f}  + {results['+'].get('mrays_s', 0):.2f} Mrays/s",
              flush=True)
        if not args.no_compile:
            results["+"].update(cold_compile(scene, args.size, args.variant))
    columns = [("scene", "scene", "s"), ("tree", "tree", "s"), ("primitives", "prims", "d"), ("depth", "depth", "d"),
               ("fps", "fps", ".2f"), ("mrays_s", "Mrays/s", ".2f"), ("median_mrays_s", "median", ".2f"),
               ("mean_steps", "steps/ray", ".1f"), ("max_steps", "max steps", "d"),
               ("solid_fraction", "solid", ".3f"), ("holes_crossed", "holes/ray", ".1f"), ("speedup", "+/-", ".1f"),
               ("path_1spp_s", "path 1spp s", ".2f"), ("compile_s", "compile s", ".2f"), ("first_trace_cold_s", "1st trace s", ".2f"),
               ("unfinished", "unfinished", "d"), ("note", "note", "s")]
    print(f"{width}x{height} primary rays, {common.machine()['cpu']}, {os.cpu_count()} cores")
    print(common.table(rows, columns))
    path = common.write(args.name, {"machine": common.machine(), "size": [width, height], "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
