"""What each traversal mechanism of the automaton buys, alone and together (optimized trees).

    ./run.sh bench traversal_mechanisms.py [--scenes cheese-1000,city-3385] [--size 1280x720]
                                           [--variant cuda_ad_rgb]

Rows per scene: no mechanism (the plain Kensler automaton with input-order descent), each
mechanism alone, every mechanism but one, and all of them (the default), all measured in this
run on the same rays: mean steps per primary ray (automaton iterations plus the iterations of
set walks, each one node visited) and Mrays/s. Ratios are against the first row of the scene.
"""
from __future__ import annotations

import argparse

import common

# `compounds`, `neighbour_passes` and `cell_passes` work inside sets: without sets (alone) they
# change nothing.
MECHANISMS = ("restart_at_sibling", "skip_to_sibling", "bounded_search", "near_first", "sets", "pass_through",
              "compounds", "neighbour_passes", "cell_passes")


def configurations():
    yield "none", {m: False for m in MECHANISMS}
    for m in MECHANISMS:
        yield f"only {m}", {k: k == m for k in MECHANISMS}
    for m in MECHANISMS:
        yield f"all but {m}", {k: k != m for k in MECHANISMS}
    yield "all (default)", {m: True for m in MECHANISMS}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="cheese-1000,cheese-8000,city-3385,satellites-87.5k")
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--name", default="traversal_mechanisms")
    args = common.parse_args(parser, argv)
    import mitsuba_csg as csg
    from mitsuba_csg.engine.options import TraversalOptions
    from trace_throughput import measure, scenes_with_rays
    rows = []
    for scene, model, o, d, width, height in scenes_with_rays(args.scenes.split(","), args.size):
        opt, _ = csg.optimize(model)
        base = None
        for label, switches in configurations():
            prepared = csg.prepare(opt, traversal=TraversalOptions(**switches))
            timing, info = measure(prepared, o, d, args.repeats)
            row = dict(scene=scene, mechanisms=label, mrays_s=width * height / timing["min_s"] / 1e6,
                       **timing, **info)
            base = base or row
            row["steps_ratio"] = row["mean_steps"] / base["mean_steps"]
            row["speedup"] = base["min_s"] / row["min_s"]
            rows.append(row)
            print(f"  {scene:16s} {label:28s} {row['mean_steps']:8.1f} steps/ray  {row['mrays_s']:6.2f} Mrays/s",
                  flush=True)
    columns = [("scene", "scene", "s"), ("mechanisms", "mechanisms", "s"), ("mean_steps", "steps/ray", ".1f"),
               ("max_steps", "max steps", "d"), ("steps_ratio", "steps ratio", ".2f"), ("mrays_s", "Mrays/s", ".2f"),
               ("speedup", "speed-up", ".2f"), ("unfinished", "unfinished", "d")]
    print(f"{width}x{height} primary rays, optimized trees, {common.machine()['cpu']}, {common.machine()['variant']}")
    print(common.table(rows, columns))
    print(f"wrote {common.write(args.name, {'machine': common.machine(), 'size': [width, height], 'rows': rows})}")


if __name__ == "__main__":
    main()
