"""`python -m mitsuba_csg` / `mitsuba-csg`: the command line."""
from __future__ import annotations

import argparse
import sys
import time


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
        return w, h
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x360, got {text!r}") from None


def _render(args) -> int:
    import numpy as np

    import mitsuba_csg as csg
    from mitsuba_csg import preview
    from mitsuba_csg.generators import cheese

    model = cheese(args.holes, seed=0)
    width, height = args.size
    t0 = time.perf_counter()
    image, info = preview.shade(model, width, height)
    elapsed = time.perf_counter() - t0
    out = preview.save(image, args.output)
    hits = int(np.count_nonzero(info.prim >= 0))
    print(f"rendered the demo Cheese ({args.holes} holes, {len(model.leaves())} primitives) at "
          f"{width}x{height} in {elapsed:.2f} s ({hits} hit pixels) -> {', '.join(map(str, out))}")
    del csg
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="mitsuba-csg", description="Exact CSG ray tracing in Mitsuba 3.")
    sub = parser.add_subparsers(dest="command")
    render = sub.add_parser("render", help="render the built-in demo (the paper's Cheese)")
    render.add_argument("-o", "--output", default="cheese.exr", help="output image (.exr; a .png preview is written too)")
    render.add_argument("--size", type=_size, default=(640, 360), help="WIDTHxHEIGHT (default 640x360)")
    render.add_argument("--holes", type=int, default=500, help="number of spherical holes (default 500)")
    args = parser.parse_args(argv)
    if args.command in (None, "render"):
        if args.command is None:
            args = parser.parse_args(["render", *(argv or [])])
        return _render(args)
    parser.print_help()
    return 2


if __name__ == "__main__":
    sys.exit(main())
