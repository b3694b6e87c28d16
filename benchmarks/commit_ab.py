"""Primary-ray frame time of this tree against another commit, in alternating processes.

    ./run.sh bench commit_ab.py --base 6227cd1 [--scenes city-3385,cheese-1000] [--rounds 4]
                                [--size 1280x720] [--repeats 15]

A change that must not slow the kernel (a refactor checked bit for bit) is timed against the
commit before it: the base commit is checked out in a temporary git worktree, and each round
runs one process of the base and one of this tree, each preparing the scenes and timing the
best of `repeats` frames (`trace_throughput.primary_frame`). Alternating processes, not two
runs minutes apart: this machine's speed drifts by 10-20 % over minutes. Prints the best and
median frame of each side per scene and writes JSON; mean steps per ray must agree.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import common

# One side's measurement, run in a fresh process with that side's tree first on sys.path.
_CHILD = """
import json, sys, time
root = sys.argv[1]
sys.path[:0] = [root, root + "/benchmarks"]
import common
common.select_variant({variant!r})
import mitsuba_csg as csg
from mitsuba_csg import scenes
from trace_throughput import primary_frame, rays_for
out = {{}}
width, height = {size}
for name in {scenes!r}:
    model = scenes.named(name)
    prepared = csg.prepare(model)
    o, d = rays_for(model, width, height)
    hits = {{}}
    run = primary_frame(prepared, o, d, hits=hits)
    run(); run()
    times = []
    for _ in range({repeats}):
        t = time.perf_counter(); run(); times.append(time.perf_counter() - t)
    out[name] = dict(best_s=min(times), steps=float(hits["h"].steps.numpy().mean()))
print(json.dumps(out))
"""


def run_side(root: Path, args, scenes) -> dict:
    size = tuple(int(v) for v in args.size.split("x"))
    code = _CHILD.format(variant=args.variant, size=size, scenes=scenes, repeats=args.repeats)
    env = dict(os.environ, PYTHONPATH=str(root))
    done = subprocess.run([sys.executable, "-c", code, str(root)], env=env, capture_output=True, text=True,
                          check=True, cwd=tempfile.gettempdir())
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", required=True, help="the commit to compare with (any git revision)")
    parser.add_argument("--scenes", default="city-3385,cheese-1000,satellites-87.5k")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--name", default="commit_ab")
    args = common.parse_args(parser, argv)
    scenes = args.scenes.split(",")
    here = common.ROOT
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base"
        subprocess.run(["git", "-C", str(here), "worktree", "add", "--detach", "-f", str(base), args.base],
                       check=True, capture_output=True)
        try:
            # The plugins ship as mitsuba_csg.plugins from the top-level plugins/ folder.
            (base / "mitsuba_csg" / "plugins").symlink_to(base / "plugins")
            runs = {"base": [], "this": []}
            for _ in range(args.rounds):
                for side, root in (("base", base), ("this", here)):
                    runs[side].append(run_side(root, args, scenes))
                    print(f"  {side:5s} " + "  ".join(f"{s} {runs[side][-1][s]['best_s'] * 1e3:.2f} ms"
                                                      for s in scenes), flush=True)
        finally:
            subprocess.run(["git", "-C", str(here), "worktree", "remove", "--force", str(base)], capture_output=True)
    rows = []
    for s in scenes:
        b = [r[s]["best_s"] for r in runs["base"]]
        t = [r[s]["best_s"] for r in runs["this"]]
        rows.append(dict(scene=s, base_best_ms=min(b) * 1e3, this_best_ms=min(t) * 1e3,
                         base_median_ms=statistics.median(b) * 1e3, this_median_ms=statistics.median(t) * 1e3,
                         ratio_best=min(t) / min(b), ratio_median=statistics.median(t) / statistics.median(b),
                         steps_base=runs["base"][0][s]["steps"], steps_this=runs["this"][0][s]["steps"]))
    columns = [("scene", "scene", "s"), ("base_best_ms", "base best ms", ".2f"), ("this_best_ms", "this best ms", ".2f"),
               ("ratio_best", "this/base best", ".3f"), ("ratio_median", "this/base median", ".3f"),
               ("steps_base", "steps base", ".2f"), ("steps_this", "steps this", ".2f")]
    print(f"{args.size} primary rays, base {args.base}, {args.rounds} alternating rounds, best of {args.repeats} "
          f"frames a process; {common.machine()['cpu']}")
    print(common.table(rows, columns))
    print(f"wrote {common.write(args.name, {'machine': common.machine(), 'base': args.base, 'rows': rows})}")


if __name__ == "__main__":
    main()
