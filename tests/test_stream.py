"""Streaming an online map to Rerun, and replaying recordings into maps."""

from __future__ import annotations

import collections
import dataclasses
import io
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from octolgp import Hyperparameters, MapConfig, OnlineConfig, OnlineMap, Scan, load_scans
from octolgp.cli import main
from octolgp.errors import OctolgpError
from octolgp.io.rrd_read import read_rrd
from octolgp.mapping.online import ScanUpdate
from octolgp.sinks.base import MapChange
from octolgp.sinks.rerun import (
    GREY_STEPS,
    UNKNOWN_GREY,
    RerunSink,
    default_blueprint,
    open_recording,
)

INTEL20 = Path(__file__).parent / "data" / "intel_first20.log"
HP = Hyperparameters(length_scale=0.8, signal_variance=1.0, noise_variance=0.05, alpha=5.0)

PRECISION = float(OnlineConfig().scan_precision or 0.0)  # what the map rounds scans to


def _scans(dim: int, n: int = 4) -> list[Scan]:
    rng = np.random.default_rng(dim)
    out = []
    for k in range(n):
        origin = np.zeros(dim)
        origin[0] = 0.3 * k
        d = rng.normal(size=(150, dim))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        out.append(Scan(origin=origin, points=origin + 3.0 * d, stamp=100.0 + k))
    return out


class Recorder(RerunSink):
    """A RerunSink that also remembers which leaves each update refitted, and where."""

    def __init__(self, rec: rr.RecordingStream, **options: Any) -> None:
        super().__init__(rec, **({"rays": 7, "uncertainty": True} | options))
        self.refits: collections.Counter[int] = collections.Counter()
        self.updates = 0
        self.corners: list[tuple[int, list[np.ndarray]]] = []  # (scan, refit leaves' lo)

    def on_update(self, update: ScanUpdate, change: MapChange) -> None:
        leaves = list(change.leaves)  # an iterator: read once, for both
        super().on_update(update, dataclasses.replace(change, leaves=leaves))
        self.refits.update(leaf.key for leaf in leaves)
        self.corners.append((update.scan, [leaf.lo for leaf in leaves]))
        self.updates += 1


def _rows(path: Path) -> collections.Counter[str]:
    rows: collections.Counter[str] = collections.Counter()
    for chunk in RrdReader(path).stream():
        rows[str(chunk.entity_path)] += int(chunk.num_rows)
    return rows


def _column(path: Path, prefix: str, column: str) -> list[tuple[str, int | None, Any]]:
    """``(entity, scan or None when static, value)`` of every row of entities under a prefix."""
    out: list[tuple[str, int | None, Any]] = []
    for chunk in RrdReader(path).stream():
        entity = str(chunk.entity_path)
        batch = chunk.to_record_batch()
        if not entity.startswith(prefix) or column not in batch.schema.names:
            continue
        values = batch.column(column)
        scans = batch.column("scan").to_pylist() if "scan" in batch.schema.names else None
        for i in range(batch.num_rows):  # one iteration per row
            if values[i].is_valid:
                out.append((entity, None if scans is None else scans[i], values[i]))
    return out


def _latest(rows: list[tuple[str, int | None, Any]]) -> dict[str, Any]:
    """Each entity's value at its last scan (static rows count as earliest)."""
    best: dict[str, tuple[int, Any]] = {}
    for entity, scan, value in rows:  # one iteration per row
        at = -1 if scan is None else scan
        if entity not in best or at >= best[entity][0]:
            best[entity] = (at, value)
    return {e: v for e, (_, v) in best.items()}


def _png_of(value: Any) -> np.ndarray:
    """The grey image of one ``EncodedImage:blob`` cell."""
    from PIL import Image

    blob = bytes(value.values[0].values.to_numpy(zero_copy_only=False))
    return np.asarray(Image.open(io.BytesIO(blob)))


def _record(path: Path, scans: list[Scan], dim: int, **options: Any) -> tuple[Recorder, Any]:
    """Map ``scans`` then ``scans[:2]`` again, streaming to ``path``; the sink and the map."""
    rec = rr.RecordingStream("octolgp-test")
    rec.save(path)
    sink = Recorder(rec, **options)
    m = OnlineMap(MapConfig(dim=dim, resolution=0.2, hyperparameters=HP), sink=sink)
    m.insert_scans(scans + scans[:2])  # repeats: refit only while free looks grow
    rec.flush()
    rec.disconnect()
    return sink, m


