"""The `csg_path` integrator: a unidirectional path tracer that sees CSG shapes."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba.ad.integrators.common import mis_weight

from mitsuba_csg.engine.device import scene_rays
from mitsuba_csg.engine.layout import NO_INDEX
from mitsuba_csg.engine.ray_order import coherent_order, sort_keys

from .csg_common import SceneCSG, camera_ray_valid, read_depths, read_hide_emitters
from .registry import integrator


# Depth after which the paths still going on are gathered into fewer lanes (`_may_compact`):
# on a Cheese of 1000 holes, about one path in five is left by then.
COMPACT_DEPTH = 2
# Widest wavefront (samples per pass) whose paths are gathered: the gathered state takes about
# 150 bytes a lane, 0.6 GB here, where the megakernel keeps it in registers (a test's 24x18
# image at 65,536 samples per pixel in one pass, 28 million lanes, ran out of 24 GB).
MAX_COMPACT_LANES = 1 << 22


class Paths:
    """The state of a wavefront of paths between bounces (a Dr.Jit struct: gathered as one)."""
    DRJIT_STRUCT = {"ray": mi.Ray3f, "L": mi.Spectrum, "beta": mi.Spectrum, "eta": mi.Float, "depth": mi.UInt32,
                    "active": mi.Bool, "prev_si": mi.Interaction3f, "prev_bsdf_pdf": mi.Float,
                    "prev_bsdf_delta": mi.Bool, "start": mi.UInt32}

    def __init__(self, ray=None, L=None, beta=None, eta=None, depth=None, active=None, prev_si=None,
                 prev_bsdf_pdf=None, prev_bsdf_delta=None, start=None):
        self.ray = ray
        self.L = L                              # radiance accumulated so far
        self.beta = beta                        # path throughput weight
        self.eta = eta                          # index of refraction ratio so far
        self.depth = depth                      # path depth
        self.active = active
        self.prev_si = prev_si                  # previous vertex, for MIS of emitter hits
        self.prev_bsdf_pdf = prev_bsdf_pdf
        self.prev_bsdf_delta = prev_bsdf_delta
        self.start = start                      # the CSG primitive the ray leaves (a traversal hint)

    @staticmethod
    def begin(ray: mi.Ray3f, active) -> "Paths":
        return Paths(ray, mi.Spectrum(0), mi.Spectrum(1), mi.Float(1), mi.UInt32(0), mi.Bool(active),
                     dr.zeros(mi.Interaction3f), mi.Float(1.0), mi.Bool(True), mi.UInt32(NO_INDEX))


def _may_compact(max_depth: int, lanes: int) -> bool:
    """Whether the paths that go on after COMPACT_DEPTH may be gathered into fewer lanes: on
    a JIT variant rendering kernel by kernel (compaction evaluates the wavefront and reads its
    size back), not recorded into a symbolic loop or a frozen function, for a wavefront of at
    most MAX_COMPACT_LANES lanes."""
    return max_depth > COMPACT_DEPTH and lanes <= MAX_COMPACT_LANES and dr.is_jit_v(mi.Float) and not any(
        dr.flag(flag) for flag in (dr.JitFlag.SymbolicScope, dr.JitFlag.FreezingScope,
                                   dr.JitFlag.ForbidSynchronization))


def _coherent_lanes(csg: SceneCSG, paths: Paths):
    """The lanes of the paths still active (evaluated), ordered by where their next rays start
    and where they go (`engine.ray_order`): neighbouring lanes then do similar traversal work."""
    alive = dr.compress(paths.active)
    if dr.width(alive) == 0:
        return alive
    tree = csg.traced_tree()
    o, d, _ = scene_rays(tree, dr.gather(mi.Point3f, paths.ray.o, alive), dr.gather(mi.Vector3f, paths.ray.d, alive))
    order, _ = coherent_order(tree.b, sort_keys(tree.b, o, d), dr.full(mi.Bool, True, dr.width(alive)))
    return dr.gather(mi.UInt32, alive, order)


@integrator("csg_path", "path tracing", {"Path": "", "Direct": "with max_depth 2"})
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

    After the second bounce, the paths still going on (on a Cheese of 1000 holes, about one
    in five) are gathered into fewer lanes, ordered by where their next rays start and go,
    and traced on with a sampler of their own, seeded from the scene's: a SIMD packet costs
    what its slowest lane costs, active or not, and a CSG traversal is long next to an
    Embree query. Their random numbers then differ from those `path` would draw, not their
    distribution. Recorded into a frozen function or a symbolic operation, where nothing can
    be evaluated, and for passes of more than 2^22 samples (whose gathered state would take
    gigabytes; `samples_per_pass` splits a render into smaller passes), all paths are traced
    in one loop, as `path` traces them.

    .. code-block:: python

        'integrator': {'type': 'csg_path', 'max_depth': 8}
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.max_depth, self.rr_depth = read_depths(props, "csg_path")
        self.hide_emitters = read_hide_emitters(props, "csg_path")

    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: bool = True):
        if self.max_depth == 0:   # as Mitsuba's path: nothing, not even emitters
            return mi.Spectrum(0), dr.zeros(mi.Bool, dr.width(ray.d)), []
        csg = SceneCSG(scene)
        paths = Paths.begin(mi.Ray3f(dr.detach(ray)), active)
        if not (csg.csg and _may_compact(self.max_depth, dr.width(ray.d))):
            paths = self._trace_paths(scene, sampler, csg, paths, self.max_depth)
            return paths.L, camera_ray_valid(scene, self.hide_emitters, paths.depth), []
        paths = self._trace_paths(scene, sampler, csg, paths, COMPACT_DEPTH)
        L, valid = paths.L, camera_ray_valid(scene, self.hide_emitters, paths.depth)
        sampler.schedule_state()     # evaluated with the paths: else a later kernel re-runs their loop
        dr.eval(paths)
        lanes = _coherent_lanes(csg, paths)
        if dr.width(lanes) == 0:
            return L, valid, []
        # The paths that go on draw their random numbers from a sampler of their own (the
        # scene's is seeded for the whole wavefront), seeded from the scene's: renders with
        # other seeds go on differently.
        seed = int(dr.gather(mi.UInt32, mi.UInt32(sampler.next_1d() * 4294967040.0), 0)[0])
        sampler = sampler.clone()
        sampler.seed(seed, dr.width(lanes))
        rest = dr.gather(Paths, paths, lanes)
        del paths                    # the whole wavefront's state, no longer needed
        rest.L = dr.zeros(mi.Spectrum, dr.width(lanes))
        rest = self._trace_paths(scene, sampler, csg, rest, self.max_depth)
        dr.scatter_add(L, rest.L, lanes)
        # Evaluated here: with a box filter, the film's kernel took L with its scatter still
        # pending and Dr.Jit aborted ("dirty variable encountered").
        dr.eval(L)
        return L, valid, []

    @dr.syntax
    def _trace_paths(self, scene, sampler, csg, paths, stop_depth):
        """Paths traced on until they end, or reach depth `stop_depth` (still active then)."""
        bsdf_ctx = mi.BSDFContext()
        ray, L, beta, eta, depth, active = paths.ray, paths.L, paths.beta, paths.eta, paths.depth, paths.active
        prev_si, prev_bsdf_pdf, prev_bsdf_delta = paths.prev_si, paths.prev_bsdf_pdf, paths.prev_bsdf_delta
        start = paths.start

        while dr.hint(active & (depth < stop_depth), max_iterations=stop_depth, label="csg_path"):
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

        return Paths(ray, L, beta, eta, depth, active, prev_si, prev_bsdf_pdf, prev_bsdf_delta, start)

    def aov_names(self):
        return []

    def to_string(self):
        return f"CSGPathIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}]"
