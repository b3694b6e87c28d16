"""The Mitsuba plugins against Mitsuba's own integrators on manifold3d meshes of the same model."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import drjit as dr
import mitsuba as mi
import manifold3d
import numpy as np
import pytest

import mitsuba_csg as csg
from mitsuba_csg.formats.mesh_export import save_mesh
from mitsuba_csg.scenes import cheese

ROOT = Path(__file__).resolve().parents[1]
LOOK = mi.ScalarTransform4f().look_at([4, -6, 3], [0, 0, 0], [0, 0, 1])
MODEL = csg.Box(2.0) - csg.Sphere(1.25) | csg.Torus(0.8, 0.2).translate((0, 0, 1.4))


def scene_dict(shape: dict, integrator: dict, width=48, height=32, spp=64, extra=None):
    d = {
        "type": "scene",
        "integrator": integrator,
        "sensor": {"type": "perspective", "fov": 40, "to_world": LOOK,
                   "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "object": shape,
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -1]).scale(6)},
        "sky": {"type": "constant", "radiance": 0.3},
        "sun": {"type": "directional", "direction": [-1, 1.5, -2], "irradiance": 2.5},
        "lamp": {"type": "point", "position": [2, -3, 4], "intensity": 20.0},
    }
    d.update(extra or {})
    return d


BSDF = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.6, 0.2]}}


def csg_shape(model, **kw):
    return {"type": "csg", "model": csg.model_ref(model), "bsdf": BSDF, **kw}


def mesh_shape(model, tmp_path, name="mesh.ply"):
    path = tmp_path / name
    save_mesh(csg.to_mesh(model, segments=256), path)
    return {"type": "ply", "filename": str(path), "face_normals": True, "bsdf": BSDF}


def render(d, seed=0, spp=None):
    return np.array(mi.render(mi.load_dict(d), seed=seed, spp=spp or 0))


def rel_mse(a, b):
    return float(np.mean((a - b) ** 2) / np.mean(b ** 2))


def test_scalar_variants_are_refused():
    code = "import mitsuba as mi; mi.set_variant('scalar_rgb'); import mitsuba_csg"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode != 0
    assert "JIT variant" in run.stderr and "llvm_ad_rgb" in run.stderr
    # only variants the installed Mitsuba ships are offered (the pip wheel has no llvm_rgb)
    offered = run.stderr.rsplit("JIT variant (", 1)[1].split(")", 1)[0].split(", ")
    assert set(offered) <= set(mi.variants()) and "scalar_rgb" not in offered


def test_other_variants_and_variant_switch():
    code = ("import mitsuba as mi; mi.set_variant('llvm_ad_mono'); import mitsuba_csg as csg;"
            "d = {'type': 'scene', 'integrator': {'type': 'csg_path'}, 's': {'type': 'csg', 'model': csg.model_ref(csg.Sphere(1))},"
            " 'e': {'type': 'constant'}, 'c': {'type': 'perspective', 'film': {'type': 'hdrfilm', 'width': 8, 'height': 8},"
            " 'to_world': mi.ScalarTransform4f().look_at([0, -5, 0], [0, 0, 0], [0, 0, 1])}};"
            "a = mi.render(mi.load_dict(d), spp=4);"
            "mi.set_variant('llvm_ad_spectral'); csg.register_plugins(); b = mi.render(mi.load_dict(d), spp=4);"
            "print(float(a.numpy().mean()) > 0.1, float(b.numpy().mean()) > 0.1)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().endswith("True True")


@pytest.mark.slow
def test_csg_path_start_hints_change_no_pixel(monkeypatch):
    """csg_path tells the traversal which CSG primitive each bounce and shadow ray leaves
    (`SceneCSG.start_of`, a hint that saves work inside holes); without the hints the image
    is the same bit for bit."""
    from mitsuba_csg.plugins import csg_common
    scene = mi.load_dict(scene_dict(csg_shape(cheese(12)), {"type": "csg_path", "max_depth": 4},
                                    width=32, height=24, spp=4))
    hinted = np.array(mi.render(scene, seed=1))
    monkeypatch.setattr(csg_common.SceneCSG, "start_of",
                        lambda self, hit, prim, shape: dr.full(mi.UInt32, 0xFFFFFFFF, dr.width(hit)))
    assert np.array_equal(hinted, np.array(mi.render(scene, seed=1)))


def test_csg_path_compacted_paths_render_the_same_light(monkeypatch):
    """csg_path gathers the paths still going on after depth COMPACT_DEPTH into fewer lanes,
    with a sampler of their own. In a closed room lit by a lamp, where much of the light
    comes after that depth, against the same integrator without compaction (Mitsuba's own
    loop over the whole wavefront): the difference is noise (relative MSE within 1.5x of two
    uncompacted renders with different seeds), and the image without the deeper light is not."""
    from mitsuba_csg.plugins import csg_path
    room = csg.Box(3.0) - csg.Box(2.6) | csg.Sphere(0.4).translate((0.5, 0.6, -1.1))
    inside = {"sensor": {"type": "perspective", "fov": 70,
                         "to_world": mi.ScalarTransform4f().look_at([1.0, -1.0, 0.6], [-1, 1, -0.6], [0, 0, 1]),
                         "film": {"type": "hdrfilm", "width": 32, "height": 24, "rfilter": {"type": "box"}},
                         "sampler": {"type": "independent", "sample_count": 128}},
              "lamp": {"type": "point", "position": [0.0, 0.0, 1.0], "intensity": 3.0}}
    d = scene_dict(csg_shape(room), {"type": "csg_path", "max_depth": 8}, extra=inside)
    for name in ("sky", "sun"):
        del d[name]
    compacted = np.array(mi.render(mi.load_dict(d), seed=3))
    first_bounces = dict(d, integrator={"type": "csg_path", "max_depth": csg_path.COMPACT_DEPTH + 1})
    shallow = np.array(mi.render(mi.load_dict(first_bounces), seed=3))
    monkeypatch.setattr(csg_path, "_may_compact", lambda max_depth, lanes: False)
    plain_a = np.array(mi.render(mi.load_dict(d), seed=1))
    plain_b = np.array(mi.render(mi.load_dict(d), seed=2))
    noise = rel_mse(plain_a, plain_b)
    assert rel_mse(compacted, plain_a) < 1.5 * noise + 1e-5, (rel_mse(compacted, plain_a), noise)
    assert rel_mse(shallow, plain_a) > 4 * noise, (rel_mse(shallow, plain_a), noise)


def test_csg_path_compaction_keeps_every_path_once():
    """The compacted lanes are the active paths, each once, ordered by their next rays."""
    from mitsuba_csg.plugins import csg_path
    scene = mi.load_dict(scene_dict(csg_shape(cheese(12)), {"type": "csg_path"}, width=8, height=8, spp=1))
    rng = np.random.default_rng(5)
    n = 500
    active = rng.random(n) < 0.3
    o = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    paths = csg_path.Paths.begin(mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(*d.T)), mi.Bool(active))
    lanes = np.array(csg_path._coherent_lanes(csg_path.SceneCSG(scene), paths))
    assert sorted(lanes.tolist()) == np.flatnonzero(active).tolist()


def test_csg_path_matches_path_on_the_mesh(tmp_path):
    """Metric: relative MSE = mean((a - b)^2) / mean(b^2) at equal spp. Two mesh renders with
    different seeds set the noise floor; the CSG render must be within 1.5x of it (plus the
    tessellation bias), and a slightly different model must not."""
    integrator = {"type": "csg_path", "max_depth": 4}
    reference = {"type": "path", "max_depth": 4}
    spp = 256
    mesh_a = render(scene_dict(mesh_shape(MODEL, tmp_path), reference, spp=spp), seed=1)
    mesh_b = render(scene_dict(mesh_shape(MODEL, tmp_path), reference, spp=spp), seed=2)
    noise = rel_mse(mesh_a, mesh_b)
    threshold = 1.5 * noise + 1e-4
    ours = rel_mse(render(scene_dict(csg_shape(MODEL), integrator, spp=spp), seed=3), mesh_a)
    assert ours < threshold, (ours, noise)
    changed = csg.Box(2.0) - csg.Sphere(1.32) | csg.Torus(0.8, 0.2).translate((0, 0, 1.4))
    theirs = rel_mse(render(scene_dict(csg_shape(changed), integrator, spp=spp), seed=3), mesh_a)
    assert theirs > 2 * threshold, (theirs, noise)


@pytest.mark.slow
def test_all_emitter_kinds_match_path_on_the_mesh(tmp_path):
    """Area light on a mesh, spot light and an environment map, same metric as above."""
    env = np.ascontiguousarray(np.ones((16, 32, 3), np.float32) * np.linspace(0.1, 1.0, 16, dtype=np.float32)[:, None, None])
    mi.Bitmap(env).write(str(tmp_path / "sky.exr"))
    lights = {
        "sun": {"type": "spot", "to_world": mi.ScalarTransform4f().look_at([3, -3, 4], [0, 0, 0], [0, 0, 1]),
                "intensity": 40.0, "cutoff_angle": 30},
        "sky": {"type": "envmap", "filename": str(tmp_path / "sky.exr"), "scale": 0.5},
        "lamp": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([-2, 2, 3]).scale(0.7),
                 "emitter": {"type": "area", "radiance": 8.0}},
    }
    spp = 256
    mesh = mesh_shape(MODEL, tmp_path)
    mesh_a = render(scene_dict(mesh, {"type": "path", "max_depth": 3}, spp=spp, extra=lights), seed=1)
    mesh_b = render(scene_dict(mesh, {"type": "path", "max_depth": 3}, spp=spp, extra=lights), seed=2)
    noise = rel_mse(mesh_a, mesh_b)
    ours = rel_mse(render(scene_dict(csg_shape(MODEL), {"type": "csg_path", "max_depth": 3}, spp=spp, extra=lights),
                          seed=3), mesh_a)
    assert ours < 1.5 * noise + 1e-4, (ours, noise)


def _silhouette_free(depth, tol=0.05):
    """Pixels whose 3x3 neighbourhood is all hit and has no depth jump (not within a pixel of an edge)."""
    hit = depth > 0
    ok = hit.copy()
    h, w = depth.shape
    pad = np.pad(depth, 1, mode="edge")
    padhit = np.pad(hit, 1, mode="constant")
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            nb = pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
            near = (np.abs(nb - depth) < tol * depth) if np.isfinite(tol) else True
            ok &= padhit[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] & near
    return ok


@pytest.mark.slow
def test_aov_depth_matches_mitsuba_depth(tmp_path):
    aov = render(scene_dict(csg_shape(MODEL), {"type": "csg_aov", "aovs": "dd:depth,prim:prim_index"},
                            width=64, height=48, spp=1), seed=5)
    ref = render(scene_dict(mesh_shape(MODEL, tmp_path), {"type": "depth"}, width=64, height=48, spp=1), seed=5)
    ours, theirs = aov[..., 3], ref[..., 0]
    ok = _silhouette_free(ours) & _silhouette_free(theirs)
    assert ok.mean() > 0.3
    np.testing.assert_allclose(ours[ok], theirs[ok], rtol=2e-3)
    # hit / miss agree everywhere except within a pixel of a silhouette (of either image)
    hit_ours, hit_theirs = ours > 0, theirs > 0
    near_edge = ~(_erode(hit_ours) | _erode(~hit_ours)) | ~(_erode(hit_theirs) | _erode(~hit_theirs))
    assert np.all((hit_ours == hit_theirs) | near_edge)
    assert np.mean(hit_ours != hit_theirs) < 0.05


def test_scene_file_loads_and_renders(tmp_path):
    scene = mi.load_file(str(ROOT / "scenes" / "cheese.xml"), spp=4, width=64, height=36)
    image = mi.render(scene)
    out = tmp_path / "cheese.exr"
    mi.Bitmap(image).write(str(out))
    back = np.array(mi.Bitmap(str(out)))
    assert back.shape == (36, 64, 3)
    assert np.isfinite(back).all() and back.mean() > 0.05
    cheese = [s for s in scene.shapes() if "CSGShape" in str(s)]
    assert len(cheese) == 1 and "primitives=501" in str(cheese[0])


def test_materials_per_primitive():
    red = {"type": "diffuse", "id": "red", "reflectance": {"type": "rgb", "value": [0.9, 0.05, 0.05]}}
    blue = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.05, 0.05, 0.9]}}
    model = csg.Sphere(1.0).translate((-1.2, 0, 0)).with_material("red") | csg.Sphere(1.0).translate((1.2, 0, 0))
    shape = {"type": "csg", "model": csg.model_ref(model), "default": blue, "red": red}
    d = scene_dict(shape, {"type": "csg_aov", "aovs": "prim:prim_index,dd:depth",
                           "color": {"type": "csg_path", "max_depth": 2}}, width=64, height=32, spp=16)
    del d["floor"]
    image = render(d)
    prim, hit = image[..., 3], _silhouette_free(image[..., 4], tol=np.inf)
    rgb = image[..., :3]
    left = hit & (prim < 0.01)        # hits on primitive 0 (red)
    right = hit & (prim > 0.99)       # hits on primitive 1 (default: blue)
    assert left.sum() > 20 and right.sum() > 20
    assert np.all(rgb[left][:, 0] > rgb[left][:, 2])
    assert np.all(rgb[right][:, 2] > rgb[right][:, 0])


def test_several_csg_shapes_with_to_world_and_mixed_meshes(tmp_path):
    a = csg.Sphere(0.8) - csg.Box(0.8).translate((0.6, 0, 0))
    shapes = {"first": csg_shape(a, to_world=mi.ScalarTransform4f().translate([-1.5, 0, 0])),
              "second": csg_shape(a, to_world=mi.ScalarTransform4f().translate([1.5, 0, 0]).rotate([0, 0, 1], 90))}
    d = scene_dict(shapes.pop("first"), {"type": "csg_aov", "aovs": "dd:depth,s:shape_index"},
                   width=64, height=32, spp=1, extra=shapes)
    image = render(d, seed=1)
    scene = mi.load_dict(d)
    names = [str(s).split("[")[0] for s in scene.shapes()]
    shape_index = image[..., 4]
    hit = image[..., 3] > 0
    seen = set(np.unique(np.round(shape_index[hit])).astype(int))
    csg_ids = {i for i, n in enumerate(names) if n == "CSGShape"}
    assert csg_ids <= seen                       # both CSG shapes visible
    assert len(seen - csg_ids) >= 1              # and the floor mesh
    # the scene's bounds include both CSG shapes (their proxies span the model boxes)
    bbox = scene.bbox()
    assert bbox.min.x < -2.2 and bbox.max.x > 2.2


def _colour(rgb):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}


# Three interpenetrating solids, one with a per-primitive material: traced as one group.
SEVERAL = {
    "object": (MODEL, {"bsdf": _colour([0.8, 0.6, 0.2])}),
    "ball": (csg.Sphere(0.9).translate((0.9, 0.4, 0.6)) - csg.Box(0.9).translate((1.3, 0.0, 1.0)),
             {"bsdf": _colour([0.1, 0.3, 0.9])}),
    "rod": (csg.Cylinder(0.35, 3.2).rotate((1, 0, 0), 70).translate((-0.6, -0.7, 0.2))
            | csg.Box(0.5).translate((-0.6, -1.9, 0.6)).with_material("red"),
            {"bsdf": _colour([0.2, 0.8, 0.2]), "red": {**_colour([0.9, 0.1, 0.1]), "id": "red"}}),
}


def _several(tmp_path, integrator, colours=None, spp=256, only=None, floor=True):
    """The SEVERAL scene (or the solids named in `only`) with csg shapes (`integrator` a csg_*
    one) or with their meshes (in `tmp_path`)."""
    shapes = {}
    for name, (model, bsdfs) in SEVERAL.items():
        if only is not None and name not in only:
            continue
        bsdfs = dict(bsdfs, **(colours or {}).get(name, {}))
        if integrator["type"].startswith("csg"):
            shapes[name] = {"type": "csg", "model": csg.model_ref(model), **bsdfs}
        else:                                   # Mitsuba's own: a mesh per material of the model
            for material in {leaf.material for leaf in model.leaves()}:
                part = model if len(bsdfs) == 1 else _material_part(model, material)
                shape = mesh_shape(part, tmp_path, f"{name}_{material}.ply")
                shape["bsdf"] = bsdfs.get(material, bsdfs["bsdf"])
                shapes[f"{name}_{material}"] = shape
    first = shapes.pop(next(iter(shapes)))
    d = scene_dict(first, integrator, spp=spp, extra=shapes)
    if not floor:
        del d["floor"]
    return d


def _material_part(model, material):
    """The part of `model`'s surface made of `material`'s primitives, as a solid: the whole
    model intersected with (or minus) the primitives of that material."""
    if material is not None:
        return model & csg.union(*[leaf for leaf in model.leaves() if leaf.material == material])
    return model - csg.union(*[leaf for leaf in model.leaves() if leaf.material is not None])


def test_several_csg_shapes_match_path_on_their_meshes(tmp_path):
    """Interpenetrating csg shapes, traced as one group, against Mitsuba's path on their
    meshes (the metric of test_csg_path_matches_path_on_the_mesh): each hit takes its own
    shape's BSDFs (per-primitive materials included); with two shapes' colours swapped the
    image must differ."""
    integrator, reference = {"type": "csg_path", "max_depth": 4}, {"type": "path", "max_depth": 4}
    mesh_a = render(_several(tmp_path, reference), seed=1)
    mesh_b = render(_several(tmp_path, reference), seed=2)
    noise = rel_mse(mesh_a, mesh_b)
    threshold = 1.5 * noise + 1e-4
    ours = rel_mse(render(_several(tmp_path, integrator), seed=3), mesh_a)
    assert ours < threshold, (ours, noise)
    swapped = {"ball": {"bsdf": SEVERAL["rod"][1]["bsdf"]}, "rod": {"bsdf": SEVERAL["ball"][1]["bsdf"]}}
    theirs = rel_mse(render(_several(tmp_path, integrator, swapped), seed=3), mesh_a)
    assert theirs > 2 * threshold, (theirs, noise)


def test_several_csg_shapes_give_mitsubas_depth_and_shape_index(tmp_path):
    """Depth and shape index of the group against Mitsuba's depth on the meshes, and against
    the nearest of the solids' depths rendered one solid at a time."""
    ours = render(_several(tmp_path, {"type": "csg_aov", "aovs": "dd:depth,s:shape_index"}, spp=1, floor=False),
                  seed=5)
    theirs = render(_several(tmp_path, {"type": "depth"}, spp=1, floor=False), seed=5)
    ok = _silhouette_free(ours[..., 3]) & _silhouette_free(theirs[..., 0])
    assert np.sum(ok & (ours[..., 3] > 0)) > 200
    np.testing.assert_allclose(ours[..., 3][ok], theirs[..., 0][ok], rtol=2e-3)
    # Which solid is nearest, per pixel: Mitsuba's depth of each solid's meshes alone.
    alone = []
    for name in SEVERAL:
        depth = render(_several(tmp_path, {"type": "depth"}, spp=1, only=[name], floor=False), seed=5)[..., 0]
        alone.append(np.where(depth > 0, depth, np.inf))
    nearest = np.array(list(SEVERAL))[np.argmin(alone, axis=0)]
    scene = mi.load_dict(_several(tmp_path, {"type": "csg_aov", "aovs": "dd:depth"}, spp=1, floor=False))
    names = np.array([s.id() for s in scene.shapes()])
    hit = ok & (ours[..., 3] > 0)
    got = names[np.round(ours[..., 4][hit]).astype(int)]
    assert np.mean(got == nearest[hit]) > 0.99
    assert {"object", "ball", "rod"} <= set(got)


