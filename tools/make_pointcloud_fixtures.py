"""Make the point-cloud reader fixtures in ``tests/data/pointcloud/`` from real scans.

Sources (see their READMEs):

- OctoMap's example scan ``../shared/data/octomap_scan/scan.dat.bz2``, beside the repository
  (world frame = sensor frame, m; the script stops with a note when it is absent);
- the 3DTK test fixture ``tests/data/3dtk`` (cut-down 3DTK example scans), read with
  :class:`octolgp.io.threedtk.ThreeDTKReader` (registered ``.frames`` poses, metres).

Outputs:

- ``scan_small.dat``: the first 2000 lines of ``scan.dat``, byte for byte.
- ``scan_nodes.dat``: the same 2000 points as two ``NODE`` scans of 1000: node 0 at the
  identity pose, node 1 at :data:`NODE1_POSE` (``x y z roll pitch yaw``), its points written in
  that sensor frame (``R^T (p - t)``, 9 significant digits), so that reading it gives back the
  world points of ``scan_small.dat``.
- ``cloud_ascii.pcd``, ``cloud_binary.pcd``, ``cloud_compressed.pcd``: every 5th point of 3DTK
  scan001 in its sensor frame, float32 ``x y z intensity`` (intensity = range, m), with
  ``VIEWPOINT`` = its registered pose; DATA ascii, binary and binary_compressed (LZF).
- ``cloud_ascii.ply``, ``cloud_binary.ply``: the same points in the world frame, float32,
  ``comment origin`` = the sensor position.
- ``two_scans.graph``: every 16th point of 3DTK scans 0 and 1 as an OctoMap binary scan graph
  (:func:`octolgp.io.octomap_graph.write_graph`, points in each sensor frame).

Run from the repository root: ``python tools/make_pointcloud_fixtures.py``.
"""

from __future__ import annotations

import bz2
from pathlib import Path

import numpy as np

from octolgp.geometry.rotations import matrix_to_quaternion, rpy_to_matrix
from octolgp.io.octomap_graph import write_graph
from octolgp.io.threedtk import ThreeDTKReader
from octolgp.scan import Scan

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "tests" / "data" / "pointcloud"
SCAN_DAT = ROOT.parent / "shared" / "data" / "octomap_scan" / "scan.dat.bz2"
THREEDTK = ROOT / "tests" / "data" / "3dtk"
NODE1_POSE = (1.0, -0.5, 0.2, 0.05, -0.1, 0.3)
"""The pose given to the second half of ``scan_small.dat``: metres and radians."""


def lzf_compress(data: bytes) -> bytes:
    """Greedy liblzf-format compressor (3-byte hash matches, offsets < 8192, lengths <= 264)."""
    out = bytearray()
    lit = bytearray()
    table: dict[bytes, int] = {}

    def flush() -> None:
        for j in range(0, len(lit), 32):
            chunk = lit[j : j + 32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
        lit.clear()

    i, n = 0, len(data)
    while i < n:
        if i + 2 < n:
            key = data[i : i + 3]
            ref = table.get(key)
            table[key] = i
            if ref is not None and i - ref <= 8192:
                length, cap = 3, min(264, n - i)
                while length < cap and data[ref + length] == data[i + length]:
                    length += 1
                flush()
                off, code = i - ref - 1, length - 2
                if code < 7:
                    out.append((code << 5) | (off >> 8))
                else:
                    out.append((7 << 5) | (off >> 8))
                    out.append(code - 7)
                out.append(off & 0xFF)
                i += length
                continue
        lit.append(data[i])
        i += 1
    flush()
    return bytes(out)


def pcd_header(n: int, viewpoint: list[float], data: str) -> bytes:
    vp = " ".join(f"{v:.9g}" for v in viewpoint)
    return (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "# derived from the 3DTK example scan001 (tools/make_pointcloud_fixtures.py)\n"
        "VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT {vp}\nPOINTS {n}\nDATA {data}\n"
    ).encode()


def ply_header(n: int, origin: np.ndarray, fmt: str) -> bytes:
    o = " ".join(f"{v:.9g}" for v in origin)
    return (
        f"ply\nformat {fmt} 1.0\n"
        "comment derived from the 3DTK example scan001 (tools/make_pointcloud_fixtures.py)\n"
        f"comment origin {o}\nelement vertex {n}\nproperty float x\nproperty float y\n"
        "property float z\nproperty float intensity\nelement face 0\n"
        "property list uchar int vertex_indices\nend_header\n"
    ).encode()


def ascii_rows(values: np.ndarray) -> bytes:
    return "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in values).encode()


def main() -> None:
    if not SCAN_DAT.is_file():
        raise SystemExit(f"{SCAN_DAT} is absent (../shared/data is not part of a clone)")
    OUT.mkdir(parents=True, exist_ok=True)
    # --- OctoMap scan.dat
    with bz2.open(SCAN_DAT, "rt") as fh:
        lines = [next(fh) for _ in range(2000)]
    (OUT / "scan_small.dat").write_text("".join(lines))
    world = np.loadtxt(lines)
    t, R = np.array(NODE1_POSE[:3]), rpy_to_matrix(*NODE1_POSE[3:])
    local = (world[1000:] - t) @ R
    text = "# scan_small.dat as two OctoMap NODE scans (tools/make_pointcloud_fixtures.py)\n"
    text += "NODE 0 0 0 0 0 0\n" + "".join(lines[:1000])
    text += "NODE " + " ".join(f"{v:g}" for v in NODE1_POSE) + "\n"
    text += "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in local)
    (OUT / "scan_nodes.dat").write_text(text)

    # --- 3DTK scans
    reader = ThreeDTKReader(THREEDTK)
    scans = list(reader)
    T = reader.transforms
    scan, pose = scans[1], T[1]
    world = scan.points[::5]
    sensor = ((world - pose[:3, 3]) @ pose[:3, :3]).astype(np.float32)
    intensity = np.linalg.norm(sensor.astype(np.float64), axis=1).astype(np.float32)
    table = np.column_stack([sensor, intensity]).astype(np.float32)
    viewpoint = [*pose[:3, 3].tolist(), *matrix_to_quaternion(pose[:3, :3], order="wxyz").tolist()]
    n = len(table)
    (OUT / "cloud_ascii.pcd").write_bytes(pcd_header(n, viewpoint, "ascii") + ascii_rows(table))
    (OUT / "cloud_binary.pcd").write_bytes(
        pcd_header(n, viewpoint, "binary") + table.astype("<f4").tobytes()
    )
    soa = np.ascontiguousarray(table.T).astype("<f4").tobytes()  # all x, all y, ...
    packed = lzf_compress(soa)
    sizes = np.array([len(packed), len(soa)], dtype="<u4").tobytes()
    (OUT / "cloud_compressed.pcd").write_bytes(
        pcd_header(n, viewpoint, "binary_compressed") + sizes + packed
    )
    wtable = np.column_stack([world, intensity]).astype(np.float32)
    origin = pose[:3, 3]
    (OUT / "cloud_ascii.ply").write_bytes(ply_header(n, origin, "ascii") + ascii_rows(wtable))
    (OUT / "cloud_binary.ply").write_bytes(
        ply_header(n, origin, "binary_little_endian") + wtable.astype("<f4").tobytes()
    )
    graph_scans = [Scan(s.origin, s.points[::16]) for s in scans[:2]]
    write_graph(OUT / "two_scans.graph", graph_scans, poses=list(T[:2]))
    for f in sorted(OUT.iterdir()):
        print(f"{f.name:24s} {f.stat().st_size:8d} bytes")


if __name__ == "__main__":
    main()
