"""Boundary derivatives of csg_prb_projective against central finite differences.

Forward-mode gradient images over the whole image (silhouette and CSG-edge pixels included)
against central differences of csg_path renders with one seed. The point light sits at the
camera, so no shadow edge is in view, except in the shadow tests, whose light stands aside
over a floor (csg_prb differentiates no shadows); the background is black. Metric (the
visibility issue's): the summed gradient within 5 % of the finite difference's, a per-pixel
correlation of at least 0.9, and the right sign; the same numbers for csg_prb say how far
interior-only derivatives are off.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mitsuba_csg as csg
from mitsuba_csg.scenes import cheese, cheese_holes

pytestmark = [pytest.mark.usefixtures("jit_variant"), pytest.mark.slow]

CAMERA = [4.0, -6.0, 3.0]


BSDF = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.6, 0.2]}}


def scene_dict(model, integrator, spp, size=(64, 48), target=(0, 0, 0), fov=40, backdrop=False, lamp=CAMERA,
               floor=False, sun=None, light=None, blocker=None, camera=CAMERA, wall=False, extra=None):
    scene = {
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "perspective", "fov": fov,
                   "to_world": mi.ScalarTransform4f().look_at(list(camera), list(target), [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": size[0], "height": size[1], "rfilter": {"type": "box"},
                            "sample_border": True},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "object": {"type": "csg", "model": csg.model_ref(model), "bsdf": BSDF},
        "lamp": {"type": "point", "position": list(lamp), "intensity": 60.0},
    }
    if sun is not None:
        scene["lamp"] = {"type": "directional", "direction": list(sun), "irradiance": 3.0}
    if light is not None:
        scene["lamp"] = light()                  # a function: Mitsuba objects are made per variant
    if blocker is not None:
        # A Mitsuba shape of that type (half size 0.25) at (-0.4, 0.5, 1.6), tilted (about a
        # unit axis: Mitsuba's rotate does not normalize it): a static caster.
        scene["blocker"] = {"type": blocker, "bsdf": {"type": "diffuse", "reflectance": 0.5},
                            "to_world": mi.ScalarTransform4f().translate([-0.4, 0.5, 1.6])
                            .rotate([0.8944272, 0.4472136, 0], 30).scale(0.25)}
    if wall:
        # Light that reaches the floor only by reflection: a white strip of wall above it
        # (y = 2.5, z from 1.7 to 3.5, facing -y), lit by a sun that travels level with the
        # floor (which it therefore does not light), and a dark model.
        scene["lamp"] = {"type": "directional", "direction": [0, 1, 0], "irradiance": 20.0}
        scene["wall"] = {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.9},
                         "to_world": mi.ScalarTransform4f().translate([0, 2.5, 2.6]).rotate([1, 0, 0], 90)
                         .scale([4, 0.9, 1])}
        scene["object"]["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.1, 0.08, 0.05]}}
        floor = 4.0
    if extra is not None:
        scene.update(extra())                    # a function, as `light`
    if floor:
        # A grey floor at z = 0 under the model, for shadows cast by a lamp away from the camera
        # (`floor`: True, or its half size).
        half = 6.0 if floor is True else float(floor)
        scene["floor"] = {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.7},
                          "to_world": mi.ScalarTransform4f().scale([half, half, 1])}
    if backdrop:
        # A white wall behind the model, lit by the lamp: the model's contours, where the
        # lamp grazes its surface (dark there), stand out against it. The model's shadow on
        # the wall lies exactly behind the model, as the lamp sits at the camera.
        behind = -0.5 * np.asarray(CAMERA)
        scene["backdrop"] = {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.9},
                             "to_world": mi.ScalarTransform4f().look_at(behind.tolist(), CAMERA, [0, 0, 1]).scale(8)}
    return scene


def scene(model, integrator, spp, size=(64, 48), **view):
    return mi.load_dict(scene_dict(model, integrator, spp, size, **view))


def forward_gradient(model, integrator, key, weights, spp, size, max_depth=2, options=None, **view):
    sc = scene(model, {"type": integrator, "max_depth": max_depth, **(options or {})}, spp, size, **view)
    params = mi.traverse(sc)
    base = np.array(params[key])
    h = mi.Float(0.0)
    dr.enable_grad(h)
    params[key] = mi.Float(base) + h * mi.Float(weights)
    params.update()
    image = mi.render(sc, params, spp=spp, seed=1)
    dr.forward(h)
    return dr.grad(image).numpy()


def finite_difference(model, key, weights, spp, size, eps, max_depth=2, **view):
    sc = scene(model, {"type": "csg_path", "max_depth": max_depth}, spp, size, **view)
    base = np.array(mi.traverse(sc)[key])

    def at(v):
        params = mi.traverse(sc)
        params[key] = mi.Float(base + v * weights)
        params.update()
        return np.array(mi.render(sc, spp=spp, seed=1))
    return (at(eps) - at(-eps)) / (2 * eps)


def check(model, key, weights, spp=256, fd_spp=4096, size=(64, 48), eps=0.02, tolerance=0.05, max_depth=2,
          options=None, **view):
    """`options`: csg_prb_projective's own parameters."""
    key = f"object.{key}"
    weights = np.asarray(weights, np.float32)
    fd = finite_difference(model, key, weights, fd_spp, size, eps, max_depth, **view)
    ours = forward_gradient(model, "csg_prb_projective", key, weights, spp, size, max_depth, options, **view)
    interior = forward_gradient(model, "csg_prb", key, weights, spp, size, max_depth, **view)
    allowed = max(tolerance * abs(fd.sum()), 0.01 * np.abs(fd).sum())
    assert abs(ours.sum() - fd.sum()) < allowed, (ours.sum(), fd.sum(), np.abs(fd).sum())
    assert np.sign(ours.sum()) == np.sign(fd.sum())
    assert np.corrcoef(ours.ravel(), fd.ravel())[0, 1] >= 0.9
    return interior.sum() / fd.sum(), np.corrcoef(interior.ravel(), fd.ravel())[0, 1]


