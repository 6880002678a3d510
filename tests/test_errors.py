"""Every input the library and the CLI refuse, one test per row of README's "Errors" table.

Library rows assert :class:`OctolgpError` (or the documented subclass) and that the
message names the field; ``insert_scan`` rows also assert that the map is unchanged.
CLI rows assert exit status 2, exactly one line on stderr and no traceback.
"""

from __future__ import annotations

import dataclasses
import itertools
import shutil
import sqlite3
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from octolgp import (
    Hyperparameters,
    MapConfig,
    OctolgpError,
    OnlineMap,
    Scan,
    build_map,
    learn_hyperparameters,
    load_scans,
)
from octolgp.cli import main
from octolgp.config import (
    ExactConfig,
    LearningConfig,
    OgmConfig,
    OnlineConfig,
    PartitionConfig,
    TrainingConfig,
)
from octolgp.errors import MapFileNotFound
from octolgp.io import save_scan_log
from octolgp.scan import check_scan_size

DATA = Path(__file__).parent / "data"
INTEL20 = DATA / "intel_first20.log"
HP = Hyperparameters(length_scale=0.5, signal_variance=1.0, noise_variance=0.1, alpha=2.0)
CFG2 = MapConfig(dim=2, resolution=0.2, hyperparameters=HP)
CFG3 = MapConfig(dim=3, resolution=0.2, hyperparameters=HP)
O2 = np.zeros(2)


def _beams(n: int = 8, radius: float = 2.0) -> np.ndarray:
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return radius * np.stack([np.cos(phi), np.sin(phi)], axis=1)


def _snapshot(m: OnlineMap) -> tuple[np.ndarray, np.ndarray, int]:
    centres, prob = m.voxels()
    return centres.copy(), prob.copy(), m.n_scans


def _assert_same(m: OnlineMap, before: tuple[np.ndarray, np.ndarray, int]) -> None:
    centres, prob, n = _snapshot(m)
    assert n == before[2]
    assert np.array_equal(centres, before[0])
    assert np.array_equal(prob, before[1])


def _assert_valid(m: OnlineMap) -> None:
    _, prob = m.voxels()
    assert np.isfinite(prob).all()
    assert ((prob >= 0) & (prob <= 1)).all()


@pytest.fixture
def map2d() -> OnlineMap:
    """A small 2D map holding one scan (fixed hyperparameters: no learning delay)."""
    m = OnlineMap(CFG2)
    m.insert_scan(Scan(O2, _beams()))
    return m


# --------------------------------------------------------------------------- Scan


@pytest.mark.parametrize(
    ("origin", "points", "kwargs", "fragment"),
    [
        (O2, [[np.nan, 1.0]], {}, "Scan.points contains NaN or inf"),
        (O2, [[1.0, np.inf]], {}, "Scan.points contains NaN or inf"),
        (O2, [[1.0, -np.inf]], {}, "Scan.points contains NaN or inf"),
        ([np.nan, 0.0], [[1.0, 1.0]], {}, "Scan.origin contains NaN or inf"),
        ([0.0, np.inf], [[1.0, 1.0]], {}, "Scan.origin contains NaN or inf"),
        (O2, np.array([[1e308 * 10, 0.0]]), {}, "Scan.points contains NaN or inf"),
        (O2, np.zeros((0, 2)), {}, "Scan.points is empty"),
        (O2, [], {}, "Scan.points"),
        (O2, [1.0, 2.0], {}, "Scan.points must have shape (n, 2)"),
        (O2, [[1.0, 2.0, 3.0]], {}, "Scan.points must have shape (n, 2)"),
        (np.zeros(3), [[1.0, 2.0]], {}, "Scan.points must have shape (n, 3)"),
        (np.zeros(1), [[1.0]], {}, "Scan.origin must have shape"),
        (np.zeros(4), [[1.0] * 4], {}, "Scan.origin must have shape"),
        (1.0, [[1.0, 2.0]], {}, "Scan.origin must have shape"),
        (O2, "abc", {}, "Scan.points must be numeric"),
        (O2, [[1, None]], {}, "Scan.points must be numeric"),
        (O2, np.array([[1 + 1j, 2]]), {}, "Scan.points must be numeric"),
        (O2, np.array([[True, False]]), {}, "Scan.points must be numeric"),
        (["a", "b"], [[1.0, 2.0]], {}, "Scan.origin must be numeric"),
        (O2, [[1.0, 2.0]], {"max_range": 0.0}, "Scan.max_range"),
        (O2, [[1.0, 2.0]], {"max_range": -1.0}, "Scan.max_range"),
        (O2, [[1.0, 2.0]], {"max_range": float("nan")}, "Scan.max_range"),
        (O2, [[1.0, 2.0]], {"max_range": float("inf")}, "Scan.max_range"),
        (O2, [[1.0, 2.0]], {"max_range": "10"}, "Scan.max_range"),
        (O2, [[1.0, 2.0]], {"stamp": float("nan")}, "Scan.stamp"),
        (O2, [[1.0, 2.0]], {"stamp": "now"}, "Scan.stamp"),
    ],
)
def test_scan_refuses(origin: Any, points: Any, kwargs: dict[str, Any], fragment: str) -> None:
    with pytest.raises(OctolgpError) as exc:
        Scan(origin, points, **kwargs)
    assert fragment in str(exc.value)


