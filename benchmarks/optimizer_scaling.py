"""Optimizer time, tree heights and node counts for Cities of 10k / 100k / 1M primitives,
and a 1280x720 trace of each (the 1M City traces as one tree).

    ./run.sh bench optimizer_scaling.py [--sizes 10000,100000,1000000] [--size 1280x720]
"""
from __future__ import annotations

import argparse
import resource
import time

import common


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="10000,100000,1000000")
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--no-trace", action="store_true")
    parser.add_argument("--name", default="optimizer_scaling")
    args = parser.parse_args(argv)
    import drjit as dr

    import mitsuba_csg as csg
    from mitsuba_csg.scenes import city
    from mitsuba_csg.queries import rays_to_device, trace_rays
    from trace_throughput import rays_for
    width, height = (int(v) for v in args.size.split("x"))
    rows = []
    for n in (int(v) for v in args.sizes.split(",")):
        t0 = time.perf_counter()
        model = city(max(1, n // 10))
        build_s = time.perf_counter() - t0
        opt, stats = csg.optimize(model)
        row = dict(primitives=stats["primitives"], build_model_s=build_s, optimize_s=stats["seconds_total"],
                   height_input=stats["height_input"], height_before=stats["height_before"],
                   height_after=stats["height_after"], nodes_before=stats["nodes_before"],
                   nodes_after=stats["nodes_after"], leaves_duplicated=stats["leaves_duplicated"],
                   phases=stats["seconds"])
        if not args.no_trace:
            prepared = csg.prepare(opt)
            o, d = rays_for(model, width, height)
            O, D = rays_to_device(o, prepared.tree.b), rays_to_device(d, prepared.tree.b)
            dr.eval(O, D)

            def run():
                h = trace_rays(prepared, O, D)
                dr.eval(h.t, h.normal, h.prim, h.finished)
                dr.sync_thread()
            timing = common.best_of(run, 2)
            row.update(trace_s=timing["min_s"], mrays_s=width * height / timing["min_s"] / 1e6)
        row["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
        rows.append(row)
        print(f"  {n}: optimize {row['optimize_s']:.1f} s  phases "
              + ", ".join(f"{k} {v:.2f}" for k, v in stats["seconds"].items()), flush=True)
    columns = [("primitives", "prims", "d"), ("build_model_s", "build s", ".1f"), ("optimize_s", "optimize s", ".1f"),
               ("height_input", "h input", "d"), ("height_before", "h before", "d"), ("height_after", "h after", "d"),
               ("nodes_before", "nodes before", "d"), ("nodes_after", "nodes after", "d"),
               ("leaves_duplicated", "dup", "d"), ("mrays_s", "Mrays/s", ".2f"), ("peak_rss_gb", "peak RSS GB", ".1f")]
    print(common.table(rows, columns))
    print(f"wrote {common.write(args.name, {'machine': common.machine(), 'rows': rows})}")


if __name__ == "__main__":
    main()
