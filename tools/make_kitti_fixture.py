"""Make the KITTI odometry fixture in ``tests/data/kitti/`` from a simulated street.

The scene (:data:`BOXES`, in the frame of the Velodyne at frame 0: x forward, y left, z up,
metres) is a straight street: the road 1.73 m below the sensor (KITTI's mounting height),
house fronts 6 m to either side, two parked cars and a lamp post. A 16-ring lidar
(:data:`N_AZIMUTH` beams per ring, rings from -24.9 to +2 degrees, as the HDL-64E's field of
view) drives :data:`N_SCANS` frames along it, 1 m per frame, turning slowly; every return is
the exact first box face along the beam (:func:`octolgp.sim.scenes.ray_box_distance`), beams
that hit nothing are left out, as in KITTI.

Outputs, in KITTI's layout and formats:

- ``sequences/00/velodyne/00000F.bin``: float32 ``x y z reflectance`` per return, in the
  Velodyne frame (reflectance = 1 / (1 + range), a stand-in);
- ``sequences/00/calib.txt``: ``P0``..``P3`` (KITTI-like camera matrices) and ``Tr``
  (:data:`TR`: Velodyne to ``cam0``, a slightly tilted axis swap plus an offset);
- ``poses/00.txt``: ``P_i = Tr V_i Tr^-1`` per frame (12 numbers, row-major), ``V_i`` the
  Velodyne's pose in its frame-0 frame, so ``P_0`` is the identity, as in KITTI.

Reading the sequence with ``world="velodyne"`` gives back the simulated points in the scene's
frame (to float32 precision); the default ``world="cam0"`` gives ``Tr`` times them.

Run from the repository root: ``python tools/make_kitti_fixture.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from octolgp.geometry.rotations import euler_xyz_to_matrix
from octolgp.sim.lidar3d import beam_pattern
from octolgp.sim.scenes import ray_box_distance

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "tests" / "data" / "kitti"
N_SCANS = 5
N_AZIMUTH = 24
N_RINGS = 16
HEIGHT = 1.73  # sensor above the road, metres
MAX_RANGE = 80.0

# [xmin, ymin, zmin, xmax, ymax, zmax], metres, Velodyne frame 0
BOXES = np.array(
    [
        [-20.0, -8.0, -HEIGHT - 0.3, 40.0, 8.0, -HEIGHT],  # road
        [-20.0, 6.0, -HEIGHT, 40.0, 7.0, 6.0],  # house fronts, left
        [-20.0, -7.0, -HEIGHT, 40.0, -6.0, 6.0],  # house fronts, right
        [6.0, 2.5, -HEIGHT, 10.5, 4.3, -0.3],  # parked car, left
        [12.0, -4.3, -HEIGHT, 16.5, -2.5, -0.2],  # parked car, right
        [3.0, -5.0, -HEIGHT, 3.2, -4.8, 3.0],  # lamp post
    ]
)

# Tr: cam0 <- Velodyne. Axis swap (cam x = -velo y, y = -velo z, z = velo x), tilted a little.
_SWAP = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
TR = np.eye(4)
TR[:3, :3] = euler_xyz_to_matrix([0.3, -0.4, 0.2], degrees=True) @ _SWAP
TR[:3, 3] = [-0.012, -0.054, -0.292]

_P0 = "7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0"


def velodyne_poses(n: int) -> np.ndarray:
    """``V_i``: 4 x 4 poses of the Velodyne in its frame 0, ``(n, 4, 4)``; 1 m per frame."""
    yaw = np.deg2rad(1.5) * np.arange(n)  # a slow left turn
    V = np.tile(np.eye(4), (n, 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    V[:, 0, 0], V[:, 0, 1], V[:, 1, 0], V[:, 1, 1] = c, -s, s, c
    V[:, 0, 3] = np.concatenate([[0.0], np.cumsum(np.cos(yaw[:-1]))])
    V[:, 1, 3] = np.concatenate([[0.0], np.cumsum(np.sin(yaw[:-1]))])
    return V


def simulate(V: np.ndarray) -> list[np.ndarray]:
    """Returns ``(k, 3)`` in each Velodyne frame: exact first hits, no-returns left out."""
    u = beam_pattern(N_AZIMUTH, N_RINGS, -24.9, 2.0)
    scans = []
    for T in V:
        dirs = u @ T[:3, :3].T
        r = ray_box_distance(np.broadcast_to(T[:3, 3], dirs.shape), dirs, BOXES)
        hit = r < MAX_RANGE
        scans.append(r[hit, None] * u[hit])
    return scans


def write_matrix_line(M: np.ndarray) -> str:
    """A 3 x 4 matrix as KITTI writes it: 12 numbers, row-major, ``%e``."""
    return " ".join(f"{v:.12e}" for v in M[:3, :].ravel())


def main() -> None:
    sequence = OUT / "sequences" / "00"
    (sequence / "velodyne").mkdir(parents=True, exist_ok=True)
    (OUT / "poses").mkdir(parents=True, exist_ok=True)
    V = velodyne_poses(N_SCANS)
    for i, xyz in enumerate(simulate(V)):
        record = np.empty(len(xyz), dtype=[("xyz", "<f4", (3,)), ("reflectance", "<f4")])
        record["xyz"] = xyz
        record["reflectance"] = 1.0 / (1.0 + np.linalg.norm(xyz, axis=1))
        (sequence / "velodyne" / f"{i:06d}.bin").write_bytes(record.tobytes())
    calib = [f"P{k}: {_P0}" for k in range(4)] + [f"Tr: {write_matrix_line(TR)}"]
    (sequence / "calib.txt").write_text("\n".join(calib) + "\n")
    P = TR @ V @ np.linalg.inv(TR)
    P[np.abs(P) < 1e-12] = 0.0  # round-off of the identity at frame 0
    (OUT / "poses" / "00.txt").write_text("".join(write_matrix_line(M) + "\n" for M in P))
    size = sum(f.stat().st_size for f in OUT.rglob("*") if f.is_file())
    print(f"wrote {OUT}: {N_SCANS} scans, {size} bytes")


if __name__ == "__main__":
    main()
