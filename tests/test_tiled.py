"""Whole-log tiled builds: local threads, a 2-worker Dask LocalCluster, and the CLI."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from octolgp import MapConfig, OctolgpError, OnlineMap, build_map, learn_hyperparameters
from octolgp.batch.leafmap import build_tiled
from octolgp.cli import main
from octolgp.engines.base import evidence_arrays
from octolgp.io import load_scans
from octolgp.mapping.store import Leaf

INTEL20 = Path(__file__).parent / "data" / "intel_first20.log"


@pytest.fixture(scope="module")
def scans() -> list:
    return list(load_scans(INTEL20))


@pytest.fixture(scope="module")
def config(scans: list) -> MapConfig:
    cfg = MapConfig(dim=2, resolution=0.2)
    return dataclasses.replace(cfg, hyperparameters=learn_hyperparameters(scans[:10], cfg))


LATTICE_TOLERANCE = 1e-6
"""The lattice engine fits many leaves per BLAS call, and a leaf fitted beside other
leaves (another batch on another worker) may round differently: its float32 voxel
values agree to a few float32 ulps. The exact engine fits each leaf alone: bit for bit."""


def _assert_same_map(a: OnlineMap, b: OnlineMap) -> None:
    leaves_a, leaves_b = dict(a.leaves()), dict(b.leaves())  # with their values
    keys_a = list(leaves_a)
    assert keys_a == list(leaves_b)
    exact = a.config.online.engine == "exact"
    for k in keys_a:
        la, lb = leaves_a[k], leaves_b[k]
        assert evidence_bytes(la) == evidence_bytes(lb), k  # the evidence: bit for bit
        for name in ("mean", "var", "prob"):
            x, y = getattr(la, name), getattr(lb, name)
            if exact:
                assert np.array_equal(x, y), (k, name)
            else:
                np.testing.assert_allclose(x, y, rtol=0, atol=LATTICE_TOLERANCE, err_msg=name)
        assert la.pruned == lb.pruned


@pytest.fixture(scope="module")
def local(scans: list, config: MapConfig) -> OnlineMap:
    return build_tiled(scans, config)


def test_tiled_build_equals_the_online_map_of_the_same_scans(
    scans: list, config: MapConfig, local: OnlineMap
) -> None:
    online = OnlineMap(config)
    online.insert_scans(scans)
    _assert_same_map(local, online)
    assert local.n_scans == online.n_scans == len(scans)
    stats = local.build_stats
    assert stats["leaves"] == len(local.store)
    assert stats["items"] > 0


def test_threads_give_the_same_map(scans: list, config: MapConfig, local: OnlineMap) -> None:
    _assert_same_map(local, build_tiled(scans, config, n_jobs=2, task_items=500))


def test_two_worker_dask_cluster_gives_the_same_map(
    scans: list, config: MapConfig, local: OnlineMap
) -> None:
    distributed = pytest.importorskip("distributed")
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        remote = build_map(scans, config, method="leaf", scheduler=client)
        assert isinstance(remote, OnlineMap)
        _assert_same_map(local, remote)
        # the work really ran on both workers, in many small tasks
        assert len(client.scheduler_info()["workers"]) == 2
        tiny = build_tiled(scans, config, scheduler=client, task_items=200)
        _assert_same_map(local, tiny)


def test_tiled_map_is_a_normal_map_that_takes_more_scans(
    scans: list, config: MapConfig, tmp_path: Path
) -> None:
    path = tmp_path / "m.octolgp"
    m = build_tiled(scans[:12], config, path=path)
    m.close()
    with OnlineMap.open(path) as reopened:
        assert reopened.n_scans == 12
        reopened.insert_scans(scans[12:])
        whole = build_tiled(scans, config)
        _assert_same_map(reopened, whole)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"scheduler": 42}, "scheduler"),
        ({"n_jobs": 0}, "n_jobs"),
        ({"task_items": 0}, "task_items"),
    ],
)
def test_bad_build_arguments_are_refused(
    scans: list, config: MapConfig, kwargs: dict, field: str
) -> None:
    with pytest.raises(OctolgpError, match=field):
        build_tiled(scans, config, **kwargs)


@pytest.mark.parametrize("method", ["lgp", "leaf"])
def test_a_scheduler_never_changes_what_is_computed(
    scans: list, config: MapConfig, method: str
) -> None:
    """The same build_map call, in-process and on a 2-worker LocalCluster."""
    distributed = pytest.importorskip("distributed")
    scans = scans[:10]
    here = build_map(scans, config, method=method)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        there = build_map(scans, config, method=method, scheduler=client)
    assert type(there) is type(here)
    assert there.hyperparameters == here.hyperparameters
    lo = np.min([s.points.min(axis=0) for s in scans], axis=0)
    hi = np.max([s.points.max(axis=0) for s in scans], axis=0)
    g = np.stack(np.meshgrid(*(np.linspace(a, b, 60) for a, b in zip(lo, hi, strict=True))), -1)
    pts = g.reshape(-1, 2)
    np.testing.assert_allclose(there.occupancy(pts), here.occupancy(pts), rtol=0, atol=1e-9)
    for a, b in zip(there.latent(pts), here.latent(pts), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    if method == "leaf":
        assert isinstance(here, OnlineMap)
        assert isinstance(there, OnlineMap)
        _assert_same_map(here, there)


def test_lgp_and_leaf_are_two_methods(scans: list, config: MapConfig) -> None:
    """The paper's k-means map and the leaf map have their own names and types."""
    assert not isinstance(build_map(scans[:5], config, method="lgp"), OnlineMap)
    assert isinstance(build_map(scans[:5], config, method="leaf"), OnlineMap)


