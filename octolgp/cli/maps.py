"""The commands on a map file: ``info``, ``query`` (P(occupied) at points), ``export``, ``correct``."""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from octolgp.cli.configs import check_outputs
from octolgp.errors import OctolgpError

if TYPE_CHECKING:
    import numpy as np

__all__ = ["cmd_correct", "cmd_export", "cmd_info", "cmd_query", "map_info"]


def map_info(path: str | Path) -> dict[str, object]:
    """What a map file holds, read without fitting a leaf or changing the file.

    Returns
    -------
    dict
        ``dim``, ``resolution`` (m), ``engine``, ``scans``, ``journal`` (the scans a
        correction can still reach, ``first``-``last``), ``leaves``, ``extent`` (the
        box of the leaves, metres, world frame: ``[min, max]`` per axis; ``None`` when
        empty), ``hyperparameters`` (``None`` while learning), the sensor model
        (``free_range``, ``no_return_range``, ``fill_voxels``) and ``file_bytes`` (the file
        with its write-ahead log).
    """
    import numpy as np

    from octolgp.geometry.keys import unpack_keys
    from octolgp.mapping.online import OnlineMap

    p = Path(path)
    with OnlineMap.open(p, read_only=True) as m:
        c, keys = m.config, np.fromiter(m.store, dtype=np.int64)
        extent = None
        if keys.size:
            lo, hi = m.grid.box(unpack_keys(keys, c.dim))
            extent = [[float(a), float(b)] for a, b in zip(lo.min(0), hi.max(0), strict=True)]
        hp = m.hyperparameters
        info: dict[str, object] = {
            "dim": c.dim,
            "resolution": c.resolution,
            "engine": c.online.engine,
            "scans": m.n_scans,
            "journal": [m.journal_start + 1, m.n_scans] if m.n_scans > m.journal_start else None,
            "leaves": int(keys.size),
            "extent": extent,
            "hyperparameters": None if hp is None else dataclasses.asdict(hp),
            "free_range": c.free_range,
            "no_return_range": c.no_return_range,
            "fill_voxels": c.fill_voxels,
        }
    wal = p.with_name(p.name + "-wal")
    info["file_bytes"] = p.stat().st_size + (wal.stat().st_size if wal.exists() else 0)
    return info


def cmd_info(args: argparse.Namespace) -> int:
    """``octolgp info``: what a map file holds, one ``key: value`` line each (or JSON)."""
    import json

    info = map_info(args.map)
    if args.json:
        print(json.dumps(info))
        return 0
    for key, value in info.items():  # a dozen lines
        if key == "hyperparameters" and isinstance(value, dict):
            value = ", ".join(f"{k}={v:.4g}" for k, v in value.items())
        elif key == "extent" and isinstance(value, list):
            value = " x ".join(f"[{lo:.1f}, {hi:.1f}]" for lo, hi in value) + " m"
        elif key == "journal" and isinstance(value, list):
            value = f"scans {value[0]}-{value[1]} (what a correction can reach)"
        print(f"{key}: {value}")
    return 0


def _load_array(flag: str, path: str) -> np.ndarray:
    """The ``.npy`` array given as ``--flag PATH``, or :class:`OctolgpError` naming the flag."""
    import numpy as np

    p = Path(path)
    if not p.is_file():
        raise OctolgpError(f"{flag} {str(p)!r} does not exist")
    try:
        return np.asarray(np.load(p, allow_pickle=False))
    except (ValueError, OSError) as exc:
        raise OctolgpError(f"{flag} {str(p)!r} is not a .npy array: {exc}") from None


def _write_answers(out: Path, values: np.ndarray, column: str) -> None:
    """``values`` (q,) to ``out``: ``.npy``, or ``.csv`` with a header line ``column``."""
    import numpy as np

    from octolgp.export.common import replacing

    with replacing(out) as tmp, open(tmp, "wb") as fh:  # never half a file at --out
        if out.suffix == ".csv":
            np.savetxt(fh, values, fmt="%.9g", header=column, comments="")
        else:
            np.save(fh, values)


