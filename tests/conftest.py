"""Shared test set-up: the package selects llvm_ad_rgb; hypothesis runs a bounded budget."""
import os

from hypothesis import HealthCheck, settings

import mitsuba_csg  # noqa: F401  (selects the Mitsuba variant before any test imports mitsuba)

settings.register_profile("ci", max_examples=40, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("thorough", max_examples=400, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
