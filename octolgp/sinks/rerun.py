"""Stream an online map to Rerun as a map people can read: tiles of many leaves, not one per leaf.

Layout of the recording (timeline ``scan``, a sequence; ``time`` too when scans
carry stamps):

``world/sensor``, ``world/sensor/points``, ``octolgp/scan``
    The scan: pose, sensor-frame points and an exact copy
    (:func:`octolgp.io.rrd_write.log_scan`), so a recording replays into the same map.
    Nothing else in the recording is a ``Points3D``/``Points2D`` under a ``Transform3D``,
    so a replay that names no entity still finds these.
``map/tiles/<tx>_<ty>`` (2D maps)
    The map as grey occupancy images of :data:`TILE` × :data:`TILE` cells (PNG, one byte a
    cell, ``255 (1 − P)`` on :data:`GREY_STEPS` + 1 levels: free light, occupied dark,
    unknown 128), placed by a static
    ``Transform3D`` in the top-down ``map`` space (``x`` right, ``y`` up: the space stores
    ``(x, −y)`` because a 2D view's ``y`` points down). A tile is re-logged, in place, only
    in the scans that changed one of its grey levels.
``map/robot``, ``map/scan``, ``map/path/<block>``, ``map/rays`` (2D maps)
    The sensor position, the current scan's endpoints, the path so far (one line strip per
    :data:`PATH_BLOCK` scans, so a scan adds a few bytes however long the mission) and
    optional decimated beams, in the same space.
``world/map/voxels/<rx>_<ry>_<rz>`` (3D maps)
    The occupied voxels (P > 0.5) of a region of :data:`REGION` voxels per edge as one
    ``Boxes3D``, coloured by height (the ramp spans the first scan's heights); re-logged
    only in the scans that moved a voxel in it across P = 0.5. A pruned occupied leaf is
    one box. ``world/path/<block>`` and ``world/sensor/rays``
    (optional) as above.
``map/variance/<tile>``, ``world/map/variance/<region>``
    Optional uncertainty layer: latent variance / σf² per voxel (white: as uncertain as
    the prior), shown in a view of its own.
``metrics/*``
    ``Scalars`` per scan: insert seconds, touched and refit leaves, leaves, memory MB,
    plotted by the default blueprint.

The default blueprint (:func:`default_blueprint`) is sent as rerun's *default* blueprint
(``default_blueprint=`` of ``save``/``connect_grpc``/``serve_grpc``, or
``send_blueprint(make_active=False)``), so a layout the user made in the viewer is kept.
:func:`open_recording` batches rows into chunks for longer than rerun's 0.2 s
(:data:`FLUSH_SAVE_SECONDS`, :data:`FLUSH_STREAM_SECONDS`): a chunk costs about 1.3 kB of framing, and a scan logs some
fifteen entities.

rerun-sdk is imported here and in the ``octolgp.io.rrd*`` modules only.
"""

from __future__ import annotations

import hashlib
import struct
import zlib
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import NDArray

from octolgp.errors import OctolgpError
from octolgp.scan import FloatArray, Scan
from octolgp.sinks.base import LeafView, MapChange

if TYPE_CHECKING:
    from octolgp.mapping.update import ScanUpdate

__all__ = [
    "PATH_BLOCK",
    "REGION",
    "TILE",
    "RerunSink",
    "default_blueprint",
    "open_recording",
    "serve_until_interrupted",
]

TILE = 128
"""Cells per edge of a 2D map tile (rounded up to whole leaves)."""
GREY_STEPS = 32
"""Steps from white (P = 0) to black (P = 1) of the 2D map images: 33 grey levels, one of
them exactly :data:`UNKNOWN_GREY`. Fewer levels change fewer tiles per scan and compress
better; 255 keeps every 8-bit level."""
REGION = 32
"""Voxels per edge of a 3D map region (rounded up to whole leaves)."""
PATH_BLOCK = 100
"""Scans per line strip of the path."""
FLUSH_SAVE_SECONDS = 5.0
"""Longest a logged row waits before it is written to a file (:func:`open_recording`)."""
FLUSH_STREAM_SECONDS = 1.0
"""Longest a logged row waits before it is sent to a viewer (:func:`open_recording`)."""
UNKNOWN_GREY = 128
"""Grey level of a cell no leaf covers (P = 0.5 is 127.5)."""

