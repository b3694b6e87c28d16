"""Mitsuba's own integrators cannot see `csg` shapes: refuse them by name instead of rendering
the scene without the model.

Mitsuba 3.9 traces its own shape types only (Embree or OptiX); a `csg` shape is a proxy mesh
with one degenerate triangle that nothing hits, traced by the `csg_*` integrators. `path`,
`prb_projective`, `aov` and the rest would render every other shape and leave the model out,
a plausible and wrong image. `install` wraps the render entry points of Mitsuba's integrator
base classes (`Integrator.render`, the forward and backward passes, the Python `ADIntegrator`
ones) with `check`, so `mi.render(scene)` and `integrator.render(scene, sensor)` alike raise an
error that names the integrator, the shapes and what to use instead.

Integrators that trace CSG are registered with `registry.integrator`, which marks them with
a class attribute `traces_csg = True` (an integrator of one's own may set it too); one that
nests another (`csg_aov`'s colour) is checked for its nested integrator too. A `csg` shape in
a shape group (instancing) is refused for every integrator: the group's own acceleration
structure holds Mitsuba's shapes only, so its copies would be invisible.

Ctrl-C: Mitsuba's `Integrator.render` binding installs its own SIGINT handler for the render
and puts back the one it found, kept in a single static slot. A Python wrapper on the base
class looks, to the trampoline of a Python integrator, like an override, so such a render
re-enters the binding, the inner call overwrites that slot, and Mitsuba's handler stays
installed afterwards: the next Ctrl-C cancels a finished render and never reaches Python.
Our own `SamplingIntegrator` plugins therefore keep the unwrapped binding and are checked
in `sample` instead (`keep_binding`, applied to each at registration), and for other Python integrators the outermost wrapper puts
Python's handler back once such a nested call has happened.
"""
from __future__ import annotations

import functools
import signal
import threading

from mitsuba_csg.errors import CSGError

from . import registry


_BOUND_BASES = {"Integrator", "SamplingIntegrator", "MonteCarloIntegrator", "AdjointIntegrator", "Shape", "Mesh"}


def _name(obj) -> str:
    """The class a user would recognise: a Python plugin's own, else the C++ class's name."""
    name = type(obj).__name__
    if name in _BOUND_BASES:
        try:
            return obj.class_name()
        except Exception:
            pass
    return name


def csg_shapes(scene) -> list:
    """The scene's `csg` shapes (top-level ones; `grouped_csg_shapes` finds the others)."""
    return [s for s in scene.shapes() if getattr(s, "is_csg_proxy", False)]


def grouped_csg_shapes(mi, scene) -> list:
    """`csg` shapes inside shape groups (instancing), found through `mi.traverse`, which walks
    the whole scene graph. Only scenes with instances are walked."""
    if not any(_name(s) == "Instance" for s in scene.shapes()):
        return []
    top = {id(s) for s in scene.shapes()}
    found, seen = [], set()
    for entry in mi.traverse(scene).properties.values():
        node = entry[2]
        if getattr(node, "is_csg_proxy", False) and id(node) not in top and id(node) not in seen:
            seen.add(id(node))
            found.append(node)
    return found


def counterpart(name: str) -> str:
    """What to use instead of a Mitsuba integrator, by the words in its class name."""
    return registry.counterpart(name) or registry.described()


