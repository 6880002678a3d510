"""The map file's guarantees under faults, misuse and concurrent access.

Each test is one class of failure: a save onto a live map, a failed commit, a closed
map, a kill during a batch, two writers, a reader beside a writer, flipped bytes,
learning without returns, and reads that must not change the file.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sqlite3
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OctolgpError, OnlineMap, Scan
from octolgp.cli import main
from octolgp.gp.learning import learn_hyperparameters

HP = Hyperparameters(length_scale=0.4, signal_variance=1.0, noise_variance=0.05, alpha=6.0)
CONFIG = MapConfig(dim=2, resolution=0.1, hyperparameters=HP)
ROOT = Path(__file__).resolve().parents[1]


def room_scan(origin: tuple[float, float], n: int = 90, size: float = 4.0) -> Scan:
    """A 2D scan from ``origin`` inside the square room [-size, size]²."""
    ang = np.linspace(-np.pi, np.pi, n, endpoint=False)
    d = np.c_[np.cos(ang), np.sin(ang)]
    o = np.asarray(origin, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.min(np.where(d != 0, (np.sign(d) * size - o) / d, np.inf), axis=1)
    return Scan(origin=o, points=o + t[:, None] * d)


SCANS = [room_scan((x, 0.5 * x)) for x in (-2.0, -1.0, 0.0, 1.0, 2.0, 2.5)]
PROBE = np.stack(np.meshgrid(np.linspace(-4.5, 4.5, 31), np.linspace(-4.5, 4.5, 31)), -1).reshape(
    -1, 2
)


def values(m: OnlineMap) -> np.ndarray:
    return m.occupancy(PROBE)


def config_with(engine: str) -> MapConfig:
    return dataclasses.replace(CONFIG, online=dataclasses.replace(CONFIG.online, engine=engine))


def reference(scans: list[Scan], engine: str = "lattice") -> np.ndarray:
    m = OnlineMap(config_with(engine))
    m.insert_scans(scans)
    return values(m)


def same_scans(journal: list[Scan], inserted: list[Scan]) -> bool:
    """Whether a journal holds the inserted scans as the map keeps them (rounded)."""
    precision = CONFIG.online.scan_precision
    assert precision is not None
    return len(journal) == len(inserted) and all(
        np.array_equal(x.origin, y.origin) and np.array_equal(x.points, y.rounded(precision).points)
        for x, y in zip(journal, inserted, strict=True)
    )


# ---------------------------------------------------------------------- data loss
def test_save_refuses_the_maps_own_file_and_existing_files(tmp_path: Path) -> None:
    path, other = tmp_path / "live.octolgp", tmp_path / "other.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(SCANS[:2])
        with pytest.raises(OctolgpError, match="own file"):
            m.save(path)
        with pytest.raises(OctolgpError, match="own file"):
            m.save(path, overwrite=True)
        m.insert_scan(SCANS[2])  # the live map goes on
        other.write_bytes(b"precious")
        with pytest.raises(OctolgpError, match="already exists"):
            m.save(other)
        assert other.read_bytes() == b"precious"
        m.save(other, overwrite=True)
    for p in (path, other):
        with OnlineMap.open(p, read_only=True) as back:
            assert back.n_scans == 3
            np.testing.assert_array_equal(values(back), reference(SCANS[:3]))


def test_save_refuses_to_replace_a_map_open_for_writing(tmp_path: Path) -> None:
    live = tmp_path / "live.octolgp"
    with OnlineMap(CONFIG, path=live) as writer:
        writer.insert_scan(SCANS[0])
        m = OnlineMap(CONFIG)
        m.insert_scans(SCANS[1:3])
        with pytest.raises(OctolgpError, match="open for writing"):
            m.save(live, overwrite=True)
        writer.insert_scan(SCANS[1])
    with OnlineMap.open(live, read_only=True) as back:
        assert back.n_scans == 2


AFTER = room_scan((0.3, 0.2), n=1440, size=9.0)
"""A scan after the failed one, with more items in the leaves the failed one reached."""

_FULL_DISK = """
import resource, signal, sys
import numpy as np
sys.path.insert(0, {tests!r})
from test_guarantees import AFTER, SCANS, PROBE, config_with, room_scan
from octolgp import OctolgpError, OnlineMap
path = sys.argv[1]
m = OnlineMap(config_with(sys.argv[2]), path=path)
m.insert_scans(SCANS[:3])
before = m.occupancy(PROBE)
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
_, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, hard))  # smaller than any new page
try:
    m.insert_scan(room_scan((0.0, 0.0), n=720, size=9.0))  # reaches the map's leaves too
