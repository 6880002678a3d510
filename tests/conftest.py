"""Shared test set-up: Hypothesis profiles, and killing a child process mid-mission.

``ci`` (the default) is deterministic and bounded; the fuzz tests in
``test_fuzz.py`` cap themselves lower still under it (``FUZZ_EXAMPLES``) so the
whole file runs in well under a minute. ``fuzz`` (``make fuzz``, or
``HYPOTHESIS_PROFILE=fuzz``) is random and long: thousands of examples per test.
"""

import os
import signal
import subprocess
from collections.abc import Callable

import pytest
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


def _sigkill_after(child: subprocess.Popen[str], count: int) -> None:
    """Read the child's stdout (one scan count per line) until ``count``, then SIGKILL it."""
    assert child.stdout is not None
    seen = 0
    while seen < count:  # wait until count inserts have returned
        line = child.stdout.readline()
        assert line, "child ended early"
        seen = int(line)
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    for stream in (child.stdout, child.stdin):
        if stream is not None:
            stream.close()


@pytest.fixture
def sigkill_after() -> Callable[[subprocess.Popen[str], int], None]:
    """Kill a mapping child process (printing its scan count per insert) after ``count``."""
    return _sigkill_after