def _assert_tiles_show(rrd: Path, m: OnlineMap, tile: int, res: float, steps: int) -> int:
    """The last image of each tile is the map's grey occupancy, within half a grey step.

    Cells no leaf covers are unknown grey (a tile the map left is all grey); each tile is
    placed once, static. Returns the number of tiles.
    """
    centres, prob = m.voxels()
    cells = np.floor(centres / res).astype(np.int64)
    expected: dict[str, np.ndarray] = {}
    for (cx, cy), p in zip(cells, prob, strict=True):  # one iteration per voxel
        tx, ty = cx // tile, cy // tile
        grid = expected.setdefault(f"/map/tiles/{tx}_{ty}", np.full((tile, tile), np.nan))
        grid[tile - 1 - (cy - ty * tile), cx - tx * tile] = 255.0 * (1.0 - p)  # row 0: top
    images = _latest(_column(rrd, "/map/tiles/", "EncodedImage:blob"))
    assert set(images) >= set(expected)
    tolerance = 255.0 / (2 * steps) + 0.5  # quantisation to steps + 1 levels, then rounding
    for entity, image in images.items():  # one iteration per tile
        got = _png_of(image).astype(np.float64)
        assert got.shape == (tile, tile)
        want = expected.get(entity, np.full((tile, tile), np.nan))
        known = ~np.isnan(want)
        if known.any():
            assert np.abs(got[known] - want[known]).max() <= tolerance
        assert np.all(got[~known] == UNKNOWN_GREY)  # cells no leaf covers: unknown grey
    # each tile is placed once, static: x0 and -y1 of its cells, one pixel per cell
    placed = _column(rrd, "/map/tiles/", "Transform3D:translation")
    assert sorted(e for e, scan, _ in placed) == sorted(images)
    assert all(scan is None for _, scan, _ in placed)
    for entity, _, value in placed:  # one iteration per tile
        tx, ty = (int(v) for v in entity.rsplit("/", 1)[1].split("_"))
        want_t = [tx * tile * res, -(ty + 1) * tile * res, 0.0]
        np.testing.assert_allclose(value.as_py()[0], want_t, atol=1e-5)
    return len(images)


@pytest.mark.parametrize("steps", [32, 255])
def test_2d_tiles_are_the_maps_occupancy(tmp_path: Path, steps: int) -> None:
    rrd = tmp_path / "m.rrd"
    _, m = _record(rrd, _scans(2), 2, tile=32, grey_steps=steps)
    with m:
        assert _assert_tiles_show(rrd, m, 32, 0.2, steps) >= 4


def test_2d_tiles_show_a_correction(tmp_path: Path) -> None:
    """Rebuilt leaves are redrawn; the cells of a leaf the correction emptied turn unknown."""
    rrd = tmp_path / "m.rrd"
    rec = rr.RecordingStream("octolgp-test")
    rec.save(rrd)
    far = Scan(origin=np.array([30.0, 30.0]), points=np.array([[31.0, 30.0], [30.0, 31.5]]))
    shift = np.array([[1.0, 0.0, -30.0], [0.0, 1.0, -30.0], [0.0, 0.0, 1.0]])
    config = MapConfig(dim=2, resolution=0.2, hyperparameters=HP)
    with OnlineMap(config, path=tmp_path / "m.octolgp", sink=RerunSink(rec, tile=32)) as m:
        m.insert_scans([*_scans(2, 2), far])
        update = m.correct_scans({3: shift})
        rec.flush()
        rec.disconnect()
        assert update.removed_leaves > 0
        _assert_tiles_show(rrd, m, 32, 0.2, GREY_STEPS)
        grey = {
            e
            for e, v in _latest(_column(rrd, "/map/tiles/", "EncodedImage:blob")).items()
            if np.all(_png_of(v) == UNKNOWN_GREY)
        }
        assert grey  # the far tiles: drawn, then emptied


