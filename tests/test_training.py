"""Scans to training data, and validation of Scan and MapConfig at the boundary."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolgp.config import (
    Hyperparameters,
    LearningConfig,
    MapConfig,
    OgmConfig,
    PartitionConfig,
    TrainingConfig,
)
from octolgp.errors import OctolgpError
from octolgp.scan import Scan
from octolgp.training import make_training_data

NO_DEDUP = TrainingConfig(dedup=False)


def _random_scan(rng: np.random.Generator, d: int, n: int, **kwargs: object) -> Scan:
    origin = rng.uniform(-1, 1, d)
    direction = rng.normal(size=(n, d))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = origin + rng.uniform(0.5, 6.0, (n, 1)) * direction
    return Scan(origin=origin, points=points, **kwargs)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# --------------------------------------------------------------------------- hits and segments


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("free_margin", [None, 0.25])
def test_hits_are_endpoints_and_segments_stop_short(d: int, free_margin: float | None) -> None:
    rng = np.random.default_rng(d)
    scans = [_random_scan(rng, d, 50) for _ in range(3)]
    config = MapConfig(
        dim=d, resolution=0.1, training=TrainingConfig(dedup=False, free_margin=free_margin)
    )
    margin = 0.1 if free_margin is None else free_margin
    data = make_training_data(scans, config)
    ends = np.concatenate([s.points for s in scans])
    origins = np.repeat([s.origin for s in scans], 50, axis=0)
    np.testing.assert_array_equal(data.hits, ends)
    np.testing.assert_array_equal(data.seg_hit, np.arange(150))
    np.testing.assert_array_equal(data.seg_start, origins)
    # the segment runs from the origin toward the hit and stops free_margin short of it
    np.testing.assert_allclose(np.linalg.norm(data.hits - data.seg_end, axis=1), margin, rtol=1e-12)
    np.testing.assert_allclose(
        _unit(data.seg_end - data.seg_start), _unit(ends - origins), atol=1e-12
    )
    np.testing.assert_allclose(
        np.linalg.norm(data.seg_end - data.seg_start, axis=1),
        np.linalg.norm(ends - origins, axis=1) - margin,
        rtol=1e-12,
    )
    assert data.dim == d
    assert data.n_items == 300


def test_beam_shorter_than_free_margin_gives_only_a_hit() -> None:
    scan = Scan(origin=[0.0, 0.0], points=[[0.05, 0.0], [2.0, 0.0], [0.0, 0.0]])
    data = make_training_data([scan], MapConfig(dim=2, resolution=0.1, training=NO_DEDUP))
    # the endpoint on the sensor has no direction: neither hit nor segment
    np.testing.assert_array_equal(data.hits, [[0.05, 0.0], [2.0, 0.0]])
    np.testing.assert_array_equal(data.seg_hit, [1])
    np.testing.assert_allclose(data.seg_end, [[1.9, 0.0]])


@pytest.mark.parametrize("d", [2, 3])
def test_no_return_beams_give_a_max_range_segment_and_no_hit(d: int) -> None:
    rng = np.random.default_rng(10 + d)
    origin = rng.uniform(-1, 1, d)
    direction = _unit(rng.normal(size=(6, d)))
    lengths = np.array([1.0, 4.99, 5.0, 5.01, 8.0, 40.0])  # >= 5 is a no-return
    scan = Scan(origin=origin, points=origin + lengths[:, None] * direction, max_range=5.0)
    data = make_training_data([scan], MapConfig(dim=d, resolution=0.1, training=NO_DEDUP))
    np.testing.assert_array_equal(data.hits, scan.points[:2])
    np.testing.assert_array_equal(data.seg_hit, [0, 1, -1, -1, -1, -1])
    seg_len = np.linalg.norm(data.seg_end - data.seg_start, axis=1)
    np.testing.assert_allclose(seg_len, [0.9, 4.89, 5.0, 5.0, 5.0, 5.0], rtol=1e-12)
    np.testing.assert_allclose(_unit(data.seg_end - data.seg_start), direction, atol=1e-12)


def test_from_ranges_at_max_range_are_no_returns() -> None:
    angles = np.linspace(0.0, 2.0 * np.pi, 1000, endpoint=False)
    scan = Scan.from_ranges([0.3, 0.7, 0.1], np.full(1000, 6.0), angles, max_range=6.0)
    data = make_training_data([scan], MapConfig(dim=2, resolution=0.1, training=NO_DEDUP))
    assert data.hits.shape[0] == 0
    assert np.all(data.seg_hit == -1)


def _voxels(points: np.ndarray, resolution: float) -> np.ndarray:
    return np.floor(points / resolution).astype(np.int64)


@pytest.mark.parametrize("d", [2, 3])
def test_dedup_keeps_one_hit_and_one_segment_per_voxel(d: int) -> None:
    """Hits: the first per voxel, every voxel kept. Segments: one per voxel of the end."""
    rng = np.random.default_rng(20 + d)
    res = 0.5
    scans = [_random_scan(rng, d, 200) for _ in range(4)]
    raw = make_training_data(scans, MapConfig(dim=d, resolution=res, training=NO_DEDUP))
    data = make_training_data(scans, MapConfig(dim=d, resolution=res))

    hit_vox = _voxels(data.hits, res)
    raw_hit_vox = _voxels(raw.hits, res)
    assert np.unique(hit_vox, axis=0).shape[0] == data.hits.shape[0]
    np.testing.assert_array_equal(np.unique(hit_vox, axis=0), np.unique(raw_hit_vox, axis=0))
    assert data.hits.shape[0] < raw.hits.shape[0]  # the dedup did something
    for h, v in zip(data.hits, hit_vox, strict=True):  # the first hit in time is kept
        first = np.flatnonzero((raw_hit_vox == v).all(axis=1))[0]
        np.testing.assert_array_equal(h, raw.hits[first])

    end_vox = _voxels(data.seg_end, res)
    assert np.unique(end_vox, axis=0).shape[0] == data.seg_end.shape[0]
    np.testing.assert_array_equal(
        np.unique(end_vox, axis=0), np.unique(_voxels(raw.seg_end, res), axis=0)
    )
    # each kept segment points at the kept hit of its own beam's hit voxel
    own_hit = data.seg_end + 0.5 * _unit(data.seg_end - data.seg_start)  # margin = resolution
    np.testing.assert_array_equal(_voxels(data.hits[data.seg_hit], res), _voxels(own_hit, res))


def test_dedup_keeps_no_return_segments_unlinked() -> None:
    scan = Scan(origin=[0.0, 0.0], points=[[10.0, 0.0], [0.0, 10.0], [1.0, 1.0]], max_range=5.0)
    data = make_training_data([scan], MapConfig(dim=2, resolution=0.1))
    assert data.hits.shape == (1, 2)
    np.testing.assert_array_equal(np.sort(data.seg_hit), [-1, -1, 0])


def test_dimension_mismatch_names_map_dim() -> None:
    scan = Scan(origin=[0.0, 0.0], points=[[1.0, 1.0]])
    with pytest.raises(OctolgpError, match=r"MapConfig\.dim"):
        make_training_data([scan], MapConfig(dim=3))
    with pytest.raises(OctolgpError, match="empty"):
        make_training_data([], MapConfig(dim=2))
    with pytest.raises(OctolgpError, match=r"scans\[1\]"):
        make_training_data([scan, np.zeros((2, 2))], MapConfig(dim=2))  # type: ignore[list-item]


def test_a_single_scan_is_accepted() -> None:
    scan = Scan(origin=[0.0, 0.0], points=[[1.0, 1.0]])
    data = make_training_data(scan, MapConfig(dim=2))  # type: ignore[arg-type]
    np.testing.assert_array_equal(data.hits, [[1.0, 1.0]])


# --------------------------------------------------------------------------- Scan validation

GOOD_POINTS = [[1.0, 2.0], [3.0, 4.0]]


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"points": [[1.0, np.nan], [3.0, 4.0]]}, "Scan.points"),
        ({"points": [[1.0, np.inf], [3.0, 4.0]]}, "Scan.points"),
        ({"points": [[1.0, 2.0, 3.0]]}, "Scan.points"),  # 3D points, 2D origin
        ({"points": [1.0, 2.0]}, "Scan.points"),  # not (n, d)
        ({"points": np.zeros((0, 2))}, "Scan.points"),  # empty
        ({"points": [["a", "b"]]}, "Scan.points"),  # not numeric
        ({"origin": [np.nan, 0.0]}, "Scan.origin"),
        ({"origin": [0.0, -np.inf]}, "Scan.origin"),
        ({"origin": [0.0, 0.0, 0.0, 0.0]}, "Scan.origin"),
        ({"origin": [[0.0, 0.0]]}, "Scan.origin"),
        ({"max_range": 0.0}, "Scan.max_range"),
        ({"max_range": -1.0}, "Scan.max_range"),
        ({"max_range": np.nan}, "Scan.max_range"),
        ({"max_range": np.inf}, "Scan.max_range"),
        ({"max_range": "10"}, "Scan.max_range"),
        ({"max_range": True}, "Scan.max_range"),
        ({"stamp": np.nan}, "Scan.stamp"),
    ],
)
def test_scan_validation_names_the_field(kwargs: dict[str, object], field: str) -> None:
    args: dict[str, object] = {"origin": [0.0, 0.0], "points": GOOD_POINTS, **kwargs}
    with pytest.raises(OctolgpError, match=field.replace(".", r"\.")):
        Scan(**args)  # type: ignore[arg-type]


def test_scan_is_float64_read_only_and_max_range_float() -> None:
    scan = Scan(origin=[0, 0], points=[[1, 2], [3, 4]], max_range=5)
    assert scan.points.dtype == np.float64
    assert scan.origin.dtype == np.float64
    assert isinstance(scan.max_range, float)
    assert len(scan) == 2
    with pytest.raises(ValueError, match="read-only"):
        scan.points[0, 0] = 7.0


# --------------------------------------------------------------------------- MapConfig


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: MapConfig(resolution=0.0), "MapConfig.resolution"),
        (lambda: MapConfig(resolution=-0.1), "MapConfig.resolution"),
        (lambda: MapConfig(resolution=math.nan), "MapConfig.resolution"),
        (lambda: MapConfig(resolution=math.inf), "MapConfig.resolution"),
        (lambda: MapConfig(resolution="0.1"), "MapConfig.resolution"),
        (lambda: MapConfig(dim=4), "MapConfig.dim"),
        (lambda: MapConfig(dim=1), "MapConfig.dim"),
        (lambda: MapConfig(dim=True), "MapConfig.dim"),
        (lambda: MapConfig(tree_depth=0), "MapConfig.tree_depth"),
        (lambda: MapConfig(tree_depth=17), "MapConfig.tree_depth"),
        (lambda: MapConfig(memory_budget_mb=-5.0), "MapConfig.memory_budget_mb"),
        (lambda: MapConfig(training="fast"), "MapConfig.training"),
        (lambda: MapConfig(hyperparameters={"length_scale": 1.0}), "MapConfig.hyperparameters"),
        (lambda: TrainingConfig(quadrature_spacing=0.0), "TrainingConfig.quadrature_spacing"),
        (lambda: TrainingConfig(free_margin=-0.1), "TrainingConfig.free_margin"),
        (lambda: TrainingConfig(dedup=1), "TrainingConfig.dedup"),
        (
            lambda: TrainingConfig(min_quadrature_nodes=5, max_quadrature_nodes=3),
            "TrainingConfig.max_quadrature_nodes",
        ),
        (lambda: PartitionConfig(max_cluster_size=1), "PartitionConfig.max_cluster_size"),
        (lambda: PartitionConfig(overlap=math.nan), "PartitionConfig.overlap"),
        (lambda: PartitionConfig(box_size=-1.0), "PartitionConfig.box_size"),
        (lambda: LearningConfig(objective="elbo"), "LearningConfig.objective"),
        (lambda: LearningConfig(max_clusters=0), "LearningConfig.max_clusters"),
        (lambda: Hyperparameters(length_scale=0.0), "Hyperparameters.length_scale"),
        (lambda: Hyperparameters(noise_variance=-1.0), "Hyperparameters.noise_variance"),
        (lambda: Hyperparameters(alpha=math.nan), "Hyperparameters.alpha"),
        (lambda: OgmConfig(prob_hit=0.4), "OgmConfig.prob_hit"),
        (lambda: OgmConfig(clamping_thres_min=1.5), "OgmConfig.clamping_thres_min"),
        (lambda: MapConfig.from_dict({"partition": {"box_size": -1}}), "PartitionConfig.box_size"),
        (lambda: MapConfig.from_dict({"training": {"bogus": 1}}), "MapConfig.training"),
        (lambda: MapConfig.from_dict({"resolutoin": 0.1}), "resolutoin"),
    ],
)
def test_config_validation_names_the_field(make: object, field: str) -> None:
    with pytest.raises(OctolgpError, match=field.replace(".", r"\.")):
        make()  # type: ignore[operator]


def test_config_rejects_a_float_dimension() -> None:
    with pytest.raises(OctolgpError, match=r"MapConfig\.dim"):
        MapConfig(dim=2.0)  # type: ignore[arg-type]


CONFIGS = [
    MapConfig(),
    MapConfig(dim=2, resolution=0.2),
    MapConfig(
        dim=2,
        resolution=0.05,
        hyperparameters=Hyperparameters(0.4, 1.5, 0.02, alpha=3.0, beta=-0.5),
        memory_budget_mb=64.0,
        tree_depth=12,
        training=TrainingConfig(free_margin=0.0, dedup=False, quadrature_spacing=0.25),
        partition=PartitionConfig(box_size=4.0, max_cluster_size=50, overlap=0.0, seed=3),
        learning=LearningConfig(max_clusters=2, max_items_per_cluster=20, objective="lml"),
        ogm=OgmConfig(prob_hit=0.8, prob_miss=0.3),
    ),
]


@pytest.mark.parametrize("config", CONFIGS)
def test_config_dict_round_trip(config: MapConfig) -> None:
    as_dict = config.to_dict()
    assert MapConfig.from_dict(as_dict) == config
    assert None not in _leaves(as_dict)


def _leaves(d: dict[str, object]) -> list[object]:
    out: list[object] = []
    for v in d.values():
        out.extend(_leaves(v) if isinstance(v, dict) else [v])
    return out


@given(
    dim=st.sampled_from([2, 3]),
    resolution=st.floats(1e-3, 10.0),
    free_margin=st.none() | st.floats(0.0, 1.0),
    spacing=st.floats(0.05, 2.0),
    overlap=st.floats(0.0, 1.0),
    cap=st.integers(2, 1000),
    hp=st.none() | st.builds(Hyperparameters, st.floats(0.01, 10.0), st.floats(0.01, 10.0)),
)
def test_config_dict_round_trip_property(
    dim: int,
    resolution: float,
    free_margin: float | None,
    spacing: float,
    overlap: float,
    cap: int,
    hp: Hyperparameters | None,
) -> None:
    config = MapConfig(
        dim=dim,
        resolution=resolution,
        hyperparameters=hp,
        training=TrainingConfig(free_margin=free_margin, quadrature_spacing=spacing),
        partition=PartitionConfig(overlap=overlap, max_cluster_size=cap),
    )
    assert MapConfig.from_dict(config.to_dict()) == config
    assert config.free_margin == (resolution if free_margin is None else free_margin)
