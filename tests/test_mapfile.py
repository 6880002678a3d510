"""Maps that survive: the SQLite map file, eviction under a memory budget, crashes, export."""

from __future__ import annotations

import dataclasses
import math
import sqlite3
import struct
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from test_online import assert_same_map

from octolgp import (
    Hyperparameters,
    LatticeConfig,
    MapConfig,
    OctolgpError,
    OnlineMap,
    load_scans,
)
from octolgp.cli import main
from octolgp.engines import engine_for
from octolgp.engines.base import evidence_arrays
from octolgp.export.octomap_read import decode_bt, read_bt_header
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf
from octolgp.persist.mapfile import VERSION, decode_leaf, encode_leaf

INTEL20 = Path(__file__).parent / "data" / "intel_first20.log"
HP = Hyperparameters(
    length_scale=1.2, signal_variance=3.8, noise_variance=0.006, alpha=4.5, beta=1.0
)
CONFIG = MapConfig(dim=2, resolution=0.1, hyperparameters=HP)
WHOLE = dataclasses.replace(
    CONFIG,
    online=dataclasses.replace(CONFIG.online, halo=0.2),
    lattice=dataclasses.replace(
        CONFIG.lattice,
        tile_voxels=16,
        inducing_spacing=0.3,
        min_inducing_per_axis=8,
        fill_voxels=-1,
        sweep_angle=0.0,
    ),
    training=dataclasses.replace(CONFIG.training, no_return_range=math.inf),
)
"""A 2D map as files from before lattice tiles hold it: leaves of 16 fitted whole (and
every voxel of a leaf filled, every no-return whole, nothing swept between beams, as
then)."""


def _scans() -> list:  # type: ignore[type-arg]
    return list(load_scans(INTEL20))


def _values(m: OnlineMap) -> dict[int, tuple[bytes, ...]]:
    fields = ("mean", "var", "prob")
    return {
        k: (*evidence_bytes(leaf), *(getattr(leaf, f).tobytes() for f in fields))
        for k, leaf in m.leaves()
    }


@pytest.fixture(scope="module")
def reference() -> list[dict[int, tuple[bytes, ...]]]:
    """The in-memory map's leaves after each of the 20 scans."""
    m = OnlineMap(CONFIG)
    out = []
    for s in _scans():
        m.insert_scan(s)
        out.append(_values(m))
    return out


@pytest.mark.parametrize("engine", ["lattice", "exact"])
def test_leaf_encoding_round_trips_and_rejects_corruption(engine: str) -> None:
    config = dataclasses.replace(CONFIG, online=dataclasses.replace(CONFIG.online, engine=engine))
    m = OnlineMap(config)
    m.insert_scans(_scans()[:2])
    codec, grid = engine_for(m.config), LeafGrid.from_config(m.config)
    for _key, leaf in m.leaves():
        blob = encode_leaf(leaf, codec)
        back = decode_leaf(blob, codec, grid)
        assert encode_leaf(back, codec) == blob
        assert evidence_bytes(back) == evidence_bytes(leaf)
        assert np.array_equal(back.index, leaf.index)
        assert (back.refits, back.touched) == (leaf.refits, leaf.touched)
        if engine == "lattice":  # values are refitted from the evidence: not stored
            assert back.pending
            assert back.prob.size == 0
        else:
            assert back.pruned == leaf.pruned
            assert not back.pending
            assert np.array_equal(back.prob, leaf.prob, equal_nan=True)
            assert np.array_equal(back.var, leaf.var, equal_nan=True)
        with pytest.raises(OctolgpError, match=r"bytes|header|truncated|checksum"):
            decode_leaf(blob[:-3], codec, grid)
        with pytest.raises(OctolgpError, match="header"):
            decode_leaf(b"XXXX" + blob[4:], codec, grid)


