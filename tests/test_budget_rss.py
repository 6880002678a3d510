"""The memory budget bounds the process: peak RSS over a small mission, in child processes.

Each mission runs in a fresh interpreter (RSS is a property of a process): import, a
one-scan warm-up (numba's compiled kernels, the lattice tables), then the *base* RSS;
then 400 scans of a simulated 3D lidar mission into a map with and without a budget,
a read of about 4,000 points, and the peak RSS since the base
(``VmHWM``, reset at the base: :func:`octolgp.memory.reset_peak_rss`). With a budget ``B`` the
peak stays within ``base + B + SLACK_MB`` = ``base + 1.5 B``, the goal of
``tools/bench_budget_rss.py``: the leaves and a step's working arrays are held to ``B``
(the store keeps room for the largest recent step), and what comes on top (a batch of
leaves fitted for a read, heap pages the C allocator cannot return) does not grow with
the mission (39.8 MB measured). Without a budget the same mission's peak passes the
bound (so the check can fail), and both maps read the same.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

BUDGET_MB = 32.0
SLACK_MB = 16.0

CHILD = """
import dataclasses, gc, hashlib, json, sys

import numpy as np

from octolgp import Hyperparameters, MapConfig, OnlineMap
from octolgp.memory import peak_rss_mb, reset_peak_rss, rss_mb
from octolgp.sim.mission import simulate_mission3d

budget = None if sys.argv[1] == "none" else float(sys.argv[1])
n = 400
mission = simulate_mission3d(n + 5.0, seed=0, spacing=1.0, max_range=8.0)
scans = [mission.scan(k).downsample(0.2) for k in range(n)]
hp = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
config = MapConfig(dim=3, resolution=0.2, hyperparameters=hp)
warm = OnlineMap(config)
warm.insert_scan(scans[0])
warm.occupancy(scans[0].points[:10])
warm.close()
del warm
gc.collect()
base = rss_mb()
assert reset_peak_rss()
m = OnlineMap(dataclasses.replace(config, memory_budget_mb=budget))
for s in scans:
    m.insert_scan(s)
probe = np.concatenate([s.points[::7] for s in scans[::10]])
p = m.occupancy(probe)
peak = peak_rss_mb()
digest = hashlib.sha256(np.round(p, 12).tobytes()).hexdigest()
print(json.dumps({"rise": peak - base, "leaves": m.memory_bytes() / 1e6, "digest": digest}))
"""


def _mission(budget: str) -> dict[str, float | str]:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, budget], capture_output=True, text=True, check=True
    )
    result: dict[str, float | str] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


@pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="reads the RSS in /proc/self (Linux)"
)
def test_the_budget_bounds_the_peak_rss_of_a_mission() -> None:
    bounded = _mission(str(BUDGET_MB))
    free = _mission("none")
    bound = BUDGET_MB + SLACK_MB
    assert float(bounded["leaves"]) <= BUDGET_MB
    assert float(bounded["rise"]) <= bound, bounded
    assert float(free["rise"]) > bound, free  # the mission outgrows the bound without it
    assert bounded["digest"] == free["digest"]  # the budget changes no value


def test_the_budget_keeps_room_for_the_largest_recent_step() -> None:
    """Leaves are held to the budget less the working arrays of the largest of the last
    RESERVE_STEPS steps (the leaves they touched times their halo boxes)."""
    from octolgp import Hyperparameters, MapConfig, OnlineMap
    from octolgp.mapping.online import RESERVE_STEPS
    from octolgp.mapping.store import STEP_BYTES_PER_HALO_VOXEL
    from octolgp.sim.mission import simulate_mission3d

    mission = simulate_mission3d(60.0, seed=0, spacing=1.0, max_range=8.0)
    hp = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=hp, memory_budget_mb=4.0)
    touched: list[int] = []
    with OnlineMap(config) as m:
        box = (m.grid.side + 2 * m.grid.halo_voxels) ** 3
        for k in range(40):
            touched.append(m.insert_scan(mission.scan(k).downsample(0.2)).touched_leaves)
            reserve = max(touched[-RESERVE_STEPS:]) * box * STEP_BYTES_PER_HALO_VOXEL
            assert m.store.reserve_bytes == reserve
            assert m.store.nbytes <= max(4_000_000 - reserve, 0) or not m.store.resident
        assert m.store.evictions
    with OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=hp)) as free:
        free.insert_scan(mission.scan(0).downsample(0.2))
        assert free.store.reserve_bytes == 0  # no budget, nothing kept free


@pytest.mark.parametrize("leaf_voxels", [256, 512, 4096, 32768])
@pytest.mark.parametrize("budget", [None, 1_000_000, 32_000_000, 4_000_000_000])
def test_a_fit_batch_holds_the_same_working_set_whatever_the_leaf_size(
    leaf_voxels: int, budget: int | None
) -> None:
    """Batches count leaves of 8³ voxels: a larger leaf counts as several, so the bytes a
    batch's fit holds stay an eighth of the budget (above a floor of 16 small leaves or
    one leaf)."""
    from octolgp.mapping.store import FIT_BYTES_PER_LEAF, READ_BATCH, UNIT_LEAF_VOXELS, LeafStore

    store = LeafStore(budget, leaf_voxels)
    units = max(1, leaf_voxels // UNIT_LEAF_VOXELS)
    assert store.units == units
    small = LeafStore(budget).batch  # the same budget's batch of 8³ leaves
    assert store.batch == max(small // units, 1)
    working = store.batch * units * FIT_BYTES_PER_LEAF
    if budget is None:
        assert small == READ_BATCH
    else:
        floor = max(16, units) * FIT_BYTES_PER_LEAF  # 16 small leaves, or one leaf
        assert working <= max(budget // 8, floor)
