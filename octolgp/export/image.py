"""2D occupancy images (PNG): a Matplotlib figure, or a floor plan of one pixel per cell.

Matplotlib and Pillow are imported lazily.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.export.common import PathLike, as_centres, as_prob, replacing
from octolgp.geometry.keys import addressable_range

__all__ = ["floor_plan", "occupancy_raster", "write_floor_plan", "write_png"]

UNKNOWN_GREY = 128
"""The floor plan's pixel where P(occupied) is exactly 0.5 (no information)."""


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
    with replacing(path) as tmp:
        fig.savefig(tmp, dpi=dpi)


def floor_plan(
    occupancy: Callable[[NDArray[np.float64]], ArrayLike],
    low: ArrayLike,
    high: ArrayLike,
    resolution: float,
    *,
    chunk: int = 1 << 18,
) -> NDArray[np.uint8]:
    """Sample a 2D map on the cell-centre grid of a box: a greyscale floor plan, north up.

    One pixel per cell of pitch ``resolution``, centred at ``low + i * resolution``
    up to ``high`` (both included, rounded to whole cells). A pixel is
    ``round(255 * (1 - P))``: free light, occupied dark, and exactly
    :data:`UNKNOWN_GREY` where P is exactly 0.5 (the map has no information there).
    Sampling a continuous map (``OnlineMap.occupancy``) leaves no seams at leaf borders.

    Parameters
    ----------
    occupancy : callable
        P(occupied) at an array of points of shape (q, 2), world frame, metres.
    low, high : array_like of float, shape (2,)
        Centres of the lower-left and upper-right cells, metres.
    resolution : float
        Cell edge, metres.
    chunk : int, optional
        Points per call of ``occupancy`` (whole rows; memory stays bounded).

    Returns
    -------
    ndarray of uint8, shape (ny, nx)
        Row 0 is the largest y (north up), column 0 the smallest x.

    Raises
    ------
    OctolgpError
        On a bad resolution or box, a box wider than 10^8 cells, or probabilities
        of the wrong shape or outside [0, 1].
    """
    addressable_range(resolution, 16)  # raises on a bad resolution
    lo = as_centres(np.reshape(np.asarray(low, dtype=np.float64), (1, -1)), (2,))[0]
    hi = as_centres(np.reshape(np.asarray(high, dtype=np.float64), (1, -1)), (2,))[0]
    if (hi < lo).any():
        raise OctolgpError(f"floor plan: high {hi.tolist()} is below low {lo.tolist()}")
    nx, ny = (np.rint((hi - lo) / resolution).astype(np.int64) + 1).tolist()
    if nx * ny > 100_000_000:
        raise OctolgpError(f"floor plan: {nx} x {ny} cells at resolution {resolution:g}")
    xs = lo[0] + resolution * np.arange(nx)
    ys = lo[1] + resolution * np.arange(ny)
    image = np.empty((ny, nx), dtype=np.uint8)
    rows = max(1, chunk // nx)
    for start in range(0, ny, rows):  # one iteration per block of rows
        y = ys[start : start + rows]
        points = np.stack(np.meshgrid(xs, y), axis=-1).reshape(-1, 2)
        p = as_prob(occupancy(points), points.shape[0]).reshape(y.size, nx)
        grey = np.rint(255.0 * (1.0 - p)).astype(np.uint8)
        image[start : start + y.size] = np.where(p == 0.5, UNKNOWN_GREY, grey)
    return image[::-1]  # row 0 is north


def write_floor_plan(path: PathLike, image: ArrayLike) -> None:
    """Write a greyscale image (from :func:`floor_plan`) as an 8-bit PNG, one pixel per cell.

    Raises
    ------
    OctolgpError
        On an image that is not 2D uint8, or a ``path`` that cannot be written.
    """
    grey = np.asarray(image)
    if grey.ndim != 2 or grey.dtype != np.uint8 or grey.size == 0:
        raise OctolgpError(f"floor plan must be a non-empty 2D uint8 array, got {grey.shape}")
    from PIL import Image  # lazy: keeps `import octolgp` light

    with replacing(path) as tmp:
        Image.fromarray(np.ascontiguousarray(grey)).save(tmp, optimize=True)
