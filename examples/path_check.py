"""Check straight-line paths through the Intel lab map, as a planner would.

Maps the bundled Intel lab log online (``OnlineMap`` at the defaults, 0.1 m), then checks
two kinds of straight legs between the robot's own positions:

- the legs of its trajectory (every ``--every``-th scan origin to the next): it drove
  them, so they should be free;
- shortcuts from the start to positions along the trajectory, straight through the
  building: most cross a wall.

Per leg: whether it is free (``segment_free``: the whole segment below P = 0.5, and in
known space), where it is first blocked (``raycast`` along it: metres from its start,
``unknown="occupied"`` so an unobserved stretch blocks too), and its clearance (the
least ``distance`` to an occupied voxel over points every 5 cm along it).

    python examples/path_check.py [--limit 300] [--every 3]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from octolgp import MapConfig, OnlineMap, load_scans

LOG = Path(__file__).resolve().parent.parent / "data" / "intel_lab" / "intel-corrected.log.gz"
CLEARANCE_STEP = 0.05  # metres between the points where a leg's clearance is read


def check_legs(m: OnlineMap, a: np.ndarray, b: np.ndarray) -> dict[str, np.ndarray]:
    """Free, first blocked distance and clearance of the legs ``a[i] -> b[i]`` (metres)."""
    length = np.linalg.norm(b - a, axis=1)
    free = m.segment_free(a, b)
    heading = np.where(length[:, None] > 0, b - a, [[1.0, 0.0]])  # any heading for a standstill
    blocked_at = m.raycast(a, heading, length, unknown="occupied")  # inf where free
    n = np.maximum(np.ceil(length / CLEARANCE_STEP).astype(int), 1)
    leg = np.repeat(np.arange(a.shape[0]), n + 1)
    s = np.concatenate([np.linspace(0.0, 1.0, k + 1) for k in n])  # one array per leg
    dist = m.distance(a[leg] + s[:, None] * (b - a)[leg], max_distance=2.0)
    clearance = np.full(a.shape[0], np.inf)
    np.minimum.at(clearance, leg, dist)
    return {"length": length, "free": free, "blocked_at": blocked_at, "clearance": clearance}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--limit", type=int, default=300, help="scans to map (default 300)")
    parser.add_argument("--every", type=int, default=3, help="scans between waypoints")
    args = parser.parse_args()

    m = OnlineMap(MapConfig(dim=2, resolution=0.1))
    scans = [s for _, s in zip(range(args.limit), load_scans(LOG), strict=False)]
    m.insert_scans(scans)
    m.flush()  # learn now if fewer than learn_scans scans came
    origins = np.array([s.origin for s in scans[:: args.every]])
    print(f"mapped {len(scans)} scans; {origins.shape[0]} waypoints")

    ahead = origins[:: max(1, origins.shape[0] // 8)][1:]  # a few positions along the way
    for name, a, b in (
        ("trajectory legs", origins[:-1], origins[1:]),
        ("shortcuts from the start", np.repeat(origins[:1], ahead.shape[0], 0), ahead),
    ):
        r = check_legs(m, a, b)
        print(f"\n{name}: {int(r['free'].sum())} of {a.shape[0]} free")
        print(f"  median clearance {np.median(r['clearance']):.2f} m")
        print("  leg   length m  free   blocked at m  clearance m")
        for i in np.flatnonzero(~r["free"] | (name != "trajectory legs"))[:12]:  # a dozen legs
            print(
                f"  {i:3d}  {r['length'][i]:8.2f}  {'yes' if r['free'][i] else 'no ':4s}"
                f"  {r['blocked_at'][i]:12.2f}  {r['clearance'][i]:11.2f}"
            )


if __name__ == "__main__":
    main()