@pytest.mark.parametrize(
    ("pose", "ranges", "angles", "fragment"),
    [
        ([0, 0, 0], [-1.0], [0.0], "ranges must be >= 0"),
        ([0, 0, 0], [np.nan], [0.0], "NaN or inf"),
        ([0, 0, 0], [np.inf], [0.0], "NaN or inf"),
        ([0, 0, 0], [1.0], [np.nan], "NaN or inf"),
        ([0, np.nan, 0], [1.0], [0.0], "pose must be 3 finite numbers"),
        ([0, 0, np.inf], [1.0], [0.0], "pose must be 3 finite numbers"),
        ([0, 0], [1.0], [0.0], "pose must be 3 finite numbers"),
        ([0, 0, 0], [1.0, 2.0], [0.0], "must be equal 1D shapes"),
    ],
)
def test_from_ranges_refuses(pose: Any, ranges: Any, angles: Any, fragment: str) -> None:
    with pytest.raises(OctolgpError) as exc:
        Scan.from_ranges(pose, ranges, angles)
    assert "Scan.from_ranges" in str(exc.value)
    assert fragment in str(exc.value)


@pytest.mark.parametrize("voxel", [0, -0.1, float("nan"), float("inf"), "0.1", True])
def test_downsample_refuses(voxel: Any) -> None:
    with pytest.raises(OctolgpError, match=r"Scan\.downsample: voxel"):
        Scan(O2, _beams()).downsample(voxel)


# --------------------------------------------------------------------------- insert_scan


def _huge_range_scan() -> Scan:
    return Scan.from_ranges([0.0, 0.0, 0.0], [1e6], [0.0])


@pytest.mark.parametrize(
    ("make", "fragment"),
    [
        (lambda: Scan(np.zeros(3), [[1.0, 1.0, 1.0]]), "scan is 3D but MapConfig.dim is 2"),
        (lambda: [[1.0, 1.0]], "scan must be a Scan"),
        (lambda: None, "scan must be a Scan"),
        (_huge_range_scan, "scan.points row 0"),
        (lambda: Scan(O2, [[1.0, 1.0], [1e300, 0.0]]), "scan.points row 1"),
        (lambda: Scan(O2, [[-7000.0, 0.0]]), "outside the addressable range"),
        (lambda: Scan([1e6, 0.0], [[1.0, 0.0]]), "scan.origin row 0"),
        (lambda: Scan(np.array([2**62, 0]), [[1, 0]]), "scan.origin row 0"),
    ],
    ids=[
        "3d-into-2d",
        "list",
        "none",
        "huge-range",
        "huge-point",
        "point-out",
        "origin-out",
        "int",
    ],
)
def test_insert_scan_refuses_and_map_unchanged(
    map2d: OnlineMap, make: Callable[[], Any], fragment: str
) -> None:
    before = _snapshot(map2d)
    with pytest.raises(OctolgpError) as exc:
        map2d.insert_scan(make())
    assert fragment in str(exc.value)
    _assert_same(map2d, before)


def test_insert_2d_scan_into_3d_map_refused() -> None:
    m = OnlineMap(CFG3)
    m.insert_scan(Scan(np.zeros(3), [[1.0, 1.0, 1.0]]))
    before = _snapshot(m)
    with pytest.raises(OctolgpError, match=r"scan is 2D but MapConfig\.dim is 3"):
        m.insert_scan(Scan(O2, [[1.0, 1.0]]))
    _assert_same(m, before)


