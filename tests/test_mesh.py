"""Ground-truth meshes (`mitsuba_csg.formats.mesh_export`): volumes against analytic answers, transforms,
Booleans, and mesh files read back by Mitsuba's own loaders."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

import manifold3d as m3

from mitsuba_csg.model import nodes as M
from mitsuba_csg.model import primitives as P
from mitsuba_csg.errors import ModelError
from mitsuba_csg.formats.mesh_export import mesh_arrays, read_stl, save_mesh, to_mesh

SEG = 128
REL = 0.01     # tessellation error at 128 segments is ~0.05 %; 1 % leaves room


def signed_volume(verts, faces):
    """Divergence-theorem volume with numpy: positive iff triangles face outwards."""
    a, b, c = (verts[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def cone_volume(r1, r2, h):
    return math.pi * h / 3.0 * (r1 * r1 + r1 * r2 + r2 * r2)


def lens_volume(r, d):
    """Intersection of two balls of radius r whose centres are d apart (0 <= d <= 2r)."""
    return math.pi * (4.0 * r + d) * (2.0 * r - d) ** 2 / 12.0


OCTAHEDRON = [[sx, sy, sz, 1.0] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]

PRIMITIVES = [
    ("sphere", P.Sphere(1.3), 4.0 / 3.0 * math.pi * 1.3 ** 3),
    ("box", P.Box((1.0, 2.0, 3.5)), 1.0 * 2.0 * 3.5),
    ("box-scalar", P.Box(2.0), 8.0),
    ("cylinder", P.Cylinder(0.7, 2.5), math.pi * 0.7 ** 2 * 2.5),
    ("cone", P.Cone(1.0, 0.0, 2.0), cone_volume(1.0, 0.0, 2.0)),
    ("cone-apex-bottom", P.Cone(0.0, 0.5, 1.0), cone_volume(0.0, 0.5, 1.0)),
    ("frustum", P.Cone(1.5, 0.5, 3.0), cone_volume(1.5, 0.5, 3.0)),
    ("torus", P.Torus(2.0, 0.5), 2.0 * math.pi ** 2 * 2.0 * 0.5 ** 2),
    ("hex-prism", P.Prism(6, 0.8, 1.5), 2.0 * math.sqrt(3.0) * 0.8 ** 2 * 1.5),
    ("square-prism", P.Prism(4, 1.0, 1.0), 4.0),
    ("octahedron", P.ConvexPolyhedron(OCTAHEDRON), 4.0 / 3.0),
    # The paraboloid's side bulges past the cone through its rims: rotated, its box is not
    # the cap circles' (a bound taken from them once culled rays that hit it).
    ("paraboloid", P.Paraboloid(0.4, 1.5, 2.0), math.pi * 2.0 * (0.4 ** 2 + 1.5 ** 2) / 2.0),
    ("paraboloid-tip-rotated", P.Paraboloid(1.5, 0.0, 2.0).rotate((1, 0.3, 0), 65).translate((3, 0, 0)),
     math.pi * 2.0 * 1.5 ** 2 / 2.0),
    ("hyperboloid", P.Hyperboloid(0.5, 1.2, 3.0), math.pi * 3.0 * (0.5 ** 2 + (1.2 ** 2 - 0.5 ** 2) / 3.0)),
    ("double-cone-rotated", P.Hyperboloid(0.0, 1.0, 2.0).rotate((0, 1, 1), 40), math.pi * 2.0 / 3.0),
]


# ---- Primitives ----

@pytest.mark.parametrize("name,prim,volume", PRIMITIVES, ids=[p[0] for p in PRIMITIVES])
def test_primitive_volume(name, prim, volume):
    mesh = to_mesh(prim, segments=SEG)
    assert mesh.status() == m3.Error.NoError
    assert mesh.volume() == pytest.approx(volume, rel=REL)
    verts, faces = mesh_arrays(mesh)
    assert signed_volume(verts, faces) == pytest.approx(mesh.volume(), rel=1e-9)
    # Round primitives are inscribed polyhedra: never larger than the solid. (A hyperboloid's
    # profile bulges inward, rho(z) being convex: its chords lie outside, a little larger.)
    if not name.startswith(("hyperboloid", "double-cone")):
        assert mesh.volume() <= volume * (1.0 + 1e-9)


@pytest.mark.parametrize("name,prim,volume", PRIMITIVES, ids=[p[0] for p in PRIMITIVES])
def test_primitive_box_matches_model_bounds(name, prim, volume):
    lo, hi = prim.bounds()
    mesh_lo, mesh_hi = np.split(np.array(to_mesh(prim, segments=SEG).bounding_box()), 2)
    # Inscribed tessellations can fall short of the true box by the sagitta, never exceed it.
    extent = np.max(hi - lo)
    assert np.all(mesh_lo >= lo - 1e-9 * extent) and np.all(mesh_hi <= hi + 1e-9 * extent)
    np.testing.assert_allclose(mesh_lo, lo, atol=1e-3 * extent)
    np.testing.assert_allclose(mesh_hi, hi, atol=1e-3 * extent)


def test_tessellation_converges():
    exact = 4.0 / 3.0 * math.pi
    errors = [exact - to_mesh(P.Sphere(1.0), segments=n).volume() for n in (16, 32, 64)]
    assert errors[0] > errors[1] > errors[2] > 0


def test_cone_orientation_and_extents():
    verts, _ = mesh_arrays(to_mesh(P.Cone(radius_bottom=1.0, radius_top=0.25, height=2.0), segments=64))
    radial = np.hypot(verts[:, 0], verts[:, 1])
    bottom, top = verts[:, 2] < -1.0 + 1e-9, verts[:, 2] > 1.0 - 1e-9
    assert bottom.any() and top.any() and np.all(bottom | top)
    assert radial[bottom].max() == pytest.approx(1.0)
    assert radial[top].max() == pytest.approx(0.25)


def test_torus_lies_around_z():
    verts, _ = mesh_arrays(to_mesh(P.Torus(3.0, 1.0), segments=64))
    tube = np.hypot(np.hypot(verts[:, 0], verts[:, 1]) - 3.0, verts[:, 2])
    np.testing.assert_allclose(tube, 1.0, rtol=1e-9)       # vertices on the true surface
    assert to_mesh(P.Torus(3.0, 1.0), segments=16).genus() == 1


def test_prism_faces_plus_x():
    # A side's normal is +x: x extent is the apothem, y extent the circumradius.
    lo, hi = np.split(np.array(to_mesh(P.Prism(6, 1.0, 4.0)).bounding_box()), 2)
    np.testing.assert_allclose(hi, [1.0, 2.0 / math.sqrt(3.0), 2.0], rtol=1e-9)
    np.testing.assert_allclose(lo, -hi, rtol=1e-9)


# ---- Transforms ----

def test_nonuniform_scale_multiplies_volume_by_det():
    base = to_mesh(P.Torus(1.0, 0.3), segments=64).volume()
    scaled = to_mesh(P.Torus(1.0, 0.3).scale((2.0, 0.5, 3.0)), segments=64).volume()
    assert scaled == pytest.approx(3.0 * base, rel=1e-9)


@pytest.mark.parametrize("factors", [(-1.0, 1.0, 1.0), (1.0, -2.0, 1.0), (-1.0, -1.0, -1.0), (-1.0, -1.0, 1.0)])
def test_mirror_keeps_volume_positive(factors):
    prim = P.Cone(1.0, 0.2, 2.0).translate((0.5, 0.2, 0.1))
    base = to_mesh(prim, segments=64)
    mirrored = to_mesh(prim.scale(factors), segments=64)
    assert mirrored.status() == m3.Error.NoError
    det = abs(float(np.prod(factors)))
    assert mirrored.volume() == pytest.approx(det * base.volume(), rel=1e-9)
    verts, faces = mesh_arrays(mirrored)
    assert signed_volume(verts, faces) == pytest.approx(det * base.volume(), rel=1e-9)


def test_mirrored_boolean_stays_valid():
    solid = P.Box(2.0) - P.Sphere(0.8).translate((1.0, 0.0, 0.0))
    base = to_mesh(solid, segments=64).volume()
    mirrored = to_mesh(solid.scale((-1.0, 1.0, 1.0)) | P.Sphere(0.1).translate((5, 0, 0)), segments=64)
    small = to_mesh(P.Sphere(0.1), segments=64).volume()
    assert mirrored.volume() == pytest.approx(base + small, rel=1e-9)


def test_general_affine_transform():
    shear = np.array([[1.0, 0.5, 0.0, 1.0], [0.0, 2.0, 0.3, -2.0], [0.2, 0.0, 1.5, 0.5], [0, 0, 0, 1]])
    mesh = to_mesh(P.Box((1.0, 2.0, 3.0)).transform(shear), segments=16)
    assert mesh.volume() == pytest.approx(6.0 * abs(np.linalg.det(shear[:3, :3])), rel=1e-9)


def test_transforms_compose_parent_after_child():
    # translate then rotate 90 deg about z: (2, 0, 0) -> (0, 2, 0)
    lo, hi = np.split(np.array(to_mesh(P.Box(1.0).translate((2.0, 0.0, 0.0)).rotate("z", 90)).bounding_box()), 2)
    np.testing.assert_allclose((lo + hi) / 2, [0.0, 2.0, 0.0], atol=1e-9)
    # an operation's matrix applies to all its operands, after theirs
    tree = M.union(P.Box(1.0).translate((1.0, 0.0, 0.0)), P.Box(1.0)).scale((1.0, 3.0, 1.0)).translate((0, 0, 5))
    lo, hi = np.split(np.array(to_mesh(tree).bounding_box()), 2)
    np.testing.assert_allclose(lo, [-0.5, -1.5, 4.5], atol=1e-9)
    np.testing.assert_allclose(hi, [1.5, 1.5, 5.5], atol=1e-9)
    assert to_mesh(tree).volume() == pytest.approx(6.0, rel=1e-9)


# ---- Booleans ----

def test_box_minus_inner_sphere():
    mesh = to_mesh(P.Box(2.0) - P.Sphere(0.6), segments=SEG)
    assert mesh.volume() == pytest.approx(8.0 - 4.0 / 3.0 * math.pi * 0.6 ** 3, rel=REL)
    assert len(mesh.decompose()) == 2        # the outer box and the inward-facing cavity


def test_union_of_disjoint_is_sum():
    parts = [P.Sphere(0.5), P.Box(1.0).translate((3, 0, 0)), P.Torus(1.0, 0.2).translate((0, 5, 0))]
    exact = 4.0 / 3.0 * math.pi * 0.125 + 1.0 + 2.0 * math.pi ** 2 * 0.04
    single = sum(to_mesh(p, segments=SEG).volume() for p in parts)
    mesh = to_mesh(M.union(*parts), segments=SEG)
    assert mesh.volume() == pytest.approx(single, rel=1e-9)
    assert mesh.volume() == pytest.approx(exact, rel=REL)


@pytest.mark.parametrize("d", [0.3, 1.0, 1.7])
def test_intersection_of_spheres_is_lens(d):
    lens = P.Sphere(1.0) & P.Sphere(1.0).translate((d, 0.0, 0.0))
    assert to_mesh(lens, segments=SEG).volume() == pytest.approx(lens_volume(1.0, d), rel=REL)


def test_difference_forms_agree():
    a = P.Box((4.0, 1.0, 1.0))
    b = P.Cylinder(0.3, 2.0).translate((-1.0, 0.0, 0.0))
    c = P.Sphere(0.4).translate((1.0, 0.0, 0.0))
    exact = 4.0 - math.pi * 0.09 * 1.0 - 4.0 / 3.0 * math.pi * 0.064
    volumes = [to_mesh(t, segments=SEG).volume()
               for t in (M.difference(a, b, c), (a - b) - c, a - (b | c), a - b - c.scale(1.0))]
    assert volumes == pytest.approx([volumes[0]] * 4, rel=1e-9)
    assert volumes[0] == pytest.approx(exact, rel=REL)


def test_nested_difference_is_not_flattened_wrongly():
    # a - (b - c): c is added back inside b's hole, not subtracted
    a, b, c = P.Box(4.0), P.Box(2.0), P.Box(1.0)
    assert to_mesh(a - (b - c)).volume() == pytest.approx(64.0 - 8.0 + 1.0, rel=1e-9)
    # (a | b) & c with transforms on the inner operation
    inner = (P.Box(1.0) | P.Box(1.0).translate((1.0, 0, 0))).translate((-0.5, 0, 0))
    assert to_mesh(inner & P.Box((1.0, 5.0, 5.0))).volume() == pytest.approx(1.0, rel=1e-9)


def test_single_operand_and_empty_result():
    assert to_mesh(M.union(P.Box(1.0))).volume() == pytest.approx(1.0)
    assert to_mesh(M.difference(P.Box(1.0))).volume() == pytest.approx(1.0)
    empty = to_mesh(P.Sphere(1.0) & P.Sphere(1.0).translate((5.0, 0.0, 0.0)))
    assert empty.is_empty() and empty.status() == m3.Error.NoError


def test_hundred_sphere_union_is_fast():
    centres = np.random.default_rng(7).uniform(-3.0, 3.0, (100, 3))
    tree = M.union(*[P.Sphere(0.4).translate(c) for c in centres])
    start = time.perf_counter()
    mesh = to_mesh(tree, segments=32)
    volume = mesh.volume()                   # forces the lazy Boolean
    assert time.perf_counter() - start < 5.0
    one = to_mesh(P.Sphere(0.4), segments=32).volume()
    assert one < volume < 100 * one
    assert mesh.status() == m3.Error.NoError


def test_deep_binary_chain_is_iterative():
    # 1500 nested binary operators: deeper than Python's recursion limit
    tree = P.Box(1.0)
    for i in range(1, 1500):
        tree = tree | P.Box(1.0).translate((2.0 * i, 0.0, 0.0))
    assert to_mesh(tree).volume() == pytest.approx(1500.0, rel=1e-9)
    holed = P.Box((3000.0, 1.0, 1.0))
    for i in range(1500):
        holed = holed - P.Box(0.5).translate((2.0 * i - 1499.0, 0.0, 0.0))
    assert to_mesh(holed).volume() == pytest.approx(3000.0 - 1500 * 0.125, rel=1e-9)


def test_errors():
    with pytest.raises(ModelError, match="segments"):
        to_mesh(P.Sphere(1.0), segments=2)
    with pytest.raises(ModelError, match="segments"):
        to_mesh(P.Sphere(1.0), segments=12.5)
    with pytest.raises(ModelError, match="CSG model"):
        to_mesh("sphere")


# ---- Files ----

@pytest.fixture(scope="module")
def mi():
    import mitsuba as mitsuba                # importing mitsuba_csg has selected a JIT variant
    assert mitsuba.variant() is not None
    return mitsuba


@pytest.fixture(scope="module")
def solid_mesh():
    solid = P.Box((2.0, 2.0, 1.0)) - P.Sphere(0.8).translate((1.0, 1.0, 0.5)) | P.Torus(1.0, 0.2).translate((0, 0, 1))
    return to_mesh(solid, segments=24)


def _sorted_rows(a):
    return a[np.lexsort(a.T[::-1])]


@pytest.mark.parametrize("ext", ["ply", "obj", "PLY"])
def test_mitsuba_loads_mesh_file(mi, solid_mesh, tmp_path, ext):
    path = save_mesh(solid_mesh, tmp_path / f"solid.{ext}")
    shape = mi.load_dict({"type": ext.lower(), "filename": str(path), "face_normals": True})
    verts, faces = mesh_arrays(solid_mesh)
    assert shape.vertex_count() == len(verts)
    assert shape.face_count() == len(faces)
    bbox = shape.bbox()
    lo, hi = np.split(np.array(solid_mesh.bounding_box()), 2)
    np.testing.assert_allclose(np.array(bbox.min).ravel(), lo, atol=1e-6)
    np.testing.assert_allclose(np.array(bbox.max).ravel(), hi, atol=1e-6)
    loaded = np.array(mi.traverse(shape)["vertex_positions"], dtype=np.float64).reshape(-1, 3)
    np.testing.assert_allclose(_sorted_rows(loaded), _sorted_rows(verts.astype(np.float32).astype(np.float64)),
                               atol=1e-6)
    index = np.array(mi.traverse(shape)["faces"], dtype=np.int64).reshape(-1, 3)
    assert signed_volume(loaded, index) == pytest.approx(solid_mesh.volume(), rel=1e-5)


def test_mitsuba_traces_saved_model(mi, tmp_path):
    path = save_mesh(P.Box(2.0) - P.Sphere(0.9).translate((0.0, 0.0, -1.0)), tmp_path / "cut.ply", segments=64)
    scene = mi.load_dict({"type": "scene", "cut": {"type": "ply", "filename": str(path)}})
    ray = mi.Ray3f(mi.Point3f(0.0, 0.0, -5.0), mi.Vector3f(0.0, 0.0, 1.0))
    si = scene.ray_intersect(ray)
    # the ray passes through the spherical dent at z = -1 + 0.9 = -0.1
    assert float(np.array(si.t).ravel()[0]) == pytest.approx(4.9, abs=1e-3)


def test_stl_round_trip(solid_mesh, tmp_path):
    path = save_mesh(solid_mesh, tmp_path / "solid.stl")
    verts, faces = mesh_arrays(solid_mesh)
    data = path.read_bytes()
    assert len(data) == 84 + 50 * len(faces)
    assert not data.startswith(b"solid")
    back_verts, back_faces = read_stl(path)
    assert len(back_faces) == len(faces) and len(back_verts) == len(verts)
    rebuilt = m3.Manifold(m3.Mesh(back_verts.astype(np.float32), back_faces.astype(np.uint32)))
    assert rebuilt.status() == m3.Error.NoError
    assert rebuilt.volume() == pytest.approx(solid_mesh.volume(), rel=1e-5)
    # facet normals point outwards and agree with the winding
    rows = np.frombuffer(data, np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")]), len(faces), 84)
    tri = rows["v"].astype(np.float64)
    winding = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.einsum("ij,ij->i", winding, rows["n"]) > 0)


def test_save_model_directly_and_sphere_normals_outward(tmp_path):
    path = save_mesh(P.Sphere(2.0).translate((1.0, 2.0, 3.0)), tmp_path / "ball.stl", segments=32)
    verts, faces = read_stl(path)
    centroid = verts[faces].mean(axis=1)
    rows = np.frombuffer(path.read_bytes(), np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")]),
                         len(faces), 84)
    assert np.all(np.einsum("ij,ij->i", centroid - [1.0, 2.0, 3.0], rows["n"]) > 0)


def test_save_errors(tmp_path, solid_mesh):
    with pytest.raises(ModelError, match=r"\.ply, \.obj, \.stl"):
        save_mesh(solid_mesh, tmp_path / "solid.gltf")
    with pytest.raises(ModelError, match="no extension"):
        save_mesh(solid_mesh, tmp_path / "solid")
    with pytest.raises(ModelError, match="Manifold or a CSG model"):
        save_mesh(np.zeros((3, 3)), tmp_path / "x.ply")


def test_mirrored_booleans_keep_their_volume():
    """A Boolean under a mirroring transform is meshed unmirrored, then mirrored (manifold3d's
    Booleans of mirrored operands were off by 5 % on a real OpenSCAD model): same volume, and
    the points of the mirror image inside."""
    from mitsuba_csg.model.mesh import Mesh
    star = to_mesh(P.Cylinder(1.0, 3.0), segments=7)
    verts, faces = mesh_arrays(star)
    part = M.difference(P.Box((4.0, 4.0, 2.0)), P.Cone(1.5, 0.5, 3.0).translate((1.0, 0.5, 0.0)),
                        Mesh(verts, faces).translate((-1.0, -0.5, 0.2)),
                        P.Sphere(0.8).translate((0.0, 1.6, 0.8)))
    mirror = np.diag([1.0, -1.0, 1.0, 1.0])
    mirror[:3, :3] = mirror[:3, :3] @ np.array([[1, 0, 0], [0, 0.5, -0.8660254], [0, 0.8660254, 0.5]])
    plain, mirrored = to_mesh(part, 64), to_mesh(part.transform(mirror), 64)
    assert mirrored.volume() == pytest.approx(plain.volume(), rel=1e-7)
    v, _ = mesh_arrays(plain)
    w, _ = mesh_arrays(mirrored)
    np.testing.assert_allclose(np.sort((v @ mirror[:3, :3].T)[:, 0]), np.sort(w[:, 0]), atol=1e-5)
