"""Stream an online map to Rerun as a map people can read: tiles of many leaves, not one per leaf.

Layout of the recording (timeline ``scan``, a sequence; ``time`` too when scans
carry stamps):

``world/sensor``, ``world/sensor/points``, ``octolgp/scan``
    The scan: pose, sensor-frame points and an exact copy
    (:func:`octolgp.io.rrd_write.log_scan`), so a recording replays into the same map.
    Nothing else in the recording is a ``Points3D``/``Points2D`` under a ``Transform3D``,
    so a replay that names no entity still finds these.
``map/tiles/<tx>_<ty>`` (2D maps)
    The map as occupancy images of :data:`TILE` × :data:`TILE` cells (PNG, one byte a
    cell, ``255 (1 − P)`` on :data:`GREY_STEPS` + 1 levels: free light, occupied dark,
    unknown 128; with ``colors="probability"`` the same levels through a palette of
    :func:`~octolgp.sinks.colours.probability_colours`), placed by a static
    ``Transform3D`` in the top-down ``map`` space (``x`` right, ``y`` up: the space stores
    ``(x, −y)`` because a 2D view's ``y`` points down). A tile is re-logged, in place, only
    in the scans that changed one of its grey levels.
``map/robot``, ``map/heading``, ``map/scan``, ``map/path/<block>``, ``map/rays`` (2D maps)
    The sensor position, an arrow the way it faces (:mod:`octolgp.sinks.heading`: scans
    carry no orientation, so the middle of a forward-facing sensor's field of view, else
    the direction of travel), the current scan's endpoints, the path so far (one line
    strip per :data:`PATH_BLOCK` scans, so a scan adds a few bytes however long the
    mission) and optional decimated beams, in the same space.
``world/map/voxels/<rx>_<ry>_<rz>`` (3D maps)
    The occupied voxels (P > 0.5) of a region of :data:`REGION` voxels per edge as one
    ``Boxes3D``, coloured by height (the ramp spans the first scan's heights) or by P;
    re-logged only in the scans that changed a box in it (or, coloured by P, a colour).
    A pruned occupied leaf is one box. ``world/sensor/heading`` (the arrow, in the
    world-aligned sensor frame), ``world/path/<block>`` and ``world/sensor/rays``
    (optional) as above.
``world/map/free/<rx>_<ry>_<rz>`` (3D maps, ``free_voxels=True``)
    Free voxels (P < :data:`FREE_BELOW`) as points, only those whose voxel key is a
    multiple of :data:`FREE_STRIDE` on every axis: at most (region / FREE_STRIDE)³ =
    4,096 a region, an eighth of the free space.
``map/provisional``, ``world/provisional``
    While the map learns its hyperparameters (the first ``OnlineConfig.learn_scans``
    scans) nothing is in the map yet; the provisional fit of the buffered scans
    (:attr:`octolgp.OnlineMap.provisional`) is drawn here, after buffered scans 1, 4,
    16, ... (powers of :data:`PROVISIONAL_GROWTH`: each draw is a learning and a fit,
    about 0.7 s on the Intel log, so three in 2D, two in 3D), with a box labelled
    ``provisional`` around it. It is cleared when the learnt map's first leaves are drawn.
``legend/bar``, ``legend/labels``
    What the map's colours mean: a colour bar (an image) and its labelled ends, shown
    in a view of their own (Rerun draws no colour bar for images).
``map/variance/<tile>``, ``world/map/variance/<region>``
    Optional uncertainty layer: latent variance / σf² per voxel (white: as uncertain as
    the prior), shown in a view of its own.
``metrics/*``
    ``Scalars`` per scan: insert seconds, touched and refit leaves, leaves, memory MB,
    plotted by the default blueprint.

The default blueprint (:func:`default_blueprint`) is sent as rerun's *default* blueprint
(``default_blueprint=`` of ``save``/``connect_grpc``/``serve_grpc``, or
``send_blueprint(make_active=False)``), so a layout the user made in the viewer is kept.
The sink sends it again, bounded on what the map knows, as the map grows
(:attr:`RerunSink.shown`). :func:`open_recording` batches rows into chunks for longer than
rerun's 0.2 s (:data:`FLUSH_SAVE_SECONDS`, :data:`FLUSH_STREAM_SECONDS`): a chunk costs
about 1.3 kB of framing, and a scan logs some fifteen entities.

rerun-sdk is imported here and in the ``octolgp.io.rrd*`` modules only.
"""

