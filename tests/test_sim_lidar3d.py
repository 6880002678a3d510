"""The 3D lidar room of issue #14's benchmark: exact ranges, ground truth, determinism, the tool."""

from __future__ import annotations

import dataclasses
import importlib.util
import re
import sys
import time
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from octolgp import MapConfig
from octolgp.bench.octomap_ref import octomap_available
from octolgp.errors import OctolgpError
from octolgp.scan import Scan
from octolgp.sim.lidar3d import ROOM_SIZE, SENSOR_HEIGHT, LidarRoom, simulate_lidar_room

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def room() -> LidarRoom:
    """A small sensor (8 x 64 beams) at 3 poses, 2 held out."""
    return simulate_lidar_room(3, n_azimuth=64, n_elevation=8, n_heldout=2)


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    """``tools/bench_3d.py`` imported as a module."""
    spec = importlib.util.spec_from_file_location("bench_3d", ROOT / "tools" / "bench_3d.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_3d"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _brute_force_range(origin: np.ndarray, u: np.ndarray, boxes: np.ndarray) -> float:
    """First box face along one ray: every face plane of every box, one at a time."""
    best = np.inf
    for box in boxes:
        lo, hi = box[:3], box[3:]
        for axis in range(3):
            if u[axis] == 0.0:
                continue
            for face in (lo[axis], hi[axis]):
                t = (face - origin[axis]) / u[axis]
                if t <= 0.0:
                    continue
                p = origin + t * u
                others = [a for a in range(3) if a != axis]
                eps = 1e-9
                if all(lo[a] - eps <= p[a] <= hi[a] + eps for a in others):
                    best = min(best, t)
    return best


def test_ranges_match_brute_force(room: LidarRoom) -> None:
    rng = np.random.default_rng(5)
    for pose in (room.poses[0], room.poses[2], room.heldout_poses[1]):
        t, dirs = room.ranges(pose)
        beams = rng.choice(t.size, 25, replace=False)
        for b in beams:
            expected = _brute_force_range(pose[:3], dirs[b], room.boxes)
            assert t[b] == pytest.approx(expected, abs=1e-9)
        np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)


def test_scan_endpoints_lie_on_surfaces(room: LidarRoom) -> None:
    scan = room.scan(1)
    assert isinstance(scan, Scan)
    assert scan.max_range == 30.0
    assert len(scan) == 8 * 64
    np.testing.assert_array_equal(scan.origin, room.poses[1, :3])
    d = scan.points - scan.origin
    r = np.linalg.norm(d, axis=1)
    assert (r < 30.0).all()  # a closed room: every beam returns
    u = d / r[:, None]
    # Just past the hit is inside a box, just before it is free (grazing beams aside).
    assert room.truth(scan.origin + (r + 1e-6)[:, None] * u).mean() > 0.99
    assert (room.truth(scan.origin + (r - 1e-3)[:, None] * u) == 0).all()
    # The beam pattern: rings from -15° to +15°, the sensor 1.2 m above the floor.
    elevation = np.rad2deg(np.arcsin(u[:, 2]))
    assert elevation.min() == pytest.approx(-15.0)
    assert elevation.max() == pytest.approx(15.0)
    assert scan.origin[2] == SENSOR_HEIGHT


def test_truth_of_known_points(room: LidarRoom) -> None:
    points = np.array(
        [
            [10.0, 10.0, 3.0],  # middle of the room, above the table
            [2.0, 2.0, 2.5],  # inside the south-west pillar
            [10.0, 10.0, -0.1],  # in the floor slab
            [10.0, 9.0, 0.5],  # inside the table-high block
            [10.0, 9.0, 1.05],  # just above it
            [10.0, 16.8, 4.5],  # inside the duct
            [10.0, 16.8, 4.0],  # under the duct
            [-0.1, 10.0, 2.0],  # in the west wall
            [19.9, 10.0, 2.0],  # free, next to the east wall (cabinet below 1.5 m)
            [19.9, 10.0, 1.0],  # in the cabinet
            [2.3, 2.0, 2.5],  # on the pillar's face: not strictly inside
        ]
    )
    expected = [0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 0]
    np.testing.assert_array_equal(room.truth(points), expected)
    assert room.truth(points).dtype == np.int8
    with pytest.raises(OctolgpError):
        room.truth(np.zeros((3, 2)))


def test_sensor_poses_are_clear_of_every_box(room: LidarRoom) -> None:
    many = simulate_lidar_room(48, n_azimuth=4, n_elevation=2, n_heldout=12)
    for poses in (many.poses, many.heldout_poses):
        p = poses[:, None, :3]
        gap = np.maximum(np.maximum(many.boxes[None, :, :3] - p, p - many.boxes[None, :, 3:]), 0.0)
        assert np.linalg.norm(gap, axis=2).min() > 0.5
        assert (poses[:, 0] > 0).all()
        assert (poses[:, 0] < ROOM_SIZE[0]).all()