def test_budget_evicts_to_the_file_and_gives_the_same_map(
    tmp_path: Path, reference: list[dict[int, tuple[bytes, ...]]]
) -> None:
    budget = dataclasses.replace(CONFIG, memory_budget_mb=0.2)
    scans = _scans() + _scans()[:5]  # a revisit loads evicted leaves back
    unbounded = OnlineMap(CONFIG)
    unbounded.insert_scans(scans)
    with OnlineMap(budget, path=tmp_path / "b.octolgp") as m:
        for s in scans:
            m.insert_scan(s)
            assert m.memory_bytes() <= 0.2e6
        assert m.store.evictions > 0
        assert m.store.loads > 0
        assert m.store.resident < len(m.store)
        assert _values(m) == _values(unbounded)


def test_budget_without_a_path_spills_to_a_temporary_file(
    reference: list[dict[int, tuple[bytes, ...]]],
) -> None:
    m = OnlineMap(dataclasses.replace(CONFIG, memory_budget_mb=0.2))
    spill = m._file.path
    assert spill.exists()
    m.insert_scans(_scans())
    assert m.memory_bytes() <= 0.2e6
    assert _values(m) == reference[-1]
    m.close()
    assert not spill.exists()


CHILD = """
import sys
from octolgp import Hyperparameters, MapConfig, OnlineMap, load_scans
hp = Hyperparameters(length_scale=1.2, signal_variance=3.8, noise_variance=0.006, alpha=4.5, beta=1.0)
config = MapConfig(dim=2, resolution=0.1, hyperparameters=hp, memory_budget_mb=float(sys.argv[3]))
m = OnlineMap.open(sys.argv[1]) if sys.argv[4] == "resume" else OnlineMap(config, path=sys.argv[1])
scans = list(load_scans(sys.argv[2]))
for s in scans[m.n_scans:]:
    m.insert_scan(s)
    print(m.n_scans, flush=True)
m.close()
"""


def _child(path: Path, mode: str = "new", budget: float = 0.3) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path), str(INTEL20), str(budget), mode],
        stdout=subprocess.PIPE,
        text=True,
    )


@pytest.mark.parametrize("kill_after", [0, 3, 9, 16])
def test_sigkill_mid_mission_loses_nothing_durable(
    tmp_path: Path,
    kill_after: int,
    reference: list[dict[int, tuple[bytes, ...]]],
    sigkill_after: Callable[[subprocess.Popen[str], int], None],
) -> None:
    path = tmp_path / "mission.octolgp"
    sigkill_after(_child(path), kill_after)
    if kill_after == 0 and not path.exists():
        return  # killed before the file existed: nothing to check
    with OnlineMap.open(path) as m:
        assert m.n_scans >= kill_after  # every returned insert is durable
        assert len(list(m._file.scans())) == m.n_scans
        if m.n_scans:
            assert _values(m) == reference[m.n_scans - 1]
    resumed = _child(path, "resume")
    resumed.communicate(timeout=300)
    assert resumed.returncode == 0
    with OnlineMap.open(path) as m:
        assert m.n_scans == 20
        assert _values(m) == reference[-1]


def test_open_refuses_foreign_and_corrupt_files_without_writing(tmp_path: Path) -> None:
    foreign = tmp_path / "foreign.sqlite"
    con = sqlite3.connect(foreign)
    con.execute("CREATE TABLE meta(key TEXT, value TEXT)")
    con.execute("INSERT INTO meta VALUES ('format', 'something-else')")
    con.commit()
    con.close()
    before = foreign.read_bytes()
    with pytest.raises(OctolgpError, match="not an octolgp map"):
        OnlineMap.open(foreign)
    assert foreign.read_bytes() == before

    good = tmp_path / "good.octolgp"
    with OnlineMap(CONFIG, path=good) as m:
        m.insert_scans(_scans()[:3])
    truncated = tmp_path / "cut.octolgp"
    truncated.write_bytes(good.read_bytes()[:3000])

    def open_and_read(path: Path) -> None:
        with OnlineMap.open(path) as m2:
            list(m2.leaves())

    with pytest.raises(OctolgpError):
        open_and_read(truncated)
    for name, payload in [("empty.octolgp", b""), ("zeros.octolgp", bytes(8192))]:
        (tmp_path / name).write_bytes(payload)
        with pytest.raises(OctolgpError, match="not an octolgp map"):
            OnlineMap.open(tmp_path / name)
    # a corrupt leaf record is named when it is read
    con = sqlite3.connect(good)
    key = con.execute("SELECT key FROM leaves LIMIT 1").fetchone()[0]
    con.execute("UPDATE leaves SET data=? WHERE key=?", (b"garbage", key))
    con.commit()
    con.close()
    with OnlineMap.open(good) as m, pytest.raises(OctolgpError, match=f"leaf {key}"):
        list(m.leaves())


