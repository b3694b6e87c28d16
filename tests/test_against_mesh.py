"""The kernel against manifold3d meshes of the same model, ray-cast by Mitsuba's Embree.

The mesh (`csg.to_mesh`) is built by manifold3d's exact mesh Booleans over the tree as
written, with each primitive meshed by manifold3d's own constructors from its parameters
(radius, size, sides, ...), not from the canonical forms the kernel traces; Mitsuba traces
it as an ordinary triangle mesh. What it shares with the kernel is the model itself: the
primitives' parameters, their transforms and, for convex polyhedra, the vertices the model
derives from the planes. So it is independent of the engine and of the float64 tracer in
reference.py.

What is compared:

* first hits of rays (hit/miss, distance, normal) away from silhouettes, CSG edges and
  grazing incidence (`ray_mismatches`);
* point membership of points well inside or well outside the solid (`csg.contains` against
  ray parity on the mesh);
* the volume (Monte Carlo over `csg.contains` against `Manifold.volume()`);
* and, so that the comparison is known to have teeth, a slightly changed model must disagree.

Tolerances. The mesh is the *inscribed* tessellation: its vertices lie on the true surface,
with `segments` edges around every full circle. Between a circle of radius r and its inscribed
polygon the largest gap is the sagitta r (1 - cos(pi / segments)), 7.5e-5 r at 256 segments
(1.2e-3 r at 64, used for the 200-hole cheese). A triangle's centre lies a little further from
a sphere than its edges' midpoints, the octahedral sphere subdivision is not uniform, and a
torus adds the gaps of its two circles, so we allow four sagittas of the largest round
primitive (its half-extent taken as r), plus float32 rounding (1e-5 of the ray length scale):
`tessellation_error`, about 3-5e-4 of the model size for unit-sized models at 256 segments.
Along a ray meeting the surface at incidence cos = |n . d| the distance between the two
surfaces grows to gap / cos, so t (in world units) must agree to tessellation_error / cos, and
facet normals must agree with the kernel's to within ~25 degrees.

Not compared, because there the exact and the tessellated solid legitimately differ by more
than the gap:
* grazing rays (|cos| < 0.2 at the kernel's hit);
* rays whose kernel or mesh answer changes discontinuously when the ray is moved sideways by
  1e-3 of the model size (silhouettes: hit/miss flips; CSG edges: t jumps or the normal there is
  grazing); near creases the normals are not compared;
* rays whose first solid interval, in the kernel or in the mesh, is thinner than 10 gaps
  (nearly touching round surfaces: the mesh can have a wall where the solid has a window);
* random models in which two primitives share surface (`shared_surfaces`), where manifold3d
  leaves slivers and sheets; zero-volume shells are dropped from every mesh (`_solid_shells`).
At least 70 % of the rays must be compared, so the test cannot pass by skipping (typically
92-97 % are), and every compared ray must agree. Membership is compared on points at least
~0.6 % of the model size from the surface, volumes within 4.5 standard errors plus the known
tessellation bias.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings

import mitsuba as mi

import mitsuba_csg as csg
from mitsuba_csg.scenes import cheese
from mitsuba_csg.formats.mesh_export import mesh_arrays
from strategies import models, seeds

pytestmark = pytest.mark.slow     # mesh references / whole benchmark scripts: the full tier only

SEGMENTS = 256
GRAZING_COS = 0.2         # rays meeting the surface at |cos| below this are not compared
RAY_JITTER = 1e-3         # sideways ray displacement for the stability test, x model size
T_JUMP = 8.0              # a t change beyond T_JUMP x jitter under that displacement is an edge
                          # (a smooth surface at |cos| >= 0.2 moves by at most 4.9 x jitter)
NORMAL_DOT = 0.9          # mesh facet normal vs kernel normal (facets tilt by ~2 pi / segments)
THIN = 10.0               # first solid intervals shorter than THIN x the gap are not compared
                          # (a wall the mesh has and the solid lacks is <= 2 gaps thick, / cos)
CREASE_DOT = 0.98         # sideways rays whose normals differ more than this straddle a crease
MIN_COMPARED = 0.7        # fraction of rays that must be compared
POINT_CLEARANCE = 1e-2    # points compared for membership lie this far (x model size) from the surface
MIN_POINTS = 0.5          # fraction of points that must be compared


# ---- Models ----

def torus_minus_box():
    box = csg.Box((1.2, 1.1, 1.0)).rotate((0.3, 0.2, 1.0), 25.0).translate((0.7, 0.5, 0.25))
    return csg.Torus(1.0, 0.35).rotate("x", 20.0) - box


def prism_and_sphere():
    return csg.Prism(6, 0.8, 2.0).rotate("y", 15.0) & csg.Sphere(1.0).translate((0.1, 0.05, 0.3))


def paper_cheese():
    return cheese(200, seed=1)


def star_mesh_minus_sphere():
    """A mesh leaf (an extruded five-pointed star, non-convex) in a tree: its triangles are
    exact in both the kernel and the reference mesh."""
    import manifold3d as m3
    angles = np.linspace(0.0, 2.0 * np.pi, 10, endpoint=False)
    radii = np.where(np.arange(10) % 2 == 0, 1.2, 0.5)
    star = m3.Manifold.extrude(m3.CrossSection([np.column_stack([radii * np.cos(angles),
                                                                  radii * np.sin(angles)]).tolist()]), 0.8)
    mesh = csg.Mesh.from_manifold(star.translate((0.0, 0.0, -0.4))).rotate((1.0, 0.3, 0.2), 35.0)
    return mesh - csg.Sphere(0.55).translate((0.2, 0.1, 0.3))


# (factory, segments): 200 holes at 256 segments would be a 3.8M-triangle mesh that takes
# manifold3d ~40 s; the holes are small (radius <= 0.24), so 64 segments keep the gap small.
FIXED = {
    "cheese": (paper_cheese, 64),
    "torus-minus-box": (torus_minus_box, SEGMENTS),
    "prism-and-sphere": (prism_and_sphere, SEGMENTS),
    "star-mesh-minus-sphere": (star_mesh_minus_sphere, SEGMENTS),
}

ROUND = (csg.Sphere, csg.Cone, csg.Torus, csg.Paraboloid, csg.Hyperboloid)   # Cylinder is a Cone; Box, Prism,
#                                                                              polyhedra are exact


# ---- Reference: the mesh in a Mitsuba scene ----

def _solid_shells(mesh):
    """(vertices, triangles, volume) of `mesh` without zero-volume debris shells.

    manifold3d can leave flat, zero-volume shells where exactly coincident surfaces cancel
    (e.g. `difference(cone, torus, torus', cone)` at 256 segments leaves six flat tetrahedra of
    area ~0.03 each). They enclose nothing, but a ray cast would hit them; we drop every
    connected shell whose |volume| is below 1e-6 x area^1.5 (a real solid has ~0.09 x area^1.5;
    void shells have negative volume and are kept).
    """
    parts = mesh.decompose() if mesh.num_tri() else []
    keep = [p for p in parts if abs(p.volume()) > 1e-6 * p.surface_area() ** 1.5]
    if len(keep) == len(parts):
        verts, faces = mesh_arrays(mesh)
        return verts, faces, mesh.volume()
    verts, faces, offset = [np.zeros((0, 3))], [np.zeros((0, 3), np.int64)], 0
    for part in keep:
        v, f = mesh_arrays(part)
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces), sum(p.volume() for p in keep)


class MeshReference:
    """A model, its manifold3d mesh, and that mesh in a Mitsuba scene."""

    def __init__(self, model, segments: int = SEGMENTS):
        self.model = model
        self.segments = segments
        self.mesh = csg.to_mesh(model, segments=segments)
        verts, faces, self.volume = _solid_shells(self.mesh)
        shapes = {"type": "scene"}
        if len(faces):
            shape = mi.Mesh("reference", len(verts), len(faces))
            params = mi.traverse(shape)
            params["vertex_positions"] = mi.Float(np.ascontiguousarray(verts.astype(np.float32).ravel()))
            params["faces"] = mi.UInt32(np.ascontiguousarray(faces.astype(np.uint32).ravel()))
            params.update()
            shapes["reference"] = shape
        self.scene = mi.load_dict(shapes)

        leaves = model.leaves()
        boxes = [leaf.bounds() for leaf in leaves]
        lo, hi = model.bounds()
        if not np.all(hi > lo):                        # empty result: use the leaves' box
            lo = np.min([b[0] for b in boxes], axis=0)
            hi = np.max([b[1] for b in boxes], axis=0)
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.centre = 0.5 * (self.lo + self.hi)
        self.size = float(np.max(self.hi - self.lo))   # "model size": longest side of its box
        self.radius = 1.5 * float(np.linalg.norm(self.hi - self.lo)) + 0.5 * self.size
        round_r = [0.5 * float(np.max(b[1] - b[0])) for leaf, b in zip(leaves, boxes) if isinstance(leaf, ROUND)]
        self.round_leaves = [leaf for leaf in leaves if isinstance(leaf, ROUND)]
        sagitta = max(round_r, default=0.0) * (1.0 - math.cos(math.pi / segments))
        self.tessellation_error = 4.0 * sagitta + 1e-5 * self.radius

    def first_hits(self, o, d):
        """(t, normal) of the first mesh hit along o + t d (d unit); t = inf on a miss."""
        ray = mi.Ray3f(mi.Point3f(*np.ascontiguousarray(o.T, np.float32)),
                       mi.Vector3f(*np.ascontiguousarray(d.T, np.float32)))
        si = self.scene.ray_intersect(ray)
        t = np.array(si.t, dtype=np.float64)
        t[~np.array(si.is_valid(), dtype=bool)] = np.inf
        return t, np.array(si.n, dtype=np.float64).T

    def contains(self, points, max_crossings: int = 64):
        """Membership by ray parity on the mesh: majority of three generic directions."""
        dirs = np.array([[0.5327, 0.6211, 0.5750], [-0.7071, 0.3152, 0.6330], [0.2291, -0.8713, 0.4340]])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        step = 1e-5 * self.size
        votes = np.zeros(len(points), dtype=np.int64)
        for d in dirs:
            o = np.array(points, dtype=np.float64)
            dd = np.broadcast_to(d, o.shape)
            crossings = np.zeros(len(o), dtype=np.int64)
            active = np.arange(len(o))
            for _ in range(max_crossings):
                if not len(active):
                    break
                t, _ = self.first_hits(o[active], dd[active])
                hit = np.isfinite(t)
                active, t = active[hit], t[hit]
                crossings[active] += 1
                o[active] += (t + step)[:, None] * d          # continue just past the hit
            assert not len(active), f"more than {max_crossings} crossings on a membership ray"
            votes += crossings % 2
        return votes >= 2


# ---- Models the mesh cannot stand in for ----

def shared_surfaces(model, samples: int = 300) -> bool:
    """Whether two primitives of `model` share a piece of surface, exactly or within ~1e-5 of
    the model size.

    Regularized CSG cancels a shared surface (`Cylinder(r, h) - Cylinder(r, h).rotate("z", 10)`
    is empty), but two tessellations out of phase leave slivers between their inscribed
    polygons, and manifold3d keeps in float64 slabs far thinner than the kernel's float32 can
    resolve (hypothesis draws two octahedra whose planes differ in the 7th digit), and even
    identical primitives can leave zero-thickness sheets (`A - (A - C)` for cones A, C comes back
    with the volume of `A & C` but 60 % more surface area): the mesh is no reference there.
    Detection: points on each leaf's surface (kernel hits on the leaf alone) stepped by +-1e-5
    of its size along the normal; if another leaf's membership differs between the two for
    more than 1 % of them, its surface passes between. Surfaces that merely cross do so for a
    fraction ~1e-5. Coplanar faces that manifold3d would handle exactly are flagged too; that
    only costs an example.
    """
    leaves = model.leaves()
    pairs = [(i, j) for i in range(len(leaves)) for j in range(len(leaves)) if i != j]
    if not pairs:
        return False
    points = {}
    for i in sorted({i for i, _ in pairs}):
        lo, hi = leaves[i].bounds()
        size = float(np.max(hi - lo))
        rng = np.random.default_rng(i)
        o = rng.normal(size=(samples, 3))
        o = 0.5 * (lo + hi) + o * (2.0 * size / np.linalg.norm(o, axis=1, keepdims=True))
        d = rng.uniform(lo, hi, size=(samples, 3)) - o
        hits = csg.trace(leaves[i], o, d)
        hit = np.isfinite(hits.t)
        p = o[hit] + hits.t[hit, None].astype(np.float64) * d[hit]
        step = 1e-5 * size * hits.normal[hit].astype(np.float64)
        points[i] = np.concatenate([p + step, p - step])
    for j in sorted({j for _, j in pairs}):
        sources = [i for i, jj in pairs if jj == j and len(points[i])]
        if not sources:
            continue
        flags = csg.contains(leaves[j], np.concatenate([points[i] for i in sources]))
        offset = 0
        for i in sources:
            half = len(points[i]) // 2
            outer, inner = flags[offset:offset + half], flags[offset + half:offset + 2 * half]
            offset += 2 * half
            if np.mean(outer != inner) > 0.01:
                return True
    return False


# ---- Rays ----

def make_rays(ref: MeshReference, seed: int, n: int):
    """Unit rays from a sphere around the model's box towards uniform points of the box."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o = ref.centre + o * (ref.radius / np.linalg.norm(o, axis=1, keepdims=True))
    aim = rng.uniform(ref.lo, ref.hi, size=(n, 3))
    d = aim - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _sideways(d):
    """Two unit vectors perpendicular to each (unit) d and to each other."""
    helper = np.where(np.abs(d[:, :1]) < 0.6, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(d, u)


def _kernel_next(model, p, d):
    hits = csg.trace(model, p, d)
    return hits.t.astype(np.float64), hits.entering


def _mesh_next(ref, p, d):
    t, normal = ref.first_hits(p, d)
    return t, np.einsum("ij,ij->i", normal, d) < 0


def _thin_first_interval(ref, o, d, t, next_hit):
    """Rays whose first solid interval (from the hit at t) is thinner than THIN x the gap.

    Where two round surfaces nearly touch, the exact solid and the inscribed mesh can differ
    in topology over a wide area: two holes of the cheese that overlap by 8e-4 leave, once both
    shrink by their sagittas, a wall of mesh material 0.013 across where the true solid has a
    window (and two nearly tangent round primitives in an intersection leave a lens that the
    mesh lacks). Sideways rays do not see that; the thickness of the first interval does. An
    exit missed because the interval is thinner than the step (2 gaps) counts as thin too.
    """
    thin = np.zeros(len(o), dtype=bool)
    hit = np.flatnonzero(np.isfinite(t))
    if not len(hit):
        return thin
    step = 2.0 * ref.tessellation_error      # past the float32 error of t (~1e-5 t on a torus)
    t2, entering = next_hit(o[hit] + (t[hit] + step)[:, None] * d[hit], d[hit])
    thin[hit] = (t2 + step < THIN * ref.tessellation_error) | (np.isfinite(t2) & entering)
    return thin


def ray_mismatches(model, ref: MeshReference, o, d, scales=None):
    """Trace `model` with the kernel and `ref`'s mesh with Embree on unit rays (o, d).

    `scales` (N,) multiplies the directions given to the kernel (its t is in units of d), so
    the kernel also sees non-unit directions. Returns (compared mask, mismatch mask, report);
    the model traced may differ from the one `ref` was meshed from (the teeth test).
    """
    n = len(o)
    if scales is None:
        scales = np.ones(n)
    u, v = _sideways(d)
    jitter = RAY_JITTER * ref.size
    origins = np.concatenate([o, o + jitter * u, o - jitter * u, o + jitter * v, o - jitter * v])
    dirs = np.tile(d * scales[:, None], (5, 1))
    hits = csg.trace(model, origins, dirs)
    t_all = hits.t.astype(np.float64).reshape(5, n) * scales        # world units
    n_all = hits.normal.astype(np.float64).reshape(5, n, 3)
    t_k, n_k = t_all[0], n_all[0]
    t_mesh, n_mesh = ref.first_hits(origins, np.tile(d, (5, 1)))
    t_mesh = t_mesh.reshape(5, n)
    t_m, n_m = t_mesh[0], n_mesh[:n]

    hit_all = np.isfinite(t_all) | np.isnan(t_all)
    cos_all = np.abs(np.einsum("kij,ij->ki", n_all, d))
    stable = np.all(hit_all == hit_all[:1], axis=0)                        # no silhouette nearby
    both = np.all(np.isfinite(t_all), axis=0)
    with np.errstate(invalid="ignore"):
        jump = np.max(np.abs(t_all - t_all[:1]), axis=0)
    stable &= ~both | (jump <= T_JUMP * jitter)                            # no CSG edge nearby
    stable &= ~both | np.all(cos_all >= GRAZING_COS, axis=0)               # not grazing, here or there
    # The same for the mesh: where two holes of the cheese meet, the inscribed polyhedra leave
    # a thin ridge of material that the true solid lacks; a ray clipping it is not compared.
    hit_mesh = np.isfinite(t_mesh)
    stable &= np.all(hit_mesh == hit_mesh[:1], axis=0)
    with np.errstate(invalid="ignore"):
        mesh_jump = np.max(np.abs(t_mesh - t_mesh[:1]), axis=0)
    stable &= ~hit_mesh[0] | (mesh_jump <= T_JUMP * jitter)
    stable &= ~_thin_first_interval(ref, o, d, t_k, lambda p, dd: _kernel_next(model, p, dd))
    stable &= ~_thin_first_interval(ref, o, d, t_m, lambda p, dd: _mesh_next(ref, p, dd))
    compared = stable | np.isnan(t_k)                                      # NaN: iteration bound hit

    hit_k, hit_m = np.isfinite(t_k), np.isfinite(t_m)
    # Near a crease (a CSG edge or a primitive's own edge, where the sideways rays see another
    # normal) the mesh may show the neighbouring face within the gap: there the distance
    # tolerance uses the smallest |cos| of the five rays, and normals are not compared.
    cos = np.maximum(np.min(cos_all, axis=0), GRAZING_COS)
    with np.errstate(invalid="ignore"):
        crease = np.any(np.einsum("kij,ij->ki", n_all, n_k) < CREASE_DOT, axis=0)
        t_bad = hit_k & hit_m & (np.abs(t_k - t_m) > ref.tessellation_error / cos)
        n_bad = hit_k & hit_m & ~crease & (np.einsum("ij,ij->i", n_k, n_m) < NORMAL_DOT)
    bad = compared & (np.isnan(t_k) | (hit_k != hit_m) | t_bad | n_bad)

    lines = []
    for i in np.flatnonzero(bad)[:5]:
        lines.append(f"  o={o[i].tolist()} d={(d[i] * scales[i]).tolist()}: kernel t={t_k[i] / scales[i]!r} "
                     f"(world {t_k[i]!r}) n={n_k[i].tolist()} prim={hits.prim[i]}; mesh t={t_m[i]!r} "
                     f"n={n_m[i].tolist()}")
    report = (f"{int(bad.sum())} of {int(compared.sum())} compared rays disagree "
              f"(tolerance {ref.tessellation_error:.2e} / cos)\n" + "\n".join(lines) + f"\nmodel: {model!r}")
    return compared, bad, report


def check_rays(model, ref: MeshReference, seed: int, n: int = 300):
    o, d = make_rays(ref, seed, n)
    scales = np.random.default_rng(seed + 1).uniform(0.5, 4.0, n)
    scales[::2] = 1.0
    compared, bad, report = ray_mismatches(model, ref, o, d, scales)
    assert compared.mean() > MIN_COMPARED, f"only {compared.mean():.0%} of the rays compared\n{report}"
    assert not bad.any(), report
    return compared


# ---- Points ----

def _random_frame(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q


def check_membership(model, ref: MeshReference, seed: int, n: int = 1500):
    """csg.contains against mesh parity on points at least ~POINT_CLEARANCE x size from the surface.

    A point counts as clear if its kernel membership does not change when it moves by
    delta = POINT_CLEARANCE x size along +-3 axes of two random frames. For a surface at
    distance e, some one of a frame's six directions has a component >= delta / sqrt(3)
    along its normal, so every point within ~0.58 delta of a smooth surface is caught, which is
    far beyond the tessellation gap.
    """
    rng = np.random.default_rng(seed)
    pad = 0.05 * (ref.hi - ref.lo) + 0.02 * ref.size
    p = rng.uniform(ref.lo - pad, ref.hi + pad, size=(n, 3))
    delta = POINT_CLEARANCE * ref.size
    offsets = np.concatenate([s * f.T for f in (_random_frame(rng), _random_frame(rng)) for s in (1, -1)]) * delta
    moved = (p[None] + offsets[:, None]).reshape(-1, 3)
    inside_all = csg.contains(model, np.concatenate([p, moved])).reshape(-1, n)
    clear = np.all(inside_all == inside_all[:1], axis=0)
    assert clear.mean() > MIN_POINTS, f"only {clear.mean():.0%} of the points are clear of the surface"
    inside_k = inside_all[0][clear]
    inside_m = ref.contains(p[clear])
    bad = np.flatnonzero(inside_k != inside_m)
    assert not len(bad), (f"membership disagrees on {len(bad)} of {int(clear.sum())} points clear of the surface; "
                          f"first: {p[clear][bad[0]].tolist()} kernel {inside_k[bad[0]]} mesh {inside_m[bad[0]]}"
                          f"\nmodel: {model!r}")
    return clear


def check_volume(model, ref: MeshReference, seed: int, n: int = 200_000):
    """Monte Carlo volume from csg.contains against the mesh volume.

    Allowed: 4.5 standard errors of the estimate, plus the tessellation bias: an inscribed
    round primitive lacks a relative ~(2 pi / segments)^2 / 6 of its volume (see mesh.py);
    we allow twice that of every round leaf's (meshed) volume, whichever sign it enters with.
    """
    rng = np.random.default_rng(seed)
    box_volume = float(np.prod(ref.hi - ref.lo))
    p = rng.uniform(ref.lo, ref.hi, size=(n, 3))
    frac = float(np.mean(csg.contains(model, p)))
    estimate = frac * box_volume
    stderr = box_volume * math.sqrt(max(frac * (1.0 - frac), 1.0 / n) / n)
    deficit = (2.0 * math.pi / ref.segments) ** 2 / 6.0
    bias = 2.0 * deficit * sum(csg.to_mesh(leaf, segments=ref.segments).volume() for leaf in ref.round_leaves)
    volume = ref.volume
    assert abs(estimate - volume) <= 4.5 * stderr + bias, (
        f"Monte Carlo volume {estimate:.5f} +- {stderr:.5f} vs mesh {volume:.5f} (bias allowance {bias:.5f})"
        f"\nmodel: {model!r}")


# ---- Tests ----

@pytest.fixture(scope="module", params=list(FIXED))
def fixed(request):
    factory, segments = FIXED[request.param]
    model = factory()
    return model, MeshReference(model, segments)


def test_fixed_models_rays(fixed):
    model, ref = fixed
    check_rays(model, ref, seed=11, n=400)


def test_fixed_models_membership(fixed):
    model, ref = fixed
    check_membership(model, ref, seed=12)


def test_fixed_models_volume(fixed):
    model, ref = fixed
    check_volume(model, ref, seed=13)


@settings(max_examples=15)
@given(models(max_leaves=6), seeds())
def test_random_models(model, seed):
    assume(not shared_surfaces(model))
    ref = MeshReference(model, SEGMENTS)
    check_rays(model, ref, seed, n=200)
    check_membership(model, ref, seed, n=600)
    check_volume(model, ref, seed, n=40_000)


@pytest.mark.parametrize("change", ["scale-torus", "move-sphere", "move-sphere-slightly"])
def test_comparison_has_teeth(change):
    """A model changed by a little must fail the ray comparison: most compared rays that hit
    the changed primitive disagree with the mesh of the unchanged model."""
    if change == "scale-torus":                  # the torus scaled by 1.02
        model = torus_minus_box()
        torus, box = model.children
        changed, moved = csg.difference(torus.scale(1.02), box), 0
    else:                                        # a dent in a box face, moved by 0.05 or 0.005
        dx = 0.05 if change == "move-sphere" else 0.005
        hole, other = csg.Sphere(0.6), csg.Sphere(0.3).translate((-1.0, -0.5, 0.0))
        model = csg.difference(csg.Box(2.0), hole.translate((0.3, 0.2, 1.0)), other)
        changed, moved = csg.difference(csg.Box(2.0), hole.translate((0.3 + dx, 0.2, 1.0)), other), 1
    ref = MeshReference(model, SEGMENTS)
    o, d = make_rays(ref, 21, 400)
    compared, bad, report = ray_mismatches(model, ref, o, d)
    assert compared.mean() > MIN_COMPARED and not bad.any(), report      # the unchanged model agrees
    compared, bad, report = ray_mismatches(changed, ref, o, d)
    on_moved = compared & (csg.trace(changed, o, d).prim == moved)
    assert on_moved.sum() >= 10
    assert bad[on_moved].mean() > 0.5, report
