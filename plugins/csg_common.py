"""What the csg_* integrators share: finding CSG shapes and intersecting scenes with them."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_csg.engine.grouping import group_trees
from mitsuba_csg.engine.hit_geometry import attached_hit, hit_normal, surface_coordinates
from mitsuba_csg.engine.layout import NO_INDEX
from mitsuba_csg.queries import prepare, trace_rays

from . import integrator_guard


# Grouped trees of recent shape sets, keyed by the identity of the shapes' prepared trees
# (which are kept alive with the entry, so the ids stay theirs): integrators build a
# SceneCSG per render, and a group's upload would otherwise repeat every frame.
_GROUP_CACHE: dict = {}
_GROUP_CACHE_SIZE = 4


def _grouped(prepared: list):
    key = tuple(id(p) for p in prepared)
    entry = _GROUP_CACHE.get(key)
    if entry is None:
        grouped = group_trees([p.flat for p in prepared])
        first = prepared[0]
        traced = prepare(grouped.flat, first.tree.b, max_iterations=first.max_iterations,
                         traversal=first.tree.options)
        entry = (list(prepared), traced, mi.UInt32(grouped.solid_of_prim().astype("uint32")),
                 mi.UInt32(grouped.prim_offset.astype("uint32")))
        if len(_GROUP_CACHE) >= _GROUP_CACHE_SIZE:
            _GROUP_CACHE.pop(next(iter(_GROUP_CACHE)))
        _GROUP_CACHE[key] = entry
    return entry[1:]


class SceneCSG:
    """The CSG shapes of a scene and whether anything else (meshes, spheres, ...) is in it."""

    def __init__(self, scene: mi.Scene, media: bool = False):
        """`media`: the integrator traces participating media (csg_volpath); the others refuse
        scenes with media rather than render them as if the media were absent."""
        shapes = scene.shapes()
        for shape in shapes if not media else ():
            if shape.interior_medium() is not None or shape.exterior_medium() is not None:
                raise ValueError(f"only csg_volpath traces participating media, and shape "
                                 f"{shape.id() or type(shape).__name__!r} has an interior or exterior medium; "
                                 f"render it with csg_volpath")
        for sensor in scene.sensors() if not media else ():
            if sensor.get_medium() is not None:
                raise ValueError(f"only csg_volpath traces participating media, and sensor "
                                 f"{sensor.id() or type(sensor).__name__!r} sits in a medium; render it with "
                                 f"csg_volpath")
        # Duck-typed: each Mitsuba variant has its own CSGShape class.
        self.csg = integrator_guard.csg_shapes(scene)
        self.shape_index = {id(s): i for i, s in enumerate(shapes)}
        # Embree costs tens of ms per frame even for tiny scenes: skip it if all is CSG.
        self.has_others = len(self.csg) < len(shapes)
        # Grouped here, before any symbolic loop: buffers made inside a loop body belong to it.
        self._traced()

    def intersect(self, scene: mi.Scene, ray: mi.Ray3f, active, attached: bool = False, start_prim=None):
        """Nearest surface interaction over Mitsuba's shapes and the CSG shapes.

        Returns (si, bsdf, csg_hit, csg_prim, csg_shape): the BSDF pointer per lane (per
        primitive material on CSG hits), whether the hit is on a CSG shape, and which.
        With `attached`, CSG hits carry derivatives of t, p and n with respect to the
        shapes' `primitive_to_world` (call it inside `dr.resume_grad`). `start_prim`: where
        the ray leaves a CSG hit, `start_of` that hit (a hint that saves traversal work).
        """
        if self.has_others:
            si = scene.ray_intersect(ray, mi.RayFlags.All, coherent=False, active=active)
        else:
            si = dr.zeros(mi.SurfaceInteraction3f, dr.width(ray.d))
            si.t = dr.inf
            si.wavelengths = ray.wavelengths
        bsdf = si.bsdf(ray)
        if not self.csg:
            return si, bsdf, mi.Bool(False), mi.UInt32(0), mi.UInt32(0)
        hits = self.trace(ray, dr.minimum(ray.maxt, si.t), active, start_prim)
        csg_hit = mi.Bool(active & (hits.t < si.t) & dr.isfinite(hits.t))
        csg_si, csg_bsdf, local_prim, solid = self.interaction(ray, hits.t, hits.prim, hits.info, csg_hit, attached,
                                                               hits.normal)
        si = dr.select(csg_hit, csg_si, si)
        bsdf = dr.select(csg_hit, csg_bsdf, bsdf)
        return si, bsdf, csg_hit, dr.select(csg_hit, local_prim, 0), dr.select(csg_hit, solid, 0)

    def traced_tree(self):
        """The device tree `trace` walks (primitives numbered as its hits name them)."""
        return self._traced()[0].tree

    def trace(self, ray: mi.Ray3f, maxt, active, start_prim=None):
        """The CSG shapes' first hits along `ray` up to `maxt` (`RayHits`: t, the traced
        tree's primitive, and the info word with the hit's face), Mitsuba's shapes ignored."""
        return trace_rays(self._traced()[0], ray.o, ray.d, 0.0, dr.detach(maxt), active=active, start_prim=start_prim)

    def interaction(self, ray: mi.Ray3f, t, prim, info, active, attached: bool = False, normal=None):
        """The surface interaction of a CSG shape at ray(t) on face `info` of the traced
        tree's primitive `prim` (as `trace` gives them): (si, bsdf, the shape's own primitive,
        which shape). The point need not be where that face wins along the ray: an edge's
        point gets the frame and BSDF of either face that meets there. `attached` as in
        `intersect`; `normal`: the face's normal there, where the trace gave it already."""
        prepared, solid_of_prim, prim_offset = self._traced()
        t = mi.Float(t)
        if normal is None:
            normal = hit_normal(prepared.tree, prim, info, ray.o, ray.d, dr.detach(t), active)
        n = mi.Normal3f(normal)
        prim = mi.UInt32(prim)               # in the traced tree: all shapes' primitives one after another
        p = ray(t)
        if solid_of_prim is None:
            solid, local_prim = mi.UInt32(0), prim
        else:
            solid = dr.gather(mi.UInt32, solid_of_prim, prim, active)
            local_prim = prim - dr.gather(mi.UInt32, prim_offset, solid, active)
        uv, dp_du, dp_dv = surface_coordinates(prepared.tree, prim, info, ray.o, ray.d,
                                               dr.detach(dr.select(active, t, 0.0)), active)
        shape_ptr = mi.ShapePtr(self.csg[0])
        bsdf = dr.zeros(mi.BSDFPtr, dr.width(ray.d))
        for k, shape in enumerate(self.csg):
            on_k = active & (solid == k)
            if attached:
                t_k, p_k, n_k = attached_hit(shape.primitive_to_world, shape.prepared.tree, local_prim,
                                             mi.UInt32(info), dr.select(on_k, t, 0.0), ray.o, ray.d, on_k)
                t, p, n = (dr.select(on_k, mi.Float(t_k), t), dr.select(on_k, mi.Point3f(p_k), p),
                           dr.select(on_k, mi.Normal3f(n_k), n))
            bsdf = dr.select(on_k, shape.prim_bsdf(local_prim, on_k), bsdf)
            shape_ptr = dr.select(on_k, mi.ShapePtr(shape), shape_ptr)
        dp_du, dp_dv = mi.Vector3f(dp_du), mi.Vector3f(dp_dv)
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(ray.d))
        si.t = t
        si.p = p
        si.n = n
        si.uv = mi.Point2f(uv)
        si.dp_du, si.dp_dv = dp_du, dp_dv
        # The shading frame's tangent follows dp_du (Gram-Schmidt against n), as Mitsuba's
        # shapes set it; where dp_du vanishes (a sphere's pole) any frame about n.
        tangent = dp_du - n * dr.dot(n, dp_du)
        usable = dr.squared_norm(tangent) > 1e-20 * dr.squared_norm(dp_du) + 1e-30
        frame = mi.Frame3f(n)
        s_axis = dr.select(usable, dr.normalize(tangent), frame.s)
        si.sh_frame = mi.Frame3f(s_axis, dr.cross(n, s_axis), n)
        si.wi = si.to_local(-ray.d)
        si.prim_index = local_prim
        si.shape = shape_ptr
        si.time = ray.time
        si.wavelengths = ray.wavelengths
        return si, bsdf, local_prim, solid

    def occluded(self, scene: mi.Scene, ray: mi.Ray3f, active, start_prim=None):
        """Shadow test of `ray` (up to ray.maxt) against Mitsuba's shapes and the CSG shapes;
        `start_prim` as in `intersect`."""
        blocked = scene.ray_test(ray, active) if self.has_others else mi.Bool(False)
        if self.csg:
            hits = trace_rays(self._traced()[0], ray.o, ray.d, 0.0, dr.detach(ray.maxt), active=active & ~blocked,
                              start_prim=start_prim)
            blocked |= active & mi.Bool(dr.isfinite(hits.t))
        return blocked

    def start_of(self, csg_hit, csg_prim, csg_shape):
        """Per lane, the traced tree's primitive of an `intersect` hit (NO_INDEX off CSG shapes):
        the `start_prim` of rays that continue from it."""
        _, _, prim_offset = self._traced()
        prim = mi.UInt32(csg_prim)
        if prim_offset is not None:
            prim += dr.gather(mi.UInt32, prim_offset, csg_shape, csg_hit)
        return dr.select(csg_hit, prim, mi.UInt32(NO_INDEX))

    def _traced(self):
        """(prepared tree, solid of each primitive, first primitive of each solid) to trace:
        a lone shape's own tree, or all shapes grouped into one (`engine.grouping`), so that a
        ray runs one traversal, not one per shape. The group is rebuilt when a shape's tree
        changes (a parameter update replaces `shape.prepared`)."""
        if len(self.csg) <= 1:
            return (self.csg[0].prepared if self.csg else None), None, None
        return _grouped([shape.prepared for shape in self.csg])