def test_area_emitter_on_a_csg_shape_is_refused():
    shape = {**csg_shape(csg.Sphere(1.0)), "emitter": {"type": "area", "radiance": 1.0}}
    with pytest.raises(Exception, match="cannot be an area emitter"):
        mi.load_dict({"type": "scene", "s": shape})


def test_traverse_exposes_primitives_and_update_moves_them():
    scene = mi.load_dict(scene_dict(csg_shape(csg.Sphere(1.0)), {"type": "csg_aov", "aovs": "dd:depth"}, spp=1))
    params = mi.traverse(scene)
    key = "object.primitive_to_world"
    assert key in params and not params.flags(key) & mi.ParamFlags.NonDifferentiable
    w = np.array(params[key])
    np.testing.assert_allclose(w.reshape(3, 4), np.hstack([np.eye(3), np.zeros((3, 1))]), atol=1e-7)
    w[3] += 3.0                                   # move the sphere by +3 in x
    params[key] = mi.Float(w)
    params.update()
    assert scene.bbox().max.x >= 4.0 - 1e-4
    shape = [s for s in scene.shapes() if "CSGShape" in str(s)][0]
    hits = csg.trace(shape.prepared, [[3.0, 0, -5]], [[0, 0, 1.0]])
    assert hits.t[0] == pytest.approx(4.0, rel=1e-5)



