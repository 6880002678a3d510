"""Streaming reader for the KITTI odometry benchmark: Velodyne scans posed by ground truth.

Layout (Geiger et al., "Are we ready for autonomous driving?", CVPR 2012; the odometry
development kit's ``readme.txt``)::

    dataset/
      sequences/NN/velodyne/000000.bin   one scan per frame
      sequences/NN/calib.txt             P0..P3 (cameras) and Tr (velodyne -> cam0)
      poses/NN.txt                       ground truth, sequences 00-10 only

- ``velodyne/FFFFFF.bin``: packed little-endian float32 records ``x y z reflectance``
  (16 bytes per point), metres, in the Velodyne frame (x forward, y left, z up); the file's
  number is the frame number. Only returns are stored, so there is no no-return range.
- ``calib.txt``: lines ``KEY: v1 v2 ...``; ``Tr:`` holds the 3 x 4 matrix (row-major) taking
  Velodyne coordinates to the left grey camera's (``cam0``: x right, y down, z forward).
- ``poses/NN.txt``: line ``i + 1`` is the 3 x 4 pose ``P_i`` (row-major, 12 numbers) of
  ``cam0`` at frame ``i`` in the frame of ``cam0`` at frame 0.

Each scan becomes a :class:`~octolgp.scan.Scan` in a world frame fixed at frame 0: by default
(``world="velodyne"``) the Velodyne's at frame 0 (``Tr^-1 P_i Tr p``, origin ``Tr^-1 P_i Tr
0``: x forward, y left, z up, as octolgp's height colours, slices and ``--z-range`` expect);
with ``world="cam0"`` the poses' own, ``cam0``'s at frame 0 (``P_i Tr p``: y down).
"""

from __future__ import annotations

import re
from collections.abc import Generator
from pathlib import Path

import numpy as np

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io import limits
from octolgp.io.pointcloud import READ_ERRORS, CloudReader
from octolgp.scan import FloatArray, Scan

__all__ = [
    "KittiReader",
    "looks_like_kitti",
    "read_kitti",
    "read_kitti_calib",
    "read_kitti_poses",
]

RECORD = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("reflectance", "<f4")])
"""One Velodyne point of a ``.bin`` file: 16 bytes."""

_FRAME_NAME = re.compile(r"(\d+)\.bin")
_RIGID_TOL = 1e-3  # |R^T R - I| and |det R - 1| allowed in Tr and the poses (float32 text)
_WORLDS = ("cam0", "velodyne")


def looks_like_kitti(path: str | Path) -> bool:
    """Tell whether ``path`` is a KITTI sequence: ``calib.txt`` and ``velodyne/*.bin``."""
    p = Path(path)
    velodyne = p / "velodyne"
    return (
        (p / "calib.txt").is_file()
        and velodyne.is_dir()
        and any(_FRAME_NAME.fullmatch(f.name) for f in velodyne.iterdir())
    )


def _read_lines(path: Path, what: str) -> list[str]:
    """The lines of a text file; an unreadable one raises naming ``what`` and the file."""
    if not path.is_file():
        raise MapFileNotFound(f"KITTI {what} {str(path)!r} does not exist")
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise OctolgpError(f"KITTI {what} {path}: unreadable: {exc}") from None


def _rigid(matrices: FloatArray) -> FloatArray:
    """Which 3 x 4 matrices ``(n, 3, 4)`` have a rotation as their 3 x 3 part, shape (n,) bool."""
    R = matrices[:, :, :3]
    gram = np.einsum("nji,njk->nik", R, R)  # R^T R
    ortho = np.abs(gram - np.eye(3)).max(axis=(1, 2)) < _RIGID_TOL
    return np.asarray(ortho & (np.abs(np.linalg.det(R) - 1.0) < _RIGID_TOL))


def _homogeneous(matrices: FloatArray) -> FloatArray:
    """``(n, 3, 4)`` to ``(n, 4, 4)`` with the last row ``0 0 0 1``."""
    out = np.zeros((matrices.shape[0], 4, 4))
    out[:, :3, :] = matrices
    out[:, 3, 3] = 1.0
    return out


