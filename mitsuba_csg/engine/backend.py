"""Which Dr.Jit backend a computation runs on, and its array types.

The kernel is written once against a `Backend` (the detached types of `drjit.llvm` or
`drjit.cuda`); differentiable code asks for the AD module of the same backend.
"""
from __future__ import annotations

import functools
import sys

import drjit as dr

_MODULES = {dr.JitBackend.LLVM: "drjit.llvm", dr.JitBackend.CUDA: "drjit.cuda"}


class Backend:
    """The detached Dr.Jit types of one backend (drjit.llvm or drjit.cuda), and the kernel's
    records of them (`Hit`)."""

    def __init__(self, module):
        self.Float, self.UInt32, self.Bool = module.Float, module.UInt32, module.Bool
        self.Array3f, self.Array4f = module.Array3f, module.Array4f
        self.module = module
        self.Hit, self.SceneRay = _kernel_records(module)


@functools.cache
def _kernel_records(module):
    """The kernel's records of a backend (`Hit`, `SceneRay`): Dr.Jit structs, so they are
    selected and carried through symbolic loops whole (`dr.select(mask, a, b)`)."""
    class Hit:
        """An event of a subtree: where (`t`), on which leaf node (`leaf`, layout.NO_INDEX for
        none) and what it is (`info`: class, flip, slope and face, layout's hit info word)."""
        DRJIT_STRUCT = {"t": module.Float, "leaf": module.UInt32, "info": module.UInt32}

        def __init__(self, t=None, leaf=None, info=None):
            self.t, self.leaf, self.info = t, leaf, info

        def __repr__(self) -> str:
            return f"Hit(t={self.t}, leaf={self.leaf}, info={self.info})"

    class SceneRay:
        """A ray as the kernel traces it: in the scene frame (`engine.device.scene_rays`), with
        its inverse direction for box tests, its tie tolerance (`engine.automaton`) and the
        end of its interval `tmax`. Read, never changed, by every step of a traversal."""
        DRJIT_STRUCT = {"o": module.Array3f, "d": module.Array3f, "inv_d": module.Array3f, "tie": module.Float,
                        "tmax": module.Float}

        def __init__(self, o=None, d=None, inv_d=None, tie=None, tmax=None):
            self.o, self.d, self.inv_d, self.tie, self.tmax = o, d, inv_d, tie, tmax
    return Hit, SceneRay


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