HOLE = csg.Box(2.0) - csg.Sphere(1.25).translate((0.3, -0.2, 0.4))


@pytest.mark.parametrize("parameter", ["x", "y", "z", "radius"])
def test_box_minus_sphere(parameter):
    """The hole's centre along each axis (primitive 1's translation column) and its radius
    (the diagonal of its linear part): the CSG edges where the hole meets the box's faces."""
    weights = np.zeros(24)
    if parameter == "radius":
        weights[[12, 17, 22]] = 1.0
    else:
        weights[12 + 3 + 4 * "xyz".index(parameter)] = 1.0
    ratio, correlation = check(HOLE, "primitive_to_world", weights)
    # csg_prb alone: interior derivatives only, far from the whole
    assert abs(ratio - 1) > 0.5 and correlation < 0.5, (ratio, correlation)


def test_union_of_two_spheres():
    """The second sphere's position: silhouettes and the circle where the spheres meet."""
    model = csg.Sphere(1.0) | csg.Sphere(0.8).translate((0.9, 0.5, 0.3))
    weights = np.zeros(24)
    weights[12 + 3] = 1.0
    check(model, "primitive_to_world", weights)


def test_cylinder_intersected_with_a_rotated_box():
    """The box's angle about z (a named parameter): box edges, cylinder contours and rims, and
    the curves where the cylinder's side and caps meet the box's faces."""
    model = csg.Cylinder(0.9, 2.4) & csg.Box((1.6, 1.6, 1.6)).rotate((1, 1, 0), 20)
    ratio, correlation = check(model, "primitive_rotation", [0, 0, 0, 0, 0, 1])
    assert abs(ratio - 1) > 0.3, ratio


@pytest.mark.parametrize("parameter", ["x", "size"])
def test_torus_silhouette(parameter):
    """A tilted torus: its contour (outer and inner, on both branches) moving with the
    torus's position and size."""
    model = csg.Torus(1.0, 0.35).rotate((1, 0.3, 0), 65)
    weights = np.zeros(12)
    weights[[0, 5, 10] if parameter == "size" else [3]] = 1.0
    ratio, correlation = check(model, "primitive_to_world", weights, spp=512, backdrop=True)
    # csg_prb alone (interior terms only): a growth's contour terms add up, a shift's cancel
    # in the sum but not pixel by pixel.
    if parameter == "size":
        assert abs(ratio - 1) > 0.3, ratio
    else:
        assert correlation < 0.7, correlation


# Curves no closed form covers, listed as chords and moved by Newton steps (csg_edges
# SURFACE_PAIR): a sphere cutting a cylinder's side and top cap, a cone cutting a
# cylinder, a torus sunk into a box's top face.
CYLINDER_MINUS_SPHERE = csg.Cylinder(0.9, 2.0) - csg.Sphere(0.55).translate((0.75, -0.3, 0.75))
CYLINDER_MINUS_CONE = csg.Cylinder(0.9, 2.0) - csg.Cone(0.5, 0.1, 1.6).rotate((1, 0, 0), 70).translate((0.2, -0.6, 0.3))
BOX_MINUS_TORUS = csg.Box((2.4, 2.4, 1.2)) - csg.Torus(0.8, 0.3).translate((0.1, 0.0, 0.65))


@pytest.mark.parametrize("model, weights, eps", [
    (CYLINDER_MINUS_SPHERE, [0] * 15 + [1] + [0] * 8, 0.01),
    pytest.param(CYLINDER_MINUS_SPHERE, [0] * 12 + [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], 0.01,
                 marks=pytest.mark.xfail(
        strict=True, reason="summed gradient -9.32 (512 spp, seed 1; -10.07 at seed 2) against central "
        "differences -10.93 (eps 0.01, 4096 spp; -10.65 over three seeds, -10.38 at eps 0.02, so about "
        "-10.7 by Richardson): 1.4 % of the summed |FD| (119), over the 1 % allowed. The old estimate "
        "(rays either side extrapolated from two offsets, also past occluding edges) gave -9.76 / -10.47, "
        "passing by 0.03 at seed 1: it is 0.4 nearer, from extrapolating the far side of the rim where the "
        "sphere leaves the cylinder's side (extrapolating it here gives -9.54 / -10.28, but the grazing "
        "rim's -244 against -223). The rest of the shortfall is older and not traced to a curve yet")),
    (CYLINDER_MINUS_CONE, [0] * 19 + [1] + [0] * 4, 0.01),
    pytest.param(BOX_MINUS_TORUS, [0] * 15 + [1] + [0] * 8, 0.01, marks=pytest.mark.xfail(
        strict=True, reason="summed gradient 5.0 (512 spp; 4.97 at 2048) against central differences 4.07 "
        "(eps 0.01, 4096 spp): 1.3 % of the summed |FD| (75), over the 1 % allowed (the shift's terms "
        "cancel to 5 % of it); 3.98 / 2.99 at eps 0.01 / 0.02 with 16384 spp, so the derivative is "
        "about 4.3 (Richardson) and ours 0.9 % of |FD| above it; correlation 0.98. Not traced to a "
        "curve yet")),
    # eps 0.005: the groove changes shape as the torus grows, and central differences at
    # 16384 spp give 44.4 at eps 0.01 and 45.6 at 0.005 (Richardson: 46.1; ours 46.4 at 2048 spp)
    (BOX_MINUS_TORUS, [0] * 12 + [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], 0.005),
], ids=["sphere-cylinder x", "sphere-cylinder radius", "cone-cylinder y", "torus-box x", "torus-box size"])
def test_curves_without_a_closed_form(model, weights, eps):
    """Before these curves were listed: summed gradients -11.4 / 59.3 / -8.1 / 11.8 / 28.5
    against central differences 13.4 / -10.9 / 11.9 / 4.1 / 43.9 (wrong sign in three)."""
    check(model, "primitive_to_world", weights, spp=512, eps=eps)


