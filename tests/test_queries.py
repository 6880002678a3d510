"""Queries: large ones run in bounded chunks and answer as one."""

from __future__ import annotations

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OnlineMap
from octolgp.sim.lidar3d import simulate_lidar_room

HP = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)


def test_a_large_query_in_chunks_reads_as_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """Queries run in chunks of QUERY_CHUNK points (bounded temporaries): the same answers."""
    from octolgp.mapping import query

    room = simulate_lidar_room(2, seed=3, n_azimuth=256, n_elevation=16, max_range=20.0)
    m = OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=HP))
    m.insert_scans([s.downsample(0.2) for s in room.scans()])
    rng = np.random.default_rng(0)
    probe = np.concatenate([room.scans()[0].points[::3], rng.uniform(-2, 22, (5000, 3))])
    whole = [m.occupancy(probe), m.occupancy(probe, interpolate=False), *m.latent(probe)]
    monkeypatch.setattr(query, "QUERY_CHUNK", 777)
    parts = [m.occupancy(probe), m.occupancy(probe, interpolate=False), *m.latent(probe)]
    for a, b in zip(whole, parts, strict=True):
        assert a.tobytes() == b.tobytes()
