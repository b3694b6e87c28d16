"""What a Cheese scene is made of, computed from its holes in float64 (no kernel involved
but for the visible hit): the solid fraction of the cube and the mean number of holes a
camera ray crosses inside the cube before its visible hit.

The two numbers say how much work a ray cannot avoid: Table 2's steps per ray are read
against them (Cheese-8000 with fixed radii is almost all holes; the constant-porosity
family keeps Cheese-500's solid fraction).
"""
from __future__ import annotations

import numpy as np

SIZE = 2.0           # the named cheeses' cube edge (scenes.cheese's default)


def holes_of(name: str):
    """(centres, radii) of the named cheese ("cheese-N" or "cheese-cp-N"), or None."""
    from mitsuba_csg import scenes
    parts = name.split("-")
    if parts[0] != "cheese":
        return None
    holes = int(parts[-1])
    scale = scenes.constant_porosity_scale(holes) if parts[1] == "cp" else 1.0
    return scenes.cheese_holes(holes, 0, SIZE, scale)


def holes_crossed(centres, radii, o, d, t_hit, chunk: int = 512) -> float:
    """Mean over rays entering the cube of the holes whose ray interval overlaps the part of
    the ray inside the cube before its hit (t_hit; inf for a miss: up to the cube's far side)."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    length = np.linalg.norm(d, axis=1)
    d, t_hit = d / length[:, None], np.asarray(t_hit, np.float64) * length      # unit directions
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1, t2 = (-0.5 * SIZE - o) * inv, (0.5 * SIZE - o) * inv
    t_in = np.maximum(np.max(np.minimum(t1, t2), axis=1), 0.0)
    t_out = np.min(np.maximum(t1, t2), axis=1)
    enters = t_in <= t_out
    o, d, t_in = o[enters], d[enters], t_in[enters]
    t_end = np.minimum(np.where(np.isfinite(t_hit[enters]), t_hit[enters], np.inf), t_out[enters])
    count = np.zeros(len(o))
    for k in range(0, len(centres), chunk):
        c, r = centres[k:k + chunk], radii[k:k + chunk]
        oc = c[None, :, :] - o[:, None, :]                      # rays x holes x 3
        b = np.einsum("rhk,rk->rh", oc, d)
        disc = b * b - (np.einsum("rhk,rhk->rh", oc, oc) - r[None, :] ** 2)
        root = np.sqrt(np.maximum(disc, 0.0))
        crossed = (disc > 0) & (b + root > t_in[:, None]) & (b - root < t_end[:, None])
        count += crossed.sum(axis=1)
    return float(count.mean()) if len(count) else 0.0


def statistics(name: str, prepared, o, d, rays: int = 8192) -> dict:
    """{"solid_fraction", "holes_crossed"} of a named cheese seen through rays (o, d), with
    the visible hits traced by `prepared` on an evenly spaced subset of `rays` rays; {} for
    other scenes."""
    holes = holes_of(name)
    if holes is None:
        return {}
    import mitsuba_csg as csg
    from mitsuba_csg import scenes
    centres, radii = holes
    pick = np.linspace(0, len(o) - 1, min(rays, len(o))).astype(int)
    hits = csg.trace(prepared, o[pick], d[pick])
    return {"solid_fraction": scenes.solid_fraction(centres, radii, SIZE, resolution=128),
            "holes_crossed": holes_crossed(centres, radii, o[pick], d[pick], hits.t)}
