"""Cost of a gradient iteration against the primal render, for a hole's radius; with
--accuracy, how close each route's gradient image comes to finite differences.

    ./run.sh bench gradient_cost.py [--size 128x96] [--spp 8] [--mesh] [--accuracy] [--indirect]

A box minus a sphere, the sphere's radius (its `primitive_scale`) differentiated, a camera
light: one optimization iteration is a render with parameters attached plus `dr.backward`
of an image loss. Measured in one run: the primal `csg_path` frame, `csg_prb` (interior
derivatives only) and `csg_prb_projective` (with the primarily visible boundaries); with
`--mesh`, Mitsuba's `prb_projective` on the manifold3d mesh of the model with its vertex
positions differentiated (the route a user would take instead).

`--accuracy` (64x48): a hole cut into the top face only, moved along x, so that the mesh's
vertices on the sphere and on the rim move rigidly with it. Forward gradient images (256
spp) of csg_prb, csg_prb_projective and Mitsuba's prb_projective on the manifold3d mesh
(with interpolated vertex normals, and with face normals), against central differences
(4096 spp, eps 0.02) of csg_path on the model and of Mitsuba's path on the mesh.

`--indirect`: the same costs where the derivative is all indirect: a floor lit only by a
sunlit wall strip above it (the sun travels level with the floor), a dark sphere between
them out of view, its radius differentiated, max_depth 3. csg_prb_projective with and
without its indirect term (`sppi`), and with `--mesh` Mitsuba's prb_projective on the
sphere's mesh (its projective sampling of indirect discontinuities).
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import common


def scene_dict(mi, csg, model, integrator, size, spp, mesh_file=None, face_normals=False):
    width, height = size
    shape = ({"type": "csg", "model": csg.model_ref(model)} if mesh_file is None
             else {"type": "ply", "filename": str(mesh_file), "face_normals": face_normals})
    shape["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.6, 0.2]}}
    return {"type": "scene", "integrator": {"type": integrator, "max_depth": 2},
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": mi.ScalarTransform4f().look_at([4, -6, 3], [0, 0, 0], [0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                                "sample_border": mesh_file is not None},
                       "sampler": {"type": "independent", "sample_count": spp}},
            "object": shape, "lamp": {"type": "point", "position": [4, -6, 3], "intensity": 60.0}}


def indirect_scene_dict(mi, csg, model, integrator, size, spp, mesh_file=None):
    """The floor lit only by what a sunlit wall strip reflects; the model between them, out
    of the camera's view (`integrator`: a dict)."""
    width, height = size
    shape = ({"type": "csg", "model": csg.model_ref(model)} if mesh_file is None
             else {"type": "ply", "filename": str(mesh_file)})
    shape["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.1, 0.08, 0.05]}}
    return {"type": "scene", "integrator": {"max_depth": 3, **integrator},
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": mi.ScalarTransform4f().look_at([0, -2.5, 5], [0, -1, 0], [0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                                "sample_border": mesh_file is not None},
                       "sampler": {"type": "independent", "sample_count": spp}},
            "object": shape,
            "floor": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.7},
                      "to_world": mi.ScalarTransform4f().scale([4, 4, 1])},
            "wall": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.9},
                     "to_world": mi.ScalarTransform4f().translate([0, 2.5, 2.6]).rotate([1, 0, 0], 90)
                     .scale([4, 0.9, 1])},
            "sun": {"type": "directional", "direction": [0, 1, 0], "irradiance": 20.0}}