def check_depth_types(props, name: str) -> None:
    """max_depth and rr_depth must be integers, as Mitsuba's own integrators require
    (`max_depth: 2.5` is refused there, not rounded)."""
    for key in ("max_depth", "rr_depth"):
        if key in props and (isinstance(props[key], bool) or not isinstance(props[key], int)):
            raise ValueError(f"{name}: \"{key}\" must be an integer, got {type(props[key]).__name__} "
                             f"{props[key]!r}")


def read_depths(props, name: str):
    """max_depth and rr_depth as Mitsuba's ADIntegrator reads them, for non-AD integrators."""
    check_depth_types(props, name)
    max_depth = props.get("max_depth", 6)
    if max_depth < 0 and max_depth != -1:
        raise ValueError(f"{name}: \"max_depth\" must be set to -1 (infinite) or a value >= 0")
    rr_depth = props.get("rr_depth", 5)
    if rr_depth <= 0:
        raise ValueError(f"{name}: \"rr_depth\" must be set to a value greater than zero!")
    return (2**32 - 1 if max_depth == -1 else max_depth), rr_depth


def read_hide_emitters(props, name: str) -> bool:
    hide = props.get("hide_emitters", False)
    if not isinstance(hide, bool):
        raise ValueError(f"{name}: \"hide_emitters\" must be a boolean, got {hide!r}")
    return hide


def camera_ray_valid(scene: mi.Scene, hide_emitters: bool, depth):
    """The alpha of a camera ray, as Mitsuba's path tracers give it: a ray that hits something
    is valid, and so is every ray when a visible environment emitter lies behind the scene."""
    if scene.environment() is not None and not hide_emitters:
        return dr.full(mi.Bool, True, dr.width(depth))
    return depth != 0
