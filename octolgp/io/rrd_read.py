"""Read scans back from a Rerun recording (``.rrd``): octolgp's own or any other.

:class:`RrdScanReader` (:func:`read_rrd`) reads the ``octolgp/scan`` records when the
recording has them (:mod:`octolgp.io.rrd_write` writes them). Any other recording is read the
way the viewer shows it: each row of a ``Points3D``/``Points2D`` entity is one scan, in the
frame of that entity; the world pose of that frame is the composition, from the root down, of
the latest ``Transform3D`` at or before the row's time on the entity and each of its ancestors
(latest-at; static data wins; translation, rotation as axis-angle, quaternion or matrix, and
scale; ``ChildFromParent`` inverted; see :mod:`octolgp.io.rrd_survey`). ``Transform3D`` with
named frames (``child_frame``/``parent_frame``) and ``CoordinateFrame`` are not supported and
raise.

Exact copies: each ``octolgp/scan`` record's CRC-32 (when it has one, see
:mod:`octolgp.io.rrd_format`) is verified, and a mismatch raises naming the scan. The float32
display copy of a scan (the ``Points3D``/``Points2D`` rows that :func:`~octolgp.io.rrd_write.log_scan`
marks, or ``world/sensor/points`` in older octolgp recordings) is never used in place of a
missing exact copy: it has no ``max_range``, so its no-return beams would become hits at the
sensor's maximum range. A recording whose exact copies are all lost is refused unless the
display entity is named (``points=``); scans of which only the display copy survives are left
out with one WARNING saying how many.

Files written by a killed process or cut at any byte (the framing is described in
:mod:`octolgp.io.rrd_format`): a killed writer leaves no End message; rerun 0.41 reads such a
file (with a ``RerunWarning``, which this reader records in ``notes``), but rejects the whole
file when its last message is incomplete. The reader therefore walks the message headers first
and, when the tail is incomplete, reads a temporary copy of the complete messages and reports
the bytes it skipped. In a recording that was not closed, trailing scans later than the last
pose of a moving frame are dropped (their pose may have been lost).

Logging (logger ``octolgp.io.rrd_read``): a WARNING when a recording was not closed or is cut
off, an INFO for each part skipped with ``skip_bad``.
"""

from __future__ import annotations

import logging
import tempfile
import warnings
import weakref
from collections.abc import Callable, Generator, Iterator
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io.base import ScanStream
from octolgp.io.rrd_format import (
    CHECKSUM_COMPONENT,
    LEGACY_MAGICS,
    RRD_MAGIC,
    SCAN_ARCHETYPE,
    SCAN_ENTITY,
    SCAN_TIMELINE,
    scan_checksum,
    scan_framing,
)
from octolgp.io.rrd_survey import (
    IntArray,
    Rows,
    Survey,
    data_columns,
    entity_chain,
    entity_path,
    flat_values,
)
from octolgp.scan import FloatArray, Scan

__all__ = ["RrdScanReader", "read_rrd"]

logger = logging.getLogger(__name__)

_T = TypeVar("_T")
_RERUN_ERRORS = (RuntimeError, ValueError, OSError)
_LEGACY_DISPLAY = "/world/sensor/points"  # the display copy in octolgp recordings without marks
_SINK_METRIC = "/metrics/insert_seconds"  # logged by octolgp's RerunSink only


def _scan_indices(blocks: list[Rows]) -> IntArray:
    """The :data:`~octolgp.io.rrd_format.SCAN_TIMELINE` values of rows (those on it)."""
    parts = [b.times[SCAN_TIMELINE] for b in blocks if SCAN_TIMELINE in b.times]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def _ranges(values: list[int], most: int = 6) -> str:
    """Sorted integers as runs, ``0..4, 7, 9..12``, the first ``most`` runs then ``...``."""
    runs: list[list[int]] = []
    for v in values:
        if runs and v == runs[-1][1] + 1:
            runs[-1][1] = v
        else:
            runs.append([v, v])
    text = [f"{a}" if a == b else f"{a}..{b}" for a, b in runs[:most]]
    return ", ".join(text) + (", ..." if len(runs) > most else "")