def test_deterministic_with_a_seed() -> None:
    kw = {"n_azimuth": 32, "n_elevation": 4, "range_noise": 0.02}
    a, b = simulate_lidar_room(3, seed=7, **kw), simulate_lidar_room(3, seed=7, **kw)
    c = simulate_lidar_room(3, seed=8, **kw)
    for i in range(3):
        np.testing.assert_array_equal(a.scan(i).points, b.scan(i).points)
        assert not np.array_equal(a.scan(i).points, c.scan(i).points)
    np.testing.assert_array_equal(a.heldout_points()[0], b.heldout_points()[0])
    # Range noise moves returns along their beams only.
    exact = dataclasses.replace(a, range_noise=0.0)
    d_noisy = a.scan(0).points - a.scan(0).origin
    d_exact = exact.scan(0).points - exact.scan(0).origin
    cos = (d_noisy * d_exact).sum(1) / np.linalg.norm(d_noisy, axis=1)
    np.testing.assert_allclose(cos, np.linalg.norm(d_exact, axis=1), rtol=1e-9)
    assert 0.01 < np.std(np.linalg.norm(d_noisy, axis=1) - np.linalg.norm(d_exact, axis=1)) < 0.03


def test_no_returns_end_at_max_range() -> None:
    room = simulate_lidar_room(1, n_azimuth=64, n_elevation=4, max_range=5.0)
    scan = room.scan(0)
    r = np.linalg.norm(scan.points - scan.origin, axis=1)
    t, _ = room.ranges(room.poses[0])
    no_return = t >= 5.0
    assert no_return.any()
    assert (~no_return).any()
    np.testing.assert_allclose(r[no_return], 5.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(r[~no_return], t[~no_return], rtol=0, atol=1e-12)
    _points, labels, _ = room.heldout_points(voxel=None)
    assert (labels == 0).sum() > 0


def test_heldout_points_agree_with_the_geometry(room: LidarRoom) -> None:
    points, labels, dropped = room.heldout_points(voxel=None, free_per_beam=2)
    np.testing.assert_array_equal(room.truth(points), labels)
    n_occ = int(labels.sum())
    assert (labels[:n_occ] == 1).all()
    assert (labels[n_occ:] == 0).all()
    beams = 2 * 8 * 64
    assert n_occ + dropped >= beams * 0.98
    assert dropped < 0.05 * beams
    # The voxel filter thins the test beams.
    assert room.heldout_points(voxel=0.2)[1].size < labels.size


def test_bad_arguments_raise() -> None:
    with pytest.raises(OctolgpError, match="n_poses"):
        simulate_lidar_room(0)
    with pytest.raises(OctolgpError, match="fov_down"):
        simulate_lidar_room(2, fov_down=10.0, fov_up=5.0)
    with pytest.raises(OctolgpError, match="max_range"):
        simulate_lidar_room(2, max_range=0.0)
    with pytest.raises(OctolgpError, match="index"):
        simulate_lidar_room(2, n_azimuth=4, n_elevation=2).scan(2)


def test_tool_settings(bench: ModuleType) -> None:
    config = bench.apply_setting(MapConfig(dim=3, resolution=0.2), "online.n_jobs=2")
    assert config.online.n_jobs == 2
    config = bench.apply_setting(config, "memory_budget_mb=64")
    assert config.memory_budget_mb == 64
    assert bench.non_defaults(config) == ["memory_budget_mb=64", "online.n_jobs=2"]
    with pytest.raises(SystemExit, match="no field"):
        bench.apply_setting(config, "online.no_such_field=1")
    with pytest.raises(SystemExit, match="give --hp"):
        bench.apply_setting(config, "hyperparameters.alpha=2")
    with pytest.raises(SystemExit, match="n_jobs"):
        bench.apply_setting(config, "online.n_jobs=0")
    args = bench.parse_args(["--hp", "0.7", "--learn-scans", "5", "--set", "online.halo=0.1"])
    config = bench.build_config(args)
    assert config.hyperparameters.length_scale == 0.7
    assert config.online.learn_scans == 5
    assert config.online.halo == 0.1
    assert bench.non_defaults(config)[0].startswith("hyperparameters=Hyperparameters(")


def test_tool_reports_learning_and_flush_rows(bench: ModuleType) -> None:
    run = bench.PairRun(
        beams=[10, 11, 12],
        octolgp_s=[0.001, 0.002, 0.003],
        octomap_s=[0.1, 0.1, 0.1],
        refit=[0, 0, 0],
        kind=["buffered"] * 3,
        learn_s=1.5,
        flush_s=4.0,
        flush_refit=30,
        scores={"octolgp": {"auc": 0.9, "auc_known": 0.95, "unknown_fraction": 0.1}},
        memory_mb={"octolgp": 1.0},
        eval_s={"octolgp": 0.1},
    )
    text = "\n".join(bench.summary_table(run))
    assert "flush() after the last scan s (learn 1.50 s, then 3 buffered scans: 30 leaves" in text
    assert "| 4.00 |" in text
    assert "hyperparameters known (0 scans" in text
    assert "| total s, every insert (+ flush, + settle) | 4.01 | 0.30 | 13.4× |" in text


def test_tool_quick_run(bench: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    t0 = time.perf_counter()
    assert (
        bench.main(["--quick", "--hp", "0.8", "--scans", "2", "--per-scan", "--scenes", "room"])
        == 0
    )
    out = capsys.readouterr().out
    assert time.perf_counter() - t0 < 60
    assert "Machine:" in out
    assert "Command:" in out
    assert "the user default" in out
    auc = re.search(r"\| held-out AUC \(unknown = 0.5\) \| ([0-9.]+) \| ([0-9.–]+) \|", out)
    assert auc is not None
    assert float(auc.group(1)) > 0.9
    rows = re.findall(r"^\| [12] \| \d+ \| [0-9.]+ \| known \|", out, flags=re.M)
    assert len(rows) == 2
    if octomap_available():
        assert float(auc.group(2)) > 0.8
        assert re.search(r"hyperparameters known \(2 scans.*\| [0-9.]+× \|", out)