def test_out_of_range_message_names_the_range(map2d: OnlineMap) -> None:
    with pytest.raises(OctolgpError, match=r"addressable range \[-\d+(\.\d+)?, \d+(\.\d+)?\) m"):
        map2d.insert_scan(_huge_range_scan())


@pytest.mark.parametrize(
    "make",
    [
        lambda: Scan(O2, [[1.0, 1.0]]),  # one point
        lambda: Scan(O2, [[1.0, 1.0]] * 50),  # duplicate points
        lambda: Scan(O2, np.zeros((5, 2))),  # degenerate: every point on the sensor
        lambda: Scan(O2, [[0.0, 0.0], [1.0, 1.0]]),  # one zero-length beam
        lambda: Scan.from_ranges([0.0, 0.0, 0.0], [0.0, 0.0], [0.0, 1.0]),  # zero ranges
        lambda: Scan(O2, [[1e-12, 0.0]]),  # a point within a voxel of the sensor
        lambda: Scan(O2, [[1.0, 1.0]], max_range=1e-9),  # every beam a no-return
        lambda: Scan(O2, _beams(), max_range=1e9),
    ],
    ids=["one-point", "duplicates", "degenerate", "zero-beam", "zero-ranges", "tiny", "mr", "MR"],
)
def test_insert_scan_accepts_and_map_stays_valid(
    map2d: OnlineMap, make: Callable[[], Scan]
) -> None:
    n = map2d.n_scans
    map2d.insert_scan(make())
    assert map2d.n_scans == n + 1
    _assert_valid(map2d)
    p = map2d.occupancy([[0.3, 0.3], [5.0, 5.0]])
    assert np.isfinite(p).all()
    assert ((p >= 0) & (p <= 1)).all()


def test_too_many_points_refused_by_check_scan_size() -> None:
    scan = Scan(O2, np.ones((11, 2)))
    check_scan_size(scan, 11)
    with pytest.raises(OctolgpError, match=r"OnlineConfig.max_scan_points \(10\)"):
        check_scan_size(scan, 10)


def test_insert_scan_refuses_more_than_max_scan_points() -> None:
    cfg = dataclasses.replace(CFG2, online=OnlineConfig(max_scan_points=10))
    m = OnlineMap(cfg)
    m.insert_scan(Scan(O2, _beams(10)))
    before = _snapshot(m)
    with pytest.raises(OctolgpError, match=r"OnlineConfig\.max_scan_points"):
        m.insert_scan(Scan(O2, _beams(11)))
    _assert_same(m, before)


def test_learning_on_degenerate_scans_refused_clearly() -> None:
    with pytest.raises(OctolgpError, match="no training data"):
        learn_hyperparameters([Scan(O2, np.zeros((3, 2)))], MapConfig(dim=2, resolution=0.2))


def test_online_learning_on_degenerate_scan_keeps_map() -> None:
    m = OnlineMap(MapConfig(dim=2, resolution=0.2, online=OnlineConfig(learn_scans=1)))
    try:
        m.insert_scan(Scan(O2, np.zeros((3, 2))))
    except OctolgpError:
        assert m.n_scans == 0
        assert not m._buffer
    else:
        _assert_valid(m)


def test_build_gp_on_degenerate_scan() -> None:
    # accepted like "lgp" and "mgp" (a map that knows nothing), or refused clearly
    g = build_map([Scan(O2, np.zeros((3, 2)))], CFG2, method="gp")
    assert np.isfinite(g.occupancy([[0.0, 0.0]])).all()


# --------------------------------------------------------------------------- build_map


@pytest.mark.parametrize(
    ("args", "kwargs", "fragment"),
    [
        (([Scan(O2, _beams())], CFG2), {"method": "foo"}, "method must be one of"),
        (([], CFG2), {}, "scans is empty"),
        (([Scan(np.zeros(3), [[1.0, 1.0, 1.0]])], CFG2), {}, "scans[0] is 3D"),
        (("abc", CFG2), {}, "scans[0] must be a Scan"),
        (([Scan(O2, _beams())], None), {}, "config must be a MapConfig"),
        (([Scan(O2, [[1e6, 1.0]])], CFG2), {"method": "ogm"}, "scans[0]"),
    ],
)
def test_build_map_refuses(args: tuple[Any, ...], kwargs: dict[str, Any], fragment: str) -> None:
    with pytest.raises(OctolgpError) as exc:
        build_map(*args, **kwargs)
    assert fragment in str(exc.value)


