"""The command line's guarantees: outputs, ``--resume``, refused scans, configs, I/O faults.

Every file the CLI writes is refused when it exists (unless ``--overwrite``) and appears
at its path only whole: a full disk keeps the earlier file, a killed export leaves no half
file. ``--resume`` checks the log against the map's journal; a refused scan is named by
its number and log; absurd config values are refused naming the field; I/O and database
faults end in one line and exit 2.
"""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_guarantees import CONFIG, HP, HP_TOML, SCANS

from octolgp import (
    Hyperparameters,
    LatticeConfig,
    MapConfig,
    OctolgpError,
    OnlineMap,
    PartitionConfig,
    Scan,
    TrainingConfig,
)
from octolgp.cli import main
from octolgp.io import save_scan_log

PRECIOUS = b"precious: the earlier file\n"


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    """The single ``octolgp: error:`` line on stderr since the last read."""
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("octolgp: error: "), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def map2d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small 2D map file (four scans of a square room)."""
    path = tmp_path_factory.mktemp("map") / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(SCANS[:4])
    return path


@pytest.fixture
def config_file(tmp_path: Path) -> Path:
    """A TOML config with given hyperparameters (nothing to learn: fast runs)."""
    path = tmp_path / "c.toml"
    path.write_text(HP_TOML)
    return path


# --------------------------------------------------------------------------- configs


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: MapConfig(memory_budget_mb=1e308), "MapConfig.memory_budget_mb"),
        (lambda: Hyperparameters(length_scale=1e-308), "Hyperparameters.length_scale"),
        (lambda: Hyperparameters(length_scale=1e308), "Hyperparameters.length_scale"),
        (lambda: Hyperparameters(signal_variance=1e308), "Hyperparameters.signal_variance"),
        (lambda: Hyperparameters(noise_variance=1e308), "Hyperparameters.noise_variance"),
        (lambda: Hyperparameters(alpha=1e200), "Hyperparameters.alpha"),
        (lambda: Hyperparameters(beta=-1e200), "Hyperparameters.beta"),
        (lambda: TrainingConfig(quadrature_spacing=1e-308), "TrainingConfig.quadrature_spacing"),
        (lambda: LatticeConfig(inducing_spacing=1e-308), "LatticeConfig.inducing_spacing"),
        (lambda: LatticeConfig(free_weight=1e-308), "LatticeConfig.free_weight"),
        (lambda: PartitionConfig(box_size=1e-308), "PartitionConfig.box_size"),
        (lambda: PartitionConfig(overlap=1e308), "PartitionConfig.overlap"),
    ],
)
def test_absurd_config_values_are_refused_naming_the_field(make: Any, field: str) -> None:
    with pytest.raises(OctolgpError, match=rf"^{field} must be "):
        make()


def test_the_learners_extremes_stay_valid() -> None:
    Hyperparameters(1e-2, 1e-2, 1e-4, 1e-3, -1e2)
    Hyperparameters(1e2, 1e3, 1e2, 1e3, 1e2)
    Hyperparameters(0.5, 1.0, 1e-300, 1.0, 0.0)  # no noise: repaired by jitter


@pytest.mark.parametrize(
    ("toml", "field", "line"),
    [
        ("dim = 2\n# a budget\nmemory_budget_mb = 1e308\n", "memory_budget_mb", 3),
        (HP_TOML.replace("length_scale = 0.4", "length_scale = 1e-308"), "length_scale", 2),
        ("dim = 2\n[online]\nhalo = 0.7\n", "online.halo", 3),
    ],
)
def test_a_bad_config_value_names_the_file_the_field_and_the_line(
    toml: str, field: str, line: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text(toml)
    log = tmp_path / "a.npz"
    save_scan_log(log, SCANS[:2])
    argv = ["run", str(log), "--out", str(tmp_path / "m.octolgp"), "--config", str(cfg)]
    capsys.readouterr()
    assert main([*argv, "--quiet"]) == 2
    message = one_error_line(capsys)
    assert f"config file {str(cfg)!r}: " in message
    assert field in message
    assert message.endswith(f"(line {line})")