def test_traced_curve_points_lie_on_both_surfaces():
    """The SURFACE_PAIR points of a cylinder minus a sphere, after the Newton steps: on the
    sphere (|x - c| = 0.55) and on the cylinder's side (x^2 + y^2 = 0.81, |z| <= 1) or top
    cap (z = 1 inside the rim), to float32 accuracy; and the chords cover the whole curve
    (their summed length against the curve's, from its closed form)."""
    from mitsuba_csg.plugins import csg_edges
    sc = mi.load_dict({"type": "scene", "s": {"type": "csg", "model": csg.model_ref(CYLINDER_MINUS_SPHERE)}})
    shape = sc.shapes()[0]
    curves = csg_edges.Curves(shape)
    pair = np.flatnonzero(curves.kind == csg_edges.SURFACE_PAIR)
    assert len(pair) > 50
    u = mi.Float(np.random.default_rng(2).random(len(pair)).astype(np.float32))
    rows = {name: mi.UInt32(getattr(curves, name)[pair]) for name in ("kind", "extra", "a", "b")}
    m_a, t_a = csg_edges.leaf_rows(shape.primitive_to_world, rows["a"], True)
    m_b, t_b = csg_edges.leaf_rows(shape.primitive_to_world, rows["b"], True)
    data = [mi.Float(np.ascontiguousarray(curves.data[pair, k])) for k in range(curves.data.shape[1])]
    x, _, valid = csg_edges.evaluate(rows["kind"], rows["extra"], m_a, t_a, m_b, t_b, data, mi.Point3f(CAMERA), u)
    x = np.array(x, np.float64).reshape(3, -1).T
    assert np.all(valid.numpy())
    on_sphere = np.abs(np.linalg.norm(x - [0.75, -0.3, 0.75], axis=1) - 0.55)
    radial = np.linalg.norm(x[:, :2], axis=1)
    on_side = np.abs(radial - 0.9) + np.maximum(np.abs(x[:, 2]) - 1, 0)
    on_cap = np.abs(x[:, 2] - 1) + np.maximum(radial - 0.9, 0)
    assert on_sphere.max() < 2e-6 and np.minimum(on_side, on_cap).max() < 2e-6
    # Reference length: on the side, z(psi) = 0.75 +- sqrt(0.55^2 - |(0.9 cos psi, 0.9 sin psi) -
    # (0.75, -0.3)|^2) for |z| <= 1; on the cap z = 1, the circle about (0.75, -0.3) of radius
    # sqrt(0.55^2 - 0.25^2) inside the rim. Polylines of a million points.
    psi = np.linspace(0, 2 * np.pi, 1_000_001)
    h2 = 0.55 ** 2 - (0.9 * np.cos(psi) - 0.75) ** 2 - (0.9 * np.sin(psi) + 0.3) ** 2
    reference_length = 0.0
    for sign in (1, -1):
        z = 0.75 + sign * np.sqrt(np.maximum(h2, 0))
        keep = (h2 >= 0) & (np.abs(z) <= 1)
        points = np.stack([0.9 * np.cos(psi), 0.9 * np.sin(psi), z], -1)
        steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
        reference_length += steps[keep[1:] & keep[:-1]].sum()
    rim = np.sqrt(0.55 ** 2 - 0.25 ** 2)
    arc = np.stack([0.75 + rim * np.cos(psi), -0.3 + rim * np.sin(psi)], -1)
    inside = np.linalg.norm(arc, axis=1) <= 0.9
    reference_length += (np.linalg.norm(np.diff(arc, axis=0), axis=1)[inside[1:] & inside[:-1]]).sum()
    listed = curves.data[pair, 2:5] - curves.data[pair, 5:8]
    assert np.linalg.norm(listed, axis=1).sum() == pytest.approx(reference_length, rel=0.01)


def _quadric_side(param):
    """(surface g and its gradient at canonical points, grid of the side) of a quadric leaf."""
    a, b = param
    c = 1 - a - abs(b)

    def g(y):
        return (y[..., 0] ** 2 + y[..., 1] ** 2 - (a * y[..., 2] ** 2 + b * y[..., 2] + c),
                np.stack([2 * y[..., 0], 2 * y[..., 1], -(2 * a * y[..., 2] + b)], -1))
    phi = np.linspace(0, 2 * np.pi, 4001)
    z = np.linspace(-1, 1, 2001)[:, None]
    rho = np.sqrt(np.maximum(a * z * z + b * z + c, 0))
    return g, np.stack(np.broadcast_arrays(rho * np.cos(phi), rho * np.sin(phi), z + 0 * phi), -1)


def _torus(param):
    """The same for a torus leaf (major radius 1, minor param[0])."""
    k = param[0]

    def g(y):
        s = (y ** 2).sum(-1) + 1 - k * k
        return s * s - 4 * (y[..., 0] ** 2 + y[..., 1] ** 2), np.stack(
            [4 * s * y[..., 0] - 8 * y[..., 0], 4 * s * y[..., 1] - 8 * y[..., 1], 4 * s * y[..., 2]], -1)
    w = np.linspace(0, 2 * np.pi, 4001)
    v = np.linspace(0, 2 * np.pi, 4001)[:, None]
    ring = 1 + k * np.cos(v)
    return g, np.stack(np.broadcast_arrays(ring * np.cos(w), ring * np.sin(w), k * np.sin(v) + 0 * w), -1)