except OctolgpError as exc:
    print("refused:", exc)
else:
    sys.exit("the insert did not fail")
resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))
assert m.n_scans == 3, m.n_scans
np.testing.assert_array_equal(m.occupancy(PROBE), before)
m.insert_scan(AFTER)  # the disk has room again: the map goes on
m.close()
"""


@pytest.mark.parametrize("engine", ["lattice", "exact"])
def test_a_failed_commit_leaves_the_map_and_its_file_as_before(tmp_path: Path, engine: str) -> None:
    path = tmp_path / "m.octolgp"
    script = _FULL_DISK.format(tests=str(ROOT / "tests"))
    run = subprocess.run(
        [sys.executable, "-c", script, str(path), engine],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "refused:" in run.stdout
    assert str(path) in run.stdout
    assert "rolled back" in run.stdout
    with OnlineMap.open(path, read_only=True) as back:
        assert back.n_scans == 4
        assert same_scans(list(back.scans()), [*SCANS[:3], AFTER])
        np.testing.assert_array_equal(values(back), reference([*SCANS[:3], AFTER], engine))


def test_a_full_disk_in_the_cli_is_one_line_and_exit_2(tmp_path: Path) -> None:
    log = tmp_path / "scans.npz"
    scans = SCANS[:3]
    offsets = np.cumsum([0] + [s.points.shape[0] for s in scans])
    np.savez(
        log,
        origins=np.stack([s.origin for s in scans]),
        points=np.concatenate([s.points for s in scans]),
        offsets=offsets,
    )
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "[hyperparameters]\nlength_scale = 0.4\nsignal_variance = 1.0\n"
        "noise_variance = 0.05\nalpha = 6.0\nbeta = 0.0\n"
    )
    out = tmp_path / "m.octolgp"
    script = (
        "import resource, signal, sys\n"
        "from octolgp.cli import main\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "_, hard = resource.getrlimit(resource.RLIMIT_FSIZE)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (2048, hard))\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    args = ["run", str(log), "--out", str(out), "--config", str(cfg), "--resolution", "0.1"]
    run = subprocess.run(
        [sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 2, (run.returncode, run.stderr[-2000:])
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, run.stderr[-2000:]
    assert "Traceback" not in run.stderr


def test_a_closed_map_refuses_every_call(tmp_path: Path) -> None:
    budget = MapConfig(dim=2, resolution=0.1, hyperparameters=HP, memory_budget_mb=0.001)
    for m in (OnlineMap(CONFIG, path=tmp_path / "m.octolgp"), OnlineMap(budget), OnlineMap(CONFIG)):
        m.insert_scan(SCANS[0])
        m.close()
        m.close()  # twice is harmless
        calls = [
            lambda m=m: m.insert_scan(SCANS[1]),
            lambda m=m: m.insert_batch(SCANS[1:3]),
            lambda m=m: m.occupancy(PROBE),
            lambda m=m: m.latent(PROBE),
            lambda m=m: m.voxels(),
            lambda m=m: m.leaves(),
            lambda m=m: m.scans(),
            lambda m=m: m.flush(),
            lambda m=m: m.save(tmp_path / "copy.octolgp"),
            lambda m=m: m.correct_scans({1: np.eye(3)}),
            lambda m=m: m.set_hyperparameters(HP),
        ]
        for call in calls:
            with pytest.raises(OctolgpError, match="closed"):
                call()
    assert not (tmp_path / "copy.octolgp").exists()


_KILLED_BATCH = """
import sys, time
sys.path.insert(0, {tests!r})
from test_guarantees import CONFIG, SCANS, room_scan
import octolgp.mapping.online as online
from octolgp import OnlineMap
online.FIT_BATCH_ITEMS = 500  # many batches, each written before the next
m = OnlineMap(CONFIG, path=sys.argv[1])
m.insert_scans(SCANS[:2])
def progress(done, total):
    print("batch", done, total, flush=True)
    if done < total:
        time.sleep(60)  # killed here, with batches written and the journal not
