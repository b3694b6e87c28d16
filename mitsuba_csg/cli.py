"""The `mitsuba-csg` command line: render, info, convert, bench."""
from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

from . import scene_setup
from .images import AOVS, DEFAULT_AOVS, channel_names, write_exr, write_png
from .scenes import NAMED as BUILTIN_SCENES


class CLIError(Exception):
    """A user error: printed as one line, exit status 2."""


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0 or w * h > 64_000_000:
            raise ValueError
        return w, h
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x360, got {text!r}") from None


def _size_list(text: str) -> list[int]:
    return list(_size(text))


def _positive_int(text: str) -> int:
    try:
        v = int(text)
        if v <= 0:
            raise ValueError
        return v
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None


def _set_variant(name: str | None):
    import mitsuba as mi
    if name:
        if name not in mi.variants():
            raise CLIError(f"unknown variant {name!r}; available JIT variants: "
                           + ", ".join(v for v in mi.variants() if not v.startswith("scalar")))
        if name.startswith("scalar"):
            raise CLIError(f"variant {name!r} is a scalar variant; mitsuba-csg needs a JIT one (e.g. llvm_ad_rgb)")
        try:
            mi.set_variant(name)
        except (ImportError, RuntimeError) as e:     # e.g. a CUDA variant on a machine without CUDA
            raise CLIError(f"variant {name!r} cannot start on this machine ({str(e).splitlines()[0]}); "
                           f"llvm_ad_rgb runs on any CPU") from None
    import mitsuba_csg as csg
    csg.register_plugins()
    return mi, csg


def _load_model(path: str, **options):
    import mitsuba_csg as csg
    p = Path(path)
    if not p.exists():
        raise CLIError(f"{path}: no such file")
    return csg.load(p, **options)


def _render(args) -> int:
    mi, csg = _set_variant(args.variant)
    import drjit as dr
    import numpy as np
    width, height = args.size
    integrator = args.integrator
    out = Path(args.output)
    if out.suffix.lower() != ".exr":
        raise CLIError(f"{out}: the output is an OpenEXR file (.exr); add --png for a preview")
    _check_writable(out)
    scene, what = scene_setup.load_scene(
        mi, csg, args.input, width, height, args.spp, integrator, cuts=args.cut, hide=args.hide,
        skip_unsupported=args.skip_unsupported, depth=args.depth, world=args.world, size_given=False)
    # --aov: the scene's own integrator gives the colour, csg_aov adds the buffers as layers.
    render_with = scene.integrator()
    if args.aov is not None:
        render_with = mi.load_dict({"type": "csg_aov", "inner": render_with,
                                    "aovs": ",".join(f"{name}:{AOVS[name]}" for name in args.aov)})
    passes = max(1, min(args.passes, args.spp))
    spp_per_pass = [args.spp // passes + (1 if i < args.spp % passes else 0) for i in range(passes)]
    t0 = time.perf_counter()
    total = None
    for i, spp in enumerate(spp_per_pass):
        image = mi.render(scene, spp=spp, seed=i, integrator=render_with)
        dr.eval(image)
        dr.sync_thread()          # kernels run asynchronously: wait, so progress and time are real
        total = image * spp if total is None else total + image * spp
        _progress(i + 1, passes, time.perf_counter() - t0)
    image = total / float(args.spp)
    elapsed = time.perf_counter() - t0
    pixels = np.array(image)
    names = channel_names(pixels.shape[-1], render_with.aov_names())
    written = [write_exr(out, pixels, names)]
    if args.png:
        colour = [k for k, name in enumerate(names) if name in ("R", "G", "B", "Y")]
        written.append(write_png(out.with_suffix(".png"), pixels[..., colour]))
    print(f"rendered {what} at {width}x{height}, {args.spp} spp, in {elapsed:.1f} s -> "
          + ", ".join(str(p) for p in written))
    return 0


def _check_writable(out: Path) -> None:
    """Before a render that may take hours: the output's folder exists or can be made, and a
    file can be created in it."""
    import tempfile
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out.parent):
            pass
    except OSError as e:
        raise CLIError(f"{out}: cannot write there ({e.strerror or e})") from None
    if out.is_dir():
        raise CLIError(f"{out}: is a directory")


