"""Streaming an online map to Rerun, and replaying recordings into maps."""

from __future__ import annotations

import collections
import dataclasses
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from octolgp import Hyperparameters, MapConfig, OnlineMap, Scan, load_scans
from octolgp.cli import main
from octolgp.io.rrd_read import read_rrd
from octolgp.mapping.online import ScanUpdate
from octolgp.sinks.base import MapChange
from octolgp.sinks.rerun import RerunSink

INTEL20 = Path(__file__).parent / "data" / "intel_first20.log"
HP = Hyperparameters(length_scale=0.8, signal_variance=1.0, noise_variance=0.05, alpha=5.0)


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
    """A RerunSink that also remembers which leaves each update refitted."""

    def __init__(self, rec: rr.RecordingStream) -> None:
        super().__init__(rec, rays=7, uncertainty=True)
        self.refits: collections.Counter[int] = collections.Counter()
        self.updates = 0

    def on_update(self, update: ScanUpdate, change: MapChange) -> None:
        leaves = list(change.leaves)  # an iterator: read once, for both
        super().on_update(update, dataclasses.replace(change, leaves=leaves))
        self.refits.update(leaf.key for leaf in leaves)
        self.updates += 1


def _rows(path: Path) -> collections.Counter[str]:
    rows: collections.Counter[str] = collections.Counter()
    for chunk in RrdReader(path).stream():
        rows[str(chunk.entity_path)] += int(chunk.num_rows)
    return rows


@pytest.mark.parametrize("dim", [2, 3])
def test_each_leaf_is_logged_exactly_when_refitted(tmp_path: Path, dim: int) -> None:
    rrd = tmp_path / "m.rrd"
    rec = rr.RecordingStream("octolgp-test")
    rec.save(rrd)
    sink = Recorder(rec)
    scans = _scans(dim)
    with OnlineMap(MapConfig(dim=dim, resolution=0.2, hyperparameters=HP), sink=sink) as m:
        m.insert_scans(scans + scans[:2])  # the repeats refit nothing
        n_leaves = len(m.store)
    rec.flush()
    rec.disconnect()
    rows = _rows(rrd)
    assert sink.updates == 6
    assert len(sink.refits) == n_leaves
    static = 1 if dim == 2 else 0  # a 2D tile's quad is logged once, static
    for key, count in sink.refits.items():
        assert rows[f"/world/map/leaves/{key}"] == count + static
        assert rows[f"/world/map/variance/{key}"] == count
    assert sum(sink.refits.values()) < 6 * n_leaves  # only what changed
    assert rows["/metrics/insert_seconds"] == 6
    assert rows["/world/sensor/points"] == 6
    assert rows["/world/sensor/rays"] == 6
    # the scans come back bit for bit
    back = list(read_rrd(rrd))
    assert len(back) == 6
    for a, b in zip(scans + scans[:2], back, strict=True):
        assert np.array_equal(a.points, b.points)
        assert np.array_equal(a.origin, b.origin)
        assert a.stamp == b.stamp


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
        assert np.array_equal(a.points, b.points)