def test_export_bt_is_read_by_octomap(tmp_path: Path) -> None:
    octomap = pytest.importorskip("pyoctomap", exc_type=ImportError)
    m = OnlineMap(CONFIG)
    m.insert_scans(_scans()[:6])
    bt = tmp_path / "m.bt"
    nodes = m.export_octomap(bt)
    assert read_bt_header(bt)["size"] == nodes  # decoder-free check
    tree = octomap.OcTree(0.1)
    tree.readBinary(str(bt))
    assert tree.size() == nodes
    centres, prob = m.voxels()
    rng = np.random.default_rng(0)
    for i in rng.choice(centres.shape[0], 300, replace=False):
        x, y = centres[i]
        node = tree.search((float(x), float(y), 0.05))
        assert node is not None
        assert tree.isNodeOccupied(node) == bool(prob[i] > 0.5)
    assert tree.search((500.0, 500.0, 0.05)) is None  # unknown stays unknown
    keys, occupied, _ = decode_bt(bt, expand=True)
    assert keys.shape[0] == centres.shape[0]
    assert int(occupied.sum()) == int((prob > 0.5).sum())


def test_cli_export_and_resume(tmp_path: Path) -> None:
    out = tmp_path / "m.octolgp"
    common = ["--quiet", "--learn-scans", "5"]
    assert main(["run", str(INTEL20), "--out", str(out), "--limit", "8", *common]) == 0
    assert main(["run", str(INTEL20), "--out", str(out), *common]) == 2  # exists
    assert main(["run", str(INTEL20), "--out", str(out), "--resume", *common]) == 0
    full = tmp_path / "full.octolgp"
    assert main(["run", str(INTEL20), "--out", str(full), *common]) == 0
    with OnlineMap.open(out) as a, OnlineMap.open(full) as b:
        assert a.n_scans == b.n_scans == 20
        assert _values(a) == _values(b)
    for suffix in (".bt", ".ot", ".ply", ".png"):
        target = tmp_path / f"m{suffix}"
        assert main(["export", str(out), "--out", str(target)]) == 0
        assert target.stat().st_size > 100
    assert main(["export", str(out), "--out", str(tmp_path / "m.txt")]) == 2


def test_reopened_budget_map_evicts_into_its_own_file(
    tmp_path: Path, reference: list[dict[int, tuple[bytes, ...]]]
) -> None:
    import tempfile

    path = tmp_path / "b.octolgp"
    budget = dataclasses.replace(CONFIG, memory_budget_mb=0.2)
    with OnlineMap(budget, path=path) as m:
        m.insert_scans(_scans()[:10])
    spills = set(Path(tempfile.gettempdir()).glob("octolgp-*.octolgp"))
    with OnlineMap.open(path) as m:
        assert m._file.path == path
        assert m.store.resident == 0  # leaves are read lazily
        m.insert_scans(_scans()[10:])
        assert m.memory_bytes() <= 0.2e6
        assert _values(m) == reference[-1]
    assert set(Path(tempfile.gettempdir()).glob("octolgp-*.octolgp")) == spills


