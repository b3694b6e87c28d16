"""Hypothesis strategies for random CSG models and rays aimed at them.

Primitives are about unit size and placed within roughly [-2, 2]^3 so that they overlap
often. Rays and points are drawn from a seed (numpy), which keeps hypothesis fast.
"""
from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

from mitsuba_csg.model import difference, intersection, union
from mitsuba_csg.model.primitives import (Box, Cone, ConvexPolyhedron, Cylinder, Hyperboloid, Paraboloid, Prism, Sphere,
                                         Torus)


def _f(lo, hi):
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


@st.composite
def unit_vectors(draw):
    v = np.array([draw(_f(-1, 1)) for _ in range(3)])
    n = np.linalg.norm(v)
    if n < 0.2:
        v = np.array([0.0, 0.0, 1.0]) if n == 0 else v / n
    return v / np.linalg.norm(v)


@st.composite
def convex_polyhedra(draw):
    kind = draw(st.sampled_from(["random", "tetra", "octa"]))
    if kind == "tetra":
        n = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / np.sqrt(3)
    elif kind == "octa":
        n = np.array([[a, b, c] for a in (1, -1) for b in (1, -1) for c in (1, -1)], float) / np.sqrt(3)
    else:
        extra = draw(st.lists(unit_vectors(), min_size=0, max_size=6))
        n = np.vstack([np.eye(3), -np.eye(3)] + [e[None] for e in extra])
    size = draw(_f(0.4, 1.0))
    jitter = draw(st.lists(_f(0.7, 1.2), min_size=len(n), max_size=len(n)))
    d = size * np.asarray(jitter)
    return ConvexPolyhedron(np.hstack([n, d[:, None]]))


def primitives():
    """Every primitive type, about unit size, in its own frame."""
    cones = st.one_of(
        st.builds(Cone, _f(0.2, 1.0), _f(0.2, 1.0), _f(0.4, 2.0)),
        st.builds(Cone, _f(0.2, 1.0), st.just(0.0), _f(0.4, 2.0)),
        st.builds(Cone, st.just(0.0), _f(0.2, 1.0), _f(0.4, 2.0)),
    )
    tori = st.tuples(_f(0.5, 1.5), _f(0.25, 0.8)).map(lambda rr: Torus(rr[0], rr[1] * rr[0] * 0.6))
    quadrics = st.one_of(
        st.builds(Paraboloid, _f(0.0, 0.5), _f(0.6, 1.2), _f(0.4, 2.0)),
        st.builds(Paraboloid, _f(0.6, 1.2), st.just(0.0), _f(0.4, 2.0)),
        st.tuples(_f(0.0, 0.9), _f(0.3, 1.2), _f(0.4, 2.0)).map(lambda p: Hyperboloid(p[0] * p[1], p[1], p[2])),
    )
    return st.one_of(
        st.builds(Sphere, _f(0.3, 1.2)),
        st.builds(Box, st.tuples(_f(0.4, 2.0), _f(0.4, 2.0), _f(0.4, 2.0))),
        st.builds(Cylinder, _f(0.2, 1.0), _f(0.4, 2.0)),
        cones,
        tori,
        quadrics,
        st.builds(Prism, st.integers(3, 8), _f(0.3, 1.0), _f(0.4, 2.0)),
        convex_polyhedra(),
    )


@st.composite
def transformed(draw, nodes, translate=1.5):
    """A node with a random chain of transforms (possibly none)."""
    node = draw(nodes)
    for _ in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(["translate", "translate", "rotate", "rotate", "scale", "nscale",
                                     "mirror", "affine"]))
        if kind == "translate":
            node = node.translate(tuple(draw(_f(-translate, translate)) for _ in range(3)))
        elif kind == "rotate":
            axis = draw(st.one_of(st.sampled_from(["x", "y", "z"]), unit_vectors().map(tuple)))
            node = node.rotate(axis, draw(_f(-180, 180)))
        elif kind == "scale":
            node = node.scale(draw(_f(0.5, 1.5)))
        elif kind == "nscale":
            node = node.scale(tuple(draw(_f(0.5, 1.5)) for _ in range(3)))
        elif kind == "mirror":
            node = node.scale(tuple(draw(st.sampled_from([1.0, -1.0])) for _ in range(3)))
        else:
            m = np.eye(4)
            m[:3, :3] += np.array([[draw(_f(-0.35, 0.35)) for _ in range(3)] for _ in range(3)])
            m[:3, 3] = [draw(_f(-1.0, 1.0)) for _ in range(3)]
            node = node.transform(m)
    return node