_ROBOT_COLOUR = (30, 144, 255)
_SCAN_COLOUR = (255, 110, 0)
_PATH_COLOUR = (60, 170, 60)
# Anchors of a blue → green → yellow → red height ramp (low to high).
_RAMP = np.array([[48, 18, 160], [33, 145, 140], [94, 201, 98], [253, 231, 37], [230, 60, 30]])


def _grey(prob: NDArray[Any], steps: int = 255) -> NDArray[np.uint8]:
    """Grey level per cell, occupied dark: ``255 (1 − P)`` rounded to one of ``steps + 1`` levels.

    With an even ``steps``, P = 0.5 is exactly :data:`UNKNOWN_GREY` (128).
    """
    k = np.rint(np.clip(1.0 - prob, 0.0, 1.0) * steps)
    return np.rint(k * (255.0 / steps)).astype(np.uint8)


def _ramp(value: NDArray[Any]) -> NDArray[np.uint8]:
    """RGB uint8 per value in [0, 1] along :data:`_RAMP` (clipped)."""
    t = np.clip(value, 0.0, 1.0) * (len(_RAMP) - 1)
    knots = np.arange(len(_RAMP))
    return np.stack([np.interp(t, knots, _RAMP[:, c]) for c in range(3)], axis=1).astype(np.uint8)


def _png(grey: NDArray[np.uint8]) -> bytes:
    """A grey image as PNG bytes: 8-bit greyscale, no row filter, zlib level 3.

    With few grey levels, unfiltered rows compress as well as filtered ones (PNG spec,
    sections 11.2 and 12.8); level 3 is three times as fast as level 6 for 20 % more bytes.
    """
    height, width = grey.shape
    raw = np.zeros((height, width + 1), np.uint8)  # each row: filter type 0, then pixels
    raw[:, 1:] = grey

    def chunk(tag: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(tag + data)
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)  # 8 bits, greyscale
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 3))
        + chunk(b"IEND", b"")
    )


def _flip_y(xy: FloatArray) -> NDArray[np.float32]:
    """World ``(x, y)`` to the 2D view's ``(x, −y)`` (its ``y`` axis points down), float32."""
    out = np.asarray(xy[:, :2], dtype=np.float32).copy()
    out[:, 1] *= -1
    return out


