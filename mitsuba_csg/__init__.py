"""mitsuba-csg: exact ray tracing of Constructive Solid Geometry in Mitsuba 3 on Dr.Jit.

Importing the package selects Mitsuba's `llvm_ad_rgb` variant unless one is set already;
every `*_rgb` / `*_ad_rgb` JIT variant (LLVM or CUDA) works.
"""
from __future__ import annotations

from ._variant import ensure_variant

ensure_variant()

from .errors import CSGError, ModelError, TreeTooDeepError  # noqa: E402
from .model import Node, Operation, Primitive, difference, intersection, union  # noqa: E402
from .primitives import Box, Cone, ConvexPolyhedron, Cylinder, Prism, Sphere, Torus  # noqa: E402
from .optimize import OptimizedModel, optimize  # noqa: E402
from .tracing import Hits, IterationLimitWarning, Prepared, contains, prepare, trace, trace_rays  # noqa: E402
from .models import model_ref  # noqa: E402
from .io import load, save  # noqa: E402


def register_plugins() -> None:
    """Register the `csg` shape and `csg_*` integrators for the current Mitsuba variant.

    `import mitsuba_csg` does this for the variant active then; call it again after
    `mi.set_variant(...)` switches to another JIT variant.
    """
    # The plugins live in plugins/ (DESIGN.md §1); installed, that folder is the subpackage
    # mitsuba_csg.plugins. In a source checkout it sits beside this package: look there too.
    import os
    beside = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if not os.path.isdir(os.path.join(os.path.dirname(__file__), "plugins")) and \
            os.path.isfile(os.path.join(beside, "plugins", "__init__.py")) and beside not in __path__:
        __path__.append(beside)
    from ._variant import check_variant
    import mitsuba as mi
    check_variant(mi.variant())
    from .plugins import register
    register()


register_plugins()


def to_mesh(model, segments: int = 64):
    """The ground-truth triangle mesh of `model` (a manifold3d.Manifold)."""
    from .mesh import to_mesh as _to_mesh
    return _to_mesh(model, segments=segments)


__all__ = [
    "Box", "CSGError", "Cone", "ConvexPolyhedron", "Cylinder", "Hits", "IterationLimitWarning", "ModelError",
    "Node", "Operation", "OptimizedModel", "Prepared", "Primitive", "Prism", "Sphere", "Torus", "TreeTooDeepError",
    "contains", "difference", "load", "model_ref", "register_plugins", "save", "intersection", "optimize", "prepare", "to_mesh", "trace", "trace_rays", "union",
]