from __future__ import annotations

from collections.abc import Callable
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
from octolgp.sinks.colours import (
    grey_levels,
    height_colours,
    legend_image,
    png,
    probability_colours,
    probability_palette,
)
from octolgp.sinks.heading import Heading
from octolgp.sinks.layers import Regions, Tiles

if TYPE_CHECKING:
    from octolgp.mapping.update import ScanUpdate

__all__ = [
    "COLORS",
    "FREE_BELOW",
    "FREE_STRIDE",
    "PATH_BLOCK",
    "PROVISIONAL_GROWTH",
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
COLORS = ("auto", "probability")
"""The map's colour schemes: ``auto`` (2D grey occupancy, 3D height) and ``probability``
(P(occupied) blue-grey-red, :data:`octolgp.sinks.colours.PROBABILITY_ANCHORS`)."""
FREE_BELOW = 0.25
"""A voxel is drawn free below this P (the nav2 export's default ``free_thresh``)."""
FREE_STRIDE = 2
"""Free voxels drawn: those whose key is a multiple of this on every axis (one in 8)."""
PROVISIONAL_GROWTH = 4
"""The provisional map is drawn after buffered scans 1, 4, 16, ...: its powers. Each draw
learns hyperparameters (the bulk of its cost), so few draws keep the learning phase quick."""

_ROBOT_COLOUR = (30, 144, 255)
_ROBOT_COLOUR_ON_PROBABILITY = (230, 0, 180)  # magenta: the probability map's free is blue
_SCAN_COLOUR = (255, 110, 0)
_PATH_COLOUR = (60, 170, 60)
_ARROW_COLOUR_3D = (245, 245, 245)  # white: no colour of the height or probability maps
_PROVISIONAL_COLOUR = (230, 120, 0)
_FREE_COLOUR = (110, 170, 235)
_LEGEND_WIDTH = 101  # colour bar columns: one per hundredth of the scale
_LEGEND_HEIGHT = 12


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


Bounds = tuple[tuple[float, float], ...]
"""Per axis ``(low, high)``, metres, world frame."""


def _eye(bounds: Bounds) -> Any:
    """A 3D camera that sees the box ``bounds`` whole: from its south-west, above, looking at it."""
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    centre = 0.5 * (lo + hi)
    reach = max(float(np.linalg.norm(hi - lo)), 1.0)
    towards = np.array([-0.55, -0.65, 0.52])  # unit-ish: down at about 30 degrees
    position = centre + 0.75 * reach * towards / np.linalg.norm(towards)
    return rrb.EyeControls3D(
        kind=rrb.Eye3DKind.Orbital,
        position=position.tolist(),
        look_target=centre.tolist(),
        eye_up=[0.0, 0.0, 1.0],
    )


def default_blueprint(
    dim: int,
    *,
    uncertainty: bool = False,
    bounds: Bounds | None = None,
) -> Any:
    """The map view (2D: top-down image; 3D: voxels) beside the legend and the per-scan plots.

    Parameters
    ----------
    dim : int
        2 or 3: the map's dimension.
    uncertainty : bool
        Add a view of the variance layer.
    bounds : ((x0, x1), (y0, y1)) or ((x0, x1), (y0, y1), (z0, z1)), optional
        What the view shows first, metres, world frame: a 2D view's visible rectangle, a
        3D view's camera (looking at the box's centre from its south-west, above, far
        enough to see it whole). Default: everything logged.

    Returns
    -------
    rerun.blueprint.Blueprint
    """
    views: list[Any]
    if dim == 2:
        shown = None
        if bounds is not None:  # the view's y is the world's −y
            (x0, x1), (y0, y1) = bounds[:2]
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
                    contents=["/map/variance/**", "/map/robot", "/map/heading", "/map/path/**"],
                    name="uncertainty",
                    visual_bounds=shown,
                )
            )
    else:
        eye = _eye(bounds) if bounds is not None and len(bounds) == 3 else None
        views = [
            rrb.Spatial3DView(
                origin="/world",
                contents=["$origin/**", "- /world/map/variance/**"],
                name="map (voxels)",
                defaults=[rr.Points3D.from_fields(radii=-1.5, colors=[_SCAN_COLOUR])],
                eye_controls=eye,
            )
        ]
        if uncertainty:
            views.append(
                rrb.Spatial3DView(
                    origin="/world",
                    contents=["/world/map/variance/**", "/world/sensor/**"],
                    name="uncertainty",
                    eye_controls=eye,
                )
            )
    legend = rrb.Spatial2DView(
        origin="/legend",
        name="legend",
        visual_bounds=rrb.VisualBounds2D(
            x_range=[-0.12 * _LEGEND_WIDTH, 1.12 * _LEGEND_WIDTH],
            y_range=[-2.2 * _LEGEND_HEIGHT, 2.8 * _LEGEND_HEIGHT],
        ),
    )
    plots = rrb.Vertical(
        legend,
        rrb.TimeSeriesView(name="insert seconds", contents=["/metrics/insert_seconds"]),
        rrb.TimeSeriesView(
            name="leaves touched / refit",
            contents=["/metrics/touched_leaves", "/metrics/refit_leaves"],
        ),
        rrb.TimeSeriesView(name="leaves in the map", contents=["/metrics/leaves"]),
        rrb.TimeSeriesView(name="memory MB", contents=["/metrics/memory_mb"]),
        row_shares=[1.0, 1.5, 1.5, 1.5, 1.5],
    )
    maps = views[0] if len(views) == 1 else rrb.Vertical(*views)
    return rrb.Blueprint(rrb.Horizontal(maps, plots, column_shares=[3, 1]), collapse_panels=True)


