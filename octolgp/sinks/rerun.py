"""Stream an online map to Rerun: one entity per leaf, re-logged only when it was refitted.

Layout of the recording (timeline ``scan``, a sequence; ``time`` too when scans
carry stamps):

``world/sensor``, ``world/sensor/points``, ``octolgp/scan``
    The scan: pose, sensor-frame points and an exact copy
    (:func:`octolgp.io.rrd_write.log_scan`), so a recording replays into the same map.
``world/sensor/rays``
    Optional, decimated beams as line strips (sensor frame).
``world/map/leaves/<packed leaf key>``
    3D: the leaf's occupied voxels (P > 0.5) as ``Boxes3D``, coloured by
    probability; a pruned occupied leaf is one box, a pruned free one is cleared.
    2D: the leaf as one textured quad (``Mesh3D``) at z = 0 whose side × side
    texture is the grey level ``1 − P`` (occupied dark), the usual occupancy-grid
    picture; the quad is static, each refit sends 3 bytes per voxel. A leaf is logged only in the scans that refit it, so a
    10,000-leaf map costs per scan only what changed.
``world/map/variance/<packed leaf key>``
    Optional uncertainty layer: latent variance / σf² per voxel.
``metrics/*``
    ``Scalars`` per scan: insert seconds, touched and refit leaves, leaves, memory MB.

rerun-sdk is imported here and in the ``octolgp.io.rrd*`` modules only.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import rerun.components as rrc

from octolgp.errors import OctolgpError
from octolgp.scan import FloatArray, Scan
from octolgp.sinks.base import LeafView, MapChange

if TYPE_CHECKING:
    from octolgp.mapping.update import ScanUpdate


def _grey(prob: np.ndarray) -> np.ndarray:
    """RGB uint8, occupied dark: ``255 (1 − P)``."""
    g = np.clip(255.0 * (1.0 - prob), 0, 255).astype(np.uint8)
    return np.repeat(g[:, None], 3, axis=1)


def _heat(value: np.ndarray) -> np.ndarray:
    """RGB uint8 from blue (0) to red (1)."""
    v = np.clip(value, 0.0, 1.0)
    return np.stack([255 * v, 64 + 96 * (1 - np.abs(2 * v - 1)), 255 * (1 - v)], axis=1).astype(
        np.uint8
    )


def open_recording(
    app_id: str = "octolgp",
    *,
    save: str | Path | None = None,
    connect: str | None = None,
    serve: bool = False,
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

    Returns
    -------
    recording : rerun.RecordingStream
        The stream, ready for a :class:`RerunSink`; ``flush()`` and ``disconnect()`` it when
        done.
    url : str or None
        The address viewers connect to when serving (``rerun --connect URL``), else None.

    Raises
    ------
    ValueError
        Unless exactly one of ``save``, ``connect`` and ``serve`` is given.
    OctolgpError
        If rerun refuses the path or URL (names which, with rerun's reason).
    """
    targets = (save is not None) + (connect is not None) + bool(serve)
    if targets != 1:
        raise ValueError("open_recording: give exactly one of save=, connect= and serve=True")
    rec = rr.RecordingStream(app_id)
    url = None
    try:
        if save is not None:
            what = f"cannot save a Rerun recording to {str(save)!r}"
            rec.save(save)
        elif connect is not None:
            what = f"cannot connect to a Rerun viewer at {connect!r}"
            rec.connect_grpc(connect)
        else:
            what = "cannot serve a Rerun recording over gRPC"
            url = rec.serve_grpc()
    except (RuntimeError, ValueError, TypeError) as exc:  # how rerun reports a bad path or URL
        raise OctolgpError(f"{what}: {exc}") from None
    return rec, url


def default_blueprint(dim: int) -> Any:
    """A map view beside a timings plot."""
    del dim  # 2D maps are drawn at z = 0 in the same 3D view
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map"),
            rrb.TimeSeriesView(origin="metrics", name="per scan"),
            column_shares=[3, 1],
        ),
        collapse_panels=True,
    )


