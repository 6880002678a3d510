"""The npz scan log: a whole scan sequence in one ``.npz`` file (see ``docs/npz-format.md``).

=============== =========== ======= =============================================
array           shape       dtype   meaning
=============== =========== ======= =============================================
``origins``     ``(S, d)``  float64 sensor position of each scan, world frame, m
``points``      ``(N, d)``  float64 all endpoints, scan after scan, world frame, m
``offsets``     ``(S+1,)``  int64   scan ``i`` is ``points[offsets[i]:offsets[i+1]]``
``max_range``   ``(S,)``    float64 optional no-return threshold; NaN means none
``stamps``      ``(S,)``    float64 optional time, seconds; NaN means none
``rotations``   ``(S,d,d)`` float64 optional sensor orientation (``Scan.rotation``); NaN: none
``truth_points````(M, d)``  float64 optional ground-truth test positions, m
``truth_labels````(M,)``    int8    optional, 1 occupied / 0 free
=============== =========== ======= =============================================

The whole file is read and validated when :func:`read_npz` is called, so a corrupt
file raises at the call; the :class:`~octolgp.scan.Scan` objects are then built
lazily, one per ``next``. Before any array is read, the ``.npy`` header of each member
above is read (a few hundred bytes inflated) and the shapes it claims are checked: together
at most :data:`~octolgp.io.limits.MAX_DECOMPRESSED_BYTES`, so a small archive of highly
compressed members (a decompression bomb) is refused at once. No scan may hold more than
:data:`~octolgp.io.limits.MAX_SCAN_POINTS` points.
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
from numpy.lib import format as npy_format
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io import limits
from octolgp.scan import FloatArray, Scan, nearest_rotation

__all__ = ["read_npz", "read_truth", "write_npz"]

_REQUIRED = ("origins", "points", "offsets")
_OPTIONAL = ("max_range", "stamps", "rotations", "truth_points", "truth_labels")
_NPY_MAGIC = b"\x93NUMPY"


def _fail(path: Path, name: str, message: str) -> OctolgpError:
    """Build the error for array ``name`` of the npz scan log at ``path``."""
    return OctolgpError(f"npz scan log {str(path)!r}: array {name!r} {message}")


def _claimed_sizes(path: Path) -> dict[str, tuple[tuple[int, ...], int]]:
    """The shape and bytes that each known member's ``.npy`` header claims, nothing else read.

    Raises
    ------
    OctolgpError
        If the file is one bare ``.npy`` array, or the archive or a member header is
        unreadable.
    """
    try:
        with open(path, "rb") as fh:
            magic = fh.read(len(_NPY_MAGIC))
        if magic == _NPY_MAGIC:
            raise ValueError("it holds one array, not an npz archive")
        claims: dict[str, tuple[tuple[int, ...], int]] = {}
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                name = info.filename.removesuffix(".npy")
                if name not in _REQUIRED + _OPTIONAL:
                    continue
                with zf.open(info) as member:  # inflates only what the header needs
                    version = npy_format.read_magic(member)
                    if version == (1, 0):
                        shape, _, dtype = npy_format.read_array_header_1_0(member)
                    else:  # 2.0 and 3.0 share the layout (3.0 decodes as UTF-8)
                        shape, _, dtype = npy_format.read_array_header_2_0(member)
                nbytes = math.prod(int(n) for n in shape) * dtype.itemsize
                old = claims.get(name, ((), 0))[1]
                claims[name] = (tuple(int(n) for n in shape), old + nbytes)
        return claims
    except Exception as exc:
        # zipfile, zlib, bz2, lzma and numpy's .npy header parser (ast, tokenize) raise a
        # dozen types on a damaged archive; every one of them means the file is unreadable
        msg = f"npz scan log {str(path)!r} is not a readable npz file: {exc}"
        raise OctolgpError(msg) from None


def _check_sizes(path: Path) -> None:
    """Refuse an archive whose arrays claim more than the size limits, before reading them."""
    claims = _claimed_sizes(path)
    total = sum(nbytes for _, nbytes in claims.values())
    if total > limits.MAX_DECOMPRESSED_BYTES:
        name, (shape, nbytes) = max(claims.items(), key=lambda kv: kv[1][1])
        raise _fail(
            path,
            name,
            f"claims shape {shape} ({nbytes} bytes); the arrays together claim {total} bytes, "
            f"more than octolgp.io.limits.MAX_DECOMPRESSED_BYTES "
            f"({limits.MAX_DECOMPRESSED_BYTES})",
        )


def _check_scan_sizes(path: Path, offsets: NDArray[np.generic]) -> None:
    """Refuse ``offsets`` that give a scan more than :data:`~octolgp.io.limits.MAX_SCAN_POINTS`.

    Offsets that are not a 1-D integer array are left to :func:`_validate`.
    """
    if offsets.ndim != 1 or offsets.dtype.kind not in "iu" or len(offsets) < 2:
        return
    counts = np.diff(offsets.astype(np.int64))
    big = int(np.argmax(counts))
    if counts[big] > limits.MAX_SCAN_POINTS:
        raise _fail(
            path,
            "offsets",
            f"gives scan {big} {int(counts[big])} points, more than "
            f"octolgp.io.limits.MAX_SCAN_POINTS ({limits.MAX_SCAN_POINTS})",
        )


def _load_arrays(path: Path) -> dict[str, NDArray[np.generic]]:
    """Read every known array of an npz file into memory (no pickles), sizes checked first."""
    if not path.is_file():
        raise MapFileNotFound(f"npz scan log {str(path)!r} does not exist")
    _check_sizes(path)
    try:
        # our own handle: np.load(path) leaks its file when the content is not an npz
        with open(path, "rb") as fh:
            npz = np.load(fh, allow_pickle=False)
            if not isinstance(npz, np.lib.npyio.NpzFile):  # a bare .npy array
                raise ValueError("it holds one array, not an npz archive")
            with npz:
                arrays: dict[str, NDArray[np.generic]] = {}
                if "offsets" in npz.files:  # small: the scan sizes, before the points are read
                    arrays["offsets"] = np.asarray(npz["offsets"])
                    _check_scan_sizes(path, arrays["offsets"])
                for k in npz.files:
                    if k in _REQUIRED + _OPTIONAL and k not in arrays:
                        arrays[k] = np.asarray(npz[k])
                return arrays
    except OctolgpError:
        raise
    except Exception as exc:
        # zipfile, zlib and numpy's .npy header parser (ast, tokenize) raise a dozen types
        # on a damaged archive; every one of them means the file is unreadable
        msg = f"npz scan log {str(path)!r} is not a readable npz file: {exc}"
        raise OctolgpError(msg) from None


def _float_array(
    path: Path, arrays: dict[str, NDArray[np.generic]], name: str, shape: tuple[int | None, ...]
) -> FloatArray:
    """Validate ``arrays[name]`` as real numbers of ``shape`` (None = any) and cast to float64."""
    if name not in arrays:
        raise _fail(path, name, "is missing")
    arr = arrays[name]
    if arr.dtype.kind not in "iuf":
        raise _fail(path, name, f"must be numeric, got dtype {arr.dtype}")
    wrong = arr.ndim != len(shape) or any(
        w is not None and s != w for s, w in zip(arr.shape, shape, strict=True)
    )
    if wrong:
        want = "(" + ", ".join("*" if w is None else str(w) for w in shape) + ")"
        raise _fail(path, name, f"must have shape {want}, got {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def _validate(
    path: Path, arrays: dict[str, NDArray[np.generic]]
) -> tuple[
    FloatArray, FloatArray, NDArray[np.int64], FloatArray, FloatArray, list[FloatArray | None]
]:
    """Check shapes, dtypes and offsets.

    Returns ``origins, points, offsets, max_range, stamps, rotations`` (a rotation per
    scan, ``None`` where the log gives none).
    """
    origins = _float_array(path, arrays, "origins", (None, None))
    S, d = origins.shape
    if d not in (2, 3):
        raise _fail(path, "origins", f"must have 2 or 3 columns, got {d}")
    points = _float_array(path, arrays, "points", (None, d))
    for name, arr in (("origins", origins), ("points", points)):
        if not np.isfinite(arr).all():
            raise _fail(path, name, "contains NaN or inf")
    if "offsets" not in arrays:
        raise _fail(path, "offsets", "is missing")
    raw = arrays["offsets"]
    if raw.dtype.kind not in "iu" or raw.shape != (S + 1,):
        got = f"{raw.dtype} {raw.shape}"
        raise _fail(path, "offsets", f"must be integers of shape ({S + 1},), got {got}")
    offsets = raw.astype(np.int64)
    if offsets[0] != 0 or offsets[-1] != points.shape[0]:
        raise _fail(path, "offsets", f"must run from 0 to {points.shape[0]} (the number of points)")
    empty = np.flatnonzero(np.diff(offsets) <= 0)
    if empty.size:
        raise _fail(path, "offsets", f"must increase strictly: scan {int(empty[0])} is empty")
    _check_scan_sizes(path, offsets)
    per_scan = np.full(S, np.nan)
    max_range = _float_array(path, arrays, "max_range", (S,)) if "max_range" in arrays else per_scan
    stamps = _float_array(path, arrays, "stamps", (S,)) if "stamps" in arrays else per_scan
    if np.isinf(max_range).any() or (max_range <= 0).any():
        raise _fail(path, "max_range", "must hold values > 0 (NaN for none)")
    if np.isinf(stamps).any():
        raise _fail(path, "stamps", "contains inf (NaN means no stamp)")
    rotations: list[FloatArray | None] = [None] * S
    if "rotations" in arrays:
        given = _float_array(path, arrays, "rotations", (S, d, d))
        for i in range(S):  # one small matrix per scan
            if np.isnan(given[i]).all():
                continue
            try:
                rotations[i] = nearest_rotation(given[i], d, f"row {i}")
            except OctolgpError as exc:
                raise _fail(path, "rotations", f"{exc} (all NaN for none)") from None
    return origins, points, offsets, max_range, stamps, rotations


def read_npz(path: str | Path) -> Iterator[Scan]:
    """Read an npz scan log; validation happens at the call, scans are built lazily.

    Parameters
    ----------
    path : str or Path
        The ``.npz`` file.

    Returns
    -------
    Iterator of Scan
        One scan per row of ``origins``, in file order. A NaN ``max_range`` or
        ``stamp``, or an all-NaN rotation, becomes ``None``.

    Raises
    ------
    MapFileNotFound
        If ``path`` does not exist.
    OctolgpError
        If the file is not an npz archive, or an array is missing or has a wrong
        shape, dtype or value; the message names the array and the file.
    """
    p = Path(path)
    origins, points, bounds, max_range, stamps, rotations = _validate(p, _load_arrays(p))

    def scans() -> Iterator[Scan]:
        for i in range(origins.shape[0]):
            mr, st = float(max_range[i]), float(stamps[i])
            yield Scan(
                origin=origins[i],
                points=points[bounds[i] : bounds[i + 1]],
                max_range=None if np.isnan(mr) else mr,
                stamp=None if np.isnan(st) else st,
                rotation=rotations[i],
            )

    return scans()


def read_truth(path: str | Path) -> tuple[FloatArray, NDArray[np.int8]]:
    """Return the ground truth ``(truth_points (M, d), truth_labels (M,) int8)`` of a log.

    Raises
    ------
    MapFileNotFound
        If ``path`` does not exist.
    OctolgpError
        If the file holds no ground truth (only simulated logs do), or it is malformed.
    """
    p = Path(path)
    arrays = _load_arrays(p)
    if "truth_points" not in arrays or "truth_labels" not in arrays:
        raise OctolgpError(f"npz scan log {str(p)!r} holds no ground truth (truth_points/labels)")
    pts = _float_array(p, arrays, "truth_points", (None, None))
    if pts.shape[1] not in (2, 3) or not np.isfinite(pts).all():
        raise _fail(p, "truth_points", f"must be finite with 2 or 3 columns, got {pts.shape}")
    labels = _float_array(p, arrays, "truth_labels", (pts.shape[0],))
    if not np.isin(labels, (0.0, 1.0)).all():
        raise _fail(p, "truth_labels", "must hold only 0 (free) and 1 (occupied)")
    return pts, labels.astype(np.int8)


def write_npz(
    path: str | Path,
    scans: Iterable[Scan],
    truth_points: ArrayLike | None = None,
    truth_labels: ArrayLike | None = None,
) -> None:
    """Write scans (and optionally ground truth) as an npz scan log.

    Parameters
    ----------
    path : str or Path
        Output file; written as given (no ``.npz`` is appended).
    scans : iterable of Scan
        At least one scan, all of the same dimension ``d``. Their rotations are written
        (``rotations``) when any has one.
    truth_points : array_like of shape (M, d), optional
        Ground-truth test positions, world frame, metres.
    truth_labels : array_like of shape (M,), optional
        1 occupied, 0 free; required together with ``truth_points``.

    Raises
    ------
    OctolgpError
        On no scans, mixed dimensions, or ground truth of the wrong shape or values.
    """
    scan_list = list(scans)
    if not scan_list:
        raise OctolgpError("write_npz: no scans to write")
    if any(not isinstance(s, Scan) for s in scan_list):
        raise OctolgpError("write_npz: scans must be Scan objects")
    d = scan_list[0].dim
    if any(s.dim != d for s in scan_list):
        raise OctolgpError("write_npz: all scans must have the same dimension")
    counts = np.array([len(s) for s in scan_list], dtype=np.int64)
    arrays: dict[str, NDArray[np.generic]] = {
        "origins": np.stack([s.origin for s in scan_list]),
        "points": np.concatenate([s.points for s in scan_list]),
        "offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "max_range": np.array([np.nan if s.max_range is None else s.max_range for s in scan_list]),
        "stamps": np.array([np.nan if s.stamp is None else s.stamp for s in scan_list]),
    }
    if any(s.rotation is not None for s in scan_list):  # the sensor poses, for correct_poses
        none = np.full((d, d), np.nan)
        arrays["rotations"] = np.stack(
            [none if s.rotation is None else s.rotation for s in scan_list]
        )
    if (truth_points is None) != (truth_labels is None):
        raise OctolgpError("write_npz: give truth_points and truth_labels together")
    if truth_points is not None and truth_labels is not None:
        pts = np.asarray(truth_points, dtype=np.float64)
        labels = np.asarray(truth_labels)
        if pts.ndim != 2 or pts.shape[1] != d or not np.isfinite(pts).all():
            raise OctolgpError(f"write_npz: truth_points must be finite (M, {d}), got {pts.shape}")
        if labels.shape != (pts.shape[0],) or not np.isin(labels, (0, 1)).all():
            raise OctolgpError("write_npz: truth_labels must be (M,) of 0 and 1")
        arrays["truth_points"] = pts
        arrays["truth_labels"] = labels.astype(np.int8)
    try:
        with open(path, "wb") as fh:
            np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
    except OSError as exc:
        raise OctolgpError(f"cannot write npz scan log {str(path)!r}: {exc}") from None
