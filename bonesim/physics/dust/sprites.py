"""What :meth:`bonesim.physics.dust.DustGrid.sprites` hands the renderer (numba kernels).

One sprite per dusty cell that the eye can see, placed at a fixed random
point of its cell, with the age of the dust in it:

* **Which cells.** Cells holding more than ``thr`` dust; with ``top_only``
  only those whose neighbour *above* (against gravity's dominant axis, see
  :mod:`bonesim.physics.dust.grid`) holds less than ``cover`` dust: the top layer of
  every pile. Deeper cells would only stack more translucent sprites on one
  another, and the dust would hide the cavity floor (the app's gravity runs
  along the view direction, so "above" is "toward the eye").
* **Where.** The cell centre plus a jitter of up to ``jitter`` cell edges
  along each axis, from an integer hash of the cell's coordinates and its
  species (dry 0, wet 1): the same every frame (no flicker), different from
  cell to cell (no regular grid pattern).
* **Age.** Each cell remembers when dust arrived in it: the time of the
  last call (:func:`_stamp`, :func:`_gather`) that saw it at or below
  ``thr`` (a cell of a brick that held no dust at the previous call counts
  as just arrived). The age is ``now - arrival`` [s].
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from bonesim.physics.dust.bricks import FULL_Q, C_HW
from bonesim.engine.grid import BRICK_SHIFT, BRICK_VOXELS, pack_brick_key

__all__ = ["DustSprites", "cell_jitter", "stamp_arrivals", "gather_sprites"]

# splitmix64 constants (a well-mixed integer hash)
_M1 = np.uint64(0x9E3779B97F4A7C15)
_M2 = np.uint64(0xBF58476D1CE4E5B9)
_M3 = np.uint64(0x94D049BB133111EB)


@njit(cache=True, nogil=True, inline="always")
def _mix(x):
    x = x + _M1
    x = (x ^ (x >> np.uint64(30))) * _M2
    x = (x ^ (x >> np.uint64(27))) * _M3
    return x ^ (x >> np.uint64(31))


@njit(cache=True, nogil=True)
def _jitter3(i, j, k, salt):
    """Three numbers in [-1, 1) from the cell ``(i, j, k)`` and ``salt``."""
    h = _mix(np.uint64(pack_brick_key(i, j, k)) ^ (np.uint64(salt) << np.uint64(63)))
    scale = 1.0 / 1048576.0                         # 20 bits each
    a = np.float64((h >> np.uint64(2)) & np.uint64(0xFFFFF)) * scale
    b = np.float64((h >> np.uint64(22)) & np.uint64(0xFFFFF)) * scale
    c = np.float64((h >> np.uint64(42)) & np.uint64(0xFFFFF)) * scale
    return 2.0 * a - 1.0, 2.0 * b - 1.0, 2.0 * c - 1.0


class DustSprites(NamedTuple):
    """What the window draws of the dust (:meth:`DustGrid.sprites`); unpacks
    into :meth:`bonesim.render.scene.Scene.set_dust`'s arguments.

    Attributes
    ----------
    positions : (n, 3) float32
        Sprite centres, case frame [mm] (cell centres plus a fixed jitter).
    density : (n,) float32
        Dust in the sprite's cell [cells] (1 full; briefly more where dust was
        just added or pushed).
    cell_mm : float
        Cell edge [mm].
    age_s : (n,) float32
        Time since dust arrived in the cell [s].
    wet : (n,) uint8
        1 for wet dust (paste), 0 for dry.
    """

    positions: np.ndarray
    density: np.ndarray
    cell_mm: float
    age_s: np.ndarray
    wet: np.ndarray


def cell_jitter(ijk, salt: int = 0) -> np.ndarray:
    """The sprite jitter of cells ``ijk`` (n, 3) int: (n, 3) float64 in
    [-1, 1), to be scaled by ``jitter * spacing_mm`` (tests, references)."""
    ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    out = np.empty((len(ijk), 3))
    for q in range(len(ijk)):
        out[q] = _jitter3(ijk[q, 0], ijk[q, 1], ijk[q, 2], int(salt) & 1)
    return out


@njit(cache=True, nogil=True, inline="always")
def _above(b, o, den, nbr, dom, up, up_dd):
    """Dust [1/Q cells] in the cell above offset ``o`` of brick ``b``."""
    sh = 6 - 3 * dom
    loc = (o >> sh) & 7
    nl = loc + up
    if 0 <= nl <= 7:
        return den[b, o + up * (1 << sh)]
    m = nbr[b, up_dd]
    if m < 0:
        return 0
    return den[m, o - up * 7 * (1 << sh)]


@njit(cache=True, nogil=True)
def _visible(b, o, den, thr, nbr, dom, up, up_dd, top_only, cover):
    if den[b, o] <= thr:
        return False
    if top_only and _above(b, o, den, nbr, dom, up, up_dd) >= cover:
        return False
    return True


@njit(cache=True, nogil=True)
def _stamp(alive, bmass, hw, den, thr, bcoord, nbr, seen, seen_key, now, dom, up, up_dd,
           top_only, cover):
    """Update the arrival times and count the sprites."""
    n = 0
    for b in range(hw):
        if not alive[b] or bmass[b] == 0:
            seen_key[b] = -1
            continue
        key = pack_brick_key(bcoord[b, 0], bcoord[b, 1], bcoord[b, 2])
        if seen_key[b] != key:
            for o in range(BRICK_VOXELS):
                seen[b, o] = now
            seen_key[b] = key
        for o in range(BRICK_VOXELS):
            if den[b, o] <= thr:
                seen[b, o] = now
            elif _visible(b, o, den, thr, nbr, dom, up, up_dd, top_only, cover):
                n += 1
    return n


@njit(cache=True, nogil=True)
def _gather(alive, bmass, hw, den, thr, bcoord, nbr, seen, seen_key, now, dom, up, up_dd,
            top_only, cover, origin, h, jitter, salt, pos, val, age, start):
    """:func:`_stamp` and the sprites in one pass: update the arrival times
    and write the sprites from index ``start`` on (``pos`` must hold them
    all); returns the next index."""
    n = start
    inv_q = 1.0 / FULL_Q
    amp = jitter * h
    for b in range(hw):
        if not alive[b] or bmass[b] == 0:
            seen_key[b] = -1
            continue
        key = pack_brick_key(bcoord[b, 0], bcoord[b, 1], bcoord[b, 2])
        if seen_key[b] != key:
            for o in range(BRICK_VOXELS):
                seen[b, o] = now
            seen_key[b] = key
        x0 = np.int64(bcoord[b, 0]) << BRICK_SHIFT
        y0 = np.int64(bcoord[b, 1]) << BRICK_SHIFT
        z0 = np.int64(bcoord[b, 2]) << BRICK_SHIFT
        for o in range(BRICK_VOXELS):
            if den[b, o] <= thr:
                seen[b, o] = now
                continue
            if top_only and _above(b, o, den, nbr, dom, up, up_dd) >= cover:
                continue
            i = x0 + (o >> 6)
            j = y0 + ((o >> 3) & 7)
            k = z0 + (o & 7)
            if amp > 0.0:
                ja, jb, jc = _jitter3(i, j, k, salt)
            else:
                ja = jb = jc = 0.0
            pos[n, 0] = origin[0] + h * i + amp * ja
            pos[n, 1] = origin[1] + h * j + amp * jb
            pos[n, 2] = origin[2] + h * k + amp * jc
            val[n] = den[b, o] * inv_q
            age[n] = now - seen[b, o]
            n += 1
    return n


def stamp_arrivals(species, thr_q, cover_q, dom, dsgn, top_only, now) -> int:
    """Update the cells' arrival times as :func:`gather_sprites` does, without
    gathering the sprites (a tenth of its cost); returns the sprite count.
    Arguments as :func:`gather_sprites`."""
    up = -dsgn
    up_dd = 2 * dom + (1 if up > 0 else 0)
    return sum(int(_stamp(g.alive, g.bmass, int(g._ctr[C_HW]), g.density_q, thr_q, g.bcoord,
                          g.nbr, g._seen, g._seen_key, now, dom, up, up_dd, top_only,
                          cover_q))
               for g in species)


def gather_sprites(species, thr_q, cover_q, dom, dsgn, top_only, now, origin_mm, spacing_mm,
                   jitter) -> DustSprites:
    """The sprites of dust species (:meth:`bonesim.physics.dust.DustGrid.sprites`).

    Parameters
    ----------
    species : sequence of DustGrid
        Dry first, then wet (a sprite's ``wet`` is its species' index).
    thr_q, cover_q : int
        Sprite threshold and cover [1/Q cells].
    dom, dsgn : int
        Gravity's dominant axis and its sign.
    top_only : bool
        Only the top layer (see :func:`_visible`).
    now : float
        Simulated time [s] stamped on newly seen cells.
    origin_mm : (3,) float
        Centre of cell (0, 0, 0) [mm].
    spacing_mm : float
        Cell edge [mm].
    jitter : float
        Largest offset from a cell centre per axis [cell edges].
    """
    up = -dsgn
    up_dd = 2 * dom + (1 if up > 0 else 0)
    # one pass: room for every cell of the bricks holding dust (memory that
    # is only reserved, not touched, but for the sprites written)
    cap = sum(int(np.count_nonzero(g.alive[:int(g._ctr[C_HW])]
                                   & (g.bmass[:int(g._ctr[C_HW])] != 0)))
              for g in species) * BRICK_VOXELS
    pos = np.empty((cap, 3), dtype=np.float32)
    val = np.empty(cap, dtype=np.float32)
    age = np.empty(cap, dtype=np.float32)
    wet = np.empty(cap, dtype=np.uint8)
    start = 0
    for salt, g in enumerate(species):
        end = _gather(g.alive, g.bmass, int(g._ctr[C_HW]), g.density_q, thr_q, g.bcoord, g.nbr,
                      g._seen, g._seen_key, now, dom, up, up_dd, top_only, cover_q, origin_mm,
                      spacing_mm, jitter, salt, pos, val, age, start)
        wet[start:end] = salt
        start = end
    return DustSprites(pos[:start].copy(), val[:start].copy(), spacing_mm, age[:start].copy(),
                       wet[:start].copy())