class RerunSink:
    """Logs scans and map updates of an online map to a recording (a :class:`~octolgp.sinks.base.Sink`).

    Parameters
    ----------
    recording : rerun.RecordingStream
        Where to log (a file, a gRPC connection, a memory sink...).
    rays : int
        Log every ``rays``-th beam as a line; 0 (default) logs none.
    uncertainty : bool
        Also log the latent-variance layer.
    blueprint : bool
        Send the default blueprint with the first scan.
    """

    def __init__(
        self,
        recording: rr.RecordingStream,
        *,
        rays: int = 0,
        uncertainty: bool = False,
        blueprint: bool = True,
    ) -> None:
        self.rec = recording
        self.rays = int(rays)
        self.uncertainty = bool(uncertainty)
        self._blueprint = blueprint
        self._tiles: set[str] = set()

    def on_scan(self, scan: Scan, index: int) -> None:
        """Log an accepted scan (pose, points, exact copy, optional rays)."""
        from octolgp.io.rrd_write import log_scan

        if self._blueprint:
            self.rec.send_blueprint(default_blueprint(scan.dim))
            self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            self._blueprint = False
        log_scan(self.rec, scan, index)
        if self.rays > 0:
            local = scan.points[:: self.rays] - scan.origin
            if local.shape[1] == 2:
                local = np.c_[local, np.zeros(local.shape[0])]
            strips = np.stack([np.zeros_like(local), local], axis=1).astype(np.float32)
            self.rec.log("world/sensor/rays", rr.LineStrips3D(strips, radii=0.005))

    def on_update(self, update: ScanUpdate, change: MapChange) -> None:
        """Re-log the refitted leaves and the per-scan metrics."""
        rec = self.rec
        rec.set_time("scan", sequence=update.scan)
        for leaf in change.leaves:  # one iteration per refitted leaf
            self._log_leaf(change, leaf)
        for key in change.removed:  # one iteration per leaf that left the map
            self._clear_leaf(change, key)
        rec.log("metrics/insert_seconds", rr.Scalars(update.seconds))
        rec.log("metrics/touched_leaves", rr.Scalars(float(update.touched_leaves)))
        rec.log("metrics/refit_leaves", rr.Scalars(float(update.refit_leaves)))
        rec.log("metrics/leaves", rr.Scalars(float(update.n_leaves)))
        rec.log("metrics/memory_mb", rr.Scalars(update.memory_bytes / 1e6))

    def _log_leaf(self, change: MapChange, leaf: LeafView) -> None:
        path = f"world/map/leaves/{leaf.key}"
        if leaf.pruned and change.dim == 3:
            self._log_box(path, leaf.lo, leaf.hi, float(leaf.prob[0]))
            if self.uncertainty:  # a pruned leaf is confident: no variance layer
                self.rec.log(f"world/map/variance/{leaf.key}", rr.Clear(recursive=False))
            return
        centres = leaf.centres
        prob = leaf.prob.astype(np.float64)
        if change.dim == 2:
            self._log_tile(path, change.side, leaf, prob)
        else:
            occ = prob > 0.5
            half = np.full((int(occ.sum()), 3), 0.5 * change.resolution)
            self.rec.log(
                path,
                rr.Boxes3D(
                    centers=centres[occ],
                    half_sizes=half,
                    colors=_heat(2.0 * (prob[occ] - 0.5)),
                    fill_mode="solid",
                ),
            )
        if self.uncertainty:
            pos = centres if change.dim == 3 else np.c_[centres, np.zeros(centres.shape[0])]
            self.rec.log(
                f"world/map/variance/{leaf.key}",
                rr.Points3D(
                    pos,
                    radii=0.3 * change.resolution,
                    colors=_heat(leaf.var.astype(np.float64) / change.signal_variance),
                ),
            )

    def _clear_leaf(self, change: MapChange, key: int) -> None:
        """A leaf that left the map: unknown grey in 2D (its quad is static), gone in 3D."""
        path = f"world/map/leaves/{key}"
        if change.dim == 2:
            if path in self._tiles:
                grey = _grey(np.full(change.side * change.side, 0.5))
                self.rec.log(path, rr.Mesh3D.from_fields(albedo_texture_buffer=grey.tobytes()))
        else:
            self.rec.log(path, rr.Clear(recursive=False))
        if self.uncertainty:
            self.rec.log(f"world/map/variance/{key}", rr.Clear(recursive=False))

    def _log_tile(self, path: str, side: int, leaf: LeafView, prob: np.ndarray) -> None:
        """A 2D leaf as one textured quad at z = 0: a side × side grey image.

        The quad, its triangles, texture coordinates and texture format are
        logged once, static; each refit logs only the texture bytes (3 per voxel).
        """
        if path not in self._tiles:
            (x0, y0), (x1, y1) = leaf.lo, leaf.hi
            quad = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
            self.rec.log(
                path,
                rr.Mesh3D.from_fields(
                    vertex_positions=quad,
                    triangle_indices=np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),
                    vertex_texcoords=np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]),
                    albedo_texture_format=rrc.ImageFormat(
                        side, side, color_model="RGB", channel_datatype="U8"
                    ),
                ),
                static=True,
            )
            self._tiles.add(path)
        # flat voxel order is x fastest, so rows of the image are y, columns x
        texture = _grey(np.broadcast_to(prob, (side * side,)))
        self.rec.log(path, rr.Mesh3D.from_fields(albedo_texture_buffer=texture.tobytes()))

    def _log_box(self, path: str, lo: FloatArray, hi: FloatArray, prob: float) -> None:
        """A pruned 3D leaf: one box if occupied, nothing (cleared) if free."""
        if prob < 0.5:
            self.rec.log(path, rr.Clear(recursive=False))
            return
        self.rec.log(
            path,
            rr.Boxes3D(
                centers=0.5 * (lo + hi),
                half_sizes=0.5 * (hi - lo),
                colors=_heat(np.array([2 * prob - 1])),
                fill_mode="solid",
            ),
        )