@pytest.mark.parametrize("solid, kind, surface", [
    (csg.Hyperboloid(0.5, 1.0, 2.0), "QUADRIC_SILHOUETTE", _quadric_side),
    (csg.Paraboloid(0.2, 0.9, 1.6), "QUADRIC_SILHOUETTE", _quadric_side),
    (csg.Torus(1.0, 0.35), "TORUS_SILHOUETTE", _torus),
], ids=["hyperboloid", "paraboloid", "torus"])
def test_contour_points_and_length(solid, kind, surface):
    """The contours of tilted quadric and torus leaves seen from the camera, each listed on two
    branches in two parametrizations: their points lie on the surface and graze it from the
    camera ((x - camera) . normal = 0), and the sum over the rows of the integral of |dx/du|
    over u (the mixture's speed, what the sampler's pdf assumes) is the contour's length,
    against marching squares on a fine grid of the surface."""
    from mitsuba_csg.plugins import csg_edges
    model = solid.rotate((1, 0.3, 0), 35).translate((0.2, -0.1, 0.3))
    sc = mi.load_dict({"type": "scene", "s": {"type": "csg", "model": csg.model_ref(model)}})
    shape = sc.shapes()[0]
    curves = csg_edges.Curves(shape)
    rows = np.flatnonzero(curves.kind == getattr(csg_edges, kind))
    assert len(rows) == 4
    n = 200_000
    pick = np.repeat(rows, n)
    u = mi.Float(np.tile((np.arange(n) + 0.5) / n, len(rows)).astype(np.float32))
    index = {name: mi.UInt32(getattr(curves, name)[pick]) for name in ("kind", "extra", "a", "b")}
    m_a, t_a = csg_edges.leaf_rows(shape.primitive_to_world, index["a"], True)
    data = [mi.Float(np.ascontiguousarray(curves.data[pick, k])) for k in range(curves.data.shape[1])]
    x, dx, valid = csg_edges.evaluate(index["kind"], index["extra"], m_a, t_a, m_a, t_a, data,
                                      mi.Point3f(CAMERA), u)
    valid = valid.numpy()
    x = np.array(x, np.float64).reshape(3, -1).T[valid]
    speed = np.linalg.norm(np.array(dx, np.float64).reshape(3, -1).T, axis=1)[valid]
    # the canonical frame: the leaf's own matrix from the prepared tree (float64)
    to_world = shape.prepared.flat.prim_to_world[0]
    g, grid = surface(shape.prepared.flat.prim_param[0])
    y = (x - to_world[:3, 3]) @ np.linalg.inv(to_world[:3, :3]).T
    value, grad = g(y)
    assert np.abs(value).max() < 1e-5
    cam = (np.array(CAMERA) - to_world[:3, 3]) @ np.linalg.inv(to_world[:3, :3]).T
    graze = np.einsum("ij,ij->i", grad, y - cam) / (np.linalg.norm(grad, axis=1) * np.linalg.norm(y - cam, axis=1))
    assert np.abs(graze).max() < 1e-4
    # the mixture's speed is bounded: no point weighs more than a few times the average
    assert speed.max() < 20 * speed.mean()
    ours = speed.sum() / n
    # reference: the zero set of (x - camera) . normal on the surface, world lengths
    f = np.einsum("...k,...k->...", g(grid)[1], grid - cam)
    world = grid @ to_world[:3, :3].T + to_world[:3, 3]
    chords = csg_edges._chords(world, f)
    reference = np.linalg.norm(chords[:, 1] - chords[:, 0], axis=1).sum()
    assert ours == pytest.approx(reference, rel=0.01), (ours, reference)


HYPERBOLOID = csg.Hyperboloid(0.5, 1.0, 2.0).rotate((1, 0.3, 0), 35)
CUP = csg.Box((2.0, 2.0, 1.4)) - csg.Paraboloid(0.0, 0.7, 1.6).rotate((1, 0, 0), 20).translate((0.2, -0.1, 0.7))
THREADED = csg.Sphere(1.1) - csg.Hyperboloid(0.3, 0.6, 3.0).rotate((1, 0, 0), 30).translate((0.2, 0.0, 0.1))


@pytest.mark.parametrize("model, weights", [
    (HYPERBOLOID, [0, 0, 0, 1] + [0] * 8),
    (HYPERBOLOID, [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]),
    (CUP, [0] * 15 + [1] + [0] * 8),
    (CUP, [0] * 12 + [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]),
    (THREADED, [0] * 15 + [1] + [0] * 8),
], ids=["hyperboloid x", "hyperboloid size", "paraboloid cup x", "paraboloid cup size", "sphere minus hyperboloid x"])
def test_quadric_curves(model, weights):
    """Quadric leaves (Geant4's paraboloids and hyperboloids): a tilted hyperboloid's contour
    and rims; a paraboloid cup cut into a box's top (where its side meets the face); a sphere
    pierced by a hyperboloid (where the two sides meet). Before quadric curves were listed:
    summed gradient -8.4 / -3.4 / 3.3 / 10.2 / 11.5 (csg_prb's alone) against central
    differences 86.0 / 371.5 / 2.28 / 21.1 / -17.2."""
    check(model, "primitive_to_world", weights, spp=512, eps=0.01)


# Shadows (indirect visibility): a lamp above and to the side casts the model's shadow on a
# floor the camera sees; moving the model moves the shadow's edge.
SHADOW_LAMP = (-1.5, 2.0, 5.0)


