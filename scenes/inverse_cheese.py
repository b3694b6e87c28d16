"""Inverse rendering: recover the holes of a small Cheese from four views.

    ./run.sh -- python scenes/inverse_cheese.py [--integrator csg_prb_projective]
        [--iterations 120] [--size 128x96] [--spp 8] [--lighting camera] [--out inverse_cheese]

A box of edge 2 minus 5 spheres, one cut into each visible face; four cameras around it.
Lighting `camera`: a point light at each camera (no shadow falls in view, so the run is
about the boundaries the camera sees); `studio`: the box stands on a grey floor under one
square area light above and to the side and a uniform sky, the same for every view (the
holes' rims cast soft shadows into them, and the box onto the floor). The targets are csg_path renders
of the true model; the optimization starts from every hole moved by 0.12 and its radius
off by 15 % (seeded), and fits the holes' centres and radii (`primitive_translation`,
`primitive_scale`) with Adam on the mean squared image error over the views. Prints the
centre and radius errors as it goes and writes the history and the target, initial and
final images of the first view (and the three side by side, views.png) to --out.

`docs/inverse_rendering.md` reports the runs of csg_prb_projective and csg_prb.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import mitsuba_csg as csg

BOX = 2.0
# (centre, radius) of each hole: one in the top face and one in each side face.
HOLES = [((0.30, -0.20, 0.85), 0.35), ((-0.40, -0.85, 0.20), 0.30), ((0.85, 0.40, -0.30), 0.30),
         ((0.20, 0.85, -0.20), 0.30), ((-0.85, 0.30, 0.40), 0.30)]
# Camera azimuths (degrees) at 30 degrees elevation: each side face seen by two of them.
AZIMUTHS = (45, 135, 225, 315)


def model():
    return csg.difference(csg.Box(BOX), *(csg.Sphere(r).translate(c) for c, r in HOLES))


def view(integrator, azimuth, size, spp, lighting="camera"):
    a, e = np.radians(azimuth), np.radians(30)
    eye = (6.5 * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])).tolist()
    scene = {
        "type": "scene", "integrator": {"type": integrator, "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(eye, [0, 0, 0], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": size[0], "height": size[1], "rfilter": {"type": "box"},
                            "sample_border": True},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "object": {"type": "csg", "model": csg.model_ref(model()),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.6, 0.2]}}},
        "lamp": {"type": "point", "position": eye, "intensity": 80.0},
    }
    if lighting == "studio":
        scene["lamp"] = {"type": "rectangle", "emitter": {"type": "area", "radiance": 30.0},
                         "to_world": mi.ScalarTransform4f().look_at([2.5, -1.5, 5.0], [0, 0, 0], [0, 0, 1]).scale(0.75)}
        scene["floor"] = {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.6},
                          "to_world": mi.ScalarTransform4f().translate([0, 0, -0.5 * BOX]).scale([8, 8, 1])}
        scene["sky"] = {"type": "constant", "radiance": 0.5}       # fill light: no face stays black
    elif lighting != "camera":
        raise ValueError(f"--lighting: 'camera' or 'studio', got {lighting!r}")
    return mi.load_dict(scene)


def errors(translation, scale):
    """Per hole, (centre error, radius error) in units of the box's edge."""
    centres = np.array([c for c, _ in HOLES])
    radii = np.array([r for _, r in HOLES])
    found = translation.reshape(-1, 3)[1:]
    return np.linalg.norm(found - centres, axis=1) / BOX, np.abs(scale[1:] * radii - radii) / BOX


