"""Point-cloud scan readers: PCD, PLY, OctoMap scan.dat and .graph, on fixtures cut from real scans."""

from __future__ import annotations

import bz2
import gzip
import shutil
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.geometry.rotations import matrix_to_quaternion, rpy_to_matrix
from octolgp.io.octomap_graph import (
    GraphReader,
    ScanDatReader,
    looks_like_graph,
    looks_like_scan_dat,
    write_graph,
)
from octolgp.io.pcd import PcdReader, looks_like_pcd, lzf_decompress, read_pcd_header
from octolgp.io.ply import PlyReader, looks_like_ply
from octolgp.io.threedtk import ThreeDTKReader
from octolgp.scan import Scan

DATA = Path(__file__).resolve().parent / "data" / "pointcloud"
THREEDTK = Path(__file__).resolve().parent / "data" / "3dtk"
NODE1_POSE = (1.0, -0.5, 0.2, 0.05, -0.1, 0.3)  # tools/make_pointcloud_fixtures.py


def _one(reader: object) -> Scan:
    scans = list(reader)  # type: ignore[call-overload]
    assert len(scans) == 1
    return scans[0]


def _data_start(path: Path) -> int:
    raw = path.read_bytes()
    return raw.index(b"DATA") + raw[raw.index(b"DATA") :].index(b"\n") + 1


@pytest.fixture(scope="module")
def scan001() -> tuple[Scan, np.ndarray]:
    reader = ThreeDTKReader(THREEDTK)
    scans = list(reader)
    return scans[1], reader.transforms[1]


# ---------------------------------------------------------------- PCD


def test_pcd_ascii_binary_compressed_identical() -> None:
    scans = [_one(PcdReader(DATA / f"cloud_{k}.pcd")) for k in ("ascii", "binary", "compressed")]
    assert len(scans[0]) == 885
    for s in scans[1:]:
        np.testing.assert_array_equal(s.points, scans[0].points)
        np.testing.assert_array_equal(s.origin, scans[0].origin)


def test_pcd_viewpoint_transform_by_hand(scan001: tuple[Scan, np.ndarray]) -> None:
    path = DATA / "cloud_binary.pcd"
    header = read_pcd_header(path)
    raw = np.fromfile(path, dtype="<f4", offset=header.data_offset).reshape(-1, 4)
    tx, ty, tz, qw, qx, qy, qz = header.viewpoint
    R = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()  # scipy: scalar last
    expected = raw[:, :3].astype(np.float64) @ R.T + [tx, ty, tz]
    scan = _one(PcdReader(path))
    np.testing.assert_allclose(scan.points, expected, atol=1e-12)
    np.testing.assert_array_equal(scan.origin, [tx, ty, tz])
    # and it is the 3DTK scan the fixture was cut from, in the world frame
    world, T = scan001
    np.testing.assert_allclose(scan.points, world.points[::5], atol=2e-6)
    np.testing.assert_allclose(scan.origin, T[:3, 3], atol=1e-9)


def test_pcd_directory_is_a_scan_set(tmp_path: Path) -> None:
    for name in ("b.pcd", "a.pcd"):
        shutil.copy(DATA / "cloud_binary.pcd", tmp_path / name)
    (tmp_path / "notes.txt").write_text("ignored")
    reader = PcdReader(tmp_path)
    assert [f.name for f in reader.files] == ["a.pcd", "b.pcd"]
    assert len(list(reader)) == 2
    assert looks_like_pcd(tmp_path)
    assert looks_like_pcd(DATA / "cloud_ascii.pcd")
    assert not looks_like_pcd(DATA / "cloud_ascii.ply")


def _pcd_text(
    rows: list[str], *, fields: str = "x y z", height: int = 1, vp: str = "0 0 0 1 0 0 0"
) -> str:
    n = len(fields.split())
    width = len(rows) // height
    return (
        f"VERSION 0.7\nFIELDS {fields}\nSIZE {' '.join(['4'] * n)}\nTYPE {' '.join(['F'] * n)}\n"
        f"COUNT {' '.join(['1'] * n)}\nWIDTH {width}\nHEIGHT {height}\nVIEWPOINT {vp}\n"
        f"POINTS {len(rows)}\nDATA ascii\n" + "".join(r + "\n" for r in rows)
    )


