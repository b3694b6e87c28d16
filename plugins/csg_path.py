"""The `csg_path` integrator: a unidirectional path tracer that sees CSG shapes."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba.ad.integrators.common import mis_weight

from . import integrator_guard
from .csg_common import SceneCSG, camera_ray_valid, read_depths, read_hide_emitters


class CSGPathIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-csg_path:

    CSG path tracer (:monosp:`csg_path`)
    ------------------------------------

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1: infinite; 1: direct emission only). (Default: 6)
     * - rr_depth
       - |int|
       - Depth from which Russian roulette may end paths. (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: false)

    Mitsuba's `path` integrator for scenes that hold `csg` shapes: next-event estimation
    with multiple importance sampling (power heuristic) against all of Mitsuba's emitters,
    BSDF sampling, Russian roulette. Every ray (camera, bounce, shadow) is tested against
    Mitsuba's own shapes and the exact CSG solids, and the nearer hit wins; CSG hits use the
    BSDF of the primitive's material. When a scene holds only CSG shapes, Embree is not
    called at all. Participating media are refused (a scene with media would render as if
    they were absent): `csg_volpath` traces them.

    .. code-block:: python

        'integrator': {'type': 'csg_path', 'max_depth': 8}
    """

    # Traces csg shapes (plugins/integrator_guard.py refuses integrators without this).
    traces_csg = True

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.max_depth, self.rr_depth = read_depths(props, "csg_path")
        self.hide_emitters = read_hide_emitters(props, "csg_path")

    @dr.syntax
    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: bool = True):
        if dr.hint(self.max_depth == 0, mode="scalar"):   # as Mitsuba's path: nothing, not even emitters
            return mi.Spectrum(0), dr.zeros(mi.Bool, dr.width(ray.d)), []
        # This class keeps Mitsuba's render binding (integrator_guard.keep_binding): checked here.
        integrator_guard.check(mi, self, scene)
        csg = SceneCSG(scene)
        bsdf_ctx = mi.BSDFContext()

        # --------------------- Configure loop state ----------------------
        ray = mi.Ray3f(dr.detach(ray))
        L = mi.Spectrum(0)                          # radiance accumulated so far
        beta = mi.Spectrum(1)                       # path throughput weight
        eta = mi.Float(1)                           # index of refraction ratio so far
        depth = mi.UInt32(0)                        # path depth
        active = mi.Bool(active)
        prev_si = dr.zeros(mi.Interaction3f)        # previous vertex, for MIS of emitter hits
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)
        start = mi.UInt32(0xFFFFFFFF)               # the CSG primitive the ray leaves (a traversal hint)

        while dr.hint(active, max_iterations=self.max_depth, label="csg_path"):
            si, bsdf, csg_hit, csg_prim, csg_shape = csg.intersect(scene, ray, active, start_prim=start)
            start = csg.start_of(csg_hit, csg_prim, csg_shape)

            # ---------------------- Direct emission ----------------------
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            em_pdf = mi.Float(0.0)
            if ~prev_bsdf_delta:
                em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
            mis_bsdf = mis_weight(prev_bsdf_pdf, em_pdf)
            visible = ~((depth == 0) & self.hide_emitters)
            L += dr.select(active & visible, beta * mis_bsdf * ds.emitter.eval(si, active), 0.0)

            active_next = active & si.is_valid() & (depth + 1 < self.max_depth)

            # ---------------------- Emitter sampling ----------------------
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), False, active_em)
            active_em &= ds.pdf != 0.0
            wo = si.to_local(ds.d)
            bsdf_value, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
            # Where the BSDF gives nothing (light from below the surface), occlusion does not
            # matter: no shadow ray.
            active_em &= dr.any(bsdf_value != 0.0)
            occluded = csg.occluded(scene, si.spawn_ray_to(ds.p), active_em, start_prim=start)
            active_em &= ~occluded
            mis_em = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, bsdf_pdf))
            L += dr.select(active_em, beta * mis_em * bsdf_value * em_weight, 0.0)

            # ---------------------- BSDF sampling ----------------------
            bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
            ray = si.spawn_ray(si.to_world(bsdf_sample.wo))
            beta *= bsdf_weight
            eta *= bsdf_sample.eta
            prev_si = mi.Interaction3f(si)
            prev_bsdf_pdf = bsdf_sample.pdf
            prev_bsdf_delta = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)

            # ---------------------- Russian roulette ----------------------
            depth[si.is_valid()] += 1
            beta_max = dr.max(mi.unpolarized_spectrum(beta))
            rr_active = depth >= self.rr_depth
            rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
            rr_continue = sampler.next_1d() < rr_prob
            beta[rr_active] *= dr.rcp(rr_prob)
            active = active_next & (~rr_active | rr_continue) & (beta_max != 0.0)

        return L, camera_ray_valid(scene, self.hide_emitters, depth), []

    def aov_names(self):
        return []

    def to_string(self):
        return f"CSGPathIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}]"