def test_2d_tiles_are_logged_only_when_a_scan_changed_them(tmp_path: Path) -> None:
    """Each scan comes clear_scans + 1 times (a voxel's free looks count up to
    clear_scans), then the first two once more: those last repeats refit nothing."""
    rrd, tile, res = tmp_path / "m.rrd", 32, 0.2
    k = MapConfig(dim=2).clear_scans
    sink, m = _record(rrd, _scans(2) * (k + 1), 2, tile=tile)
    m.close()
    n = 4 * (k + 1) + 2
    logged: dict[int, set[str]] = collections.defaultdict(set)
    for entity, scan, _ in _column(rrd, "/map/tiles/", "EncodedImage:blob"):
        assert scan is not None
        logged[scan].add(entity)
    n_tiles = len({e for tiles in logged.values() for e in tiles})
    assert n_tiles >= 4
    for scan, corners in sink.corners:  # one iteration per update
        cells = [np.rint(lo / res).astype(np.int64) // tile for lo in corners]
        touched = {f"/map/tiles/{tx}_{ty}" for tx, ty in cells}
        assert logged.get(scan, set()) <= touched  # a tile no refit leaf lies in: not logged
    assert sink.updates == n
    assert not logged.get(n - 1)  # the repeats refit nothing
    assert not logged.get(n)
    assert sum(len(t) for t in logged.values()) < sink.updates * n_tiles
    rows = _rows(rrd)
    assert not any(e.startswith("/world/map/leaves") for e in rows)  # no entity per leaf
    assert rows["/metrics/insert_seconds"] == n
    assert rows["/world/sensor/points"] == n
    assert rows["/map/scan"] == n + 1  # positions per scan, the style once (static)
    assert rows["/map/rays"] == n
    assert sum(v for e, v in rows.items() if e.startswith("/map/variance/")) > 0
    # the scans come back bit for bit
    back = list(read_rrd(rrd))
    scans = _scans(2) * (k + 1)
    assert len(back) == n
    for a, b in zip(scans + scans[:2], back, strict=True):
        assert np.array_equal(a.rounded(PRECISION).points, b.points)  # as the map kept it
        assert np.array_equal(a.origin, b.origin)
        assert a.stamp == b.stamp
    # and so do the points of the sensor entity (only it is posed)
    posed = list(read_rrd(rrd, points="world/sensor/points"))
    np.testing.assert_allclose(posed[0].points, scans[0].rounded(PRECISION).points, atol=1e-5)


def test_3d_regions_hold_the_occupied_voxels(tmp_path: Path) -> None:
    rrd, res = tmp_path / "m.rrd", 0.2
    _, m = _record(rrd, _scans(3), 3, region=32)
    with m:
        centres, prob = m.voxels()
        n_leaves = len(m.store)
    want = {tuple(k) for k in np.floor(centres[prob > 0.5] / res).astype(np.int64)}
    boxes = _latest(_column(rrd, "/world/map/voxels/", "Boxes3D:centers"))
    halves = _latest(_column(rrd, "/world/map/voxels/", "Boxes3D:half_sizes"))
    assert 0 < len(boxes) < n_leaves  # one entity per region, not per leaf
    got: set[tuple[int, ...]] = set()
    for entity, value in boxes.items():  # one iteration per region
        c = np.asarray(value.as_py(), dtype=np.float64)
        h = np.broadcast_to(np.asarray(halves[entity].as_py(), dtype=np.float64), c.shape)
        for centre, half in zip(c, h, strict=True):  # one iteration per box
            n = np.rint(2 * half / res).astype(int)  # voxels per edge (a pruned leaf: side)
            offsets = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1)
            lo = centre - half + 0.5 * res
            keys = np.floor((lo + res * offsets.reshape(-1, 3)) / res + 1e-6).astype(np.int64)
            got.update(tuple(k) for k in keys)
    assert got == want
    rows = _rows(rrd)
    assert rows["/world/sensor/points"] == 6
    assert rows["/world/sensor/rays"] == 6
    assert sum(v for e, v in rows.items() if e.startswith("/world/map/variance/")) > 0
    assert len(list(read_rrd(rrd))) == 6


def _activations(path: Path) -> list[tuple[bool, bool]]:
    """``(make_active, make_default)`` of each blueprint activation command in an RRD file.

    Messages are ``kind: u64, len: u64, payload`` (kind 3: BlueprintActivationCommand, a
    protobuf: 1 blueprint id, 2 make_active, 3 make_default; false fields are omitted).
    """
    data, off, out = path.read_bytes(), 12, []
    while off + 16 <= len(data):
        if data[off : off + 4] == b"RRF2":
            off += 12
            continue
        kind, length = struct.unpack("<QQ", data[off : off + 16])
        payload = data[off + 16 : off + 16 + length]
        if kind == 0:
            break
        if kind == 3:
            assert payload[0] == 0x0A  # field 1, the store id: skip it
            i, size, shift = 1, 0, 0
            while True:  # varint length
                size |= (payload[i] & 0x7F) << shift
                shift += 7
                i += 1
                if payload[i - 1] < 0x80:
                    break
            flags = payload[i + size :]
            out.append((b"\x10\x01" in flags, b"\x18\x01" in flags))
        off += 16 + length
    return out