def _captured(notes: list[str], fn: Callable[[], _T]) -> _T:
    """Call ``fn``, recording rerun's Python warnings in ``notes`` instead of raising them."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = fn()
    for w in caught:
        text = str(w.message)
        if "no footer" not in text and text not in notes:  # reported by the framing note
            notes.append(text)
    return result


class RrdScanReader(ScanStream):
    """A one-pass iterator of :class:`~octolgp.scan.Scan` over a Rerun recording.

    The recording is read twice: once at construction (times and poses only, so that every
    error about entities and timelines is raised at the call) and once while iterating (the
    point data, one chunk at a time; chunks are held only while an earlier scan is still due).

    Parameters
    ----------
    path : str or Path
        The ``.rrd`` file.
    points : str, optional
        Entity of the scans: ``octolgp/scan`` or a ``Points3D``/``Points2D`` entity. Default:
        ``octolgp/scan`` if present, else the only points entity, else the only one with a
        ``Transform3D`` on it or an ancestor.
    pose : str, optional
        Entity whose frame the points are in; its world pose composes its own and its
        ancestors' ``Transform3D``. Default: the points entity.
    timeline : str, optional
        Timeline giving the order and the pose time. Default: the first sequence timeline of
        the points entity, else its first time timeline (a note says which).
    max_range : float, optional
        No-return threshold given to every scan (generic recordings carry none); overrides
        the stored one of ``octolgp/scan`` records.
    skip_bad : bool
        Skip scans that fail validation, and read up to an unrecognised message, instead of
        raising.

    Attributes
    ----------
    entity, pose_entity, timeline : str
        What was chosen (``pose_entity`` is ``None`` for ``octolgp/scan`` records).
    exact : bool
        Whether the scans are the exact ``octolgp/scan`` records.
    count : int
        Scans planned; iteration yields this many less those skipped by ``skip_bad``.
    skipped : int
        Rows not turned into scans (no pose yet, not on the timeline, no finite point, cut
        off, invalid with ``skip_bad``).
    dropped_points : int
        Non-finite points dropped from generic recordings (a row with none left is skipped).
    skipped_bytes : int
        Bytes at the end of the file that were not read (an incomplete last message).
    lost : int
        Scans of an octolgp recording whose exact copy is missing (cut off or damaged) while
        their display copy is there; they are not replayed.
    closed : bool
        Whether the writer closed the file (it has an End message).
    notes : list of str
        What the reader assumed or skipped, one sentence each.

    Raises
    ------
    MapFileNotFound
        If ``path`` does not exist.
    OctolgpError
        At construction, naming the file, if it is not a Rerun recording, holds no complete
        message, is corrupt, holds no scans, lacks the named entity or timeline, or was
        written by octolgp but holds none of its scans' exact copies (unless ``points=``
        names the display entity); while iterating, if a scan is invalid or its exact copy
        fails its checksum (without ``skip_bad``), naming the scan.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        points: str | None = None,
        pose: str | None = None,
        timeline: str | None = None,
        max_range: float | None = None,
        skip_bad: bool = False,
    ) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise MapFileNotFound(f"Rerun recording {str(self.path)!r} does not exist")
        if not self.path.is_file():
            raise OctolgpError(f"Rerun recording {str(self.path)!r} is not a file")
        if max_range is not None and not (np.isfinite(max_range) and max_range > 0):
            raise OctolgpError(f"read_rrd: max_range must be finite and > 0, got {max_range!r}")
        self.max_range = max_range
        self.skip_bad = skip_bad
        self.notes: list[str] = []
        self.skipped = 0
        self.skipped_bytes = 0
        self.count = 0
        self.dropped_points = 0
        self.lost = 0
        self.entity = ""
        self.pose_entity: str | None = None
        self.closed = False
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self._lazy = self._open(self._readable_copy())
        survey = self._survey()
        self.exact = self._choose_entity(survey, points, pose)
        self.timeline = self._choose_timeline(survey, timeline)
        self._checksummed = survey.checksummed
        self._check_display_copies(survey, explicit=points is not None or pose is not None)
        self._plan(survey)
        self._scans = self._generate()

    # ---------------------------------------------------------------- construction

    def _what(self) -> str:
        return f"Rerun recording {str(self.path)!r}"

    def _readable_copy(self) -> Path:
        """The file itself, or a temporary copy of its complete messages."""
        try:
            with open(self.path, "rb") as fh:
                magic = fh.read(4)
        except OSError as exc:
            raise OctolgpError(f"{self._what()} cannot be read: {exc}") from None
        if magic in LEGACY_MAGICS:
            raise OctolgpError(
                f"{self._what()} is in the old {magic.decode()} format; rerun 0.41 reads "
                f"{RRD_MAGIC.decode()} (re-save it with a newer rerun)"
            )
        if magic != RRD_MAGIC:
            raise OctolgpError(f"{str(self.path)!r} is not a Rerun recording (no RRF2 header)")
        framing = scan_framing(self.path)
        self.closed = framing.closed
        if framing.data_end == 0:
            why = framing.problem or "it holds only a header"
            raise OctolgpError(f"{self._what()} holds no complete message: {why}")
        if framing.corrupt and not self.skip_bad:
            raise OctolgpError(f"{self._what()} is corrupt: {framing.problem}")
        if not framing.closed:
            self.notes.append("the writer did not close the file (no End message); reading it")
            logger.warning("%s was not closed by its writer (no End message)", self._what())
        if framing.problem is None:
            return self.path
        self.skipped_bytes = framing.size - framing.data_end
        self.notes.append(
            f"{framing.problem}: read the first {framing.data_end} of {framing.size} bytes, "
            f"skipped {self.skipped_bytes}"
        )
        logger.warning("%s is incomplete: %s", self._what(), self.notes[-1])
        return self._copy_prefix(framing.data_end)

    def _copy_prefix(self, nbytes: int) -> Path:
        """Copy the first ``nbytes`` to a temporary file that lives as long as the reader."""
        self._tmp = tempfile.TemporaryDirectory(prefix="octolgp-rrd-")
        weakref.finalize(self, self._tmp.cleanup)
        copy = Path(self._tmp.name) / self.path.name
        with open(self.path, "rb") as src, open(copy, "wb") as dst:
            remaining = nbytes
            while remaining > 0:
                block = src.read(min(remaining, 1 << 22))
                if not block:
                    break
                dst.write(block)
                remaining -= len(block)
        return copy

    def _open(self, source: Path) -> Any:
        """A lazy chunk stream over the first recording store (each iteration re-reads it)."""
        import rerun.chunk

        try:
            reader = _captured(self.notes, lambda: rerun.chunk.RrdReader(source))
            stores = _captured(self.notes, reader.recordings)
            lazy = None
            if stores:
                lazy = _captured(self.notes, lambda: reader.stream(store=stores[0]))
        except _RERUN_ERRORS as exc:
            raise OctolgpError(f"{self._what()} is unreadable: {exc}") from None
        if not stores:
            raise OctolgpError(f"{self._what()} holds no recording store")
        if len(stores) > 1:
            self.notes.append(f"the file holds {len(stores)} recordings; reading the first")
        return lazy

    def _stream(self) -> Iterator[Any]:
        """The chunks of the recording, in file order."""
        return _captured(self.notes, lambda: iter(self._lazy))

    def _survey(self) -> Survey:
        """Pass 1: times, transforms and entities of every chunk."""
        survey = Survey()
        stream = self._stream()
        while True:
            try:
                chunk = _captured(self.notes, lambda: next(stream, None))
            except _RERUN_ERRORS as exc:
                if not self.skip_bad:
                    raise OctolgpError(
                        f"{self._what()} is corrupt after {survey.chunks} chunks: {exc}"
                    ) from None
                self.notes.append(f"stopped at chunk {survey.chunks}: {exc}")
                logger.warning("%s is incomplete: %s", self._what(), self.notes[-1])
                break
            if chunk is None:
                break
            survey.add(chunk)
        return survey

    def _choose_entity(self, survey: Survey, points: str | None, pose: str | None) -> bool:
        """Set ``entity`` and ``pose_entity``; tell whether the rows are ``octolgp/scan``."""
        scan_entity = "/" + SCAN_ENTITY
        want = None if points is None else entity_path(points)
        if want == scan_entity or (want is None and pose is None and survey.scans):
            if not survey.scans:
                raise OctolgpError(f"{self._what()} has no {SCAN_ENTITY} records")
            if pose is not None:
                raise OctolgpError(f"read_rrd: pose= does not apply to {SCAN_ENTITY} records")
            self.entity = scan_entity
            return True
        candidates = sorted(survey.points)
        if want is not None:
            if want not in survey.entities:
                raise OctolgpError(f"{self._what()} has no entity {want!r}")
            if want not in survey.points:
                raise OctolgpError(
                    f"{self._what()}: entity {want!r} logs no Points3D/Points2D over time "
                    f"(points entities: {candidates or 'none'})"
                )
            self.entity = want
        elif not candidates:
            static = f" (only static ones: {sorted(survey.static_points)})"
            raise OctolgpError(
                f"{self._what()} has no Points3D/Points2D entity logged over time"
                + (static if survey.static_points else "")
            )
        elif len(candidates) == 1:
            self.entity = candidates[0]
        else:
            posed = [c for c in candidates if any(e in survey.poses for e in entity_chain(c))]
            if len(posed) != 1:
                raise OctolgpError(
                    f"{self._what()} has several points entities {candidates}; "
                    "name one with points="
                )
            self.entity = posed[0]
            self.notes.append(
                f"points entities {candidates}: using {self.entity}, the one under a Transform3D"
            )
        self.pose_entity = self.entity if pose is None else entity_path(pose)
        if self.pose_entity not in survey.entities and pose is not None:
            raise OctolgpError(f"{self._what()} has no pose entity {self.pose_entity!r}")
        chain = entity_chain(self.pose_entity)
        if pose is not None and not any(e in survey.poses for e in chain):
            raise OctolgpError(
                f"{self._what()}: no Transform3D on pose entity {self.pose_entity!r} "
                "or its ancestors"
            )
        framed = sorted({*chain, self.entity} & survey.named_frames)
        if framed:
            raise OctolgpError(
                f"{self._what()}: {framed} use named transform frames "
                "(child_frame/parent_frame/CoordinateFrame), which are not supported"
            )
        return False

    def _display_copies(self, survey: Survey) -> dict[str, list[Rows]]:
        """Points rows that are the float32 display copy of a scan with an exact copy.

        Rows marked by :func:`~octolgp.io.rrd_write.log_scan`, and in an older octolgp
        recording (one with exact records or the sink's metrics) the rows of its default
        display entity.
        """
        out = dict(survey.displays)
        octolgp_made = bool(survey.scans) or _SINK_METRIC in survey.entities
        if octolgp_made and _LEGACY_DISPLAY in survey.points and _LEGACY_DISPLAY not in out:
            out[_LEGACY_DISPLAY] = survey.points[_LEGACY_DISPLAY]
        return out

    def _check_display_copies(self, survey: Survey, *, explicit: bool) -> None:
        """Never let a display copy stand in for an exact one; say what is lost.

        Raises
        ------
        OctolgpError
            If the recording was written by octolgp, none of its exact copies survives and
            the caller did not name an entity.
        """
        displays = self._display_copies(survey)
        if not displays:
            return
        shown = {int(i) for blocks in displays.values() for i in _scan_indices(blocks)}
        if self.exact:
            exact = {int(i) for i in _scan_indices(survey.scans)}
            missing = sorted(shown - exact)
            if missing:
                self.lost = len(missing)
                self.notes.append(
                    f"{len(missing)} of {len(shown | exact)} scans have only their float32 display "
                    f"copy, their exact copy being cut off or damaged ({SCAN_TIMELINE}="
                    f"{_ranges(missing)}); they are not replayed"
                )
                logger.warning("%s: %s", self._what(), self.notes[-1])
            return
        if not explicit and not survey.scans:
            names = sorted(displays)
            raise OctolgpError(
                f"{self._what()} was written by octolgp, but none of the exact copies "
                f"({SCAN_ENTITY}) of its {len(shown)} scans can be read: the file is cut off "
                f"or damaged. Its display copy {names[0]} is float32 and has no max_range, so "
                "its no-return beams would become hits; to replay it anyway, name it "
                f"(points={names[0].lstrip('/')!r}) and give max_range"
            )
        if self.entity in displays and self.max_range is None:
            self.notes.append(
                f"{self.entity} is octolgp's float32 display copy and has no max_range: "
                "no-return beams replay as hits (give max_range, or read the exact copies)"
            )
            logger.warning("%s: %s", self._what(), self.notes[-1])

    def _rows(self, survey: Survey) -> list[Rows]:
        return survey.scans if self.exact else survey.points[self.entity]

    def _choose_timeline(self, survey: Survey, timeline: str | None) -> str:
        """The given timeline (checked), else the first sequence, else the first time one."""
        names: list[str] = []
        for block in self._rows(survey):
            names += [t for t in block.times if t not in names]
        if not names:
            raise OctolgpError(f"{self._what()}: entity {self.entity!r} is on no timeline")
        if timeline is not None:
            if timeline not in names:
                raise OctolgpError(
                    f"{self._what()}: entity {self.entity!r} is not on timeline {timeline!r} "
                    f"(its timelines: {names})"
                )
            return timeline
        sequences = [t for t in names if survey.timeline_kinds[t] == "sequence"]
        times = [t for t in names if t not in sequences and t != "log_time"]
        chosen = (sequences or times or names)[0]
        if not sequences:
            self.notes.append(f"no sequence timeline on {self.entity}; ordered by {chosen!r}")
        elif len(sequences) > 1:
            self.notes.append(f"sequence timelines {sequences}: ordered by {chosen!r}")
        return chosen

    def _latest_at(
        self, survey: Survey, entity: str, q: IntArray
    ) -> tuple[FloatArray, NDArray[np.bool_] | None, int | None]:
        """Latest-at transform of one entity at times ``q`` on the timeline.

        Returns
        -------
        matrices : ndarray of shape (k, 4, 4)
            Parent-from-entity transforms (identity where there is none).
        valid : ndarray of shape (k,) or None
            Whether a transform was logged at or before each time; ``None`` when the entity
            has no moving transform (static, or none on this timeline).
        last : int or None
            Time of its last moving transform.
        """
        blocks = survey.poses.get(entity, [])
        static = [b.matrices for b in blocks if b.static and b.matrices is not None]
        if static:  # static data wins over temporal data
            return np.broadcast_to(static[-1][-1], (len(q), 4, 4)), None, None
        timed = [b for b in blocks if self.timeline in b.times and b.matrices is not None]
        if not timed:
            if blocks:
                self.notes.append(f"Transform3D of {entity} is not on {self.timeline!r}; ignored")
            return np.broadcast_to(np.eye(4), (len(q), 4, 4)), None, None
        T = np.concatenate([b.times[self.timeline] for b in timed])
        S = np.concatenate([np.full(len(b.rows), b.seq) for b in timed])
        R = np.concatenate([b.rows for b in timed])
        Ms = np.concatenate([b.matrices for b in timed if b.matrices is not None])
        order = np.lexsort((R, S, T))  # ties at one time: the last logged wins
        T, Ms = T[order], Ms[order]
        idx = np.searchsorted(T, q, side="right") - 1
        return Ms[np.maximum(idx, 0)], idx >= 0, int(T[-1])

    def _world_poses(self, survey: Survey, q: IntArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """World-from-sensor transforms at times ``q``, and which of them are known."""
        assert self.pose_entity is not None
        chain = entity_chain(self.pose_entity)
        poses: FloatArray = np.broadcast_to(np.eye(4), (len(q), 4, 4))
        keep = np.ones(len(q), dtype=bool)
        last = np.iinfo(np.int64).max
        for entity in chain:  # root first: world_from_sensor = M_root @ ... @ M_sensor
            M, valid, entity_last = self._latest_at(survey, entity, q)
            poses = poses @ M
            if valid is not None:
                keep &= valid
            if entity_last is not None:
                last = min(last, entity_last)
        if not keep.all():
            self.notes.append(f"{int((~keep).sum())} scans logged before their first pose skipped")
        if not any(e in survey.poses for e in chain):
            self.notes.append("no Transform3D: the points are taken as world-frame points")
        late = keep & (q > last)
        if not self.closed and late.any():
            self.notes.append(
                f"{int(late.sum())} scans after the last pose dropped: the file was not closed, "
                "so their pose may be lost"
            )
            logger.warning("%s: %s", self._what(), self.notes[-1])
            keep &= ~late
        return poses, keep

    def _plan(self, survey: Survey) -> None:
        """Order the rows on the timeline and give each its pose and stamp."""
        blocks = self._rows(survey)
        on = [b for b in blocks if self.timeline in b.times]
        off = sum(len(b.rows) for b in blocks if self.timeline not in b.times)
        if off:
            self.skipped += off
            self.notes.append(f"{off} rows of {self.entity} are not on {self.timeline!r}")
        chunks = [c for b in on for c in [b.chunk] * len(b.rows)]
        rows = np.concatenate([b.rows for b in on])
        q = np.concatenate([b.times[self.timeline] for b in on])
        seqs = np.concatenate([np.full(len(b.rows), b.seq) for b in on])
        indices = np.concatenate(
            [b.times.get(SCAN_TIMELINE, np.full(len(b.rows), -1, np.int64)) for b in on]
        )
        dims = np.concatenate([np.full(len(b.rows), b.dim) for b in on])
        # Stamp (s): the ordering timeline if it is a time, else the row's first time timeline.
        kinds = survey.timeline_kinds
        stamps = np.full(len(rows), np.nan)
        start = 0
        for b in on:
            clocks = [t for t in b.times if kinds[t] != "sequence" and t != "log_time"]
            clock = (
                self.timeline if kinds[self.timeline] != "sequence" else next(iter(clocks), None)
            )
            if clock is not None:
                stamps[start : start + len(b.rows)] = b.times[clock] * 1e-9
            start += len(b.rows)
        keep = np.ones(len(rows), dtype=bool)
        poses: FloatArray | None = None
        if not self.exact:
            poses, keep = self._world_poses(survey, q)
        self.skipped += int((~keep).sum())
        order = np.lexsort((rows, seqs, q))
        order = order[keep[order]]
        self._chunks = [chunks[i] for i in order]
        self._rows_in_chunk = rows[order]
        self._times = q[order]
        self._indices = indices[order]
        self._stamps = stamps[order]
        self._poses = None if poses is None else np.ascontiguousarray(poses[order])
        self._dims = dims[order]
        self.count = len(order)
        if self.count == 0:
            raise OctolgpError(
                f"{self._what()}: no scan of {self.entity} could be read ({'; '.join(self.notes)})"
            )

    # ---------------------------------------------------------------- iteration (pass 2)

    def close(self) -> None:
        """Stop reading and remove any temporary copy."""
        super().close()
        if self._tmp is not None:
            self._tmp.cleanup()

    def _generate(self) -> Generator[Scan, None, None]:
        """Stream the point chunks again, yielding scans in timeline order."""
        due: dict[str, list[int]] = {}
        for pos, chunk in enumerate(self._chunks):
            due.setdefault(chunk, []).append(pos)
        ready: dict[int, Scan | None] = {}
        upcoming = 0
        try:
            stream = self._stream()
            while upcoming < self.count:
                try:
                    chunk = _captured(self.notes, lambda: next(stream, None))
                except _RERUN_ERRORS as exc:
                    raise OctolgpError(f"{self._what()} is unreadable: {exc}") from None
                if chunk is None:
                    raise OctolgpError(f"{self._what()} changed while it was being read")
                positions = due.pop(chunk.id, None)
                if positions is None:
                    continue
                ready.update(zip(positions, self._scans_of(chunk, positions), strict=True))
                while upcoming in ready:
                    scan = ready.pop(upcoming)
                    upcoming += 1
                    if scan is not None:
                        yield scan
            if self.dropped_points:
                self.notes.append(f"dropped {self.dropped_points} non-finite points")
        finally:
            if self._tmp is not None:
                self._tmp.cleanup()

    def _scans_of(self, chunk: Any, positions: list[int]) -> list[Scan | None]:
        """Build the scans at plan ``positions`` from one chunk."""
        cols = data_columns(chunk.to_record_batch())
        if self.exact:
            return [self._exact(cols, pos) for pos in positions]
        arrays: dict[int, tuple[FloatArray, IntArray]] = {}
        for dim in sorted({int(self._dims[pos]) for pos in positions}):
            col = cols[f"Points{dim}D:positions"]
            values = flat_values(col.values, dim)
            if dim == 2:  # in the plane z = 0 of the sensor frame
                values = np.concatenate([values, np.zeros((len(values), 1))], axis=1)
            arrays[dim] = values, np.asarray(col.offsets.to_numpy(), dtype=np.int64)
        return [self._posed(*arrays[int(self._dims[pos])], pos) for pos in positions]

    def _posed(self, values: FloatArray, offsets: IntArray, pos: int) -> Scan | None:
        """World-frame scan ``R·p + t`` of one points row (x, y of it for Points2D)."""
        assert self._poses is not None
        row = self._rows_in_chunk[pos]
        dim = int(self._dims[pos])
        local = values[offsets[row] : offsets[row + 1]]
        finite = np.isfinite(local).all(axis=1)
        if not finite.all():
            local = local[finite]
            self.dropped_points += int((~finite).sum())
        if len(local) == 0:
            self.skipped += 1
            return None
        M = self._poses[pos]
        world = local @ M[:3, :3].T + M[:3, 3]
        stamp = self._stamps[pos]
        return self._checked(
            lambda: Scan(
                origin=M[:dim, 3],
                points=world[:, :dim],
                max_range=self.max_range,
                stamp=None if np.isnan(stamp) else float(stamp),
            ),
            pos,
        )

    def _exact(self, cols: dict[str, Any], pos: int) -> Scan | None:
        """The float64 ``octolgp/scan`` record of one row, its checksum verified."""
        row = int(self._rows_in_chunk[pos])

        def raw(name: str) -> NDArray[Any] | None:
            col = cols.get(f"{SCAN_ARCHETYPE}:{name}")
            if col is None or not col[row].is_valid:
                return None
            return np.asarray(col[row].values.to_numpy(zero_copy_only=False))

        def value(name: str) -> FloatArray:
            got = raw(name)
            return np.full(1, np.nan) if got is None else np.asarray(got, dtype=np.float64)

        def verify() -> None:
            stored = raw(CHECKSUM_COMPONENT)
            if stored is None:
                if self._checksummed:
                    raise OctolgpError("its exact copy has lost its checksum: it is damaged")
                return  # written before exact copies carried one
            parts = [raw(n) for n in ("dim", "origin", "points", "max_range", "stamp")]
            if stored.shape != (1,) or any(p is None for p in parts):
                raise OctolgpError("its exact copy is damaged (a component is missing)")
            crc = scan_checksum(int(self._indices[pos]), *parts)  # type: ignore[arg-type]
            if crc != int(stored[0]):
                raise OctolgpError(
                    f"its exact copy is corrupt: CRC-32 {crc:08x}, stored {int(stored[0]):08x}"
                )

        def build() -> Scan:
            verify()
            dim = int(value("dim")[0])
            origin = value("origin")
            max_range, stamp = value("max_range")[0], value("stamp")[0]
            if self.max_range is not None:
                max_range = self.max_range
            if dim != len(origin):
                raise OctolgpError(f"dim {dim} but origin has {len(origin)} values")
            return Scan(
                origin=origin,
                points=value("points").reshape(-1, dim),
                max_range=None if np.isnan(max_range) else float(max_range),
                stamp=None if np.isnan(stamp) else float(stamp),
            )

        return self._checked(build, pos)

    def _checked(self, build: Callable[[], Scan], pos: int) -> Scan | None:
        """Build a scan; name the file and row on failure, or skip it with ``skip_bad``."""
        try:
            return build()
        except (OctolgpError, ValueError) as exc:
            where = f"{self._what()}: {self.entity} at {self.timeline}={self._times[pos]}"
            if not self.skip_bad:
                raise OctolgpError(f"{where}: {exc}") from None
            self.skipped += 1
            self.notes.append(f"{where}: skipped: {exc}")
            logger.info("%s: skipped: %s", where, exc)
            return None


def read_rrd(
    path: str | Path,
    *,
    points: str | None = None,
    pose: str | None = None,
    timeline: str | None = None,
    max_range: float | None = None,
    skip_bad: bool = False,
) -> RrdScanReader:
    """Open a Rerun recording as a stream of world-frame scans; see :class:`RrdScanReader`."""
    return RrdScanReader(
        path, points=points, pose=pose, timeline=timeline, max_range=max_range, skip_bad=skip_bad
    )