def indirect_costs(mi, dr, csg, save_mesh, size, spp, repeats, mesh):
    """Rows: seconds of the primal frame and of a gradient iteration (the sphere's radius) in
    the indirect scene."""
    model = csg.Sphere(0.6).translate((0, 1.5, 0.9))

    def load(integrator, mesh_file=None):
        return mi.load_dict(indirect_scene_dict(mi, csg, model, integrator, size, spp, mesh_file))
    primal = load({"type": "csg_path"})
    target = mi.render(primal, spp=spp, seed=0)

    def time_primal():
        dr.eval(mi.render(primal, spp=spp, seed=1))
        dr.sync_thread()
    primal_s = common.best_of(time_primal, repeats)["min_s"]
    rows = [{"integrator": "csg_path (primal)", "seconds": primal_s, "ratio": 1.0}]
    routes = [("csg_prb", {"type": "csg_prb"}, "object.primitive_scale"),
              ("csg_prb_projective, sppi 0", {"type": "csg_prb_projective", "sppi": 0}, "object.primitive_scale"),
              ("csg_prb_projective", {"type": "csg_prb_projective"}, "object.primitive_scale")]
    for name, integrator, key in routes:
        scene = load(integrator)
        run = _gradient_iteration(mi, dr, scene, key, mi.Float([1.0]), target, spp)
        seconds = common.best_of(run, repeats)["min_s"]
        rows.append({"integrator": name, "seconds": seconds, "ratio": seconds / primal_s})
    if mesh:
        with tempfile.TemporaryDirectory() as tmp:
            ply = Path(tmp) / "model.ply"
            save_mesh(csg.to_mesh(model, segments=64), ply)
            scene = load({"type": "prb_projective"}, ply)
            positions = mi.Float(mi.traverse(scene)["object.vertex_positions"])
            run = _gradient_iteration(mi, dr, scene, "object.vertex_positions", positions, target, spp)
            seconds = common.best_of(run, 1)["min_s"]
            rows.append({"integrator": "prb_projective on the mesh", "seconds": seconds, "ratio": seconds / primal_s})
    return rows


def _gradient_iteration(mi, dr, scene, key, value, target, spp):
    """One optimization iteration: render with `key` attached, backward from the image loss."""
    params = mi.traverse(scene)

    def run():
        v = type(value)(value)
        dr.enable_grad(v)
        params[key] = v
        params.update()
        image = mi.render(scene, params, spp=spp, seed=1)
        dr.backward(dr.mean(dr.square(image - target), axis=None))
        dr.eval(dr.grad(v))
        dr.sync_thread()
    return run