def test_pcd_organised_nan_dropped_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "org.pcd"
    path.write_text(_pcd_text(["1 2 3", "nan nan nan", "4 5 6", "nan 1 1"], height=2))
    reader = PcdReader(path)
    scan = _one(reader)
    np.testing.assert_array_equal(scan.points, [[1, 2, 3], [4, 5, 6]])
    assert reader.dropped_nan == 2
    assert reader.skipped == 0
    # the same in binary, with a padding field and a double x
    header = (
        "VERSION 0.7\nFIELDS x y _ z\nSIZE 8 4 4 4\nTYPE F F U F\nCOUNT 1 1 1 1\n"
        "WIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA binary\n"
    )
    rec = np.dtype([("x", "<f8"), ("y", "<f4"), ("_", "<u4"), ("z", "<f4")])
    arr = np.array([(1, 2, 9, 3), (np.nan, 0, 9, 0), (4, 5, 9, 6), (7, np.nan, 9, 8)], rec)
    path.write_bytes(header.encode() + arr.tobytes())
    reader = PcdReader(path)
    np.testing.assert_array_equal(_one(reader).points, [[1, 2, 3], [4, 5, 6]])
    assert reader.dropped_nan == 2


def test_pcd_unorganised_nan_is_bad(tmp_path: Path) -> None:
    path = tmp_path / "u.pcd"
    path.write_text(_pcd_text(["1 2 3", "nan 2 3", "4 5 6"]))
    with pytest.raises(OctolgpError, match=r"u\.pcd:12: NaN or inf"):
        list(PcdReader(path))
    reader = PcdReader(path, skip_bad=True)
    assert len(_one(reader)) == 2
    assert reader.skipped == 1
    assert reader.bad_lines == [(path, 12)]