def legend_colours(colors: str, dim: int) -> NDArray[np.uint8]:
    """The legend's colour bar: :data:`_LEGEND_WIDTH` RGB colours, low values first.

    ``auto`` in 2D: grey occupancy (P = 0 white to 1 black); ``auto`` in 3D: the height
    ramp; ``probability``: :func:`~octolgp.sinks.colours.probability_colours`.
    """
    t = np.linspace(0.0, 1.0, _LEGEND_WIDTH)
    if colors == "probability":
        return probability_colours(t)
    if dim == 2:
        return np.repeat(grey_levels(t)[:, None], 3, axis=1)
    return height_colours(t)


class RerunSink:
    """Logs scans and map updates of an online map to a recording (a :class:`~octolgp.sinks.base.Sink`).

    A 2D map is drawn as occupancy images, one per :data:`TILE` × :data:`TILE` cells,
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
        Steps from P = 0 to P = 1 of the 2D images' levels (:data:`GREY_STEPS`; 255: every
        level).
    follow : bool, optional
        Send :func:`default_blueprint` again, as the default, with the view's bounds on
        what the map knows (:attr:`shown`) whenever the map outgrows them, so the view
        opens on the map and not on the scans' longest rays (2D: the leaves with values;
        3D: the voxels drawn). Default: ``blueprint``.
    colors : {"auto", "probability"}
        The map's colours (:data:`COLORS`): ``auto`` draws 2D maps in grey occupancy and
        3D voxels by height; ``probability`` draws P(occupied) blue (free), grey (0.5,
        unknown), red (occupied). The ``legend/*`` entities say which.
    free_voxels : bool
        3D maps: also draw free voxels (P < :data:`FREE_BELOW`), one in
        :data:`FREE_STRIDE` cubed, at most 4,096 a region. Off by default: free space
        hides the occupied voxels behind it.
    provisional : bool
        While the map learns its hyperparameters, draw its provisional fit after buffered
        scans 1, 4, 16, ... (each draw costs a learning and a fit of the buffer, about
        0.7 s on the Intel log). Default True.

    Attributes
    ----------
    shown : tuple of (low, high) per axis, or None
        The bounds of the default view the sink last sent (metres, world frame).
    heading : ndarray of shape (d,) or None
        Unit vector of the last arrow drawn (:class:`~octolgp.sinks.heading.Heading`).

    Raises
    ------
    OctolgpError
        On a bad ``tile``, ``region``, ``grey_steps`` or ``colors``, naming it.
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
        colors: str = "auto",
        free_voxels: bool = False,
        provisional: bool = True,
    ) -> None:
        if min(tile, region, grey_steps) < 1 or grey_steps > 255:
            raise OctolgpError(
                "RerunSink: tile and region must be >= 1 and grey_steps in [1, 255], "
                f"got {tile}, {region}, {grey_steps}"
            )
        if colors not in COLORS:
            raise OctolgpError(
                f"RerunSink: colors must be one of {', '.join(map(repr, COLORS))}, got {colors!r}"
            )
        self.rec = recording
        self.rays = int(rays)
        self.uncertainty = bool(uncertainty)
        self.tile = int(tile)
        self.region = int(region)
        self.grey_steps = int(grey_steps)
        self.colors = colors
        self.free_voxels = bool(free_voxels)
        self.provisional = bool(provisional)
        self._blueprint = blueprint
        self._follow_view = blueprint if follow is None else bool(follow)
        self._started = False
        self._path: list[NDArray[np.float64]] = []  # origins of the current path block
        self._occupancy: Tiles | None = None
        self._variance: Tiles | None = None
        self._voxels: Regions | None = None
        self._free: Regions | None = None
        self._variance3d: Regions | None = None
        self._heights: tuple[float, float] | None = None
        self._heading = Heading()
        self._arrow = 1.0  # metres, set from the first scan's ranges
        self._buffered = 0  # provisional steps seen since the last learnt one
        self._provisional_drawn = False
        self._palette = probability_palette(self.grey_steps) if colors == "probability" else None
        self.shown: Bounds | None = None
        self.heading: FloatArray | None = None
        self._known: tuple[FloatArray, FloatArray] | None = None
        self._provisional_paths: dict[str, set[str]] = {}

    # ------------------------------------------------------------------ events
    def on_scan(self, scan: Scan, index: int) -> None:
        """Log an accepted scan: pose, points and exact copy, then what the map view draws."""
        from octolgp.io.rrd_write import log_scan

        rec = self.rec
        if not self._started:
            self._start(scan)
        log_scan(rec, scan, index)
        self._log_path(scan, index)
        heading = self._heading.update(scan)
        if scan.dim == 2:
            rec.log("map/robot", rr.Points2D(_flip_y(scan.origin[None, :])))
            rec.log("map/scan", rr.Points2D(_flip_y(scan.points)))
        if heading is not None:
            self.heading = heading
            arrow = heading[None, :] * self._arrow
            if scan.dim == 2:
                origin = _flip_y(scan.origin[None, :])
                rec.log("map/heading", rr.Arrows2D(origins=origin, vectors=_flip_y(arrow)))
            else:  # the sensor frame is world-aligned (log_scan)
                rec.log("world/sensor/heading", rr.Arrows3D(vectors=arrow.astype(np.float32)))
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
        if self._provisional_drawn:  # the learnt map replaces the provisional one
            rec.log(
                "map/provisional" if change.dim == 2 else "world/provisional", rr.Clear.recursive()
            )
            self._provisional_drawn = False
            self._provisional_paths.clear()
        self._buffered = 0
        if change.dim == 2:
            self._update_tiles(change)
        else:
            self._update_regions(change)
        self._metrics(update)

    def on_provisional(self, update: ScanUpdate, provisional: Callable[[], MapChange]) -> None:
        """A step that only buffered scans to learn on: its metrics, and the provisional map.

        The provisional map (``provisional()`` builds it: a learning and a fit of the
        buffered scans) is drawn after the 1st, 4th, 16th, ... buffered scan, under
        ``map/provisional`` (2D) or ``world/provisional`` (3D) with a labelled box around
        it, and cleared by the first :meth:`on_update`.
        """
        rec = self.rec
        rec.set_time("scan", sequence=update.scan)
        self._metrics(update)
        self._buffered += 1
        if not self.provisional or not _is_power(self._buffered, PROVISIONAL_GROWTH):
            return
        change = provisional()
        leaves = [leaf for leaf in change.leaves if leaf.prob.size]
        if not leaves:  # no training data yet (no return): nothing to draw
            return
        res = change.resolution
        if change.dim == 2:
            prefix = "map/provisional"
            tiles = Tiles(change.side * -(-self.tile // change.side), UNKNOWN_GREY)
            box = self._paint(tiles, None, change, leaves)
            self._log_tiles(f"{prefix}/tiles", tiles, res, self._palette, clear_others=True)
        else:
            prefix = "world/provisional"
            regions = Regions(change.side * -(-self.region // change.side), False)
            box = None
            for leaf in leaves:  # one iteration per provisional leaf
                value = self._occupied(leaf, res)
                regions.put(leaf.key, np.rint(leaf.lo / res).astype(np.int64), value)
                box = _grow(box, value[0], value[1])
            self._log_voxels(f"{prefix}/voxels", regions, clear_others=True)
        self._provisional_drawn = True
        if box is None:
            return
        self._follow(*box)
        lo, hi = box
        label = f"provisional: hyperparameters still being learnt (scan {update.scan})"
        shape: Any
        if change.dim == 2:
            corner = _flip_y(np.array([[lo[0], hi[1]]]))
            shape = rr.Boxes2D(
                mins=corner,
                sizes=[hi - lo],
                labels=[label],
                show_labels=True,
                colors=[_PROVISIONAL_COLOUR],
            )
        else:
            shape = rr.Boxes3D(
                centers=[0.5 * (lo + hi)],
                half_sizes=[0.5 * (hi - lo)],
                labels=[label],
                show_labels=True,
                colors=[_PROVISIONAL_COLOUR],
            )
        rec.log(f"{prefix}/label", shape)

    def _metrics(self, update: ScanUpdate) -> None:
        rec = self.rec
        rec.log("metrics/insert_seconds", rr.Scalars(update.seconds))
        rec.log("metrics/touched_leaves", rr.Scalars(float(update.touched_leaves)))
        rec.log("metrics/refit_leaves", rr.Scalars(float(update.refit_leaves)))
        rec.log("metrics/leaves", rr.Scalars(float(update.n_leaves)))
        rec.log("metrics/memory_mb", rr.Scalars(update.memory_bytes / 1e6))

    # ------------------------------------------------------------------ scans
    def _start(self, scan: Scan) -> None:
        """Once: the default blueprint, the world's axes, the legend and the styles."""
        rec = self.rec
        ranges = np.linalg.norm(scan.points - scan.origin, axis=1)
        self._arrow = float(np.clip(0.5 * np.median(ranges), 2.0, 8.0))
        if scan.dim == 3:  # colour ramp from the first scan's heights
            lo, hi = np.percentile(scan.points[:, 2], [2.0, 98.0])
            self._heights = (float(lo), float(max(hi, lo + 1e-6)))
        if self._blueprint:
            rec.send_blueprint(
                default_blueprint(scan.dim, uncertainty=self.uncertainty),
                make_active=False,
                make_default=True,
            )
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._log_legend(scan.dim)
        if scan.dim == 2:  # styles, static: each scan then sends positions only
            robot = _ROBOT_COLOUR_ON_PROBABILITY if self.colors == "probability" else _ROBOT_COLOUR
            rec.log("map/robot", rr.Points2D.from_fields(radii=-6.0, colors=[robot]), static=True)
            rec.log("map/heading", rr.Arrows2D.from_fields(radii=-2.0, colors=[robot]), static=True)
            rec.log(
                "map/scan", rr.Points2D.from_fields(radii=-1.5, colors=[_SCAN_COLOUR]), static=True
            )
        else:
            rec.log(
                "world/sensor/heading",
                rr.Arrows3D.from_fields(radii=-4.0, colors=[_ARROW_COLOUR_3D]),
                static=True,
            )
        self._started = True

    def _log_legend(self, dim: int) -> None:
        """The colour bar and its labels, static: what the map's colours mean."""
        bar = legend_image(legend_colours(self.colors, dim), _LEGEND_HEIGHT)
        self.rec.log(
            "legend/bar", rr.EncodedImage(contents=png(bar), media_type="image/png"), static=True
        )
        if self.colors == "probability" or dim == 2:
            title = "P(occupied)"
            ends = ["0 free", "0.5 unknown", "1 occupied"]
        else:
            lo, hi = self._heights or (0.0, 1.0)
            title = "height of occupied voxels" + (" (free: light blue)" * self.free_voxels)
            ends = [f"{lo:.1f} m", f"{0.5 * (lo + hi):.1f} m", f"{hi:.1f} m"]
        w, h = _LEGEND_WIDTH - 1, _LEGEND_HEIGHT
        self.rec.log(
            "legend/labels",
            rr.Points2D(
                [[0.5 * w, -1.3 * h], [0.0, 1.9 * h], [0.5 * w, 1.9 * h], [w, 1.9 * h]],
                labels=[title, *ends],
                radii=0.5,
                colors=[(230, 230, 230)],  # the labels' text, on the viewer's dark boxes
                show_labels=True,
            ),
            static=True,
        )

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
    def _tiles(self, side: int) -> tuple[Tiles, Tiles | None]:
        if self._occupancy is None:
            size = side * -(-self.tile // side)  # whole leaves per tile
            self._occupancy = Tiles(size, UNKNOWN_GREY)
            if self.uncertainty:
                self._variance = Tiles(size, 255)
        return self._occupancy, self._variance

    def _update_tiles(self, change: MapChange) -> None:
        """Paint the refitted leaves into their tiles, then log the tiles that changed."""
        occupancy, variance = self._tiles(change.side)
        box = self._paint(occupancy, variance, change, list(change.leaves))
        if box is not None:  # the view follows what the map knows, not the scans' rays
            self._follow(*box)
        for key in change.removed:  # one iteration per leaf that left the map
            occupancy.erase(key)
            if variance is not None:
                variance.erase(key)
        self._log_tiles("map/tiles", occupancy, change.resolution, self._palette)
        if variance is not None:
            self._log_tiles("map/variance", variance, change.resolution, None)

    def _paint(
        self, occupancy: Tiles, variance: Tiles | None, change: MapChange, leaves: list[LeafView]
    ) -> tuple[FloatArray, FloatArray] | None:
        """Paint leaves into the tiles; the box of those with a value (``None``: none has)."""
        if not leaves:
            return None
        res, side = change.resolution, change.side
        # one row per leaf, NaN where a leaf has no prediction yet; a pruned leaf's one
        # value is broadcast over its voxels
        prob = np.full((len(leaves), side * side), np.nan)
        var = np.full_like(prob, np.nan) if variance is not None else None
        for i, leaf in enumerate(leaves):  # one iteration per refitted leaf: a copy
            if leaf.prob.size:
                prob[i] = leaf.prob
            if var is not None and leaf.var.size:
                var[i] = leaf.var
        keys = [leaf.key for leaf in leaves]
        corners = np.array([leaf.lo for leaf in leaves])
        cells = np.rint(corners / res).astype(np.int64)
        occupancy.paint(keys, cells, self._grey(prob, occupancy.fill).reshape(-1, side, side))
        if variance is not None and var is not None:
            level = 1.0 - var / change.signal_variance
            variance.paint(keys, cells, self._grey(level, variance.fill).reshape(-1, side, side))
        known = ~np.isnan(prob).all(axis=1)
        if not known.any():
            return None
        uppers = np.array([leaf.hi for leaf in leaves])
        return corners[known].min(axis=0), uppers[known].max(axis=0)

    def _follow(self, lo: FloatArray, hi: FloatArray) -> None:
        """Grow the default view to hold the box ``lo``-``hi`` (metres), with a margin.

        The first known box sets :attr:`shown`; a box outside it widens it by a tenth of
        its size (at least a metre) on every side and sends the default blueprint again
        (``make_default``, not active: a layout the user chose is kept).
        """
        if self._known is not None:
            lo, hi = np.minimum(lo, self._known[0]), np.maximum(hi, self._known[1])
        self._known = (lo, hi)  # what the map knows, without the margin
        if self.shown is not None:
            inside = [a >= s[0] and b <= s[1] for a, b, s in zip(lo, hi, self.shown, strict=True)]
            if all(inside):
                return
        pad = np.maximum(0.1 * (hi - lo), 1.0)
        a, b = lo - pad, hi + pad
        self.shown = tuple((float(x0), float(x1)) for x0, x1 in zip(a, b, strict=True))
        if self._follow_view:
            self.rec.send_blueprint(
                default_blueprint(len(lo), uncertainty=self.uncertainty, bounds=self.shown),
                make_active=False,
                make_default=True,
            )

    def _grey(self, prob: FloatArray, fill: int) -> NDArray[np.uint8]:
        """Grey levels of P (:func:`~octolgp.sinks.colours.grey_levels`), ``fill`` where NaN."""
        known = ~np.isnan(prob)
        grey = np.full(prob.shape, fill, np.uint8)
        grey[known] = grey_levels(prob[known], self.grey_steps)
        return grey

    def _log_tiles(
        self,
        prefix: str,
        tiles: Tiles,
        res: float,
        palette: tuple[NDArray[np.uint8], NDArray[np.uint8]] | None,
        *,
        clear_others: bool = False,
    ) -> None:
        """Log the tiles that changed, through ``palette`` (indices, colours) when given.

        ``clear_others`` clears the tiles under ``prefix`` an earlier call logged and this
        one did not.
        """
        logged = set()
        for (tx, ty), grey in tiles.changed():  # one iteration per tile that changed
            path = f"{prefix}/{tx}_{ty}"
            logged.add(path)
            if (tx, ty) not in tiles.placed:
                x0, y1 = tx * tiles.tile * res, (ty + 1) * tiles.tile * res
                # pixel (u, v) → (x0 + u r, −y1 + v r): row 0 is the tile's top (largest y)
                self.rec.log(
                    path, rr.Transform3D(translation=[x0, -y1, 0.0], scale=res), static=True
                )
                tiles.placed.add((tx, ty))
            rows = grey[::-1]
            data = png(rows) if palette is None else png(palette[0][rows], palette[1])
            self.rec.log(path, rr.EncodedImage(contents=data, media_type="image/png"))
        if clear_others:
            self._clear_others(prefix, logged)

    def _clear_others(self, prefix: str, logged: set[str]) -> None:
        """Clear the entities under ``prefix`` logged by an earlier call and not by this one."""
        earlier = self._provisional_paths.get(prefix, set())
        for path in sorted(earlier - logged):  # one iteration per entity gone
            self.rec.log(path, rr.Clear(recursive=False))
        self._provisional_paths[prefix] = logged

    # ------------------------------------------------------------------ 3D regions
    def _regions(self, side: int) -> Regions:
        if self._voxels is None:
            size = side * -(-self.region // side)
            probability = self.colors == "probability"  # a colour change is a change
            self._voxels = Regions(size, compare_extra=probability)
            self._variance3d = Regions(size, compare_extra=True) if self.uncertainty else None
            self._free = Regions(size, compare_extra=probability) if self.free_voxels else None
        return self._voxels

    def _update_regions(self, change: MapChange) -> None:
        """Re-collect the voxels drawn of the refitted leaves, then log changed regions."""
        voxels = self._regions(change.side)
        variance, free = self._variance3d, self._free
        res = change.resolution
        box = None
        for leaf in change.leaves:  # one iteration per refitted leaf
            cell = np.rint(leaf.lo / res).astype(np.int64)
            value = self._occupied(leaf, res)
            box = _grow(box, value[0], value[1])
            voxels.put(leaf.key, cell, value)
            if free is not None:
                free.put(leaf.key, cell, self._free_of(leaf, res))
            if variance is not None:
                level = leaf.var.astype(np.float64) / change.signal_variance
                none = np.zeros((0, 3))
                empty = leaf.pruned or leaf.var.size == 0
                known = ~np.isnan(level)  # voxels far from every observation hold no value
                variance.put(
                    leaf.key,
                    cell,
                    (none, none, np.zeros(0))
                    if empty
                    else (leaf.centres[known], none, level[known]),
                )
        for key in change.removed:  # one iteration per leaf that left the map
            for regions in (voxels, free, variance):
                if regions is not None:
                    regions.remove(key)
        if box is not None:  # the camera follows the voxels drawn, not the scans' rays
            self._follow(*box)
        self._log_voxels("world/map/voxels", voxels)
        if free is not None:
            for (rx, ry, rz), centres, _, prob in free.changed():  # one per region
                colours = (
                    probability_colours(prob)
                    if self.colors == "probability"
                    else np.array([_FREE_COLOUR], np.uint8)
                )
                self.rec.log(
                    f"world/map/free/{rx}_{ry}_{rz}",
                    rr.Points3D(centres.astype(np.float32), radii=0.25 * res, colors=colours),
                )
        if variance is not None:
            for (rx, ry, rz), centres, _, level in variance.changed():  # one per region
                self.rec.log(
                    f"world/map/variance/{rx}_{ry}_{rz}",
                    rr.Points3D(
                        centres.astype(np.float32),
                        radii=0.3 * res,
                        colors=np.repeat(grey_levels(1.0 - level)[:, None], 3, axis=1),
                    ),
                )

    def _log_voxels(self, prefix: str, regions: Regions, *, clear_others: bool = False) -> None:
        """Log the regions of occupied boxes that changed, coloured by height or P."""
        lo, hi = self._heights or (0.0, 1.0)
        logged = set()
        for (rx, ry, rz), centres, half, prob in regions.changed():  # one per region changed
            path = f"{prefix}/{rx}_{ry}_{rz}"
            if centres.shape[0] == 0:
                self.rec.log(path, rr.Clear(recursive=False))
                continue
            logged.add(path)
            same = bool(np.all(half == half[0]))
            colours = (
                probability_colours(prob)
                if self.colors == "probability"
                else height_colours((centres[:, 2] - lo) / (hi - lo))
            )
            self.rec.log(
                path,
                rr.Boxes3D(
                    centers=centres.astype(np.float32),
                    half_sizes=half[:1] if same else half,
                    colors=colours,
                    fill_mode="solid",
                ),
            )
        if clear_others:
            self._clear_others(prefix, logged)

    def _occupied(self, leaf: LeafView, res: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """A 3D leaf's occupied boxes: voxels with P > 0.5, or the whole leaf when pruned.

        The third array is P, rounded to the 2D images' steps when colours show it (a
        refit that changes no colour then re-logs nothing).
        """
        if leaf.pruned or leaf.prob.size == 0:
            if leaf.prob.size == 0 or float(leaf.prob[0]) <= 0.5:
                none = np.zeros((0, 3))
                return none, none, np.zeros(0)
            centres = (0.5 * (leaf.lo + leaf.hi))[None, :]
            half = (0.5 * (leaf.hi - leaf.lo))[None, :]
            prob = leaf.prob.astype(np.float64)
        else:
            occ = leaf.prob > 0.5
            centres = leaf.centres[occ]
            half = np.full((centres.shape[0], 3), 0.5 * res)
            prob = leaf.prob[occ].astype(np.float64)
        return centres, half, self._level(prob)

    def _free_of(self, leaf: LeafView, res: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """A 3D leaf's free voxels drawn: P < :data:`FREE_BELOW`, keys multiples of the stride."""
        none = np.zeros((0, 3))
        if leaf.prob.size == 0:
            return none, none, np.zeros(0)
        prob = np.broadcast_to(leaf.prob, leaf.centres.shape[:1])
        cells = np.floor(leaf.centres / res).astype(np.int64)
        keep = (prob < FREE_BELOW) & np.all(cells % FREE_STRIDE == 0, axis=1)
        return leaf.centres[keep], none, self._level(prob[keep].astype(np.float64))

    def _level(self, prob: FloatArray) -> FloatArray:
        """P as drawn: rounded to :attr:`grey_steps` steps when colours show it, else zeros."""
        if self.colors != "probability":
            return np.zeros(prob.shape)
        return np.rint(prob * self.grey_steps) / self.grey_steps


def _is_power(n: int, base: int) -> bool:
    """Whether ``n`` is ``base`` to a whole power (1 is)."""
    while n > 1 and n % base == 0:
        n //= base
    return n == 1


def _grow(
    box: tuple[FloatArray, FloatArray] | None, centres: FloatArray, half: FloatArray
) -> tuple[FloatArray, FloatArray] | None:
    """``box`` grown to hold the boxes ``centres`` ± ``half`` (``None``: empty so far)."""
    if centres.shape[0] == 0:
        return box
    lo, hi = (centres - half).min(axis=0), (centres + half).max(axis=0)
    if box is None:
        return lo, hi
    return np.minimum(box[0], lo), np.maximum(box[1], hi)