def perturbed(translation, rng):
    """The starting guess: every hole's centre moved by 0.12 in a random direction and its
    radius off by 15 %, redrawn where the hole would no longer cut its face by at least
    0.1 (a hole hidden inside the box shows nothing to move it by)."""
    centres = translation.reshape(-1, 3).copy()
    scale = np.ones(len(centres))
    for i, (centre, radius) in enumerate(HOLES, start=1):
        while True:
            direction = rng.normal(size=3)
            moved = np.asarray(centre) + 0.12 * direction / np.linalg.norm(direction)
            factor = 1.0 + 0.15 * rng.choice([-1.0, 1.0])
            if radius * factor - (0.5 * BOX - np.max(np.abs(moved))) >= 0.1:
                break
        centres[i], scale[i] = moved, factor
    return centres, scale


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--integrator", default="csg_prb_projective")
    parser.add_argument("--iterations", type=int, default=120)
    parser.add_argument("--size", default="128x96")
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--lr", type=float, default=0.01)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--lighting", default="camera", choices=("camera", "studio"))
    parser.add_argument("--out", type=Path, default=Path("inverse_cheese"))
    parser.add_argument("--variant", default="llvm_ad_rgb", help="an AD variant, e.g. cuda_ad_rgb")
    args = parser.parse_args(argv)
    mi.set_variant(args.variant)
    csg.register_plugins()
    size = tuple(int(v) for v in args.size.split("x"))

    targets = []
    for azimuth in AZIMUTHS:
        targets.append(mi.render(view("csg_path", azimuth, size, 256, args.lighting), spp=256, seed=0))
    scenes = [view(args.integrator, azimuth, size, args.spp, args.lighting) for azimuth in AZIMUTHS]
    params = [mi.traverse(scene) for scene in scenes]
    true_translation = np.array(params[0]["object.primitive_translation"])

    start_translation, start_scale = perturbed(true_translation, np.random.default_rng(args.seed))
    count = len(HOLES) + 1

    opt = mi.ad.Adam(lr=args.lr)
    opt["translation"] = mi.Float(start_translation.ravel().astype(np.float32))
    opt["scale"] = mi.Float(start_scale.astype(np.float32))
    free = np.ones(count, np.float32)
    free[0] = 0.0                                                       # the box stays where it is
    keep = mi.Float(np.repeat(free, 3))
    base_t = mi.Float(start_translation.ravel().astype(np.float32))
    history = []
    args.out.mkdir(parents=True, exist_ok=True)
    first = None
    start = time.perf_counter()
    for it in range(args.iterations + 1):
        translation = np.array(opt["translation"])
        scale = np.array(opt["scale"])
        centre_errors, radius_errors = errors(translation, scale)
        loss = 0.0
        for k, (scene, p, target) in enumerate(zip(scenes, params, targets)):
            p["object.primitive_translation"] = keep * opt["translation"] + (1 - keep) * base_t
            p["object.primitive_scale"] = opt["scale"] * mi.Float(free) + mi.Float(1 - free)
            p.update()
            image = mi.render(scene, p, spp=args.spp, seed=it * len(scenes) + k + 1)
            if k == 0 and first is None:
                first = np.array(image)
            term = dr.mean(dr.square(image - target), axis=None) / len(scenes)
            dr.backward(term)
            loss += float(term.array[0])
        history.append({"iteration": it, "loss": loss, "centre_errors": centre_errors.tolist(),
                        "radius_errors": radius_errors.tolist(), "seconds": time.perf_counter() - start})
        if it % 10 == 0 or it == args.iterations:
            print(f"{it:4d}  loss {loss:.3e}  centre errors {np.array2string(centre_errors, precision=3)}  "
                  f"radius errors {np.array2string(radius_errors, precision=3)} (box edges)  "
                  f"{time.perf_counter() - start:.1f} s", flush=True)
        if it < args.iterations:
            opt.step()
            opt["scale"] = dr.clip(opt["scale"], 0.2, 3.0)
    final = np.array(mi.render(scenes[0], spp=64, seed=0))
    views = (("target", np.array(targets[0])), ("initial", first), ("final", final))
    for name, image in views:
        mi.util.write_bitmap(str(args.out / f"{name}.png"), image)
    mi.util.write_bitmap(str(args.out / "views.png"), np.concatenate([image for _, image in views], axis=1))
    result = {"integrator": args.integrator, "size": args.size, "spp": args.spp, "lr": args.lr,
              "lighting": args.lighting, "history": history}
    (args.out / "history.json").write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}/")
    return result


if __name__ == "__main__":
    main()
