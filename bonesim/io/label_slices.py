"""One decoded label slice to structure indices, in one pass (numba).

A label stack's slice is an RGB(A) image whose colours name structures
(:mod:`bonesim.io.label_stack`). :func:`map_slice` turns one decoded slice
straight into structure indices written into its place in the stack's
case-frame array (any strides: the slice's plane of the LPS volume seen in
image axes), with no packed-colour or index temporaries. Colours no
structure claims are counted and written as 0; the caller then maps that
slice again on its slow path, which names them.

This module is imported only when a stack is read (reading a ``case.toml``
loads no numba).
"""
from __future__ import annotations

import numpy as np
from numba import njit, types

__all__ = ["UNKNOWN", "TABLE_SIZE", "map_slice", "warmup"]

UNKNOWN = 0xFFFF
"""Colour-table entry of a colour no structure has."""

TABLE_SIZE = 1 << 24
"""Entries of a colour table: one per packed RGB ``(r << 16) | (g << 8) | b``."""


# one compiled signature for every slice: pixels as Pillow hands them over
# (read-only, C order; writable arrays convert), the table, and the slice's
# plane of the volume with whatever strides the stack's orientation gives it
_SIGNATURE = types.int64(types.Array(types.uint8, 3, "C", readonly=True),
                         types.Array(types.uint16, 1, "C", readonly=True),
                         types.Array(types.uint8, 2, "A"))


@njit(_SIGNATURE, cache=True, nogil=True)
def _map_rgb(px, table, out):
    """``out[c, r] = table[rgb(px[r, c])]``; transparent pixels 0; returns
    how many pixels had an unknown colour (written 0)."""
    rows, cols, depth = px.shape
    unknown = 0
    for r in range(rows):
        for c in range(cols):
            if depth == 4 and px[r, c, 3] == 0:
                out[c, r] = 0
                continue
            code = (np.int64(px[r, c, 0]) << 16) | (np.int64(px[r, c, 1]) << 8) \
                | np.int64(px[r, c, 2])
            s = table[code]
            if s == UNKNOWN:
                unknown += 1
                s = 0
            out[c, r] = s
    return unknown


def map_slice(px: np.ndarray, table: np.ndarray, out: np.ndarray) -> int:
    """Write the structure index of every pixel of one slice into ``out``.

    Parameters
    ----------
    px : (rows, cols, 3 or 4) uint8
        The decoded slice, RGB or RGBA (alpha 0 is background).
    table : (2**24,) uint16
        Structure index per packed colour ``(r << 16) | (g << 8) | b``
        (0 background, :data:`UNKNOWN` for a colour no structure has);
        indices are at most 255.
    out : (cols, rows) uint8
        Receives the indices: ``out[column, row]``, any strides (a view into
        the stack's volume).

    Returns
    -------
    int
        Pixels whose colour the table does not know (written as 0).
    """
    px = np.ascontiguousarray(px)
    if px.ndim != 3 or px.dtype != np.uint8 or px.shape[2] not in (3, 4):
        raise ValueError(f"px must be (rows, cols, 3|4) uint8, got {px.dtype} {px.shape}")
    if table.shape != (TABLE_SIZE,) or table.dtype != np.uint16:
        raise ValueError(f"table must be ({TABLE_SIZE},) uint16, got {table.dtype} "
                         f"{table.shape}")
    if out.dtype != np.uint8 or out.shape != (px.shape[1], px.shape[0]):
        raise ValueError(f"out must be ({px.shape[1]}, {px.shape[0]}) uint8, got "
                         f"{out.dtype} {out.shape}")
    if not out.flags.writeable:
        raise ValueError("out must be writeable")
    return int(_map_rgb(px, np.ascontiguousarray(table), out))


def warmup() -> None:
    """Load (or compile) the kernel."""
    table = np.full(TABLE_SIZE, UNKNOWN, dtype=np.uint16)
    table[0] = 0
    map_slice(np.zeros((2, 3, 3), np.uint8), table, np.zeros((3, 2), np.uint8))
