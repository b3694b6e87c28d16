"""Shared helpers for the benchmark scripts: timing, machine description, table and JSON output."""
from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Tests redirect the JSON files with MITSUBA_CSG_BENCH_RESULTS, so smoke runs never overwrite results.
RESULTS = Path(os.environ.get("MITSUBA_CSG_BENCH_RESULTS", ROOT / "benchmarks" / "results"))
sys.path.insert(0, str(ROOT))


def select_variant(name: str | None) -> None:
    """Select a Mitsuba variant (e.g. cuda_ad_rgb) before mitsuba_csg is imported."""
    if name:
        import mitsuba as mi
        mi.set_variant(name)


# The order camera rays are traced in (`trace_throughput.rays_for`): 4x4 pixel tiles, as a
# tiled renderer would trace them (`mitsuba_csg.camera.tile_order`), or image rows.
RAY_ORDERS = ("tiles", "rows")
ray_order = "tiles"


def parse_args(parser, argv=None):
    """`parser.parse_args(argv)` with the `--variant` and `--ray-order` every benchmark takes,
    applied at once."""
    global ray_order
    parser.add_argument("--variant", default=None, help="Mitsuba variant, e.g. cuda_ad_rgb (default: llvm_ad_rgb)")
    parser.add_argument("--ray-order", choices=RAY_ORDERS, default="tiles",
                        help="camera rays in 4x4 pixel tiles (default) or in image rows; both the CSG "
                             "kernel and Embree trace the same rays")
    args = parser.parse_args(argv)
    select_variant(args.variant)
    ray_order = args.ray_order
    return args


def machine() -> dict:
    import drjit as dr
    import mitsuba as mi
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "mitsuba": mi.__version__, "drjit": dr.__version__, "variant": mi.variant(),
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "ray_order": ray_order}


def best_of(fn, repeats: int = 5) -> dict:
    """Run fn() `repeats` times; report min and median seconds. A first run before them is
    warm-up (kernels compiled, or read from Dr.Jit's cache); `first_s` is its time."""
    return alternating({"fn": fn}, repeats)["fn"]


def alternating(fns: dict, repeats: int = 5) -> dict:
    """best_of for several functions whose times are compared as ratios: one warm-up run each,
    then `repeats` rounds that run each once in turn, so that a machine whose speed drifts
    (a shared host, turbo) slows all of them alike. {name: best_of's dict}."""
    first = {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        fn()
        first[name] = time.perf_counter() - t0
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {name: {"min_s": min(ts), "median_s": statistics.median(ts), "runs": ts, "first_s": first[name]}
            for name, ts in times.items()}


def table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """columns: (key, header, format)."""
    head = [h for _, h, _ in columns]
    body = [[(f"{r[k]:{fmt}}" if r.get(k) is not None else "-") for k, _, fmt in columns] for r in rows]
    widths = [max(len(x) for x in col) for col in zip(head, *body)]
    line = lambda cells: "  ".join(c.rjust(w) for c, w in zip(cells, widths))  # noqa: E731
    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in body])


def write(name: str, payload: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(payload, indent=2, default=float) + "\n")
    return path