def read_kitti_calib(path: str | Path) -> FloatArray:
    """Read ``Tr`` (Velodyne to ``cam0``) from a KITTI odometry ``calib.txt``.

    Parameters
    ----------
    path : str or Path
        The ``calib.txt``: lines ``KEY: numbers``; other keys (``P0``..``P3``) are checked
        for form and ignored.

    Returns
    -------
    ndarray of shape (4, 4)
        ``T_cam0_velodyne``, metres.

    Raises
    ------
    MapFileNotFound
        If the file does not exist.
    OctolgpError
        On a line that is not ``KEY: numbers`` or a ``Tr`` without 12 numbers or not rigid
        (``KITTI calib path:line: why``), or no ``Tr`` line (``KITTI calib path: ...``).
    """
    p = Path(path)
    found: FloatArray | None = None
    for i, line in enumerate(_read_lines(p, "calib"), start=1):
        if not line.strip():
            continue
        key, colon, rest = line.partition(":")
        if not colon or not key.strip() or len(key.split()) != 1:
            raise OctolgpError(
                f"KITTI calib {p}:{i}: expected 'KEY: numbers', got {line.strip()[:80]!r}"
            )
        try:
            values = np.array([float(t) for t in rest.split()])
        except ValueError:
            raise OctolgpError(
                f"KITTI calib {p}:{i}: {key.strip()}: non-numeric value in {rest.strip()[:80]!r}"
            ) from None
        if not np.isfinite(values).all():
            raise OctolgpError(f"KITTI calib {p}:{i}: {key.strip()}: NaN or inf")
        if key.strip() != "Tr":
            continue
        if found is not None:
            raise OctolgpError(f"KITTI calib {p}:{i}: repeated Tr")
        if values.size != 12:
            raise OctolgpError(
                f"KITTI calib {p}:{i}: Tr needs 12 numbers (3 x 4, row-major), got {values.size}"
            )
        Tr = values.reshape(1, 3, 4)
        if not _rigid(Tr)[0]:
            raise OctolgpError(f"KITTI calib {p}:{i}: Tr's 3 x 3 part is not a rotation")
        found = _homogeneous(Tr)[0]
    if found is None:
        raise OctolgpError(f"KITTI calib {p}: no 'Tr:' line (the velodyne-to-cam0 transform)")
    return found


def read_kitti_poses(path: str | Path) -> FloatArray:
    """Read KITTI ground-truth poses: one 3 x 4 row-major matrix (12 numbers) per line.

    Parameters
    ----------
    path : str or Path
        ``poses/NN.txt``; line ``i + 1`` is the pose of ``cam0`` at frame ``i`` in the frame of
        ``cam0`` at frame 0. Blank lines at the end are ignored; blank lines elsewhere are
        errors, since they would shift the frames.

    Returns
    -------
    ndarray of shape (n, 4, 4)
        ``T_world_cam0`` per frame, metres.

    Raises
    ------
    MapFileNotFound
        If the file does not exist.
    OctolgpError
        On a line without 12 finite numbers or with a non-rigid rotation
        (``KITTI poses path:line: why``), or no pose at all.
    """
    p = Path(path)
    lines = _read_lines(p, "poses")
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise OctolgpError(f"KITTI poses {p}: no poses")
    rows = [line.split() for line in lines]
    counts = np.array([len(r) for r in rows])
    bad = np.flatnonzero(counts != 12)
    if bad.size:
        i = int(bad[0])
        raise OctolgpError(
            f"KITTI poses {p}:{i + 1}: expected 12 numbers (3 x 4, row-major), got {counts[i]}"
        )
    try:
        values = np.array(rows, dtype=np.float64)
    except ValueError:
        i = next(k for k, r in enumerate(rows) if not _numeric(r))
        raise OctolgpError(
            f"KITTI poses {p}:{i + 1}: non-numeric value in {lines[i].strip()[:80]!r}"
        ) from None
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        raise OctolgpError(f"KITTI poses {p}:{int(np.argmin(finite)) + 1}: NaN or inf")
    matrices = values.reshape(-1, 3, 4)
    rigid = _rigid(matrices)
    if not rigid.all():
        raise OctolgpError(
            f"KITTI poses {p}:{int(np.argmin(rigid)) + 1}: the 3 x 3 part is not a rotation"
        )
    return _homogeneous(matrices)


def _numeric(tokens: list[str]) -> bool:
    try:
        [float(t) for t in tokens]
    except ValueError:
        return False
    return True


