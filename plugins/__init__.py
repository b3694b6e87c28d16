"""Mitsuba plugins of mitsuba-csg, registered by `import mitsuba_csg` (see `register`)."""
from __future__ import annotations

_registered_for: set[str] = set()
_modules_variant: list[str] = []


def register() -> None:
    """Register the `csg` shape and the `csg_*` integrators (`registry.integrators`) for the
    current Mitsuba variant.

    The plugin classes derive from the variant's own `mi.Mesh` / `mi.SamplingIntegrator`, so
    their modules are run again for each variant; each registration keeps its classes.
    """
    import mitsuba as mi
    from mitsuba.ad.integrators.common import ADIntegrator

    from . import integrator_guard, registry
    variant = mi.variant()
    if variant in _registered_for:
        return
    registry.load_plugin_modules(reload=bool(_modules_variant) and _modules_variant[-1] != variant)
    _modules_variant.append(variant)
    from .csg_shape import CSGShape
    mi.register_shape("csg", lambda props, cls=CSGShape: cls(props))
    integrator_guard.install(mi)
    for name in registry.integrator_names():
        cls = registry.integrator_class(name)
        mi.register_integrator(name, lambda props, cls=cls: cls(props))
        if not issubclass(cls, ADIntegrator):
            integrator_guard.keep_binding(mi, cls)
    _registered_for.add(variant)
