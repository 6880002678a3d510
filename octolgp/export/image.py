"""2D occupancy images (PNG) drawn with Matplotlib, imported lazily."""

from __future__ import annotations

import os

import numpy as np
from numpy.typing import ArrayLike

from octolgp.errors import OctolgpError
from octolgp.export.common import PathLike, as_centres, as_prob
from octolgp.geometry.keys import addressable_range


def occupancy_raster(
    centres: ArrayLike, prob: ArrayLike, resolution: float
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Cells of pitch ``resolution`` over the centres' bounding box, unknown = 0.5.

    Returns
    -------
    grid : ndarray of shape (ny, nx)
        P(occupied), rows along y (``origin="lower"`` for ``imshow``).
    extent : tuple of float
        ``(xmin, xmax, ymin, ymax)`` of the cell edges, metres.

    Raises
    ------
    OctolgpError
        As :func:`write_png`.
    """
    addressable_range(resolution, 16)  # raises on a bad resolution
    c = as_centres(centres, (2,))
    p = as_prob(prob, c.shape[0])
    if c.shape[0] == 0:
        raise OctolgpError("centres must hold at least one cell to draw")
    low = c.min(axis=0)
    cell = np.rint((c - low) / resolution).astype(np.int64)
    nx, ny = (cell.max(axis=0) + 1).tolist()
    if nx * ny > 100_000_000:
        raise OctolgpError(f"centres span {nx} x {ny} cells at resolution {resolution:g}")
    grid = np.full((ny, nx), 0.5)
    grid[cell[:, 1], cell[:, 0]] = p
    half = 0.5 * resolution
    extent = (
        float(low[0] - half),
        float(low[0] + (nx - 0.5) * resolution),
        float(low[1] - half),
        float(low[1] + (ny - 0.5) * resolution),
    )
    return grid, extent


def write_png(
    path: PathLike,
    centres: ArrayLike,
    prob: ArrayLike,
    resolution: float,
    *,
    dpi: int = 100,
) -> None:
    """Draw a 2D occupancy image: occupied dark, free light, unknown mid-grey.

    The cells form a grid of pitch ``resolution`` over the centres' bounding box;
    cells without a centre are unknown (P = 0.5). The axes show world x and y in
    metres. Uses Matplotlib's object API (``matplotlib.figure.Figure``), so no
    global backend or pyplot state is touched.

    Parameters
    ----------
    path : str or os.PathLike
        Output image; the format follows the extension (``.png``).
    centres : array_like of float, shape (k, 2)
        Cell centres in the world frame, metres.
    prob : array_like of float, shape (k,)
        P(occupied) per cell, in [0, 1].
    resolution : float
        Cell edge, metres.
    dpi : int, optional
        Image resolution in dots per inch.

    Raises
    ------
    OctolgpError
        On a bad shape or non-finite value in ``centres`` or ``prob``, no cells,
        a bad ``resolution``, or a ``path`` that cannot be written.
    """
    grid, extent = occupancy_raster(centres, prob, resolution)
    ny, nx = grid.shape

    from matplotlib.figure import Figure  # lazy: keeps `import octolgp` light

    width = 8.0
    fig = Figure(
        figsize=(width, max(2.0, min(3 * width, width * ny / nx))), dpi=dpi, layout="constrained"
    )
    ax = fig.add_subplot()
    image = ax.imshow(
        grid,
        origin="lower",
        extent=extent,
        cmap="gray_r",
        vmin=0.0,
        vmax=1.0,
        interpolation="nearest",
    )
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.colorbar(image, ax=ax, label="P(occupied)")
    try:
        fig.savefig(os.fspath(path), dpi=dpi)
    except OSError as exc:
        raise OctolgpError(f"path {os.fspath(path)!r} cannot be written: {exc}") from exc