def test_an_update_keeps_the_traversal_options_and_relists_the_curves():
    """A parameter update prepares the moved model as it was prepared (traversal options,
    iteration bound); the boundary terms' curves are listed once per prepared tree, again
    after an update (they follow the new geometry)."""
    from mitsuba_csg.engine.options import TraversalOptions
    from mitsuba_csg.plugins import csg_edges
    scene = mi.load_dict(scene_dict(csg_shape(csg.Box(2.0) - csg.Sphere(1.2)), {"type": "csg_aov", "aovs": "dd:depth"},
                                    spp=1))
    shape = [s for s in scene.shapes() if "CSGShape" in str(s)][0]
    options = TraversalOptions(sets=False, near_first=False)
    shape.prepared = csg.prepare(shape.prepared.flat, traversal=options, max_iterations=5000)
    curves = csg_edges.curves_of(shape)
    assert csg_edges.curves_of(shape) is curves
    params = mi.traverse(scene)
    w = np.array(params["object.primitive_to_world"])
    w[12 + 3] += 5.0                              # move the sphere (the second primitive) out of the box
    params["object.primitive_to_world"] = mi.Float(w)
    params.update()
    assert shape.prepared.tree.options is options and shape.prepared.max_iterations == 5000
    moved = csg_edges.curves_of(shape)
    # Listed for the new geometry: the sphere no longer meets the box's faces.
    assert moved is not curves and moved.count < curves.count
    assert not np.any(moved.kind == csg_edges.SPHERE_PLANE) and np.any(curves.kind == csg_edges.SPHERE_PLANE)


