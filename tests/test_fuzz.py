"""Fuzzing: bad input is refused with OctolgpError, never another exception.

(a) ``insert_scan`` with random valid and invalid scans; (b) every loader on mutated
bytes of the real fixtures; (c) ``OnlineMap.open`` on a mutated map file.

Under the default ``ci`` Hypothesis profile each test runs ``FUZZ_EXAMPLES`` examples
(the file takes well under a minute); ``make fuzz`` (``HYPOTHESIS_PROFILE=fuzz``) runs
thousands.
"""

from __future__ import annotations

import itertools
import os
import shutil
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from octolgp import Hyperparameters, MapConfig, OctolgpError, OnlineMap, Scan, load_scans
from octolgp.io import log_scan, save_scan_log

DATA = Path(__file__).parent / "data"
INTEL20 = DATA / "intel_first20.log"
HP = Hyperparameters(length_scale=0.5, signal_variance=1.0, noise_variance=0.1, alpha=2.0)
FUZZ = os.environ.get("HYPOTHESIS_PROFILE") == "fuzz"
FUZZ_EXAMPLES = settings.default.max_examples if FUZZ else 20
HANG_SECONDS = 30
FUZZ_SETTINGS = settings(
    max_examples=FUZZ_EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


class HangError(Exception):
    """A call ran past HANG_SECONDS."""


@contextmanager
def no_hang(seconds: int = HANG_SECONDS) -> Iterator[None]:
    def fire(signum: int, frame: Any) -> None:
        raise HangError(f"ran past {seconds} s")

    old = signal.signal(signal.SIGALRM, fire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


# --------------------------------------------------------------------------- (a) insert_scan

SPECIAL = st.sampled_from([np.nan, np.inf, -np.inf, 1e300, -1e6, 1e6, 7000.0, 0.0, 1e-300])
COORD = st.one_of(st.floats(-20, 20, allow_nan=False), SPECIAL)


@st.composite
def scans(draw: st.DrawFn) -> tuple[Any, Any, Any]:
    """An (origin, points, max_range) triple: usually valid 2D, sometimes anything."""
    d = draw(st.sampled_from([2, 2, 2, 2, 3, 1]))
    valid = draw(st.booleans())
    coord = st.floats(-20, 20, allow_nan=False) if valid else COORD
    origin = [draw(coord) for _ in range(d)]
    n = draw(st.integers(0, 30))
    points = np.array([[draw(coord) for _ in range(d)] for _ in range(n)]).reshape(n, d)
    if n and draw(st.booleans()):  # duplicates and points on the sensor
        k = draw(st.integers(1, n))
        points[:k] = points[0] if draw(st.booleans()) else origin
    if draw(st.integers(0, 9)) == 0:  # a wrong shape
        points = points.reshape(-1)
    max_range = draw(st.one_of(st.none(), st.floats(0.01, 100), SPECIAL))
    return origin, points, max_range


@pytest.fixture(scope="module")
def fuzz_map() -> Iterator[OnlineMap]:
    with OnlineMap(MapConfig(dim=2, resolution=0.2, hyperparameters=HP)) as m:
        yield m


@FUZZ_SETTINGS
@given(case=scans())
def test_insert_scan_succeeds_or_refuses_cleanly(fuzz_map: OnlineMap, case: Any) -> None:
    origin, points, max_range = case
    try:
        scan = Scan(origin, points, max_range=max_range)
    except OctolgpError:
        scan = points  # a bad array: insert_scan must refuse it too
    before = fuzz_map.voxels(), fuzz_map.n_scans
    try:
        with no_hang():
            fuzz_map.insert_scan(scan)
    except OctolgpError:
        (c0, p0), n0 = before
        c1, p1 = fuzz_map.voxels()
        assert fuzz_map.n_scans == n0
        assert np.array_equal(c0, c1)
        assert np.array_equal(p0, p1)
        return
    _, prob = fuzz_map.voxels()
    assert np.isfinite(prob).all()
    assert ((prob >= 0) & (prob <= 1)).all()


# --------------------------------------------------------------------------- (b) loaders


def _carmen(d: Path) -> Path:
    lines = INTEL20.read_text().splitlines(keepends=True)
    (d / "s.log").write_text("".join(lines[:14]))
    return d / "s.log"


def _npz(d: Path) -> Path:
    save_scan_log(d / "s.npz", list(itertools.islice(load_scans(INTEL20), 2)))
    return d / "s.npz"


def _rrd(d: Path) -> Path:
    import rerun as rr

    rec = rr.RecordingStream("octolgp_fuzz")
    rec.save(str(d / "s.rrd"))
    for i, scan in enumerate(itertools.islice(load_scans(INTEL20), 2)):
        log_scan(rec, scan, i)
    rec.flush()
    rec.disconnect()
    return d / "s.rrd"


def _scandat(d: Path) -> Path:
    lines = (DATA / "pointcloud/scan_small.dat").read_text().splitlines(keepends=True)
    (d / "s.dat").write_text("".join(lines[:200]))
    return d / "s.dat"


def _copy(src: str, name: str) -> Callable[[Path], Path]:
    def make(d: Path) -> Path:
        s = DATA / src
        if s.is_dir():
            return Path(shutil.copytree(s, d / name))
        return Path(shutil.copy(s, d / name))

    return make


# name -> (fixture maker, file to mutate inside a directory or None, format)
LOADERS: dict[str, tuple[Callable[[Path], Path], str | None, str]] = {
    "carmen": (_carmen, None, "carmen"),
    "npz": (_npz, None, "npz"),
    "rrd": (_rrd, None, "rrd"),
    "pcd-ascii": (_copy("pointcloud/cloud_ascii.pcd", "s.pcd"), None, "pcd"),
    "pcd-binary": (_copy("pointcloud/cloud_binary.pcd", "s.pcd"), None, "pcd"),
    "pcd-compressed": (_copy("pointcloud/cloud_compressed.pcd", "s.pcd"), None, "pcd"),
    "ply-ascii": (_copy("pointcloud/cloud_ascii.ply", "s.ply"), None, "ply"),
    "ply-binary": (_copy("pointcloud/cloud_binary.ply", "s.ply"), None, "ply"),
    "scandat": (_scandat, None, "scandat"),
    "scandat-nodes": (_copy("pointcloud/scan_nodes.dat", "s.dat"), None, "scandat"),
    "graph": (_copy("pointcloud/two_scans.graph", "s.graph"), None, "graph"),
    "rosbag1": (_copy("rosbag/intel.bag", "s.bag"), None, "rosbag"),
    "rosbag2-sqlite": (_copy("rosbag/intel_ros2", "b"), "intel_ros2.db3", "rosbag"),
    "rosbag2-yaml": (_copy("rosbag/intel_ros2", "b"), "metadata.yaml", "rosbag"),
    "rosbag2-mcap": (_copy("rosbag/cloud_ros2", "b"), "cloud_ros2.mcap", "rosbag"),
    "3dtk-xz": (_copy("3dtk", "t"), "scan002.3d.xz", "3dtk"),
    "3dtk-pose": (_copy("3dtk", "t"), "scan002.pose", "3dtk"),
    "3dtk-frames": (_copy("3dtk", "t"), "scan002.frames", "3dtk"),
}


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Each loader's fixture, made once."""
    out = {}
    for name, (make, _, _) in LOADERS.items():
        out[name] = make(tmp_path_factory.mktemp(name))
    return out


OPS = st.sampled_from(["flip", "insert", "delete", "truncate", "overwrite"])


def mutations() -> st.SearchStrategy[list[tuple[str, int, bytes]]]:
    """A few byte edits; positions favour the header (the first 512 bytes)."""
    pos = st.one_of(st.integers(0, 512), st.integers(0, 1 << 20))
    edit = st.tuples(OPS, pos, st.binary(min_size=1, max_size=16))
    return st.lists(edit, min_size=1, max_size=4)


def mutate(data: bytes, edits: list[tuple[str, int, bytes]]) -> bytes:
    buf = bytearray(data)
    for op, pos, blob in edits:
        i = pos % (len(buf) + 1)
        if op == "flip" and buf:
            i = min(i, len(buf) - 1)
            buf[i] ^= blob[0] or 0xFF
        elif op == "insert":
            buf[i:i] = blob
        elif op == "delete":
            del buf[i : i + len(blob) * 8]
        elif op == "truncate":
            del buf[i:]
        elif op == "overwrite":
            buf[i : i + len(blob)] = blob
    return bytes(buf)


def _check_scans(got: list[Scan]) -> None:
    for scan in got:
        assert isinstance(scan, Scan)
        assert np.isfinite(scan.points).all()
        assert np.isfinite(scan.origin).all()
        assert scan.points.ndim == 2
        assert scan.points.shape[1] == scan.dim
        assert len(scan) >= 1


@pytest.mark.parametrize("name", sorted(LOADERS))
def test_loader_on_mutated_bytes(
    name: str, pristine: dict[str, Path], tmp_path_factory: pytest.TempPathFactory
) -> None:
    _, inner, fmt = LOADERS[name]
    src = pristine[name]
    original = (src / inner if inner else src).read_bytes()
    work = tmp_path_factory.mktemp(f"fuzz-{name}")

    @FUZZ_SETTINGS
    @given(edits=mutations(), named=st.booleans())
    def check(edits: list[tuple[str, int, bytes]], named: bool) -> None:
        dst = work / src.name
        if dst.is_dir():
            shutil.rmtree(dst)
        if src.is_dir():
            shutil.copytree(src, dst)
        target = dst / inner if inner else dst
        target.write_bytes(mutate(original, edits))
        try:
            with no_hang():
                got = list(load_scans(dst, format=fmt if named else None))
        except OctolgpError:
            return
        _check_scans(got)

    check()


# --------------------------------------------------------------------------- (c) OnlineMap.open


@pytest.fixture(scope="module")
def map_bytes(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A small map file (3 Intel scans at 0.5 m), checkpointed into one file."""
    path = tmp_path_factory.mktemp("map") / "m.octolgp"
    with OnlineMap(MapConfig(dim=2, resolution=0.5, hyperparameters=HP), path=path) as m:
        for scan in itertools.islice(load_scans(INTEL20), 3):
            m.insert_scan(scan)
    return path.read_bytes()


def test_open_on_mutated_map_file(
    map_bytes: bytes, tmp_path_factory: pytest.TempPathFactory
) -> None:
    work = tmp_path_factory.mktemp("fuzz-map")

    @FUZZ_SETTINGS
    @given(edits=mutations())
    def check(edits: list[tuple[str, int, bytes]]) -> None:
        path = work / "m.octolgp"
        for suffix in ("", "-wal", "-shm"):
            Path(str(path) + suffix).unlink(missing_ok=True)
        path.write_bytes(mutate(map_bytes, edits))
        try:
            with no_hang(), OnlineMap.open(path) as m:
                m.voxels()
                m.occupancy(np.zeros((3, 2)))
        except OctolgpError:
            return

    check()
