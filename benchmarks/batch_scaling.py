"""Batch rendering: speed-up with Ray workers, and what a chunk costs beyond its samples.

    ./run.sh bench batch_scaling.py [--scene cheese-500] [--jobs 4] [--size 320x180] [--spp 32] [--chunk-spp 8]

One batch (a turntable of `--jobs` frames of a built-in scene through csg_path) rendered in
one run by each way of running it:
  in-process            this process, Dr.Jit on all cores
  ray 1 x N threads     one Ray worker using all N cores
  ray W x 1 thread      W Ray workers of one thread each (W = 1, then the core count)
Wall time is the whole `batch.run` call; for Ray it includes starting the local cluster,
which a long batch pays once. Each variant renders into a fresh folder (nothing resumed).

Per-chunk overhead: the same frames rendered as few large chunks and as many 1-spp chunks,
in-process and on Ray workers; (time with many - time with few) / (chunks added).
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import common


def timed_batch(jobs, **options) -> dict:
    from mitsuba_csg import batch
    t0 = time.perf_counter()
    summary = batch.run(jobs, progress=False, **options)
    wall = time.perf_counter() - t0
    failed = [r.error for r in summary.results if r.status != "done"]
    if failed:
        raise RuntimeError(f"batch failed: {failed}")
    chunks = sum(r.chunks_rendered for r in summary.results)
    return {"wall_s": wall, "chunks": chunks, "worker_s": sum(r.seconds for r in summary.results),
            "backend": summary.backend, "workers": summary.workers}


def frames(folder: Path, scene: str, count: int, size: str, spp: int, chunk_spp: int):
    from mitsuba_csg import batch
    return batch.parse_jobs({"jobs": [{"input": scene, "output": str(folder / "frame.exr"), "size": size, "spp": spp,
                                       "chunk_spp": chunk_spp, "png": False}]}, folder, "bench", frames=count)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="cheese-500")
    parser.add_argument("--jobs", type=int, default=4)
    parser.add_argument("--size", default="320x180")
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--chunk-spp", type=int, default=8)
    parser.add_argument("--overhead-spp", type=int, default=16, help="samples per frame of the overhead runs")
    args = common.parse_args(parser, argv)
    import mitsuba_csg  # noqa: F401  (selects the variant, registers the plugins)
    from mitsuba_csg.batch import ray_available

    cores = os.cpu_count() or 1
    width, height = (int(v) for v in args.size.split("x"))
    rays = args.jobs * width * height * args.spp
    root = Path(tempfile.mkdtemp(prefix="batch_bench_"))
    variants = [("in-process", {"use_ray": False})]
    if ray_available():
        variants += [(f"ray 1 x {cores} threads", {"use_ray": True, "workers": 1, "threads": cores}),
                     ("ray 1 x 1 thread", {"use_ray": True, "workers": 1, "threads": 1})]
        if cores > 1:
            variants.append((f"ray {cores} x 1 thread", {"use_ray": True, "workers": cores, "threads": 1}))
    rows = []
    try:
        # Warm-up: compile the kernels once (Dr.Jit's on-disk cache serves every process after).
        timed_batch(frames(root / "warm", args.scene, 1, "32x18", 1, 1), use_ray=False)
        for k, (name, options) in enumerate(variants):
            result = timed_batch(frames(root / f"v{k}", args.scene, args.jobs, args.size, args.spp, args.chunk_spp),
                                 **options)
            rows.append({"variant": name, **result, "mrays_s": rays / result["wall_s"] / 1e6})
        base = rows[0]["wall_s"]
        for row in rows:
            row["speedup"] = base / row["wall_s"]
        one = next((r for r in rows if r["variant"] == "ray 1 x 1 thread"), None)
        for row in rows:
            row["speedup_vs_1_worker"] = one["wall_s"] / row["wall_s"] if one else None

        overhead = []
        runs = [("in-process", {"use_ray": False})]
        if ray_available():
            runs.append((f"ray {cores} x 1 thread", {"use_ray": True, "workers": cores, "threads": 1}))
        for name, options in runs:
            few = timed_batch(frames(root / f"few_{len(overhead)}", args.scene, args.jobs, args.size,
                                     args.overhead_spp, args.overhead_spp), **options)
            many = timed_batch(frames(root / f"many_{len(overhead)}", args.scene, args.jobs, args.size,
                                      args.overhead_spp, 1), **options)
            added = many["chunks"] - few["chunks"]
            overhead.append({"variant": name, "few_chunks": few["chunks"], "few_s": few["wall_s"],
                             "many_chunks": many["chunks"], "many_s": many["wall_s"],
                             "per_chunk_ms": 1e3 * (many["wall_s"] - few["wall_s"]) / added})
    finally:
        shutil.rmtree(root, ignore_errors=True)

    print(f"{args.jobs} frames of {args.scene} at {args.size}, {args.spp} spp in chunks of {args.chunk_spp} "
          f"({rays / 1e6:.1f} M camera rays), {cores} cores")
    print(common.table(rows, [("variant", "variant", "s"), ("chunks", "chunks", "d"), ("wall_s", "wall s", ".2f"),
                              ("worker_s", "worker s", ".2f"), ("mrays_s", "Mrays/s", ".3f"),
                              ("speedup", "vs in-process", ".2f"), ("speedup_vs_1_worker", "vs 1 worker", ".2f")]))
    print()
    print(f"Per-chunk overhead ({args.overhead_spp} spp per frame: one chunk per frame, then 1-spp chunks)")
    print(common.table(overhead, [("variant", "variant", "s"), ("few_chunks", "chunks", "d"), ("few_s", "s", ".2f"),
                                  ("many_chunks", "chunks", "d"), ("many_s", "s", ".2f"),
                                  ("per_chunk_ms", "ms per chunk", ".1f")]))
    path = common.write("batch_scaling", {"machine": common.machine(), "scene": args.scene, "jobs": args.jobs,
                                          "size": args.size, "spp": args.spp, "chunk_spp": args.chunk_spp,
                                          "rows": rows, "overhead": overhead})
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
