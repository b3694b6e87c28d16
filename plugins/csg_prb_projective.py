"""The `csg_prb_projective` integrator: csg_prb plus the primarily visible boundary derivative."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from . import csg_edges
from .csg_common import SceneCSG
from .csg_prb import CSGPRBIntegrator


# Camera rays either side of a curve pass it at this fraction of its distance (about 1e-3
# pixel at 64 pixels over 40 degrees).
OFFSET = 1e-5
# Where the visibility test of a torus contour point starts, as a fraction of its distance.
TORUS_VIEW_OFFSET = 1e-3
# (offset factor, weight) pairs: the differences at OFFSET and 4 OFFSET extrapolated to 0 for a
# difference D(s) = D0 + c sqrt(s) + O(s): beside a contour the surface is seen at grazing
# incidence, its cosine (hence its shading) grows like the square root of the offset.
EXTRAPOLATION = ((1.0, 2.0), (4.0, -1.0))


class CSGPRBProjectiveIntegrator(CSGPRBIntegrator):
    r"""
    .. _integrator-csg_prb_projective:

    CSG projective path replay backpropagation (:monosp:`csg_prb_projective`)
    -------------------------------------------------------------------------

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1: infinite). (Default: 6)
     * - rr_depth
       - |int|
       - Depth from which Russian roulette may end paths. (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide emitters seen directly by the camera. (Default: false)
     * - sppc
       - |int|
       - Samples per pixel of the interior (continuous) derivative; 0 switches it off.
         (Default: the render call's spp)
     * - sppp
       - |int|
       - Boundary samples per pixel of the primarily visible discontinuities; 0 switches
         them off. (Default: the render call's spp)

    `csg_prb`'s derivatives (interior: shading at a fixed visible primitive) plus those of
    the boundaries the camera sees move: silhouettes of sphere, cylinder, cone and torus leaves,
    edges of boxes, convex polyhedra (prisms) and mesh leaves, cylinder and cone rims, the
    edges where a sphere meets a face of a box, polyhedron or mesh, or another sphere (the
    CSG edges of holes), where a cylinder's or cone's side or caps meet such a face, where
    the faces of two boxes or polyhedra (or one of them and a mesh's triangle) meet, and
    the curves with no closed form: where sphere, cylinder, cone and torus leaves meet each
    other, or a torus meets a box's or polyhedron's face (traced into chords on a grid,
    each point moved onto both surfaces by Newton steps).
    Points on those curves are sampled in proportion to their length in the image, each
    moving with the shapes' `primitive_to_world` (and so with the named parameters); the
    estimate is the radiance difference across the curve (camera rays either side of it, at
    two offsets extrapolated to the curve) times the curve's motion normal to itself in the
    image (Mitsuba's `prb_projective` treats its own meshes the same way; Li et al. 2018's
    edge sampling). A curve point the camera does not see (a ray from it towards the camera
    is blocked) adds nothing, and one that is not on the solid's boundary has no radiance
    difference across it. Forward and backward mode.

    Not yet differentiated: the curves of quadrics, where two meshes' triangles meet, where
    a torus meets a mesh's triangles, and indirect visibility (shadows, reflections).
    Perspective cameras only.

    .. code-block:: python

        'integrator': {'type': 'csg_prb_projective', 'max_depth': 4}
    """

    def __init__(self, props: mi.Properties):
        sppc, sppp = props.get("sppc", None), props.get("sppp", None)
        for name, value in (("sppc", sppc), ("sppp", sppp)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
                raise ValueError(f"csg_prb_projective: '{name}' must be a non-negative integer, got {value!r}")
            if value is not None:
                del props[name]
        super().__init__(props)
        self.sppc, self.sppp = sppc, sppp

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        sppc, sppp = self._spp(sensor, spp)
        grad = super().render_forward(scene, params, sensor, seed, sppc) if sppc > 0 else None
        boundary = self.render_boundary(scene, sensor, seed, sppp) if sppp > 0 else None
        if boundary is not None and dr.grad_enabled(boundary):
            dr.forward_to(boundary)
            grad = dr.grad(boundary) if grad is None else grad + dr.grad(boundary)
        if grad is None:
            film = sensor.film()
            grad = dr.zeros(mi.TensorXf, (film.crop_size()[1], film.crop_size()[0], film.base_channels_count()))
        return grad

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        sppc, sppp = self._spp(sensor, spp)
        if sppc > 0:
            super().render_backward(scene, params, grad_in, sensor, seed, sppc)
        boundary = self.render_boundary(scene, sensor, seed, sppp) if sppp > 0 else None
        if boundary is not None and dr.grad_enabled(boundary):
            dr.set_grad(boundary, grad_in)
            dr.enqueue(dr.ADMode.Backward, boundary)
            dr.traverse(dr.ADMode.Backward)
        dr.eval()

    def _spp(self, sensor, spp):
        """(interior, boundary) samples per pixel: the property, else the call's, else the sampler's."""
        fallback = spp or sensor.sampler().sample_count()
        return tuple(fallback if own is None else own for own in (self.sppc, self.sppp))

    def render_boundary(self, scene, sensor, seed, spp):
        """The primarily visible boundary term as an image attached to the shapes' parameters
        (its value is 0; its derivative is the term): forward_to or backward from it."""
        if not sensor.__repr__().startswith("PerspectiveCamera"):
            raise ValueError("csg_prb_projective: boundary derivatives need a perspective camera")
        csg = SceneCSG(scene)
        film = sensor.film()
        to_world = np.array(dr.detach(sensor.world_transform().matrix), np.float64)
        if to_world.ndim == 3 and to_world.shape[-1] != 1:
            raise ValueError("csg_prb_projective: an animated camera is not supported")
        camera = to_world.reshape(4, 4, -1)[:3, 3, 0]
        curves = [csg_edges.Curves(shape, camera) for shape in csg.csg]
        if not sum(c.count for c in curves):
            return None
        shape_of = np.concatenate([np.full(c.count, s, np.uint32) for s, c in enumerate(curves)])
        weights = np.concatenate([c.weight for c in curves])
        data = np.concatenate([c.data for c in curves])
        distribution = mi.DiscreteDistribution(mi.Float(weights.astype(np.float32)))

        sampler, spp = self.prepare(sensor, 0xFFFFFFFF ^ seed, spp, [])
        with dr.suspend_grad():
            index, u, pmf = distribution.sample_reuse_pmf(sampler.next_1d())
            wavelengths, wavelength_weight = sensor.sample_wavelengths(
                dr.zeros(mi.SurfaceInteraction3f), sampler.next_1d() if mi.is_spectral else 0.0)
        kind = dr.gather(mi.UInt32, mi.UInt32(np.concatenate([c.kind for c in curves])), index)
        a = dr.gather(mi.UInt32, mi.UInt32(np.concatenate([c.a for c in curves])), index)
        b = dr.gather(mi.UInt32, mi.UInt32(np.concatenate([c.b for c in curves])), index)
        extra = dr.gather(mi.UInt32, mi.UInt32(np.concatenate([c.extra for c in curves])), index)
        solid = dr.gather(mi.UInt32, mi.UInt32(shape_of), index)
        data = [dr.gather(mi.Float, mi.Float(np.ascontiguousarray(data[:, k])), index) for k in range(data.shape[1])]
        cam = mi.Point3f(*[float(c) for c in camera])

        # The leaves' matrices, attached to each shape's primitive_to_world.
        m_a, t_a, m_b, t_b = mi.Matrix3f(0), mi.Vector3f(0), mi.Matrix3f(0), mi.Vector3f(0)
        for s, shape in enumerate(csg.csg):
            mine = solid == s
            ma, ta = csg_edges.leaf_rows(shape.primitive_to_world, a, mine)
            mb, tb = csg_edges.leaf_rows(shape.primitive_to_world, b, mine)
            m_a, t_a = dr.select(mine, ma, m_a), dr.select(mine, ta, t_a)
            m_b, t_b = dr.select(mine, mb, m_b), dr.select(mine, tb, t_b)
        x, dx, valid = csg_edges.evaluate(kind, extra, m_a, t_a, m_b, t_b, data, cam, u)
        with dr.suspend_grad():
            x_d, dx_d = dr.detach(x), dr.detach(dx)
            speed = dr.norm(dx_d)
            tangent = dx_d / speed
            view = dr.normalize(x_d - cam)
            normal = dr.normalize(dr.cross(tangent, view))
            pdf = pmf / speed                                  # per unit length of the curve
            it = dr.zeros(mi.Interaction3f)
            it.p = x_d
            ds, _ = sensor.sample_direction(it, mi.Point2f(0), valid)
            valid &= (ds.pdf != 0) & (speed > 0) & dr.isfinite(pdf) & (pdf > 0)
            # Film area per (curve length x normal displacement): Mitsuba's own Jacobian of the
            # camera's projection, for a point moving along `silhouette_d` and `n` (the method
            # reads nothing of its ProjectiveDetail instance).
            sample = dr.zeros(mi.SilhouetteSample3f, dr.width(x_d))
            sample.p, sample.silhouette_d, sample.n = x_d, tangent, normal
            jacobian = mi.ad.ProjectiveDetail.sensor_jacobian(None, sensor, sample)
            # Only a visible curve point: a hidden curve can pass near a visible discontinuity
            # in the image (a hole's sphere's contour just beneath the face runs along the
            # rim, tangent to it where it meets the face), and camera rays either side of the
            # hidden point would measure the jump across the visible one. Tested from just in
            # front of the point, so that its own surfaces do not count.
            # A torus contour point is tested from further away: along its own tangent line,
            # 1e-5 of the distance from a grazing point, the quartic's float32 roots are not
            # exact enough to tell the point's own surface from an occluder (tori cover
            # themselves only a tube's width away).
            towards_camera = cam - x_d
            distance = dr.norm(towards_camera)
            start = dr.select(kind == csg_edges.TORUS_SILHOUETTE, TORUS_VIEW_OFFSET, OFFSET)
            view_ray = mi.Ray3f(x_d + start * towards_camera, towards_camera / distance)
            view_ray.maxt = (1.0 - 2.0 * start) * distance
            valid &= ~csg.occluded(scene, view_ray, valid)
            # The radiance difference across the curve, from camera rays either side of it at
            # offsets d and 4 d, extrapolated to the curve (EXTRAPOLATION): where the surface
            # beside the curve is seen obliquely (a hole's far rim, a silhouette), the hit point
            # moves fast with the offset, and one offset alone is biased by a few percent. The
            # offset, 1e-5 of the distance, stays well above the kernel's tie window.
            offset = OFFSET * dr.norm(x_d - cam)
            delta = mi.Spectrum(0)
            for factor, scale in EXTRAPOLATION:
                inside = self._radiance(scene, sampler, cam, x_d - factor * offset * normal, wavelengths, valid)
                outside = self._radiance(scene, sampler, cam, x_d + factor * offset * normal, wavelengths, valid)
                delta += scale * (inside - outside)
            delta *= wavelength_weight
            valid &= dr.any(delta != 0)
            weight = delta * jacobian / pdf / spp

        # Moving the curve by v . n in the image replaces the outside radiance by the inside.
        motion = dr.dot(x - x_d, normal)
        film.prepare([])
        block = film.create_block(normalize=True)
        block.set_coalesce(block.coalesce() and spp >= 4)
        block.put(pos=ds.uv, wavelengths=wavelengths, value=weight * motion, weight=0, alpha=1, active=valid)
        film.put_block(block)
        return film.develop()

    def _radiance(self, scene, sampler, origin, target, wavelengths, active):
        ray = mi.Ray3f(origin, dr.normalize(target - origin))
        ray.wavelengths = wavelengths
        L, _, _, _ = self.sample(dr.ADMode.Primal, scene, sampler, ray, None, None, active)
        return dr.select(active, L, 0)

    def to_string(self):
        return (f"CSGPRBProjectiveIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"sppc={self.sppc}, sppp={self.sppp}]")
