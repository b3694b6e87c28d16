"""Mitsuba variant selection: the engine needs a JIT variant (LLVM or CUDA; RGB, mono or spectral)."""
from __future__ import annotations

import glob
import os

from .errors import CSGError

DEFAULT_VARIANT = "llvm_ad_rgb"


def prefer_llvm19() -> None:
    """Point Dr.Jit at LLVM 19 when the system has it: Dr.Jit 1.5 fails with LLVM 15."""
    if "DRJIT_LIBLLVM_PATH" in os.environ:
        return
    found = sorted(glob.glob("/usr/lib/*/libLLVM-19.so*") + glob.glob("/usr/lib/*/libLLVM.so.19*"))
    if found:
        os.environ["DRJIT_LIBLLVM_PATH"] = found[0]


def ensure_variant() -> str:
    """Select `llvm_ad_rgb` if no variant is set; refuse scalar variants with a clear error."""
    prefer_llvm19()
    import mitsuba as mi
    variant = mi.variant()
    if variant is None:
        mi.set_variant(DEFAULT_VARIANT)
        variant = DEFAULT_VARIANT
    check_variant(variant)
    return variant


def check_variant(variant: str) -> None:
    if variant.startswith("scalar_"):
        import mitsuba as mi
        jit = [v for v in mi.variants() if v.startswith(("llvm_", "cuda_"))]
        raise CSGError(f"mitsuba-csg needs a JIT variant ({', '.join(jit) or 'none is installed'}); "
                       f"the current variant is {variant!r}. Call mi.set_variant('llvm_ad_rgb') first.")