def _aov_list(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in AOVS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list of {', '.join(AOVS)}, got {text!r}")
    return names


def _progress(done: int, total: int, elapsed: float):
    if total <= 1 or not sys.stderr.isatty():
        return
    bar = "#" * (30 * done // total)
    sys.stderr.write(f"\r[{bar:<30}] {done}/{total} passes, {elapsed:.1f} s")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()


def _info(args) -> int:
    _, csg = _set_variant(args.variant)
    model = _load_model(args.model)
    leaves = model.leaves()
    kinds = Counter(type(p).__name__ for p in leaves)
    ops, stack = Counter(), [model]
    while stack:
        node = stack.pop()
        if isinstance(node, csg.Operation):
            ops[node.kind] += 1
            stack.extend(node.children)
    lower, upper = model.bounds()
    opt, stats = csg.optimize(model)
    materials = Counter(p.material for p in leaves if p.material)
    print(f"{args.model}")
    print(f"  primitives   {len(leaves)}: " + ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())))
    print("  operations   " + (", ".join(f"{n} {k}" for k, n in sorted(ops.items())) or "none"))
    print("  materials    " + (", ".join(f"{k} ({n})" for k, n in sorted(materials.items())) or "none"))
    print(f"  bounds       {lower.round(6).tolist()} .. {upper.round(6).tolist()}")
    print(f"  height       input {stats['height_input']}, lowered {stats['height_before']}, "
          f"optimized {stats['height_after']}")
    print(f"  nodes        lowered {stats['nodes_before']}, optimized {stats['nodes_after']} "
          f"({stats['leaves_duplicated']} leaves duplicated), optimizer {stats['seconds_total']:.2f} s")
    return 0


def _convert(args) -> int:
    _, csg = _set_variant(args.variant)
    model = _load_model(args.model)
    out = Path(args.output)
    if out.suffix.lower() not in (".ply", ".obj", ".stl", ".json"):
        raise CLIError(f"{out}: can write .ply, .obj, .stl (meshes) or .json (native model)")
    options = {} if out.suffix.lower() == ".json" else {"segments": args.segments}
    csg.save(model, out, **options)
    print(f"wrote {out}")
    return 0


def _bench(args) -> int:
    mi, csg = _set_variant(args.variant)
    import drjit as dr

    from .camera import framing, look_at_rays, tile_order
    from .queries import rays_to_device, trace_rays
    if args.input is None:
        from .scenes import cheese
        model, what = cheese(1000), "the Cheese-1000"
    elif args.input in BUILTIN_SCENES:
        model, what = BUILTIN_SCENES[args.input](), f"the built-in {args.input}"
    else:
        model, what = _load_model(args.input), args.input
    width, height = args.size
    prepared = csg.prepare(model, optimize=not args.no_optimize)
    lower, upper = model.bounds()
    origin, target = framing(lower, upper, 40.0, width / height)
    o, d = look_at_rays(origin, target, fov_degrees=40.0, width=width, height=height)
    perm = tile_order(width, height)            # rays in 4x4 pixel tiles: fuller SIMD packets
    O, D = rays_to_device(o[perm], prepared.tree.b), rays_to_device(d[perm], prepared.tree.b)
    best = float("inf")
    for _ in range(args.repeats + 1):
        t0 = time.perf_counter()
        hits = trace_rays(prepared, O, D)
        dr.eval(hits.t, hits.normal, hits.prim)
        dr.sync_thread()
        best = min(best, time.perf_counter() - t0)
    print(f"{what}: {prepared.flat.num_prims} primitives, tree height {prepared.flat.height}; "
          f"{width}x{height} primary rays (4x4 tiles) in {best * 1e3:.1f} ms = {width * height / best / 1e6:.2f} Mrays/s "
          f"({mi.variant()}, best of {args.repeats} after a warm-up)")
    return 0


