"""Scaling curves: optimized trace time versus primitive count and versus image size,
plotted to docs/images/scaling.png.

    ./run.sh bench scaling.py [--quick]
"""
from __future__ import annotations

import argparse

import common
from trace_throughput import measure, rays_for


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    parser.add_argument("--plot", default=str(common.ROOT / "docs" / "images" / "scaling.png"))
    args = parser.parse_args(argv)
    import mitsuba_csg as csg
    from mitsuba_csg import scenes as generators
    families = {
        "cheese": (lambda n: generators.cheese(n), [125, 500, 2000, 8000]),
        "city": (lambda n: generators.city(max(1, n // 10)), [340, 3400, 34000, 340000]),
        "satellites": (lambda n: generators.satellites(max(1, n // 14)), [875, 8750, 87500]),
    }
    sizes = [(320, 180), (640, 360), (1280, 720), (1920, 1080)]
    if args.quick:
        families = {k: (f, counts[:2]) for k, (f, counts) in families.items()}
        sizes = sizes[:2]
    base_w, base_h = (320, 180) if args.quick else (640, 360)
    rows = []
    for family, (make, counts) in families.items():
        for n in counts:
            model = make(n)
            prepared = csg.prepare(model)
            o, d = rays_for(model, base_w, base_h)
            timing, info = measure(prepared, o, d, 2)
            rows.append(dict(curve="primitives", family=family, primitives=prepared.flat.num_prims,
                             width=base_w, height=base_h, seconds=timing["min_s"],
                             mrays_s=base_w * base_h / timing["min_s"] / 1e6, mean_steps=info["mean_steps"]))
            print(f"  {family} {prepared.flat.num_prims}: {rows[-1]['mrays_s']:.2f} Mrays/s", flush=True)
    model = generators.cheese(1000)
    prepared = csg.prepare(model)
    for w, h in sizes:
        o, d = rays_for(model, w, h)
        timing, info = measure(prepared, o, d, 2)
        rows.append(dict(curve="image", family="cheese", primitives=prepared.flat.num_prims, width=w, height=h,
                         seconds=timing["min_s"], mrays_s=w * h / timing["min_s"] / 1e6, mean_steps=info["mean_steps"]))
    columns = [("curve", "curve", "s"), ("family", "scene", "s"), ("primitives", "prims", "d"), ("width", "w", "d"),
               ("height", "h", "d"), ("seconds", "s/frame", ".3f"), ("mrays_s", "Mrays/s", ".2f"),
               ("mean_steps", "steps/ray", ".1f")]
    print(common.table(rows, columns))
    name = "scaling_quick" if args.quick else "scaling"
    print(f"wrote {common.write(name, {'machine': common.machine(), 'rows': rows})}")
    if not args.quick:
        plot(rows, args.plot)


def plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    for family in sorted({r["family"] for r in rows if r["curve"] == "primitives"}):
        pts = [r for r in rows if r["curve"] == "primitives" and r["family"] == family]
        a.loglog([r["primitives"] for r in pts], [r["seconds"] for r in pts], "o-", label=family)
    w, h = next((r["width"], r["height"]) for r in rows if r["curve"] == "primitives")
    a.set_xlabel("primitives")
    a.set_ylabel(f"seconds per {w}x{h} frame (optimized tree)")
    a.grid(True, which="both", alpha=0.3)
    a.legend()
    pts = [r for r in rows if r["curve"] == "image"]
    b.loglog([r["width"] * r["height"] for r in pts], [r["seconds"] for r in pts], "o-", label="cheese-1000")
    b.set_xlabel("pixels (one primary ray each)")
    b.set_ylabel("seconds per frame")
    b.grid(True, which="both", alpha=0.3)
    b.legend()
    fig.suptitle("mitsuba-csg primary rays, " + common.machine()["cpu"])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
