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


# --------------------------------------------------------------------------- outputs

# an output, written again with --overwrite over an earlier file, and its side files
OUTPUTS = {
    "export .ply": (["export", "{map}", "--out", "{dir}/o.ply"], ["o.ply"]),
    "export .pcd": (["export", "{map}", "--out", "{dir}/o.pcd"], ["o.pcd"]),
    "export .bt": (["export", "{map}", "--out", "{dir}/o.bt"], ["o.bt"]),
    "export .png": (["export", "{map}", "--out", "{dir}/o.png"], ["o.png"]),
    "export .pgm": (["export", "{map}", "--out", "{dir}/o.pgm"], ["o.pgm", "o.yaml"]),
    "query": (["query", "{map}", "--points", "{dir}/pts.npy", "--out", "{dir}/p.npy"], ["p.npy"]),
    "simulate": (["simulate", "paper2d", "--out", "{dir}/sim.npz"], ["sim.npz"]),
}

FULL_DISK = """
import resource, sys
from octolgp.cli import main
_, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
resource.setrlimit(resource.RLIMIT_FSIZE, (1024, hard))  # writes past 1 KiB fail (EFBIG)
sys.exit(main(sys.argv[1:]))
"""

KILLED = """
import builtins, os, sys
from octolgp.cli import main
real_open = builtins.open
class Dying:  # a file whose writer is killed once it has written 1 KiB
    def __init__(self, f):
        self.f, self.n = f, 0
    def write(self, b):
        self.n += memoryview(b).nbytes
        if self.n > 1024:
            self.f.write(bytes(memoryview(b))[:16]); self.f.flush(); os._exit(137)
        return self.f.write(b)
    def __getattr__(self, name):
        return getattr(self.f, name)
    def __enter__(self):
        return self
    def __exit__(self, *exc):
        return self.f.__exit__(*exc)
def dying_open(file, mode="r", *args, **kwargs):
    f = real_open(file, mode, *args, **kwargs)
    return Dying(f) if "w" in mode and str(file).endswith(sys.argv[1]) else f
builtins.open = dying_open
sys.exit(main(sys.argv[2:]))
"""


def _argv(template: list[str], map_path: Path, folder: Path) -> list[str]:
    return [a.format(map=map_path, dir=folder) for a in template]


