"""The `mitsuba-csg` command line: render, info, convert, bench."""
from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

from .formats import MODEL_SUFFIXES
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


def _load_options(args, path: str) -> dict:
    """Reader options from the command line: --skip-unsupported (GDML, OpenSCAD), --depth and
    --world (GDML)."""
    suffix = Path(path).suffix.lower()
    options = {}
    if getattr(args, "skip_unsupported", False):
        if suffix not in (".gdml", ".csg", ".scad"):
            raise CLIError(f"{path}: --skip-unsupported applies to GDML and OpenSCAD files")
        options["on_unsupported"] = "skip"
    gdml_only = {"depth": getattr(args, "depth", None), "show_world": getattr(args, "world", None) or None,
                 "hide": getattr(args, "hide", None)}
    if suffix != ".gdml" and any(v is not None for v in gdml_only.values()):
        raise CLIError(f"{path}: --depth, --world and --hide apply to GDML detectors")
    if suffix == ".gdml":
        options.update({k: v for k, v in gdml_only.items() if k != "hide" and v is not None})
    return options


def demo_scene_dict(mi, csg, width, height, spp, integrator):
    """The built-in demo: the paper's Cheese (a cube minus 500 spheres) on a floor."""
    from .scenes import cheese
    return model_scene_dict(mi, csg, cheese(500, seed=0), width, height, spp, integrator,
                            colour=[0.85, 0.65, 0.25])


def model_scene_dict(mi, csg, model, width, height, spp, integrator, colour=None):
    """A model on a floor, framed by a camera, lit by a sky and a sun; each material in its colour
    (`viewing.material_colour`), or all in `colour`."""
    from . import viewing
    default = viewing.bsdf((*colour, 1.0) if colour is not None else viewing.material_colour(None))
    return scene_dict(mi, csg, [(model, {} if colour is not None else viewing.material_bsdfs(model), default)],
                      width, height, spp, integrator)


def scene_dict(mi, csg, parts, width, height, spp, integrator):
    """Mitsuba's dict for csg shapes `parts` [(model, {material: bsdf}, default bsdf)] on a floor,
    framed by a camera whose clip planes follow the scene's size (a 40 m detector in mm too)."""
    import numpy as np

    from .camera import framing
    boxes = np.array([part[0].bounds() for part in parts])
    lower, upper = boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)
    origin, target = framing(lower, upper, 40.0, width / height)
    size = float((upper - lower).max())
    distance = float(np.linalg.norm(origin - target))
    shapes = {}
    for k, (model, bsdfs, default) in enumerate(parts):
        shape = {"type": "csg", "model": csg.model_ref(model), "bsdf": default}
        shape.update({name: value for name, value in bsdfs.items()})
        shapes[f"model{k}" if k else "model"] = shape
    return {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": 6} if integrator != "csg_aov" else {"type": "csg_aov"},
        "sensor": {"type": "perspective", "fov": 40.0, "fov_axis": "x",
                   "near_clip": 1e-4 * distance, "far_clip": distance + 10.0 * size,
                   "to_world": mi.ScalarTransform4f().look_at(origin.tolist(), target.tolist(), [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": width, "height": height},
                   "sampler": {"type": "independent", "sample_count": spp}},
        **shapes,
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([float(target[0]), float(target[1]), float(lower[2])])
                  .scale(4.0 * size),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.55]}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.35, 0.4, 0.5]}},
        "sun": {"type": "directional", "direction": [-1.0, 1.2, -2.0], "irradiance": {"type": "rgb", "value": [3.0, 2.8, 2.5]}},
    }


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
    if args.input is None:
        scene = mi.load_dict(demo_scene_dict(mi, csg, width, height, args.spp, integrator))
        what = "the built-in Cheese (500 holes)"
    elif args.input.lower().endswith(".xml"):
        if not Path(args.input).exists():
            raise CLIError(f"{args.input}: no such file")
        # Mitsuba refuses parameters a scene does not use: pass those it names ($spp ...).
        text = Path(args.input).read_text(errors="replace")
        params = {k: v for k, v in (("spp", args.spp), ("width", width), ("height", height)) if f"${k}" in text}
        try:
            scene = mi.load_file(args.input, **params)
        except Exception as e:                               # Mitsuba's parser errors
            raise CLIError(f"{args.input}: {_mitsuba_reason(str(e))}") from e
        what = args.input
    elif args.input.lower().endswith(MODEL_SUFFIXES):
        scene = mi.load_dict(scene_dict(mi, csg, _model_parts(args), width, height, args.spp, integrator))
        what = args.input
    elif args.input in BUILTIN_SCENES:
        model = BUILTIN_SCENES[args.input]()
        scene = mi.load_dict(model_scene_dict(mi, csg, model, width, height, args.spp, integrator))
        what = f"the built-in {args.input}"
    else:
        raise CLIError(f"{args.input}: expected a Mitsuba scene (.xml), a model ({', '.join(MODEL_SUFFIXES)}) "
                       f"or a built-in scene ({', '.join(BUILTIN_SCENES)})")
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


def _mitsuba_reason(message: str) -> str:
    """Mitsuba's error without the Python traceback it embeds for a failing Python plugin: its
    place (file, line, plugin) and the exception's own last line, which says why."""
    lines = [line for line in message.splitlines() if line.strip()]
    if len(lines) > 1 and "Traceback (most recent call last)" in lines[0]:
        head = lines[0].split("Traceback (most recent call last)")[0].rstrip(": ")
        return f"{head}: {lines[-1].strip()}"
    return lines[0] if lines else message


def _model_parts(args):
    """The csg shapes of a model file (`viewing.model_parts`), with the command line's options."""
    from . import viewing
    if not Path(args.input).exists():
        raise CLIError(f"{args.input}: no such file")
    cuts = [viewing.parse_cut(c) for c in (args.cut or [])]
    return viewing.model_parts(args.input, cuts, _names(args.hide), **_load_options(args, args.input))


def _names(text):
    return [n.strip() for n in (text or "").split(",") if n.strip()]


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

    from .camera import framing, look_at_rays
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
    O, D = rays_to_device(o, prepared.tree.b), rays_to_device(d, prepared.tree.b)
    best = float("inf")
    for _ in range(args.repeats + 1):
        t0 = time.perf_counter()
        hits = trace_rays(prepared, O, D)
        dr.eval(hits.t, hits.normal, hits.prim)
        dr.sync_thread()
        best = min(best, time.perf_counter() - t0)
    print(f"{what}: {prepared.flat.num_prims} primitives, tree height {prepared.flat.height}; "
          f"{width}x{height} primary rays in {best * 1e3:.1f} ms = {width * height / best / 1e6:.2f} Mrays/s "
          f"({mi.variant()}, best of {args.repeats} after a warm-up)")
    return 0


COMMANDS = ("render", "info", "convert", "bench")


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
    r.add_argument("--integrator", default="csg_path", choices=["csg_path", "csg_aov", "csg_prb"])
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
    return p


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = parser()
    if not any(a in (*COMMANDS, "-h", "--help") for a in argv):
        argv = ["render", *argv]          # `mitsuba-csg scene.xml`: render is implied
    args = p.parse_args(argv)
    handlers = {"render": _render, "info": _info, "convert": _convert, "bench": _bench}
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
