"""How far a beam's evidence reaches: ``TrainingConfig.free_range`` and ``no_return_range``."""

from __future__ import annotations

import json
import math
import sqlite3
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from octolgp import (
    LatticeConfig,
    MapConfig,
    OctolgpError,
    OnlineMap,
    Scan,
    TrainingConfig,
    load_scans,
)
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
    # no_return_range: only the no-return is cut, the returns keep their hits whole
    cut = split_beams(origins, ends, max_range, 0.1, no_return_range=15.0)
    np.testing.assert_array_equal(cut.is_hit, [False, True, True, True])
    np.testing.assert_allclose(cut.free_end[:2], [[15.0, 0.0], [0.0, 29.9]], atol=1e-12)
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


def test_the_ranges_are_validated_and_round_trip() -> None:
    for name in ("free_range", "no_return_range"):
        for bad in (0.0, -1.0, float("nan"), "30", True):
            with pytest.raises(OctolgpError, match=rf"TrainingConfig\.{name}"):
                TrainingConfig(**{name: bad})
    with pytest.raises(OctolgpError, match=r"TrainingConfig\.free_range"):
        TrainingConfig(free_range=None)  # type: ignore[arg-type]
    # the no-return range never exceeds the free range
    short = MapConfig(dim=2, training=TrainingConfig(free_range=5.0, no_return_range=9.0))
    assert short.no_return_range == 5.0
    assert MapConfig(dim=2, training=TrainingConfig(no_return_range=9.0)).no_return_range == 9.0
    config = MapConfig(dim=2, resolution=0.1, training=TrainingConfig(free_range=30.0))
    assert config.free_range == 30.0
    assert MapConfig.from_dict(config.resolve().to_dict()).free_range == 30.0
    unbounded = MapConfig(dim=2, training=TrainingConfig(free_range=math.inf)).resolve()
    assert MapConfig.from_dict(json.loads(json.dumps(unbounded.to_dict()))).free_range == math.inf
    assert "free_range = inf" in unbounded.to_toml()


def test_a_file_from_before_the_ranges_keeps_every_beam_whole_and_fills(tmp_path: Path) -> None:
    path = tmp_path / "m.octolgp"
    config = MapConfig(
        dim=2,
        resolution=0.1,
        training=TrainingConfig(no_return_range=5.0),
        lattice=LatticeConfig(fill_voxels=1),
    )
    with OnlineMap(config, path=path):
        pass
    con = sqlite3.connect(path)
    (text,) = con.execute("SELECT value FROM meta WHERE key='config'").fetchone()
    stored = json.loads(text)
    del stored["training"]["no_return_range"]  # as a file written before the settings
    del stored["lattice"]["fill_voxels"]
    con.execute("UPDATE meta SET value=? WHERE key='config'", (json.dumps(stored),))
    con.commit()
    con.close()
    with OnlineMap.open(path, read_only=True) as back:
        assert back.config.no_return_range == math.inf
        assert back.config.fill_voxels == -1


INTEL20 = Path(__file__).resolve().parent / "data" / "intel_first20.log"


@pytest.mark.parametrize("bad", ["0", "-3", "nan", "far"])
def test_a_bad_free_range_flag_exits_2(
    bad: str, tmp_path: Path, cli_exit_2: Callable[..., str]
) -> None:
    argv = ["run", str(INTEL20), "--out", str(tmp_path / "m.octolgp"), "--free-range", bad]
    cli_exit_2(argv, tmp_path, "--free-range", prefix="octolgp run: error:")


def test_the_free_range_flag_reaches_the_map(tmp_path: Path) -> None:
    from octolgp.cli.main import main

    out = tmp_path / "m.octolgp"
    poses = np.array([s.origin for s in load_scans(INTEL20)])
    reach = {}
    for free_range in ("7.5", "inf"):
        argv = ["run", str(INTEL20), "--out", str(out), "--free-range", free_range, "--quiet"]
        assert main([*argv, "--learn-scans", "5", "--overwrite"]) == 0
        with OnlineMap.open(out, read_only=True) as m:
            assert m.config.free_range == float(free_range)
            centres, _ = m.voxels()
        reach[free_range] = np.linalg.norm(centres[:, None] - poses[None], axis=2).min(1).max()
    # nothing beyond the range but what the GP fills (2 voxels); returns to ~14 m without
    assert reach["7.5"] < 7.5 + 0.5
    assert reach["inf"] > 12.0