def test_scheduler_needs_a_scheduled_method_and_scans(scans: list, config: MapConfig) -> None:
    for method in ("gp", "mgp", "ogm"):
        with pytest.raises(OctolgpError, match="only methods lgp, leaf run on Dask"):
            build_map(scans, config, method=method, scheduler="local")
    with pytest.raises(OctolgpError, match="scans is empty"):
        build_tiled([], config)


def test_cli_build_writes_the_map_and_refuses_to_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "b.octolgp"
    argv = ["build", str(INTEL20), "--out", str(out), "--resolution", "0.2", "--quiet"]
    assert main([*argv, "--learn-scans", "10", "--jobs", "2"]) == 0
    assert "wrote" in capsys.readouterr().out
    assert not (tmp_path / "b.octolgp.partial").exists()
    run_out = tmp_path / "r.octolgp"
    run = ["run", str(INTEL20), "--out", str(run_out), "--resolution", "0.2", "--quiet"]
    run += ["--learn-scans", "10"]
    assert main(run) == 0
    with OnlineMap.open(out) as built, OnlineMap.open(run_out) as ran:
        _assert_same_map(built, ran)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "already exists" in err[0]


def test_build_method_ogm_stores_the_grid_at_the_voxel_centres(scans: list, tmp_path: Path) -> None:
    out = tmp_path / "g.octolgp"
    argv = ["build", str(INTEL20), "--out", str(out), "--resolution", "0.2", "--quiet"]
    assert main([*argv, "--method", "ogm"]) == 0
    grid = build_map(scans, MapConfig(dim=2, resolution=0.2), method="ogm")
    with OnlineMap.open(out) as m:
        assert m.n_scans == len(scans)
        centres, prob = m.voxels()
        expected = grid.occupancy(centres).astype(np.float32)
        assert np.array_equal(prob.astype(np.float32), expected)
        # no hyperparameters: queries read the voxel holding the point
        assert np.array_equal(m.occupancy(centres[:50]), prob[:50])
    assert main([*argv, "--overwrite", "--method", "ogm", "--scheduler", "local"]) == 2


def evidence_bytes(leaf: Leaf) -> tuple[bytes, ...]:
    """Every array of a leaf's engine evidence, as bytes."""
    return tuple(a.tobytes() for a in evidence_arrays(leaf.evidence))