@pytest.mark.parametrize("how", ["sink", "open_recording"])
def test_the_blueprint_is_a_default_blueprint(tmp_path: Path, how: str) -> None:
    """Sent as the default, never made active: a layout the user made is kept."""
    rrd = tmp_path / "m.rrd"
    if how == "sink":
        rec = rr.RecordingStream("octolgp-test")
        rec.save(rrd)
        sink = RerunSink(rec)
    else:
        rec, url = open_recording("octolgp-test", save=rrd, blueprint=default_blueprint(2))
        assert url is None
        sink = RerunSink(rec, blueprint=False)
    with OnlineMap(MapConfig(dim=2, resolution=0.2, hyperparameters=HP), sink=sink) as m:
        m.insert_scans(_scans(2))
    rec.flush()
    rec.disconnect()
    # sent as the default, never made active; the sink's own follows the map (2D)
    sent = _activations(rrd)
    assert set(sent) == {(False, True)}
    assert (len(sent) > 1) == (how == "sink")
    assert len(RrdReader(rrd).blueprints()) == len(sent)


def test_blueprints_for_each_dimension() -> None:
    for dim in (2, 3):
        for uncertainty in (False, True):
            assert default_blueprint(dim, uncertainty=uncertainty) is not None
    assert default_blueprint(2, bounds=((-5.0, 5.0), (0.0, 3.0))) is not None
    with pytest.raises(OctolgpError, match="grey_steps"):
        RerunSink(rr.RecordingStream("octolgp-test"), grey_steps=0)


def test_streaming_does_not_change_the_map(tmp_path: Path) -> None:
    rec = rr.RecordingStream("octolgp-test")
    rec.save(tmp_path / "m.rrd")
    config = MapConfig(dim=2, resolution=0.1, hyperparameters=HP)
    with OnlineMap(config, recording=rec) as a, OnlineMap(config) as b:
        a.insert_scans(_scans(2))
        b.insert_scans(_scans(2))
        centres, prob = b.voxels()
        assert np.array_equal(a.occupancy(centres, interpolate=False), prob)
    rec.disconnect()


