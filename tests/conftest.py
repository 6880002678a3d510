"""Shared test set-up: Hypothesis profiles, the shared data, killing a child mid-mission, CLI errors.

``ci`` (the default) is deterministic and bounded; the fuzz tests in
``test_fuzz.py`` cap themselves lower still under it (``FUZZ_EXAMPLES``) so the
whole file runs in well under a minute. ``fuzz`` (``make fuzz``, or
``HYPOTHESIS_PROFILE=fuzz``) is random and long: thousands of examples per test.

``cli_exit_2`` runs ``python -m octolgp.cli`` in a real process and checks the
contract for bad input: exit status 2 and one ``octolgp: error:`` line, no traceback.

``SHARED_DATA`` is the shared data set, ``../shared/data`` beside the repository (not
part of a clone); the ``shared_data`` fixture gives a path in it, or skips the test
when that path is absent.
"""

import os
import signal
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

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

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
"""The shared data set: ``shared/data`` in the repository's parent folder."""


def _shared_data(*parts: str) -> Path:
    """``SHARED_DATA / parts``, or skip the test when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} is absent (the shared data set ../shared/data is not in a clone)")
    return path


@pytest.fixture
def shared_data() -> Callable[..., Path]:
    """A path in the shared data set, ``shared_data("fr079", name)``; skips when absent."""
    return _shared_data


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


def _cli_exit_2(
    argv: Sequence[str], cwd: Path, message: str = "", prefix: str = "octolgp: error:"
) -> str:
    """Run the CLI on ``argv`` in ``cwd``; check it exits 2 with one error line; return it.

    The line must start with ``prefix`` and contain ``message``; stderr must hold no
    traceback. (argparse's own errors name the subcommand: ``octolgp run: error:``.)
    """
    proc = subprocess.run(
        [sys.executable, "-m", "octolgp.cli", *argv],
        capture_output=True,
        text=True,
        cwd=cwd,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(prefix), lines[0]
    assert message in lines[0]
    return lines[0]


@pytest.fixture
def cli_exit_2() -> Callable[..., str]:
    """Run the CLI in a subprocess on bad input: exit 2, one error line, no traceback.

    Called as ``cli_exit_2(argv, cwd, message="", prefix="octolgp: error:")``; returns
    the error line.
    """
    return _cli_exit_2