class KittiReader(CloudReader):
    """A one-pass iterator of :class:`~octolgp.scan.Scan` over a KITTI odometry sequence.

    Parameters
    ----------
    path : str or Path
        The sequence directory ``.../sequences/NN`` (``calib.txt``, ``velodyne/*.bin``).
    poses : str or Path, optional
        Ground-truth poses; ``.../poses/NN.txt`` beside ``sequences/`` when omitted.
    world : {"velodyne", "cam0"}
        The world frame: the Velodyne at frame 0 (default; z up), or ``cam0`` at frame 0,
        the poses' own (y down).
    skip_bad : bool
        Skip and count points with a NaN or inf coordinate and unreadable scans (a size that
        is not a multiple of 16 bytes, no finite point) instead of raising. ``calib.txt`` and
        the poses are always strict.
    max_range : float, optional
        Passed to each :class:`~octolgp.scan.Scan`, metres (the files hold returns only).

    Attributes
    ----------
    files : tuple of Path
        The ``.bin`` files, in frame order.
    frames : tuple of int
        Their frame numbers (the file names).
    calibration : ndarray of shape (4, 4)
        ``Tr``: Velodyne to ``cam0``.
    transforms : ndarray of shape (n, 4, 4)
        ``T_world_velodyne`` per file; the scan's origin is ``T[:3, 3]``.
    skipped, bad_lines, bad_scans
        See :class:`~octolgp.io.pointcloud.CloudReader`; ``bad_lines`` holds
        ``(file, point index)``.

    Raises
    ------
    MapFileNotFound
        At construction, if ``path``, ``calib.txt`` or the poses file does not exist.
    OctolgpError
        At construction, on bad arguments, no ``velodyne/*.bin``, a malformed ``calib.txt`` or
        poses file, or fewer poses than the highest frame needs (all naming the file and
        line); while iterating, on a ``.bin`` whose size is not a multiple of 16 bytes or a
        non-finite point (``KITTI path:point i: why``).
    """

    kind = "KITTI"

    def __init__(
        self,
        path: str | Path,
        *,
        poses: str | Path | None = None,
        world: str = "velodyne",
        skip_bad: bool = False,
        max_range: float | None = None,
    ) -> None:
        super().__init__(path, skip_bad=skip_bad, max_range=max_range)
        if world not in _WORLDS:
            raise OctolgpError(f"read_kitti: world must be one of {_WORLDS}, got {world!r}")
        if not self.path.is_dir():
            raise OctolgpError(f"KITTI sequence {str(self.path)!r} is not a directory")
        self.calibration = read_kitti_calib(self.path / "calib.txt")
        self.files, self.frames = self._discover()
        if poses is None:
            poses = self.path.parent.parent / "poses" / f"{self.path.name}.txt"
            if not Path(poses).is_file():
                raise MapFileNotFound(
                    f"KITTI poses {str(poses)!r} do not exist (sequences 11-21 have no ground "
                    "truth): pass the poses file"
                )
        self.poses_path = Path(poses)
        cam0 = read_kitti_poses(self.poses_path)
        last = self.frames[-1]
        if last >= cam0.shape[0]:
            raise OctolgpError(
                f"KITTI poses {self.poses_path}:{cam0.shape[0] + 1}: no pose for frame {last} "
                f"({self.files[-1].name}): {cam0.shape[0]} poses, fewer than the scans need"
            )
        # world <- cam0_i <- velodyne: P_i Tr; in the Velodyne's frame 0: Tr^-1 P_i Tr
        T = cam0[list(self.frames)] @ self.calibration
        if world == "velodyne":
            T = np.linalg.inv(self.calibration) @ T
        self.transforms: FloatArray = T

    def _discover(self) -> tuple[tuple[Path, ...], tuple[int, ...]]:
        """The ``velodyne/NNNNNN.bin`` files and their frame numbers, in frame order."""
        velodyne = self.path / "velodyne"
        found: dict[int, Path] = {}
        if velodyne.is_dir():
            for f in velodyne.iterdir():
                match = _FRAME_NAME.fullmatch(f.name)
                if match and f.is_file():
                    n = int(match[1])
                    if n in found:
                        raise OctolgpError(f"KITTI scans: both {found[n]} and {f} are frame {n}")
                    found[n] = f
        if not found:
            raise OctolgpError(f"KITTI sequence {str(self.path)!r}: no velodyne/NNNNNN.bin files")
        frames = tuple(sorted(found))
        return tuple(found[n] for n in frames), frames

    def _generate(self) -> Generator[Scan, None, None]:
        for path, T in zip(self.files, self.transforms, strict=True):
            try:
                scan = self._read_scan(path, T)
            except OctolgpError as exc:
                self.bad_scan(exc)
                continue
            yield scan

    def _read_scan(self, path: Path, T: FloatArray) -> Scan:
        """Read one ``.bin`` and move it into the world by ``T`` (4 x 4).

        A file of more than :data:`~octolgp.io.limits.MAX_SCAN_POINTS` records is refused
        from its size, before it is read.
        """
        try:
            limits.check_points(path.stat().st_size // RECORD.itemsize, f"KITTI {path}: the file")
            raw = path.read_bytes()
        except READ_ERRORS as exc:
            raise OctolgpError(f"KITTI {path}: unreadable: {exc}") from None
        if len(raw) % RECORD.itemsize:
            raise OctolgpError(
                f"KITTI {path}: byte {len(raw) - len(raw) % RECORD.itemsize}: size {len(raw)} "
                f"is not a multiple of {RECORD.itemsize} (float32 x, y, z, reflectance)"
            )
        records = np.frombuffer(raw, dtype=RECORD)
        with np.errstate(invalid="ignore"):  # a signalling NaN in the file; caught as NaN
            xyz = np.column_stack([records[a].astype(np.float64) for a in "xyz"])
        bad = np.flatnonzero(~np.isfinite(xyz).all(axis=1))
        for r in bad:
            self.bad_line(path, int(r), "NaN or inf in x/y/z", unit="point ")
        if bad.size:
            xyz = np.delete(xyz, bad, axis=0)
        return self.make_scan(path, "", T[:3, 3].copy(), [xyz], T[:3, :3])


def read_kitti(
    path: str | Path,
    *,
    poses: str | Path | None = None,
    world: str = "velodyne",
    skip_bad: bool = False,
    max_range: float | None = None,
) -> KittiReader:
    """Open a KITTI odometry sequence as a stream of scans; see :class:`KittiReader`."""
    return KittiReader(path, poses=poses, world=world, skip_bad=skip_bad, max_range=max_range)