def cmd_query(args: argparse.Namespace) -> int:
    """``octolgp query``: P(occupied), ray casts or distances on a map file, into .npy/.csv."""
    from octolgp.mapping.online import OnlineMap

    out = Path(args.out)
    if out.suffix not in (".npy", ".csv"):
        raise OctolgpError(f"--out must end in .npy or .csv, got {str(out)!r}")
    if args.raycast is None and args.max_range is not None:
        raise OctolgpError("--max-range applies to --raycast only")
    if args.distance is None and args.max_distance is not None:
        raise OctolgpError("--max-distance applies to --distance only")
    if args.raycast is not None and args.max_range is None:
        raise OctolgpError("--raycast needs --max-range (metres along each ray)")
    if args.points is None and args.nearest:
        raise OctolgpError("--nearest applies to --points only")
    if args.raycast is None and args.unknown is not None:
        raise OctolgpError("--unknown applies to --raycast only")
    if args.points is not None and args.threshold is not None:
        raise OctolgpError("--threshold applies to --raycast and --distance only")
    threshold = 0.5 if args.threshold is None else args.threshold
    flag, path = next(
        (f, p)
        for f, p in (
            ("--points", args.points),
            ("--raycast", args.raycast),
            ("--distance", args.distance),
        )
        if p is not None
    )
    data = _load_array(flag, path)
    check_outputs(args.overwrite, out)
    with OnlineMap.open(args.map, read_only=True) as m:
        if args.points is not None:
            values, column, what = (
                m.occupancy(data, interpolate=not args.nearest),
                "p_occupied",
                "P(occupied)",
            )
        elif args.raycast is not None:
            d = m.config.dim
            if data.ndim != 2 or data.shape[1] != 2 * d:
                raise OctolgpError(
                    f"--raycast must be an array of shape (n, {2 * d}) (origins then "
                    f"directions), got {data.shape}"
                )
            try:
                values = m.raycast(
                    data[:, :d],
                    data[:, d:],
                    args.max_range,
                    threshold,
                    unknown=args.unknown or "stop",
                )
            except OctolgpError as exc:
                raise OctolgpError(f"--raycast: {exc}") from None
            column, what = "distance", "ray cast distances"
        else:
            try:
                values = m.distance(data, threshold, max_distance=args.max_distance)
            except OctolgpError as exc:
                raise OctolgpError(f"--distance: {exc}") from None
            column, what = "distance", "distances to the nearest occupied voxel"
    _write_answers(out, values, column)
    print(f"wrote {out}: {what} at {values.size} {'rays' if args.raycast else 'points'}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """``octolgp export``: a map file as OctoMap ``.bt``/``.ot``, PLY/PCD, PNG or nav2 PGM/YAML."""
    import numpy as np

    from octolgp.export.image import write_png
    from octolgp.mapping.online import OnlineMap

    out = Path(args.out)
    kinds = (".bt", ".ot", ".ply", ".pcd", ".png", ".pgm", ".obj")
    if out.suffix not in kinds:
        raise OctolgpError(f"--out must end in one of {', '.join(kinds)}, got {str(out)!r}")
    if args.mesh and out.suffix not in (".ply", ".obj"):
        raise OctolgpError("--mesh applies to --out FILE.ply or FILE.obj only")
    if args.mesh or out.suffix == ".obj":
        from octolgp.export.mesh import write_mesh

        check_outputs(args.overwrite, out)
        with OnlineMap.open(args.map, read_only=True) as m:
            vertices, faces = m.surface(args.threshold)
        write_mesh(out, vertices, faces)
        kind = "triangles" if vertices.shape[1] == 3 else "segments"
        print(f"wrote {out}: {vertices.shape[0]} vertices, {faces.shape[0]} {kind}")
        return 0
    z_range = args.z_range
    if z_range is not None and out.suffix != ".pgm":
        raise OctolgpError("--z-range applies to a nav2 map (--out FILE.pgm) only")
    siblings = [out.with_suffix(".yaml")] if out.suffix == ".pgm" else []
    check_outputs(args.overwrite, out, *siblings)
    with OnlineMap.open(args.map, read_only=True) as m:
        if out.suffix in (".bt", ".ot"):
            nodes = m.export_octomap(out, threshold=args.threshold)
            print(f"wrote {out}: {nodes} OctoMap nodes")
            return 0
        if out.suffix in (".ply", ".pcd"):  # streamed: one chunk of voxels at a time
            from octolgp.export.pcd import write_pcd_chunks
            from octolgp.export.ply import write_ply_chunks

            occupied = ((c[p > args.threshold], p[p > args.threshold]) for c, p in m.voxel_chunks())
            write = write_ply_chunks if out.suffix == ".ply" else write_pcd_chunks
            n = write(out, occupied)
            print(f"wrote {out}: {n} occupied voxel centres with P(occupied)")
            return 0
        res = m.config.resolution
        if out.suffix == ".pgm":  # one chunk of voxels at a time, merged into cells
            return _export_nav2(args, out, m.voxel_chunks, m.config.dim, res, z_range)
        if m.config.dim == 3:  # a height slice of a 3D map: its layer's voxels only
            z = args.z if args.z is not None else median_height(m.voxel_chunks())
            cells = [
                (c[layer, :2], p[layer])
                for c, p in m.voxel_chunks()
                for layer in [np.floor(c[:, 2] / res) == np.floor(z / res)]
            ]
        else:
            cells = list(m.voxel_chunks())
    centres = np.concatenate([np.zeros((0, 2)), *(c for c, _ in cells)])
    prob = np.concatenate([np.zeros(0), *(p for _, p in cells)])
    write_png(out, centres, prob, res)
    print(f"wrote {out}: {prob.size} voxels")
    return 0


def median_height(chunks: Iterable[tuple[np.ndarray, np.ndarray]]) -> float:
    """``np.median`` of the voxel centres' z over chunks of voxels, holding their heights' counts.

    Raises
    ------
    OctolgpError
        On no voxel.
    """
    import numpy as np

    heights: dict[float, int] = {}
    for centres, _ in chunks:  # one chunk per iteration: its distinct heights counted
        z, n = np.unique(centres[:, 2], return_counts=True)
        for value, count in zip(z.tolist(), n.tolist(), strict=True):  # one per layer
            heights[value] = heights.get(value, 0) + count
    if not heights:
        raise OctolgpError("the map has no voxel to draw")
    z_sorted = np.array(sorted(heights))
    ends = np.cumsum([heights[v] for v in z_sorted.tolist()])
    total = int(ends[-1])
    middle = z_sorted[np.searchsorted(ends, [(total - 1) // 2, total // 2], side="right")]
    return float(np.mean(middle))


def _export_nav2(
    args: argparse.Namespace,
    out: Path,
    chunks: Callable[[], Iterator[tuple[np.ndarray, np.ndarray]]],
    dim: int,
    res: float,
    z_range: tuple[float, float] | None,
) -> int:
    """``octolgp export --out FILE.pgm``: a nav2 map, a 3D map sliced (--z) or projected."""
    from octolgp.export.nav2 import trinary_grid_chunks, write_nav2_grid
    from octolgp.export.nav2_read import read_nav2_map

    occupied, free = args.occupied_thresh, args.free_thresh
    if not free < occupied:
        raise OctolgpError(f"--free-thresh ({free}) must be below --occupied-thresh ({occupied})")
    if dim == 3 and args.z is None and z_range is None:
        raise OctolgpError(
            "a 3D map's nav2 export needs --z HEIGHT (a slice) or --z-range ZMIN ZMAX "
            "(a 2.5D projection)"
        )
    if dim == 2 and (args.z is not None or z_range is not None):
        raise OctolgpError("--z and --z-range apply to 3D maps only; this map is 2D")
    grid = trinary_grid_chunks(
        chunks(),
        res,
        occupied_thresh=occupied,
        free_thresh=free,
        z=args.z if dim == 3 else None,
        z_range=None if z_range is None else (z_range[0], z_range[1]),
    )
    yaml = write_nav2_grid(out, grid, occupied_thresh=occupied, free_thresh=free)
    cells = read_nav2_map(yaml).cells
    counts = {name: int((cells == v).sum()) for name, v in (("occupied", 100), ("free", 0))}
    print(
        f"wrote {out} and {yaml}: {cells.shape[1]} x {cells.shape[0]} cells, "
        f"{counts['occupied']} occupied, {counts['free']} free"
    )
    return 0


def cmd_correct(args: argparse.Namespace) -> int:
    """``octolgp correct``: move scans of a map file by corrections or to absolute poses."""
    from octolgp.io.corrections import read_corrections, read_poses
    from octolgp.mapping.online import OnlineMap

    with OnlineMap.open(args.map) as m:
        reach = range(m.journal_start + 1, m.n_scans + 1)
        if args.absolute is not None:
            poses = read_poses(args.absolute, m.config.dim, reach)
            update, n = m.correct_poses(poses), len(poses)
        else:
            corrections = read_corrections(args.poses, m.config.dim, reach)
            update, n = m.correct_scans(corrections), len(corrections)
    print(
        f"corrected {n} scans of {args.map}: {update.refit_leaves} leaves "
        f"rebuilt, {update.removed_leaves} removed, in {update.seconds:.2f} s"
    )
    return 0