# ---- Gradients ----

def _erode(mask):
    out = mask.copy()
    h, w = mask.shape
    pad = np.pad(mask, 1)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out &= pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
    return out


def _gradient_check(model, weights, light, eps=0.01, spp=64, key="primitive_to_world", others=None, moved="object"):
    """Forward-mode csg_prb derivative vs central differences with the same seed, on pixels
    whose visible primitive is the same at -eps, 0 and +eps and which are not within a pixel
    of an edge or a face's edge (visibility derivatives are not computed). `others`: more
    csg shapes by name; `moved`: the shape whose parameter moves."""
    def d(integrator):
        extra = {"sun": light, **{name: csg_shape(m) for name, m in (others or {}).items()}}
        return scene_dict(csg_shape(model), integrator, width=64, height=48, spp=spp, extra=extra)

    scene = mi.load_dict({k: v for k, v in d({"type": "csg_prb", "max_depth": 2}).items()
                          if k not in ("floor", "lamp", "sky")})
    params = mi.traverse(scene)
    key = f"{moved}.{key}"
    # to_world is a transform: its 4x4 matrix moves along `weights` (16 values, row-major).
    as_value = ((lambda v: mi.Transform4f(mi.Matrix4f(*[dr.gather(mi.Float, v, i) for i in range(16)])))
                if key.endswith(".to_world") else (lambda v: v))
    base = (np.array(params[key].matrix)[..., 0].ravel() if key.endswith(".to_world") else np.array(params[key]))
    h = mi.Float(0.0)
    dr.enable_grad(h)
    params[key] = as_value(mi.Float(base) + h * mi.Float(weights))
    params.update()
    image = mi.render(scene, params, spp=spp, seed=1)
    dr.forward(h)
    grad = dr.grad(image).numpy()

    def at(v, sc):
        p = mi.traverse(sc)
        p[key] = as_value(mi.Float(base + v * weights))
        p.update()
        return np.array(mi.render(sc, spp=spp, seed=1))
    fd = (at(eps, scene) - at(-eps, scene)) / (2 * eps)
    aov_scene = mi.load_dict({k: v for k, v in d({"type": "csg_aov", "aovs": "prim:prim_index,dd:depth,nn:sh_normal"})
                              .items() if k not in ("floor", "lamp", "sky")})
    aovs = [at(v, aov_scene) for v in (-eps, 0.0, eps)]
    same = np.all([np.abs(a[..., 3] - aovs[1][..., 3]) < 1e-6 for a in aovs], axis=0)
    hit = np.all([a[..., 4] > 0 for a in aovs], axis=0)

    def unit(n):
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    # The same face too (a box's edges move within one primitive): a pixel across an edge
    # averages two normals, shorter than 1, and a face keeps its normal within 0.01 rad or so.
    same_face = np.all([(np.linalg.norm(a[..., 5:8], axis=-1) > 0.98)
                        & (np.sum(unit(a[..., 5:8]) * unit(aovs[1][..., 5:8]), axis=-1) > 0.99) for a in aovs], axis=0)
    interior = _erode(same & hit) & same_face
    assert interior.sum() > 100
    g, f = grad[interior], fd[interior]
    return g, f


@pytest.mark.slow
@pytest.mark.parametrize("case", ["position", "radius", "hole_position", "mesh_hole_position", "named_translation",
                                  "named_scale", "named_rotation", "named_to_world"])
def test_prb_interior_derivatives_match_finite_differences(case):
    """Tolerance: the summed interior derivative within 2% and a per-pixel correlation > 0.98.
    The named_* cases move the same primitives through the shape's named parameters."""
    point = {"type": "point", "position": [3, -4, 5], "intensity": 60.0}
    named = {"named_translation": (csg.Sphere(1.0), "primitive_translation", [1.0, 0.0, 0.0]),
             "named_scale": (csg.Sphere(1.0), "primitive_scale", [1.0]),
             # about z: a tilt moves the light's terminator and shadow edges across faces
             "named_rotation": (csg.Box(1.6), "primitive_rotation", [0.0, 0.0, 1.0]),
             "named_to_world": (csg.Box(1.6), "to_world", None)}
    if case in named:
        model, key, w = named[case]
        if w is None:           # the whole shape's to_world: turn about z (its first two rows)
            w = [0.0, -1.0, 0, 0, 1.0, 0.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]
        g, f = _gradient_check(model, np.array(w, np.float32), point, key=key)
        assert abs(g.sum() - f.sum()) < 0.02 * abs(f.sum()), (g.sum(), f.sum())
        assert np.corrcoef(g.ravel(), f.ravel())[0, 1] > 0.98
        return
    if case == "position":       # a sphere's centre x: entry 3 of its 3x4 to_world rows
        model, w = csg.Sphere(1.0), np.eye(1, 12, 3).ravel()
    elif case == "radius":       # a sphere's radius: the diagonal of the linear part
        model, w = csg.Sphere(1.0), np.array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], float)
    else:                        # the subtracted sphere's centre x (primitive 1, entry 12 + 3)
        # A mesh leaf with large faces: moving it moves no facet edges across the pixels,
        # whose derivatives the finite differences would include and csg_prb does not.
        cube = csg.Mesh.from_manifold(manifold3d.Manifold.cube([2.2, 2.2, 2.2], center=True)).rotate((1, 1, 1), 30)
        hole = csg.Sphere(1.25) if case == "hole_position" else cube
        model, w = csg.Box(2.0) - hole, np.eye(1, 24, 15).ravel()
        point = {"type": "point", "position": [4, -6, 3], "intensity": 60.0}
    g, f = _gradient_check(model, w.astype(np.float32), point)
    assert abs(g.sum() - f.sum()) < 0.02 * abs(f.sum()), (g.sum(), f.sum())
    assert np.corrcoef(g.ravel(), f.ravel())[0, 1] > 0.98


