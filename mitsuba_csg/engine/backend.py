"""Which Dr.Jit backend a computation runs on, and its array types.

The kernel is written once against a `Backend` (the detached types of `drjit.llvm` or
`drjit.cuda`); differentiable code asks for the AD module of the same backend.
"""
from __future__ import annotations

import sys

import drjit as dr

_MODULES = {dr.JitBackend.LLVM: "drjit.llvm", dr.JitBackend.CUDA: "drjit.cuda"}


class Backend:
    """The detached Dr.Jit types of one backend (drjit.llvm or drjit.cuda)."""

    def __init__(self, module):
        self.Float, self.UInt32, self.Bool = module.Float, module.UInt32, module.Bool
        self.Array3f, self.Array4f = module.Array3f, module.Array4f
        self.module = module


def _module_name(array) -> str:
    tp = array if isinstance(array, type) else type(array)
    name = _MODULES.get(dr.backend_v(tp))
    if name is None:
        raise TypeError(f"mitsuba-csg kernels need a JIT array type (LLVM or CUDA), got {tp.__name__}")
    return name


def backend_of(array) -> Backend:
    """The detached backend of a Dr.Jit array or array type."""
    return Backend(sys.modules[_module_name(array)])


def ad_module(array):
    """drjit.llvm.ad or drjit.cuda.ad: the AD types of the backend `array` lives on."""
    return sys.modules[_module_name(array) + ".ad"]


def default_backend() -> Backend:
    """The backend of Mitsuba's current variant."""
    import mitsuba as mi
    return backend_of(mi.Float)


def owned(array_type, values):
    """A Dr.Jit array holding a copy of `values` in memory Dr.Jit allocated.

    Built from numpy, an LLVM array may map numpy's buffer, and the generated code depends
    on that buffer's alignment (packet loads or not), so the same model could compile a new
    kernel each time. An evaluated copy of Dr.Jit's own is always aligned.
    """
    source = array_type(values)
    array = dr.empty(array_type, dr.width(source))
    dr.scatter(array, source, dr.arange(dr.uint32_array_t(array_type), dr.width(source)))
    dr.eval(array)
    return array