@pytest.mark.parametrize("model, weights", [
    (csg.Sphere(0.6).translate((0.3, 0.2, 1.0)), [0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0]),
    (csg.Sphere(0.6).translate((0.3, 0.2, 1.0)), [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]),
    pytest.param(csg.Box((1.2, 1.2, 0.8)).translate((0, 0, 1.2)) - csg.Sphere(0.5).translate((0.3, -0.3, 1.6)),
                 [0] * 15 + [1] + [0] * 8, marks=pytest.mark.xfail(
                     strict=True, reason="summed gradient 56.3 (2048 spp) against central differences 49.9 / "
                     "50.4 (eps 0.01 / 0.005, 16384 spp), 2.9 % of the summed |FD| (216); the floor's "
                     "part agrees (20.6 against 21.3 below the model in the image), the excess lies on the "
                     "model itself (the rim, and the rim's shadow inside the hole): 35.8 against 28.7. With the "
                     "lamp at the camera (no shadow in view) the same model is off too, 4.4 against 8.1 "
                     "(6 % of its |FD|): its far rim is seen past at grazing incidence, as in "
                     "test_cheese_hole_radius_grazing_rim")),
], ids=["sphere x", "sphere radius", "hole x"])
def test_shadow_edges_move(model, weights):
    """Before the shadow term: summed gradients 30.2 / -273.9 / 46.7 against central
    differences -40.0 / -913.8 / 49.9 (the sphere's shadow on the floor missing)."""
    check(model, "primitive_to_world", weights, spp=512, eps=0.01, lamp=SHADOW_LAMP, floor=True)


def test_shadow_edges_of_a_directional_light_move():
    """The same sphere over the floor, lit by a sun (a directional light), moving along x."""
    check(csg.Sphere(0.6).translate((0.3, 0.2, 1.0)), "primitive_to_world", [0, 0, 0, 1] + [0] * 8, spp=512,
          eps=0.01, sun=(0.5, -0.4, -1.0), floor=True)


def _area_lamp():
    """A 1 x 1 square lamp where SHADOW_LAMP stands, facing the origin."""
    return {"type": "rectangle", "emitter": {"type": "area", "radiance": 40.0},
            "to_world": mi.ScalarTransform4f().look_at(list(SHADOW_LAMP), [0, 0, 0], [0, 0, 1]).scale(0.5)}


def _sky():
    """A uniform sky."""
    return {"type": "constant", "radiance": 1.0}


def _sky_with_a_sun():
    """An environment map: a dim sky and a bright blurred spot high up on one side."""
    theta = (np.arange(32) + 0.5) / 32
    phi = (np.arange(64) + 0.5) / 64
    sky = 0.3 + 4.0 * np.exp(-((theta[:, None] - 0.25) ** 2 + (phi[None, :] - 0.6) ** 2) / 0.01)
    return {"type": "envmap", "bitmap": mi.Bitmap(np.repeat(sky[:, :, None], 3, axis=2).astype(np.float32))}


def _spot():
    return {"type": "spot", "intensity": 60.0, "cutoff_angle": 25.0, "beam_width": 15.0,
            "to_world": mi.ScalarTransform4f().look_at(list(SHADOW_LAMP), [0.3, 0.2, 0.0], [0, 0, 1])}


def _spherical_lamp():
    """A glowing Mitsuba sphere where SHADOW_LAMP stands."""
    return {"type": "sphere", "center": list(SHADOW_LAMP), "radius": 0.4, "emitter": {"type": "area", "radiance": 30.0}}


def _projector():
    return {"type": "projector", "fov": 40, "scale": 30,
            "to_world": mi.ScalarTransform4f().look_at(list(SHADOW_LAMP), [0.3, 0.2, 0.0], [0, 0, 1])}


@pytest.mark.parametrize("light", [_area_lamp, _spherical_lamp, _sky, _sky_with_a_sun, _spot, _projector],
                         ids=["area light", "spherical area light", "constant sky", "environment map", "spot light",
                              "projector"])
def test_shadows_of_area_and_environment_lights_move(light):
    """The sphere over the floor moving along x under lights with soft shadows: the sum of the
    sharp shadows of a point sampled per boundary sample on the lamp, or of a direction
    sampled from the sky (also a glowing Mitsuba sphere and a projector). Without the term (as
    csg_prb), for the square lamp, the skies and the spot: 23.6 / 28.0 / 13.4 / 36.6 against
    central differences of about -30 / -45 / -37 / -47 (the derivative of the shadow's
    penumbra missing: the wrong sign). Central differences at 16384 spp: at 4096 the spot
    light's came out -44.8 against -47.4. Under the skies the floor's edges (a Mitsuba
    rectangle's) cast too: the sky below the horizon, past the floor, lights the sphere's
    underside, and that shadow's edges move over the sphere with it (the constant sky
    without them: -48.9 +- 0.8 against -45.2 +- 0.5 at eps 0.02, six seeds; with them
    -44.2 +- 0.9)."""
    ratio, _ = check(csg.Sphere(0.6).translate((0.3, 0.2, 1.0)), "primitive_to_world", [0, 0, 0, 1] + [0] * 8,
                     spp=512, fd_spp=16384, eps=0.01, floor=True, light=light)
    assert ratio < 0, ratio


def test_shadows_and_interreflections_of_an_area_light_move():
    """The sphere over the floor under the square lamp, moving along x, with one bounce of
    interreflection (max_depth 3): the floor lights the sphere's underside, and the sphere
    sees its own soft shadow on the floor and the floor's edges move relative to it (the
    indirect terms). Summed gradients against central differences (16384 spp) when
    written: -27.67 / -28.10, correlation 0.999; without the indirect terms (sppi 0)
    -21.14. Under the constant sky -36.07 / -36.16 (sppi 0: -46.19), under the spot light
    -44.78 / -47.97 (-35.13)."""
    check(csg.Sphere(0.6).translate((0.3, 0.2, 1.0)), "primitive_to_world", [0, 0, 0, 1] + [0] * 8, spp=512,
          fd_spp=16384, eps=0.01, max_depth=3, floor=True, light=_area_lamp)


@pytest.mark.parametrize("blocker", ["cube", "sphere", "disk", "cylinder"])
def test_shadow_of_a_mitsuba_shape_on_a_moving_csg_shape(blocker):
    """A Mitsuba shape (static) shades a csg slab that moves up: its shadow on the slab moves
    with it (the shape's edges, contour or rims cast from the lamp, projected onto the moving
    face). Without the static casters, correlation with central differences 0.74 / 0.81 /
    0.80 / 0.80 (cube, sphere, disk, cylinder; the shadow's edges missing), with them 0.996 /
    0.997 / 0.98 / 0.99."""
    slab = csg.Box((1.6, 1.6, 0.3)).translate((0.0, 0.0, 0.4))
    check(slab, "primitive_to_world", [0] * 11 + [1], spp=512, eps=0.01, lamp=SHADOW_LAMP, floor=True,
          blocker=blocker)


