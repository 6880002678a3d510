"""The map after k scans is a function of those k scans and the config only.

Queries, ``save``, ``export_octomap``, ``voxels``, opening and closing never change
what later inserts produce, in the learning phase (hyperparameters not yet learnt,
``learn_scans`` scans buffered) and after it; a map killed mid-mission and reopened
equals the uninterrupted map of the scans it holds. Default config throughout
(``learn_scans=40``), so the learning phase is the one a new user gets.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from octolgp import MapConfig, OnlineMap, Scan
from octolgp.engines.base import evidence_arrays
from octolgp.mapping.store import Leaf

N_SCANS = 43
CONFIG = MapConfig(dim=2, resolution=0.1)
PROBE = np.array([[0.0, 0.0], [2.9, 0.3], [-1.0, 2.95], [1.5, -1.5], [3.5, 3.5]])


def office_scans(n: int = N_SCANS) -> list[Scan]:
    """A robot circling a 6 x 6 m room with a 0.8 m crate in it; 60 beams per scan."""
    ang = np.linspace(-np.pi, np.pi, 60, endpoint=False)
    d = np.c_[np.cos(ang), np.sin(ang)]
    lo = np.array([[-3.0, -3.0], [0.6, 0.6]])
    hi = np.array([[3.0, 3.0], [1.4, 1.4]])
    scans = []
    for k in range(n):  # one scan per pose
        t = 2 * np.pi * k / n
        o = np.array([1.8 * np.cos(t), 1.8 * np.sin(t)]) - 0.5
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (lo[:, None, :] - o) / d  # (box, beam, axis)
            t1 = (hi[:, None, :] - o) / d
        near = np.minimum(t0, t1).max(axis=2)
        far = np.maximum(t0, t1).min(axis=2)
        # the room's walls: exit distance of the room box; the crate: entry distance
        r = np.minimum(far[0], np.where((near[1] > 0) & (near[1] < far[1]), near[1], np.inf))
        scans.append(Scan(origin=o, points=o + r[:, None] * d))
    return scans


def values(m: OnlineMap) -> dict[int, tuple[bytes, ...]]:
    """Every stored array of every leaf, as bytes."""
    fields = ("mean", "var", "prob")
    return {
        k: (*evidence_bytes(leaf), *(getattr(leaf, f).tobytes() for f in fields))
        for k, leaf in m.leaves()
    }


@pytest.fixture(scope="module")
def scans() -> list[Scan]:
    return office_scans()


@pytest.fixture(scope="module")
def reference(scans: list[Scan]) -> list[tuple[object, dict[int, tuple[bytes, ...]]]]:
    """The untouched map's hyperparameters and leaves after each scan (index k-1)."""
    m = OnlineMap(CONFIG)
    out = []
    for s in scans:  # one insert per scan, nothing else
        m.insert_scan(s)
        out.append((m.hyperparameters, values(m)))
    return out


def test_reads_saves_and_exports_never_change_later_inserts(
    tmp_path: Path, scans: list[Scan], reference: list
) -> None:
    m = OnlineMap(CONFIG)
    for k, s in enumerate(scans, start=1):
        m.insert_scan(s)
        if k in (1, 39, 40, 41, N_SCANS):  # in the learning phase and after
            before = (m.hyperparameters, values(m), m.n_scans, m.buffered_scans)
            p1 = m.occupancy(PROBE)
            m.latent(PROBE, interpolate=False)
            centres, prob = m.voxels()
            m.occupied_voxels()
            planning_reads(m)
            m.export_octomap(tmp_path / f"m{k}.bt")
            m.save(tmp_path / f"m{k}.octolgp")
            assert (m.hyperparameters, values(m), m.n_scans, m.buffered_scans) == before
            assert np.array_equal(m.occupancy(PROBE), p1)  # a read is repeatable
            if k < CONFIG.learn_scans:
                assert m.provisional
                assert m.hyperparameters is None
                assert not list(m.leaves())  # no leaf is fitted while learning
                assert len(m.store) == len(m.store.pending)  # evidence waits, if deferred
                assert centres.shape[0] > 0  # the provisional answer has voxels
                assert ((prob >= 0) & (prob <= 1)).all()
        assert (m.hyperparameters, values(m)) == reference[k - 1]