@pytest.mark.parametrize("method", ["lgp", "mgp", "ogm"])
def test_build_map_accepts_degenerate_and_one_point(method: str) -> None:
    scans = [Scan(O2, [[1.0, 1.0]]), Scan(O2, np.zeros((3, 2))), Scan(O2, [[1.0, 1.0]] * 5)]
    g = build_map(scans, CFG2, method=method)
    p = g.occupancy([[1.0, 1.0], [0.1, 0.1]])
    assert np.isfinite(p).all()
    assert ((p >= 0) & (p <= 1)).all()


# --------------------------------------------------------------------------- config


BAD_CONFIGS: list[tuple[Callable[[], Any], str]] = [
    *[
        (lambda v=v: MapConfig(resolution=v), "MapConfig.resolution")
        for v in (0, -0.1, float("nan"), float("inf"), "0.1", True, None)
    ],
    *[
        (lambda v=v: MapConfig(memory_budget_mb=v), "MapConfig.memory_budget_mb")
        for v in (0, -1, float("nan"), float("inf"), "64")
    ],
    *[(lambda v=v: MapConfig(dim=v), "MapConfig.dim") for v in (1, 4, 2.0, "2", True)],
    *[(lambda v=v: MapConfig(tree_depth=v), "MapConfig.tree_depth") for v in (0, 17, 2.5)],
    (lambda: MapConfig(online="x"), "MapConfig.online"),  # type: ignore[arg-type]
    (lambda: MapConfig(hyperparameters={"alpha": 1}), "MapConfig.hyperparameters"),  # type: ignore[arg-type]
    *[
        (lambda n=n, v=v: Hyperparameters(**{n: v}), f"Hyperparameters.{n}")
        for n in ("length_scale", "signal_variance", "noise_variance")
        for v in (0, -1.0, float("nan"), float("inf"), "1")
    ],
    *[
        (lambda n=n, v=v: Hyperparameters(**{n: v}), f"Hyperparameters.{n}")
        for n in ("alpha", "beta")
        for v in (float("nan"), float("inf"), "1", None, True)
    ],
    *[
        (lambda k=k, v=v: OnlineConfig(**{k: v}), f"OnlineConfig.{k}")
        for k, v in [
            ("halo", -0.1),
            ("halo", 0.5),
            ("halo", float("nan")),
            ("halo", "0.2"),
            ("learn_scans", 0),
            ("prune", "yes"),
            ("n_jobs", 0),
            ("leaf_depth", 0),
            ("leaf_depth", 17),
            ("max_scan_points", 0),
            ("max_scan_points", 1.5e6),
        ]
    ],
    *[
        (lambda k=k, v=v: ExactConfig(**{k: v}), f"ExactConfig.{k}")
        for k, v in [
            ("max_leaf_items", 1),
            ("max_leaf_items", 2.5),
            ("free_voxels", 0),
            ("free_voxels", 65),
        ]
    ],
    (lambda: MapConfig(exact="x"), "MapConfig.exact"),  # type: ignore[arg-type]
    (lambda: MapConfig(lattice="x"), "MapConfig.lattice"),  # type: ignore[arg-type]
    (
        lambda: MapConfig.from_dict({"online": {"prune_free": 0.2}}),
        "online.prune_free: no longer a setting",
    ),
    (lambda: MapConfig(tree_depth=8, online=OnlineConfig(leaf_depth=9)), "OnlineConfig.leaf_depth"),
    (lambda: TrainingConfig(quadrature_spacing=0), "TrainingConfig.quadrature_spacing"),
    (lambda: TrainingConfig(free_margin=-1), "TrainingConfig.free_margin"),
    (lambda: TrainingConfig(max_quadrature_nodes=2), "TrainingConfig.max_quadrature_nodes"),
    (lambda: PartitionConfig(box_size=float("inf")), "PartitionConfig.box_size"),
    (lambda: PartitionConfig(max_cluster_size=1), "PartitionConfig.max_cluster_size"),
    (lambda: LearningConfig(objective="foo"), "LearningConfig.objective"),
    (lambda: LearningConfig(max_clusters=0), "LearningConfig.max_clusters"),
    (lambda: OgmConfig(prob_hit=0.4), "OgmConfig.prob_hit"),
    (lambda: OgmConfig(clamping_thres_min=float("nan")), "OgmConfig.clamping_thres_min"),
]


