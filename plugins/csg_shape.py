"""The `csg` shape: a CSG model in a Mitsuba scene."""
from __future__ import annotations

import warnings

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_csg.engine.device import upload
from mitsuba_csg.engine.lowering import with_primitive_transforms
from mitsuba_csg.engine.optimize import OptimizedModel
from mitsuba_csg.errors import CSGError
from mitsuba_csg.queries import Prepared, prepare

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
    (`mitsuba_csg.to_mesh`) where they are needed. It cannot be an area emitter, hold other
    shapes or media, or sit in a `shapegroup` (instancing: refused, the group's own
    acceleration structure would not see it); any other property is refused by name, as
    Mitsuba's own plugins refuse unused ones, and a BSDF that matches no material once a
    default is chosen is reported as unused.

    Hits carry texture coordinates and tangents, so bitmap textures, normal and bump maps and
    anisotropic BSDFs work: spheres as Mitsuba's `sphere` (u = phi / 2 pi, v = theta / pi),
    cylinder, cone and quadric sides as Mitsuba's `cylinder` (u = phi / 2 pi, v from 0 at the
    bottom to 1 at the top), caps and box faces [0, 1] across each face, tori by their two
    angles, convex faces by a frame in their plane, mesh triangles by barycentric coordinates;
    the shading frame's tangent follows dp_du.

    `mi.traverse` exposes `primitive_to_world` (differentiable): 12 floats per primitive,
    in `model.leaves()` order, the rows of the 3x4 matrix that maps the primitive's
    canonical solid to world space. Its last column is the primitive's centre; its linear
    part holds the sizes: a `Sphere(r)` has `r * R` (R a rotation), a `Box(size)` has
    `R * diag(size) / 2`, a `Cylinder(r, h)` has `R * diag(r, r, h / 2)`. After
    `params.update()` the tree's boxes and kernel arrays are re-derived (the tree itself is
    kept). `csg_prb` differentiates through it.

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
                raise CSGError(f"csg shape ({source}): media ('{name}') are not supported on csg shapes: the csg_* "
                               f"integrators do not trace participating media")
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
        for name, bsdf in self.material_bsdfs.items():
            callback.put(f"material_{name}", bsdf, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        if "primitive_to_world" in keys:
            rows = np.array(dr.detach(self.primitive_to_world), dtype=np.float64).reshape(-1, 3, 4)
            flat = self.prepared.flat
            if len(rows) != flat.num_prims:
                raise CSGError(f"csg shape: primitive_to_world needs {12 * flat.num_prims} values, got {12 * len(rows)}")
            to_world = flat.prim_to_world.copy()
            to_world[:, :3, :] = rows
            dets = np.linalg.det(to_world[:, :3, :3])
            if not np.all(np.isfinite(rows)) or np.any(np.abs(dets) < 1e-30):
                raise CSGError("csg shape: primitive_to_world has NaN or singular matrices")
            flat = with_primitive_transforms(flat, to_world)
            self.prepared = Prepared(flat, upload(flat, self.prepared.tree.b))
            super().parameters_changed([])
            self._update_proxy_bounds()
        else:
            super().parameters_changed(keys)

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
