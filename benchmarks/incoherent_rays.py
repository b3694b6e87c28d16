"""Incoherent ray batches traced as given and reordered (`trace_rays(reorder=True)`), and the
same rays through Embree on the manifold3d mesh, measured in one run.

    ./run.sh bench incoherent_rays.py [--scenes city-3385,cheese-1000] [--rays 921600]
                                      [--no-mesh] [--variant cuda_ad_rgb]

Three batches per scene, seeded:
- bounce: points on the ground plane under the model (a square twice the model's size across)
  with cosine-distributed upward directions, as the first bounce of a path tracer whose floor
  surrounds the model;
- points: points uniform in the model's box, each with the one fixed direction of
  `csg.contains` (a membership query per point);
- surface: the benchmark camera's hits on the model (1280x720, trace_throughput.py's camera,
  4x4 pixel tiles), each continued in a cosine-distributed direction about the hit's normal
  from 1e-4 of the model's size off the surface: the first bounce of a path tracer off the
  model itself (one ray per hit, up to --rays: fewer rays than the other batches). It is
  traced a third time with each ray's start primitive (`trace_rays(start_prim=...)`, the
  camera hit's primitive, as csg_path passes it): 'hinted' columns.
Rows give the fraction of rays that meet the model's box, mean steps per ray (and for the
rays in the box, those that hit the model and those that leave it), the SIMD
packet utilization of the batch as given (mean steps / mean of each 16-lane packet's maximum:
how much of a packet's work is useful), seconds as given and reordered (the sort included),
and Embree's seconds for the same rays on the mesh.
"""
from __future__ import annotations

import argparse

import numpy as np

import common

PACKET = 16   # lanes of an AVX-512 packet of Dr.Jit's LLVM backend


def batches(model, n, seed=1):
    """{name: (origins, directions)} of the benchmark's incoherent batches for `model`."""
    from mitsuba_csg.queries import _PROBE
    lo, hi = (np.asarray(v, np.float64) for v in model.bounds())
    size = float((hi - lo).max())
    centre = 0.5 * (lo + hi)
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(centre[0] - size, centre[0] + size, n),
                              rng.uniform(centre[1] - size, centre[1] + size, n),
                              np.full(n, lo[2] + 1e-3 * size)])
    u1, u2 = rng.random(n), rng.random(n)
    cosine = cosine_directions(u1, u2)
    points = rng.uniform(lo, hi, (n, 3))
    return {"bounce": (ground, cosine, None), "points": (points, np.tile(_PROBE, (n, 1)), None),
            "surface": surface_bounces(model, rng, n)}


def cosine_directions(u1, u2):
    """Cosine-distributed directions about +z from two uniform samples (Malley's method)."""
    radius, phi = np.sqrt(u1), 2 * np.pi * u2
    return np.column_stack([radius * np.cos(phi), radius * np.sin(phi), np.sqrt(1 - u1)])