@pytest.mark.parametrize(("make", "field"), BAD_CONFIGS)
def test_config_refuses(make: Callable[[], Any], field: str) -> None:
    with pytest.raises(OctolgpError) as exc:
        make()
    assert field in str(exc.value)


@pytest.mark.parametrize(
    "data",
    [{"resolution": -1}, {"online": {"halo": 2}}, {"nope": 1}, {"online": {"nope": 1}}],
)
def test_config_from_dict_refuses(data: dict[str, Any]) -> None:
    with pytest.raises(OctolgpError):
        MapConfig.from_dict(data)


# --------------------------------------------------------------------------- loaders


def _small_npz(path: Path) -> Path:
    save_scan_log(path, list(itertools.islice(load_scans(INTEL20), 3)))
    return path


def _small_rrd(path: Path) -> Path:
    import rerun as rr

    from octolgp.io import log_scan

    rec = rr.RecordingStream("octolgp_test")
    rec.save(str(path))
    for i, scan in enumerate(itertools.islice(load_scans(INTEL20), 3)):
        log_scan(rec, scan, i)
    rec.flush()
    rec.disconnect()
    return path


# (format, fixture maker or path); directories are damaged in their largest file
LOADERS: dict[str, Callable[[Path], Path]] = {
    "npz": lambda d: _small_npz(d / "s.npz"),
    "carmen": lambda d: Path(shutil.copy(INTEL20, d / "s.log")),
    "rrd": lambda d: _small_rrd(d / "s.rrd"),
    "3dtk": lambda d: Path(shutil.copytree(DATA / "3dtk", d / "3dtk")),
    "rosbag": lambda d: Path(shutil.copy(DATA / "rosbag/intel.bag", d / "s.bag")),
    "rosbag2": lambda d: Path(shutil.copytree(DATA / "rosbag/intel_ros2", d / "ros2")),
    "pcd": lambda d: Path(shutil.copy(DATA / "pointcloud/cloud_binary.pcd", d / "s.pcd")),
    "ply": lambda d: Path(shutil.copy(DATA / "pointcloud/cloud_binary.ply", d / "s.ply")),
    "scandat": lambda d: Path(shutil.copy(DATA / "pointcloud/scan_small.dat", d / "s.dat")),
    "graph": lambda d: Path(shutil.copy(DATA / "pointcloud/two_scans.graph", d / "s.graph")),
}
FORMAT = {"rosbag2": "rosbag"}


def _target(path: Path) -> Path:
    """The file to damage: the path itself, or a directory's largest scan file."""
    if path.is_file():
        return path
    files = [p for p in path.iterdir() if p.suffix not in (".yaml", ".pose", ".frames", ".md")]
    return max(files, key=lambda p: p.stat().st_size)


