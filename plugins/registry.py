"""The csg_* integrators, as their modules register them.

Each integrator's module registers its class with the `integrator` decorator, as Mitsuba's
own Python integrators end with `mi.register_integrator`: adding an integrator is adding its
module to this package. Every list of integrators (the plugin registration, the guard's
advice for Mitsuba's own integrators, the command line's and batch jobs' choices, the plugin
docs) is read from here, so none is kept by hand.
"""
from __future__ import annotations

import importlib
import pkgutil
from dataclasses import dataclass, field


@dataclass(frozen=True)
class IntegratorInfo:
    name: str               # the plugin name in a scene: <integrator type="csg_path">
    summary: str            # what it is for, in a few words (error messages, --help)
    module: str             # the module that registered it
    # Words of Mitsuba integrator class names it stands in for (the guard's advice), each with
    # what to add ("with max_depth 2"); the longest word found in a class name decides.
    stands_in_for: dict = field(default_factory=dict)


_INFO: dict[str, IntegratorInfo] = {}
_CLASS: dict[str, type] = {}       # the classes of the variant whose modules ran last


def integrator(name: str, summary: str, stands_in_for: dict | None = None):
    """Class decorator: registers a `mi.SamplingIntegrator` subclass as the csg integrator
    `name`, marking it as one that traces csg shapes (`traces_csg`, `integrator_guard`)."""
    def register(cls):
        cls.traces_csg = True
        _INFO[name] = IntegratorInfo(name, summary, cls.__module__, dict(stands_in_for or {}))
        _CLASS[name] = cls
        return cls
    return register


def plugin_modules() -> list[str]:
    """The names of this package's plugin modules (csg_*), in name order."""
    from . import __path__ as package_path
    return sorted(m.name for m in pkgutil.iter_modules(package_path) if m.name.startswith("csg_"))


def load_plugin_modules(reload: bool = False) -> None:
    """Import every plugin module (its classes derive from the current variant's Mitsuba
    types), or run them again for another variant (`reload`): the modules that register no
    integrator first, since the integrators' modules import their classes."""
    modules = [importlib.import_module(f"{__package__}.{name}") for name in plugin_modules()]
    if reload:
        integrator_modules = {info.module for info in _INFO.values()}
        for module in sorted(modules, key=lambda m: m.__name__ in integrator_modules):
            importlib.reload(module)


def integrators() -> dict[str, IntegratorInfo]:
    """The registered integrators by name, in name order (imports the plugin modules, which
    needs a Mitsuba variant: `import mitsuba_csg` selects one)."""
    if not _INFO:
        load_plugin_modules()
    return {name: _INFO[name] for name in sorted(_INFO)}


def integrator_names() -> tuple[str, ...]:
    return tuple(integrators())


def integrator_class(name: str) -> type:
    """The class registered as `name` for the variant whose plugin modules ran last."""
    integrators()
    return _CLASS[name]


def described() -> str:
    """'csg_aov (buffers), csg_path (path tracing), ... or csg_volpath (media)'."""
    items = [f"{info.name} ({info.summary})" for info in integrators().values()]
    return ", ".join(items[:-1]) + " or " + items[-1] if len(items) > 1 else "".join(items)


def counterpart(class_name: str) -> str | None:
    """The csg integrator to use instead of a Mitsuba integrator of this class name, or None."""
    matches = [(len(word), info.name, advice) for info in integrators().values()
               for word, advice in info.stands_in_for.items() if word.lower() in class_name.lower()]
    if not matches:
        return None
    _, name, advice = max(matches)
    return f"{name} {advice}".strip()
