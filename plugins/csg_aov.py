"""The `csg_aov` integrator: geometric buffers (depth, position, normal, ids) of scenes with CSG."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .csg_common import SceneCSG
from .registry import integrator

AOV_TYPES = {"depth": 1, "position": 3, "uv": 2, "dp_du": 3, "sh_normal": 3, "prim_index": 1, "shape_index": 1}
# Channel suffixes as Mitsuba's own `aov` integrator names them.
_SUFFIXES = {"uv": "UV", "dp_du": "XYZ", "position": "xyz", "sh_normal": "xyz"}


@integrator("csg_aov", "buffers", {"Depth": "", "AOV": ""})
class CSGAOVIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-csg_aov:

    CSG arbitrary output variables (:monosp:`csg_aov`)
    --------------------------------------------------

    .. pluginparameters::

     * - aovs
       - |string|
       - Comma-separated `name:type` list; types: `depth` (distance along the camera ray),
         `position`, `uv`, `dp_du`, `sh_normal`, `prim_index` (index into the model's `leaves()`, or the
         mesh triangle), `shape_index` (index in `scene.shapes()`). Pixels with no hit are 0.
         (Default: `dd.y:depth,p:position,nn:sh_normal,prim:prim_index,shape:shape_index`)
     * - (Nested plugin)
       - |integrator|
       - Optional integrator whose RGB output comes first, as with Mitsuba's `aov`.

    Geometric buffers of the first hit over Mitsuba's shapes and exact CSG shapes alike.

    .. code-block:: python

        'integrator': {'type': 'csg_aov', 'aovs': 'dd.y:depth,nn:sh_normal'}
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        spec = props.get("aovs", "dd.y:depth,p:position,nn:sh_normal,prim:prim_index,shape:shape_index")
        self.aovs = []
        for item in (s.strip() for s in spec.split(",") if s.strip()):
            if item.count(":") != 1:
                raise ValueError(f"csg_aov: \"aovs\": expected name:type, got {item!r}")
            name, kind = item.split(":")
            if kind not in AOV_TYPES:
                raise ValueError(f"csg_aov: \"aovs\": unknown type {kind!r} in {item!r}; "
                                 f"known: {', '.join(AOV_TYPES)}")
            self.aovs.append((name, kind))
        self.inner = None
        for name in props.keys():
            if isinstance(props[name], mi.SamplingIntegrator):
                self.inner = props[name]

    def aov_names(self):
        names = []
        for name, kind in self.aovs:
            n = AOV_TYPES[kind]
            names += [name] if n == 1 else [f"{name}.{c}" for c in _SUFFIXES[kind]]
        return (self.inner.aov_names() if self.inner else []) + names

    def sample(self, scene, sampler, ray, medium=None, active=True):
        csg = SceneCSG(scene)
        if self.inner is not None:
            color, valid, inner_aovs = self.inner.sample(scene, sampler, ray, medium, active)
        else:
            color, valid, inner_aovs = mi.Spectrum(0), mi.Bool(active), []
        ray = mi.Ray3f(dr.detach(ray))
        si, _, csg_hit, csg_prim, csg_shape = csg.intersect(scene, ray, mi.Bool(active))
        hit = si.is_valid()
        shapes = scene.shapes()
        out = list(inner_aovs)
        for _, kind in self.aovs:
            if kind == "depth":
                out.append(dr.select(hit, si.t, 0.0))
            elif kind == "position":
                out += [dr.select(hit, si.p[i], 0.0) for i in range(3)]
            elif kind == "uv":
                out += [dr.select(hit, si.uv[i], 0.0) for i in range(2)]
            elif kind == "dp_du":
                out += [dr.select(hit, si.dp_du[i], 0.0) for i in range(3)]
            elif kind == "sh_normal":
                out += [dr.select(hit, si.sh_frame.n[i], 0.0) for i in range(3)]
            elif kind == "prim_index":
                out.append(dr.select(hit, mi.Float(si.prim_index), 0.0))
            else:
                index = mi.Float(0.0)
                for k, shape in enumerate(csg.csg):
                    index = dr.select(csg_hit & (csg_shape == k), float(csg.shape_index[id(shape)]), index)
                mesh_index = mi.Float(0.0)
                for k, shape in enumerate(shapes):
                    if not getattr(shape, "is_csg_proxy", False):      # the same test as SceneCSG
                        mesh_index = dr.select(si.shape == mi.ShapePtr(shape), float(k), mesh_index)
                out.append(dr.select(hit, dr.select(csg_hit, index, mesh_index), 0.0))
        return color, valid, out

    def to_string(self):
        return f"CSGAOVIntegrator[aovs={self.aovs}]"
