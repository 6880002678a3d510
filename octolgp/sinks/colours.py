"""The colours of the Rerun view: grey occupancy, the probability and height colour maps, PNG.

Pure functions of arrays; :mod:`octolgp.sinks.rerun` logs what they make.

Grey occupancy (2D, the default)
    ``255 (1 − P)`` on ``steps + 1`` levels (:func:`grey_levels`): free light, occupied
    dark, P = 0.5 (and unknown) mid grey.
Probability (``RerunSink(colors="probability")``)
    P(occupied) on a diverging map (:data:`PROBABILITY_ANCHORS`, ColorBrewer's RdBu reversed
    with a grey middle): P = 0 blue (free), P = 0.5 grey (unknown: no leaf, or a leaf that
    cannot tell), P = 1 red (occupied). Colour-blind readers tell blue from red.
Height (3D, the default)
    :data:`HEIGHT_ANCHORS`, blue (low) to red (high), over the first scan's heights.
"""

from __future__ import annotations

import struct
import zlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "HEIGHT_ANCHORS",
    "PROBABILITY_ANCHORS",
    "grey_levels",
    "height_colours",
    "legend_image",
    "png",
    "probability_colours",
    "probability_palette",
]

PROBABILITY_ANCHORS = np.array(
    [
        [0.00, 33, 102, 172],  # free: blue
        [0.25, 146, 197, 222],
        [0.50, 190, 190, 190],  # unknown: grey
        [0.75, 244, 165, 130],
        [1.00, 178, 24, 43],  # occupied: red
    ]
)
"""``(P, R, G, B)`` rows of the probability colour map, linear in between."""

HEIGHT_ANCHORS = np.array(
    [
        [0.00, 48, 18, 160],
        [0.25, 33, 145, 140],
        [0.50, 94, 201, 98],
        [0.75, 253, 231, 37],
        [1.00, 230, 60, 30],
    ]
)
"""``(t, R, G, B)`` rows of the height ramp (t: 0 lowest, 1 highest), linear in between."""


def _interpolate(anchors: NDArray[Any], value: NDArray[Any]) -> NDArray[np.uint8]:
    """RGB uint8 per value along a ``(t, R, G, B)`` anchor table (values clipped to [0, 1])."""
    t = np.clip(np.asarray(value, dtype=np.float64), 0.0, 1.0)
    rgb = [np.interp(t, anchors[:, 0], anchors[:, c]) for c in (1, 2, 3)]
    out: NDArray[np.uint8] = np.rint(np.stack(rgb, axis=-1)).astype(np.uint8)
    return out


def probability_colours(prob: NDArray[Any]) -> NDArray[np.uint8]:
    """RGB uint8, shape ``prob.shape + (3,)``, of P(occupied) on :data:`PROBABILITY_ANCHORS`."""
    return _interpolate(PROBABILITY_ANCHORS, prob)


def height_colours(t: NDArray[Any]) -> NDArray[np.uint8]:
    """RGB uint8 of heights scaled to [0, 1] (clipped) on :data:`HEIGHT_ANCHORS`."""
    return _interpolate(HEIGHT_ANCHORS, t)


def grey_levels(prob: NDArray[Any], steps: int = 255) -> NDArray[np.uint8]:
    """Grey level per cell, occupied dark: ``255 (1 − P)`` rounded to one of ``steps + 1`` levels.

    With an even ``steps``, P = 0.5 is exactly grey 128.
    """
    k = np.rint(np.clip(1.0 - prob, 0.0, 1.0) * steps)
    return np.rint(k * (255.0 / steps)).astype(np.uint8)


def probability_palette(steps: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """The palette that shows :func:`grey_levels` images in the probability colours.

    Returns
    -------
    index : ndarray of uint8, shape (256,)
        Palette index of each grey level: ``k = round(g steps / 255)``, the level's step.
    palette : ndarray of uint8, shape (steps + 1, 3)
        Colour of step ``k``: P = 1 − k / steps on :data:`PROBABILITY_ANCHORS`.
    """
    index = np.rint(np.arange(256) * (steps / 255.0)).astype(np.uint8)
    palette = probability_colours(1.0 - np.arange(steps + 1) / steps)
    return index, palette


def legend_image(colours: NDArray[np.uint8], height: int) -> NDArray[np.uint8]:
    """A colour bar: ``colours`` (n, 3) as the columns of an RGB image ``height`` rows high."""
    return np.ascontiguousarray(np.broadcast_to(colours[None, :, :], (height, *colours.shape)))


def png(pixels: NDArray[np.uint8], palette: NDArray[np.uint8] | None = None) -> bytes:
    """An image as PNG bytes: 8 bits a sample, no row filter, zlib level 3.

    Parameters
    ----------
    pixels : ndarray of uint8, shape (h, w) or (h, w, 3)
        Grey levels, palette indices (with ``palette``) or RGB.
    palette : ndarray of uint8, shape (n, 3), optional
        Colours of the indices in ``pixels`` (an indexed PNG: the same bytes as a grey
        one, plus ``3 n`` for the palette).

    Notes
    -----
    With few levels, unfiltered rows compress as well as filtered ones (PNG spec, sections
    11.2 and 12.8); level 3 is three times as fast as level 6 for 20 % more bytes.
    """
    height, width = pixels.shape[:2]
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    raw = np.zeros((height, width * channels + 1), np.uint8)  # each row: filter 0, then pixels
    raw[:, 1:] = pixels.reshape(height, width * channels)
    colour_type = 2 if channels == 3 else (3 if palette is not None else 0)

    def chunk(tag: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(tag + data)
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    plte = b"" if colour_type != 3 or palette is None else chunk(b"PLTE", palette.tobytes())
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + plte
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 3))
        + chunk(b"IEND", b"")
    )