def test_rerun_is_not_imported_when_logging_is_off() -> None:
    code = (
        "import sys, numpy as np\n"
        "from octolgp import OnlineMap, MapConfig, Scan, Hyperparameters\n"
        "m = OnlineMap(MapConfig(dim=2, hyperparameters=Hyperparameters()))\n"
        "m.insert_scan(Scan(origin=[0.0, 0.0], points=[[1.0, 0.0], [0.0, 1.0]]))\n"
        "assert 'rerun' not in sys.modules, 'rerun imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def _voxel_values(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with OnlineMap.open(path) as m:
        return m.voxels()


def test_run_then_replay_gives_the_same_map(tmp_path: Path) -> None:
    a, b, rrd = tmp_path / "a.octolgp", tmp_path / "b.octolgp", tmp_path / "a.rrd"
    common = ["--learn-scans", "5", "--quiet", "--resolution", "0.1"]
    assert main(["run", str(INTEL20), "--out", str(a), "--rerun-save", str(rrd), *common]) == 0
    assert main(["replay", str(rrd), "--out", str(b), *common]) == 0
    # the view is a few tiles, not an entity per leaf, and the recording stays small
    with OnlineMap.open(a) as m:
        n_leaves = len(m.store)
    rows = _rows(rrd)
    tiles = [e for e in rows if e.startswith("/map/tiles/")]
    assert 0 < len(tiles) <= n_leaves / 8  # a tile holds up to 16 leaves
    assert len(rows) < n_leaves / 4
    # 74 kB per scan here (every tile is new; 1,230 kB per scan with one entity per leaf)
    assert rrd.stat().st_size / len(list(load_scans(INTEL20))) < 100e3
    sent = _activations(rrd)  # the CLI's default blueprint, then bounded on the map
    assert len(sent) > 1
    assert set(sent) == {(False, True)}
    ca, pa = _voxel_values(a)
    cb, pb = _voxel_values(b)
    assert ca.shape[0] > 1000
    assert np.array_equal(ca, cb)
    np.testing.assert_allclose(pa, pb, rtol=0, atol=1e-6)
    with OnlineMap.open(b) as m:
        assert m.n_scans == len(list(load_scans(INTEL20)))


@pytest.mark.parametrize("content", [b"", b"hello, not a recording\n", bytes(4096)])
def test_replay_of_a_foreign_file_exits_2(tmp_path: Path, content: bytes) -> None:
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(content)
    proc = subprocess.run(
        [sys.executable, "-m", "octolgp.cli", "replay", str(bad), "--out", "m.octolgp"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "m.octolgp").exists()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _default_signals() -> None:
    """In the receiver (before exec): default SIGINT handling and no blocked signals.

    Both are inherited: earlier tests in the same pytest process (threads of the Rust
    SDK, Dask) can leave SIGINT ignored or blocked, and the receiver then never exits.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_SETMASK, [])


def test_stream_over_loopback_grpc(tmp_path: Path) -> None:
    binary = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not Path(binary).exists():
        pytest.skip("the rerun binary is not installed")
    port = _free_port()
    received = tmp_path / "received.rrd"
    server = subprocess.Popen(
        [
            binary,
            "--serve-grpc",
            "--bind",
            "127.0.0.1",
            "--port",
            str(port),
            "--save",
            str(received),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        # its own process group: the `rerun` entry point is a Python wrapper around the
        # native viewer binary, and a signal must reach both
        start_new_session=True,
        preexec_fn=_default_signals,
    )
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:  # wait for the receiver to listen
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.1)
        rec = rr.RecordingStream("octolgp-grpc")
        rec.connect_grpc(f"rerun+http://127.0.0.1:{port}/proxy")
        scans = _scans(2)
        with OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP), recording=rec) as m:
            m.insert_scans(scans)
        rec.flush()
        rec.disconnect()
        time.sleep(0.5)
    finally:
        os.killpg(server.pid, signal.SIGINT)
        try:
            server.wait(timeout=60)  # the receiver finishes writing, then exits
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)  # never leak it into the next test
            server.wait()
            pytest.fail("the rerun receiver did not exit within 60 s of SIGINT")
    back = list(read_rrd(received))
    assert len(back) == len(scans)
    for a, b in zip(scans, back, strict=True):
        assert np.array_equal(a.rounded(PRECISION).points, b.points)  # as the map kept it


@pytest.mark.parametrize("option", ["--rerun-serve", "--rerun-web"])
def test_a_served_map_is_served_until_ctrl_c(tmp_path: Path, option: str) -> None:
    """The map is done, the server stays up (the web viewer answers), Ctrl-C ends it cleanly."""
    grpc_port, web_port = _free_port(), _free_port()
    cmd = [sys.executable, "-m", "octolgp.cli", "run", str(INTEL20), "--out", "m.octolgp"]
    cmd += ["--limit", "3", "--learn-scans", "2", "--quiet", "--resolution", "0.2", option]
    cmd += ["--rerun-port", str(grpc_port), "--rerun-web-port", str(web_port)]
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,
        start_new_session=True,
        preexec_fn=_default_signals,
    )
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:  # one iteration per line, until the map is done
            lines.append(line)
            if "Ctrl-C to stop" in line:
                break
        assert (tmp_path / "m.octolgp").exists()
        assert proc.poll() is None  # still serving
        if option == "--rerun-web":
            url = next(ln for ln in lines if "web viewer at" in ln).split()[5]
            assert url.startswith(f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp")
            with urllib.request.urlopen(url.split("?")[0], timeout=30) as page:
                assert page.status == 200
        else:
            assert any(f"127.0.0.1:{grpc_port}" in ln for ln in lines)
        os.killpg(proc.pid, signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, "".join(lines) + out
    assert "stopped serving" in out
    assert "Traceback" not in out


def test_the_2d_view_opens_on_what_the_map_knows(tmp_path: Path) -> None:
    """The default view's bounds hold every voxel with a value, with a margin, and not the
    scans' 80 m no-return rays (which the view's own default, everything logged, would)."""
    rec = rr.RecordingStream("octolgp-test")
    rec.save(tmp_path / "m.rrd")
    sink = RerunSink(rec)
    scans = list(load_scans(INTEL20))
    with OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP), sink=sink) as m:
        m.insert_scans(scans)
        centres, _ = m.voxels()
    rec.disconnect()
    assert sink.shown is not None
    (x0, x1), (y0, y1) = sink.shown
    assert x0 < centres[:, 0].min()
    assert centres[:, 0].max() < x1
    assert y0 < centres[:, 1].min()
    assert centres[:, 1].max() < y1
    rays = np.concatenate([s.points for s in scans])
    assert np.ptp(rays[:, 0]) > 2 * (x1 - x0)  # the rays reach far beyond the map
    assert x1 - x0 < 1.3 * np.ptp(centres[:, 0]) + 2.1  # the map, a tenth and a metre a side