def _batch(args) -> int:
    _set_variant(args.variant)
    from . import batch
    single = {"output": args.output, "spp": args.spp, "chunk_spp": args.chunk_spp, "size": args.size,
              "seed": args.seed, "integrator": args.integrator}
    given = {k: v for k, v in single.items() if v is not None}
    if args.no_png:
        given["png"] = False
    if args.input is not None and batch.is_job_file(args.input):
        if given:
            raise CLIError(f"{args.input}: a job file sets {', '.join(sorted(given))} itself "
                           "(per job, or for all in its \"defaults\")")
        jobs = batch.load_jobs(args.input, args.frames)
    else:
        given.setdefault("output", "turntable.exr" if args.frames else "batch.exr")
        if args.input is not None:
            given["input"] = args.input
        jobs = batch.parse_jobs({"jobs": [given]}, Path.cwd(), "command line", args.frames)
    if args.local and args.address:
        raise CLIError("--local and --address exclude each other")
    try:
        summary = batch.run(jobs, workers=args.workers, threads=args.threads, address=args.address,
                            use_ray=False if args.local else None)
    except KeyboardInterrupt:
        print("mitsuba-csg: interrupted; finished chunks are saved, rerun the same command to resume",
              file=sys.stderr)
        return 130
    _print_summary(summary)
    if summary.failed:
        print(f"mitsuba-csg: error: {len(summary.failed)} of {len(summary.results)} jobs failed", file=sys.stderr)
        return 1
    return 0


def _print_summary(summary) -> None:
    width = max(len(r.job.name) for r in summary.results)
    print(f"{len(summary.results)} jobs in {summary.seconds:.1f} s ({summary.backend}, {summary.workers} "
          f"worker{'s' if summary.workers != 1 else ''})")
    for r in summary.results:
        chunks = f"{r.chunks_rendered} rendered, {r.chunks_reused} reused"
        where = ", ".join(str(p) for p in r.outputs) if r.status != "failed" else r.error
        print(f"  {r.job.name:<{width}}  {r.status:<12}  {chunks:<24}  {where}")


COMMANDS = ("render", "info", "convert", "bench", "batch")


def _integrator_names() -> tuple[str, ...]:
    from .plugins.registry import integrator_names
    return integrator_names()


