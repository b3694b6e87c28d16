"""Closed triangle meshes as CSG leaves: validation, the kernel against the float64 reference
(its own ray/triangle code), watertightness on edges and vertices, and a mesh cube against
`csg.Box`."""
from __future__ import annotations

import warnings

import manifold3d as m3
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import mitsuba_csg as csg
from agreement import compare
from mitsuba_csg.engine.options import TraversalOptions
from strategies import make_rays, meshes, models_with_meshes

pytestmark = pytest.mark.usefixtures("jit_variant")

CUBE_V = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
# Outward (counter-clockwise seen from outside) triangles of the cube [-1, 1]^3.
CUBE_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                   [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def cube_mesh():
    return csg.Mesh(CUBE_V, CUBE_F)


def test_cube_mesh_is_the_box():
    """Twelve triangles and csg.Box(2): same hits, classes and normals, also transformed, in
    a difference, and for rays starting inside."""
    rng = np.random.default_rng(0)
    o = rng.uniform(-3, 3, (3000, 3))
    d = rng.uniform(-1.2, 1.2, (3000, 3)) - o
    move = lambda n: n.rotate((1, 2, 3), 30).scale((1.0, 0.5, 2.0)).translate((0.1, 0.2, 0.3))  # noqa: E731
    for mesh, box in [(cube_mesh(), csg.Box(2.0)), (move(cube_mesh()), move(csg.Box(2.0))),
                      (cube_mesh() - csg.Sphere(1.2), csg.Box(2.0) - csg.Sphere(1.2)),
                      (csg.Sphere(1.3) - cube_mesh().scale(0.5), csg.Sphere(1.3) - csg.Box(1.0))]:
        a, b = csg.trace(mesh, o, d), csg.trace(box, o, d)
        assert np.array_equal(np.isfinite(a.t), np.isfinite(b.t))
        both = np.isfinite(a.t)
        assert np.allclose(a.t[both], b.t[both], rtol=1e-5, atol=1e-5)
        assert np.all(np.einsum("ij,ij->i", a.normal[both], b.normal[both]) > 0.9999)
        assert np.array_equal(a.entering, b.entering) and np.array_equal(a.prim, b.prim)
    inside = rng.uniform(-0.9, 0.9, (500, 3))
    a, b = csg.trace(cube_mesh(), inside, rng.normal(size=(500, 3))), csg.trace(csg.Box(2.0), inside,
                                                                               rng.normal(size=(500, 3)))
    assert not a.entering.any() and np.isfinite(a.t).all()


def test_rays_through_edges_and_vertices_of_a_cube():
    """Axis-aligned rays onto the cube's face diagonals (shared edges of two triangles), its
    edges and its corners: each enters at the near face and, through the solid behind, is
    seen from inside as an exit at the far face: no crossing missed or doubled."""
    g = np.linspace(-1.0, 1.0, 9)
    pts = np.array([[x, y] for x in g for y in g])
    pts = np.vstack([pts, [[s * t, t] for t in g for s in (1, -1)]])        # the diagonals
    for axis in range(3):
        for sign in (1.0, -1.0):
            o = np.zeros((len(pts), 3))
            others = [k for k in range(3) if k != axis]
            o[:, others] = pts
            o[:, axis] = -5.0 * sign
            d = np.zeros_like(o)
            d[:, axis] = sign
            hits = csg.trace(cube_mesh(), o, d)
            assert np.all(hits.t == 4.0) and hits.entering.all()
            # From inside, just past the entry: the exit at the far face.
            behind = csg.trace(cube_mesh() - csg.Box(0.5).translate((5, 5, 5)), o + 4.5 * d, d)
            assert np.allclose(behind.t, 1.5, atol=1e-6) and not behind.entering.any()


def test_rays_onto_icosphere_vertices():
    """A grid of rays aimed at every vertex of a coarse sphere mesh from outside: each hits
    the vertex's own t, and the ray continues inside to an exit (a missed or doubled crossing
    would make the exit an enter or lose it)."""
    sphere = m3.Manifold.sphere(1.0, 12)
    mesh = csg.Mesh.from_manifold(sphere)
    v = mesh.vertices
    rng = np.random.default_rng(1)
    o = v * 3.0 + rng.normal(0, 0.2, v.shape)
    d = v - o
    hits = csg.trace(mesh, o, d)
    assert np.all(np.abs(hits.t - 1.0) < 1e-5) and hits.entering.all()
    exits = csg.trace(mesh, o, d, tmin=1.0 + 1e-4)
    assert np.all(np.isfinite(exits.t)) and not exits.entering.any()


def test_validation_names_the_problem():
    with pytest.raises(csg.ModelError, match="not closed"):
        csg.Mesh(CUBE_V, CUBE_F[:-1])
    flipped = CUBE_F.copy()
    flipped[0] = flipped[0, ::-1]
    with pytest.raises(csg.ModelError, match="consistently oriented"):
        csg.Mesh(CUBE_V, flipped)
    with pytest.raises(csg.ModelError, match="vertex 3"):
        bad = CUBE_V.copy()
        bad[3, 1] = np.nan
        csg.Mesh(bad, CUBE_F)
    with pytest.raises(csg.ModelError, match="refers to vertex"):
        csg.Mesh(CUBE_V, np.where(CUBE_F == 7, 8, CUBE_F))
    with pytest.warns(csg.MeshOrientationWarning):
        inward = csg.Mesh(CUBE_V, CUBE_F[:, ::-1])
    assert np.array_equal(inward.faces, CUBE_F)
    # A degenerate triangle (repeated vertex) is dropped; the rest stays closed.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kept = csg.Mesh(CUBE_V, np.vstack([CUBE_F, [[0, 0, 1]]]))
    assert len(kept.faces) == 12


@pytest.mark.parametrize("traversal", ["default", "none"])
@given(model=models_with_meshes(max_leaves=6), seed=st.integers(0, 2**31))
def test_random_trees_with_meshes_agree_with_reference(model, seed, traversal):
    targets = [leaf.matrix[:3, 3] for leaf in model.leaves()]
    o, d = make_rays(seed, 96, targets=targets)
    options = TraversalOptions() if traversal == "default" else TraversalOptions(*[False] * 6)
    hits = csg.trace(csg.prepare(model, traversal=options), o, d)
    compare(model, hits, o, d)


@given(mesh=meshes(), seed=st.integers(0, 2**31))
def test_lone_meshes_agree_with_reference(mesh, seed):
    o, d = make_rays(seed, 128, targets=[np.zeros(3)])
    compare(mesh, csg.trace(mesh, o, d), o, d)
