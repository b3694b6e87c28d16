"""Mitsuba plugins of mitsuba-csg, registered by `import mitsuba_csg` (see `register`)."""
from __future__ import annotations

_registered_for: set[str] = set()


def register() -> None:
    """Register the `csg` shape and the `csg_*` integrators for the current Mitsuba variant."""
    import mitsuba as mi
    variant = mi.variant()
    if variant in _registered_for:
        return
    from . import csg_aov, csg_path, csg_shape
    mi.register_shape("csg", lambda props: csg_shape.CSGShape(props))
    mi.register_integrator("csg_path", lambda props: csg_path.CSGPathIntegrator(props))
    mi.register_integrator("csg_aov", lambda props: csg_aov.CSGAOVIntegrator(props))
    try:
        from . import csg_prb
        mi.register_integrator("csg_prb", lambda props: csg_prb.CSGPRBIntegrator(props))
    except ImportError:
        pass
    _registered_for.add(variant)