def open_recording(
    app_id: str = "octolgp",
    *,
    save: str | Path | None = None,
    connect: str | None = None,
    serve: bool = False,
    web: bool = False,
    blueprint: Any = None,
    grpc_port: int | None = None,
    web_port: int | None = None,
) -> tuple[rr.RecordingStream, str | None]:
    """A new recording stream sent to one place: a file, a viewer, or a gRPC server.

    Parameters
    ----------
    app_id : str
        The recording's application id (what the viewer groups recordings by).
    save : str or Path, optional
        Write the recording to this ``.rrd`` file.
    connect : str, optional
        Stream to the viewer at this URL (``rerun+http://host:port/proxy``).
    serve : bool
        Serve the recording over gRPC from this process, for viewers to connect to.
    web : bool
        Serve over gRPC and also rerun's web viewer over HTTP, connected to it (nothing
        opens a browser: open the returned URL).
    blueprint : rerun.blueprint.Blueprint, optional
        Sent as the *default* blueprint (:func:`default_blueprint`): a layout the user
        changed in the viewer is kept. Then give the sink ``blueprint=False``.
    grpc_port : int, optional
        Port of the gRPC server (``serve``, ``web``; rerun's default, 9876, when omitted).
    web_port : int, optional
        HTTP port of the web viewer (rerun's default, 9090, when omitted).

    Returns
    -------
    recording : rerun.RecordingStream
        The stream, ready for a :class:`RerunSink`; ``flush()`` and ``disconnect()`` it when
        done.
    url : str or None
        Where to look when serving: the gRPC address (``rerun --connect URL``), or with
        ``web`` the web viewer's address; else None.

    Raises
    ------
    ValueError
        Unless exactly one of ``save``, ``connect``, ``serve`` and ``web`` is given.
    OctolgpError
        If rerun refuses the path or URL (names which, with rerun's reason).
    """
    targets = (save is not None) + (connect is not None) + bool(serve) + bool(web)
    if targets != 1:
        raise ValueError("open_recording: give exactly one of save=, connect=, serve= and web=")
    # Rows of one entity logged within a tick share a chunk: fewer, larger chunks make a
    # long recording several times smaller (a viewer lags by at most the tick).
    tick = FLUSH_SAVE_SECONDS if save is not None else FLUSH_STREAM_SECONDS
    batcher = rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=tick), flush_num_bytes=4 << 20)
    rec = rr.RecordingStream(app_id, batcher_config=batcher)
    url = None
    try:
        if save is not None:
            what = f"cannot save a Rerun recording to {str(save)!r}"
            rec.save(save, default_blueprint=blueprint)
        elif connect is not None:
            what = f"cannot connect to a Rerun viewer at {connect!r}"
            rec.connect_grpc(connect, default_blueprint=blueprint)
        else:
            what = "cannot serve a Rerun recording over gRPC"
            url = rec.serve_grpc(grpc_port=grpc_port, default_blueprint=blueprint)
            if web:
                what = "cannot serve rerun's web viewer"
                port = 9090 if web_port is None else int(web_port)
                rr.serve_web_viewer(web_port=port, open_browser=False, connect_to=url)
                url = f"http://127.0.0.1:{port}/?url={quote(url, safe='')}"
    except (RuntimeError, ValueError, TypeError, OSError) as exc:  # rerun's bad path or URL
        raise OctolgpError(f"{what}: {exc}") from None
    return rec, url


def serve_until_interrupted(url: str, *, poll: float = 0.5) -> None:
    """Keep this process (and the recording it serves) alive until Ctrl-C.

    Parameters
    ----------
    url : str
        What to tell the user to open.
    poll : float
        Seconds between checks for the interrupt.
    """
    import time

    try:
        print(f"the map is done; still serving at {url} (Ctrl-C to stop)", flush=True)
        while True:
            time.sleep(poll)
    except KeyboardInterrupt:
        print("stopped serving", flush=True)


