"""A 3D mesh of the simulated lidar room: the map's P(occupied) level set as PLY or OBJ.

Maps ``octolgp.sim.lidar3d.simulate_lidar_room`` (a 20 x 20 x 5 m room of boxes, a
32 x 1024 lidar) at 0.2 m, then writes the level set ``P = --threshold`` as a triangle
mesh (``OnlineMap.surface``, marching tetrahedra on the voxel centres) and prints how far
its vertices lie from the room's exact box faces. Open the file in MeshLab or Blender.

    python examples/room_mesh.py --out room.ply [--poses 12] [--threshold 0.9]
"""

from __future__ import annotations

import argparse

import numpy as np

from octolgp import Hyperparameters, MapConfig, OnlineMap
from octolgp.export.mesh import write_mesh
from octolgp.sim.lidar3d import simulate_lidar_room

HP = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)


def face_distance(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest face of the boxes ``(k, 6)``, metres."""
    lo, hi = boxes[None, :, :3], boxes[None, :, 3:]
    p = points[:, None, :]
    inside = ((p > lo) & (p < hi)).all(axis=2)
    gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
    outside = np.sqrt((gap * gap).sum(axis=2)).min(axis=1)
    depth = np.where(inside, np.minimum(p - lo, hi - p).min(axis=2), np.inf).min(axis=1)
    return np.where(inside.any(axis=1), depth, outside)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="room.ply", help=".ply or .obj mesh to write")
    parser.add_argument("--poses", type=int, default=12, help="lidar scans (default 12)")
    parser.add_argument("--threshold", type=float, default=0.5, help="P of the level set")
    args = parser.parse_args()

    room = simulate_lidar_room(args.poses)
    m = OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=HP))
    m.insert_scans([s.downsample(0.2) for s in room.scans()])
    vertices, faces = m.surface(args.threshold)
    write_mesh(args.out, vertices, faces)
    gap = face_distance(vertices, np.asarray(room.boxes))
    print(f"wrote {args.out}: {vertices.shape[0]:,} vertices, {faces.shape[0]:,} triangles")
    print(
        f"vertex to the nearest true face: median {np.median(gap):.3f} m, mean {gap.mean():.3f} m"
    )


if __name__ == "__main__":
    main()
