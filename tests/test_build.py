"""End to end: ``build_map`` on small ray-cast rooms, scored against ground-truth grids.

The scenes are built here with a slab-method ray caster of their own (not
:mod:`octolgp.sim.scenes`), so they are an independent check of the pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from octolgp.batch.build import build_map
from octolgp.config import Hyperparameters, LearningConfig, MapConfig, PartitionConfig
from octolgp.errors import OctolgpError
from octolgp.gp.learning import learn_hyperparameters
from octolgp.scan import Scan
from octolgp.training import make_training_data

HP = Hyperparameters(length_scale=0.6, signal_variance=1.0, noise_variance=0.05, alpha=3.0)
GP_METHODS = ["lgp", "gp", "mgp"]


@dataclass(frozen=True)
class Scene:
    """Scans of a room of boxes, and the cell centres and labels of its ground truth."""

    scans: list[Scan]
    cells: np.ndarray  # (m, d) cell centres, metres
    occupied: np.ndarray  # (m,) bool: the centre lies in a box
    resolution: float


def _cast(origin: np.ndarray, directions: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Range to the first axis-aligned box along each unit direction (slab method).

    ``boxes`` is ``(k, 2d)``: ``[min..., max...]``. The origin is outside every box
    and no direction is parallel to an axis.
    """
    d = origin.size
    lo, hi = boxes[None, :, :d], boxes[None, :, d:]
    u = directions[:, None, :]
    t0, t1 = (lo - origin) / u, (hi - origin) / u
    t_in = np.minimum(t0, t1).max(axis=2)
    t_out = np.maximum(t0, t1).min(axis=2)
    return np.where((t_in <= t_out) & (t_in > 0), t_in, np.inf).min(axis=1)


def _scene(
    boxes: np.ndarray,
    poses: np.ndarray,
    directions: np.ndarray,
    extent: tuple[float, ...],
    resolution: float,
    max_range: float | None = None,
) -> Scene:
    scans = []
    for p in poses:
        r = _cast(p, directions, boxes)
        if max_range is not None:
            # a no-return reports exactly max_range, the usual encoding
            r = np.minimum(r, max_range)
        scans.append(Scan(origin=p, points=p + r[:, None] * directions, max_range=max_range))
    axes = [(np.arange(round(e / resolution)) + 0.5) * resolution for e in extent]
    cells = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(extent))
    d = len(extent)
    inside = (cells[:, None, :] >= boxes[None, :, :d]) & (cells[:, None, :] <= boxes[None, :, d:])
    return Scene(scans, cells, inside.all(axis=2).any(axis=1), resolution)


def room2d() -> Scene:
    """An 8 × 6 m room with 0.2 m walls, a pillar and a partition wall; four poses.

    180 beams per pose; beams are no-returns beyond 6 m.
    """
    boxes = np.array(
        [
            [0.0, 0.0, 8.0, 0.2],
            [0.0, 5.8, 8.0, 6.0],
            [0.0, 0.0, 0.2, 6.0],
            [7.8, 0.0, 8.0, 6.0],
            [4.6, 2.2, 5.4, 3.0],  # pillar
            [1.8, 3.6, 2.0, 5.8],  # partition wall
        ]
    )
    poses = np.array([[1.2, 1.2], [6.5, 1.2], [6.5, 4.8], [3.0, 3.0]])
    angles = np.linspace(0.0, 2.0 * np.pi, 180, endpoint=False) + 0.0123
    directions = np.column_stack([np.cos(angles), np.sin(angles)])
    return _scene(boxes, poses, directions, (8.0, 6.0), 0.2, max_range=6.0)


def room3d() -> Scene:
    """A 4 × 3.5 × 2.5 m box room, 0.25 m walls, floor and ceiling, and a block.

    Three poses, 400 beams each on a Fibonacci sphere; test cells of 0.25 m.
    """
    t = 0.25
    boxes = np.array(
        [
            [0.0, 0.0, 0.0, 4.0, 3.5, t],
            [0.0, 0.0, 2.5 - t, 4.0, 3.5, 2.5],
            [0.0, 0.0, 0.0, t, 3.5, 2.5],
            [4.0 - t, 0.0, 0.0, 4.0, 3.5, 2.5],
            [0.0, 0.0, 0.0, 4.0, t, 2.5],
            [0.0, 3.5 - t, 0.0, 4.0, 3.5, 2.5],
            [2.0, 1.5, t, 2.75, 2.25, 1.0],  # block on the floor
        ]
    )
    i = np.arange(400) + 0.5
    z = 1.0 - 2.0 * i / 400
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    directions = np.column_stack(
        [np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z]
    )
    poses = np.array([[1.0, 1.0, 1.3], [3.0, 2.6, 1.1], [1.2, 2.7, 1.6]])
    return _scene(boxes, poses, directions, (4.0, 3.5, 2.5), t)


def _config(scene: Scene, hp: Hyperparameters | None = HP, overlap: float = 0.2) -> MapConfig:
    d = scene.cells.shape[1]
    return MapConfig(
        dim=d,
        resolution=scene.resolution,
        hyperparameters=hp,
        partition=PartitionConfig(
            box_size=4.0, max_cluster_size=60 if d == 2 else 100, overlap=overlap
        ),
        learning=LearningConfig(max_clusters=3, max_items_per_cluster=120),
    )