def surface_bounces(model, rng, n):
    """(origins, directions, start primitives) of first bounces off the model: the benchmark
    camera's hits (the first n), each with a cosine-distributed direction about the hit's
    normal, and the primitive hit."""
    import mitsuba_csg as csg
    from trace_throughput import rays_for
    o, d = rays_for(model, 1280, 720)
    hits = csg.trace(model, o, d)
    found = np.flatnonzero(np.isfinite(hits.t))[:n]
    normal = hits.normal[found]
    lo, hi = (np.asarray(v, np.float64) for v in model.bounds())
    origin = o[found] + hits.t[found, None] * d[found] + 1e-4 * float((hi - lo).max()) * normal
    local = cosine_directions(rng.random(len(normal)), rng.random(len(normal)))
    helper = np.where(np.abs(normal[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    s = np.cross(normal, helper)
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    t = np.cross(normal, s)
    direction = local[:, :1] * s + local[:, 1:2] * t + local[:, 2:] * normal
    return origin, direction, hits.prim[found].astype(np.uint32)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="city-3385,cheese-1000")
    parser.add_argument("--rays", type=int, default=1280 * 720)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--segments", type=int, default=48)
    parser.add_argument("--no-mesh", action="store_true", help="skip the mesh route (manifold3d + Embree)")
    parser.add_argument("--name", default="incoherent_rays")
    args = common.parse_args(parser, argv)
    import mitsuba_csg as csg
    from mitsuba_csg import scenes
    from trace_throughput import measure
    rows = []
    for scene in args.scenes.split(","):
        model = scenes.named(scene)
        prepared = csg.prepare(model)
        mesh = None
        if not args.no_mesh:
            from mesh_route import composed_mesh, embree_primary, mitsuba_mesh
            mesh = mitsuba_mesh(*composed_mesh(model, args.segments))
        for batch, (o, d, start) in batches(model, args.rays).items():
            plain, reordered = {}, {}
            plain_s = measure(prepared, o, d, args.repeats, hits=plain)[0]["min_s"]
            reorder_s = measure(prepared, o, d, args.repeats, reorder=True, hits=reordered)[0]["min_s"]
            plain, reordered = plain["h"], reordered["h"]
            same = all(np.array_equal(getattr(plain, k).numpy(), getattr(reordered, k).numpy(), equal_nan=True)
                       for k in ("t", "prim", "steps"))
            steps = plain.steps.numpy().astype(np.float64)
            packets = steps[:len(steps) // PACKET * PACKET].reshape(-1, PACKET)
            in_box, hit = steps > 0, np.isfinite(plain.t.numpy())
            row = dict(scene=scene, batch=batch, rays=len(o),
                       box_fraction=float(np.mean(in_box)),
                       mean_steps=float(steps.mean()), utilization=float(packets.mean() / packets.max(axis=1).mean()),
                       steps_hit=float(steps[in_box & hit].mean()) if np.any(in_box & hit) else float("nan"),
                       steps_leave=float(steps[in_box & ~hit].mean()) if np.any(in_box & ~hit) else float("nan"),
                       plain_s=plain_s, reorder_s=reorder_s, speedup=plain_s / reorder_s, identical=same)
            if start is not None:
                given = {}
                row["hinted_s"] = measure(prepared, o, d, args.repeats, hits=given, start_prim=start)[0]["min_s"]
                row["steps_hinted"] = float(given["h"].steps.numpy().mean())
                row["hinted_same_t"] = bool(np.array_equal(given["h"].t.numpy(), plain.t.numpy(), equal_nan=True))
            if mesh is not None:
                row["embree_s"] = embree_primary(mesh, o, d, args.repeats)
                row["reorder_over_embree"] = reorder_s / row["embree_s"]
            rows.append(row)
            print(f"  {scene:14s} {batch:7s} as given {plain_s * 1e3:7.1f} ms  reordered {reorder_s * 1e3:7.1f} ms"
                  f"  ({row['speedup']:.2f}x)", flush=True)
    columns = [("scene", "scene", "s"), ("batch", "batch", "s"), ("rays", "rays", "d"),
               ("box_fraction", "rays in box", ".2f"), ("mean_steps", "steps/ray", ".1f"),
               ("steps_hit", "steps/ray hit", ".1f"), ("steps_leave", "steps/ray leave", ".1f"),
               ("utilization", "SIMD use", ".2f"), ("plain_s", "as given s", ".3f"),
               ("reorder_s", "reordered s", ".3f"), ("speedup", "speed-up", ".2f"),
               ("steps_hinted", "steps/ray hinted", ".1f"), ("hinted_s", "hinted s", ".3f"), ("embree_s", "Embree s", ".3f"),
               ("reorder_over_embree", "reordered/Embree", ".1f")]
    print(f"{args.rays} rays per bounce / points batch, {common.machine()['cpu']}, {common.machine()['variant']}")
    print(common.table(rows, columns))
    if not all(r["identical"] for r in rows):
        raise SystemExit("reordered results differ from the rays traced as given")
    if not all(r.get("hinted_same_t", True) for r in rows):
        raise SystemExit("rays traced with start_prim hit at other distances than without")
    print(f"wrote {common.write(args.name, {'machine': common.machine(), 'args': vars(args), 'rows': rows})}")


if __name__ == "__main__":
    main()
