"""The `csg_prb` integrator: path replay backpropagation through exact CSG hits."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
from mitsuba.ad.integrators.common import RBIntegrator, mis_weight

from .csg_common import SceneCSG, camera_ray_valid, check_depth_types
from .registry import integrator


@integrator("csg_prb", "differentiable", {"PRB": ""})
class CSGPRBIntegrator(RBIntegrator):
    r"""
    .. _integrator-csg_prb:

    CSG path replay backpropagation (:monosp:`csg_prb`)
    ---------------------------------------------------

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

    A differentiable path tracer (Vicini et al. 2021's path replay, with next-event
    estimation and MIS, as Mitsuba's `prb`) for scenes with `csg` shapes. Gradients flow to
    BSDF and emitter parameters and to the CSG shapes' `primitive_to_world`: each CSG hit
    is found by the detached automaton and then recomputed with AD for the winning
    primitive (t, position, normal), which gives the *interior* derivatives.

    Not differentiated: visibility changes, i.e. silhouettes of CSG shapes, edges where the
    visible primitive changes, and shadow boundaries (like Mitsuba's `prb`, which also
    ignores them); the motion of the next path vertex is not propagated into the previous
    one. Gradients of pixels straddling such edges are therefore biased; `csg_prb_projective`
    adds the boundaries the camera sees.

    .. code-block:: python

        'integrator': {'type': 'csg_prb', 'max_depth': 4}
    """

    def __init__(self, props: mi.Properties):
        check_depth_types(props, "csg_prb")
        super().__init__(props)

    @dr.syntax
    def sample(self, mode: dr.ADMode, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
               δL, state_in, active: mi.Bool, max_depth=None, hide_first_emitter=None, lane_depth=None,
               first=None, **kwargs):
        """Mitsuba's `sample`; `max_depth` and `hide_first_emitter` (the integrator's
        `max_depth` and `hide_emitters` unless given) let csg_prb_projective trace paths that
        continue one from a surface point (one bounce shorter, the emitter their first ray
        meets left out); `lane_depth` (per lane, at most `max_depth`) shortens them further
        where that point lies deeper along a path. `first` (primal only): (si, bsdf, mask), a
        surface interaction and its BSDF where the path's first vertex is given instead of
        found along `ray` (per lane where mask holds): csg_prb_projective's radiance leaving
        a crease's point from either face."""
        primal = mode == dr.ADMode.Primal
        max_depth = self.max_depth if max_depth is None else max_depth
        hide_first = self.hide_emitters if hide_first_emitter is None else hide_first_emitter
        if dr.hint(max_depth == 0, mode="scalar"):   # as Mitsuba's path tracers: nothing at all
            nothing = mi.Spectrum(0)
            return nothing, dr.zeros(mi.Bool, dr.width(ray.d)), [], nothing
        csg = SceneCSG(scene)
        bsdf_ctx = mi.BSDFContext()

        # --------------------- Configure loop state ----------------------
        ray = mi.Ray3f(dr.detach(ray))
        depth = mi.UInt32(0)                             # depth of the current vertex
        L = mi.Spectrum(0 if primal else state_in)       # radiance accumulator
        δL = mi.Spectrum(δL if δL is not None else 0)    # adjoint radiance
        β = mi.Spectrum(1)                               # path throughput weight
        η = mi.Float(1)                                  # index of refraction ratio
        active = mi.Bool(active)
        si_prev = dr.zeros(mi.SurfaceInteraction3f)
        bsdf_pdf_prev = mi.Float(1.0)
        bsdf_delta_prev = mi.Bool(True)
        given = mi.Bool(active & first[2]) if first is not None else mi.Bool(False)

        while dr.hint(active, max_iterations=max_depth, label=f"csg_prb ({mode.name})"):
            active_next = mi.Bool(active)
            with dr.resume_grad(when=not primal):
                si, bsdf, _, _, _ = csg.intersect(scene, ray, active & ~given, attached=not primal)
            if dr.hint(first is not None, mode="scalar"):
                si = dr.select(given, first[0], si)
                bsdf = dr.select(given, first[1], bsdf)

            # ---------------------- Direct emission ----------------------
            ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
            mis = mis_weight(bsdf_pdf_prev, scene.pdf_emitter_direction(si_prev, ds, ~bsdf_delta_prev))
            # hide_emitters: emitters seen directly by the camera give nothing (as in csg_path)
            seen = active_next & ~((depth == 0) & hide_first)
            with dr.resume_grad(when=not primal):
                Le = β * mis * ds.emitter.eval(si, seen)

            # ---------------------- Emitter sampling ----------------------
            active_next &= (depth + 1 < max_depth) & si.is_valid()
            if dr.hint(lane_depth is not None, mode="scalar"):
                active_next &= depth + 1 < lane_depth
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), False, active_em)
            active_em &= ds.pdf != 0.0
            active_em &= ~csg.occluded(scene, si.spawn_ray_to(ds.p), active_em)
            with dr.resume_grad(when=not primal):
                if dr.hint(not primal, mode="scalar"):
                    # Re-attach the emitter sample to the (moving) shading point.
                    is_infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
                    ds_diff = dr.detach(ds)
                    ds_diff.d = dr.select(is_infinite, ds.d, dr.normalize(ds.p - si.p))
                    ds = dr.replace_grad(ds, ds_diff)
                    em_val = scene.eval_emitter_direction(si, ds, active_em)
                    inv_pdf = dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0)
                    em_weight = dr.replace_grad(em_weight, em_val * dr.detach(inv_pdf))
                wo = si.to_local(ds.d)
                bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
                mis_em = dr.select(ds.delta, 1, mis_weight(ds.pdf, bsdf_pdf_em))
                Lr_dir = dr.select(active_em, β * mis_em * bsdf_value_em * em_weight, 0)

            # ------------------ Detached BSDF sampling -------------------
            bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
            L = (L + Le + Lr_dir) if primal else (L - Le - Lr_dir)
            ray_next = si.spawn_ray(si.to_world(bsdf_sample.wo))
            η *= bsdf_sample.eta
            β *= bsdf_weight
            si_prev = dr.detach(si, True)
            bsdf_pdf_prev = bsdf_sample.pdf
            bsdf_delta_prev = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)

            # -------------------- Stopping criterion ---------------------
            β_max = dr.max(mi.unpolarized_spectrum(β))
            active_next &= β_max != 0
            rr_prob = dr.minimum(β_max * dr.square(η), 0.95)
            rr_active = depth >= self.rr_depth
            β[rr_active] *= dr.rcp(rr_prob)
            active_next &= ~rr_active | (sampler.next_1d() < rr_prob)

            # ------------------ Differential phase only ------------------
            if dr.hint(not primal, mode="scalar"):
                with dr.resume_grad():
                    # Replace the detached BSDF value inside L by an attached one.
                    wo = si.to_local(ray_next.d)
                    bsdf_val = bsdf.eval(bsdf_ctx, si, wo, active_next)
                    Lr_ind = L * dr.relative_grad(bsdf_val)
                    Lo = Le + Lr_dir + Lr_ind
                    # As Mitsuba's prb: a detached contribution here means a parameter that
                    # cannot get derivatives, or a forgotten dr.enable_grad; say so.
                    detached = dr.flag(dr.JitFlag.VCallRecord) and not dr.grad_enabled(Lo)
                    if dr.hint(detached, mode="scalar"):
                        raise RuntimeError("csg_prb: the contribution of the differential phase is not "
                                           "attached to the AD graph (is dr.enable_grad called on a "
                                           "differentiable scene parameter?)")
                    if dr.hint(mode == dr.ADMode.Backward, mode="scalar"):
                        dr.backward_from(δL * Lo)
                    else:
                        δL += dr.forward_to(Lo)

            ray = ray_next
            given = mi.Bool(False)
            depth[si.is_valid()] += 1
            active = active_next

        return (L if primal else δL, camera_ray_valid(scene, self.hide_emitters, depth), [], L)

    def to_string(self):
        return f"CSGPRBIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}]"