@pytest.fixture(scope="module")
def scene2d() -> Scene:
    return room2d()


@pytest.fixture(scope="module")
def scene3d() -> Scene:
    return room3d()


def test_scene_is_sane(scene2d: Scene) -> None:
    """Every beam hits a wall within 6 m or is a no-return (reported at 6 m)."""
    r = np.concatenate([np.linalg.norm(s.points - s.origin, axis=1) for s in scene2d.scans])
    no_return = np.isclose(r, 6.0, rtol=1e-9)
    assert np.all((r < 6.0) & (r > 0.3) | no_return)
    assert 20 < no_return.sum() < r.size // 4
    assert 0.05 < scene2d.occupied.mean() < 0.3


@pytest.mark.parametrize("method", GP_METHODS)
def test_build_map_2d_auc(scene2d: Scene, method: str) -> None:
    """AUC against the ground-truth grid > 0.9 (measured 0.98 to 0.997)."""
    m = build_map(scene2d.scans, _config(scene2d), method)
    p = m.occupancy(scene2d.cells)
    assert p.shape == (scene2d.cells.shape[0],)
    assert np.all((p >= 0) & (p <= 1))
    assert roc_auc_score(scene2d.occupied, p) > 0.9
    assert {"training_data", "clustering", "learning", "fitting"} <= m.timings.keys()


@pytest.mark.parametrize("method", GP_METHODS)
def test_build_map_3d_auc(scene3d: Scene, method: str) -> None:
    """The same code with MapConfig(dim=3): AUC > 0.85 (measured 0.98 to 0.99)."""
    m = build_map(scene3d.scans, _config(scene3d), method)
    p = m.occupancy(scene3d.cells)
    assert roc_auc_score(scene3d.occupied, p) > 0.85


def test_local_gps_with_overlap_agree_with_global_gp_at_hits(scene2d: Scene) -> None:
    """Near the data (at the hits), overlapping local GPs approximate the global GP.

    Measured mean |Δ latent mean| at the hits: 0.006 with overlap 0.2 and 0.019
    without overlap; the global GP's latent mean there is 0.8 to 1.0.
    """
    hits = make_training_data(scene2d.scans, _config(scene2d)).hits
    mean_gp, _ = build_map(scene2d.scans, _config(scene2d), "gp").latent(hits)
    diffs = {}
    for overlap in (0.0, 0.2):
        lgp = build_map(scene2d.scans, _config(scene2d, overlap=overlap), "lgp")
        mean, _ = lgp.latent(hits)
        diffs[overlap] = np.abs(mean - mean_gp).mean()
    assert diffs[0.2] < 0.02, diffs
    assert diffs[0.2] < diffs[0.0], diffs


def test_lgp_n_jobs_does_not_change_the_map(scene2d: Scene) -> None:
    one = build_map(scene2d.scans, _config(scene2d), "lgp", n_jobs=1)
    two = build_map(scene2d.scans, _config(scene2d), "lgp", n_jobs=2)
    assert len(one.clusters) > 2  # threads really have clusters to share
    assert np.array_equal(one.occupancy(scene2d.cells), two.occupancy(scene2d.cells))
    for a, b in zip(one.latent(scene2d.cells), two.latent(scene2d.cells), strict=True):
        assert np.array_equal(a, b)


def test_build_map_rejects_bad_arguments(scene2d: Scene) -> None:
    with pytest.raises(OctolgpError, match="method"):
        build_map(scene2d.scans, _config(scene2d), "svm")
    with pytest.raises(OctolgpError, match="scheduler"):
        build_map(scene2d.scans, _config(scene2d), "lgp", scheduler=object())
    with pytest.raises(OctolgpError, match="config"):
        build_map(scene2d.scans, {"dim": 2}, "lgp")  # type: ignore[arg-type]
    with pytest.raises(OctolgpError, match=r"MapConfig\.dim"):
        build_map(scene2d.scans, MapConfig(dim=3, hyperparameters=HP), "lgp")
    m = build_map(scene2d.scans, _config(scene2d), "lgp")
    with pytest.raises(OctolgpError, match="points"):
        m.occupancy(np.zeros((3, 3)))


def test_learned_hyperparameters_are_valid_and_used(scene2d: Scene) -> None:
    """Learnt kernel values are finite and positive, α > 0; build_map learns the same.

    The batch map learns on its own model, hits and free segments (``model="segments"``).
    """
    config = _config(scene2d, hp=None)
    config = replace(config, learning=replace(config.learning, model="segments"))
    hp = learn_hyperparameters(scene2d.scans, config)
    values = np.array([hp.length_scale, hp.signal_variance, hp.noise_variance, hp.alpha])
    assert np.all(np.isfinite(values))
    assert np.all(values > 0)
    assert np.isfinite(hp.beta)
    m = build_map(scene2d.scans, config, "lgp")
    assert m.timings["learning"] > 0
    for name in ("length_scale", "signal_variance", "noise_variance", "alpha", "beta"):
        assert getattr(m.hyperparameters, name) == pytest.approx(getattr(hp, name), rel=1e-9)
    assert roc_auc_score(scene2d.occupied, m.occupancy(scene2d.cells)) > 0.9