@pytest.mark.slow
@pytest.mark.parametrize("moved", ["object", "other"])
def test_prb_derivatives_with_several_csg_shapes(moved):
    """Two interpenetrating csg shapes traced as one group: moving a primitive of either (the
    second's primitives come after the first's in the group) gives the interior derivative
    of that shape alone, as central differences do."""
    # A light at the camera: no shadow edge is in view (shadows of one shape moving over the
    # other are visibility changes, which csg_prb does not differentiate and FD includes).
    point = {"type": "point", "position": [4, -6, 3], "intensity": 60.0}
    other = csg.Box(1.4).translate((0.9, 0.6, -0.2)) - csg.Sphere(0.7).translate((0.9, 0.0, 0.2))
    # the x of the first primitive's centre: the sphere of `object`, the box of `other`
    g, f = _gradient_check(csg.Sphere(1.0), np.eye(1, 12 if moved == "object" else 24, 3).ravel().astype(np.float32),
                           point, others={"other": other}, moved=moved)
    assert abs(g.sum() - f.sum()) < 0.02 * abs(f.sum()), (g.sum(), f.sum())
    assert np.corrcoef(g.ravel(), f.ravel())[0, 1] > 0.98


def test_named_parameters_move_primitives_as_the_model_api_does():
    """primitive_translation / _rotation / _scale and to_world give the matrices that the same
    placement written with the model API (translate, rotate, a larger radius) gives."""
    model = csg.Box(2.0) - csg.Sphere(0.8).translate((0.5, 0, 0))
    scene = mi.load_dict({"type": "scene", "obj": {"type": "csg", "model": csg.model_ref(model), "optimize": False,
                                                   "to_world": mi.ScalarTransform4f().translate([0, 0, 1])}})
    params = mi.traverse(scene)
    np.testing.assert_allclose(np.array(params["obj.primitive_translation"]), [0, 0, 0, 0.5, 0, 0])
    params["obj.primitive_translation"] = mi.Float([0, 0, 0, 0.2, 0.3, 0.4])
    params["obj.primitive_rotation"] = mi.Float([0, 0, np.pi / 2, 0, 0, 0])
    params["obj.primitive_scale"] = mi.Float([1.0, 1.5])
    params.update()
    expected = (csg.Box(2.0).rotate((0, 0, 1), 90) - csg.Sphere(1.2).translate((0.2, 0.3, 0.4))).translate((0, 0, 1))
    reference = csg.prepare(expected, optimize=False).flat.prim_to_world[:, :3, :]
    got = np.array(params["obj.primitive_to_world"]).reshape(-1, 3, 4)
    np.testing.assert_allclose(got, reference, atol=1e-6)
    shape = scene.shapes()[0]
    hits = csg.trace_rays(shape.prepared, mi.Point3f(0.2, 0.3, 5.0), mi.Vector3f(0, 0, -1))
    # Down through the hole's centre: the box's top (z = 2) lies inside the enlarged hole, whose
    # bottom is at z = 1.4 - 1.2.
    assert float(hits.t[0]) == pytest.approx(5.0 - 0.2, abs=1e-5)
    # to_world moves everything; a write of primitive_to_world re-bases the named parameters.
    params["obj.to_world"] = mi.Transform4f().translate([0, 0, 3])
    params.update()
    got = np.array(params["obj.primitive_to_world"]).reshape(-1, 3, 4)
    np.testing.assert_allclose(got[:, :, 3], reference[:, :, 3] + [0, 0, 2], atol=1e-6)
    params["obj.primitive_to_world"] = mi.Float(reference.astype(np.float32).ravel())
    params.update()
    np.testing.assert_allclose(np.array(params["obj.primitive_scale"]), [1, 1])
    np.testing.assert_allclose(np.array(params["obj.primitive_translation"]), [0, 0, -2, 0.2, 0.3, -1.6], atol=1e-6)
    params["obj.primitive_scale"] = mi.Float([1.0, -1.0])
    with pytest.raises(csg.CSGError, match="primitive_scale must be positive"):
        params.update()


@pytest.mark.slow
def test_inverse_rendering_recovers_a_radius():
    """Adam on a sphere's radius, from 0.8 to the target 1.0. The sphere fills the view, so
    every pixel is interior (visibility derivatives are not computed, see csg_prb)."""
    def d(model):
        return {"type": "scene", "integrator": {"type": "csg_prb", "max_depth": 2},
                "sensor": {"type": "perspective", "fov": 14,
                           "to_world": mi.ScalarTransform4f().look_at([0, -4, 0], [0, 0, 0], [0, 0, 1]),
                           "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}},
                           "sampler": {"type": "independent", "sample_count": 8}},
                "object": csg_shape(model),
                "lamp": {"type": "point", "position": [2.0, -3.0, 1.5], "intensity": 20.0}}

    target = mi.render(mi.load_dict(d(csg.Sphere(1.0))), spp=256, seed=7)
    scene = mi.load_dict(d(csg.Sphere(1.0)))
    params = mi.traverse(scene)
    # The sphere's own scale (its radius, relative to the loaded 1.0): as in docs/plugins.md.
    key = "object.primitive_scale"
    opt = mi.ad.Adam(lr=0.02)
    opt["radius"] = mi.Float(0.8)
    for it in range(60):
        if it == 40:
            opt.set_learning_rate(0.005)
        params[key] = opt["radius"]
        params.update()
        image = mi.render(scene, params, spp=32, seed=it)
        dr.backward(dr.mean(dr.square(image - target), axis=None))
        opt.step()
    rows = np.array(params["object.primitive_to_world"]).reshape(3, 4)
    np.testing.assert_allclose(rows[:, :3], rows[0, 0] * np.eye(3), atol=1e-6)    # still a sphere
    assert abs(opt["radius"][0] - 1.0) < 0.03, opt["radius"]


