"""Shared test set-up: Hypothesis profiles.

``ci`` (the default) is deterministic and bounded; the fuzz tests in
``test_fuzz.py`` cap themselves lower still under it (``FUZZ_EXAMPLES``) so the
whole file runs in well under a minute. ``fuzz`` (``make fuzz``, or
``HYPOTHESIS_PROFILE=fuzz``) is random and long: thousands of examples per test.
"""

import os

from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    max_examples=40,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile(
    "fuzz",
    deadline=None,
    max_examples=2000,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