def _old_record(leaf: object, version: int) -> bytes:
    """A leaf in the record layout of versions 1 and 2 (both engines' arrays in one)."""
    import struct

    ev = leaf.evidence  # type: ignore[attr-defined]
    d = leaf.index.size  # type: ignore[attr-defined]
    none = np.zeros((0, d))
    hits, hit_keys = ev.hits, ev.hit_keys
    fs, fe, fk = (getattr(ev, n, none) for n in ("free_start", "free_end", "free_keys"))
    counts = getattr(ev, "counts", np.zeros((2, 0), np.uint8))
    head = struct.pack(
        "<4sBBxxqqqqqq", b"OLGL", version, d, hits.shape[0], fs.shape[0],
        leaf.prob.size, int(leaf.pruned), leaf.refits, leaf.touched,  # type: ignore[attr-defined]
    )  # fmt: skip
    parts = [
        leaf.index.astype("<i8"),  # type: ignore[attr-defined]
        hits.astype("<f8"), hit_keys.astype("<i8"), fs.astype("<f8"), fe.astype("<f8"),
        np.asarray(fk, dtype="<i8"), leaf.mean.astype("<f4"),  # type: ignore[attr-defined]
        leaf.var.astype("<f4"), leaf.prob.astype("<f4"),  # type: ignore[attr-defined]
    ]  # fmt: skip
    if version == 2:
        head += struct.pack("<q", counts.shape[1])
        parts.append(np.ascontiguousarray(counts, dtype=np.uint8))
    return head + b"".join(p.tobytes() for p in parts)


@pytest.mark.parametrize(("engine", "version"), [("exact", 1), ("exact", 2), ("lattice", 2)])
def test_old_leaf_records_still_read(engine: str, version: int) -> None:
    """Leaf records of file version 2 (records 1 and 2) decode to the same leaves."""
    config = dataclasses.replace(CONFIG, online=dataclasses.replace(CONFIG.online, engine=engine))
    if engine == "exact":  # such files filled every voxel: their leaves kept no seen mask
        config = dataclasses.replace(config, lattice=LatticeConfig(fill_voxels=-1))
    m = OnlineMap(config)
    m.insert_scans(_scans()[:2])
    codec, grid = engine_for(m.config), LeafGrid.from_config(m.config)
    for _key, leaf in m.leaves():
        back = decode_leaf(_old_record(leaf, version), codec, grid)
        assert not back.fitted  # values of unknown provenance: a rewrite keeps them
        assert encode_leaf(back.evolve(fitted=True), codec) == encode_leaf(leaf, codec)
        assert evidence_bytes(back) == evidence_bytes(leaf)
        assert back.prob.tobytes() == leaf.prob.tobytes()


def _as_version_2(path: Path, meta_clear_scans: int | None) -> None:
    """Rewrite a map file's meta as file version 2 wrote it: derived fields left out,
    the engines' settings in ``online``, and ``clear_scans`` pinned in its own row."""
    import json

    con = sqlite3.connect(path)
    stored = json.loads(con.execute("SELECT value FROM meta WHERE key = 'config'").fetchone()[0])
    online = stored["online"]
    for name in ("leaf_depth", "learn_scans", "clear_scans"):
        online.pop(name, None)
    lattice, exact = stored.pop("lattice"), stored.pop("exact")
    names = ("inducing_spacing", "max_inducing_per_axis", "clear_margin", "tile_voxels")
    later = ("min_inducing_per_axis", "fill_voxels", "sweep_angle", "free_evidence", "chord_weight")
    for name in (*names, *later):  # came later
        lattice.pop(name, None)
    stored["training"].pop("no_return_range", None)  # as did this
    online.update(lattice, **exact, prune_free=0.1192, prune_occupied=0.971)
    online.update(kernel_cache_mb=64.0, max_inducing_per_axis=0)
    stored["learning"].update(balance_classes=False, min_noise_variance=0.01)
    stored["training"].pop("free_margin", None)
    con.execute("UPDATE meta SET value = ? WHERE key = 'config'", (json.dumps(stored),))
    con.execute("UPDATE meta SET value = '2' WHERE key = 'version'")
    if meta_clear_scans is not None:
        con.execute("INSERT INTO meta VALUES ('clear_scans', ?)", (str(meta_clear_scans),))
    con.commit()
    con.close()