DAMAGE: dict[str, Callable[[bytes], bytes]] = {
    "empty": lambda b: b"",
    "garbage": lambda b: np.random.default_rng(1).bytes(2000),
    "truncated": lambda b: b[: max(1, len(b) // 2)],
    "text": lambda b: b"hello world\n1 2 3\n",
}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
@pytest.mark.parametrize("name", sorted(LOADERS))
@pytest.mark.parametrize("named", [True, False], ids=["format", "guessed"])
def test_loader_refuses_damaged_file(tmp_path: Path, name: str, damage: str, named: bool) -> None:
    path = LOADERS[name](tmp_path)
    target = _target(path)
    target.write_bytes(DAMAGE[damage](target.read_bytes()))
    fmt = FORMAT.get(name, name) if named else None
    if name == "rrd" and damage == "truncated":
        # Documented: replays the complete exact scans, or refuses naming the file when none
        # survives; never the float32 display copy, which has no max_range.
        try:
            scans, error = list(load_scans(path, format=fmt)), ""
        except OctolgpError as exc:
            scans, error = [], str(exc)
        if scans:
            assert all(s.max_range is not None for s in scans)
        else:
            assert path.name in error
        return
    with pytest.raises(OctolgpError) as exc:
        list(load_scans(path, format=fmt))
    assert path.name in str(exc.value) or target.name in str(exc.value)


@pytest.mark.parametrize("name", sorted(LOADERS))
def test_loader_refuses_missing_path(tmp_path: Path, name: str) -> None:
    with pytest.raises(MapFileNotFound, match="nope"):
        load_scans(tmp_path / "nope", format=FORMAT.get(name, name))


@pytest.mark.parametrize("name", sorted(set(LOADERS) - {"3dtk", "rosbag2"}))
def test_loader_refuses_wrong_format(tmp_path: Path, name: str) -> None:
    # a real file of another format, read with this format's reader
    other = DATA / (
        "pointcloud/cloud_binary.pcd" if name == "ply" else "pointcloud/cloud_binary.ply"
    )
    with pytest.raises(OctolgpError):
        list(load_scans(other, format=FORMAT.get(name, name)))


@pytest.mark.parametrize("name", sorted(set(LOADERS) - {"3dtk", "rosbag2"}))
def test_loader_refuses_a_directory(tmp_path: Path, name: str) -> None:
    (tmp_path / "d").mkdir()
    with pytest.raises(OctolgpError):
        list(load_scans(tmp_path / "d", format=FORMAT.get(name, name)))


def test_load_scans_unknown_format() -> None:
    with pytest.raises(OctolgpError, match="unknown format 'xyz'"):
        load_scans(INTEL20, format="xyz")


def test_unknown_file_format_named(tmp_path: Path) -> None:
    path = tmp_path / "x.bin"
    path.write_bytes(np.random.default_rng(0).bytes(500))
    with pytest.raises(OctolgpError, match="unknown format"):
        load_scans(path)


def test_rerun_recording_without_scans(tmp_path: Path) -> None:
    import rerun as rr

    path = tmp_path / "empty.rrd"
    rec = rr.RecordingStream("x")
    rec.save(str(path))
    rec.log("log", rr.TextLog("no scans here"))
    rec.flush()
    rec.disconnect()
    with pytest.raises(OctolgpError, match="no Points3D/Points2D entity"):
        list(load_scans(path))


def test_rerun_recording_lacking_named_entity(tmp_path: Path) -> None:
    from octolgp.io import read_rrd

    path = _small_rrd(tmp_path / "s.rrd")
    with pytest.raises(OctolgpError, match="has no entity '/nope'"):
        list(read_rrd(path, points="nope"))


# --------------------------------------------------------------------------- OnlineMap.open


@pytest.fixture(scope="module")
def map_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small 2D map file: 3 scans of the Intel fixture at 0.5 m, fixed hyperparameters."""
    path = tmp_path_factory.mktemp("map") / "m.octolgp"
    cfg = MapConfig(dim=2, resolution=0.5, hyperparameters=HP)
    with OnlineMap(cfg, path=path) as m:
        for scan in itertools.islice(load_scans(INTEL20), 3):
            m.insert_scan(scan)
    return path


def _foreign_sqlite(path: Path) -> None:
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE t (x)")
    con.commit()
    con.close()


def _wrong_version(path: Path, src: Path) -> None:
    shutil.copy(src, path)
    con = sqlite3.connect(path)
    con.execute("UPDATE meta SET value='99' WHERE key='version'")
    con.commit()
    con.close()


@pytest.mark.parametrize(
    ("make", "error", "fragment"),
    [
        (lambda p, src: None, MapFileNotFound, "does not exist"),
        (lambda p, src: p.mkdir(), MapFileNotFound, "does not exist"),
        (lambda p, src: p.write_bytes(b""), OctolgpError, "not an octolgp map"),
        (lambda p, src: p.write_bytes(b"hello"), OctolgpError, "not an octolgp map"),
        (lambda p, src: p.write_bytes(np.random.default_rng(0).bytes(5000)), OctolgpError, "not"),
        (
            lambda p, src: p.write_bytes(b"SQLite format 3\x00" + bytes(5000)),
            OctolgpError,
            "not an octolgp map",
        ),
        (lambda p, src: p.write_bytes(src.read_bytes()[:4096]), OctolgpError, "m.octolgp"),
        (lambda p, src: p.write_bytes(src.read_bytes()[:100]), OctolgpError, "m.octolgp"),
        (lambda p, src: _foreign_sqlite(p), OctolgpError, "not an octolgp map"),
        (lambda p, src: _wrong_version(p, src), OctolgpError, "has version 99"),
        (lambda p, src: shutil.copy(INTEL20, p), OctolgpError, "not SQLite"),
    ],
    ids=[
        "missing",
        "dir",
        "empty",
        "text",
        "garbage",
        "sqlite-garbage",
        "trunc",
        "trunc100",
        "foreign-sqlite",
        "version",
        "carmen",
    ],
)
def test_open_refuses(
    tmp_path: Path, map_file: Path, make: Callable[[Path, Path], Any], error: type, fragment: str
) -> None:
    path = tmp_path / "m.octolgp"
    make(path, map_file)
    before = path.read_bytes() if path.is_file() else None
    with pytest.raises(error) as exc:
        OnlineMap.open(path)
    assert fragment in str(exc.value)
    if before is not None:  # opening never modifies a file it refuses
        assert path.read_bytes() == before


def test_open_reads_the_fixture(map_file: Path) -> None:
    with OnlineMap.open(map_file) as m:
        assert m.n_scans == 3
        _assert_valid(m)


# --------------------------------------------------------------------------- CLI


def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse usage errors
        rc = int(exc.code or 0)
    return rc, capsys.readouterr().err


@pytest.fixture(scope="module")
def cli_dir(tmp_path_factory: pytest.TempPathFactory, map_file: Path) -> Path:
    d = tmp_path_factory.mktemp("cli")
    shutil.copy(map_file, d / "m.octolgp")
    shutil.copy(INTEL20, d / "i20.log")
    (d / "garbage.bin").write_bytes(np.random.default_rng(0).bytes(3000))
    (d / "empty.log").write_bytes(b"")
    np.save(d / "nan.npy", np.array([[np.nan, 0.0]]))
    np.save(d / "p3.npy", np.zeros((2, 3)))
    np.save(d / "p2.npy", np.zeros((2, 2)))
    np.save(d / "huge.npy", np.array([[1e9, 0.0]]))
    np.save(d / "obj.npy", np.array([object()]), allow_pickle=True)
    save_scan_log(d / "huge.npz", [Scan(O2, [[1e7, 0.0]])])
    return d


CLI_BAD: list[list[str]] = [
    [],
    ["nope"],
    ["simulate", "paper2d", "--out", "x.txt"],
    ["simulate", "nope", "--out", "x.npz"],
    ["simulate", "paper2d", "--out", "x.npz", "--seed", "abc"],
    ["simulate", "paper2d", "--out", "x.npz", "--seed", "-1"],
    ["simulate", "paper2d", "--out", "/proc/forbidden/x.npz"],
    ["run", "missing.log", "--out", "a.octolgp"],
    ["run", "garbage.bin", "--out", "a.octolgp"],
    ["run", "empty.log", "--out", "a.octolgp"],
    ["run", "i20.log", "--out", "a.octolgp", "--resolution", "0"],
    ["run", "i20.log", "--out", "a.octolgp", "--resolution", "nan"],
    ["run", "i20.log", "--out", "a.octolgp", "--resolution", "abc"],
    ["run", "i20.log", "--out", "a.octolgp", "--format", "xyz"],
    ["run", "i20.log", "--out", "a.octolgp", "--format", "npz"],
    ["run", "i20.log", "--out", "a.octolgp", "--limit", "0"],
    ["run", "i20.log", "--out", "a.octolgp", "--jobs", "0"],
    ["run", "i20.log", "--out", "a.octolgp", "--memory-budget", "-1"],
    ["run", "i20.log", "--out", "a.octolgp", "--rerun-rays", "-3"],
    ["run", "i20.log", "--out", "a.octolgp", "--rerun-colors", "viridis"],
    ["replay", "x.rrd", "--out", "r.octolgp", "--rerun-colors", "grey"],
    ["run", "i20.log", "--out", "a.octolgp", "--rerun-connect", "notaurl", "--quiet"],
    ["run", "i20.log", "--out", "a.octolgp", "--rerun-save", "/proc/nope/x.rrd", "--quiet"],
    ["run", "i20.log", "--out", "m.octolgp"],
    ["run", "i20.log", "--out", "garbage.bin", "--resume"],
    ["run", "huge.npz", "--out", "h.octolgp", "--quiet"],
    ["build", "missing.log", "--out", "b.octolgp"],
    ["build", "garbage.bin", "--out", "b.octolgp"],
    ["build", "i20.log", "--out", "m.octolgp"],
    ["build", "i20.log", "--out", "b.octolgp", "--downsample", "0"],
    ["build", "huge.npz", "--out", "bh.octolgp", "--quiet"],
    ["replay", "i20.log", "--out", "r.octolgp"],
    ["replay", "missing.rrd", "--out", "r.octolgp"],
    ["replay", "garbage.bin", "--out", "r.octolgp"],
    ["replay", "x.rrd", "--out", "r.octolgp", "--max-range", "-1"],
    ["query", "missing.octolgp", "--points", "p2.npy", "--out", "q.npy"],
    ["query", "garbage.bin", "--points", "p2.npy", "--out", "q.npy"],
    ["query", "i20.log", "--points", "p2.npy", "--out", "q.npy"],
    ["query", "m.octolgp", "--points", "nan.npy", "--out", "q.npy"],
    ["query", "m.octolgp", "--points", "p3.npy", "--out", "q.npy"],
    ["query", "m.octolgp", "--points", "obj.npy", "--out", "q.npy"],
    ["query", "m.octolgp", "--points", "huge.npy", "--out", "q.npy"],
    ["query", "m.octolgp", "--points", "garbage.bin", "--out", "q.npy"],
    ["query", "m.octolgp", "--points", "missing.npy", "--out", "q.npy"],
    ["query", "m.octolgp", "--points", "p2.npy", "--out", "/proc/nope/q.npy"],
    ["query", "m.octolgp"],
    ["export", "m.octolgp", "--out", "x.txt"],
    ["export", "missing.octolgp", "--out", "x.bt"],
    ["export", "garbage.bin", "--out", "x.bt"],
    ["export", "m.octolgp", "--out", "/proc/nope/x.bt"],
    ["export", "m.octolgp", "--out", "x.png", "--threshold", "nan"],
    ["export", "m.octolgp", "--out", "x.ply", "--threshold", "1.5"],
    ["bench", "nope"],
    ["bench", "paper2d", "--repeats", "0"],
    ["bench", "paper2d", "--seeds", "0"],
    ["bench", "paper2d", "--seed", "-1"],
    ["eval", "missing.log"],
    ["eval", "garbage.bin", "--out", "ev"],
    ["eval", "i20.log", "--methods", "foo", "--out", "ev", "--quiet"],
    ["eval", "i20.log", "--methods", ",", "--out", "ev", "--quiet"],
    ["eval", "i20.log", "--fraction", "2", "--out", "ev"],
    ["eval", "i20.log", "--short", "nan", "--out", "ev"],
    ["eval", "i20.log", "--seeds", "0", "--out", "ev"],
]


@pytest.mark.parametrize("argv", CLI_BAD, ids=[" ".join(a) or "(none)" for a in CLI_BAD])
def test_cli_user_error_is_one_line_exit_2(
    argv: list[str], cli_dir: Path, capsys: pytest.CaptureFixture[str], monkeypatch: Any
) -> None:
    monkeypatch.chdir(cli_dir)
    before = (cli_dir / "m.octolgp").read_bytes()
    rc, err = _cli(argv, capsys)
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert ": error: " in lines[0]
    assert "Traceback" not in err
    assert (cli_dir / "m.octolgp").read_bytes() == before  # never clobbered


def test_cli_degenerate_log_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: Any
) -> None:
    monkeypatch.chdir(tmp_path)
    save_scan_log(tmp_path / "deg.npz", [Scan(O2, np.zeros((3, 2)))])
    rc, err = _cli(["run", "deg.npz", "--out", "d.octolgp", "--quiet"], capsys)
    assert rc in (0, 2)
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("argv", "error"),
    [
        (["run", "missing.log", "--out", "a.octolgp"], MapFileNotFound),
        (["query", "m.octolgp", "--points", "nan.npy", "--out", "q.npy"], OctolgpError),
        (["export", "garbage.bin", "--out", "x.bt"], OctolgpError),
        (["eval", "i20.log", "--methods", "foo", "--out", "ev", "--quiet"], OctolgpError),
    ],
)
def test_cli_debug_shows_the_traceback(
    argv: list[str], error: type, cli_dir: Path, monkeypatch: Any
) -> None:
    monkeypatch.chdir(cli_dir)
    with pytest.raises(error):
        main(["--debug", *argv])


def test_npz_holding_one_bare_array_refused(tmp_path: Path) -> None:
    path = tmp_path / "a.npz"
    with path.open("wb") as fh:
        np.save(fh, np.zeros(3))
    with pytest.raises(OctolgpError, match="not a readable npz file"):
        list(load_scans(path))


def test_insert_scan_beam_with_subnormal_component(map2d: OnlineMap) -> None:
    map2d.insert_scan(Scan(O2, [[1.0, 1.11253693e-308]]))
    _assert_valid(map2d)
