"""Mitsuba plugins of mitsuba-csg, registered by `import mitsuba_csg` (see `register`)."""
from __future__ import annotations

import importlib

_registered_for: set[str] = set()
_modules_variant: list[str] = []


def register() -> None:
    """Register the `csg` shape and the `csg_*` integrators for the current Mitsuba variant.

    The plugin classes derive from the variant's own `mi.Mesh` / `mi.SamplingIntegrator`, so
    their modules are re-executed for each variant; each registration keeps its classes.
    """
    import mitsuba as mi
    variant = mi.variant()
    if variant in _registered_for:
        return
    from . import csg_aov, csg_common, csg_path, csg_shape, csg_volpath, integrator_guard
    modules = [csg_shape, csg_common, csg_path, csg_aov, csg_volpath]
    if _modules_variant and _modules_variant[-1] != variant:
        modules = [importlib.reload(m) for m in modules]
    _modules_variant.append(variant)
    shape_cls, path_cls, aov_cls = csg_shape.CSGShape, csg_path.CSGPathIntegrator, csg_aov.CSGAOVIntegrator
    volpath_cls = csg_volpath.CSGVolpathIntegrator
    mi.register_shape("csg", lambda props: shape_cls(props))
    mi.register_integrator("csg_path", lambda props: path_cls(props))
    mi.register_integrator("csg_aov", lambda props: aov_cls(props))
    mi.register_integrator("csg_volpath", lambda props: volpath_cls(props))
    if variant.startswith(("llvm_ad", "cuda_ad")):
        from . import csg_edges, csg_prb, csg_prb_projective
        if len(_modules_variant) > 1:
            csg_edges = importlib.reload(csg_edges)
            csg_prb = importlib.reload(csg_prb)
            csg_prb_projective = importlib.reload(csg_prb_projective)
        prb_cls = csg_prb.CSGPRBIntegrator
        projective_cls = csg_prb_projective.CSGPRBProjectiveIntegrator
        mi.register_integrator("csg_prb", lambda props: prb_cls(props))
        mi.register_integrator("csg_prb_projective", lambda props: projective_cls(props))
    integrator_guard.install(mi)
    for cls in (path_cls, aov_cls, volpath_cls):
        integrator_guard.keep_binding(mi, cls)
    _registered_for.add(variant)
