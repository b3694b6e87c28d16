"""The `csg_volpath` integrator: a volumetric path tracer that sees CSG shapes."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba.ad.integrators.common import mis_weight

from .csg_common import SceneCSG, camera_ray_valid, read_depths, read_hide_emitters
from .registry import integrator


def _spectrum_channel(spectrum, channel):
    """One colour channel of an RGB spectrum (the channel a free flight was sampled in)."""
    if mi.is_rgb:
        return dr.select(channel == 0, spectrum[0], dr.select(channel == 1, spectrum[1], spectrum[2]))
    return spectrum[0]


@integrator("csg_volpath", "media", {"Volpath": "", "Volumetric": ""})
class CSGVolpathIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-csg_volpath:

    CSG volumetric path tracer (:monosp:`csg_volpath`)
    --------------------------------------------------

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

    Mitsuba's `volpath` for scenes that hold `csg` shapes: participating media inside and
    around shapes (`interior` / `exterior` media on `csg` shapes and on Mitsuba's own, a
    `medium` on the sensor), homogeneous and heterogeneous, with free-flight sampling (delta
    tracking in one colour channel, weighted over all), phase-function sampling, next-event
    estimation through media and null-BSDF boundaries (transmittance by ratio tracking, or in
    closed form in homogeneous media) with multiple importance sampling, Russian roulette.
    CSG boundaries are medium transitions as mesh boundaries are: the hit's normal says
    whether the path enters the shape's interior medium or leaves it.

    .. code-block:: python

        'integrator': {'type': 'csg_volpath', 'max_depth': 16}
    """

    traces_media = True

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.max_depth, self.rr_depth = read_depths(props, "csg_volpath")
        self.hide_emitters = read_hide_emitters(props, "csg_volpath")

    @dr.syntax
    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: bool = True):
        if dr.hint(self.max_depth == 0, mode="scalar"):
            return mi.Spectrum(0), dr.zeros(mi.Bool, dr.width(ray.d)), []
        csg = SceneCSG(scene, media=True)
        ray = mi.Ray3f(dr.detach(ray))
        L = mi.Spectrum(0)
        throughput = mi.Spectrum(1)
        eta = mi.Float(1)
        depth = mi.UInt32(0)
        active = mi.Bool(active)
        valid_ray = mi.Bool(False)
        specular_chain = mi.Bool(True)     # emitters seen through delta events only: no MIS
        si = dr.zeros(mi.SurfaceInteraction3f)
        bsdf = dr.zeros(mi.BSDFPtr)
        needs_intersection = mi.Bool(True)
        last_event = dr.zeros(mi.Interaction3f)
        last_pdf = mi.Float(1.0)
        current = dr.zeros(mi.MediumPtr) if medium is None else mi.MediumPtr(medium)
        channel = mi.UInt32(0)
        if mi.is_rgb:      # free flights are sampled in one colour channel, weighted over all three
            channel = mi.UInt32(dr.minimum(3 * sampler.next_1d(active), 2))
        bsdf_ctx = mi.BSDFContext()

        while dr.hint(active, label="csg_volpath"):
            active &= dr.any(throughput != 0.0)
            q = dr.minimum(dr.max(mi.unpolarized_spectrum(throughput)) * dr.square(eta), 0.99)
            roulette = depth > self.rr_depth
            active &= (sampler.next_1d(active) < q) | ~roulette
            throughput[roulette] *= dr.rcp(q)

            in_medium = active & (current != None)
            on_surface = active & ~in_medium

            # ---- Free flight in the current medium ----
            mei = current.sample_interaction(ray, sampler.next_1d(in_medium), channel, in_medium)
            mei.t = dr.detach(mei.t)
            ray.maxt[in_medium & current.is_homogeneous() & mei.is_valid()] = mei.t
            hit_now = needs_intersection & in_medium
            found, found_bsdf, _, _, _ = csg.intersect(scene, ray, hit_now)
            si[hit_now] = found
            bsdf[hit_now] = found_bsdf
            needs_intersection &= ~in_medium
            mei.t[in_medium & (si.t < mei.t)] = dr.inf
            tr, free_flight_pdf = current.transmittance_eval_pdf(mei, si, in_medium)
            tr_pdf = _spectrum_channel(free_flight_pdf, channel)
            weight = mi.Spectrum(1.0)
            weight[in_medium] *= dr.select(tr_pdf > 0.0, tr / tr_pdf, 0.0)
            escaped = in_medium & ~mei.is_valid()
            in_medium &= mei.is_valid()
            # Heterogeneous media: a null collision continues the flight, a real one scatters.
            scatter_prob = _spectrum_channel(mei.sigma_t, channel) / _spectrum_channel(mei.combined_extinction, channel)
            scatter_prob = dr.select(current.is_homogeneous(), 1.0, scatter_prob)
            null_event = in_medium & (sampler.next_1d(in_medium) >= scatter_prob)
            scatter = in_medium & ~null_event
            weight[null_event] *= mei.sigma_n / dr.maximum(1.0 - scatter_prob, 1e-8)
            weight[scatter] *= mei.sigma_s / dr.maximum(scatter_prob, 1e-8)
            depth[scatter] += 1
            last_event[scatter] = mei
            active &= depth < self.max_depth
            scatter &= active
            ray.o[null_event] = mei.p
            si.t[null_event] = si.t - mei.t
            throughput *= weight

            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = mei.medium.phase_function()
            phase[~scatter] = dr.zeros(mi.PhaseFunctionPtr)

            # ---- Surfaces ----
            on_surface |= escaped
            hit_now = on_surface & needs_intersection
            found, found_bsdf, _, _, _ = csg.intersect(scene, ray, hit_now)
            si[hit_now] = found
            bsdf[hit_now] = found_bsdf
            emitter = si.emitter(scene)
            seen = on_surface & (emitter != None) & ~((depth == 0) & self.hide_emitters)
            ds = mi.DirectionSample3f(scene, si, last_event)
            emitter_pdf = scene.pdf_emitter_direction(last_event, ds, seen & ~specular_chain)
            emitted = emitter.eval(si, seen)
            L[seen] += throughput * emitted * dr.select(specular_chain | (depth == 0), 1.0,
                                                        mis_weight(last_pdf, emitter_pdf))
            on_surface &= si.is_valid()

            # ---- Next-event estimation (from a surface or a medium) ----
            nee_surface = on_surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & (depth + 1 < self.max_depth)
            nee_medium = scatter & mei.medium.use_emitter_sampling()
            specular_chain &= ~scatter
            specular_chain |= scatter & ~mei.medium.use_emitter_sampling()
            nee = nee_surface | nee_medium
            emitted, ds = self._sample_emitter(scene, csg, sampler, mei, si, nee_medium, nee_surface, current,
                                               channel, nee)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, si.to_local(ds.d), nee_surface)
            phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, nee_medium)
            value = dr.select(nee_surface, bsdf_val, phase_val)
            pdf = dr.select(ds.delta, 0.0, dr.select(nee_surface, bsdf_pdf, phase_pdf))
            L[nee] += throughput * value * mis_weight(ds.pdf, pdf) * emitted

            # ---- Phase function sampling ----
            valid_ray |= scatter
            wo, phase_weight, phase_pdf = phase.sample(phase_ctx, mei, sampler.next_1d(scatter),
                                                       sampler.next_2d(scatter), scatter)
            scatter &= phase_pdf > 0.0
            throughput[scatter] *= phase_weight
            ray[scatter] = mei.spawn_ray(wo)
            needs_intersection |= scatter
            last_pdf[scatter] = phase_pdf

            # ---- BSDF sampling ----
            bs, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(on_surface), sampler.next_2d(on_surface),
                                          on_surface)
            on_surface &= bs.pdf > 0
            throughput[on_surface] *= bsdf_weight
            eta[on_surface] *= bs.eta
            ray[on_surface] = si.spawn_ray(si.to_world(bs.wo))
            needs_intersection |= on_surface
            real = on_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            depth[real] += 1
            last_event[real] = si
            last_pdf[real] = bs.pdf
            valid_ray |= real
            specular_chain |= real & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            specular_chain &= ~(on_surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
            crossing = on_surface & si.is_medium_transition()
            current[crossing] = si.target_medium(ray.d)
            active &= on_surface | in_medium

        return L, camera_ray_valid(scene, self.hide_emitters, mi.UInt32(valid_ray)), []

    @dr.syntax
    def _sample_emitter(self, scene, csg, sampler, mei, si, from_medium, from_surface, medium, channel, active):
        """An emitter sample from the medium event or surface, and its transmittance through
        media and null-BSDF surfaces (CSG solids block it)."""
        active = mi.Bool(active)
        ref = dr.zeros(mi.Interaction3f)
        ref[from_medium] = mei
        ref[from_surface] = si
        ds, emitter_value = scene.sample_emitter_direction(ref, sampler.next_2d(active), False, active)
        ds = dr.detach(ds)
        emitter_value[ds.pdf == 0.0] = 0.0
        active &= ds.pdf != 0.0
        medium = dr.select(active, medium, dr.zeros(mi.MediumPtr))
        medium[from_surface & si.is_medium_transition()] = si.target_medium(ds.d)
        ray = ref.spawn_ray_to(ds.p)
        length = mi.Float(ray.maxt)
        travelled = mi.Float(0.0)
        hit = dr.zeros(mi.SurfaceInteraction3f)
        hit_bsdf = dr.zeros(mi.BSDFPtr)
        needs_intersection = mi.Bool(True)
        transmittance = mi.Spectrum(1.0)
        while dr.hint(active, label="csg_volpath_shadow"):
            remaining = length - travelled
            ray.maxt = remaining
            active &= remaining > 0.0
            needs_intersection &= active
            found, found_bsdf, _, _, _ = csg.intersect(scene, ray, needs_intersection)
            hit[needs_intersection] = found
            hit_bsdf[needs_intersection] = found_bsdf
            needs_intersection &= False
            in_medium = active & (medium != None)
            on_surface = active & ~in_medium
            event = medium.sample_interaction(ray, sampler.next_1d(in_medium), channel, in_medium)
            event.t[in_medium & (hit.t < event.t)] = dr.inf
            factor = mi.Spectrum(1.0)
            # Homogeneous media: the transmittance to the next surface in closed form.
            homogeneous = in_medium & medium.is_homogeneous()
            event.t[homogeneous] = dr.minimum(remaining, hit.t)
            factor[homogeneous] = medium.transmittance_eval_pdf(event, hit, homogeneous)[0]
            event.t[homogeneous] = dr.inf
            escaped = in_medium & ~event.is_valid()
            # Heterogeneous media: ratio tracking.
            in_medium &= event.is_valid()
            ray.o[in_medium] = event.p
            hit.t[in_medium] = hit.t - event.t
            factor[in_medium] *= event.sigma_n / event.combined_extinction
            on_surface |= escaped
            on_surface &= hit.is_valid() & ~in_medium
            factor[on_surface] *= hit_bsdf.eval_null_transmission(hit, on_surface)
            transmittance *= factor
            ray[on_surface] = hit.spawn_ray(mi.Vector3f(ray.d))
            ray.maxt = remaining
            needs_intersection |= on_surface
            active &= (in_medium | on_surface) & dr.any(transmittance != 0.0)
            travelled[active] += dr.select(in_medium, event.t, hit.t)
            crossing = on_surface & hit.is_medium_transition()
            medium[crossing] = hit.target_medium(ray.d)
        return emitter_value * transmittance, ds

    def aov_names(self):
        return []

    def to_string(self):
        return f"CSGVolpathIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}]"
