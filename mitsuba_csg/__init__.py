"""mitsuba-csg: exact ray tracing of Constructive Solid Geometry in Mitsuba 3 on Dr.Jit.

Importing the package has three effects, all on Mitsuba's side:

* if `DRJIT_LIBLLVM_PATH` is unset and the system has LLVM 19, it is set to it (Dr.Jit 1.5
  crashes with LLVM 15, the default of older distributions);
* if no Mitsuba variant is set, `llvm_ad_rgb` is selected (every `*_rgb` / `*_ad_rgb` JIT
  variant works; a scalar variant is refused with `CSGError`);
* the `csg` shape and the `csg_*` integrators are registered for the current variant (call
  `register_plugins()` again after `mi.set_variant` switches to another one).

The data flows file / Python API -> `model` -> `engine` (optimizer, flat arrays, Dr.Jit
kernel) -> hits (`queries`) -> Mitsuba integrators (`plugins`); `formats` reads and writes
files, `scenes` builds the paper's test scenes.
"""
from __future__ import annotations

from .variant import ensure_variant

ensure_variant()

from .errors import CSGError, ModelError, TreeTooDeepError  # noqa: E402
from .model import (Box, Cone, ConvexPolyhedron, Cylinder, Hyperboloid, Mesh, MeshOrientationWarning, Node,  # noqa: E402
                    Operation, Paraboloid, Primitive, Prism, Sphere, Torus, difference, intersection, union)
from .engine.lowering import PrecisionWarning  # noqa: E402
from .engine.optimize import OptimizedModel, optimize  # noqa: E402
from .queries import (Hits, IterationLimitWarning, Prepared, RayHits, contains, prepare, rays_to_device,  # noqa: E402
                      trace, trace_rays)
from .formats import load, save  # noqa: E402
from .plugins.model_ref import model_ref  # noqa: E402


def register_plugins() -> None:
    """Register the `csg` shape and `csg_*` integrators for the current Mitsuba variant.

    `import mitsuba_csg` does this for the variant active then; call it again after
    `mi.set_variant(...)` switches to another JIT variant.
    """
    import mitsuba as mi

    from .plugins import register
    from .variant import check_variant
    check_variant(mi.variant())
    register()


register_plugins()


def to_mesh(model, segments: int = 64):
    """The ground-truth triangle mesh of `model` (a manifold3d.Manifold)."""
    from .formats.mesh_export import to_mesh as _to_mesh
    return _to_mesh(model, segments=segments)


__all__ = [
    "Box", "CSGError", "Cone", "ConvexPolyhedron", "Cylinder", "Hits", "Hyperboloid", "IterationLimitWarning", "Mesh",
    "MeshOrientationWarning", "ModelError",
    "Node", "Operation", "OptimizedModel", "Paraboloid", "PrecisionWarning", "Prepared", "Primitive", "Prism", "RayHits", "Sphere", "Torus",
    "TreeTooDeepError", "contains", "difference", "intersection", "load", "model_ref", "optimize", "prepare",
    "rays_to_device", "register_plugins", "save", "to_mesh", "trace", "trace_rays", "union",
]