@pytest.mark.parametrize("integrator", ["csg_path", "csg_prb"])
def test_integrator_details_match_mitsubas_path(integrator):
    """As Mitsuba's `path`: max_depth 0 renders nothing; an environment emitter makes every
    camera ray valid (alpha 1; it averaged 0.43); hide_emitters hides the sky seen directly
    (csg_prb ignored it) and makes alpha the coverage; a fractional max_depth is refused."""
    shape = {"type": "csg", "model": csg.model_ref(csg.Sphere(1.0)), "bsdf": BSDF}

    def render(**options):
        d = {"type": "scene", "integrator": {"type": integrator, **options},
             "sensor": {"type": "perspective", "fov": 40, "to_world": LOOK,
                        "film": {"type": "hdrfilm", "width": 24, "height": 16, "pixel_format": "rgba",
                                 "rfilter": {"type": "box"}},
                        "sampler": {"type": "independent", "sample_count": 4}},
             "object": shape, "sky": {"type": "constant", "radiance": 0.5}}
        return np.array(mi.render(mi.load_dict(d)))

    reference = {"type": "path"}
    mitsuba = np.array(mi.render(mi.load_dict({
        "type": "scene", "integrator": reference,
        "sensor": {"type": "perspective", "fov": 40, "to_world": LOOK,
                   "film": {"type": "hdrfilm", "width": 24, "height": 16, "pixel_format": "rgba",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "object": {"type": "sphere", "bsdf": BSDF}, "sky": {"type": "constant", "radiance": 0.5}})))
    image = render()
    assert np.all(image[..., 3] == 1.0) and np.all(mitsuba[..., 3] == 1.0)
    assert np.all(render(max_depth=0) == 0.0)
    hidden = render(hide_emitters=True)
    sky = hidden[..., 3] == 0
    assert 0.2 < sky.mean() < 0.95 and np.all(hidden[sky][:, :3] == 0.0)
    assert np.all(image[sky][:, :3] > 0.4)
    with pytest.raises(Exception, match="max_depth"):
        render(max_depth=2.5)


def test_shape_shows_what_it_holds_and_warns_of_unused_bsdfs():
    """print(shape) gives bounds and the material -> BSDF map; a second BSDF that matches no
    material is reported, not dropped silently; mi.traverse lists what moves the model, not
    the proxy mesh's own buffers."""
    model = (csg.Box(2.0).with_material("steel") - csg.Sphere(1.25)).with_material("steel")
    with pytest.warns(UserWarning, match="BSDF 'other' is not used: it matches no material of the model \\(steel\\)"):
        shape = mi.load_dict({"type": "csg", "model": csg.model_ref(model),
                              "steel": {"type": "conductor", "id": "steel"},
                              "first": {"type": "diffuse", "id": "first"},
                              "other": {"type": "plastic", "id": "other"}})
    text = str(shape)
    assert "bounds=[[-1.0" in text and "steel -> " in text and "default bsdf='first'" in text, text
    keys = set(mi.traverse(shape).keys())
    assert "primitive_to_world" in keys and not keys & {"vertex_positions", "faces", "face_csgproxy"}, keys


@pytest.mark.parametrize("integrator", ["csg_path", "csg_prb", "csg_aov"])
def test_media_are_refused_not_ignored(integrator, capfd):
    """A medium inside a glass sphere next to a CSG shape rendered as if absent."""
    scene = mi.load_dict({"type": "scene", "integrator": {"type": integrator},
                          "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
                          "fog_ball": {"type": "sphere", "id": "fog_ball", "bsdf": {"type": "dielectric"},
                                       "interior": {"type": "homogeneous"}},
                          "model": {"type": "csg", "model": csg.model_ref(csg.Box(1.0))}})
    with pytest.raises(Exception) as info:
        mi.render(scene)
    # Mitsuba prints the integrator's own error and raises its render operation's failure
    shown = str(info.value) + str(info.value.__cause__) + capfd.readouterr().err
    assert "only csg_volpath traces participating media, and shape 'fog_ball'" in shown, shown[-500:]
    foggy_camera = mi.load_dict({"type": "scene", "integrator": {"type": integrator},
                                 "sensor": {"type": "perspective", "id": "cam", "medium": {"type": "homogeneous"},
                                            "film": {"type": "hdrfilm", "width": 8, "height": 8}},
                                 "model": {"type": "csg", "model": csg.model_ref(csg.Box(1.0))}})
    with pytest.raises(Exception) as info:
        mi.render(foggy_camera)
    shown = str(info.value) + str(info.value.__cause__) + capfd.readouterr().err
    assert "sensor 'cam' sits in a medium" in shown, shown[-500:]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["absorbing_glass", "fog"])
def test_csg_volpath_matches_volpath_on_the_mesh(case, tmp_path):
    """A glass CSG solid with an absorbing interior, and the scene in fog (the camera inside it,
    a null-BSDF cube holding it): csg_volpath on the CSG against Mitsuba's volpath on the
    manifold3d mesh, the metric of test_csg_path_matches_path_on_the_mesh."""
    mesh = {**mesh_shape(MODEL, tmp_path), "face_normals": True}
    if case == "absorbing_glass":
        interior = {"bsdf": {"type": "dielectric"}, "interior": {"type": "homogeneous", "albedo": 0.0, "sigma_t": 1.5}}
        shape_csg, shape_mesh, extra = {**csg_shape(MODEL), **interior}, {**mesh, **interior}, {}
    else:
        extra = {"fog": {"type": "homogeneous", "id": "fog", "albedo": 0.8, "sigma_t": 0.12},
                 "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": {"type": "ref", "id": "fog"},
                         "to_world": mi.ScalarTransform4f().scale(12)}}
        shape_csg, shape_mesh = csg_shape(MODEL), mesh

    def d(shape, integrator):
        scene = scene_dict(shape, {"type": integrator, "max_depth": 8}, spp=256, extra=extra)
        if case == "fog":
            scene["sensor"]["medium"] = {"type": "ref", "id": "fog"}
            del scene["lamp"]      # a point light inside the fog: fine for both, but slow to converge
        return scene
    mesh_a = render(d(shape_mesh, "volpath"), seed=1)
    mesh_b = render(d(shape_mesh, "volpath"), seed=2)
    noise = rel_mse(mesh_a, mesh_b)
    ours = rel_mse(render(d(shape_csg, "csg_volpath"), seed=3), mesh_a)
    assert ours < 1.5 * noise + 1e-4, (ours, noise)
    without = dict(d(shape_mesh, "volpath"))
    without["object"] = {k: v for k, v in shape_mesh.items() if k != "interior"}
    if case == "fog":
        del without["box"]
        without["sensor"] = {k: v for k, v in without["sensor"].items() if k != "medium"}
    assert rel_mse(render(without, seed=3), mesh_a) > 4 * noise        # the medium shows