PRISM = csg.Prism(6, 1.0, 2.0).rotate((0, 0, 1), 10) - csg.Sphere(0.6).translate((0.9, -0.5, 0.3))


# The camera sees only the floor of the `wall` scene (the model and the wall out of view).
INDIRECT_VIEW = {"camera": (0.0, -2.5, 5.0), "target": (0.0, -1.0, 0.0), "wall": True}


def _black_box():
    """A black Mitsuba cube standing on the floor between the floor in view and the wall."""
    return {"blocker": {"type": "cube", "bsdf": {"type": "diffuse", "reflectance": 0.0},
                        "to_world": mi.ScalarTransform4f().translate([0, 1.2, 0.75]).scale([0.6, 0.3, 0.45])}}


@pytest.mark.parametrize("model, weights, extra, size, spp", [
    (csg.Sphere(0.6).translate((0, 1.5, 0.9)), [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], None, (48, 36), 1024),
    (csg.Sphere(0.6).translate((0, 1.5, 0.9)), [0] * 11 + [1], None, (48, 36), 1024),
    # a box with a notch cut into its top front edge (the notch's radius): the CSG edges in
    # the outline the floor sees against the wall
    (csg.Box((1.4, 0.4, 1.0)).translate((0, 1.4, 0.9)) - csg.Sphere(0.3).translate((0.1, 1.2, 1.4)),
     [0] * 12 + [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], None, (48, 36), 1024),
    # the floor itself a csg slab, rising (the point the camera sees moves): the edges of a
    # Mitsuba cube and of the wall move relative to it (a weak change: larger pixels, more
    # samples)
    (csg.Box((8.0, 8.0, 0.2)), [0] * 11 + [1], _black_box, (24, 18), 4096),
    # a sphere in the sun's beam above the box, its shadow on the wall: the shadow's edge, seen
    # from the floor, moves as the sphere grows
    (csg.Sphere(0.5).translate((0, 1.5, 2.4)), [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], None, (24, 18), 4096),
], ids=["sphere radius", "sphere z", "notch radius", "rising floor", "shadow on the wall"])
def test_indirect_shadows_move(model, weights, extra, size, spp):
    """The floor, lit only by light the wall reflects, seen from above; a dark model (or a
    black cube) between them casts a soft indirect shadow. Summed gradients against central
    differences (65536 spp) when written: sphere radius -656.2 / -658.3, height -364.5 /
    -367.6, notch radius 189.1 / 191.1, rising floor 9.36 / 9.35, shadow on the wall -179.4 /
    -180.1 (correlation 0.971); without the indirect term (as csg_prb) +46.4, -11.0, 3.9, 0
    and +4.8. The shadow on the wall needs the shadows' edges seen from the floor: without
    them -78.1 (correlation 0.63). The camera sees no curve and no shadow, so the primary
    and shadow terms are off (they gave exactly csg_prb's image here)."""
    ratio, _ = check(model, "primitive_to_world", weights, spp=spp, fd_spp=65536, size=size, max_depth=3,
                     options={"sppp": 0}, extra=extra, **INDIRECT_VIEW)
    assert not abs(ratio - 1) < 0.5, ratio


def _ceiling():
    """A white ceiling at z = 1.5, facing down over the floor in front of the `wall` scene's
    model: neither the sun (level with it) nor the wall (above it) lights it directly."""
    return {"ceiling": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.9},
                        "to_world": mi.ScalarTransform4f().translate([0, -1.35, 1.5]).rotate([1, 0, 0], 180)
                        .scale([2.5, 2.15, 1])}}


# The camera beneath the ceiling sees only the ceiling, lit by the floor, which the wall lights.
CEILING_VIEW = {"camera": (0.0, -1.5, 0.3), "target": (0.0, -1.0, 1.5), "wall": True, "extra": _ceiling}


def test_curves_seen_from_a_deeper_vertex_move():
    """The sphere of test_indirect_shadows_move growing, seen only by way of the floor it
    shades: camera, ceiling, floor, wall, sun (max_depth 4). Its soft shadow on the floor is
    drawn by its contour as the floor sees it, the second vertex of the camera's paths.
    Summed gradients against central differences (1048576 spp) when written: -11.84 /
    -11.94, correlation 0.945; with the curves seen from the camera's first vertex only
    (the ceiling) +2.63 (correlation 0.16), csg_prb +2.16. Large pixels, many samples: the
    derivative image is smooth, and half the boundary samples look from the ceiling."""
    ratio, _ = check(csg.Sphere(0.6).translate((0, 1.5, 0.9)), "primitive_to_world",
                     [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], spp=32768, fd_spp=1048576, size=(8, 6), max_depth=4,
                     options={"sppp": 0}, **CEILING_VIEW)
    assert not abs(ratio - 1) < 0.5, ratio


@pytest.mark.parametrize("key, weights", [("primitive_rotation", [0, 0, 1, 0, 0, 0]),
                                          ("primitive_to_world", [0] * 15 + [1] + [0] * 8),
                                          ("primitive_scale", [0, 1])],
                         ids=["prism angle", "hole x", "hole radius"])
def test_hexagonal_prism_minus_sphere(key, weights):
    """A convex polyhedron leaf: the prism's edges (turning about its axis) and the circles
    where the hole meets its faces (the hole moving, growing)."""
    ratio, correlation = check(PRISM, key, weights, spp=512, eps=0.01)
    assert abs(ratio - 1) > 0.5 and correlation < 0.5, (ratio, correlation)


