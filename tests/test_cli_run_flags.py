"""``octolgp run``'s flags for the sensor and the log: --downsample, --max-range, --log-level, progress."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from octolgp import OnlineMap, load_scans
from octolgp.cli import online
from octolgp.cli.main import main
from octolgp.cli.scans import scan_total

INTEL20 = Path(__file__).resolve().parent / "data" / "intel_first20.log"
ROOT = Path(__file__).resolve().parents[1]


def test_max_range_and_downsample_shape_the_inserted_scans(tmp_path: Path) -> None:
    out = tmp_path / "m.octolgp"
    argv = ["run", str(INTEL20), "--out", str(out), "--learn-scans", "5", "--quiet"]
    assert main([*argv, "--max-range", "5", "--downsample", "0.5"]) == 0
    logged = list(load_scans(INTEL20))
    with OnlineMap.open(out, read_only=True) as m:
        journaled = list(m.scans())
    assert len(journaled) == len(logged)
    for got, raw in zip(journaled, logged, strict=True):
        assert got.max_range == 5.0  # below the log's 81.8 m
        want = online.prepared(raw, 5.0, 0.5).rounded(m.config.online.scan_precision)
        np.testing.assert_array_equal(got.points, want.points)
        assert len(got) < len(raw)


def test_prepared_keeps_a_lower_log_range_and_its_points() -> None:
    scan = next(iter(load_scans(INTEL20)))
    assert online.prepared(scan, 200.0, None).max_range == scan.max_range
    assert online.prepared(scan, None, None) is scan
    cut = online.prepared(scan, 3.0, None)
    np.testing.assert_array_equal(cut.points, scan.points)
    assert cut.max_range == 3.0


@pytest.mark.parametrize(
    ("flag", "value"), [("--downsample", "0"), ("--max-range", "-1"), ("--log-level", "LOUD")]
)
def test_bad_run_flags_exit_2(
    flag: str, value: str, tmp_path: Path, cli_exit_2: Callable[..., str]
) -> None:
    argv = ["run", str(INTEL20), "--out", str(tmp_path / "m.octolgp"), flag, value]
    if flag == "--log-level":
        argv = [flag, value, *argv]
    cli_exit_2(argv, tmp_path, flag, prefix="octolgp")


def test_log_level_shows_the_learning_step(tmp_path: Path) -> None:
    out = tmp_path / "m.octolgp"
    argv = ["--log-level", "INFO", "run", str(INTEL20), "--out", str(out), "--learn-scans", "5"]
    proc = subprocess.run(
        [sys.executable, "-m", "octolgp.cli", *argv, "--quiet"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
    )
    assert "octolgp: INFO: learnt hyperparameters on 5 scans" in proc.stderr
    quiet = subprocess.run(
        [sys.executable, "-m", "octolgp.cli", *argv[2:], "--quiet", "--overwrite"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
    )
    assert "INFO" not in quiet.stderr


def test_progress_lines_off_a_terminal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    assert scan_total(str(INTEL20), None, None) == 20
    assert scan_total(str(INTEL20), None, 7) == 7
    monkeypatch.setattr(online, "PROGRESS_SECONDS", 0.0)  # a line after every scan
    out = tmp_path / "m.octolgp"
    assert main(["run", str(INTEL20), "--out", str(out), "--learn-scans", "5"]) == 0
    lines = [x for x in capsys.readouterr().err.splitlines() if x.startswith("octolgp: scan")]
    assert len(lines) == 20
    assert lines[0].startswith("octolgp: scan 1/20 (5%), ")
    assert lines[-1].startswith("octolgp: scan 20/20 (100%), ")
    assert "ETA 0:00" in lines[-1]
    assert online.progress_line(3, None, 1.5, 7) == "octolgp: scan 3, 2.0 scans/s, 7 leaves"


KITTI = Path(__file__).resolve().parent / "data" / "kitti" / "sequences" / "00"


@pytest.mark.parametrize("frame", ["velodyne", "cam0"])
def test_run_reads_kitti_in_the_frame_asked(tmp_path: Path, frame: str) -> None:
    from octolgp.io import read_kitti

    out = tmp_path / "m.octolgp"
    argv = ["run", str(KITTI), "--out", str(out), "--learn-scans", "2", "--quiet"]
    if frame == "cam0":
        argv += ["--kitti-frame", "cam0"]
    assert main(argv) == 0
    with OnlineMap.open(out, read_only=True) as m:
        journaled = list(m.scans())
        precision = m.config.online.scan_precision
    want = [s.rounded(precision) for s in read_kitti(KITTI, world=frame)]
    for got, scan in zip(journaled, want, strict=True):
        np.testing.assert_array_equal(got.points, scan.points)
    # z up in the Velodyne's frame: the sensor stays at one height while it drives
    heights = np.array([s.origin[2] for s in journaled])
    assert (np.ptp(heights) < 0.5) == (frame == "velodyne")


BAG = Path(__file__).resolve().parent / "data" / "rosbag" / "intel.bag"


def test_run_reads_a_bag_with_the_topics_and_frame_asked(tmp_path: Path) -> None:
    from octolgp.io import read_rosbag

    out = tmp_path / "m.octolgp"
    argv = ["run", str(BAG), "--out", str(out), "--learn-scans", "5", "--quiet"]
    assert main([*argv, "--scan-topic", "/scan", "--frame", "odom"]) == 0
    with OnlineMap.open(out, read_only=True) as m:
        journaled = list(m.scans())
        precision = m.config.online.scan_precision
    want = [s.rounded(precision) for s in read_rosbag(BAG, scan_topic="/scan", frame="odom")]
    assert len(journaled) == len(want) == 20
    for got, scan in zip(journaled, want, strict=True):
        np.testing.assert_array_equal(got.points, scan.points)
    in_map = next(iter(read_rosbag(BAG)))  # the default frame, map: the scans move
    assert not np.allclose(in_map.origin, journaled[0].origin)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--scan-topic", "/scan"], "--scan-topic: for ROS bags only"),
        (["--frame", "odom", "--pose-topic", "/pose"], "--pose-topic, --frame: for ROS bags"),
    ],
)
def test_bag_flags_on_another_log_exit_2(
    argv: list[str], message: str, tmp_path: Path, cli_exit_2: Callable[..., str]
) -> None:
    run = ["run", str(INTEL20), "--out", str(tmp_path / "m.octolgp"), *argv]
    cli_exit_2(run, tmp_path, message)