def _binary(args):
    op, a, b = args
    return {"|": a | b, "&": a & b, "-": a - b}[op]


def _nary(args):
    op, xs = args
    if op == "union":
        return union(*xs)
    if op == "intersection":
        return intersection(*xs)
    return difference(xs[0], *xs[1:])


def _operations(children):
    return transformed(st.one_of(
        st.tuples(st.sampled_from(["|", "&", "-"]), children, children).map(_binary),
        st.tuples(st.sampled_from(["union", "intersection", "difference"]),
                  st.lists(children, min_size=1, max_size=4)).map(_nary),
    ), translate=0.5)


@st.composite
def unions_of_leaves(draw):
    """A union of 2-12 transformed leaves (a set for the kernel), alone, subtracted from a box,
    subtracting one, or intersected with a random tree."""
    members = union(*draw(st.lists(transformed(primitives()), min_size=2, max_size=12)))
    box = Box(tuple(draw(_f(1.5, 3.5)) for _ in range(3)))
    how = draw(st.sampled_from(["alone", "holes", "cut", "and"]))
    if how == "holes":
        return box - members
    if how == "cut":
        return members - box.scale(0.5)
    if how == "and":
        return members & draw(models(max_leaves=3))
    return members


def convex_primitives():
    """The primitives whose inside along a ray is one interval (compound members' literals)."""
    return st.one_of(
        st.builds(Sphere, _f(0.3, 1.2)),
        st.builds(Box, st.tuples(_f(0.4, 2.0), _f(0.4, 2.0), _f(0.4, 2.0))),
        st.builds(Cylinder, _f(0.2, 1.0), _f(0.4, 2.0)),
        st.builds(Cone, _f(0.2, 1.0), _f(0.0, 1.0), _f(0.4, 2.0)),
        st.builds(Prism, st.integers(3, 8), _f(0.3, 1.0), _f(0.4, 2.0)),
        convex_polyhedra(),
    )


@st.composite
def compounds(draw):
    """A small intersection of convex solids and complements of convex solids (a compound set
    member for the kernel): a solid with 1-3 cuts, cuts flush with its faces in other frames
    among them, or the intersection of two solids, or one cut by a union of two."""
    base = draw(transformed(convex_primitives(), translate=0.3))
    how = draw(st.sampled_from(["cuts", "flush", "and", "cut_by_union"]))
    if how == "cuts":
        return difference(base, *draw(st.lists(transformed(convex_primitives(), translate=0.8), min_size=1,
                                               max_size=3)))
    if how == "flush":
        w, h = draw(_f(0.8, 2.0)), draw(_f(0.3, 1.5))
        slot = Box((w / 3, w / 3, h)).rotate("z", draw(_f(-180, 180))).translate((draw(_f(-0.2, 0.2)), 0, 0))
        return draw(transformed(st.just(Box((w, w, h)) - slot), translate=0.5))
    if how == "and":
        return base & draw(transformed(convex_primitives(), translate=0.5))
    return base - (draw(transformed(convex_primitives(), translate=0.8)) |
                   draw(transformed(convex_primitives(), translate=0.8)))


@st.composite
def unions_of_compounds(draw):
    """A union of 4-8 members, compounds or convex leaves, alone, subtracted from a box, or
    subtracting one."""
    members = union(*draw(st.lists(st.one_of(compounds(), transformed(convex_primitives())), min_size=4,
                                   max_size=8)))
    how = draw(st.sampled_from(["alone", "alone", "holes", "cut"]))
    if how == "holes":
        return Box(tuple(draw(_f(1.5, 3.5)) for _ in range(3))) - members
    if how == "cut":
        return members - Box(tuple(draw(_f(0.8, 1.8)) for _ in range(3)))
    return members


