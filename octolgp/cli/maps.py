"""The commands on a map file: ``query`` (P(occupied) at points), ``export``, ``correct``."""

from __future__ import annotations

import argparse
from pathlib import Path

from octolgp.errors import OctolgpError

__all__ = ["cmd_correct", "cmd_export", "cmd_query"]


def cmd_query(args: argparse.Namespace) -> int:
    """``octolgp query``: P(occupied) of a map file at the points of a ``.npy``, into a ``.npy``."""
    import numpy as np

    from octolgp.mapping.online import OnlineMap

    pts_path = Path(args.points)
    if not pts_path.is_file():
        raise OctolgpError(f"--points {str(pts_path)!r} does not exist")
    try:
        pts = np.load(pts_path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise OctolgpError(f"--points {str(pts_path)!r} is not a .npy array: {exc}") from None
    with OnlineMap.open(args.map) as m:
        prob = m.occupancy(pts, interpolate=not args.nearest)
    np.save(args.out, prob)
    print(f"wrote {args.out}: P(occupied) at {prob.size} points")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """``octolgp export``: a map file as OctoMap ``.bt``/``.ot``, PLY voxel centres or a PNG."""
    import numpy as np

    from octolgp.export.image import write_png
    from octolgp.export.ply import write_ply
    from octolgp.mapping.online import OnlineMap

    out = Path(args.out)
    kinds = (".bt", ".ot", ".ply", ".png")
    if out.suffix not in kinds:
        raise OctolgpError(f"--out must end in one of {', '.join(kinds)}, got {str(out)!r}")
    with OnlineMap.open(args.map) as m:
        if out.suffix in (".bt", ".ot"):
            nodes = m.export_octomap(out, threshold=args.threshold)
            print(f"wrote {out}: {nodes} OctoMap nodes")
            return 0
        centres, prob = m.voxels()
        res = m.config.resolution
    if out.suffix == ".ply":
        keep = prob > args.threshold
        write_ply(out, centres[keep], prob[keep])
        print(f"wrote {out}: {int(keep.sum())} occupied voxel centres with P(occupied)")
        return 0
    if centres.shape[1] == 3:  # a height slice of a 3D map
        z = args.z if args.z is not None else float(np.median(centres[:, 2]))
        layer = np.floor(centres[:, 2] / res) == np.floor(z / res)
        centres, prob = centres[layer, :2], prob[layer]
    write_png(out, centres, prob, res)
    print(f"wrote {out}: {prob.size} voxels")
    return 0


def cmd_correct(args: argparse.Namespace) -> int:
    """``octolgp correct``: apply pose corrections to a map file, in one transaction."""
    from octolgp.io.corrections import read_corrections
    from octolgp.mapping.online import OnlineMap

    with OnlineMap.open(args.map) as m:
        corrections = read_corrections(args.poses, m.config.dim)
        update = m.correct_scans(corrections)
    print(
        f"corrected {len(corrections)} scans of {args.map}: {update.refit_leaves} leaves "
        f"rebuilt, {update.removed_leaves} removed, in {update.seconds:.2f} s"
    )
    return 0
