"""Pass 1 over a Rerun recording: which entities, timelines, scan rows and poses it holds.

:class:`Survey` records each chunk of a recording without keeping point data: the rows that
may become scans (``octolgp/scan`` records, ``Points3D``/``Points2D`` rows), with their
times, and every ``Transform3D`` row as a parent-from-child matrix. A ``Transform3D`` is
composed from its own components only (each log replaces the whole transform):
``translation · rotation_axis_angle · quaternion · scale · mat3x3``, inverted for
``relation=ChildFromParent``. Rotations come from :mod:`octolgp.geometry.rotations`.

Also the Arrow-to-NumPy helpers the reader (:mod:`octolgp.io.rrd_read`) shares, and
entity-path helpers. rerun's chunks are used through their Arrow record batches only; nothing
here imports rerun.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from octolgp.geometry.rotations import axis_angle_to_matrix, quaternion_to_matrix
from octolgp.io.rrd_format import CHECKSUM_COMPONENT, DISPLAY_MARK, SCAN_ARCHETYPE, SCAN_ENTITY
from octolgp.scan import FloatArray

__all__ = [
    "IntArray",
    "Rows",
    "Survey",
    "data_columns",
    "entity_chain",
    "entity_path",
    "flat_values",
]

IntArray = NDArray[np.int64]

_POINT_COMPONENTS = MappingProxyType({"Points3D:positions": 3, "Points2D:positions": 2})
_TRANSFORM_COMPONENTS = frozenset(
    f"Transform3D:{name}"
    for name in (
        "translation",
        "rotation_axis_angle",
        "quaternion",
        "scale",
        "mat3x3",
        "relation",
        "child_frame",
        "parent_frame",
    )
)
_FRAME_COMPONENTS = ("Transform3D:child_frame", "Transform3D:parent_frame")
_CHILD_FROM_PARENT = 2  # rerun.TransformRelation.ChildFromParent


# --------------------------------------------------------------------------- arrow -> numpy


def _lengths(col: Any) -> IntArray:
    """Instances per row of a list column (0 where null)."""
    return np.asarray(col.value_lengths().fill_null(0).to_numpy(), dtype=np.int64)


def flat_values(values: Any, width: int) -> FloatArray:
    """A fixed-size-list array as a float64 ``(m, width)`` array."""
    flat = values.flatten().to_numpy(zero_copy_only=False)
    return np.asarray(flat, dtype=np.float64).reshape(-1, width)


def _first_instances(col: Any, width: int) -> tuple[FloatArray, NDArray[np.bool_]]:
    """First instance of each row of a ``list<fixed_size_list<float>[width]>`` column."""
    has = _lengths(col) > 0
    start = np.asarray(col.offsets.to_numpy(), dtype=np.int64)[:-1]
    out = np.zeros((len(has), width))
    if has.any():
        out[has] = flat_values(col.values, width)[start[has]]
    return out, has


def _index_columns(rb: Any) -> dict[str, tuple[str, IntArray]]:
    """Timeline columns of a chunk: name -> (kind, int64 values; nanoseconds for times)."""
    out: dict[str, tuple[str, IntArray]] = {}
    for f in rb.schema:
        if (f.metadata or {}).get(b"rerun:kind") != b"index":
            continue
        values = rb.column(f.name).to_numpy(zero_copy_only=False)
        kind = {"M": "timestamp", "m": "duration"}.get(values.dtype.kind, "sequence")
        out[f.name] = (kind, np.asarray(values.view(np.int64), dtype=np.int64))
    return out


def data_columns(rb: Any) -> dict[str, Any]:
    """Component columns of a chunk by component identifier (``Points3D:positions``)."""
    out: dict[str, Any] = {}
    for i, f in enumerate(rb.schema):
        md = f.metadata or {}
        if md.get(b"rerun:kind") in (b"index", b"control"):
            continue
        name = md.get(b"rerun:component", f.name.encode()).decode()
        out[name] = rb.column(i)
    return out


# --------------------------------------------------------------------------- transforms


def _transform_rows(cols: dict[str, Any]) -> tuple[FloatArray, NDArray[np.bool_], bool]:
    """The ``Transform3D`` rows of a chunk as parent-from-child matrices ``(rows, 4, 4)``.

    Each logged ``Transform3D`` replaces the whole transform, so a row is built from its own
    components only: ``translation · rotation_axis_angle · quaternion · scale · mat3x3``.

    Returns
    -------
    matrices, is_transform_row, uses_named_frames
    """
    rows = len(next(iter(cols.values())))
    M = np.tile(np.eye(4), (rows, 1, 1))
    any_row = np.zeros(rows, dtype=bool)
    named = False
    for name, col in cols.items():
        any_row |= _lengths(col) > 0
        named |= name in _FRAME_COMPONENTS and bool((_lengths(col) > 0).any())

    def then(block: FloatArray, has: NDArray[np.bool_]) -> None:
        A = np.tile(np.eye(4), (rows, 1, 1))
        A[has, :3, :3] = block[has]
        M[:] = M @ A

    if (col := cols.get("Transform3D:translation")) is not None:
        t, has = _first_instances(col, 3)
        M[has, :3, 3] = t[has]
    if (col := cols.get("Transform3D:rotation_axis_angle")) is not None:
        has = _lengths(col) > 0
        start = np.asarray(col.offsets.to_numpy(), dtype=np.int64)[:-1]
        axis_arr, angle_arr = col.values.flatten()
        axis = np.zeros((rows, 3))
        angle = np.zeros(rows)
        axis[has] = flat_values(axis_arr, 3)[start[has]]
        angle[has] = np.asarray(angle_arr.to_numpy(zero_copy_only=False), float)[start[has]]
        then(axis_angle_to_matrix(axis, angle), has)
    if (col := cols.get("Transform3D:quaternion")) is not None:
        q, has = _first_instances(col, 4)
        q[~(np.linalg.norm(q, axis=1) > 0)] = (0.0, 0.0, 0.0, 1.0)  # zero or NaN: no rotation
        then(quaternion_to_matrix(q, order="xyzw"), has)
    if (col := cols.get("Transform3D:scale")) is not None:
        s, has = _first_instances(col, 3)
        then(np.eye(3) * s[:, None, :], has)
    if (col := cols.get("Transform3D:mat3x3")) is not None:
        m, has = _first_instances(col, 9)
        then(m.reshape(rows, 3, 3).transpose(0, 2, 1), has)  # stored column-major
    if (col := cols.get("Transform3D:relation")) is not None:
        has = _lengths(col) > 0
        start = np.asarray(col.offsets.to_numpy(), dtype=np.int64)[:-1]
        relation = np.zeros(rows, dtype=np.int64)
        relation[has] = np.asarray(col.values.to_numpy(zero_copy_only=False))[start[has]]
        inverse = relation == _CHILD_FROM_PARENT
        if inverse.any():
            M[inverse] = np.linalg.inv(M[inverse])
    return M, any_row, named


# --------------------------------------------------------------------------- survey (pass 1)


@dataclass(slots=True)
class Rows:
    """Rows of one chunk that may become scans, or that hold transforms.

    Attributes
    ----------
    chunk : str
        The chunk's id, to find it again in pass 2.
    seq : int
        The chunk's position in the stream (later chunks win ties).
    rows : ndarray of int64
        The rows, within the chunk.
    times : dict of str to ndarray of int64
        Each timeline's value at those rows (nanoseconds for time timelines).
    static : bool
        Whether the chunk is static.
    dim : int
        2 or 3 for ``Points2D``/``Points3D`` rows, else 0.
    matrices : ndarray of shape (len(rows), 4, 4), optional
        Parent-from-child transforms of ``Transform3D`` rows.
    """

    chunk: str
    seq: int
    rows: IntArray
    times: dict[str, IntArray]
    static: bool = False
    dim: int = 0
    matrices: FloatArray | None = None


@dataclass(slots=True)
class Survey:
    """What one pass over a recording found: entities, timelines, scan rows and poses.

    Attributes
    ----------
    entities : set of str
        Every entity path seen (rerun's internal ``/__...`` ones left out).
    timeline_kinds : dict of str to str
        ``"sequence"``, ``"timestamp"`` or ``"duration"`` per timeline.
    points : dict of str to list of Rows
        Non-static ``Points3D``/``Points2D`` rows per entity.
    static_points : set of str
        Entities with static points only (not scans).
    scans : list of Rows
        The ``octolgp/scan`` records.
    checksummed : bool
        Whether any chunk of ``octolgp/scan`` records has a checksum column (then every
        record must have one).
    displays : dict of str to list of Rows
        Points rows marked as the display copy of a scan that has an exact copy
        (:data:`~octolgp.io.rrd_format.DISPLAY_MARK`), per entity.
    poses : dict of str to list of Rows
        ``Transform3D`` rows per entity, with their matrices.
    named_frames : set of str
        Entities using named transform frames (not supported).
    chunks : int
        Chunks seen.
    """

    entities: set[str] = field(default_factory=set)
    timeline_kinds: dict[str, str] = field(default_factory=dict)
    points: dict[str, list[Rows]] = field(default_factory=dict)
    static_points: set[str] = field(default_factory=set)
    scans: list[Rows] = field(default_factory=list)
    checksummed: bool = False
    displays: dict[str, list[Rows]] = field(default_factory=dict)
    poses: dict[str, list[Rows]] = field(default_factory=dict)
    named_frames: set[str] = field(default_factory=set)
    chunks: int = 0

    def add(self, chunk: Any) -> None:
        """Record one chunk; only times and transforms are kept, never point data."""
        entity: str = chunk.entity_path
        seq, self.chunks = self.chunks, self.chunks + 1
        if entity.startswith("/__"):
            return
        self.entities.add(entity)
        rb = chunk.to_record_batch()
        index = _index_columns(rb)
        for name, (kind, _) in index.items():
            self.timeline_kinds.setdefault(name, kind)
        cols = data_columns(rb)
        static = bool(chunk.is_static)

        def rows_of(mask: NDArray[np.bool_]) -> Rows:
            rows = np.flatnonzero(mask)
            times = {name: values[rows] for name, (_, values) in index.items()}
            return Rows(chunk.id, seq, rows, times, static)

        if entity == "/" + SCAN_ENTITY and f"{SCAN_ARCHETYPE}:points" in cols:
            has = _lengths(cols[f"{SCAN_ARCHETYPE}:points"]) > 0
            if has.any() and not static:
                self.scans.append(rows_of(has))
                self.checksummed |= f"{SCAN_ARCHETYPE}:{CHECKSUM_COMPONENT}" in cols
        for name, dim in _POINT_COMPONENTS.items():
            if name in cols:
                has = _lengths(cols[name]) > 0
                if static:
                    self.static_points.add(entity)
                elif has.any():
                    block = rows_of(has)
                    block.dim = dim
                    self.points.setdefault(entity, []).append(block)
                    if DISPLAY_MARK in cols:
                        marked = has & (_lengths(cols[DISPLAY_MARK]) > 0)
                        if marked.any():
                            self.displays.setdefault(entity, []).append(rows_of(marked))
        transform = {k: v for k, v in cols.items() if k in _TRANSFORM_COMPONENTS}
        if transform:
            M, has, named = _transform_rows(transform)
            if named:
                self.named_frames.add(entity)
            if has.any():
                block = rows_of(has)
                block.matrices = M[has]
                self.poses.setdefault(entity, []).append(block)
        if "CoordinateFrame:frame" in cols:
            self.named_frames.add(entity)


def entity_path(path: str) -> str:
    """Normalise an entity path to rerun's form: a leading ``/``, no trailing ``/``."""
    return "/" + path.strip().strip("/")


def entity_chain(entity: str) -> list[str]:
    """The entity and its ancestors, root first: ``/a/b`` -> ``['/', '/a', '/a/b']``."""
    parts = entity.strip("/").split("/")
    return ["/"] + ["/" + "/".join(parts[: i + 1]) for i in range(len(parts)) if parts[0]]