@st.composite
def stacked_columns(draw):
    """2-6 columns stacked along z, each turned about its axis and shifted a little: every
    neighbour's caps coincide in the model but not in the primitives' frames. Alone, or
    drilled through a block (where a false cap would show as a wall across the tunnel)."""
    z, parts = 0.0, []
    for _ in range(draw(st.integers(2, 6))):
        h = draw(_f(0.3, 0.8))
        offset = (draw(_f(-0.1, 0.1)), draw(_f(-0.1, 0.1)))
        parts.append(draw(_column(h)).rotate("z", draw(_f(-180, 180))).translate((*offset, z + h / 2)))
        z += h
    tower = union(*parts).translate((0, 0, -z / 2))
    if draw(st.booleans()):
        tower = Box((2.0, 2.0, 0.8 * z)) - tower
    return draw(transformed(st.just(tower), translate=1.0))


def models(max_leaves: int = 8):
    """Random CSG trees (depth up to about 5) of transformed primitives."""
    return st.recursive(transformed(primitives()), _operations, max_leaves=max_leaves)


def make_rays(seed: int, n: int, radius: float = 6.0, target: float = 2.0, targets=None):
    """Rays from a sphere of `radius` towards uniform points of [-target, target]^3.

    With `targets` ((K, 3) points, e.g. the leaves' world origins), half of the rays aim at
    one of them plus a normal jitter of 0.4 instead, so that they hit small models often.
    Directions are not normalized (length between ~4 and ~9.5) half of the time.
    """
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o *= radius / np.linalg.norm(o, axis=1, keepdims=True)
    aim = rng.uniform(-target, target, size=(n, 3))
    if targets is not None and len(targets):
        targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
        pick = rng.random(n) < 0.5
        k = rng.integers(0, len(targets), size=n)
        aim = np.where(pick[:, None], targets[k] + rng.normal(scale=0.4, size=(n, 3)), aim)
    d = aim - o
    unit = rng.random(n) < 0.5
    d[unit] /= np.linalg.norm(d[unit], axis=1, keepdims=True)
    return o, d


def rays(n: int = 64, radius: float = 6.0):
    """(origins, directions) arrays of n rays aimed at [-2, 2]^3."""
    return st.integers(0, 2**32 - 1).map(lambda s: make_rays(s, n, radius))


def seeds():
    """A seed for make_rays / make_points when the targets depend on the drawn model."""
    return st.integers(0, 2**32 - 1)


def make_points(seed: int, n: int, extent: float = 3.0):
    return np.random.default_rng(seed).uniform(-extent, extent, size=(n, 3))


def points(n: int = 256, extent: float = 3.0):
    return st.integers(0, 2**32 - 1).map(lambda s: make_points(s, n, extent))


def aimed_rays(model, seed: int, n: int = 64, radius: float = 6.0):
    """make_rays with half of the rays aimed near the model's primitives (their world origins)."""
    try:                                 # the test reference, a sibling module
        from .reference import leaf_list
    except ImportError:
        from reference import leaf_list
    targets = np.array([world[:3, 3] for _, world in leaf_list(model)])
    return make_rays(seed, n, radius, targets=targets)


# ---- Touching and coincident faces ----

@st.composite
def _column(draw, height, scale=1.0):
    """A solid around the z axis spanning z in [-height/2, height/2] in its own frame."""
    kind = draw(st.sampled_from(["box", "cylinder", "cone", "prism"]))
    r = scale * draw(_f(0.3, 0.8))
    if kind == "box":
        return Box((2 * r, 2 * r * draw(_f(0.6, 1.0)), height))
    if kind == "cylinder":
        return Cylinder(r, height)
    if kind == "cone":
        return Cone(r, r * draw(_f(0.2, 1.0)), height)
    return Prism(draw(st.integers(3, 8)), r, height)