def planning_reads(m: OnlineMap) -> None:
    """Every planning query once: ray casts, segments, gradients, distance, coarse and box reads."""
    directions = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0], [1.0, 1.0], [0.0, -1.0]])
    for unknown in ("stop", "free", "occupied"):
        m.raycast(PROBE, directions, 4.0, unknown=unknown)
    m.segment_free(PROBE, PROBE[::-1])
    m.segment_free(PROBE, PROBE[::-1], unknown_is_free=True)
    m.gradient(PROBE)
    m.latent_gradient(PROBE)
    m.normals(PROBE)
    m.distance(PROBE)
    m.distance(PROBE, max_distance=1.0)
    m.occupancy(PROBE, depth=13)
    m.voxels(depth=14)
    m.voxels(bbox=([-1.0, -1.0], [1.0, 1.0]))
    m.surface()


def test_provisional_answer_before_any_training_data_is_the_prior() -> None:
    m = OnlineMap(CONFIG)
    m.insert_scan(Scan(origin=[0.0, 0.0], points=np.zeros((3, 2))))  # beams on the sensor
    assert m.provisional
    np.testing.assert_array_equal(m.occupancy(PROBE), 0.5)
    mean, var = m.latent(PROBE)
    np.testing.assert_array_equal(mean, 0.0)
    np.testing.assert_array_equal(var, 1.0)


@pytest.mark.parametrize("reopen_at", [5, 41])
def test_save_close_and_reopen_continue_as_the_uninterrupted_map(
    tmp_path: Path, scans: list[Scan], reference: list, reopen_at: int
) -> None:
    path = tmp_path / "m.octolgp"
    with OnlineMap(CONFIG, path=path) as m:
        m.insert_scans(scans[:reopen_at])
        m.occupancy(PROBE)  # a read in between changes nothing
        m.save(tmp_path / "copy.octolgp")
    for p in (path, tmp_path / "copy.octolgp"):
        with OnlineMap.open(p) as back:
            assert back.n_scans == reopen_at
            assert (back.hyperparameters, values(back)) == reference[reopen_at - 1]
            back.insert_scans(scans[reopen_at:])
            assert (back.hyperparameters, values(back)) == reference[-1]


def test_an_in_memory_map_saved_while_learning_keeps_its_buffer(
    tmp_path: Path, scans: list[Scan], reference: list
) -> None:
    m = OnlineMap(CONFIG)
    m.insert_scans(scans[:10])
    m.save(tmp_path / "early.octolgp")
    with OnlineMap.open(tmp_path / "early.octolgp") as back:
        assert back.buffered_scans == 10
        back.insert_scans(scans[10:])
        assert (back.hyperparameters, values(back)) == reference[-1]


def test_flush_is_the_explicit_way_to_learn_early(scans: list[Scan]) -> None:
    m = OnlineMap(CONFIG)
    m.insert_scans(scans[:10])
    provisional = m.occupancy(PROBE)
    update = m.flush()
    assert update is not None
    assert "learning" in update.stages
    assert m.hyperparameters is not None
    assert not m.provisional
    np.testing.assert_array_equal(m.occupancy(PROBE), provisional)
    assert m.flush() is None


CHILD = """
import sys
sys.path.insert(0, sys.argv[3])
from test_reads_never_change import CONFIG, office_scans
from octolgp import OnlineMap
m = OnlineMap(CONFIG, path=sys.argv[1])
for k, s in enumerate(office_scans(), start=1):
    m.insert_scan(s)
    if k in (6, 41):
        m.occupancy([[0.0, 0.0]])  # reads in between, as a user's program makes them
    print(m.n_scans, flush=True)
    if k == int(sys.argv[2]):
        sys.stdin.readline()  # wait here until killed
"""


@pytest.mark.parametrize("kill_after", [12, 40])
def test_a_killed_map_reopens_as_the_uninterrupted_map(
    tmp_path: Path,
    scans: list[Scan],
    reference: list,
    kill_after: int,
    sigkill_after: Callable[[subprocess.Popen[str], int], None],
) -> None:
    path = tmp_path / "mission.octolgp"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path), str(kill_after), str(Path(__file__).parent)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    sigkill_after(child, kill_after)
    with OnlineMap.open(path) as m:
        k = m.n_scans
        assert k in (kill_after, kill_after + 1)
        assert (m.hyperparameters, values(m)) == reference[k - 1]
        m.insert_scans(scans[k:])
        assert (m.hyperparameters, values(m)) == reference[-1]


def evidence_bytes(leaf: Leaf) -> tuple[bytes, ...]:
    """Every array of a leaf's engine evidence, as bytes."""
    return tuple(a.tobytes() for a in evidence_arrays(leaf.evidence))