@pytest.mark.parametrize("name", list(OUTPUTS))
def test_a_full_disk_keeps_the_earlier_output_and_leaves_no_temporary_file(
    name: str, map2d: Path, tmp_path: Path
) -> None:
    template, files = OUTPUTS[name]
    np.save(tmp_path / "pts.npy", np.zeros((1000, 2)))
    for f in files:
        (tmp_path / f).write_bytes(PRECIOUS)
    before = sorted(p.name for p in tmp_path.iterdir())
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    proc = subprocess.run(
        [sys.executable, "-c", FULL_DISK, *_argv(template, map2d, tmp_path), "--overwrite"],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert files[0] in lines[0]  # names the file it could not write
    for f in files:
        assert (tmp_path / f).read_bytes() == PRECIOUS, f
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no temporary file left


@pytest.mark.parametrize("name", ["export .ply", "export .pgm", "query"])
def test_a_killed_export_leaves_no_half_file(name: str, map2d: Path, tmp_path: Path) -> None:
    template, files = OUTPUTS[name]
    np.save(tmp_path / "pts.npy", np.zeros((1000, 2)))
    suffix = Path(files[0]).suffix
    proc = subprocess.run(
        [sys.executable, "-c", KILLED, suffix, *_argv(template, map2d, tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 137, proc.stderr[-2000:]  # killed mid-write
    for f in files:
        assert not (tmp_path / f).exists(), f
    # with the earlier file there, the kill keeps it whole
    for f in files:
        (tmp_path / f).write_bytes(PRECIOUS)
    proc = subprocess.run(
        [sys.executable, "-c", KILLED, suffix, *_argv(template, map2d, tmp_path), "--overwrite"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 137, proc.stderr[-2000:]
    for f in files:
        assert (tmp_path / f).read_bytes() == PRECIOUS, f


def test_exports_write_whole_files_with_the_default_permissions(
    map2d: Path, tmp_path: Path
) -> None:
    out = tmp_path / "o.pgm"
    assert main(["export", str(map2d), "--out", str(out)]) == 0
    mask = os.umask(0)
    os.umask(mask)
    for f in (out, out.with_suffix(".yaml")):
        assert f.stat().st_mode & 0o777 == 0o666 & ~mask
    assert f"image: {out.name}\n" in out.with_suffix(".yaml").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.pgm", "o.yaml"]


def test_run_and_build_refuse_an_existing_config_or_recording(
    tmp_path: Path, config_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "a.npz"
    save_scan_log(log, SCANS[:3])
    out = tmp_path / "m.octolgp"
    toml = tmp_path / "m.octolgp.toml"  # left from an earlier map, the map deleted
    toml.write_bytes(PRECIOUS)
    common = ["--out", str(out), "--config", str(config_file), "--quiet"]
    for cmd in (["run", str(log), *common], ["build", str(log), *common]):
        capsys.readouterr()
        assert main(cmd) == 2
        line = one_error_line(capsys)
        assert "m.octolgp.toml" in line
        assert "already exists" in line
        assert toml.read_bytes() == PRECIOUS
        assert not out.exists()
    toml.unlink()
    rrd = tmp_path / "rec.rrd"
    rrd.write_bytes(PRECIOUS)
    assert main(["run", str(log), *common, "--rerun-save", str(rrd)]) == 2
    line = one_error_line(capsys)
    assert "--rerun-save" in line
    assert "rec.rrd" in line
    assert rrd.read_bytes() == PRECIOUS
    assert not out.exists()
    assert not toml.exists()
    assert main(["run", str(log), *common, "--rerun-save", str(rrd), "--overwrite"]) == 0
    assert rrd.read_bytes() != PRECIOUS
    assert MapConfig.from_toml(toml).hyperparameters == HP


# --------------------------------------------------------------------------- resume


def test_resume_checks_the_log_against_the_journal(
    tmp_path: Path, config_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "a.npz"
    save_scan_log(log, SCANS)
    out = tmp_path / "m.octolgp"
    common = ["--out", str(out), "--config", str(config_file), "--quiet"]
    assert main(["run", str(log), *common, "--limit", "4"]) == 0
    # --limit counts the log's scans: 2 is fewer than the map holds, so nothing to add
    assert main(["run", str(log), *common, "--resume", "--limit", "2"]) == 0
    with OnlineMap.open(out, read_only=True) as m:
        assert m.n_scans == 4
    short = tmp_path / "short.npz"
    save_scan_log(short, SCANS[:3])
    other = tmp_path / "other.npz"  # the same first two scans, then another
    save_scan_log(other, [*SCANS[:2], SCANS[3], SCANS[2], *SCANS[4:]])
    capsys.readouterr()
    assert main(["run", str(short), *common, "--resume"]) == 2
    line = one_error_line(capsys)
    assert "short.npz' holds 3 scans" in line
    assert "m.octolgp' 4" in line
    assert main(["run", str(other), *common, "--resume"]) == 2
    line = one_error_line(capsys)
    assert "scan 3 of SCANS is not scan 3" in line
    assert "other.npz" in line
    assert "m.octolgp" in line
    with OnlineMap.open(out, read_only=True) as m:
        assert m.n_scans == 4
    saved, emptied = tmp_path / "saved.octolgp", tmp_path / "emptied.octolgp"
    memory = OnlineMap(CONFIG)  # a map in memory keeps its journal in RAM, and its save too
    memory.insert_scans(SCANS[:4])
    memory.save(saved)
    memory.save(emptied)
    con = sqlite3.connect(emptied)  # as earlier versions saved a map in memory
    con.execute("DELETE FROM scans")
    con.commit()
    con.close()
    assert main(["run", str(log), *common, "--out", str(emptied), "--resume"]) == 2
    assert "keeps no journal" in one_error_line(capsys)
    for path in (out, saved):
        assert main(["run", str(log), *common, "--out", str(path), "--resume"]) == 0
        with OnlineMap.open(path, read_only=True) as m:
            assert m.n_scans == len(SCANS)


# --------------------------------------------------------------------------- refused scans


@pytest.mark.parametrize("command", ["run", "build"])
def test_a_refused_scan_names_its_number_and_its_log(
    command: str, tmp_path: Path, config_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    far = Scan(origin=[0.0, 0.0], points=[[5000.0, 0.0], [1.0, 1.0]])
    log = tmp_path / "bad.npz"
    save_scan_log(log, [SCANS[0], SCANS[1], far, SCANS[2]])
    out = tmp_path / "m.octolgp"
    capsys.readouterr()
    argv = [command, str(log), "--out", str(out), "--config", str(config_file), "--quiet"]
    assert main(argv) == 2
    line = one_error_line(capsys)
    assert f"SCANS {str(log)!r}, scan 3: " in line
    assert "outside the addressable range" in line


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


# --------------------------------------------------------------------------- I/O faults


@pytest.mark.parametrize(
    "fault",
    [
        sqlite3.OperationalError("database or disk is full"),
        OSError(28, "No space left on device"),
    ],
)
def test_an_io_fault_is_one_line_naming_the_map(
    fault: Exception,
    map2d: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    def failing_open(*args: Any, **kwargs: Any) -> OnlineMap:
        raise fault

    monkeypatch.setattr(OnlineMap, "open", failing_open)
    np.save(tmp_path / "pts.npy", np.zeros((3, 2)))
    argv = ["query", str(map2d), "--points", str(tmp_path / "pts.npy")]
    capsys.readouterr()
    assert main([*argv, "--out", str(tmp_path / "p.npy")]) == 2
    line = one_error_line(capsys)
    assert str(map2d) in line
    assert str(fault.args[-1]) in line


def test_an_unexpected_error_still_shows_its_traceback(
    map2d: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def failing_open(*args: Any, **kwargs: Any) -> OnlineMap:
        raise RuntimeError("a bug")

    monkeypatch.setattr(OnlineMap, "open", failing_open)
    np.save(tmp_path / "pts.npy", np.zeros((3, 2)))
    argv = ["query", str(map2d), "--points", str(tmp_path / "pts.npy")]
    with pytest.raises(RuntimeError, match="a bug"):
        main([*argv, "--out", str(tmp_path / "p.npy")])