@st.composite
def touching_pairs(draw):
    """Two solids whose faces coincide in the model but lie in different primitive frames:
    stacked (one's top cap is the other's bottom), flush (a narrower solid through a wider
    one, both caps shared), or one round surface twice (a shell and its core, the core
    rotated about its own centre or axis)."""
    kind = draw(st.sampled_from(["stacked", "flush", "same_surface"]))
    op = draw(st.sampled_from(["|", "-", "&"]))
    turn = draw(_f(-180, 180))
    offset = (draw(_f(-0.2, 0.2)), draw(_f(-0.2, 0.2)))
    h1, h2 = draw(_f(0.4, 1.5)), draw(_f(0.4, 1.5))
    if kind == "stacked":
        a = draw(_column(h1)).translate((0, 0, -h1 / 2))
        b = draw(_column(h2)).rotate("z", turn).translate((*offset, h2 / 2))
    elif kind == "flush":
        a = draw(_column(h1))
        b = draw(_column(h1, scale=0.5)).rotate("z", turn).translate((*offset, 0))
    else:
        r_out, r_in = draw(_f(0.8, 1.3)), draw(_f(0.3, 0.7))
        if draw(st.booleans()):
            a = Sphere(r_out) - Sphere(r_in)
            b = Sphere(r_in).rotate(tuple(draw(unit_vectors())), turn)
        else:
            a = Cylinder(r_out, h1) - Cylinder(r_in, h1)
            b = Cylinder(r_in, h1).rotate("z", turn)
        op = "|"
    return _binary((op, a, b))


def touching_models():
    """A touching pair under a random chain of transforms, alone or inside a random tree."""
    pair = transformed(touching_pairs(), translate=1.0)
    return st.one_of(pair, st.tuples(st.sampled_from(["|", "&", "-"]), pair, models(max_leaves=3)).map(_binary),
                     st.tuples(st.sampled_from(["|", "-"]), models(max_leaves=3), pair).map(_binary))


# ---- Closed triangle meshes (mesh leaves), made by manifold3d ----

def _mesh_of(manifold):
    from mitsuba_csg.model.mesh import Mesh
    return Mesh.from_manifold(manifold)


@st.composite
def meshes(draw):
    """Convex hulls of random points, tori, extruded stars and coarse spheres and cylinders."""
    import manifold3d as m3
    kind = draw(st.sampled_from(["hull", "torus", "star", "sphere", "cylinder"]))
    seed = draw(st.integers(0, 2**31))
    rng = np.random.default_rng(seed)
    if kind == "hull":
        return _mesh_of(m3.Manifold.hull_points(rng.normal(size=(draw(st.integers(5, 16)), 3)) * 0.7))
    if kind == "torus":
        minor = draw(_f(0.15, 0.4))
        ring = m3.CrossSection.circle(minor, draw(st.integers(4, 10))).translate((draw(_f(0.5, 1.0)), 0.0))
        return _mesh_of(m3.Manifold.revolve(ring, draw(st.integers(5, 16))))
    if kind == "star":
        points = draw(st.integers(3, 7))
        inner = draw(_f(0.25, 0.7))
        angles = np.linspace(0.0, 2.0 * np.pi, 2 * points, endpoint=False)
        radii = np.where(np.arange(2 * points) % 2 == 0, 1.0, inner)
        outline = np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])
        prism = m3.Manifold.extrude(m3.CrossSection([outline.tolist()]), draw(_f(0.4, 1.5)))
        return _mesh_of(prism.translate((0.0, 0.0, -0.5)))
    if kind == "sphere":
        return _mesh_of(m3.Manifold.sphere(draw(_f(0.3, 1.1)), draw(st.integers(4, 12))))
    return _mesh_of(m3.Manifold.cylinder(draw(_f(0.4, 1.5)), draw(_f(0.2, 0.9)), -1.0, draw(st.integers(3, 10)),
                                        center=True))


def models_with_meshes(max_leaves: int = 6):
    """Random trees whose leaves are meshes or analytic primitives."""
    leaves = transformed(st.one_of(meshes(), meshes(), primitives()))
    return st.recursive(leaves, _operations, max_leaves=max_leaves)