batch = [room_scan((x, y), n=360, size=8.0) for x in (-5.0, 0.0, 5.0) for y in (-5.0, 5.0)]
m.insert_batch(batch, progress=progress)
print("done", flush=True)
"""


def test_sigkill_during_insert_batch_leaves_the_file_before_the_batch(tmp_path: Path) -> None:
    path = tmp_path / "m.octolgp"
    script = _KILLED_BATCH.format(tests=str(ROOT / "tests"))
    with subprocess.Popen(
        [sys.executable, "-c", script, str(path)], stdout=subprocess.PIPE, text=True
    ) as child:
        assert child.stdout is not None
        line = child.stdout.readline()  # the first batch is written
        assert line.startswith("batch"), line
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=60)
    with OnlineMap.open(path, read_only=True) as back:
        assert back.n_scans == 2
        assert len(list(back.leaves())) == len(reference_leaves(SCANS[:2]))
        np.testing.assert_array_equal(values(back), reference(SCANS[:2]))


def reference_leaves(scans: list[Scan]) -> list[int]:
    m = OnlineMap(CONFIG)
    m.insert_scans(scans)
    return [k for k, _ in m.leaves()]


# ---------------------------------------------------------------------- one writer, snapshots
def test_one_writer_per_map_file(tmp_path: Path) -> None:
    path = tmp_path / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scan(SCANS[0])
        with pytest.raises(OctolgpError, match="open for writing elsewhere"):
            OnlineMap.open(path)
        other = subprocess.run(
            [sys.executable, "-c", "import sys; from octolgp import OnlineMap; "
             "OnlineMap.open(sys.argv[1])", str(path)],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert other.returncode != 0
        assert "open for writing elsewhere" in other.stderr
        poses = tmp_path / "poses.txt"
        poses.write_text("1 " + " ".join(map(str, np.eye(3).ravel())) + "\n")
        assert main(["correct", str(path), "--poses", str(poses)]) == 2
        m.insert_scan(SCANS[1])  # the writer is unaffected
    with OnlineMap.open(path) as again:  # free once the writer closed
        again.insert_scan(SCANS[2])
    with OnlineMap.open(path, read_only=True) as back:
        np.testing.assert_array_equal(values(back), reference(SCANS[:3]))


def test_threads_sharing_a_map_take_turns(tmp_path: Path) -> None:
    m = OnlineMap(CONFIG, path=tmp_path / "m.octolgp")
    errors: list[BaseException] = []

    def insert(scans: list[Scan]) -> None:
        try:
            for s in scans:
                m.insert_scan(s)
                m.occupancy(PROBE)
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=insert, args=(SCANS[i::3],)) for i in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    journal = list(m.scans())
    assert m.n_scans == len(SCANS) == len(journal)
    np.testing.assert_array_equal(values(m), reference(journal))
    m.close()


def test_a_reader_sees_a_snapshot_beside_a_live_writer(tmp_path: Path) -> None:
    path = tmp_path / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as writer:
        writer.insert_scans(SCANS[:2])
        reader = OnlineMap.open(path, read_only=True)
        writer.insert_scans(SCANS[2:])  # the writer goes on; the reader does not see it
        assert reader.n_scans == 2
        assert same_scans(list(reader.scans()), SCANS[:2])
        np.testing.assert_array_equal(values(reader), reference(SCANS[:2]))
        with pytest.raises(OctolgpError, match="read-only"):
            reader.insert_scan(SCANS[0])
        reader.close()
        with OnlineMap.open(path, read_only=True) as fresh:
            assert fresh.n_scans == len(SCANS)


# ---------------------------------------------------------------------- integrity
def test_flipped_bytes_in_a_leaf_record_are_an_error_naming_the_leaf(tmp_path: Path) -> None:
    path = tmp_path / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(SCANS[:2])
    con = sqlite3.connect(path)
    (key, blob), (key2, _) = con.execute("SELECT key, data FROM leaves LIMIT 2").fetchall()
    flipped = bytearray(blob)
    flipped[len(blob) // 2] ^= 0x40  # inside the voxel values
    con.execute("UPDATE leaves SET data=? WHERE key=?", (bytes(flipped), key))
    con.execute("UPDATE leaves SET data=? WHERE key=?", (blob, key2))  # another leaf's record
    con.commit()
    con.close()
    with OnlineMap.open(path, read_only=True) as back:
        with pytest.raises(OctolgpError, match=rf"leaf {key}: .*checksum"):
            back.occupancy(PROBE)
        with pytest.raises(OctolgpError, match=rf"leaf {key}"):
            dict(back.leaves())


def test_a_swapped_leaf_record_is_an_error_naming_the_leaf(tmp_path: Path) -> None:
    path = tmp_path / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(SCANS[:2])
    con = sqlite3.connect(path)
    (_, blob), (key2, _) = con.execute("SELECT key, data FROM leaves LIMIT 2").fetchall()
    con.execute("UPDATE leaves SET data=? WHERE key=?", (blob, key2))
    con.commit()
    con.close()
    match = rf"leaf {key2}: leaf record holds leaf"
    with OnlineMap.open(path, read_only=True) as back, pytest.raises(OctolgpError, match=match):
        dict(back.leaves())


def test_flipped_bytes_in_a_journaled_scan_are_an_error_naming_the_scan(tmp_path: Path) -> None:
    path = tmp_path / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(SCANS[:3])
    con = sqlite3.connect(path)
    (points,) = con.execute("SELECT points FROM scans WHERE idx=2").fetchone()
    flipped = bytearray(points)
    flipped[len(flipped) // 2] ^= 0x10  # one bit of the stored points
    con.execute("UPDATE scans SET points=? WHERE idx=2", (bytes(flipped),))
    con.commit()
    con.close()
    with (
        OnlineMap.open(path) as back,
        pytest.raises(OctolgpError, match="scan 2 fails its checksum"),
    ):
        list(back.scans())


# ---------------------------------------------------------------------- learning
def test_scans_without_returns_keep_the_map_buffering() -> None:
    ang = np.linspace(0.0, np.pi, 90)
    blind = Scan(origin=[0.0, 0.0], points=np.c_[np.cos(ang), np.sin(ang)] * 10.0, max_range=10.0)
    config = MapConfig(dim=2, resolution=0.1)
    with pytest.raises(OctolgpError, match="no return"):
        learn_hyperparameters([blind] * 3, config)
    m = OnlineMap(config)
    for _ in range(config.learn_scans + 2):  # past learn_scans: nothing to learn from yet
        assert m.insert_scan(blind).buffered
    assert m.buffered_scans == m.n_scans == config.learn_scans + 2
    assert m.flush() is None
    assert np.all(m.occupancy([[0.0, 5.0]]) == 0.5)


def test_a_refused_learning_step_leaves_the_buffer_as_it_was() -> None:
    ang = np.linspace(0.0, np.pi, 90)
    blind = Scan(origin=[0.0, 0.0], points=np.c_[np.cos(ang), np.sin(ang)] * 10.0, max_range=10.0)
    m = OnlineMap(MapConfig(dim=2, resolution=0.1))
    m.insert_scans([blind] * 3)
    with pytest.raises(OctolgpError, match="no return"):  # the batch learns first, and cannot
        m.insert_batch([blind])
    assert m.buffered_scans == m.n_scans == 3
    assert m.provisional


# ---------------------------------------------------------------------- reads never write
def test_reading_a_map_never_changes_its_bytes(tmp_path: Path) -> None:
    saved, live = tmp_path / "saved.octolgp", tmp_path / "live.octolgp"
    with OnlineMap(CONFIG, path=live) as m:
        m.insert_scans(SCANS[:3])
        m.save(saved)
    for path in (saved, live):
        before = path.read_bytes()
        for read_only in (True, False):
            with OnlineMap.open(path, read_only=read_only) as m:
                m.occupancy(PROBE)
                list(m.scans())
                m.voxels()
            assert path.read_bytes() == before, (path.name, read_only)
            assert not Path(str(path) + "-wal").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file permissions")
def test_a_read_only_map_in_a_read_only_directory_can_be_queried(tmp_path: Path) -> None:
    folder = tmp_path / "ro"
    folder.mkdir()
    path = folder / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(SCANS[:2])
    path.chmod(0o444)
    folder.chmod(0o555)
    try:
        with pytest.raises(OctolgpError, match="read-only"):
            OnlineMap.open(path)
        with OnlineMap.open(path, read_only=True) as back:
            np.testing.assert_array_equal(values(back), reference(SCANS[:2]))
    finally:
        folder.chmod(0o755)


@pytest.mark.parametrize(
    ("key", "value"), [("config", "null"), ("config", "[1, 2]"), ("hyperparameters", "[1]")]
)
def test_a_map_file_with_a_null_config_is_refused_naming_the_file(
    tmp_path: Path, key: str, value: str
) -> None:
    path = tmp_path / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scan(SCANS[0])
    con = sqlite3.connect(path)
    con.execute("UPDATE meta SET value=? WHERE key=?", (value, key))
    con.commit()
    con.close()
    before = path.read_bytes()
    for read_only in (True, False):
        with pytest.raises(OctolgpError, match=rf"{path.name}.* is corrupt: .*JSON object"):
            OnlineMap.open(path, read_only=read_only)
    assert path.read_bytes() == before


def test_cli_outputs_refuse_existing_files_without_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(SCANS[:2])
    pts = tmp_path / "pts.npy"
    np.save(pts, PROBE)
    sim, prob, pgm = tmp_path / "sim.npz", tmp_path / "p.npy", tmp_path / "map.pgm"
    for p in (sim, prob, pgm.with_suffix(".yaml")):
        p.write_bytes(b"precious")
    commands = [
        ["simulate", "paper2d", "--out", str(sim)],
        ["query", str(path), "--points", str(pts), "--out", str(prob)],
        ["export", str(path), "--out", str(pgm)],  # its sibling map.yaml exists
    ]
    for cmd in commands:
        capsys.readouterr()
        assert main(cmd) == 2
        err = capsys.readouterr().err.strip()
        assert "already exists" in err
        assert len(err.splitlines()) == 1
    for p in (sim, prob, pgm.with_suffix(".yaml")):
        assert p.read_bytes() == b"precious"
    assert not pgm.exists()
    for cmd in commands:
        assert main([*cmd, "--overwrite"]) == 0
    np.testing.assert_array_equal(np.load(prob), reference(SCANS[:2]))


def npz_log(path: Path, scans: list[Scan]) -> Path:
    offsets = np.cumsum([0] + [s.points.shape[0] for s in scans])
    np.savez(
        path,
        origins=np.stack([s.origin for s in scans]),
        points=np.concatenate([s.points for s in scans]),
        offsets=offsets,
    )
    return path


HP_TOML = (
    "[hyperparameters]\nlength_scale = 0.4\nsignal_variance = 1.0\n"
    "noise_variance = 0.05\nalpha = 6.0\nbeta = 0.0\n"
)


def test_cli_resume_refuses_another_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(HP_TOML)
    log_a = npz_log(tmp_path / "a.npz", SCANS[:4])
    log_b = npz_log(tmp_path / "b.npz", SCANS[2:6])
    out = tmp_path / "m.octolgp"
    common = ["--out", str(out), "--config", str(cfg), "--quiet"]
    assert main(["run", str(log_a), *common, "--limit", "2"]) == 0
    capsys.readouterr()
    assert main(["run", str(log_b), *common, "--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert "scan 1 of SCANS is not scan 1" in err
    assert len(err.splitlines()) == 1
    with OnlineMap.open(out, read_only=True) as m:
        assert m.n_scans == 2
    assert main(["run", str(log_a), *common, "--resume"]) == 0
    with OnlineMap.open(out, read_only=True) as m:
        assert m.n_scans == 4
        np.testing.assert_array_equal(values(m), reference(SCANS[:4]))


def test_cli_names_the_scan_it_refuses(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(HP_TOML)
    far = Scan(origin=[0.0, 0.0], points=[[5000.0, 0.0], [1.0, 1.0]])
    log = npz_log(tmp_path / "bad.npz", [SCANS[0], far, SCANS[1]])
    out = tmp_path / "m.octolgp"
    capsys.readouterr()
    assert main(["run", str(log), "--out", str(out), "--config", str(cfg), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "scan 2:" in err
    assert "outside the addressable range" in err
    assert len(err.splitlines()) == 1


def test_an_absurd_resolution_is_refused_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(OctolgpError, match=r"MapConfig.resolution must be at most"):
        MapConfig(resolution=1e308)
    cfg = tmp_path / "c.toml"
    cfg.write_text("resolution = 1e308\n")
    capsys.readouterr()
    assert main(["dump-config", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert "resolution" in err
    assert len(err.splitlines()) == 1