def describe(shapes) -> str:
    names = [s.id() or "(no id)" for s in shapes]
    shown = ", ".join(repr(n) for n in names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
    return f"csg shape{'s' if len(names) > 1 else ''} {shown}"


def check(mi, integrator, scene) -> None:
    """Raise if `integrator` would render `scene` without its csg shapes."""
    if scene is None:
        return
    if getattr(integrator, "traces_csg", False):
        grouped = grouped_csg_shapes(mi, scene)
        if grouped:
            # A shape group builds its own acceleration structure, of Mitsuba's shapes only.
            raise CSGError(f"the {describe(grouped)} sit{'s' if len(grouped) == 1 else ''} in a shapegroup: csg "
                           f"shapes cannot be instanced; give each copy its own csg shape (with its to_world), "
                           f"or make one csg shape of the union of the copies")
        inner = getattr(integrator, "inner", None)
        if inner is None or getattr(inner, "traces_csg", False):
            return
        shapes = csg_shapes(scene)
        if shapes:
            raise CSGError(f"{_name(integrator)}: its nested {_name(inner)} integrator cannot see the "
                           f"{describe(shapes)} (Mitsuba's own integrators trace only Mitsuba's shapes), so the "
                           f"colour would lack the model; nest {registry.counterpart(_name(inner)) or 'csg_path'} instead")
        return
    shapes = csg_shapes(scene) + grouped_csg_shapes(mi, scene)
    if shapes:
        raise CSGError(f"the {_name(integrator)} integrator cannot see the {describe(shapes)}: Mitsuba's own "
                       f"integrators trace only Mitsuba's shapes and would render the scene without the model. "
                       f"Use {counterpart(_name(integrator))} (the csg_* integrators: {registry.described()}), or "
                       f"render a mesh of the model (mitsuba_csg.to_mesh) with {_name(integrator)}")


# (integrator, scene) pairs that `mi.render` checked and is rendering now: its call reaches
# the integrator's own (wrapped) render, which need not scan the scene again.
_checked = threading.local()


# Wrapped render calls in progress on this thread, and whether one of them re-entered
# Mitsuba's render binding (see the module's docstring).
_calls = threading.local()


def _guarded(mi, method):
    @functools.wraps(method)
    def render(self, scene, *args, **kwargs):
        if getattr(_checked, "pair", None) != (id(self), id(scene)):
            check(mi, self, scene)
        depth = getattr(_calls, "depth", 0)
        _calls.nested = depth > 0
        _calls.depth = depth + 1
        try:
            return method(self, scene, *args, **kwargs)
        finally:
            _calls.depth = depth
            if depth == 0 and _calls.nested:
                _restore_python_sigint()
    render._csg_guard = True
    return render


def _restore_python_sigint() -> None:
    """Reinstall Python's own SIGINT handler (only the main thread may; elsewhere Ctrl-C does
    not reach Python code anyway)."""
    if threading.current_thread() is threading.main_thread():
        handler = signal.getsignal(signal.SIGINT)
        if handler is not None:
            signal.signal(signal.SIGINT, handler)


def _guarded_render_function(mi, render):
    """`mi.render`, checked before Dr.Jit's custom operation (which would replace our error by
    its own 'error while performing a custom differentiable operation')."""
    @functools.wraps(render)
    def guarded(scene, params=None, sensor=0, integrator=None, *args, **kwargs):
        used = integrator if integrator is not None else scene.integrator()
        check(mi, used, scene)
        outer, _checked.pair = getattr(_checked, "pair", None), (id(used), id(scene))
        try:
            return render(scene, params, sensor, integrator, *args, **kwargs)
        finally:
            _checked.pair = outer
    guarded._csg_guard = True
    return guarded


def install(mi) -> None:
    """Wrap `mi.render` and the render entry points of the current variant's integrator classes
    (once each)."""
    import mitsuba
    if not getattr(mitsuba.render, "_csg_guard", False):
        mitsuba.render = _guarded_render_function(mitsuba, mitsuba.render)
    from mitsuba.ad.integrators.common import ADIntegrator
    targets = [(mi.Integrator, "render"), (mi.SamplingIntegrator, "render_forward"),
               (mi.SamplingIntegrator, "render_backward"), (ADIntegrator, "render"),
               (ADIntegrator, "render_forward"), (ADIntegrator, "render_backward")]
    for cls, name in targets:
        method = cls.__dict__.get(name)
        if method is None or getattr(method, "_csg_guard", False):
            continue
        setattr(cls, name, _guarded(mi, method))


def keep_binding(mi, cls) -> None:
    """Give a Python `SamplingIntegrator` subclass Mitsuba's own `render` binding, so its
    trampoline sees no override and Mitsuba's Ctrl-C handling works as for its own integrators,
    and check the scene in its `sample` instead (once per render pass, as it is traced)."""
    if "render" not in cls.__dict__:
        method = mi.Integrator.__dict__["render"]
        cls.render = getattr(method, "__wrapped__", method)
    sample = cls.__dict__.get("sample")
    if sample is not None and not getattr(sample, "_csg_guard", False):
        @functools.wraps(sample)
        def checked(self, scene, *args, **kwargs):
            check(mi, self, scene)
            return sample(self, scene, *args, **kwargs)
        checked._csg_guard = True
        cls.sample = checked