def test_a_map_file_stores_its_resolved_config_whole(tmp_path: Path) -> None:
    """Every derived default is written, so the file does not depend on the code's defaults."""
    import json

    path = tmp_path / "m.octolgp"
    with OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP), path=path) as m:
        m.insert_scans(_scans()[:2])
    con = sqlite3.connect(path)
    stored = json.loads(con.execute("SELECT value FROM meta WHERE key = 'config'").fetchone()[0])
    con.close()
    assert stored["online"]["leaf_depth"] == 12
    assert stored["online"]["learn_scans"] == 40
    assert stored["online"]["clear_scans"] == 5
    assert stored["lattice"]["inducing_spacing"] == 0.4
    assert stored["lattice"]["max_inducing_per_axis"] == 12
    assert stored["lattice"]["clear_margin"] == pytest.approx(0.5)
    assert stored["training"]["free_margin"] == 0.1
    assert MapConfig.from_dict(stored) == m.config == CONFIG.resolve()


def test_a_reopened_map_keeps_its_config_when_the_defaults_change(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file written under one set of defaults reopens identically under another."""
    from octolgp import config as config_module

    path = tmp_path / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(_scans()[:4])
        before, config = _values(m), m.config
        probe = np.random.default_rng(0).uniform(-5, 5, (200, 2))
        p_before = m.occupancy(probe)
    changed = {(2, "lattice"): 3, (2, "exact"): 3, (3, "lattice"): 1, (3, "exact"): 2}
    monkeypatch.setattr(config_module, "LEAF_VOXELS_LOG2", changed)
    monkeypatch.setattr(config_module, "DEFAULT_CLEAR_SCANS", 9)
    monkeypatch.setattr(config_module, "CLEAR_MARGIN_VOXELS", 2)
    monkeypatch.setattr(config_module, "DEFAULT_LEARN_SCANS", {2: 7, 3: 2})
    monkeypatch.setattr(config_module, "DEFAULT_INDUCING_SPACING", {2: 0.5, 3: 0.7})
    monkeypatch.setattr(config_module, "DEFAULT_MAX_INDUCING", {2: 6, 3: 3})
    assert CONFIG.resolve() != config  # the code's defaults did change
    with OnlineMap.open(path) as m:
        assert m.config == config
        assert _values(m) == before
        np.testing.assert_array_equal(m.occupancy(probe), p_before)
        m.insert_scan(_scans()[4])  # and it goes on mapping by its own rules
        assert m.config.clear_scans == 5


def test_a_version_2_map_file_reopens_as_it_did(tmp_path: Path) -> None:
    """A file of the previous layout (derived fields dropped; 2D leaves fitted whole, as
    before tiles) reopens with today's resolution."""
    path = tmp_path / "v2.octolgp"
    with OnlineMap(WHOLE, path=path) as m:
        m.insert_scans(_scans()[:3])
        before = _values(m)
    _as_version_2(path, meta_clear_scans=5)
    with OnlineMap.open(path) as m:
        assert m.config == WHOLE.resolve()
        assert _values(m) == before
        m.insert_scan(_scans()[3])
    con = sqlite3.connect(path)  # a write brings the file to today's version
    assert con.execute("SELECT value FROM meta WHERE key = 'version'").fetchone()[0] == str(VERSION)
    con.close()


def test_a_map_file_from_before_newer_evidence_won_reopens_static(tmp_path: Path) -> None:
    """Files without a resolved ``clear_scans`` hold static counts and keep that rule."""
    path = tmp_path / "static.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(_scans()[:3])
        assert m.config.clear_scans == 5
    with OnlineMap.open(path) as m:  # a file of today keeps its rule and its config
        assert m.config == CONFIG.resolve()
    _as_version_2(path, meta_clear_scans=None)
    with OnlineMap.open(path) as m:
        assert m.config.online.clear_scans == 0


def test_a_map_file_from_before_the_lattice_engine_reopens_exact(tmp_path: Path) -> None:
    """Files whose config names no engine hold exact-engine leaves and reopen as such."""
    import json

    exact = dataclasses.replace(CONFIG, online=dataclasses.replace(CONFIG.online, engine="exact"))
    path = tmp_path / "old.octolgp"
    with OnlineMap(exact, path=path) as m:
        m.insert_scans(_scans()[:3])
        before = _values(m)
    _as_version_2(path, meta_clear_scans=0)
    con = sqlite3.connect(path)
    stored = json.loads(con.execute("SELECT value FROM meta WHERE key = 'config'").fetchone()[0])
    del stored["online"]["engine"]
    con.execute("UPDATE meta SET value = ? WHERE key = 'config'", (json.dumps(stored),))
    con.commit()
    con.close()
    with OnlineMap.open(path) as m:
        assert m.config.online.engine == "exact"
        assert _values(m) == before
        m.insert_scan(_scans()[3])  # and it goes on mapping with its engine
        assert all(type(leaf.evidence).__name__ == "ExactEvidence" for _, leaf in m.leaves())


def evidence_bytes(leaf: Leaf) -> tuple[bytes, ...]:
    """Every array of a leaf's engine evidence, as bytes."""
    return tuple(a.tobytes() for a in evidence_arrays(leaf.evidence))


def test_a_2d_map_file_of_whole_leaves_reopens_as_it_was(tmp_path: Path) -> None:
    """2D lattice files from before tiles (no ``tile_voxels``) fitted each 16 x 16 leaf as
    one GP; they reopen and go on mapping so, in version 2 form too."""
    import json

    scans = _scans()
    path = tmp_path / "old2d.octolgp"
    with OnlineMap(WHOLE, path=path) as m:
        m.insert_scans(scans[:3])
        before = _values(m)
    with OnlineMap(WHOLE) as fresh:  # what the old code made of four scans
        fresh.insert_scans(scans[:4])
        four = _values(fresh)
    con = sqlite3.connect(path)
    stored = json.loads(con.execute("SELECT value FROM meta WHERE key = 'config'").fetchone()[0])
    del stored["lattice"]["tile_voxels"], stored["lattice"]["min_inducing_per_axis"]
    con.execute("UPDATE meta SET value = ? WHERE key = 'config'", (json.dumps(stored),))
    con.commit()
    con.close()
    with OnlineMap.open(path) as m:
        assert m.config.tile_voxels == 16
        assert _values(m) == before
        m.insert_scan(scans[3])
        assert _values(m) == four
    _as_version_2(path, meta_clear_scans=5)
    with OnlineMap.open(path) as m:
        assert m.config.tile_voxels == 16
        assert _values(m) == four


def test_a_3d_map_file_of_leaves_of_four_reopens_as_it_was(tmp_path: Path) -> None:
    """3D lattice files from before tiles (leaves of 4 voxels, no ``tile_voxels``) reopen with
    their leaves, fitted as one tile each; a version 2 file (no ``leaf_depth``) too."""
    import json

    from octolgp.sim.lidar3d import simulate_lidar_room

    room = simulate_lidar_room(3, seed=1, n_azimuth=128, n_elevation=8, max_range=8.0, n_heldout=1)
    scans = [s.downsample(0.2) for s in room.scans()]
    config = MapConfig(  # the lattice of then: one point per 3 voxels of the halo box
        dim=3,
        resolution=0.2,
        hyperparameters=HP,
        lattice=LatticeConfig(fill_voxels=-1, min_inducing_per_axis=2, free_evidence="looks"),
    )
    old = dataclasses.replace(config, online=dataclasses.replace(config.online, leaf_depth=14))
    path = tmp_path / "old3d.octolgp"
    with OnlineMap(old, path=path) as m:
        m.insert_scans(scans[:2])
        before = _values(m)
    con = sqlite3.connect(path)
    stored = json.loads(con.execute("SELECT value FROM meta WHERE key = 'config'").fetchone()[0])
    del stored["lattice"]["tile_voxels"], stored["lattice"]["min_inducing_per_axis"]
    con.execute("UPDATE meta SET value = ? WHERE key = 'config'", (json.dumps(stored),))
    con.commit()
    con.close()
    with OnlineMap.open(path) as m:
        assert m.config.leaf_depth == 14
        assert m.config.tile_voxels == 4
        assert _values(m) == before
        m.insert_scan(scans[2])
        after = _values(m)
    _as_version_2(path, meta_clear_scans=5)
    with OnlineMap.open(path) as m:
        assert (m.config.leaf_depth, m.config.tile_voxels) == (14, 4)
        assert _values(m) == after


def _write_version_4(path: Path, m: OnlineMap, scans: list) -> None:  # type: ignore[type-arg]
    """``m`` (unrounded scans) as file version 4 wrote it: every voxel value in record 4,
    the evidence at full precision, the journal in float64, no checkpoints, and a config
    without the settings that came later."""
    import json
    import zlib

    engine = engine_for(m.config)
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL)")
    con.execute("CREATE TABLE leaves(key INTEGER PRIMARY KEY, data BLOB NOT NULL)")
    con.execute(
        "CREATE TABLE scans(idx INTEGER PRIMARY KEY, dim INTEGER NOT NULL, origin BLOB NOT NULL, "
        "points BLOB NOT NULL, max_range REAL, stamp REAL, crc INTEGER)"
    )
    stored = m.config.to_dict()
    stored["online"].pop("scan_precision", None)  # None: to_dict leaves them out anyway
    stored["online"].pop("journal_scans", None)
    hp = m.hyperparameters
    assert hp is not None
    meta = [
        ("format", "octolgp-map"),
        ("version", "4"),
        ("config", json.dumps(stored)),
        ("hyperparameters", json.dumps(dataclasses.asdict(hp))),
        ("n_scans", str(len(scans))),
    ]
    con.executemany("INSERT INTO meta VALUES (?, ?)", meta)
    for k, leaf in m.leaves():
        head = struct.pack(
            "<4sBBxxqqqq", b"OLGL", 4, leaf.index.size, leaf.prob.size, int(leaf.pruned),
            leaf.refits, leaf.touched,
        )  # fmt: skip
        parts = [
            leaf.index.astype("<i8"),
            *(a.astype("<f4") for a in (leaf.mean, leaf.var, leaf.prob)),
        ]
        body = head + b"".join(p.tobytes() for p in parts) + engine.encode(leaf.evidence)
        con.execute(
            "INSERT INTO leaves VALUES (?, ?)", (k, body + struct.pack("<I", zlib.crc32(body)))
        )
    for i, s in enumerate(scans, start=1):
        origin, points = s.origin.astype("<f8").tobytes(), s.points.astype("<f8").tobytes()
        crc = zlib.crc32(
            points, zlib.crc32(origin, zlib.crc32(f"{s.dim}|{s.max_range!r}|{s.stamp!r}".encode()))
        )
        con.execute(
            "INSERT INTO scans VALUES (?, ?, ?, ?, ?, ?, ?)",
            (i, s.dim, origin, points, s.max_range, s.stamp, crc),
        )
    con.commit()
    con.close()


def test_a_version_4_file_reads_as_written_and_goes_on_in_the_new_records(tmp_path: Path) -> None:
    """Files of version 4 keep every voxel value and float64 scans: they read back exactly,
    keep scans as given (no rounding, every scan journaled) and take new scans."""
    old = dataclasses.replace(
        CONFIG, online=dataclasses.replace(CONFIG.online, scan_precision=None, journal_scans=None)
    )
    scans = _scans()
    m = OnlineMap(old)
    m.insert_scans(scans[:6])
    path = tmp_path / "v4.octolgp"
    _write_version_4(path, m, scans[:6])
    with OnlineMap.open(path, read_only=True) as back:
        assert back.config.online.scan_precision is None
        assert back.config.online.journal_scans is None
        assert _values(back) == _values(m)  # the stored values, not refits
        assert [s.points.tobytes() for s in back.scans()] == [s.points.tobytes() for s in scans[:6]]
    with OnlineMap.open(path) as back:
        back.insert_scans(scans[6:10])
        m.insert_scans(scans[6:10])
        assert_same_map(back, m)
        back.correct_scans({3: np.eye(3)})
    with OnlineMap.open(path, read_only=True) as again:
        assert_same_map(again, m)
        assert len(list(again.scans())) == 10