def _global_options(p: argparse.ArgumentParser, default) -> None:
    p.add_argument("--verbose", action="store_true", default=default, help="show tracebacks on errors")
    p.add_argument("--variant", default=default, help="Mitsuba variant (default: llvm_ad_rgb)")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mitsuba-csg", description="Exact CSG ray tracing in Mitsuba 3.")
    _global_options(p, None)
    # The global options are accepted after the command too (`render x.xml --verbose`);
    # SUPPRESS keeps a subcommand from resetting what was given before it.
    common = argparse.ArgumentParser(add_help=False)
    _global_options(common, argparse.SUPPRESS)
    sub = p.add_subparsers(dest="command")
    r = sub.add_parser("render", parents=[common], help="render a scene (.xml), a model file, or the built-in demo")
    r.add_argument("input", nargs="?", help="scene .xml, model (.json/.gdml/.csg/.scad/.stl/...) or a built-in scene name "
                   "(cheese-1000, city-3385, satellites-87.5k, ...); none: the demo Cheese")
    r.add_argument("-o", "--output", default="cheese.exr", help="output OpenEXR file (default: cheese.exr)")
    r.add_argument("--spp", type=_positive_int, default=16, help="samples per pixel (default 16)")
    r.add_argument("--size", type=_size, default=(640, 360), help="WIDTHxHEIGHT (default 640x360)")
    r.add_argument("--integrator", default="csg_path", choices=_integrator_names(),
                   help="the csg_* integrator of a model or built-in scene (default csg_path)")
    r.add_argument("--passes", type=_positive_int, default=4, help="render in this many passes (progress)")
    r.add_argument("--png", action="store_true", help="also write a tonemapped sRGB .png preview")
    r.add_argument("--cut", action="append", metavar="AXIS>VALUE",
                   help="keep the part of the model beyond a plane, e.g. x>0 or z<10 (repeatable): a cut-away")
    r.add_argument("--skip-unsupported", action="store_true",
                   help="GDML, OpenSCAD: leave out unsupported solids and nodes (with a warning) instead of failing")
    r.add_argument("--depth", type=int, default=None, metavar="K",
                   help="GDML: volumes at most K placement levels below the world")
    r.add_argument("--world", action="store_true", default=None, help="GDML: show the world volume too")
    r.add_argument("--hide", metavar="NAMES", default=None,
                   help="GDML: comma-separated logical volume names or materials to leave out")
    r.add_argument("--aov", nargs="?", type=_aov_list, const=DEFAULT_AOVS, default=None, metavar="LIST",
                   help="add geometric layers to the EXR: comma-separated from depth, normal, position, prim, "
                        f"shape (no LIST: {','.join(DEFAULT_AOVS)})")
    i = sub.add_parser("info", parents=[common], help="primitives, operations, height and bounds of a model")
    i.add_argument("model")
    c = sub.add_parser("convert", parents=[common], help="convert a model to a mesh (.ply/.obj/.stl) or native .json")
    c.add_argument("model")
    c.add_argument("-o", "--output", required=True)
    c.add_argument("--segments", type=_positive_int, default=64, help="circular segments of round primitives")
    b = sub.add_parser("bench", parents=[common], help="primary-ray throughput of a model (default: Cheese-1000)")
    b.add_argument("input", nargs="?")
    b.add_argument("--size", type=_size, default=(1280, 720))
    b.add_argument("--repeats", type=_positive_int, default=3)
    b.add_argument("--no-optimize", action="store_true")
    a = sub.add_parser("batch", parents=[common],
                       help="render many images (a job file, or a turntable) in sample chunks, on Ray or here")
    a.add_argument("input", nargs="?", help="a job file (JSON with \"jobs\", see docs/batch.md), or one scene, model "
                   "or built-in scene as for render (none: the demo Cheese)")
    a.add_argument("--frames", type=_positive_int, default=None,
                   help="a turntable: each job as N frames, the camera circling the scene (outputs NAME_0000.exr ...)")
    a.add_argument("-o", "--output", default=None, help="output .exr of a single input (default batch.exr, "
                   "or turntable.exr with --frames)")
    a.add_argument("--spp", type=_positive_int, default=None, help="samples per pixel (default 16)")
    a.add_argument("--chunk-spp", type=_positive_int, default=None, help="samples per chunk (default 8)")
    a.add_argument("--size", type=_size_list, default=None, help="WIDTHxHEIGHT (default 640x360; "
                   "an .xml scene: its own)")
    a.add_argument("--seed", type=int, default=None, help="seed of the job's chunk seeds (default 0)")
    a.add_argument("--integrator", default=None, choices=_integrator_names(),
                   help="the csg_* integrator of models and built-in scenes (default csg_path)")
    a.add_argument("--no-png", action="store_true", help="write only the .exr images")
    a.add_argument("--workers", type=_positive_int, default=None,
                   help="Ray workers (default: the cluster's CPUs / --threads)")
    a.add_argument("--threads", type=_positive_int, default=None, help="Dr.Jit threads per Ray worker (default 1), or of this process with --local "
                   "(default: all; one thread renders bit for bit alike run to run)")
    a.add_argument("--address", default=None, help="join this Ray cluster (e.g. auto, or ray://host:10001) instead "
                   "of starting a local one")
    a.add_argument("--local", action="store_true", help="render in this process, without Ray")
    return p


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = parser()
    if not any(a in (*COMMANDS, "-h", "--help") for a in argv):
        argv = ["render", *argv]          # `mitsuba-csg scene.xml`: render is implied
    args = p.parse_args(argv)
    handlers = {"render": _render, "info": _info, "convert": _convert, "bench": _bench, "batch": _batch}
    try:
        return handlers[args.command](args)
    except KeyboardInterrupt:
        print("mitsuba-csg: interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        from .errors import CSGError
        if args.verbose:
            raise
        if isinstance(e, (CLIError, CSGError, OSError)):
            print(f"mitsuba-csg: error: {e}", file=sys.stderr)
            return 2
        print(f"mitsuba-csg: internal error: {type(e).__name__}: {e} (run with --verbose for details)",
              file=sys.stderr)
        return 1
