"""Meshes of the map's level set: Wavefront OBJ and PLY (triangles in 3D, segments in 2D)."""

from __future__ import annotations

import numpy as np

from octolgp.errors import OctolgpError
from octolgp.export.common import PathLike, replacing
from octolgp.scan import FloatArray

__all__ = ["write_mesh"]


def write_mesh(path: PathLike, vertices: FloatArray, faces: np.ndarray) -> None:
    """Write a mesh (``faces`` of 3 vertices) or polyline (2) as ``.obj`` or ``.ply``.

    Parameters
    ----------
    path : str or os.PathLike
        ``.obj`` (text; segments as ``l`` lines) or ``.ply`` (binary little-endian;
        triangles as the ``face`` element, segments as the ``edge`` element).
    vertices : ndarray of shape (v, 2) or (v, 3)
        Metres, world frame; 2D vertices get ``z = 0``.
    faces : ndarray of int, shape (f, 3) or (f, 2)
        Vertex indices from 0.

    Raises
    ------
    OctolgpError
        On another suffix or a bad shape.
    """
    suffix = str(path).rsplit(".", 1)[-1].lower()
    if suffix not in ("obj", "ply"):
        raise OctolgpError(f"mesh path must end in .obj or .ply, got {str(path)!r}")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] not in (2, 3) or f.ndim != 2 or f.shape[1] not in (2, 3):
        raise OctolgpError(f"mesh: vertices (v, 2|3) and faces (f, 2|3), got {v.shape}, {f.shape}")
    if v.shape[1] == 2:
        v = np.hstack([v, np.zeros((v.shape[0], 1))])
    with replacing(path) as tmp, open(tmp, "wb") as fh:  # never half a file at path
        if suffix == "obj":
            fh.write(b"# octolgp level set\n")
            np.savetxt(fh, v, fmt="v %.6f %.6f %.6f")
            np.savetxt(fh, f + 1, fmt=("f" if f.shape[1] == 3 else "l") + " %d" * f.shape[1])
            return
        kind = "face" if f.shape[1] == 3 else "edge"
        element = (
            "element face {n}\nproperty list uchar int vertex_indices\n"
            if kind == "face"
            else "element edge {n}\nproperty int vertex1\nproperty int vertex2\n"
        )
        fh.write(
            (
                "ply\nformat binary_little_endian 1.0\ncomment octolgp level set\n"
                f"element vertex {v.shape[0]}\nproperty float x\nproperty float y\n"
                f"property float z\n{element.format(n=f.shape[0])}end_header\n"
            ).encode("ascii")
        )
        fh.write(v.astype("<f4").tobytes())
        if kind == "face":
            rec = np.zeros(f.shape[0], dtype=[("n", "u1"), ("i", "<i4", (3,))])
            rec["n"], rec["i"] = 3, f
            fh.write(rec.tobytes())
        else:
            fh.write(f.astype("<i4").tobytes())