def test_pcd_extra_fields_and_viewpoint_rotation(tmp_path: Path) -> None:
    # 90° about z: q = (cos 45°, 0, 0, sin 45°); sensor x maps to world y.
    c = np.sqrt(0.5)
    path = tmp_path / "r.pcd"
    path.write_text(_pcd_text(["7 1 0 0", "8 0 2 1"], fields="i x y z", vp=f"1 2 3 {c} 0 0 {c}"))
    scan = _one(PcdReader(path, max_range=30.0))
    np.testing.assert_allclose(scan.points, [[1, 3, 3], [-1, 2, 4]], atol=1e-7)
    assert scan.max_range == 30.0


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "no DATA line"),
        ("VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 1\nDATA ascii\n1 2\n", "field 'z'"),
        ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nDATA zip\n", "DATA must be"),
        ("FIELDS x y z\nSIZE 4 4\nTYPE F F F\nWIDTH 1\nDATA ascii\n1 2 3\n", "3 entries"),
        ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nPOINTS 3\nDATA ascii\n", "POINTS"),
        ("BOGUS 1\nDATA ascii\n", "unknown PCD header keyword"),
    ],
)
def test_pcd_bad_header(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.pcd"
    path.write_text(text)
    with pytest.raises(OctolgpError, match=match) as info:
        list(PcdReader(path))
    assert str(path) in str(info.value)
    reader = PcdReader(path, skip_bad=True)
    assert list(reader) == []
    assert reader.skipped == 1
    assert match in reader.bad_scans[0]


def test_pcd_garbage_bytes_and_non_numeric_line(tmp_path: Path) -> None:
    path = tmp_path / "g.pcd"
    path.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(OctolgpError, match=r"g\.pcd:1: (unknown PCD header keyword|not a PCD)"):
        list(PcdReader(path))
    assert not looks_like_pcd(path)
    path.write_text(_pcd_text(["1 2 3", "1 two 3", "4 5"]))
    with pytest.raises(OctolgpError, match=r"g\.pcd:12: non-numeric value"):
        list(PcdReader(path))
    reader = PcdReader(path, skip_bad=True)
    assert len(_one(reader)) == 1
    assert [line for _, line in reader.bad_lines] == [12, 13]


def test_pcd_truncated(tmp_path: Path) -> None:
    for kind in ("binary", "compressed", "ascii"):
        src = (DATA / f"cloud_{kind}.pcd").read_bytes()
        path = tmp_path / f"t_{kind}.pcd"
        path.write_bytes(src[: len(src) - 100])
        with pytest.raises(OctolgpError, match="truncated") as info:
            list(PcdReader(path))
        assert str(path) in str(info.value)
        reader = PcdReader(path, skip_bad=True)
        assert list(reader) == []
        assert reader.skipped == 1


def test_pcd_binary_non_finite_record(tmp_path: Path) -> None:
    src = DATA / "cloud_binary.pcd"
    raw = bytearray(src.read_bytes())
    start = _data_start(src)
    raw[start + 16 * 5 : start + 16 * 5 + 4] = np.float32(np.inf).tobytes()
    path = tmp_path / "inf.pcd"
    path.write_bytes(bytes(raw))
    with pytest.raises(OctolgpError, match=r"inf\.pcd:point 5: NaN or inf"):
        list(PcdReader(path))
    reader = PcdReader(path, skip_bad=True)
    assert len(_one(reader)) == 884
    assert reader.bad_lines == [(path, 5)]


def test_lzf_decompress_literals_and_overlapping_backref() -> None:
    # "abc" literal, then an 8-byte copy from 3 back (overlapping): "abcabcab"
    assert lzf_decompress(b"\x02abc\xc0\x02", 11) == b"abcabcabcab"
    # long match: length code 7 + extra byte
    assert lzf_decompress(b"\x00a\xe0\x05\x00", 1 + 14) == b"a" * 15
    with pytest.raises(OctolgpError, match="before the start"):
        lzf_decompress(b"\x00a\x20\x05", 4)
    with pytest.raises(OctolgpError, match="past the end"):
        lzf_decompress(b"\x05ab", 6)
    with pytest.raises(OctolgpError, match="not the stated"):
        lzf_decompress(b"\x00a", 2)


# ---------------------------------------------------------------- PLY


def test_ply_ascii_binary_identical_and_origin(scan001: tuple[Scan, np.ndarray]) -> None:
    a = _one(PlyReader(DATA / "cloud_ascii.ply"))
    b = _one(PlyReader(DATA / "cloud_binary.ply", origin=[9, 9, 9]))  # header origin wins
    np.testing.assert_array_equal(a.points, b.points)
    world, T = scan001
    np.testing.assert_array_equal(a.origin, T[:3, 3])
    np.testing.assert_array_equal(a.points, world.points[::5].astype(np.float32))
    pcd = _one(PcdReader(DATA / "cloud_binary.pcd"))
    np.testing.assert_allclose(a.points, pcd.points, atol=1e-5)
    assert looks_like_ply(DATA / "cloud_ascii.ply")
    assert not looks_like_ply(DATA / "scan_small.dat")


def _ply(fmt: str, body: bytes, *, origin: str = "", before: str = "") -> bytes:
    head = f"ply\nformat {fmt} 1.0\n{origin}{before}"
    head += "element vertex 2\nproperty double x\nproperty uchar k\nproperty float y\n"
    head += "property float z\nend_header\n"
    return head.encode() + body


def test_ply_big_endian_skipped_element_and_default_origin(tmp_path: Path) -> None:
    rec = np.dtype([("x", ">f8"), ("k", "u1"), ("y", ">f4"), ("z", ">f4")])
    verts = np.array([(1.5, 7, 2, 3), (-1, 0, 0.25, 8)], rec).tobytes()
    # a face element with list properties before the vertices: 2 faces, 3 and 4 indices
    faces = b"\x03" + np.array([0, 1, 1], ">i4").tobytes() + b"\x04" + bytes(16)
    before = "element face 2\nproperty list uchar int vertex_indices\n"
    path = tmp_path / "be.ply"
    path.write_bytes(_ply("binary_big_endian", faces + verts, before=before))
    scan = _one(PlyReader(path))
    np.testing.assert_array_equal(scan.points, [[1.5, 2, 3], [-1, 0.25, 8]])
    np.testing.assert_array_equal(scan.origin, [0, 0, 0])
    scan = _one(PlyReader(path, origin=(1, 2, 3)))
    np.testing.assert_array_equal(scan.origin, [1, 2, 3])
    path.write_bytes(_ply("ascii", b"1.5 7 2 3\n-1 0 0.25 8\n", origin="obj_info origin 4 5 6\n"))
    scan = _one(PlyReader(path, origin=(1, 2, 3)))
    np.testing.assert_array_equal(scan.origin, [4, 5, 6])


def test_ply_malformed(tmp_path: Path) -> None:
    path = tmp_path / "m.ply"
    path.write_bytes(_ply("ascii", b"1 2 3 4\n1 2 3\n"))
    with pytest.raises(OctolgpError, match=r"m\.ply:10: expected 4 numbers"):
        list(PlyReader(path))
    reader = PlyReader(path, skip_bad=True)
    assert len(_one(reader)) == 1
    assert reader.bad_lines == [(path, 10)]
    path.write_bytes(_ply("ascii", b"1 2 3 nan\n1 2 3 4\n"))
    with pytest.raises(OctolgpError, match=r"m\.ply:9: NaN or inf"):
        list(PlyReader(path))
    src = (DATA / "cloud_binary.ply").read_bytes()
    path.write_bytes(src[:-10])
    with pytest.raises(OctolgpError, match="truncated binary data"):
        list(PlyReader(path))
    reader = PlyReader(path, skip_bad=True)
    assert list(reader) == []
    assert reader.skipped == 1
    for text, match in [
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n", "'y'"),
        (b"ply\nformat zip 1.0\nend_header\n", "bad format line"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\n", "no end_header"),
        (b"", "not a PLY file"),
        (bytes(range(256)), "not a PLY file"),
    ]:
        path.write_bytes(text)
        with pytest.raises(OctolgpError, match=match) as info:
            list(PlyReader(path))
        assert str(path) in str(info.value)
    path.write_bytes(_ply("ascii", b""))
    with pytest.raises(OctolgpError, match="truncated"):
        list(PlyReader(path))


# ---------------------------------------------------------------- OctoMap scan.dat


def test_scan_dat_plain_equals_loadtxt() -> None:
    path = DATA / "scan_small.dat"
    scan = _one(ScanDatReader(path, max_range=40.0))
    np.testing.assert_array_equal(scan.points, np.loadtxt(path))
    np.testing.assert_array_equal(scan.origin, [0, 0, 0])
    assert len(scan) == 2000
    assert scan.max_range == 40.0
    assert looks_like_scan_dat(path)


def test_scan_dat_first_lines_of_real_scan(shared_data: Callable[..., Path]) -> None:
    full = shared_data("octomap_scan", "scan.dat.bz2")
    with bz2.open(full, "rt") as fh:
        head = [next(fh) for _ in range(2000)]
    assert (DATA / "scan_small.dat").read_text() == "".join(head)


def test_scan_dat_nodes_give_world_points() -> None:
    path = DATA / "scan_nodes.dat"
    scans = list(ScanDatReader(path))
    assert [len(s) for s in scans] == [1000, 1000]
    world = np.loadtxt(DATA / "scan_small.dat")
    np.testing.assert_array_equal(scans[0].points, world[:1000])
    np.testing.assert_allclose(scans[1].points, world[1000:], atol=1e-6)
    np.testing.assert_array_equal(scans[1].origin, NODE1_POSE[:3])
    assert looks_like_scan_dat(path)


def test_rpy_matches_octomap() -> None:
    R = rpy_to_matrix(0.3, -0.5, 1.2)
    expected = Rotation.from_euler("ZYX", [1.2, -0.5, 0.3]).as_matrix()
    np.testing.assert_allclose(R, expected, atol=1e-12)
    pyoctomap = pytest.importorskip("pyoctomap")
    pc = pyoctomap.Pointcloud()
    pc.push_back(1.0, 2.0, 3.5)
    pc.transform(0.5, -1.0, 2.0, 0.3, -0.5, 1.2)  # octomap pose6d(x, y, z, roll, pitch, yaw)
    np.testing.assert_allclose(pc.to_numpy()[0], R @ [1, 2, 3.5] + [0.5, -1, 2], atol=1e-5)


@pytest.mark.parametrize("opener", [gzip.open, bz2.open])
def test_scan_dat_compressed(tmp_path: Path, opener: object) -> None:
    path = tmp_path / "scan.dat.x"
    with opener(path, "wb") as fh:  # type: ignore[operator]
        fh.write((DATA / "scan_nodes.dat").read_bytes())
    scans = list(ScanDatReader(path))
    plain = list(ScanDatReader(DATA / "scan_nodes.dat"))
    for a, b in zip(scans, plain, strict=True):
        np.testing.assert_array_equal(a.points, b.points)


def test_scan_dat_malformed(tmp_path: Path) -> None:
    path = tmp_path / "m.dat"
    path.write_text("1 2 3\n1 2 x\n4 5 6\n")
    with pytest.raises(OctolgpError, match=r"m\.dat:2: non-numeric value"):
        list(ScanDatReader(path))
    reader = ScanDatReader(path, skip_bad=True)
    assert len(_one(reader)) == 2
    assert reader.bad_lines == [(path, 2)]
    path.write_text("NODE 0 0 0 0 0\n1 2 3\nNODE 1 1 1 0 0 0\n4 5 6\n")
    with pytest.raises(OctolgpError, match=r"m\.dat:1: expected 'NODE"):
        list(ScanDatReader(path))
    reader = ScanDatReader(path, skip_bad=True)
    scan = _one(reader)  # the bad node is skipped with its point
    np.testing.assert_array_equal(scan.points, [[5, 6, 7]])
    assert reader.skipped == 1
    path.write_text("NODE 0 0 0 0 0 0\nNODE 1 1 1 0 0 0\n4 5 6\n")
    with pytest.raises(OctolgpError, match=r"m\.dat:1: NODE: no points"):
        list(ScanDatReader(path))
    reader = ScanDatReader(path, skip_bad=True)
    assert len(_one(reader)) == 1
    assert reader.skipped == 1
    path.write_text("")
    with pytest.raises(OctolgpError, match="no points"):
        list(ScanDatReader(path))
    path.write_text("1 2 3 4\n")
    with pytest.raises(OctolgpError, match="expected 3 numbers"):
        list(ScanDatReader(path))
    path.write_bytes(b"\x1f\x8b" + bytes(50))
    with pytest.raises(OctolgpError, match="unreadable"):
        list(ScanDatReader(path))
    assert not looks_like_scan_dat(path)


# ---------------------------------------------------------------- OctoMap .graph


def test_graph_fixture_is_the_3dtk_scans() -> None:
    reader = ThreeDTKReader(THREEDTK)
    scans = list(reader)
    graph = list(GraphReader(DATA / "two_scans.graph"))
    assert len(graph) == 2
    for g, s in zip(graph, scans, strict=False):
        np.testing.assert_allclose(g.points, s.points[::16], atol=1e-12)
        np.testing.assert_allclose(g.origin, s.origin, atol=1e-12)
    assert looks_like_graph(DATA / "two_scans.graph")
    assert not looks_like_graph(DATA / "cloud_binary.pcd")


def test_graph_round_trip(tmp_path: Path) -> None:
    scans = list(ScanDatReader(DATA / "scan_nodes.dat"))
    path = tmp_path / "x.bin"  # no suffix needed to sniff
    write_graph(path, scans)
    back = GraphReader(path)
    got = list(back)
    assert back.node_ids == [0, 1]
    for a, b in zip(got, scans, strict=True):
        np.testing.assert_allclose(a.points, b.points, atol=1e-12)
        np.testing.assert_array_equal(a.origin, b.origin)
    assert looks_like_graph(path)


def test_graph_point_layout_is_octomap_pointcloud(tmp_path: Path) -> None:
    pyoctomap = pytest.importorskip("pyoctomap")
    pc = pyoctomap.Pointcloud()
    pc.push_back(1.0, 2.0, 3.5)
    pc.push_back(-1.0, 0.25, 7.0)
    assert pc.writeBinary(str(tmp_path / "pc.bin"))
    path = tmp_path / "g.graph"
    write_graph(path, [Scan(np.zeros(3), [[1.0, 2.0, 3.5], [-1.0, 0.25, 7.0]])])
    assert path.read_bytes()[4 : 4 + 60] == (tmp_path / "pc.bin").read_bytes()


def test_graph_rotation_pose(tmp_path: Path) -> None:
    T = np.eye(4)
    T[:3, :3] = rpy_to_matrix(0.1, 0.2, -0.7)
    T[:3, 3] = [3, 2, 1]
    scan = Scan(T[:3, 3], np.loadtxt(DATA / "scan_small.dat")[:50])
    path = tmp_path / "r.graph"
    write_graph(path, [scan], poses=[T])
    raw = path.read_bytes()
    local = np.frombuffer(raw, dtype=[("n", "<i4"), ("p", "<f8", (3,))], count=50, offset=8)
    np.testing.assert_allclose(local["p"] @ T[:3, :3].T + T[:3, 3], scan.points, atol=1e-12)
    q = struct.unpack_from("<4d", raw, 8 + 28 * 50 + 28 + 4)
    assert np.allclose(q, matrix_to_quaternion(T[:3, :3], order="wxyz"))
    np.testing.assert_allclose(_one(GraphReader(path)).points, scan.points, atol=1e-12)


def test_graph_malformed(tmp_path: Path) -> None:
    src = (DATA / "two_scans.graph").read_bytes()
    path = tmp_path / "t.graph"
    path.write_bytes(src[:-50])  # cut inside node 1
    with pytest.raises(OctolgpError, match=r"t\.graph: byte \d+: node 1: .*truncated"):
        list(GraphReader(path))
    reader = GraphReader(path, skip_bad=True)
    assert len(list(reader)) == 1
    assert reader.skipped == 1
    for data, match in [
        (b"", "empty or truncated"),
        (b"\x00\x00\x00\x00\x00\x00\x00\x00", "no nodes"),
        (bytes(range(200)), "node 0"),
    ]:
        path.write_bytes(data)
        with pytest.raises(OctolgpError, match=match) as info:
            list(GraphReader(path))
        assert str(path) in str(info.value)
        reader = GraphReader(path, skip_bad=True)
        assert list(reader) == []
        assert reader.skipped == 1
    garbled = bytearray(src)
    garbled[8 + 28 * 3] = 9  # point 3's Vector3 marker
    path.write_bytes(bytes(garbled))
    with pytest.raises(OctolgpError, match="point 3 is garbled"):
        list(GraphReader(path))
    nan = bytearray(src)
    nan[8 + 28 * 2 + 4 : 8 + 28 * 2 + 12] = struct.pack("<d", float("nan"))
    path.write_bytes(bytes(nan))
    with pytest.raises(OctolgpError, match=r"t\.graph:point 2: node 0: NaN"):
        list(GraphReader(path))
    reader = GraphReader(path, skip_bad=True)
    assert [len(s) for s in reader] == [1122, 277]
    assert reader.bad_lines == [(path, 2)]


# ---------------------------------------------------------------- common


@pytest.mark.parametrize("cls", [PcdReader, PlyReader, ScanDatReader, GraphReader])
def test_missing_path_and_bad_max_range(tmp_path: Path, cls: type) -> None:
    with pytest.raises(MapFileNotFound):
        cls(tmp_path / "nope")
    with pytest.raises(OctolgpError, match="max_range"):
        cls(DATA / "scan_small.dat", max_range=-1.0)


def test_directory_without_files(tmp_path: Path) -> None:
    with pytest.raises(OctolgpError, match=r"no \.pcd files"):
        PcdReader(tmp_path)
    with pytest.raises(OctolgpError, match=r"no \.ply files"):
        PlyReader(tmp_path)
    with pytest.raises(OctolgpError, match="not a file"):
        ScanDatReader(tmp_path)