def default_blueprint(
    dim: int,
    *,
    uncertainty: bool = False,
    bounds: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> Any:
    """The map view (2D: top-down image; 3D: voxels) beside the per-scan plots.

    Parameters
    ----------
    dim : int
        2 or 3: the map's dimension.
    uncertainty : bool
        Add a view of the variance layer.
    bounds : ((x0, x1), (y0, y1)), optional
        What a 2D view shows first, metres, world frame (default: everything logged).

    Returns
    -------
    rerun.blueprint.Blueprint
    """
    views: list[Any]
    if dim == 2:
        shown = None
        if bounds is not None:  # the view's y is the world's −y
            (x0, x1), (y0, y1) = bounds
            shown = rrb.VisualBounds2D(x_range=[x0, x1], y_range=[-y1, -y0])
        views = [
            rrb.Spatial2DView(
                origin="/map",
                contents=["$origin/**", "- /map/variance/**"],
                name="map (top-down)",
                visual_bounds=shown,
            )
        ]
        if uncertainty:
            views.append(
                rrb.Spatial2DView(
                    origin="/map",
                    contents=["/map/variance/**", "/map/robot", "/map/path/**"],
                    name="uncertainty",
                    visual_bounds=shown,
                )
            )
    else:
        views = [
            rrb.Spatial3DView(
                origin="/world",
                contents=["$origin/**", "- /world/map/variance/**"],
                name="map (occupied voxels)",
                defaults=[rr.Points3D.from_fields(radii=-1.5, colors=[_SCAN_COLOUR])],
            )
        ]
        if uncertainty:
            views.append(
                rrb.Spatial3DView(
                    origin="/world",
                    contents=["/world/map/variance/**", "/world/sensor/**"],
                    name="uncertainty",
                )
            )
    plots = rrb.Vertical(
        rrb.TimeSeriesView(name="insert seconds", contents=["/metrics/insert_seconds"]),
        rrb.TimeSeriesView(
            name="leaves touched / refit",
            contents=["/metrics/touched_leaves", "/metrics/refit_leaves"],
        ),
        rrb.TimeSeriesView(name="leaves in the map", contents=["/metrics/leaves"]),
        rrb.TimeSeriesView(name="memory MB", contents=["/metrics/memory_mb"]),
    )
    maps = views[0] if len(views) == 1 else rrb.Vertical(*views)
    return rrb.Blueprint(rrb.Horizontal(maps, plots, column_shares=[3, 1]), collapse_panels=True)


@dataclass
class _Tiles:
    """A 2D map as grey uint8 tiles, ``tile`` × ``tile`` cells each (row y, column x).

    ``cell`` coordinates are world voxel keys less the key offset: cell ``c`` covers
    ``[c r, (c + 1) r)`` metres. Leaves never straddle tiles (``tile`` is a multiple of
    the leaf side).
    """

    tile: int
    fill: int
    grey: dict[tuple[int, int], NDArray[np.uint8]] = field(default_factory=dict)
    logged: dict[tuple[int, int], NDArray[np.uint8]] = field(default_factory=dict)
    where: dict[int, tuple[tuple[int, int], int, int, int]] = field(default_factory=dict)
    dirty: set[tuple[int, int]] = field(default_factory=set)
    placed: set[tuple[int, int]] = field(default_factory=set)  # static transform logged

    def paint(self, keys: list[int], cells: NDArray[np.int64], grey: NDArray[np.uint8]) -> None:
        """Write leaves' grey levels: ``cells`` (n, 2) their lower corners, ``grey`` (n, s, s)."""
        side = grey.shape[1]
        tiles = cells // self.tile
        offsets = cells - tiles * self.tile
        steps = np.arange(side)
        unique, inverse = np.unique(tiles, axis=0, return_inverse=True)
        for k, (tx, ty) in enumerate(unique.tolist()):  # one iteration per tile written to
            t = (int(tx), int(ty))
            image = self.grey.get(t)
            if image is None:
                image = self.grey[t] = np.full((self.tile, self.tile), self.fill, np.uint8)
            mine = np.flatnonzero(inverse.reshape(-1) == k)
            rows = offsets[mine, 1, None, None] + steps[None, :, None]
            cols = offsets[mine, 0, None, None] + steps[None, None, :]
            image[rows, cols] = grey[mine]  # flat voxel order is x fastest: rows are y
            self.dirty.add(t)
            for i in mine.tolist():  # one iteration per leaf: where to erase it from
                self.where[keys[i]] = (t, int(offsets[i, 1]), int(offsets[i, 0]), side)

    def erase(self, key: int) -> None:
        """A leaf left the map: its cells turn back to the fill (unknown)."""
        placed = self.where.pop(key, None)
        if placed is not None:
            t, row, col, side = placed
            self.grey[t][row : row + side, col : col + side] = self.fill
            self.dirty.add(t)

    def changed(self) -> list[tuple[tuple[int, int], NDArray[np.uint8]]]:
        """The dirty tiles whose grey levels differ from when they were last taken; clears."""
        out = []
        for t in sorted(self.dirty):  # one iteration per tile the step wrote to
            image = self.grey[t]
            last = self.logged.get(t)
            if last is None or not np.array_equal(last, image):
                self.logged[t] = image.copy()
                out.append((t, image))
        self.dirty.clear()
        return out


@dataclass
class _Regions:
    """A 3D map's occupied voxels per leaf, grouped in regions of ``region`` voxels per edge."""

    region: int
    compare_extra: bool
    boxes: dict[tuple[int, int, int], dict[int, tuple[FloatArray, FloatArray, FloatArray]]] = field(
        default_factory=dict
    )
    where: dict[int, tuple[int, int, int]] = field(default_factory=dict)
    dirty: set[tuple[int, int, int]] = field(default_factory=set)
    logged: dict[tuple[int, int, int], bytes] = field(default_factory=dict)

    def put(
        self, key: int, cell: NDArray[np.int64], value: tuple[FloatArray, FloatArray, FloatArray]
    ) -> None:
        """One leaf's ``(centres, half sizes, extra)``; empty arrays remove its boxes."""
        r = (
            int(cell[0] // self.region),
            int(cell[1] // self.region),
            int(cell[2] // self.region),
        )
        leaves = self.boxes.setdefault(r, {})
        if value[0].shape[0]:
            leaves[key] = value
        else:
            leaves.pop(key, None)
        self.where[key] = r
        self.dirty.add(r)

    def remove(self, key: int) -> None:
        """A leaf left the map."""
        r = self.where.pop(key, None)
        if r is not None:
            self.boxes[r].pop(key, None)
            self.dirty.add(r)

    def changed(self) -> list[tuple[tuple[int, int, int], FloatArray, FloatArray, FloatArray]]:
        """Each dirty region's boxes, concatenated, unless the same as when last taken; clears.

        Boxes are compared by geometry (centres and half sizes), and by ``extra`` too when
        ``compare_extra``: a refit that moves no voxel across P = 0.5 re-logs nothing.
        """
        out = []
        for r in sorted(self.dirty):  # one iteration per region the step wrote to
            leaves = self.boxes.get(r, {})
            parts = [leaves[k] for k in sorted(leaves)]
            if parts:
                centres, half, extra = (np.concatenate(p) for p in zip(*parts, strict=True))
            else:
                centres = half = np.zeros((0, 3))
                extra = np.zeros(0)
            digest = hashlib.blake2b(centres.tobytes() + half.tobytes())
            if self.compare_extra:
                digest.update(extra.tobytes())
            if self.logged.get(r) != digest.digest():
                self.logged[r] = digest.digest()
                out.append((r, centres, half, extra))
        self.dirty.clear()
        return out


class RerunSink:
    """Logs scans and map updates of an online map to a recording (a :class:`~octolgp.sinks.base.Sink`).

    A 2D map is drawn as grey occupancy images, one per :data:`TILE` × :data:`TILE` cells,
    re-logged only when a scan changed one of their grey levels; a 3D map as occupied
    voxels, one ``Boxes3D`` per region of :data:`REGION` voxels per edge. See the module
    docstring for the entities.

    Parameters
    ----------
    recording : rerun.RecordingStream
        Where to log (a file, a gRPC connection, a memory sink...).
    rays : int
        Log every ``rays``-th beam as a line; 0 (default) logs none.
    uncertainty : bool
        Also log the latent-variance layer.
    blueprint : bool
        Send :func:`default_blueprint` as the recording's default blueprint with the first
        scan. Pass False when the recording already has one (``open_recording(blueprint=)``).
    tile : int
        Cells per 2D tile edge (rounded up to whole leaves).
    region : int
        Voxels per 3D region edge (rounded up to whole leaves).
    grey_steps : int
        Steps from white to black of the 2D images (:data:`GREY_STEPS`; 255: every level).
    follow : bool, optional
        2D: send :func:`default_blueprint` again, as the default, with the view's bounds
        on what the map knows (:attr:`shown`) whenever the map outgrows them, so the view
        opens on the map and not on the scans' longest rays. Default: ``blueprint``.
    """

    def __init__(
        self,
        recording: rr.RecordingStream,
        *,
        rays: int = 0,
        uncertainty: bool = False,
        blueprint: bool = True,
        tile: int = TILE,
        region: int = REGION,
        grey_steps: int = GREY_STEPS,
        follow: bool | None = None,
    ) -> None:
        if min(tile, region, grey_steps) < 1 or grey_steps > 255:
            raise OctolgpError(
                "RerunSink: tile and region must be >= 1 and grey_steps in [1, 255], "
                f"got {tile}, {region}, {grey_steps}"
            )
        self.rec = recording
        self.rays = int(rays)
        self.uncertainty = bool(uncertainty)
        self.tile = int(tile)
        self.region = int(region)
        self.grey_steps = int(grey_steps)
        self._blueprint = blueprint
        self._follow_view = blueprint if follow is None else bool(follow)
        self._started = False
        self._path: list[NDArray[np.float64]] = []  # origins of the current path block
        self._occupancy: _Tiles | None = None
        self._variance: _Tiles | None = None
        self._voxels: _Regions | None = None
        self._variance3d: _Regions | None = None
        self._heights: tuple[float, float] | None = None
        self.shown: tuple[tuple[float, float], tuple[float, float]] | None = None
        self._known: tuple[FloatArray, FloatArray] | None = None

    # ------------------------------------------------------------------ events
    def on_scan(self, scan: Scan, index: int) -> None:
        """Log an accepted scan: pose, points and exact copy, then what the map view draws."""
        from octolgp.io.rrd_write import log_scan

        rec = self.rec
        if not self._started:
            self._start(scan)
        log_scan(rec, scan, index)
        if self._heights is None and scan.dim == 3:  # colour ramp from the first scan's heights
            lo, hi = np.percentile(scan.points[:, 2], [2.0, 98.0])
            self._heights = (float(lo), float(max(hi, lo + 1e-6)))
        self._log_path(scan, index)
        if scan.dim == 2:
            rec.log("map/robot", rr.Points2D(_flip_y(scan.origin[None, :])))
            rec.log("map/scan", rr.Points2D(_flip_y(scan.points)))
        if self.rays > 0:
            ends = scan.points[:: self.rays]
            if scan.dim == 2:
                strips = np.stack([np.broadcast_to(scan.origin, ends.shape), ends], axis=1)
                flat = _flip_y(strips.reshape(-1, 2)).reshape(-1, 2, 2)
                rec.log("map/rays", rr.LineStrips2D(flat))
            else:
                local = (ends - scan.origin).astype(np.float32)
                strips3 = np.stack([np.zeros_like(local), local], axis=1)
                rec.log("world/sensor/rays", rr.LineStrips3D(strips3, radii=-0.5))

    def on_update(self, update: ScanUpdate, change: MapChange) -> None:
        """Redraw the tiles or regions the step changed, and log the per-scan metrics."""
        rec = self.rec
        rec.set_time("scan", sequence=update.scan)
        if change.dim == 2:
            self._update_tiles(change)
        else:
            self._update_regions(change)
        rec.log("metrics/insert_seconds", rr.Scalars(update.seconds))
        rec.log("metrics/touched_leaves", rr.Scalars(float(update.touched_leaves)))
        rec.log("metrics/refit_leaves", rr.Scalars(float(update.refit_leaves)))
        rec.log("metrics/leaves", rr.Scalars(float(update.n_leaves)))
        rec.log("metrics/memory_mb", rr.Scalars(update.memory_bytes / 1e6))

    # ------------------------------------------------------------------ scans
    def _start(self, scan: Scan) -> None:
        """Once: the default blueprint, the world's axes and the styles that never change."""
        rec = self.rec
        if self._blueprint:
            rec.send_blueprint(
                default_blueprint(scan.dim, uncertainty=self.uncertainty),
                make_active=False,
                make_default=True,
            )
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if scan.dim == 2:  # styles, static: each scan then sends positions only
            rec.log(
                "map/robot",
                rr.Points2D.from_fields(radii=-6.0, colors=[_ROBOT_COLOUR]),
                static=True,
            )
            rec.log(
                "map/scan", rr.Points2D.from_fields(radii=-1.5, colors=[_SCAN_COLOUR]), static=True
            )
        else:
            rec.log("world/sensor", rr.TransformAxes3D(axis_length=0.5), static=True)
        self._started = True

    def _log_path(self, scan: Scan, index: int) -> None:
        """The path as line strips of :data:`PATH_BLOCK` scans: one strip grows, the rest stay."""
        block = (index - 1) // PATH_BLOCK
        if (index - 1) % PATH_BLOCK == 0:
            self._path = self._path[-1:]  # the new strip starts where the last one ended
        self._path.append(np.asarray(scan.origin, dtype=np.float64))
        xy = np.asarray(self._path)
        if scan.dim == 2:
            self.rec.log(
                f"map/path/{block}",
                rr.LineStrips2D([_flip_y(xy)], radii=-1.0, colors=[_PATH_COLOUR]),
            )
        else:
            self.rec.log(
                f"world/path/{block}",
                rr.LineStrips3D([xy.astype(np.float32)], radii=-1.0, colors=[_PATH_COLOUR]),
            )

    # ------------------------------------------------------------------ 2D tiles
    def _tiles(self, side: int) -> tuple[_Tiles, _Tiles | None]:
        if self._occupancy is None:
            size = side * -(-self.tile // side)  # whole leaves per tile
            self._occupancy = _Tiles(size, UNKNOWN_GREY)
            if self.uncertainty:
                self._variance = _Tiles(size, 255)
        return self._occupancy, self._variance

    def _update_tiles(self, change: MapChange) -> None:
        """Paint the refitted leaves into their tiles, then log the tiles that changed."""
        occupancy, variance = self._tiles(change.side)
        res, side = change.resolution, change.side
        leaves = list(change.leaves)
        if leaves:
            # one row per leaf, NaN where a leaf has no prediction yet; a pruned leaf's one
            # value is broadcast over its voxels
            prob = np.full((len(leaves), side * side), np.nan)
            var = np.full_like(prob, np.nan) if variance is not None else None
            for i, leaf in enumerate(leaves):  # one iteration per refitted leaf: a copy
                if leaf.prob.size:
                    prob[i] = leaf.prob
                if var is not None and leaf.var.size:
                    var[i] = leaf.var
            known = ~np.isnan(prob).all(axis=1)
            if known.any():  # the view follows what the map knows, not the scans' rays
                lo = np.array([leaf.lo for leaf in leaves])[known].min(axis=0)
                hi = np.array([leaf.hi for leaf in leaves])[known].max(axis=0)
                self._follow(lo, hi)
            keys = [leaf.key for leaf in leaves]
            cells = np.rint(np.array([leaf.lo for leaf in leaves]) / res).astype(np.int64)
            occupancy.paint(keys, cells, self._grey(prob, occupancy.fill).reshape(-1, side, side))
            if variance is not None and var is not None:
                level = 1.0 - var / change.signal_variance
                variance.paint(
                    keys, cells, self._grey(level, variance.fill).reshape(-1, side, side)
                )
        for key in change.removed:  # one iteration per leaf that left the map
            occupancy.erase(key)
            if variance is not None:
                variance.erase(key)
        self._log_tiles("map/tiles", occupancy, res)
        if variance is not None:
            self._log_tiles("map/variance", variance, res)

    def _follow(self, lo: FloatArray, hi: FloatArray) -> None:
        """Grow the default 2D view to hold the box ``lo``-``hi`` (metres), with a margin.

        The first known leaves set :attr:`shown`; a leaf outside it widens it by a tenth of
        its size (at least a metre) on every side and sends the default blueprint again
        (``make_default``, not active: a layout the user chose is kept).
        """
        if self._known is not None:
            lo, hi = np.minimum(lo, self._known[0]), np.maximum(hi, self._known[1])
        self._known = (lo, hi)  # what the map knows, without the margin
        if self.shown is not None:
            (x0, x1), (y0, y1) = self.shown
            if lo[0] >= x0 and lo[1] >= y0 and hi[0] <= x1 and hi[1] <= y1:
                return
        pad = np.maximum(0.1 * (hi - lo), 1.0)
        a, b = lo - pad, hi + pad
        self.shown = ((float(a[0]), float(b[0])), (float(a[1]), float(b[1])))
        if self._follow_view:
            self.rec.send_blueprint(
                default_blueprint(2, uncertainty=self.uncertainty, bounds=self.shown),
                make_active=False,
                make_default=True,
            )

    def _grey(self, prob: FloatArray, fill: int) -> NDArray[np.uint8]:
        """Grey levels of P (:func:`_grey`), ``fill`` where P is NaN."""
        known = ~np.isnan(prob)
        grey = np.full(prob.shape, fill, np.uint8)
        grey[known] = _grey(prob[known], self.grey_steps)
        return grey

    def _log_tiles(self, prefix: str, tiles: _Tiles, res: float) -> None:
        for (tx, ty), grey in tiles.changed():  # one iteration per tile that changed
            path = f"{prefix}/{tx}_{ty}"
            if (tx, ty) not in tiles.placed:
                x0, y1 = tx * tiles.tile * res, (ty + 1) * tiles.tile * res
                # pixel (u, v) → (x0 + u r, −y1 + v r): row 0 is the tile's top (largest y)
                self.rec.log(
                    path, rr.Transform3D(translation=[x0, -y1, 0.0], scale=res), static=True
                )
                tiles.placed.add((tx, ty))
            self.rec.log(path, rr.EncodedImage(contents=_png(grey[::-1]), media_type="image/png"))

    # ------------------------------------------------------------------ 3D regions
    def _update_regions(self, change: MapChange) -> None:
        """Re-collect the occupied voxels of the refitted leaves, then log changed regions."""
        if self._voxels is None:
            size = change.side * -(-self.region // change.side)
            self._voxels = _Regions(size, compare_extra=False)
            self._variance3d = _Regions(size, compare_extra=True) if self.uncertainty else None
        voxels, variance = self._voxels, self._variance3d
        res = change.resolution
        for leaf in change.leaves:  # one iteration per refitted leaf
            cell = np.rint(leaf.lo / res).astype(np.int64)
            voxels.put(leaf.key, cell, self._occupied(leaf, res))
            if variance is not None:
                level = leaf.var.astype(np.float64) / change.signal_variance
                none = np.zeros((0, 3))
                empty = leaf.pruned or leaf.var.size == 0
                known = ~np.isnan(level)  # voxels far from every observation hold no value
                value = (
                    (none, none, np.zeros(0))
                    if empty
                    else (leaf.centres[known], none, level[known])
                )
                variance.put(leaf.key, cell, value)
        for key in change.removed:  # one iteration per leaf that left the map
            voxels.remove(key)
            if variance is not None:
                variance.remove(key)
        lo, hi = self._heights or (0.0, 1.0)
        for (rx, ry, rz), centres, half, _ in voxels.changed():  # one per region that changed
            path = f"world/map/voxels/{rx}_{ry}_{rz}"
            if centres.shape[0] == 0:
                self.rec.log(path, rr.Clear(recursive=False))
                continue
            same = bool(np.all(half == half[0]))
            self.rec.log(
                path,
                rr.Boxes3D(
                    centers=centres.astype(np.float32),
                    half_sizes=half[:1] if same else half,
                    colors=_ramp((centres[:, 2] - lo) / (hi - lo)),
                    fill_mode="solid",
                ),
            )
        if variance is not None:
            for (rx, ry, rz), centres, _, level in variance.changed():  # one per region
                self.rec.log(
                    f"world/map/variance/{rx}_{ry}_{rz}",
                    rr.Points3D(
                        centres.astype(np.float32),
                        radii=0.3 * res,
                        colors=np.repeat(_grey(1.0 - level)[:, None], 3, axis=1),
                    ),
                )

    @staticmethod
    def _occupied(leaf: LeafView, res: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """A 3D leaf's occupied boxes: voxels with P > 0.5, or the whole leaf when pruned."""
        if leaf.pruned or leaf.prob.size == 0:
            if leaf.prob.size == 0 or float(leaf.prob[0]) <= 0.5:
                none = np.zeros((0, 3))
                return none, none, np.zeros(0)
            return (
                (0.5 * (leaf.lo + leaf.hi))[None, :],
                (0.5 * (leaf.hi - leaf.lo))[None, :],
                leaf.prob.astype(np.float64),
            )
        occ = leaf.prob > 0.5
        n = int(occ.sum())
        return leaf.centres[occ], np.full((n, 3), 0.5 * res), leaf.prob[occ].astype(np.float64)
