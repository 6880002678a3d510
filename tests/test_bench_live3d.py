"""The live-mapping benchmark tools: the DUFOMap peer, the street's held-out labels, the 3D and 2D smoke runs."""

from __future__ import annotations

import importlib.util
import re
import sys
import time
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from octolgp.bench.dufomap_ref import DufomapReference, dufomap_available
from octolgp.bench.octomap_ref import octomap_available
from octolgp.errors import OctolgpError
from octolgp.scan import Scan
from octolgp.sim.lidar3d import simulate_lidar_room
from octolgp.sim.mission import simulate_mission3d

ROOT = Path(__file__).resolve().parents[1]
needs_dufomap = pytest.mark.skipif(not dufomap_available(), reason="dufomap is not installed")


def _tool(name: str) -> ModuleType:
    """``tools/NAME.py`` imported as a module (``tools/`` on the path for its imports)."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
        assert spec is not None
        assert spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses look their module up
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(ROOT / "tools"))
    return module


@pytest.fixture(scope="module")
def bench3d() -> ModuleType:
    return _tool("bench_3d")


@pytest.fixture(scope="module")
def bench2d() -> ModuleType:
    return _tool("bench_2d_online")


@needs_dufomap
def test_dufomap_reference_casts_rays_from_the_scan_origin() -> None:
    room = simulate_lidar_room(1, n_azimuth=1024, n_elevation=32, n_heldout=0)
    scan = room.scan(0).downsample(0.2)
    mid = (scan.origin + 0.5 * (scan.points - scan.origin)).astype(np.float32)
    eye = np.eye(4)
    ref = DufomapReference(0.2)
    seconds = ref.insert_scan(scan)
    assert 0.0 <= seconds < 5.0
    # Half-way along the rays is mostly seen free (d_p = 1 needs free neighbours); the
    # surfaces hit are not.
    assert ref.map.segment(mid, eye, cloud_transform=False).mean() > 0.7
    hits = scan.points.astype(np.float32)
    assert ref.map.segment(hits, eye, cloud_transform=False).mean() < 0.01
    # The same points cast from an origin 50 m below: the real rays are not seen free.
    moved = DufomapReference(0.2)
    moved.insert_scan(Scan(scan.origin - [0.0, 0.0, 50.0], scan.points, scan.max_range))
    assert moved.map.segment(mid, eye, cloud_transform=False).mean() < 0.1


@needs_dufomap
def test_dufomap_reference_refuses_bad_input() -> None:
    with pytest.raises(OctolgpError, match="resolution"):
        DufomapReference(0.0)
    with pytest.raises(OctolgpError, match="d_p"):
        DufomapReference(0.2, d_p=-1)
    scan2d = Scan(np.zeros(2), np.array([[1.0, 0.0]]), 10.0)
    with pytest.raises(OctolgpError, match="2D scan"):
        DufomapReference(0.2).insert_scan(scan2d)


def test_street_heldout_points_agree_with_the_geometry(bench3d: ModuleType) -> None:
    mission = simulate_mission3d(1000.0, n_azimuth=128, n_elevation=8, max_range=40.0)
    poses = bench3d.street_heldout_poses(mission, 100.0, 6.0, 2, seed=0)
    assert poses.shape == (2, 4)
    assert (mission.truth(poses[:, :3]) == 0).all()  # the sensor stands in free space
    assert np.all((poses[:, 0] > 100.0) & (poses[:, 0] < 106.0))
    assert np.all(np.abs(poses[:, 1]) <= 1.0)
    points, labels, dropped = bench3d.street_heldout_points(mission, poses, 0.2, seed=0)
    assert points.shape == (labels.size, 3)
    np.testing.assert_array_equal(mission.truth(points), labels)
    occupied = int(labels.sum())
    assert 0 < occupied < labels.size
    assert (labels[:occupied] == 1).all()  # occupied first
    assert dropped < 0.05 * labels.size
    # Every occupied point lies just beyond a surface: within OCCUPIED_INSIDE of a free point.
    again = bench3d.street_heldout_points(mission, poses, 0.2, seed=0)
    np.testing.assert_array_equal(again[0], points)
    other = bench3d.street_heldout_points(mission, poses, 0.2, seed=1)
    assert not np.array_equal(other[0][occupied:], points[occupied:])


def test_bench3d_scene_options(bench3d: ModuleType) -> None:
    args = bench3d.parse_args([])
    assert args.scene_list == list(bench3d.SCENES)
    assert (args.scans, args.street_scans, args.street_range) == (12, 7, 80.0)
    args = bench3d.parse_args(["--quick"])
    assert "3dtk" not in args.scene_list
    assert args.street_range == 20.0
    args = bench3d.parse_args(["--scenes", "room,kitti", "--threedtk"])
    assert args.scene_list == ["room", "kitti", "3dtk"]
    assert bench3d.parse_args(["--no-sim"]).scene_list == ["kitti", "3dtk"]
    with pytest.raises(SystemExit):
        bench3d.parse_args(["--scenes", "moon"])


def test_bench3d_verdict(bench3d: ModuleType) -> None:
    stats = bench3d.SceneStats(
        n_known=3,
        timing_given=False,
        lg=[0.1, 0.2, 0.3],
        om=[0.2, 0.2, 0.2],
        du=[0.01] * 3,
        auc={"octolgp": 0.990, "OctoMap": 0.980, "exact": 0.993},
        auc_known={},
        unknown={},
        exact_s=[],
        peak_rss=100.0,
    )
    line = bench3d.verdict("room", stats)
    assert "median insert 1.00x OctoMap (≤ 1x): **yes**" in line
    assert "AUC − exact -0.0030 (≥ -0.002): **no**" in line
    assert "AUC − OctoMap +0.0100 (≥ +0.003): **yes**" in line
    assert bench3d.goals_met(stats) == "2/3"
    stats.auc["exact"] = float("nan")
    assert bench3d.goals_met(stats) == "2/2"


def test_bench3d_quick_run_of_every_scene(
    bench3d: ModuleType, capsys: pytest.CaptureFixture[str]
) -> None:
    t0 = time.perf_counter()
    assert bench3d.main(["--quick", "--hp", "0.8", "--no-exact"]) == 0
    out = capsys.readouterr().out
    assert time.perf_counter() - t0 < 90
    assert "Machine:" in out
    assert "Command:" in out
    for key in ("room", "street32", "street64", "sparse", "kitti"):
        row = re.search(rf"^\| {key} \| (\d+)", out, flags=re.M)
        assert row is not None, key
        assert int(row.group(1)) >= 1
        assert re.search(rf"^Verdict {key}: median insert", out, flags=re.M)
    assert "ranges to 20 m" in out
    aucs = re.findall(r"^\| held-out AUC \(unknown = 0.5\)[^|]* \| ([0-9.]+) \|", out, flags=re.M)
    assert len(aucs) == 5
    assert all(float(a) > 0.8 for a in aucs)
    if octomap_available():
        assert re.search(r"^\| room \| 2 \| [0-9.]+ \| [0-9.]+ \|", out, flags=re.M)
    if dufomap_available():
        assert re.search(r"^\| room \| 2 \| [0-9.]+ \| [0-9.]+ \| [0-9.]+ \|", out, flags=re.M)


def test_bench2d_quick_run_against_octomap(
    bench2d: ModuleType, capsys: pytest.CaptureFixture[str]
) -> None:
    t0 = time.perf_counter()
    assert bench2d.main(["--scans", "8", "--learn-scans", "3"]) == 0
    out = capsys.readouterr().out
    assert time.perf_counter() - t0 < 60
    assert "Machine:" in out
    assert "Command:" in out
    # Scans 1-2 buffer, the 3rd learns, 5 inserts after it.
    row = re.search(r"^\| default \| [0-9.]+ \| [0-9.]+ \| 5 \| ([0-9.]+) \|", out, flags=re.M)
    assert row is not None
    step = re.search(r"\| ([0-9.]+) \(scan 3\) \| ([0-9.]+) \|", out)
    assert step is not None
    assert 0 < float(step.group(2)) <= float(step.group(1))
    assert re.search(r"^Verdict intel: ", out, flags=re.M)
    if octomap_available():
        assert re.search(r"^\| default \| [0-9.]+ \| [0-9.]+ \| [0-9.]+× \|", out, flags=re.M)
        assert "(goal ≤ 0.5x)" in out


def test_bench2d_keeps_config_of(bench2d: ModuleType) -> None:
    config = bench2d.config_of("online.engine=exact; online.n_jobs=1")
    assert config.online.engine == "exact"
    assert config.online.n_jobs == 1
    assert config.resolution == 0.1
    run = bench2d.Run2D(
        octolgp_s=[0.001, 2.0, 0.01, 0.03],
        octomap_s=[0.02, 0.02, 0.02, 0.04],
        kind=["buffered", "learning", "known", "known"],
        learn_s=1.5,
    )
    assert run.after() == ([0.01, 0.03], [0.02, 0.04])
    assert "| 2.00 (scan 2) | 1.50 |" in bench2d.timing_row("default", run)
    assert "0.67×" in bench2d.octomap_row("default", run)
    assert "**no**" in bench2d.verdict("intel", run)
