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


def to_mesh(model, segments: int = 64):
    """The ground-truth triangle mesh of `model` (a manifold3d.Manifold)."""
    from .mesh import to_mesh as _to_mesh
    return _to_mesh(model, segments=segments)


__all__ = [
    "Box", "CSGError", "Cone", "ConvexPolyhedron", "Cylinder", "Hits", "IterationLimitWarning", "ModelError",
    "Node", "Operation", "OptimizedModel", "Prepared", "Primitive", "Prism", "Sphere", "Torus", "TreeTooDeepError",
    "contains", "difference", "intersection", "optimize", "prepare", "to_mesh", "trace", "trace_rays", "union",
]