def _aov_image(shape: dict, integrator: dict, to_world=LOOK, size=(48, 32)):
    return np.array(mi.render(mi.load_dict({
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "perspective", "fov": 40, "to_world": to_world,
                   "film": {"type": "hdrfilm", "width": size[0], "height": size[1], "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "object": shape}), spp=1))


@pytest.mark.parametrize("model, mitsuba_shape", [
    (csg.Sphere(1.2), {"type": "sphere", "radius": 1.2}),
    (csg.Sphere(1.0).scale(1.3).rotate((1, 1, 0), 35).translate((0.2, -0.1, 0.3)),
     {"type": "sphere", "to_world": mi.ScalarTransform4f().translate([0.2, -0.1, 0.3])
      .rotate([0.5 ** 0.5, 0.5 ** 0.5, 0], 35).scale(1.3)}),      # Mitsuba takes a unit axis
    (csg.Cylinder(0.8, 2.0).rotate("y", 20), {"type": "cylinder", "radius": 0.8, "p0": [0, 0, -1], "p1": [0, 0, 1],
                                              "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], 20)}),
    (csg.Box(2.0), {"type": "cube"}),
    (csg.Box((1.0, 2.0, 1.4)).rotate("z", 30), {"type": "cube", "to_world": mi.ScalarTransform4f().rotate([0, 0, 1], 30)
                                                .scale([0.5, 1.0, 0.7])}),
    (csg.Box(1.5).rotate((1, 0, 1), 120), {"type": "cube", "to_world": mi.ScalarTransform4f()     # the other faces
                                           .rotate([0.5 ** 0.5, 0, 0.5 ** 0.5], 120).scale(0.75)}),
])
def test_uv_and_tangents_match_mitsubas_own_shapes(model, mitsuba_shape):
    """uv was (0, 0) on every CSG hit and dp_du missing: spheres and cylinder sides now carry
    Mitsuba's own parameterization (compared pixel by pixel through the AOV integrators; the
    cylinder's caps, which Mitsuba's open cylinder lacks, are left out by depth)."""
    ours = _aov_image({"type": "csg", "model": csg.model_ref(model)}, {"type": "csg_aov", "aovs": "uv:uv,t:dp_du,d:depth"})
    theirs = _aov_image(mitsuba_shape, {"type": "aov", "aovs": "uv:uv,t:dp_du,d:depth"})
    ours = ours[..., 3:]                                 # csg_aov puts the (black) colour first
    same = (ours[..., 5] > 0) & (np.abs(ours[..., 5] - theirs[..., 5]) < 1e-3 * theirs[..., 5])
    assert same.mean() > 0.1
    du = np.abs(ours[..., 0] - theirs[..., 0])[same]
    assert np.percentile(np.minimum(du, 1 - du), 99) < 1e-4            # u wraps at the seam
    assert np.percentile(np.abs(ours[..., 1] - theirs[..., 1])[same], 99) < 1e-4
    # 99 %: a pixel on a cylinder's rim may see our cap where Mitsuba's open tube shows its side
    tangent_error = np.abs(ours[..., 2:5] - theirs[..., 2:5]).max(-1)[same]
    assert np.percentile(tangent_error, 99) < 1e-3 * np.abs(theirs[..., 2:5]).max()


def test_every_primitive_has_a_parameterization():
    """Box faces, caps, cones, tori, prisms, quadrics and mesh triangles: uv defined and in
    range where it is normalized, dp_du tangent to the surface (orthogonal to the normal)."""
    import manifold3d
    parts = [csg.Box((1.0, 1.4, 0.8)).translate((-3, 0, 0)), csg.Cone(0.6, 0.2, 1.2).translate((-1.5, 0, 0)),
             csg.Torus(0.6, 0.2).rotate("x", 60), csg.Prism(6, 0.5, 1.0).translate((1.5, 0, 0)),
             csg.Paraboloid(0.2, 0.6, 1.0).translate((3, 0, 0)),
             csg.Mesh.from_manifold(manifold3d.Manifold.sphere(0.5, 16)).translate((0, 0, 1.6))]
    image = _aov_image({"type": "csg", "model": csg.model_ref(csg.union(parts))},
                       {"type": "csg_aov", "aovs": "uv:uv,t:dp_du,n:sh_normal,d:depth"},
                       to_world=mi.ScalarTransform4f().look_at([1, -9, 4], [0, 0, 0.3], [0, 0, 1]), size=(96, 48))
    hit = image[..., 3 + 8] > 0
    uv, tangent, normal = image[..., 3:5][hit], image[..., 5:8][hit], image[..., 8:11][hit]
    assert hit.mean() > 0.1 and np.all(np.isfinite(uv)) and np.all(np.isfinite(tangent))
    length = np.linalg.norm(tangent, axis=1)
    assert np.percentile(length, 1) > 1e-3
    assert np.percentile(np.abs((tangent * normal).sum(1)) / length, 99) < 1e-3


def _torus_mesh(major: float, minor: float, n_phi: int = 256, n_psi: int = 128):
    """A torus mesh carrying the CSG torus's documented parameterization (u = phi / 2 pi,
    v = psi / 2 pi, psi measured from the outer equator towards +z), seams duplicated."""
    phi = np.linspace(0, 2 * np.pi, n_phi + 1)
    psi = np.linspace(0, 2 * np.pi, n_psi + 1)
    P, S = np.meshgrid(phi, psi, indexing="ij")
    ring = major + minor * np.cos(S)
    positions = np.stack([ring * np.cos(P), ring * np.sin(P), minor * np.sin(S)], -1).reshape(-1, 3)
    uv = np.stack([P / (2 * np.pi), S / (2 * np.pi)], -1).reshape(-1, 2)
    index = np.arange((n_phi + 1) * (n_psi + 1)).reshape(n_phi + 1, n_psi + 1)
    a, b, c, d = index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    mesh = mi.Mesh("torus", len(positions), len(faces), has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params["vertex_texcoords"] = mi.Float(uv.astype(np.float32).ravel())
    params.update()
    mesh.recompute_vertex_normals()
    return mesh


SIDE_VIEW = mi.ScalarTransform4f().look_at([0, -6, 0], [0, 0, 0], [0, 0, 1])    # a cylinder's caps edge-on


@pytest.mark.slow
@pytest.mark.parametrize("bsdf_name", ["texture", "normal_map", "anisotropic"])
@pytest.mark.parametrize("shape_name", ["sphere", "cylinder", "box", "torus"])
def test_textures_normal_maps_and_anisotropy_match_mitsubas_shapes(shape_name, bsdf_name, tmp_path):
    """A checkerboard texture, a normal map and an anisotropic conductor render on CSG spheres,
    cylinders, boxes and tori as on Mitsuba's `sphere`, `cylinder`, `cube` and a torus mesh
    carrying the CSG torus's parameterization: the error against a 2048-spp render of Mitsuba's
    shape is within 1.5x that of Mitsuba's own render at the same 512 spp (at 16 or 64 spp
    the sun's anisotropic highlights make the ratio swing from 0.5 to 2.3 between seeds)."""
    u, v = np.meshgrid(np.linspace(0, 1, 64), np.linspace(0, 1, 64))
    normals = np.stack([0.4 * np.sin(2 * np.pi * 6 * u), 0.4 * np.cos(2 * np.pi * 3 * v), np.ones_like(u)], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    mi.Bitmap(np.ascontiguousarray((0.5 * normals + 0.5).astype(np.float32))).write(str(tmp_path / "normals.exr"))
    bsdf = {"texture": {"type": "diffuse", "reflectance": {
                "type": "checkerboard", "color0": {"type": "rgb", "value": 0.1}, "color1": {"type": "rgb", "value": 0.9},
                "to_uv": mi.ScalarTransform4f().scale([8, 4, 1])}},
            "normal_map": {"type": "normalmap", "normalmap": {"type": "bitmap", "raw": True,
                                                              "filename": str(tmp_path / "normals.exr")},
                           "bsdf": {"type": "roughplastic", "alpha": 0.2}},
            "anisotropic": {"type": "roughconductor", "distribution": "ggx", "alpha_u": 0.05, "alpha_v": 0.4}}[bsdf_name]
    look = LOOK
    if shape_name == "sphere":
        model, theirs_shape = csg.Sphere(1.2), {"type": "sphere", "radius": 1.2}
    elif shape_name == "cylinder":
        model = csg.Cylinder(0.8, 2.0)
        theirs_shape = {"type": "cylinder", "radius": 0.8, "p0": [0, 0, -1], "p1": [0, 0, 1]}
        look = SIDE_VIEW
    elif shape_name == "box":
        model = csg.Box((1.6, 2.0, 1.4)).rotate("z", 30)
        theirs_shape = {"type": "cube", "to_world": mi.ScalarTransform4f().rotate([0, 0, 1], 30).scale([0.8, 1.0, 0.7])}
    else:
        model, theirs_shape = csg.Torus(1.0, 0.35), _torus_mesh(1.0, 0.35)

    def image(shape, integrator, spp, seed):
        d = scene_dict(shape, {"type": integrator}, width=32, height=24, spp=spp)
        d["sensor"]["to_world"] = look
        return np.array(mi.render(mi.load_dict(d), spp=spp, seed=seed))
    theirs_shape = theirs_shape if isinstance(theirs_shape, mi.Mesh) else {**theirs_shape, "bsdf": bsdf}
    if isinstance(theirs_shape, mi.Mesh):
        theirs_shape.set_bsdf(mi.load_dict(bsdf))
    reference = image(theirs_shape, "path", 2048, 7)
    theirs = image(theirs_shape, "path", 512, 1)
    ours = image({"type": "csg", "model": csg.model_ref(model), "bsdf": bsdf}, "csg_path", 512, 2)
    mse = lambda a: float(np.mean((a - reference) ** 2) / np.mean(reference ** 2))   # noqa: E731
    assert mse(ours) < 1.5 * mse(theirs) + 1e-4, (mse(ours), mse(theirs))


# Every integrator Mitsuba 3.9 ships for the RGB variants (stokes needs a polarized variant).
MITSUBA_INTEGRATORS = {
    "path": {}, "direct": {}, "volpath": {}, "volpathmis": {}, "prbvolpath": {}, "prb": {}, "prb_basic": {},
    "prb_projective": {}, "direct_projective": {}, "ptracer": {}, "depth": {}, "aov": {"aovs": "dd:depth"},
    "moment": {"nested": {"type": "path"}}, "volprim_rf_basic": {},
}


@pytest.mark.parametrize("name", sorted(MITSUBA_INTEGRATORS))
def test_mitsubas_own_integrators_refuse_a_scene_with_csg(name):
    """Mitsuba's integrators trace only Mitsuba's shapes: on the example scene each raises an
    error naming the csg shape (through mi.render and through the integrator's own render),
    instead of an image without the Cheese."""
    scene = mi.load_file(str(ROOT / "scenes" / "cheese.xml"), width=16, height=12, spp=1)
    integrator = mi.load_dict({"type": name, **MITSUBA_INTEGRATORS[name]})
    with pytest.raises(csg.CSGError, match="cannot see the csg shape 'cheese_model'.*Use csg_") as info:
        mi.render(scene, integrator=integrator)
    instead = {"path": "csg_path", "direct": "csg_path with max_depth 2", "volpath": "csg_volpath",
               "volpathmis": "csg_volpath", "prbvolpath": "csg_volpath", "prb": "csg_prb", "prb_basic": "csg_prb",
               "prb_projective": "csg_prb_projective", "direct_projective": "csg_prb_projective with max_depth 2",
               "depth": "csg_aov", "aov": "csg_aov"}
    if name in instead:
        assert f"Use {instead[name]} (" in str(info.value)
    with pytest.raises(csg.CSGError, match="cannot see the csg shape 'cheese_model'"):
        integrator.render(scene, scene.sensors()[0])


def test_the_csg_integrators_render_the_example_scene_with_its_model():
    scene = mi.load_file(str(ROOT / "scenes" / "cheese.xml"), width=32, height=18, spp=2)
    shapes = [s.id() for s in scene.shapes()]
    centre = mi.render(scene, integrator=mi.load_dict({"type": "csg_aov", "aovs": "s:shape_index"}))
    assert shapes[int(np.array(centre)[9, 16, -1])] == "cheese_model"      # the model is where the camera looks
    for name in ("csg_path", "csg_prb", "csg_prb_projective"):
        image = np.array(mi.render(scene, integrator=mi.load_dict({"type": name})))
        assert np.isfinite(image).all() and image.mean() > 0.05


def test_a_nested_integrator_that_cannot_see_csg_is_refused():
    scene = mi.load_file(str(ROOT / "scenes" / "cheese.xml"), width=8, height=6, spp=1)
    aov = mi.load_dict({"type": "csg_aov", "aovs": "d:depth", "inner": {"type": "path"}})
    with pytest.raises(csg.CSGError, match="nested PathIntegrator integrator cannot see"):
        mi.render(scene, integrator=aov)
    with pytest.raises(csg.CSGError, match="nested PathIntegrator integrator cannot see"):
        aov.render(scene, scene.sensors()[0])


class _PythonIntegrator(mi.SamplingIntegrator):
    """A user's own integrator written in Python (no csg shapes): white where a ray hits."""
    def sample(self, scene, sampler, ray, medium=None, active=True):
        hit = scene.ray_intersect(ray, active).is_valid()
        return mi.Spectrum(dr.select(hit, 1.0, 0.0)), hit, []


@pytest.mark.parametrize("name", ["csg_path", "csg_aov", "csg_volpath", "csg_prb", "python"])
def test_ctrl_c_after_a_render_reaches_python(name):
    """Mitsuba's render binding swaps in its own SIGINT handler for the render; after a render
    (any csg_* integrator, or a user's Python one, which our render guard wraps) Python's own
    handler is back: the next Ctrl-C reaches it instead of cancelling the finished render."""
    import os
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers are set from the main thread only")
    integrator = _PythonIntegrator(mi.Properties()) if name == "python" else mi.load_dict({"type": name})
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere"}, "sky": {"type": "constant"},
                          "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at([0, 0, 5], [0, 0, 0], [0, 1, 0]),
                                     "film": {"type": "hdrfilm", "width": 8, "height": 6}}})
    seen = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: seen.append(signum))
    try:
        image = np.array(mi.render(scene, integrator=integrator, spp=1))
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(100):                    # Python runs its handlers between bytecodes
            if seen:
                break
    finally:
        signal.signal(signal.SIGINT, previous)
    assert seen == [signal.SIGINT]
    assert image.shape[:2] == (6, 8) and image.max() > 0


@pytest.mark.parametrize("integrator, message", [("csg_path", "csg shape 'ball' sits in a shapegroup"),
                                                 ("path", "cannot see the csg shape 'ball'")])
def test_instancing_a_csg_shape_is_refused(integrator, message):
    """A shape group builds its own acceleration structure of Mitsuba's shapes: its csg copies
    rendered nothing."""
    scene = mi.load_dict({"type": "scene", "integrator": {"type": integrator},
                          "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
                          "group": {"type": "shapegroup", "ball": {"type": "csg", "model": csg.model_ref(MODEL)}},
                          "copy": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"}}})
    with pytest.raises(csg.CSGError, match=message):
        mi.render(scene)
    with pytest.raises(csg.CSGError, match=message):
        scene.integrator().render(scene, scene.sensors()[0])


def test_the_media_example_scene_renders_its_ink(tmp_path):
    """scenes/ink_glass.xml: blue ink in a glass tumbler, in haze, through csg_volpath; where the
    camera looks through the tumbler the ink makes the image bluer than clear water does."""
    import re
    text = (ROOT / "scenes" / "ink_glass.xml").read_text()
    clear = tmp_path / "clear.xml"
    clear.write_text(re.sub(r'<medium type="homogeneous" name="interior">.*?</medium>', "", text, flags=re.S))

    def centre(path):
        image = np.array(mi.render(mi.load_file(str(path), width=48, height=36, spp=16), seed=0))
        assert np.isfinite(image).all() and image.mean() > 0.05
        rgb = image[16:26, 20:28].reshape(-1, 3).mean(axis=0)
        return rgb[2] / rgb[0]
    assert centre(ROOT / "scenes" / "ink_glass.xml") > 1.2 * centre(clear)


@pytest.mark.parametrize("name", ["sppc", "sppp", "sppi"])
@pytest.mark.parametrize("value", [-1, 1.5, True])
def test_csg_prb_projective_sample_counts_must_be_non_negative_integers(name, value):
    with pytest.raises(Exception, match=name):
        mi.load_dict({"type": "csg_prb_projective", name: value})
