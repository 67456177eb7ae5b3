"""Incremental update of the hybrid surface for any set of removed voxels:
scattered input is tiled into windows, each re-planned on dense bit rows by
:mod:`bonesim.engine.surface_window` (:meth:`bonesim.engine.surface.Surface.update`).

Removed voxels whose window (bounding box plus ``WINDOW_MARGIN``) is small
(the usual case: a burr's worth of voxels) are one window. Others are
grouped by the aligned cube of ``2**TILE_SHIFT`` voxels they fall in, and
the tiles are updated one after the other, each as a window of its own
removed voxels (:func:`bonesim.engine.surface_window._window_pass`).

Why this equals one update over all of them:

* A cell is re-evaluated from the current grid (all removals applied) and
  the mesh's own owner lists, so once any tile has re-evaluated a cell it
  owns exactly the triangles it should, and a later tile that re-evaluates
  it again changes nothing. Every cell whose triangles change contains a
  source or has one below its minimum face, and the tile of that source
  re-evaluates it (a tile skips a cell only when no source of its own is in
  it and the ownership tests all pass: then a source of another tile is in
  the cell or nothing changed).
* A tile adds triangles only to cells holding one of its sources, whose
  corners are all next to that source (corners of a cell are pairwise
  26-adjacent); the tile creates the vertices next to its sources before it
  adds triangles, so every corner has its vertex. (It re-evaluates other
  cells only when an ownership test reads four empty voxels, and then the
  cell owns nothing: a triangle in its minimum face along an axis qualifies
  only when its far layer along that axis is empty, so all its triangles
  lie in that face and belong to the cell below.)
* A source's vertex is dropped by its own tile, which first re-evaluates
  every cell containing the source, so its triangles are gone. A tile that
  drops a triangle with another tile's source as a corner leaves it on that
  source's vertex list only, a list dropped whole with the vertex.

The naive reference (a from-scratch tessellation equals the incremental
result) is checked with tiles of 2 voxels, where tiles meet everywhere.

Touched voxels (density lowered, still > 0) change no occupancy, so they
change nothing here (only the shading, :meth:`bonesim.engine.shading.Shader.refresh`);
their coordinates are still checked.

An update that runs out of room stops before the tile that needs it and
records where it stopped (``stats[S_RESUME]``); the caller grows the arrays
and calls again with ``resume`` set, and the update goes on from that tile.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from bonesim.engine.brick_hash import BRICK, pack_brick_key
from bonesim.engine.surface_tables import S_RESUME, S_STATUS
from bonesim.engine.surface_window import WINDOW_DEPTH, WINDOW_MARGIN, window_pass

__all__ = ["WINDOW_MIN_VOXELS", "WINDOW_VOXELS_PER_INPUT", "TILE_SHIFT", "COORD_LIMIT"]

#: Removed voxels are updated as one window when it is at most
#: ``WINDOW_DEPTH`` voxels deep along k and holds at most ``WINDOW_MIN_VOXELS
#: + WINDOW_VOXELS_PER_INPUT * n_removed`` voxels; otherwise they are tiled.
WINDOW_MIN_VOXELS = 32768
WINDOW_VOXELS_PER_INPUT = 64
#: Tiles are aligned cubes of ``2**TILE_SHIFT`` voxels (a tile's window,
#: ``2**TILE_SHIFT + 2 * WINDOW_MARGIN`` voxels at most, must fit
#: ``WINDOW_DEPTH``).
TILE_SHIFT = 5
#: Voxel coordinates must have a magnitude below this (packed keys, margins).
COORD_LIMIT = (1 << 20) - 2 * BRICK

if (1 << TILE_SHIFT) + 2 * WINDOW_MARGIN > WINDOW_DEPTH:
    raise AssertionError("a tile's window must fit WINDOW_DEPTH")


@njit(cache=True, nogil=True, inline="always")
def _tile_key(ijk, q, shift):
    """Packed key of the tile of voxel ``ijk[q]`` (ordered by (i, j, k) tile;
    packed as brick keys are)."""
    return pack_brick_key(ijk[q, 0] >> shift, ijk[q, 1] >> shift, ijk[q, 2] >> shift)


@njit(cache=True, nogil=True)
def _out_of_range(ijk):
    for q in range(ijk.shape[0]):
        for a in range(3):
            if ijk[q, a] <= -COORD_LIMIT or ijk[q, a] >= COORD_LIMIT:
                return True
    return False


@njit(cache=True, nogil=True)
def update_tiles(keys, vals, density, origin, spacing, removed, touched, win_limit, tile_shift,
            resume, vmap, pos, vijk, valive, vrec, vfree, trec, tfree, cnt, stats,
            sf32, si32, su8, su64):
    """Re-tessellate around ``removed`` (int32 (n, 3)), one window or tiles.

    ``win_limit`` replaces ``WINDOW_MIN_VOXELS`` (< 0: always tile, for
    tests) and ``tile_shift`` ``TILE_SHIFT`` (1 to 5). Unless ``resume``,
    ``stats`` is cleared first; counts are added to it.

    Sets ``stats[S_STATUS]``: 0 done, 1 vertex / triangle arrays too small,
    2 scratch too small (sizes in ``stats[_S_NEED_V]``, ``stats[_S_NEED_T]``;
    call again with ``resume`` after growing), 4 / 5 a removed / touched
    voxel has a coordinate of magnitude ``COORD_LIMIT`` or more (nothing
    changed).
    """
    if not resume:
        for s in range(stats.shape[0]):
            stats[s] = 0
    stats[S_STATUS] = 0
    if _out_of_range(removed):
        stats[S_STATUS] = 4
        return
    if _out_of_range(touched):
        stats[S_STATUS] = 5
        return
    nr = removed.shape[0]
    if nr == 0:
        return
    lo = np.empty(3, dtype=np.int64)
    hi = np.empty(3, dtype=np.int64)
    for a in range(3):
        lo[a] = removed[0, a]
        hi[a] = removed[0, a]
    for q in range(nr):
        for a in range(3):
            lo[a] = min(lo[a], removed[q, a])
            hi[a] = max(hi[a], removed[q, a])
    vol = 1
    for a in range(3):
        vol *= hi[a] - lo[a] + 1 + 2 * WINDOW_MARGIN
    if (win_limit >= 0 and hi[2] - lo[2] + 1 + 2 * WINDOW_MARGIN <= WINDOW_DEPTH
            and vol <= win_limit + WINDOW_VOXELS_PER_INPUT * nr):
        stats[S_STATUS] = window_pass(keys, vals, density, origin, spacing, removed,
                                        vmap, pos, vijk, valive, vrec, vfree, trec, tfree,
                                        cnt, stats, sf32, si32, su8, su64)
        return
    # ---- tiles: the removed voxels sorted by tile, one run per tile ----------
    tkey = np.empty(nr, dtype=np.int64)
    for q in range(nr):
        tkey[q] = _tile_key(removed, q, tile_shift)
    order = np.argsort(tkey, kind="mergesort")
    srt = np.empty((nr, 3), dtype=np.int32)
    start = np.empty(nr + 1, dtype=np.int64)
    n_tiles = 0
    for q in range(nr):
        p = order[q]
        for a in range(3):
            srt[q, a] = removed[p, a]
        if q == 0 or tkey[p] != tkey[order[q - 1]]:
            start[n_tiles] = q
            n_tiles += 1
    start[n_tiles] = nr
    first = stats[S_RESUME] if resume else 0
    for t in range(first, n_tiles):
        st = window_pass(keys, vals, density, origin, spacing, srt[start[t]:start[t + 1]],
                          vmap, pos, vijk, valive, vrec, vfree, trec, tfree, cnt, stats,
                          sf32, si32, su8, su64)
        if st != 0:
            stats[S_STATUS] = st
            stats[S_RESUME] = t
            return
    stats[S_RESUME] = 0
