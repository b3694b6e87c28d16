"""The `csg` shape: a CSG model in a Mitsuba scene."""
from __future__ import annotations

import warnings

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_csg.engine.optimize import OptimizedModel
from mitsuba_csg.errors import CSGError
from mitsuba_csg.queries import moved, prepare

from . import model_ref


class CSGShape(mi.Mesh):
    r"""
    .. _shape-csg:

    CSG model (:monosp:`csg`)
    -------------------------

    .. pluginparameters::

     * - filename
       - |string|
       - A model file in a format `mitsuba_csg.load` knows (by extension, e.g. `.json`).
     * - model
       - |string|
       - Instead of `filename`: a model registered with `mitsuba_csg.model_ref(model)`, or the
         text of a native JSON model.
     * - optimize
       - |bool|
       - Optimize the tree (paper §4) before tracing. (Default: true)
     * - to_world
       - |transform|
       - Placement of the model in the scene. (Default: none)
     * - interior, exterior
       - |medium|
       - Media inside and outside the solid, for `csg_volpath`. (Default: none)
     * - (Nested plugin)
       - |bsdf|
       - The default BSDF. BSDFs with an `id` equal to a material name used by the model are
         used for the primitives of that material. (Default: diffuse)

    An exact CSG solid, traced analytically by the `csg_*` integrators. Mitsuba's own
    integrators (`path`, `volpath`, `prb_projective`, `aov`, ...) trace only Mitsuba's
    shapes (to them this is a proxy mesh with one degenerate triangle spanning the model's
    bounding box, which keeps scene bounds right), so rendering a scene that holds a `csg`
    shape with one of them raises an error naming the integrator and the shape rather than
    rendering the scene without the model; render a mesh of the model
    (`mitsuba_csg.to_mesh`) where they are needed. `interior` and `exterior` media are
    crossed at the CSG boundary by `csg_volpath` (a glass solid full of ink, say). It cannot
    be an area emitter, hold other shapes, or sit in a `shapegroup` (instancing: refused, the
    group's own acceleration structure would not see it); any other property is refused by name, as
    Mitsuba's own plugins refuse unused ones, and a BSDF that matches no material once a
    default is chosen is reported as unused.

    Hits carry texture coordinates and tangents, so bitmap textures, normal and bump maps and
    anisotropic BSDFs work: spheres as Mitsuba's `sphere` (u = phi / 2 pi, v = theta / pi),
    cylinder, cone and quadric sides as Mitsuba's `cylinder` (u = phi / 2 pi, v from 0 at the
    bottom to 1 at the top), box faces as Mitsuba's `cube`, caps [0, 1] across, tori by their two
    angles, convex faces by a frame in their plane, mesh triangles by barycentric coordinates;
    the shading frame's tangent follows dp_du.

    `mi.traverse` exposes, all differentiable (`csg_prb` differentiates through them):

    - `primitive_translation`: 3 floats per primitive, in `model.leaves()` order: its centre
      in the model's frame;
    - `primitive_rotation`: 3 floats per primitive, a rotation vector (axis times angle, in
      radians) turning it about its centre, relative to its loaded orientation (0 at load);
    - `primitive_scale`: 1 float per primitive, a uniform scale about its centre relative to
      its loaded size (1 at load): a `Sphere(r)`'s radius is `r * scale`;
    - `to_world`: the placement of the whole model, as Mitsuba's own shapes have it;
    - `primitive_to_world`: 12 floats per primitive, the rows of the 3x4 matrix that maps the
      primitive's canonical solid to world space, composed from the above as
      `to_world . [R(rotation) . scale . L | translation]` (L the loaded linear part). Its
      linear part holds the sizes: a `Sphere(r)` has `r * R`, a `Box(size)` has
      `R * diag(size) / 2`, a `Cylinder(r, h)` has `R * diag(r, r, h / 2)`, so writing it
      directly changes sizes per axis; such a write becomes the new base of the named
      parameters (translation = the centres, rotation 0, scale 1). One update may change
      either the matrices or the named parameters.

    After `params.update()` the tree's boxes and kernel arrays are re-derived (the tree
    itself is kept). To recover a hole's position and radius:

    .. code-block:: python

        params = mi.traverse(scene)
        opt = mi.ad.Adam(lr=0.02)
        opt['t'] = params['cheese.primitive_translation']
        opt['s'] = params['cheese.primitive_scale']
        for it in range(100):
            params['cheese.primitive_translation'] = opt['t']
            params['cheese.primitive_scale'] = opt['s']
            params.update()
            image = mi.render(scene, params, spp=16, seed=it)     # with csg_prb
            dr.backward(dr.mean(dr.square(image - target), axis=None))
            opt.step()

    Placing the model:

    .. code-block:: python

        import mitsuba_csg as csg
        m = csg.Box(2.0) - csg.Sphere(1.2)
        shape = {'type': 'csg', 'model': csg.model_ref(m),
                 'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': [0.8, 0.6, 0.2]}}}
    """

    is_csg_proxy = True

    def __init__(self, props: mi.Properties):
        model, source = _model_from(props)
        optimize = props.get("optimize", True)
        if not isinstance(optimize, bool):
            raise CSGError(f"csg shape ({source}): 'optimize' must be a boolean (<boolean name=\"optimize\" "
                           f"value=\"false\"/>), got {type(optimize).__name__} {str(optimize)[:40]!r}")
        to_world = props.get("to_world", mi.ScalarTransform4f())
        if not hasattr(to_world, "matrix"):
            raise CSGError(f"csg shape ({source}): 'to_world' must be a transform (<transform name=\"to_world\">), "
                           f"got {type(to_world).__name__} {str(to_world)[:40]!r}")
        # BSDF children: the default one plus one per material name; Mesh only takes one.
        # Every other property is refused by name, as Mitsuba's own plugins refuse unused ones.
        bsdfs = {}
        for name in list(props.keys()):
            if name in _PROPERTIES:
                del props[name]
                continue
            value = props[name]
            if isinstance(value, mi.Emitter):
                raise CSGError(f"csg shape ({source}): cannot be an area emitter (it is traced analytically, "
                               "and its proxy mesh has no area); put the light on an ordinary shape")
            if isinstance(value, mi.BSDF):
                bsdfs[value.id() or name] = value
                del props[name]
            elif isinstance(value, mi.Shape):
                raise CSGError(f"csg shape ({source}): cannot hold other shapes ('{name}'); put them beside it in "
                               f"the scene, or make them part of the model")
            elif isinstance(value, mi.Medium):
                if name not in ("interior", "exterior"):
                    raise CSGError(f"csg shape ({source}): a medium goes in 'interior' or 'exterior', not '{name}'")
                # Kept for Mitsuba's Shape: csg_volpath crosses it at the CSG boundary.
            else:
                raise CSGError(f"csg shape ({source}): unknown property '{name}'; a csg shape takes filename or "
                               f"model, optimize, to_world and BSDFs")
        matrix = np.array(to_world.matrix, dtype=np.float64).reshape(4, 4)
        if isinstance(model, OptimizedModel):
            model = model.source
        if not np.allclose(matrix, np.eye(4)):
            model = model.transform(matrix)
        self.model = model
        self.source = source
        self.optimize = bool(optimize)
        self.prepared = prepare(model, optimize=self.optimize)
        flat = self.prepared.flat
        self.primitive_to_world = mi.Float(flat.prim_to_world[:, :3, :].astype(np.float32).ravel())
        # Named, differentiable parameters (parameters_changed composes primitive_to_world from them).
        self.to_world = mi.Transform4f(matrix.tolist())
        self.primitive_translation = mi.Float(np.zeros(3 * flat.num_prims, np.float32))
        self.primitive_rotation = mi.Float(np.zeros(3 * flat.num_prims, np.float32))
        self.primitive_scale = mi.Float(np.ones(flat.num_prims, np.float32))
        self._rebase(flat.prim_to_world[:, :3, :], matrix)
        super().__init__(f"csg:{source}", 2, 1, props)
        self._setup_materials(bsdfs)
        self._update_proxy_bounds()
        self.add_attribute("face_csgproxy", 1, [0.0])   # keeps the loader from merging proxies

    def _update_proxy_bounds(self):
        flat = self.prepared.flat
        lower, upper = flat.node_lower[flat.root], flat.node_upper[flat.root]
        self._proxy_traversal = True
        try:
            params = mi.traverse(self)
        finally:
            self._proxy_traversal = False
        params["vertex_positions"] = mi.Float(np.concatenate([lower, upper]).astype(np.float32))
        params["faces"] = mi.UInt32([0, 0, 0])
        params.update()

    def traverse(self, callback):
        # The proxy mesh's own buffers (two box corners, one degenerate face) are ours to set;
        # users see only what moves the model.
        if getattr(self, "_proxy_traversal", False):
            super().traverse(callback)
            return
        callback.put("primitive_to_world", self.primitive_to_world, mi.ParamFlags.Differentiable)
        for name in _NAMED_PARAMETERS:
            callback.put(name, getattr(self, name), mi.ParamFlags.Differentiable)
        for name, bsdf in self.material_bsdfs.items():
            callback.put(f"material_{name}", bsdf, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        named = [k for k in keys if k in _NAMED_PARAMETERS]
        if "primitive_to_world" in keys and named:
            raise CSGError(f"csg shape: primitive_to_world and {', '.join(named)} changed in one update; "
                           "set either the matrices or the named parameters")
        if "primitive_to_world" in keys:
            rows = self._checked_rows(self.primitive_to_world)
            self._rebase(rows, np.array(self.to_world.matrix, np.float64)[..., 0])
        elif named:
            self._check_named()
            mi.set_property(self.primitive_to_world, self._compose())
            rows = self._checked_rows(self.primitive_to_world)
        else:
            super().parameters_changed(keys)
            return
        to_world = self.prepared.flat.prim_to_world.copy()
        to_world[:, :3, :] = rows
        self.prepared = moved(self.prepared, to_world)
        super().parameters_changed([])
        self._update_proxy_bounds()

    def _checked_rows(self, values) -> np.ndarray:
        rows = np.array(dr.detach(values), dtype=np.float64)
        count = self.prepared.flat.num_prims
        if rows.size != 12 * count:
            raise CSGError(f"csg shape: primitive_to_world needs {12 * count} values, got {rows.size}")
        rows = rows.reshape(-1, 3, 4)
        dets = np.linalg.det(rows[:, :, :3])
        if not np.all(np.isfinite(rows)) or np.any(np.abs(dets) < 1e-30):
            raise CSGError("csg shape: primitive_to_world has NaN or singular matrices")
        return rows

    def _check_named(self):
        count = self.prepared.flat.num_prims
        for name, per in (("primitive_translation", 3), ("primitive_rotation", 3), ("primitive_scale", 1)):
            values = np.array(dr.detach(getattr(self, name)), dtype=np.float64)
            if values.size != per * count:
                raise CSGError(f"csg shape: {name} needs {per * count} values ({per} per primitive), got {values.size}")
            if not np.all(np.isfinite(values)):
                raise CSGError(f"csg shape: {name} has NaN or infinite values")
        scale = np.array(dr.detach(self.primitive_scale), dtype=np.float64)
        if np.any(scale <= 0):
            raise CSGError(f"csg shape: primitive_scale must be positive (primitive {int(np.argmin(scale))} has "
                           f"{scale.min():g})")
        matrix = np.array(dr.detach(self.to_world.matrix), np.float64)[..., 0]
        if not np.all(np.isfinite(matrix)) or abs(np.linalg.det(matrix[:3, :3])) < 1e-30:
            raise CSGError("csg shape: to_world has NaN or is singular")

    def _rebase(self, rows: np.ndarray, to_world: np.ndarray):
        """Make (P, 3, 4) world matrices the base of the named parameters: translation = each
        primitive's centre in the model's frame, rotation 0, scale 1."""
        inverse = np.linalg.inv(to_world)
        linear = np.einsum("ij,pjk->pik", inverse[:3, :3], rows[:, :, :3])
        centre = np.einsum("ij,pj->pi", inverse[:3, :3], rows[:, :, 3]) + inverse[:3, 3]
        self._base_linear = linear
        mi.set_property(self.primitive_translation, mi.Float(centre.astype(np.float32).ravel()))
        mi.set_property(self.primitive_rotation, dr.zeros(mi.Float, 3 * len(rows)))
        mi.set_property(self.primitive_scale, dr.ones(mi.Float, len(rows)))

    def _compose(self):
        """primitive_to_world = to_world . [R(rotation) . scale . base linear | translation],
        per primitive, with Dr.Jit's AD: gradients reach the named parameters through it."""
        count = len(self._base_linear)
        t = dr.unravel(mi.Point3f, self.primitive_translation)
        rotation = _rotation_matrix(dr.unravel(mi.Vector3f, self.primitive_rotation))
        base = mi.Matrix3f(*[mi.Float(self._base_linear[:, i, j].astype(np.float32))
                             for i in range(3) for j in range(3)])
        linear = (rotation @ base) * self.primitive_scale
        outer = self.to_world
        world_linear = mi.Matrix3f(outer.matrix) @ linear
        world_t = outer @ t
        rows = dr.zeros(mi.Float, 12 * count)
        base_index = dr.arange(mi.UInt32, count) * 12
        for i in range(3):
            for j in range(3):
                dr.scatter(rows, world_linear[i][j], base_index + 4 * i + j)
            dr.scatter(rows, world_t[i], base_index + 4 * i + 3)
        return rows

    def _setup_materials(self, bsdfs: dict):
        names = self.prepared.flat.prim_material
        materials = sorted(set(n for n in names if n))
        default = None
        for key, bsdf in bsdfs.items():
            if key in materials:
                continue
            if default is None:
                default = bsdf
            else:          # Mitsuba would warn of an unused child; so do we, with what would match
                warnings.warn(f"csg shape ({self.source}): BSDF '{key}' is not used: it matches no material of "
                              f"the model ({', '.join(materials) or 'the model names none'}) and another BSDF "
                              f"is already the default", UserWarning, stacklevel=2)
        if default is None:
            default = mi.load_dict({"type": "diffuse"})
        self.set_bsdf(default)
        table = [default]
        index = {}
        for name in sorted(set(n for n in names if n)):
            index[name] = len(table)
            table.append(bsdfs.get(name, default))
        self.bsdf_table = table
        self.material_bsdfs = {n: bsdfs[n] for n in index if n in bsdfs}
        self.prim_bsdf_index = mi.UInt32(np.array([index.get(n, 0) for n in names], dtype=np.uint32))
        self.bsdf_ptrs = mi.BSDFPtr(table)

    def prim_bsdf(self, prim, active):
        """The BSDF of each hit primitive (a BSDFPtr array)."""
        idx = dr.gather(mi.UInt32, self.prim_bsdf_index, prim, active)
        return dr.gather(mi.BSDFPtr, self.bsdf_ptrs, idx, active)

    def to_string(self):
        flat = self.prepared.flat
        lower, upper = flat.node_lower[flat.root], flat.node_upper[flat.root]
        bsdfs = ", ".join(f"{name} -> {type(b).__name__}[{b.id()}]" for name, b in self.material_bsdfs.items())
        return (f"CSGShape[source={self.source!r}, primitives={flat.num_prims}, nodes={flat.num_nodes}, "
                f"height={flat.height}, optimize={self.optimize}, bounds=[{lower.tolist()}, {upper.tolist()}], "
                f"default bsdf={self.bsdf().id()!r}, materials={{{bsdfs}}}]")


_PROPERTIES = ("filename", "model", "optimize", "to_world")
# mi.traverse names that compose primitive_to_world (see the docstring).
_NAMED_PARAMETERS = ("to_world", "primitive_translation", "primitive_rotation", "primitive_scale")


def _rotation_matrix(v):
    """Rodrigues' rotation for rotation vectors v (axis times angle, radians), differentiable at 0."""
    theta2 = dr.squared_norm(v)
    theta = dr.sqrt(dr.maximum(theta2, 1e-12))
    small = theta2 < 1e-6
    # sin(t) / t and (1 - cos(t)) / t^2, by their series near 0 (no 0 / 0 in value or gradient)
    a = dr.select(small, 1.0 - theta2 / 6.0, dr.sin(theta) / theta)
    b = dr.select(small, 0.5 - theta2 / 24.0, (1.0 - dr.cos(theta)) / dr.maximum(theta2, 1e-12))
    k = mi.Matrix3f(0.0, -v.z, v.y,
                    v.z, 0.0, -v.x,
                    -v.y, v.x, 0.0)
    return dr.identity(mi.Matrix3f) + k * a + (k @ k) * b


def _model_from(props):
    if ("filename" in props) == ("model" in props):
        raise CSGError("csg shape: give exactly one of 'filename' or 'model'")
    for key in ("filename", "model"):
        if key in props and not isinstance(props[key], str):
            raise CSGError(f"csg shape: '{key}' must be a string, got {type(props[key]).__name__}")
    if "filename" in props:
        from mitsuba_csg import load
        path = str(props["filename"])
        resolved = mi.file_resolver().resolve(path)
        return load(str(resolved)), path
    return model_ref.resolve(str(props["model"])), "inline model"
