"""The free range (``TrainingConfig.free_range``): how far a beam's evidence reaches."""

from __future__ import annotations

import json
import math
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from octolgp import MapConfig, OctolgpError, OnlineMap, Scan, TrainingConfig
from octolgp.geometry.keys import key_to_coord
from octolgp.observations import observe
from octolgp.training import split_beams


def test_split_beams_truncates_as_octomaps_maxrange() -> None:
    origins = np.zeros((4, 2))
    ends = np.array([[80.0, 0.0], [0.0, 30.0], [10.0, 0.0], [0.0, -20.0]])
    max_range = np.full(4, 80.0)  # the first beam is a no-return
    beams = split_beams(origins, ends, max_range, 0.1, free_range=20.0)
    # the no-return and the 30 m return: free to 20 m, no hit; the 10 m return whole;
    # a return at exactly the free range keeps its hit
    np.testing.assert_array_equal(beams.is_hit, [False, False, True, True])
    np.testing.assert_array_equal(beams.has_seg, [True, True, True, True])
    np.testing.assert_allclose(
        beams.free_end, [[20.0, 0.0], [0.0, 20.0], [9.9, 0.0], [0.0, -19.9]], atol=1e-12
    )
    whole = split_beams(origins, ends, max_range, 0.1)  # inf: every beam whole
    np.testing.assert_array_equal(whole.is_hit, [False, True, True, True])
    np.testing.assert_allclose(whole.free_end[:2], [[80.0, 0.0], [0.0, 29.9]], atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_no_voxel_is_observed_beyond_the_free_range(dim: int) -> None:
    rng = np.random.default_rng(dim)
    u = rng.normal(size=(300, dim))
    u /= np.linalg.norm(u, axis=1)[:, None]
    r = rng.uniform(1.0, 25.0, 300)
    r[::4] = 25.0  # no-returns
    origin = rng.uniform(-3.0, 3.0, dim)
    scan = Scan(origin=origin, points=origin + u * r[:, None], max_range=25.0)
    res, reach = 0.2, 8.0
    config = MapConfig(dim=dim, resolution=res, training=TrainingConfig(free_range=reach))
    obs = observe([scan], config)
    centres = key_to_coord(obs.keys, res, config.tree_depth)
    # every observed voxel holds a point within the free range (its centre within a
    # voxel's diagonal of it)
    assert np.linalg.norm(centres - origin, axis=1).max() <= reach + res * math.sqrt(dim)
    near = (r < reach) & (np.arange(300) % 4 != 0)
    assert (
        obs.hits.sum()
        == np.unique(np.floor((origin + u[near] * r[near, None]) / res), axis=0).shape[0]
    )  # the returns within the range, and only they, are hits
    whole = observe([scan], MapConfig(dim=dim, resolution=res))
    assert whole.keys.shape[0] > obs.keys.shape[0]


def test_the_free_range_is_validated_and_round_trips() -> None:
    for bad in (0.0, -1.0, float("nan"), "30", True):
        with pytest.raises(OctolgpError, match=r"TrainingConfig\.free_range"):
            TrainingConfig(free_range=bad)  # type: ignore[arg-type]
    config = MapConfig(dim=2, resolution=0.1, training=TrainingConfig(free_range=30.0))
    assert config.free_range == 30.0
    assert MapConfig.from_dict(config.resolve().to_dict()).free_range == 30.0
    unbounded = MapConfig(dim=2, training=TrainingConfig(free_range=math.inf)).resolve()
    assert MapConfig.from_dict(json.loads(json.dumps(unbounded.to_dict()))).free_range == math.inf
    assert "free_range = inf" in unbounded.to_toml()


def test_a_file_from_before_the_free_range_keeps_every_beam_whole(tmp_path: Path) -> None:
    path = tmp_path / "m.octolgp"
    config = MapConfig(dim=2, resolution=0.1, training=TrainingConfig(free_range=5.0))
    with OnlineMap(config, path=path):
        pass
    con = sqlite3.connect(path)
    (text,) = con.execute("SELECT value FROM meta WHERE key='config'").fetchone()
    stored = json.loads(text)
    del stored["training"]["free_range"]  # as a file written before the setting
    con.execute("UPDATE meta SET value=? WHERE key='config'", (json.dumps(stored),))
    con.commit()
    con.close()
    with OnlineMap.open(path, read_only=True) as back:
        assert back.config.free_range == math.inf