NOTCH = csg.Box(2.0) - csg.Box(1.0).rotate((1, 1, 0), 25).translate((0.8, -0.8, 0.8))


@pytest.mark.parametrize("key, weights", [("primitive_rotation", [0, 0, 0, 0, 0, 1]),
                                          ("primitive_translation", [0, 0, 0, 1, 0, 0]),
                                          ("primitive_scale", [0, 1])],
                         ids=["angle", "x", "size"])
def test_box_notched_by_a_rotated_box(key, weights):
    """Where two boxes' faces meet (the lines of their planes) and the cutting box's own
    edges, as the cutting box turns, moves and grows."""
    ratio, correlation = check(NOTCH, key, weights, spp=512, eps=0.01)
    assert abs(ratio - 1) > 0.3 or correlation < 0.6, (ratio, correlation)


OCTAHEDRON = csg.Mesh(1.3 * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float),
                      [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
MESH_LEAF = OCTAHEDRON.rotate((0, 0, 1), 20) - csg.Sphere(0.5).translate((0.5, -0.5, 0.3))


@pytest.mark.parametrize("key, weights", [("primitive_translation", [1, 0, 0, 0, 0, 0]),
                                          ("primitive_scale", [1, 0])], ids=["mesh x", "mesh size"])
def test_mesh_leaf_minus_sphere(key, weights):
    """A mesh leaf (an octahedron): its edges, and the circles where the hole's sphere meets
    its triangles' planes, as the mesh moves and grows."""
    ratio, correlation = check(MESH_LEAF, key, weights, spp=512, eps=0.01)
    assert abs(ratio - 1) > 0.3 or correlation < 0.6, (ratio, correlation)


MESH_NOTCH = OCTAHEDRON.rotate((0, 0, 1), 20) - OCTAHEDRON.scale(0.6).rotate((1, 1, 0), 30).translate((0.6, -0.6, 0.5))


@pytest.mark.parametrize("key, weights", [("primitive_translation", [0, 0, 0, 1, 0, 0]),
                                          ("primitive_scale", [0, 1])], ids=["notch x", "notch size"])
def test_mesh_notched_by_a_mesh(key, weights):
    """Two mesh leaves: where the notching octahedron's triangles cross the other's (segments
    each pair of crossing triangles holds). Before those were listed: summed gradient 4.64
    against central differences 2.28 (notch x), correlation 0.58."""
    check(MESH_NOTCH, key, weights, spp=512, eps=0.01)


PARABOLOID_IN_A_MESH = OCTAHEDRON - csg.Paraboloid(0.0, 0.4, 0.8).rotate((1, 1, 0), 54.7356).translate((0.5, -0.5, 0.5))


def test_quadric_cut_into_a_mesh():
    """A paraboloid cup cut into an octahedron's face (where the quadric meets the mesh's
    triangles: SURFACE_PAIR chords on the triangle), moving along x. Before: -4.43 (csg_prb's
    alone: -4.37) against central differences 17.1."""
    check(PARABOLOID_IN_A_MESH, "primitive_to_world", [0] * 15 + [1] + [0] * 8, spp=512, eps=0.01)


def _cheese_hole_radius(hole):
    """The 20-hole Cheese seen close up (fov 6) around one hole, whose radius (its sphere's
    diagonal) moves: (model, weights, view)."""
    model = cheese(20)
    centres, _ = cheese_holes(20)
    weights = np.zeros(12 * 21)
    weights[[12 * (1 + hole) + k for k in (0, 5, 10)]] = 1.0
    return model, weights, {"target": tuple(float(c) for c in centres[hole]), "fov": 6}


def test_cheese_hole_radius():
    """A hole of the 20-hole Cheese cutting the box's edge (radius 0.164, centre 0.13 inside
    the face x = 1 and 0.01 inside the bottom face): its rims on both faces and the notch it
    cuts in the box's silhouette edge."""
    model, weights, view = _cheese_hole_radius(3)
    ratio, _ = check(model, "primitive_to_world", weights, spp=1024, eps=0.005, **view)
    assert abs(ratio - 1) > 0.5, ratio


def test_cheese_hole_radius_grazing_rim():
    """Another hole (radius 0.114, centre 0.07 inside the front face, so the cavity overhangs
    its rim): the cavity wall beneath one arc of the rim faces the camera at grazing
    incidence (cosine below 0.06), and where that arc ends, the sphere's contour, in the
    air just in front of the face, meets the rim. Before curve points were required to lie
    on the solid's boundary and rims' jumps were taken at the rim from each face: -194
    against central differences of -224, correlation 0.82, the contour counting the rim's
    jump again and camera rays beside the grazed wall meeting it far from the rim."""
    model, weights, view = _cheese_hole_radius(4)
    check(model, "primitive_to_world", weights, spp=1024, eps=0.005, **view)


@pytest.mark.parametrize("parameter", ["x", "radius"])
def test_sphere_against_prb_projective_on_its_mesh(parameter, tmp_path):
    """Mitsuba's own prb_projective on the manifold3d mesh of a sphere, its vertices moved with
    the primitive (translated, or radially for the radius), against csg_prb_projective on the
    exact sphere: the same gradient image within noise (a silhouette only; Mitsuba samples
    silhouette edges of meshes, not creases whose two faces both face the camera, so the
    rims of holes are checked against finite differences above instead)."""
    from mitsuba_csg.formats.mesh_export import save_mesh
    centre = np.array([0.3, -0.2, 0.4])
    model = csg.Sphere(1.0).translate(tuple(centre))
    weights = np.zeros(12, np.float32)
    weights[[0, 5, 10] if parameter == "radius" else [3]] = 1.0
    ours = forward_gradient(model, "csg_prb_projective", "object.primitive_to_world", weights, 256, (64, 48))

    ply = tmp_path / "sphere.ply"
    save_mesh(csg.to_mesh(model, segments=256), ply)
    sc = mi.load_dict({**scene_dict(model, {"type": "prb_projective", "max_depth": 2, "sppi": 0}, 256),
                       "object": {"type": "ply", "filename": str(ply), "bsdf": BSDF}})
    params = mi.traverse(sc)
    vertices = np.array(params["object.vertex_positions"]).reshape(-1, 3)
    motion = vertices - centre if parameter == "radius" else np.tile([1.0, 0.0, 0.0], (len(vertices), 1))
    h = mi.Float(0.0)
    dr.enable_grad(h)
    params["object.vertex_positions"] = mi.Float(vertices.ravel()) + h * mi.Float(motion.ravel().astype(np.float32))
    params.update()
    image = mi.render(sc, params, spp=256, seed=1)
    dr.forward(h)
    mesh = dr.grad(image).numpy()
    assert abs(ours.sum() / mesh.sum() - 1) < 0.05, (ours.sum(), mesh.sum())
    assert np.corrcoef(ours.ravel(), mesh.ravel())[0, 1] >= 0.95


@pytest.mark.parametrize("model, weights, max_depth, options, view", [
    (HOLE, [0] * 12 + [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], 2, None, {}),       # the hole's radius
    (csg.Sphere(0.6).translate((0, 1.5, 0.9)), [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], 3, {"sppp": 0},
     INDIRECT_VIEW),                                                               # the indirect term
    (csg.Sphere(0.5).translate((0, 1.5, 2.4)), [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], 3, {"sppp": 0},
     INDIRECT_VIEW),                                               # its shadow on the wall, seen from the floor
    (csg.Sphere(0.6).translate((0, 1.5, 0.9)), [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], 4, {"sppp": 0},
     CEILING_VIEW),                                                # curves seen from a deeper vertex
], ids=["primary", "indirect", "indirect shadow", "deeper vertex"])
def test_backward_mode_gives_the_forward_derivative(model, weights, max_depth, options, view):
    """The adjoint of the boundary terms: dr.backward of a weighted image sum, dotted with a
    direction, equals the forward derivative along it (same samples)."""
    key = "object.primitive_to_world"
    weights = np.asarray(weights, np.float32)
    rng = np.random.default_rng(0)
    mask = mi.TensorXf(rng.uniform(0, 1, (48, 64, 3)).astype(np.float32))
    forward = forward_gradient(model, "csg_prb_projective", key, weights, 64, (64, 48), max_depth, options, **view)
    sc = scene(model, {"type": "csg_prb_projective", "max_depth": max_depth, **(options or {})}, 64, **view)
    params = mi.traverse(sc)
    value = mi.Float(params[key])
    dr.enable_grad(value)
    params[key] = value
    params.update()
    image = mi.render(sc, params, spp=64, seed=1)
    dr.backward(dr.sum(image * mask, axis=None))
    backward = float(np.dot(np.array(dr.grad(value)), weights))
    expected = float(np.sum(forward * np.array(mask)))
    assert abs(backward - expected) < 0.01 * abs(expected), (backward, expected)


def _recover_radius(integrator, start, iterations=30):
    """Adam on a hole's radius (primitive_scale of the subtracted sphere, target 0.5) from
    one 128x96 view at 8 spp, against a 256-spp csg_path target. Returns the radius."""
    model = csg.Box(2.0) - csg.Sphere(1.0).translate((0.3, -0.8, 0.4))
    target_scene = scene(model, {"type": "csg_path", "max_depth": 2}, 256, (128, 96))
    params = mi.traverse(target_scene)
    params["object.primitive_scale"] = mi.Float([1.0, 0.5])
    params.update()
    target = mi.render(target_scene, spp=256, seed=0)
    sc = scene(model, {"type": integrator, "max_depth": 2}, 8, (128, 96))
    params = mi.traverse(sc)
    opt = mi.ad.Adam(lr=0.02)
    opt["radius"] = mi.Float(start)
    for it in range(iterations):
        params["object.primitive_scale"] = mi.Float([1.0, 0.0]) + mi.Float([0.0, 1.0]) * opt["radius"]
        params.update()
        image = mi.render(sc, params, spp=8, seed=it + 1)
        dr.backward(dr.mean(dr.square(image - target), axis=None))
        opt.step()
        opt["radius"] = dr.clip(opt["radius"], 0.05, 1.5)
    return float(opt["radius"][0])


def test_inverse_rendering_recovers_a_hole_radius():
    """From radius 0.4 (the loss falls towards 0.5 from there; below about 0.3 a smaller hole
    matches the target better, as finite differences of the loss show), csg_prb_projective
    ends within 2 % of the box's size of 0.5; csg_prb, blind to the rim's motion, overshoots."""
    assert abs(_recover_radius("csg_prb_projective", 0.4) - 0.5) < 0.04
    assert _recover_radius("csg_prb", 0.4) > 0.6


def test_inverse_rendering_example_recovers_a_cheeses_holes(tmp_path):
    """scenes/inverse_cheese.py, smaller (64x48, 40 iterations): every hole's centre and
    radius within 2 % of the box's edge with csg_prb_projective; not with csg_prb."""
    import importlib.util
    from pathlib import Path
    spec = importlib.util.spec_from_file_location(
        "inverse_cheese", Path(__file__).resolve().parents[1] / "scenes" / "inverse_cheese.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)

    def final_errors(integrator):
        result = example.main(["--integrator", integrator, "--size", "64x48", "--iterations", "40",
                               "--variant", mi.variant(), "--out", str(tmp_path / integrator)])
        last = result["history"][-1]
        return max(last["centre_errors"]), max(last["radius_errors"])
    centre, radius = final_errors("csg_prb_projective")
    assert centre < 0.02 and radius < 0.02, (centre, radius)
    centre, radius = final_errors("csg_prb")
    assert max(centre, radius) > 0.02, (centre, radius)
