"""Shared test set-up: the package selects llvm_ad_rgb; hypothesis runs a bounded budget;
kernel tests run once per JIT backend this machine has (LLVM always, CUDA with a GPU)."""
import os

import drjit as dr
import mitsuba as mi
import pytest
from hypothesis import HealthCheck, settings

import mitsuba_csg  # noqa: F401  (selects the Mitsuba variant before any test imports mitsuba)

settings.register_profile("ci", max_examples=40, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("thorough", max_examples=400, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

JIT_VARIANTS = ["llvm_ad_rgb"] + (["cuda_ad_rgb"] if "cuda_ad_rgb" in mi.variants()
                                  and dr.has_backend(dr.JitBackend.CUDA) else [])


@pytest.fixture(scope="module", params=JIT_VARIANTS)
def jit_variant(request):
    """Run a module's tests on each JIT variant (`pytestmark = pytest.mark.usefixtures("jit_variant")`).

    Module scope: hypothesis refuses function-scoped fixtures, and a variant switch per module
    keeps kernel compilation caches warm.
    """
    previous = mi.variant()
    mi.set_variant(request.param)
    mitsuba_csg.register_plugins()
    yield request.param
    mi.set_variant(previous)
    mitsuba_csg.register_plugins()