def accuracy(mi, dr, csg, save_mesh, spp=256, fd_spp=4096, eps=0.02, size=(64, 48)):
    """Rows: each route's gradient image sum against the finite difference's, and their correlation."""
    import numpy as np
    centre, radius = np.array([0.3, -0.2, 0.9]), 0.5
    model = csg.Box(2.0) - csg.Sphere(radius).translate(tuple(centre))
    key = "object.primitive_to_world"

    def forward(scene, key, direction):
        params = mi.traverse(scene)
        base = np.array(params[key])
        h = mi.Float(0.0)
        dr.enable_grad(h)
        params[key] = mi.Float(base) + h * mi.Float(direction.astype(np.float32))
        params.update()
        image = mi.render(scene, params, spp=spp, seed=1)
        dr.forward(h)
        return dr.grad(image).numpy()

    def central(scene, key, direction):
        base = np.array(mi.traverse(scene)[key])

        def at(v):
            params = mi.traverse(scene)
            params[key] = mi.Float((base + v * direction).astype(np.float32))
            params.update()
            return np.array(mi.render(scene, spp=fd_spp, seed=1))
        return (at(eps) - at(-eps)) / (2 * eps)

    move = np.zeros(24)
    move[12 + 3] = 1.0                                       # the sphere's x translation
    fd = central(mi.load_dict(scene_dict(mi, csg, model, "csg_path", size, fd_spp)), key, move)
    rows = [{"route": "finite differences, csg_path", "sum": float(fd.sum()), "ratio": 1.0, "correlation": 1.0}]

    def row(name, image):
        rows.append({"route": name, "sum": float(image.sum()), "ratio": float(image.sum() / fd.sum()),
                     "correlation": float(np.corrcoef(image.ravel(), fd.ravel())[0, 1])})
    for name in ("csg_prb", "csg_prb_projective"):
        row(name, forward(mi.load_dict(scene_dict(mi, csg, model, name, size, spp)), key, move))
    with tempfile.TemporaryDirectory() as tmp:
        ply = Path(tmp) / "model.ply"
        save_mesh(csg.to_mesh(model, segments=128), ply)
        for face_normals in (False, True):
            label = "face normals" if face_normals else "vertex normals"
            scene = mi.load_dict(scene_dict(mi, csg, model, "prb_projective", size, spp, ply, face_normals))
            vertices = np.array(mi.traverse(scene)["object.vertex_positions"]).reshape(-1, 3)
            motion = np.zeros_like(vertices)
            motion[np.linalg.norm(vertices - centre, axis=1) < radius + 1e-3, 0] = 1.0
            row(f"prb_projective on the mesh, {label}", forward(scene, "object.vertex_positions", motion.ravel()))
            path = mi.load_dict(scene_dict(mi, csg, model, "path", size, fd_spp, ply, face_normals))
            row(f"finite differences, path on the mesh, {label}",
                central(path, "object.vertex_positions", motion.ravel()))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="128x96")
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--mesh", action="store_true", help="also time prb_projective on the mesh (slow)")
    parser.add_argument("--accuracy", action="store_true",
                        help="also compare gradient images with finite differences (64x48, slow)")
    parser.add_argument("--indirect", action="store_true",
                        help="also time a scene whose derivative is all indirect (max_depth 3)")
    args = common.parse_args(parser, argv)
    import drjit as dr
    import mitsuba as mi

    import mitsuba_csg as csg
    from mitsuba_csg.formats.mesh_export import save_mesh
    size = tuple(int(v) for v in args.size.split("x"))
    model = csg.Box(2.0) - csg.Sphere(0.45).translate((0.3, -0.8, 0.4))
    primal = mi.load_dict(scene_dict(mi, csg, model, "csg_path", size, args.spp))
    target = mi.render(primal, spp=args.spp, seed=0)
    rows = []

    def time_primal():
        dr.eval(mi.render(primal, spp=args.spp, seed=1))
        dr.sync_thread()
    timing = common.best_of(time_primal, args.repeats)
    primal_s = timing["min_s"]
    rows.append({"integrator": "csg_path (primal)", "seconds": primal_s, "ratio": 1.0, "first_s": timing["first_s"]})

    def gradient_iteration(scene, key, value):
        return _gradient_iteration(mi, dr, scene, key, value, target, args.spp)

    for name in ("csg_prb", "csg_prb_projective"):
        scene = mi.load_dict(scene_dict(mi, csg, model, name, size, args.spp))
        run = gradient_iteration(scene, "object.primitive_scale", mi.Float([1.0, 1.0]))
        timing = common.best_of(run, args.repeats)
        seconds = timing["min_s"]
        rows.append({"integrator": name, "seconds": seconds, "ratio": seconds / primal_s, "first_s": timing["first_s"]})
    if args.mesh:
        with tempfile.TemporaryDirectory() as tmp:
            ply = Path(tmp) / "model.ply"
            save_mesh(csg.to_mesh(model, segments=64), ply)
            scene = mi.load_dict(scene_dict(mi, csg, model, "prb_projective", size, args.spp, ply))
            positions = mi.Float(mi.traverse(scene)["object.vertex_positions"])
            run = gradient_iteration(scene, "object.vertex_positions", positions)
            timing = common.best_of(run, 1)
            seconds = timing["min_s"]
            rows.append({"integrator": "prb_projective on the mesh", "seconds": seconds, "ratio": seconds / primal_s,
                         "first_s": timing["first_s"]})
    print(f"One gradient iteration, {args.size}, {args.spp} spp (best of {args.repeats}; the first iteration "
          "compiles the kernels, or reads them from Dr.Jit's cache in ~/.drjit)")
    print(common.table(rows, [("integrator", "integrator", "s"), ("seconds", "s / iteration", ".3f"),
                              ("ratio", "x primal", ".1f"), ("first_s", "first iteration s", ".2f")]))
    result = {"machine": common.machine(), "size": args.size, "spp": args.spp, "rows": rows}
    if args.indirect:
        result["indirect"] = indirect_costs(mi, dr, csg, save_mesh, size, args.spp, args.repeats, args.mesh)
        print(f"\nOne gradient iteration where the derivative is all indirect (a sphere's radius), {args.size}, "
              f"{args.spp} spp")
        print(common.table(result["indirect"], [("integrator", "integrator", "s"), ("seconds", "s / iteration", ".3f"),
                                                ("ratio", "x primal", ".1f")]))
    if args.accuracy:
        result["accuracy"] = accuracy(mi, dr, csg, save_mesh)
        print("\nGradient images of a hole's x position (64x48) against finite differences")
        print(common.table(result["accuracy"], [("route", "route", "s"), ("sum", "sum", ".3f"),
                                                ("ratio", "/ FD", ".3f"), ("correlation", "correlation", ".3f")]))
    path = common.write("gradient_cost", result)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
