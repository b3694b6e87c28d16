"""The `csg_prb_projective` integrator: csg_prb plus the boundary derivatives of what the camera
sees directly, of the shadows lights cast on it, and of the curves and shadows the surfaces it
sees see."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_csg.engine import layout as K
from mitsuba_csg.engine.backend import owned
from mitsuba_csg.engine.hit_geometry import face_at

from . import csg_edges
from .csg_common import SceneCSG
from .csg_prb import CSGPRBIntegrator
from .registry import integrator

# max_depth -1 (no bound) as Mitsuba's integrators hold it: an unsigned 32-bit word.
UNBOUNDED_DEPTH = 0xFFFFFFFF


# Camera rays either side of a curve pass it at this fraction of its distance (about 1e-3
# pixel at 64 pixels over 40 degrees).
OFFSET = 1e-5
# How far from a contour point (sphere, cone, torus) a ray along its viewpoint's line may meet
# the point's own leaf again and be stepped past, as a fraction of the scale
# (`_first_hit_past_own`).
CONTOUR_VIEW_OFFSET = 1e-3
# Camera rays either side of a shadow's edge pass it at this fraction of its distance: the
# receiver's shadow rays then pass the caster's contour at about that fraction of their
# length, and at 1e-5 a float32 sphere test near tangency told the two sides apart only
# part of the time (the radiance difference came out of the wrong sign for 59 % of the
# points along part of a sphere's shadow). Shadow rays from beside a shadow's edge on its
# receiver (`_shadow_jump`) start this fraction of the caster's distance from the edge.
SHADOW_OFFSET = 1e-3
# Rays from a surface point the camera sees pass a curve at this fraction of its distance
# either side (the indirect term). Measured on a dark box with a notch cut into its top
# edge, seen against a lit wall from the floor (the radius's derivative, central
# differences 189-190): 170.9 at 1e-3, 185.4 at 1e-4, 186.7 at 3e-5, 187.0 at 1e-5; a
# sphere's contour gave the same at all four.
INDIRECT_OFFSET = 3e-5
# A camera ray to a shadow's edge passing its casting point closer than this fraction of the
# point's distance sees the edge right behind the caster's own contour.
SHADOW_GAP = 1e-3
# A face found beside a curve point passes through it where the point lies within this of
# the face's surface, in units of the face's canonical shape (a unit sphere, cube, ...).
FACE_GAP = 1e-4
# A face whose normal at a curve point makes a cosine below this with the line of sight is
# seen edge-on there (a contour): its limit at the curve is left to rays beside the point.
CONTOUR_COSINE = 1e-3
# (offset factor, weight) pairs: the differences at OFFSET and 4 OFFSET extrapolated to 0 for a
# difference D(s) = D0 + c sqrt(s) + O(s): beside a contour the surface is seen at grazing
# incidence, its cosine (hence its shading) grows like the square root of the offset.
EXTRAPOLATION = ((1.0, 2.0), (4.0, -1.0))


@integrator("csg_prb_projective", "differentiable, with visibility",
            {"Projective": "", "DirectProjective": "with max_depth 2"})
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
       - Boundary samples per pixel of the primarily visible discontinuities and of the
         shadows lights cast on what the camera sees; 0 switches them off. (Default: the
         render call's spp)
     * - sppi
       - |int|
       - Boundary samples per pixel of the indirectly visible discontinuities: the curves
         and the lights' shadows as seen from the surfaces the camera sees, which cut off the
         light those surfaces receive by reflection; 0 switches them off. (Default: the render call's spp)

    `csg_prb`'s derivatives (interior: shading at a fixed visible primitive) plus those of
    the boundaries the camera sees move: silhouettes of sphere, cylinder, cone, torus and
    quadric (paraboloid, hyperboloid) leaves, edges of boxes, convex polyhedra (prisms) and
    mesh leaves, rims of cylinders, cones and quadrics, the edges where a sphere meets a
    face of a box, polyhedron or mesh, or another sphere (the CSG edges of holes), where a
    cylinder's or cone's side or caps meet such a face, where the faces of two boxes or
    polyhedra or meshes meet, and the curves with no closed form: where sphere, cylinder,
    cone, torus and quadric leaves meet each other, or a torus or quadric meets a face of a
    box, polyhedron or mesh (traced into chords on a grid, each point moved onto both
    surfaces by Newton steps).
    Points on those curves are sampled in proportion to their length in the image, each
    moving with the shapes' `primitive_to_world` (and so with the named parameters); the
    estimate is the radiance difference across the curve times the curve's motion normal to
    itself in the image (Mitsuba's `prb_projective` treats its own meshes the same way; Li
    et al. 2018's edge sampling). Camera rays passing the point either side name the faces
    there: a face that passes through the point and faces the camera gives the radiance
    leaving the point itself from that face (with its frame and BSDF), the side where the
    solid's surface lies elsewhere (past an occluding edge) what the ray beside the point
    meets, and a contour, whose face is seen edge-on, rays either side at two offsets
    extrapolated to the curve. A curve point the camera does not see (a ray from it towards
    the camera is blocked) adds nothing, nor does one off the solid's boundary (a hole's
    sphere's contour in the air in front of the face it cuts). Forward and backward mode.

    Shadows: the same curves, seen from a light, cast the edges of shadows where the light's
    rays through them meet a surface (the floor, another csg shape, the solid itself); the
    camera sees those edges move as it sees any curve (each edge point the projection of its
    curve point along the light's ray onto the receiver's tangent plane, which moves too
    where the receiver is a csg shape), and the difference across one is the direct light of
    that light alone. Point, spot and directional lights cast sharp shadows; an area light's
    soft shadow is the sum of the sharp shadows of its points, one sampled per boundary
    sample, and an environment light's (`constant`, `envmap`) that of its directions. The
    edges of Mitsuba's meshes (rectangles, cubes, loaded meshes: creases and open
    boundaries) and the contours and rims of its spheres, disks and (open) cylinders cast
    shadows too, counted where they fall on a csg shape, which may move.

    Indirect visibility: a surface the camera sees (a pixel's camera ray meets it at a
    point p) receives light reflected by other surfaces, and the curves as p sees them
    (silhouettes relative to p, edges, CSG edges) cut that light off: a solid's soft
    indirect shadow on the floor beside it, a hole's rim hiding the cavity's far wall from
    its floor. For each pixel sample the same curves are sampled as seen from p; the
    estimate is the difference of the reflected light arriving at p from either side of a
    curve point (rays from p either side of it, extrapolated to the curve as above, without
    the emission of the surface they meet: the shadow term counts light that comes straight
    from an emitter) times p's BSDF and the curve's motion normal to itself on p's sphere
    of directions, relative to p where p moves too. The edges of the lights' shadows move as
    seen from p too (a sphere's shadow on a sunlit wall that lights the floor the camera
    sees): the jump across one is the light of that light its receiver reflects towards p,
    on the side the light reaches (shadow rays from the receiver either side of the edge).
    It needs `max_depth` >= 3 (camera, p, the surface that lights p, a light). Above 3, p
    is also a vertex deeper along the camera's path (the floor that lights the ceiling the
    camera sees): per sample, the first vertex with probability 1/2, else one of the
    deeper ones that a light's path can still reach within `max_depth`, down to the 8th.

    Not yet differentiated: shadows and curves seen in reflections off or through delta BSDFs
    (mirrors, glass). Perspective cameras only.

    .. code-block:: python

        'integrator': {'type': 'csg_prb_projective', 'max_depth': 4}
    """

    def __init__(self, props: mi.Properties):
        sppc, sppp, sppi = props.get("sppc", None), props.get("sppp", None), props.get("sppi", None)
        for name, value in (("sppc", sppc), ("sppp", sppp), ("sppi", sppi)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
                raise ValueError(f"csg_prb_projective: '{name}' must be a non-negative integer, got {value!r}")
            if value is not None:
                del props[name]
        super().__init__(props)
        self.sppc, self.sppp, self.sppi = sppc, sppp, sppi

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        sppc, sppp, sppi = self._spp(sensor, spp)
        grad = super().render_forward(scene, params, sensor, seed, sppc) if sppc > 0 else None
        boundary = self.render_boundary(scene, sensor, seed, sppp, sppi)
        if boundary is not None and dr.grad_enabled(boundary):
            dr.forward_to(boundary)
            grad = dr.grad(boundary) if grad is None else grad + dr.grad(boundary)
        if grad is None:
            film = sensor.film()
            grad = dr.zeros(mi.TensorXf, (film.crop_size()[1], film.crop_size()[0], film.base_channels_count()))
        return grad

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        sppc, sppp, sppi = self._spp(sensor, spp)
        if sppc > 0:
            super().render_backward(scene, params, grad_in, sensor, seed, sppc)
        boundary = self.render_boundary(scene, sensor, seed, sppp, sppi)
        if boundary is not None and dr.grad_enabled(boundary):
            dr.set_grad(boundary, grad_in)
            dr.enqueue(dr.ADMode.Backward, boundary)
            dr.traverse(dr.ADMode.Backward)
        dr.eval()

    def _spp(self, sensor, spp):
        """(interior, primary and shadow boundary, indirect boundary) samples per pixel: the
        property, else the call's, else the sampler's."""
        fallback = spp or sensor.sampler().sample_count()
        return tuple(fallback if own is None else own for own in (self.sppc, self.sppp, self.sppi))

    def render_boundary(self, scene, sensor, seed, spp, spp_indirect=0):
        """The boundary terms as an image attached to the shapes' parameters (its value is 0;
        its derivative is the terms): forward_to or backward from it. The primarily visible
        curves and the shadows they cast from each light onto what the camera sees (`spp`
        samples per pixel), and the curves and shadows seen from the surfaces along the
        camera's paths (`spp_indirect`)."""
        if spp <= 0 and spp_indirect <= 0:
            return None
        if not sensor.__repr__().startswith("PerspectiveCamera"):
            raise ValueError("csg_prb_projective: boundary derivatives need a perspective camera")
        csg = SceneCSG(scene)
        if not csg.csg:
            return None
        film = sensor.film()
        to_world = np.array(dr.detach(sensor.world_transform().matrix), np.float64)
        if to_world.ndim == 3 and to_world.shape[-1] != 1:
            raise ValueError("csg_prb_projective: an animated camera is not supported")
        camera = to_world.reshape(4, 4, -1)[:3, 3, 0]
        film.prepare([])
        block = film.create_block(normalize=True)
        block.set_coalesce(block.coalesce() and min(s for s in (spp, spp_indirect) if s > 0) >= 4)
        # The curves, listed once; each viewpoint (the camera, each light) only weighs them.
        curves = [csg_edges.curves_of(shape) for shape in csg.csg]
        # Mitsuba's shapes stand still, but their shadows on moving csg shapes move, and so
        # do they relative to a moving csg surface that sees them.
        static = csg_edges.StaticCurves(scene) if csg.has_others else None
        static = static if static is not None and static.count else None
        terms = []
        if spp > 0:
            sampler, spp = self.prepare(sensor, 0xFFFFFFFF ^ seed, spp, [])
            ctx = _Pass(scene, sensor, csg, camera, sampler, spp, *self._wavelengths(sensor, sampler))
            terms.append(self._primary_term(ctx, curves))
            if self.max_depth >= 2:                 # else no light reaches a surface the camera sees
                for source in _shadow_sources(scene, sampler, camera):
                    terms.append(self._shadow_term(ctx, curves, source))
                    if static is not None:
                        terms.append(self._shadow_term(ctx, static, source))
            terms = [(*term, ctx.wavelengths) for term in terms if term is not None]
        if spp_indirect > 0 and self.max_depth >= 3:    # camera, what it sees, what lights that, a light
            # A sampler of its own (forked, seeded apart): one lane per pixel sample.
            sampler, spp_indirect = self.prepare(sensor, 0x9E3779B9 ^ seed, spp_indirect, [])
            ctx = _Pass(scene, sensor, csg, camera, sampler, spp_indirect, *self._wavelengths(sensor, sampler))
            casters = [curves] if static is None else [curves, static]
            indirect = [self._indirect_term(ctx, caster) for caster in casters]
            # Every light's shadows, a light at the camera's too: p sees them from elsewhere.
            for source in _shadow_sources(scene, sampler):
                indirect += [self._indirect_shadow_term(ctx, caster, source) for caster in casters]
            terms += [(*term, ctx.wavelengths) for term in indirect if term is not None]
        if not terms:
            return None
        for uv, value, valid, wavelengths in terms:
            block.put(pos=uv, wavelengths=wavelengths, value=value, weight=0, alpha=1, active=valid)
        film.put_block(block)
        return film.develop()

    @staticmethod
    def _wavelengths(sensor, sampler):
        with dr.suspend_grad():
            return sensor.sample_wavelengths(dr.zeros(mi.SurfaceInteraction3f),
                                             sampler.next_1d() if mi.is_spectral else 0.0)

    @staticmethod
    def _sample_curves(ctx, curves, viewpoint, scale=None, view=None):
        """Points on the curves of the scene's csg shapes (`curves`, a `csg_edges.Curves` per
        shape) as seen from `viewpoint` (the camera, or a light), sampled in proportion to
        their length over their distance (`_CurvePoints`, x attached to the shapes'
        parameters), or None where there are no curves. `scale`: the length the
        visibility test's offsets are fractions of (default: the distance to the viewpoint; a
        directional light's stand-in point is far away). `view`: the viewpoint per lane (a
        point sampled on an area light), where `viewpoint` only sets the sampling weights."""
        if not sum(c.count for c in curves):
            return None
        shape_of = np.concatenate([np.full(c.count, s, np.uint32) for s, c in enumerate(curves)])
        weights = np.concatenate([c.weight(viewpoint) for c in curves])
        data = np.concatenate([c.data for c in curves])
        # Tables in memory Dr.Jit owns (`owned`): one mapped from numpy puts its alignment into
        # the kernel, and the kernels that trace paths from them were compiled anew each call.
        distribution = mi.DiscreteDistribution(owned(mi.Float, weights.astype(np.float32)))
        with dr.suspend_grad():
            index, u, pmf = distribution.sample_reuse_pmf(ctx.sampler.next_1d())
        kind = dr.gather(mi.UInt32, owned(mi.UInt32, np.concatenate([c.kind for c in curves])), index)
        a = dr.gather(mi.UInt32, owned(mi.UInt32, np.concatenate([c.a for c in curves])), index)
        b = dr.gather(mi.UInt32, owned(mi.UInt32, np.concatenate([c.b for c in curves])), index)
        extra = dr.gather(mi.UInt32, owned(mi.UInt32, np.concatenate([c.extra for c in curves])), index)
        solid = dr.gather(mi.UInt32, owned(mi.UInt32, shape_of), index)
        data = [dr.gather(mi.Float, owned(mi.Float, np.ascontiguousarray(data[:, k])), index)
                for k in range(data.shape[1])]
        if view is None:
            view = _point(viewpoint)

        # The leaves' matrices, attached to each shape's primitive_to_world.
        m_a, t_a, m_b, t_b = mi.Matrix3f(0), mi.Vector3f(0), mi.Matrix3f(0), mi.Vector3f(0)
        for s, shape in enumerate(ctx.csg.csg):
            mine = solid == s
            ma, ta = csg_edges.leaf_rows(shape.primitive_to_world, a, mine)
            mb, tb = csg_edges.leaf_rows(shape.primitive_to_world, b, mine)
            m_a, t_a = dr.select(mine, ma, m_a), dr.select(mine, ta, t_a)
            m_b, t_b = dr.select(mine, mb, m_b), dr.select(mine, tb, t_b)
        x, dx, valid = csg_edges.evaluate(kind, extra, m_a, t_a, m_b, t_b, data, view, u)
        with dr.suspend_grad():
            valid &= _seen_from(ctx.scene, ctx.csg, dr.detach(x), view, scale, _contour(kind), a, solid, valid)
        return _CurvePoints(x, dx, valid, pmf, kind, a, solid)

    def _difference(self, ctx, curve, offset=OFFSET, radiance=None, jump=None):
        """(film position, value, valid) of the boundary term of an image curve through y
        (`curve`: `_CurvePoints`, y = curve.x attached) with tangent dy/du sampled at `pmf`:
        the radiance difference across it,
        from camera rays either side at offsets d and 4 d extrapolated to the curve
        (EXTRAPOLATION: where the surface beside the curve is seen obliquely, a hole's far
        rim, a silhouette, the hit point moves fast with the offset, and one offset alone is
        biased by a few percent; the offset, 1e-5 of the distance, stays well above the
        kernel's tie window; `offset` sets it), times the film Jacobian, over the pdf; its derivative is the
        term (the curve's motion normal to itself, Mitsuba's own sensor Jacobian). `radiance(target,
        active)`: what the camera sees through `target` (default: the integrator's estimate of
        all of it; a shadow's edge needs only the light that casts it). `jump(y, normal, offset,
        active, radiance)`: the jump across the curve, where not `_jump` of that radiance."""
        scene, sampler, sensor, camera = ctx.scene, ctx.sampler, ctx.sensor, ctx.camera
        y, valid = curve.x, curve.valid
        cam = _point(camera)
        with dr.suspend_grad():
            y_d, dy_d = dr.detach(y), dr.detach(curve.dx)
            speed = dr.norm(dy_d)
            tangent = dy_d / speed
            view = dr.normalize(y_d - cam)
            normal = dr.normalize(dr.cross(tangent, view))
            pdf = curve.pmf / speed                            # per unit length of the curve
            it = dr.zeros(mi.Interaction3f)
            it.p = y_d
            ds, _ = sensor.sample_direction(it, mi.Point2f(0), valid)
            valid &= (ds.pdf != 0) & (speed > 0) & dr.isfinite(pdf) & (pdf > 0)
            # Film area per (curve length x normal displacement): Mitsuba's own Jacobian of the
            # camera's projection, for a point moving along `silhouette_d` and `n` (the method
            # reads nothing of its ProjectiveDetail instance).
            sample = dr.zeros(mi.SilhouetteSample3f, dr.width(y_d))
            sample.p, sample.silhouette_d, sample.n = y_d, tangent, normal
            jacobian = mi.ad.ProjectiveDetail.sensor_jacobian(None, sensor, sample)
            offset = offset * dr.norm(y_d - cam)
            # The curve points once, for all the jump's kernels; the weights once, for the
            # image and its gradient.
            _evaluate(sampler, y_d, dy_d, normal, offset, valid, ds.uv, jacobian, pdf)
            if radiance is None:
                def radiance(target, active):
                    return self._radiance(scene, sampler, cam, target, ctx.wavelengths, active)
            if jump is None:
                delta = _jump(radiance, y_d, normal, offset, valid)
            else:
                delta = jump(y_d, normal, offset, valid, radiance)
            delta *= ctx.wavelength_weight
            valid &= dr.any(delta != 0)
            weight = delta * jacobian / pdf / ctx.spp
            _evaluate(sampler, weight, valid)
        # Moving the curve by v . n in the image replaces the outside radiance by the inside.
        return ds.uv, weight * dr.dot(y - y_d, normal), valid

    def _primary_term(self, ctx, curves):
        """The curves the camera sees directly."""
        sampled = self._sample_curves(ctx, curves, ctx.camera)
        if sampled is None:
            return None
        cam = _point(ctx.camera)

        def jump(y, normal, offset, active, radiance):
            return self._seen_jump(ctx, cam, y, normal, offset, active, radiance)
        return self._difference(ctx, sampled, jump=jump)

    def _seen_jump(self, ctx, camera, x, normal, offset, active, radiance):
        """The jump of the radiance the camera sees across the curve point x (the side
        towards -normal minus the side towards +normal). Camera rays passing x at `offset`
        either side name the faces there.

        Only a point on the solid's boundary has one: a face that a ray beside x meets passes
        through x, and the solid lies beneath it there (a point a little into the face's side
        of x and under it is inside). Elsewhere no jump, even where rays beside x would
        measure one: a hole's sphere's contour, in the air just in front of the face it cuts,
        runs along the visible rim, within `offset` of it in the image near where the two
        touch, and rays beside it would count the rim's jump a second time.

        The limits at the curve, taken at x itself where they can be: a face that passes
        through x and faces the camera gives the radiance leaving x from that face, with its
        own frame and BSDF; across an edge whose other face turns away (an occluding edge),
        the other side is what the camera's ray passing x on that side meets. So a crease
        seen from both sides (a hole's rim above the cavity wall beneath it, a box's edge
        between two visible faces) is the difference of two faces' radiance at x. Beside a face seen
        nearly edge-on, rays at an offset meet it far from x, or miss it for the face
        behind (where a hole's rim meets the contour of its sphere), and no extrapolation in
        the offset mends that. Contours (the face at x seen edge-on) keep `_jump` of rays
        either side, extrapolated to the curve: `radiance(target, active)`, what the camera sees
        through `target` (`_difference`'s). `camera`: the camera's point."""
        scene, csg, sampler, wavelengths = ctx.scene, ctx.csg, ctx.sampler, ctx.wavelengths
        at_x, distance, sides, near, on_boundary, normals = _faces_beside(csg, camera, x, normal, offset, active)
        at_x.wavelengths = wavelengths
        crease = on_boundary & near[0] & near[1]
        crease &= (sides[0].prim != sides[1].prim) | (K.info_face(sides[0].info) != K.info_face(sides[1].info))
        # One face at x faces the camera, the other side lies elsewhere: what the camera's ray
        # passing x on that side meets (that surface is not seen edge-on there, as a
        # contour's face is: no extrapolation in the offset needed; and not the ray through x
        # itself, whose far surface's shadow rays towards a lamp at the camera would graze x).
        edge = on_boundary & ~crease & (near[0] ^ near[1])
        exact = crease | edge
        # Paths leave x from just outside both faces (outside the solid whether the edge
        # is convex or concave: from one face's side only, a concave edge's other face would
        # hide the light): from x along the faces' mean normal, or the visible one's.
        away = dr.normalize(dr.select(crease, normals[0] + normals[1], dr.select(near[0], normals[0], normals[1])))
        leaving = []
        for sign, side, at_face, n in zip((-1.0, 1.0), sides, near, normals):
            at_face = at_face & exact
            si, bsdf, _, _ = csg.interaction(at_x, distance, side.prim, side.info, at_face, normal=n)
            si.p = x + offset * away
            passing = mi.Ray3f(camera, dr.normalize(x + sign * offset * normal - camera))
            passing.wavelengths = wavelengths
            leaving.append(self._path_radiance(scene, sampler, passing, exact, first=(si, bsdf, at_face)))

        beside = _jump(radiance, x, normal, offset, on_boundary & ~exact)
        return dr.select(exact, leaving[0] - leaving[1], beside)

    def _shadow_term(self, ctx, casters, source):
        """The edges of the shadows the curves `casters` cast from a light `source` (a point
        per lane, `_Source`; `_shadow_edges`) as the camera sees them: the difference across
        one is the light of that light alone. Mitsuba's shapes' curves (`csg_edges.StaticCurves`)
        count where they cast onto a csg shape (elsewhere their shadows stand still)."""
        edges = self._shadow_edges(ctx, casters, source)
        if edges is None:
            return None
        scene, csg = ctx.scene, ctx.csg
        cam = _point(ctx.camera)
        with dr.suspend_grad():
            valid = edges.valid & edges.on_csg if edges.static else edges.valid
            # A camera ray to y0 that passes the casting point itself sees the shadow's edge
            # right behind the caster's own contour, which the primary term counts (a light at
            # the camera hides every shadow behind its caster): only edges clear of it count.
            valid &= _edge_in_view(scene, csg, cam, edges.x, edges.receiver.p, valid, SHADOW_GAP)

        def light_of_source(target, active):
            return _direct_light(scene, csg, cam, target, source, ctx.wavelengths, active)
        return self._difference(ctx, _CurvePoints(edges.y, edges.dy, valid, edges.pmf), SHADOW_OFFSET, light_of_source)

    def _shadow_edges(self, ctx, casters, source):
        """The edges of the shadows the curves `casters` cast from a light `source` (`_ShadowEdges`,
        or None where there are no curves): a curve point x the light's point l sees casts the
        edge of a shadow where the light's ray through x, continued, meets a surface (y0,
        normal n). Within that surface's tangent plane the edge is the curve's central
        projection from l, y = l + (x - l) ((y0 - l) . n) / ((x - l) . n), which moves with x,
        and with y0 and n where the receiver is a csg shape (a hole's rim casting its shadow
        into the hole moves with it). Mitsuba's own shapes receive as if they stood still.

        A light at infinity (directional, environment) is seen from a stand-in point far along
        its direction, and its edges are parallel projections, y = x + d ((y0 - x) . n) /
        (d . n), d where its light travels.

        `casters`: the csg shapes' curves (a `csg_edges.Curves` per shape), or those of
        Mitsuba's shapes (`csg_edges.StaticCurves`), which stand still."""
        scene, csg = ctx.scene, ctx.csg
        static = isinstance(casters, csg_edges.StaticCurves)
        parallel = source.away is not None
        size = float(np.linalg.norm(np.array(scene.bbox().extents())))
        lamp = source.lamp
        scale = size if parallel else None
        if static:
            sampled = _sample_static(ctx, casters, source.viewpoint, scale, lamp)
        else:
            sampled = self._sample_curves(ctx, casters, source.viewpoint, scale, lamp)
        if sampled is None:
            return None
        x, dx, valid, kind, pmf = sampled.x, sampled.dx, sampled.valid, sampled.kind, sampled.pmf
        a, solid = sampled.leaf, sampled.solid
        with dr.suspend_grad():
            x_d, dx_d = dr.detach(x), dr.detach(dx)
            away = source.away if parallel else dr.normalize(x_d - lamp)
            found, start = _first_hit_past_own(scene, csg, x_d, away, dr.inf, size if parallel else dr.norm(x_d - lamp),
                                               _contour(kind), a, solid, valid, static)
            valid &= found
            ray = mi.Ray3f(x_d + start * away, away)
        with dr.resume_grad():
            si, bsdf, on_csg, _, _ = csg.intersect(scene, ray, valid, attached=True)
            y0_a, n_a = mi.Point3f(si.p), mi.Vector3f(si.n)
        with dr.suspend_grad():
            receiver = dr.detach(si)
            y0, n = receiver.p, mi.Vector3f(receiver.n)
            valid &= si.is_valid()
            reach = dr.dot(x_d - lamp, n)
            valid &= dr.abs(dr.dot(away, n)) > 1e-6
            # the projection's magnification within the receiver's tangent plane
            magnification = 1.0 if parallel else dr.dot(y0 - lamp, n) / reach
            dy = magnification * (dx_d - away * (dr.dot(dx_d, n) / dr.dot(away, n)))
        if parallel:
            y = x + away * (dr.dot(y0_a - x, n_a) / dr.dot(away, n_a))
        else:
            y = lamp + (x - lamp) * (dr.dot(y0_a - lamp, n_a) / dr.dot(x - lamp, n_a))
        return _ShadowEdges(x_d, y, dy, receiver, bsdf, on_csg, pmf, valid, static)

    def _indirect_term(self, ctx, casters):
        """The curves as seen from the surfaces the camera sees. A pixel sample's camera ray
        meets a surface at p (BSDF f, not a delta); the light p reflects towards the camera
        is the integral over directions w of f cos L(p, w), and a curve point x that p sees,
        at distance r, bounds a region of p's sphere of directions where L jumps. Moving x
        by dx (p by dp) moves that boundary by ((dx - dp) . m) / r across itself (m normal
        to the ray p -> x and to the curve's tangent t), and the curve's length there is
        |t x w| / r per unit length of the curve: the pixel's derivative is the camera's
        weight times f cos times the jump of L across x times both, over the pdf of x. The
        jump is the reflected light only (rays from p either side of x without the emission
        of the surface they meet: light straight from an emitter is the shadow term's), from
        paths that end where the integrator's would (one bounce fewer from the camera's
        surface point).

        `casters`: the csg shapes' curves (a `csg_edges.Curves` per shape), or those of
        Mitsuba's shapes (`csg_edges.StaticCurves`), which stand still but move relative to
        a p on a moving csg shape (only such p are sampled for them).

        p is the camera's surface point, or where max_depth allows, a surface point deeper
        along the sample's path (`_path_vertex`)."""
        static = isinstance(casters, csg_edges.StaticCurves)
        vertex = self._path_vertex(ctx)
        valid = vertex.valid & vertex.on_csg if static else vertex.valid
        p = vertex.si.p
        # Curves as seen from p (silhouettes relative to p), weighed as seen from the camera.
        if static:
            sampled = _sample_static(ctx, casters, ctx.camera, None, p)
        else:
            sampled = self._sample_curves(ctx, casters, ctx.camera, None, p)
        if sampled is None:
            return None
        valid &= sampled.valid

        def jump(x_d, normal, distance, active):
            def radiance(target, active):
                return self._reflected_radiance(ctx.scene, ctx.sampler, vertex.si, target, active, vertex.depth)
            return _jump(radiance, x_d, normal, INDIRECT_OFFSET * distance, active)
        return self._seen_from_vertex(ctx, vertex, _CurvePoints(sampled.x, sampled.dx, valid, sampled.pmf), jump)

    def _indirect_shadow_term(self, ctx, casters, source):
        """The edges of the shadows the curves `casters` cast from a light `source`
        (`_shadow_edges`) as the surfaces the camera sees see them: a sphere's shadow on a lit
        wall moves, and so does the light the wall reflects onto the floor the camera sees.
        The estimate is the indirect term's (`_seen_from_vertex`), the jump across an edge
        point the light of `source` that its receiver reflects towards p, on the lit side
        (`_shadow_jump`). Mitsuba's shapes' curves count where they cast onto a csg shape
        or p is on one (else their shadows stand still relative to p). p as the indirect
        term's (`_path_vertex`)."""
        scene, csg = ctx.scene, ctx.csg
        vertex = self._path_vertex(ctx)
        edges = self._shadow_edges(ctx, casters, source)
        if edges is None:
            return None
        p = vertex.si.p
        with dr.suspend_grad():
            valid = vertex.valid & edges.valid
            if edges.static:
                valid &= edges.on_csg | vertex.on_csg
            # p's own shadow edges (y0 at p) add nothing: p sees them edge-on.
            valid &= dr.norm(edges.receiver.p - p) > SHADOW_GAP * dr.norm(edges.x - p)
            valid &= _edge_in_view(scene, csg, p, edges.x, edges.receiver.p, valid, SHADOW_GAP)

        def jump(y, normal, distance, active):
            return _shadow_jump(scene, csg, edges, source, p, normal, ctx.wavelengths, active)
        return self._seen_from_vertex(ctx, vertex, _CurvePoints(edges.y, edges.dy, valid, edges.pmf), jump)

    def _camera_vertex(self, ctx):
        """A camera ray per pixel sample and the surface it meets (`_Vertex`): only a smooth
        BSDF there (not a delta) reflects light from a region of directions."""
        with dr.resume_grad():
            ray, ray_weight, pos = self.sample_rays(ctx.scene, ctx.sensor, ctx.sampler)
        ray_weight = dr.detach(ray_weight)
        ray = mi.Ray3f(dr.detach(ray))
        ray.wavelengths = ctx.wavelengths
        return _vertex_at(ctx.scene, ctx.csg, ray, mi.Bool(True), pos, ray_weight)

    @dr.syntax
    def _path_vertex(self, ctx):
        """A surface point along a camera path (`_Vertex`): where max_depth is 3, the camera's
        (`_camera_vertex`); above, the one at depth k (the camera's surface point is 1),
        chosen per lane: 1 with probability 1/2, else one of 2 ... K uniformly, K =
        max_depth - 2 (k, the surface that lights it, a light), at most DEEPEST_VERTEX (curves
        seen from deeper vertices are left out: their light has come a long way, and a K in
        the hundreds would leave 1/K of the samples to each depth). One vertex per sample,
        not one of each depth: every depth's terms would compile the integrator's path
        tracer again for its jumps (at max_depth 6 the first pass took 218 s instead of 88).
        The path to it is sampled as the integrator's (the BSDF at each vertex), its weight
        the path's over the choice's probability; paths from it are max_depth - k segments long. Ray origins and
        directions stay detached (also from BSDF and Mitsuba shape parameters), so that only
        the last point moves with the shapes, along its ray (as csg_prb's interior
        derivatives parametrize paths)."""
        scene, sensor, csg, sampler, wavelengths = ctx.scene, ctx.sensor, ctx.csg, ctx.sampler, ctx.wavelengths
        infinite = self.max_depth == UNBOUNDED_DEPTH
        deepest = min(DEEPEST_VERTEX, self.max_depth - 2)
        if dr.hint(deepest <= 1, mode="scalar"):
            return self._camera_vertex(ctx)
        with dr.resume_grad():
            ray, ray_weight, pos = self.sample_rays(scene, sensor, sampler)
        ray = mi.Ray3f(dr.detach(ray))
        ray.wavelengths = wavelengths
        u = sampler.next_1d()
        deeper = u >= 0.5
        k = dr.select(deeper, 2 + dr.minimum(mi.UInt32(dr.maximum(2 * u - 1, 0) * (deepest - 1)), deepest - 2), 1)
        weight = mi.Spectrum(dr.detach(ray_weight)) * dr.select(deeper, mi.Float(2 * (deepest - 1)), mi.Float(2))
        depth = mi.UInt32(1)
        active = depth < k
        with dr.suspend_grad():
            while dr.hint(active, max_iterations=deepest, label="csg_prb_projective (path to a vertex)"):
                si, bsdf, _, _, _ = csg.intersect(scene, ray, active)
                active &= si.is_valid()
                sample, bsdf_weight = bsdf.sample(mi.BSDFContext(), si, sampler.next_1d(), sampler.next_2d(),
                                                  active)
                weight = dr.select(active, weight * bsdf_weight, 0)
                ray = dr.select(active, si.spawn_ray(si.to_world(sample.wo)), ray)
                depth += 1
                active &= dr.any(weight != 0) & (depth < k)
        ray.wavelengths = wavelengths
        reached = dr.any(weight != 0) & (depth == k)
        return _vertex_at(scene, csg, ray, reached, pos, weight, None if infinite else self.max_depth - k)

    @staticmethod
    def _seen_from_vertex(ctx, vertex, curve, jump):
        """(film position, value, valid) of a discontinuity point x (`curve`: `_CurvePoints`, x
        attached; tangent dx/du, sampled at `pmf` per unit u) that a surface point p along a
        camera path (`vertex`) sees
        at distance r: moving x by dx (p by dp) moves the boundary it draws on p's sphere of
        directions by ((dx - dp) . m) / r across itself (m normal to the ray p -> x and to the
        curve's tangent t), and the curve's length there is |t x w| / r per unit length of the
        curve: the pixel's derivative is the path's weight up to p times p's f cos times the
        jump of the light arriving at p across x times both, over the pdf of x. `jump(x, m, r,
        active)`: that jump, the side towards -m minus the side towards +m."""
        x, dx, pmf, valid = curve.x, curve.dx, curve.pmf, curve.valid
        si, p = vertex.si, vertex.si.p
        with dr.suspend_grad():
            x_d, dx_d = dr.detach(x), dr.detach(dx)
            speed = dr.norm(dx_d)
            tangent = dx_d / speed
            towards = x_d - p
            distance = dr.norm(towards)
            w = towards / distance
            across = dr.cross(tangent, w)
            sine = dr.norm(across)
            normal = across / sine
            pdf = pmf / speed                                  # per unit length of the curve
            valid &= (speed > 0) & (sine > 0) & dr.isfinite(pdf) & (pdf > 0) & (distance > 0)
            reflected = vertex.bsdf.eval(mi.BSDFContext(), si, si.to_local(w), valid)    # f cos
            valid &= dr.any(reflected != 0)
            dr.eval(x_d, dx_d, normal, distance, valid, reflected, sine, pdf, vertex.pos, vertex.path_weight, si,
                    vertex.bsdf, vertex.p_a, *([] if vertex.depth is None else [vertex.depth]))   # as in `_difference`
            delta = jump(x_d, normal, distance, valid) * ctx.wavelength_weight
            valid &= dr.any(delta != 0)
            weight = vertex.path_weight * reflected * delta * sine / (dr.square(distance) * pdf * ctx.spp)
            weight = dr.select(valid, weight, 0)
            dr.eval(weight, valid)
        motion = (x - x_d) - (vertex.p_a - p)
        return vertex.pos, weight * dr.dot(motion, normal), valid

    def _reflected_radiance(self, scene, sampler, si, target, active, lane_depth=None):
        """The light arriving at the surface point `si` from `target`'s direction that the
        surface met there reflects (its own emission left out), from paths one bounce shorter
        than the integrator's, or `lane_depth` segments long (per lane) where given."""
        ray = si.spawn_ray(dr.normalize(target - si.p))
        # Aimed from the origin spawn_ray moved off the surface: from p itself the ray would
        # pass the curve that far to one side, which offsets close to it cannot afford.
        ray.d = dr.normalize(target - ray.o)
        depth = self.max_depth if self.max_depth == UNBOUNDED_DEPTH else self.max_depth - 1
        return self._path_radiance(scene, sampler, ray, active, max_depth=depth, hide_first_emitter=True,
                                   lane_depth=lane_depth)

    def _radiance(self, scene, sampler, origin, target, wavelengths, active):
        ray = mi.Ray3f(origin, dr.normalize(target - origin))
        ray.wavelengths = wavelengths
        return self._path_radiance(scene, sampler, ray, active)

    def _path_radiance(self, scene, sampler, ray, active, **options):
        """The integrator's primal estimate along `ray` (zero off `active`), in a kernel of its
        own (`_evaluate`); `options` as `sample` takes them."""
        lanes = [options[k] for k in ("lane_depth", "first") if options.get(k) is not None]   # per-lane inputs
        _evaluate(sampler, ray, active, *lanes)
        L, _, _, _ = self.sample(dr.ADMode.Primal, scene, sampler, ray, None, None, active, **options)
        return _evaluate(sampler, dr.select(active, L, 0))

    def to_string(self):
        return (f"CSGPRBProjectiveIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"sppc={self.sppc}, sppp={self.sppp}, sppi={self.sppi}]")


# The deepest path vertex the curves are seen from (`_path_vertex`).
DEEPEST_VERTEX = 8
# A directional light's curves are seen from a point this many scene sizes up its beam:
# their contours then lie within ~1e-5 of the size of the parallel view's.
FAR = 1e5


class _Pass:
    """What every boundary term of one sampling pass reads: the scene, its sensor, its csg
    shapes (`SceneCSG`), the camera's position (numpy), the pass's sampler and samples per
    pixel, and the wavelengths its samples carry with their weight."""

    def __init__(self, scene, sensor, csg, camera, sampler, spp, wavelengths, wavelength_weight):
        self.scene, self.sensor, self.csg, self.camera = scene, sensor, csg, camera
        self.sampler, self.spp = sampler, spp
        self.wavelengths, self.wavelength_weight = wavelengths, wavelength_weight


class _CurvePoints:
    """Points sampled on discontinuity curves (`_sample_curves`, `_sample_static`), or on the
    edges of shadows: the point x and its tangent dx/du (attached where the curve moves),
    validity, the pmf it was sampled with, and for curves of csg shapes their kind, leaf a
    and solid (None where not needed)."""

    def __init__(self, x, dx, valid, pmf, kind=None, leaf=None, solid=None):
        self.x, self.dx, self.valid, self.pmf = x, dx, valid, pmf
        self.kind, self.leaf, self.solid = kind, leaf, solid


class _Source:
    """A light as the shadow term samples it: per lane a point `lamp` the curves are seen from
    (on an area light, sampled; a light at infinity's stand-in far along its direction),
    `away` where a light at infinity's light travels (None for lights at a finite place),
    `viewpoint` one point for the curves' sampling weights, and `incident(si, active)`: the
    shadow ray from a surface point to the lamp and the light arriving along it per unit of
    BSDF value (Mitsuba's emitter sample weight), or 0 where the lamp sends none that way."""

    def __init__(self, viewpoint, lamp, away, incident):
        self.viewpoint, self.lamp, self.away, self.incident = viewpoint, lamp, away, incident


class _ShadowEdges:
    """Points on the edges of a light's shadows (`_shadow_edges`): the casting curve point x
    (detached), the edge point y (attached) and its tangent dy/du, the surface interaction
    where the light's ray through x meets the receiver (detached; its point y0), the
    receiver's BSDF, whether it is a csg shape's, the curves' pmf, validity, and whether the
    casters are Mitsuba's shapes'."""

    def __init__(self, x, y, dy, receiver, bsdf, on_csg, pmf, valid, static):
        self.x, self.y, self.dy, self.receiver, self.bsdf = x, y, dy, receiver, bsdf
        self.on_csg, self.pmf, self.valid, self.static = on_csg, pmf, valid, static


class _Vertex:
    """A surface point p along a camera path (`_camera_vertex`, `_path_vertex`): the film
    position, the path's weight, the surface interaction (detached) and p attached, the
    BSDF, whether it is a csg shape's, validity, and how many segments paths from p may have
    (per lane; None: one fewer than the integrator's)."""

    def __init__(self, pos, path_weight, si, p_a, bsdf, on_csg, valid, depth=None):
        self.pos, self.path_weight, self.si, self.p_a = pos, path_weight, si, p_a
        self.bsdf, self.on_csg, self.valid, self.depth = bsdf, on_csg, valid, depth


def _vertex_at(scene, csg, ray, active, pos, path_weight, depth=None):
    """The `_Vertex` where `ray` (detached) meets a surface, attached where it is a csg
    shape's (it may move too): only a smooth BSDF there (not a delta) reflects light from a
    region of directions."""
    with dr.resume_grad():
        si_a, bsdf, on_csg, _, _ = csg.intersect(scene, ray, active, attached=True)
        p_a = mi.Point3f(si_a.p)
    with dr.suspend_grad():
        si = dr.detach(si_a)
        valid = active & si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    return _Vertex(pos, path_weight, si, p_a, bsdf, on_csg, valid, depth)


def _edge_in_view(scene, csg, viewer, x, y0, active, gap):
    """Whether `viewer` sees the shadow's edge point y0 cast by the curve point x: a ray from
    just in front of y0 towards it is not blocked, and passes x farther than `gap` of x's
    distance (closer, the edge lies right behind the caster's own contour, a discontinuity
    the curve's own term counts)."""
    towards = viewer - y0
    closest = y0 + towards * (dr.dot(x - y0, towards) / dr.squared_norm(towards))
    visible = active & (dr.norm(x - closest) > gap * dr.norm(x - viewer))
    distance = dr.norm(towards)
    view_ray = mi.Ray3f(y0 + OFFSET * towards, towards / distance)
    view_ray.maxt = (1.0 - 2.0 * OFFSET) * distance
    return visible & ~csg.occluded(scene, view_ray, visible)


def _shadow_sources(scene, sampler, camera=None):
    """A `_Source` per emitter whose shadows the camera may see: point and spot lights (not one
    at the `camera`, where given: it hides every shadow behind its caster) and directional lights, whose
    one lamp is the light; area lights, a point sampled on the emitting shape per lane;
    environment lights (`constant`, `envmap`), a direction sampled per lane by the emitter."""
    bbox = scene.bbox()
    centre = np.array(bbox.center(), np.float64)
    size = max(float(np.linalg.norm(np.array(bbox.extents()))), 1e-3)
    far = FAR * size
    it = dr.zeros(mi.Interaction3f)
    it.p = _point(centre)
    sources = []
    for emitter in scene.emitters():
        flags = emitter.flags()
        with dr.suspend_grad():
            if mi.has_flag(flags, mi.EmitterFlags.DeltaPosition) or mi.has_flag(flags, mi.EmitterFlags.DeltaDirection):
                ds, _ = emitter.sample_direction(it, mi.Point2f(0.5, 0.5))
                towards = np.array([dr.slice(c) for c in ds.d], np.float64)
                if mi.has_flag(flags, mi.EmitterFlags.DeltaPosition):
                    where = np.array([dr.slice(c) for c in ds.p], np.float64)
                    if camera is not None and np.linalg.norm(where - camera) <= 1e-6 * max(1.0, np.linalg.norm(camera)):
                        continue
                    sources.append(_Source(where, _point(where), None, _delta_incident(emitter)))
                else:
                    where = centre + towards * far
                    sources.append(_Source(where, _point(where), mi.Vector3f(*[float(-c) for c in towards]),
                                           _delta_incident(emitter)))
            elif emitter.get_shape() is not None:
                shape = emitter.get_shape()
                ps = shape.sample_position(0.0, sampler.next_2d())
                where = np.array(shape.bbox().center(), np.float64)
                sources.append(_Source(where, mi.Point3f(ps.p), None, _area_incident(emitter, ps)))
            elif mi.has_flag(flags, mi.EmitterFlags.Infinite):
                ds, weight = emitter.sample_direction(it, sampler.next_2d())
                weight = dr.select(ds.pdf > 0, weight, 0)
                sources.append(_Source(centre + np.array([0.0, 0.0, far]), it.p + ds.d * far, -ds.d,
                                       _infinite_incident(ds.d, weight)))
    return sources


def _shadow_jump(scene, csg, edges, source, viewer, normal, wavelengths, active):
    """The jump, seen from `viewer`, of the light of `source` across shadow edge points
    (`edges`, receiver point y0) along the normal `normal` of the edge's image: the light y0
    reflects towards the viewer, on the side of the edge that the source lights, the side
    towards -normal minus the side towards +normal. Which side is lit, from shadow rays from
    the receiver's tangent plane either side of y0 (SHADOW_OFFSET of the caster's distance
    away), not from rays from the viewer either side: where a receiver lies right next to its
    caster (a notch's rim grazed by the light), those would measure the jump across the
    caster's own curve."""
    si = mi.SurfaceInteraction3f(edges.receiver)      # a copy: its wi and p change below
    si.wavelengths = wavelengths
    y0, n = mi.Point3f(si.p), mi.Vector3f(si.n)
    w = dr.normalize(viewer - y0)
    facing = dr.dot(w, n)
    active = active & (dr.abs(facing) > 1e-6)
    si.wi = si.to_local(w)
    shadow_ray, weight = source.incident(si, active)
    value = edges.bsdf.eval(mi.BSDFContext(), si, si.to_local(shadow_ray.d), active) * weight
    active &= dr.any(value != 0)
    # the image normal carried along the ray from the viewer into the receiver's tangent plane
    side = dr.normalize(normal - w * (dr.dot(normal, n) / facing))
    step = SHADOW_OFFSET * dr.norm(y0 - edges.x)
    lit = []
    for sign in (-1.0, 1.0):
        si.p = y0 + sign * step * side
        ray, _ = source.incident(si, active)
        lit.append(active & ~csg.occluded(scene, ray, active))
    return dr.select(lit[0], value, 0) - dr.select(lit[1], value, 0)


def _faces_beside(csg, camera, x, normal, offset, active):
    """The faces the camera sees beside the curve point x (`_seen_jump`): (the camera's ray
    through x, x's distance, the csg hits of the rays passing x at `offset` towards -normal
    and +normal, whether each hit's face passes through x and faces the camera there, and
    whether x lies on the solid's boundary, and each face's normal at x)."""
    towards = x - camera
    distance = dr.norm(towards)
    at_x = mi.Ray3f(camera, towards / distance)
    tree = csg.traced_tree()
    sides, near, normals = [], [], []
    on_boundary = mi.Bool(False)
    for sign in (-1.0, 1.0):
        side = csg.trace(mi.Ray3f(camera, dr.normalize(x + sign * offset * normal - camera)), dr.inf, active)
        met = active & dr.isfinite(side.t)
        n, residual = face_at(tree, side.prim, side.info, at_x.o, at_x.d, distance, met)
        n = mi.Vector3f(n)
        passes = met & (residual < FACE_GAP)
        # a point on that face's side of x, a little into the face and under it (at a
        # contour, where the face's normal is the curve's in the image, just under it)
        along = sign * normal - n * dr.dot(sign * normal, n)
        length = dr.norm(along)
        along = dr.select(length > 0.1, along / length, 0)
        probe = x + offset * (2.0 * along - 0.5 * n)
        out = csg.trace(mi.Ray3f(probe, -n), dr.inf, passes)
        on_boundary |= passes & dr.isfinite(out.t) & (K.info_class(mi.UInt32(out.info)) != K.ENTER)
        sides.append(side)
        near.append(passes & (dr.dot(n, at_x.d) < -CONTOUR_COSINE))
        normals.append(n)
    return at_x, distance, sides, near, on_boundary, normals


def _jump(radiance, x, normal, offset, active):
    """The jump of `radiance(target, active)` across the curve point x: the side towards
    -normal minus the side towards +normal, from targets either side at `offset` and 4
    `offset`, extrapolated to the curve (EXTRAPOLATION)."""
    jump = mi.Spectrum(0)
    for factor, scale in EXTRAPOLATION:
        inside = radiance(x - factor * offset * normal, active)
        outside = radiance(x + factor * offset * normal, active)
        jump += scale * (inside - outside)
    return jump


def _evaluate(sampler, *values):
    """Evaluates `values` and `sampler`'s state now (returns the last value): a boundary
    between kernels. The path tracer a jump calls for its rays then compiles to a kernel of
    its own, the same for every call (the rays read from memory, their offsets no constants
    in it), so LLVM compiles it once, rather than once per call in one kernel that holds
    them all (a primary term's took 16 s to compile, twice: again for the gradient)."""
    sampler.schedule_state()
    dr.eval(*values)
    return values[-1]


def _point(where):
    return mi.Point3f(*[float(c) for c in where])


def _delta_incident(emitter):
    def incident(si, active):
        ds, weight = emitter.sample_direction(si, mi.Point2f(0.5, 0.5), active)
        return si.spawn_ray_to(ds.p), dr.select(ds.pdf > 0, weight, 0)
    return incident


def _area_incident(emitter, ps):
    def incident(si, active):
        towards = ps.p - si.p
        distance = dr.norm(towards)
        on_light = dr.zeros(mi.SurfaceInteraction3f, dr.width(towards))
        on_light.p, on_light.n, on_light.uv, on_light.time = ps.p, ps.n, ps.uv, si.time
        on_light.sh_frame = mi.Frame3f(ps.n)
        on_light.wi = on_light.to_local(-towards / distance)
        on_light.wavelengths = si.wavelengths
        cosine = dr.maximum(dr.dot(ps.n, -towards / distance), 0.0)
        weight = emitter.eval(on_light, active) * cosine / (dr.square(distance) * ps.pdf)
        return si.spawn_ray_to(ps.p), dr.select(active & (ps.pdf > 0) & (distance > 0), weight, 0)
    return incident


def _infinite_incident(direction, weight):
    def incident(si, active):
        return si.spawn_ray(direction), weight
    return incident


def _direct_light(scene, csg, camera, target, source, wavelengths, active):
    """What the camera sees through `target` of the light of `source` alone: the surface there,
    lit directly by the source's lamp (zero where the lamp is hidden or the BSDF is a delta)."""
    ray = mi.Ray3f(camera, dr.normalize(target - camera))
    ray.wavelengths = wavelengths
    dr.eval(ray, active)
    si, bsdf, _, _, _ = csg.intersect(scene, ray, active)
    active = active & si.is_valid()
    shadow_ray, weight = source.incident(si, active)
    active &= dr.any(weight != 0)
    active &= ~csg.occluded(scene, shadow_ray, active)
    value = bsdf.eval(mi.BSDFContext(), si, si.to_local(shadow_ray.d), active) * weight
    value = dr.select(active, value, 0)
    dr.eval(value)
    return value


def _first_hit_past_own(scene, csg, origin, direction, length, scale, contour, leaf, solid, active, mesh_edge=False):
    """(found, start): whether the ray from `origin` (a curve point) meets anything within
    `length`, and the distance from which its first hit lies. Tested from just past the
    point (OFFSET of `scale`: its distance from the viewpoint, or the scene's size for a
    directional light), so that the point's own surfaces do not count; a contour point's
    ray grazes its own leaf, and in float32 meets it again near the point
    (63 % of a sphere's contour points came out hidden by their own sphere from 1e-5 of the
    distance), so such re-hits of the same leaf within CONTOUR_VIEW_OFFSET of the scale are
    stepped past, up to twice (a larger start offset would also step past a face just in
    front of the point: a hole's contour hidden just beneath the face it cuts). A Mitsuba
    mesh's edge (`mesh_edge`) has no leaf: hits on Mitsuba's shapes that near are its own faces
    grazed."""
    start = OFFSET * scale
    found = mi.Bool(False)
    active = mi.Bool(active)
    for _ in range(3):
        ray = mi.Ray3f(origin + start * direction, direction)
        ray.maxt = length - start
        si, _, csg_hit, prim, shape = csg.intersect(scene, ray, active)
        hit = active & si.is_valid()
        own = (~csg_hit if mesh_edge else contour & csg_hit & (prim == leaf) & (shape == solid))
        own &= hit & (start + si.t < CONTOUR_VIEW_OFFSET * scale)
        found |= hit & ~own
        start = dr.select(own, start + si.t + OFFSET * scale, start)
        active &= own
    return found, start


def _sample_static(ctx, static, viewpoint, scale, view):
    """Points on the curves of Mitsuba's shapes (`csg_edges.StaticCurves`) that the lamp `view`
    (per lane) sees, sampled in proportion to their length over their distance from
    `viewpoint`: `_CurvePoints` as `_sample_curves` gives them, x detached (they do not move)."""
    distribution = mi.DiscreteDistribution(owned(mi.Float, static.weight(viewpoint).astype(np.float32)))
    with dr.suspend_grad():
        index, u, pmf = distribution.sample_reuse_pmf(ctx.sampler.next_1d())

        def column(values, kind=mi.Float):
            return dr.gather(kind, owned(kind, np.ascontiguousarray(values)), index)
        kind, extra = column(static.kind, mi.UInt32), column(static.extra, mi.UInt32)
        m = mi.Matrix3f(*[column(static.to_world[:, i, j]) for i in range(3) for j in range(3)])
        t = mi.Vector3f(*[column(static.to_world[:, i, 3]) for i in range(3)])
        data = [column(static.data[:, k]) for k in range(static.data.shape[1])]
        x, dx, valid = csg_edges.evaluate(kind, extra, m, t, m, t, data, view, u)
        valid &= dr.norm(dx) > 0
        none = dr.zeros(mi.UInt32, dr.width(x))
        valid &= _seen_from(ctx.scene, ctx.csg, x, view, scale, mi.Bool(False), none, none, valid, mesh_edge=True)
    return _CurvePoints(x, dx, valid, pmf, kind, none, none)


def _seen_from(scene, csg, x, view, scale, contour, leaf, solid, active, mesh_edge=False):
    """Whether nothing hides the curve points x from `view` (`_first_hit_past_own`, tested from
    just in front of the point, so that its own surfaces do not count; `scale`: default its
    distance). Only points seen count: a hidden curve can pass near a visible discontinuity
    (a hole's sphere's contour just beneath the face runs along the rim, tangent to it where
    it meets the face), and rays either side of the hidden point would measure the jump
    across the visible one."""
    towards = view - x
    distance = dr.norm(towards)
    found, _ = _first_hit_past_own(scene, csg, x, towards / distance, (1.0 - OFFSET) * distance,
                                   distance if scale is None else scale, contour, leaf, solid, active, mesh_edge)
    return ~found


def _contour(kind):
    """Curves on a smooth surface where the viewpoint's rays graze it."""
    return ((kind == csg_edges.SPHERE_SILHOUETTE) | (kind == csg_edges.CONE_SILHOUETTE)
            | (kind == csg_edges.TORUS_SILHOUETTE) | (kind == csg_edges.QUADRIC_SILHOUETTE))
