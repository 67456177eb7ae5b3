"""The brick hash table and the sphere-over-voxels walk shared by the bone
grid (:mod:`bonesim.engine.grid`) and the dust grid (:mod:`bonesim.physics.dust.grid`).

Hash table
----------
Bricks of ``BRICK**3 = 8**3`` voxels are found through an open-addressing
table with linear probing and a power-of-two capacity: ``keys`` (int64,
:data:`EMPTY_KEY` for an empty slot) holds the packed brick coordinate
(:func:`pack_brick_key`), ``vals`` (int32) the brick's index in the brick
arrays. :func:`find_brick` looks a brick up, :func:`table_insert` adds one
and :func:`table_remove` deletes one by backward-shift deletion (no
tombstones, so lookups stay as short as after a fresh build). The bone grid
inserts once, at build time; the dust grid inserts and removes as dust
moves.

Sphere over voxels
------------------
Voxel ``(i, j, k)`` has its centre at ``origin + h * (i, j, k)`` [mm].
:func:`sphere_cells` lists, into a caller's scratch, the voxels of the
occupied bricks whose centres lie within a radius ``r`` of a point ``c``
(``|x - c| <= r`` inclusive, or ``< r`` strict, as the caller's rule says),
in one fixed order: bricks by ``(bi, bj, bk)``, voxels by ``(x, y, z)``
inside each. Every rule that works on a sphere of cells (the dust's tool
push, suction and wetting) walks that list, so there is one walk. Its bounds
come from :func:`sphere_voxel_range` (per axis, a range that holds every
such voxel) and :func:`brick_voxel_span`; :func:`sphere_cells_bound` is the
scratch a radius needs.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["BRICK", "BRICK_SHIFT", "BRICK_MASK", "BRICK_VOXELS", "EMPTY_KEY",
           "pack_brick_key", "unpack_brick_keys", "find_brick", "table_insert", "table_remove",
           "sphere_voxel_range", "brick_voxel_span", "sphere_cells", "sphere_cells_bound",
           "SC_BRICK", "SC_OFF", "SC_I", "SC_J", "SC_K", "SC_WIDTH"]

#: Columns of a :func:`sphere_cells` row: brick index, voxel offset in the
#: brick, voxel coordinates ``i, j, k``.
SC_BRICK, SC_OFF, SC_I, SC_J, SC_K = range(5)
SC_WIDTH = 5

BRICK = 8
BRICK_SHIFT = 3
BRICK_MASK = 7
BRICK_VOXELS = BRICK ** 3
_KEY_OFFSET = 1 << 20          # brick coordinates in [-2**20, 2**20)
_KEY_BITS = 21
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)
_HASH_SHIFT = np.uint64(32)
EMPTY_KEY = np.int64(-1)


@njit(cache=True, nogil=True, inline="always")
def pack_brick_key(bi, bj, bk):
    """Pack a brick coordinate into one non-negative int64."""
    return ((np.int64(bi) + _KEY_OFFSET) << (2 * _KEY_BITS)) | \
           ((np.int64(bj) + _KEY_OFFSET) << _KEY_BITS) | (np.int64(bk) + _KEY_OFFSET)


def unpack_brick_keys(keys) -> np.ndarray:
    """Brick coordinates (n, 3) int64 of the packed keys ``keys`` (n,)
    (:func:`pack_brick_key`'s inverse; give only occupied slots)."""
    keys = np.asarray(keys, dtype=np.int64).reshape(-1)
    low = (1 << _KEY_BITS) - 1
    return np.stack([(keys >> (2 * _KEY_BITS)) - _KEY_OFFSET,
                     ((keys >> _KEY_BITS) & low) - _KEY_OFFSET,
                     (keys & low) - _KEY_OFFSET], axis=1)


@njit(cache=True, nogil=True, inline="always")
def _hash_slot(key, mask):
    """Home slot of ``key`` in a table of ``mask + 1`` slots (Fibonacci hashing)."""
    h = np.uint64(key) * _HASH_MULT
    return np.int64((h >> _HASH_SHIFT) & np.uint64(mask))


@njit(cache=True, nogil=True)
def find_brick(keys, vals, bi, bj, bk):
    """Index of brick ``(bi, bj, bk)`` in the brick arrays, or -1 if absent.

    Parameters
    ----------
    keys : (capacity,) int64
        Hash table keys (``-1`` marks an empty slot).
    vals : (capacity,) int32
        Brick index stored with each key.
    bi, bj, bk : int
        Brick coordinates (voxel coordinates shifted right by 3).
    """
    key = pack_brick_key(bi, bj, bk)
    mask = keys.shape[0] - 1
    s = _hash_slot(key, mask)
    while True:
        k = keys[s]
        if k == key:
            return vals[s]
        if k == -1:
            return -1
        s = (s + 1) & mask


@njit(cache=True, nogil=True)
def table_insert(keys, vals, key, b):
    """Insert packed ``key`` (absent; the table has a free slot) with brick index ``b``."""
    mask = keys.shape[0] - 1
    s = _hash_slot(key, mask)
    while keys[s] != -1:
        s = (s + 1) & mask
    keys[s] = key
    vals[s] = b


@njit(cache=True, nogil=True)
def table_remove(keys, vals, key):
    """Delete packed ``key`` (which must be present) by backward-shift deletion."""
    mask = keys.shape[0] - 1
    s = _hash_slot(key, mask)
    while keys[s] != key:
        s = (s + 1) & mask
    j = s
    while True:
        j = (j + 1) & mask
        kj = keys[j]
        if kj == -1:
            break
        h = _hash_slot(kj, mask)
        # keep keys[j] where it is if its home slot lies cyclically in (s, j]
        if s <= j:
            stay = s < h <= j
        else:
            stay = h > s or h <= j
        if not stay:
            keys[s] = kj
            vals[s] = vals[j]
            s = j
    keys[s] = -1
    vals[s] = -1


@njit(cache=True, nogil=True, inline="always")
def sphere_voxel_range(c, r, o, h):
    """Voxels ``[lo, hi)`` along one axis whose centres may lie within ``r``
    [mm] of ``c`` [mm] (origin ``o`` [mm], spacing ``h`` [mm]); one voxel of
    slack on each side, so rounding never drops a voxel."""
    return (int(math.floor((c - r - o) / h)) - 1, int(math.floor((c + r - o) / h)) + 2)


@njit(cache=True, nogil=True, inline="always")
def brick_voxel_span(lo, hi, bc):
    """Local voxels ``[x0, x1)`` of brick coordinate ``bc`` (along one axis)
    that lie in the voxel range ``[lo, hi)``; empty when ``x1 <= x0``."""
    first = bc << BRICK_SHIFT
    return max(lo - first, 0), min(hi - first, BRICK)


def sphere_cells_bound(radius_mm: float, spacing_mm: float) -> int:
    """Rows of scratch :func:`sphere_cells` may fill for a sphere of
    ``radius_mm`` [mm] on voxels of ``spacing_mm`` [mm] (the voxels of the
    ranges :func:`sphere_voxel_range` gives, whatever the centre)."""
    n = int(math.floor(2.0 * float(radius_mm) / float(spacing_mm))) + 4
    return n * n * n


@njit(cache=True, nogil=True)
def sphere_cells(keys, vals, occupied, cx, cy, cz, rad, ox, oy, oz, h, inclusive, out):
    """List the voxels of a sphere (see the module docstring).

    Parameters
    ----------
    keys, vals : hash table of the bricks
    occupied : (n_bricks,) int array
        Bricks whose entry is 0 are skipped (e.g. the dust's brick masses).
    cx, cy, cz, rad : float
        Centre and radius [mm].
    ox, oy, oz, h : float
        Centre of voxel (0, 0, 0) and voxel edge [mm].
    inclusive : bool
        Voxels at exactly ``rad`` count (``<=``) or not (``<``).
    out : (m, SC_WIDTH) int64
        Rows ``(brick, offset, i, j, k)``; ``m`` at least
        :func:`sphere_cells_bound` of ``rad``.

    Returns
    -------
    int
        Rows written (brick by brick, in the module docstring's order).
    """
    r2 = rad * rad
    i0, i1 = sphere_voxel_range(cx, rad, ox, h)
    j0, j1 = sphere_voxel_range(cy, rad, oy, h)
    k0, k1 = sphere_voxel_range(cz, rad, oz, h)
    if (i1 - i0) * (j1 - j0) * (k1 - k0) > out.shape[0]:
        raise ValueError("sphere_cells: scratch smaller than sphere_cells_bound")
    n = 0
    for bi in range(i0 >> BRICK_SHIFT, ((i1 - 1) >> BRICK_SHIFT) + 1):
        for bj in range(j0 >> BRICK_SHIFT, ((j1 - 1) >> BRICK_SHIFT) + 1):
            for bk in range(k0 >> BRICK_SHIFT, ((k1 - 1) >> BRICK_SHIFT) + 1):
                b = find_brick(keys, vals, bi, bj, bk)
                if b < 0 or occupied[b] == 0:
                    continue
                x0, x1 = brick_voxel_span(i0, i1, bi)
                y0, y1 = brick_voxel_span(j0, j1, bj)
                z0, z1 = brick_voxel_span(k0, k1, bk)
                for x in range(x0, x1):
                    ci = (bi << BRICK_SHIFT) + x
                    dx = (ox + h * ci) - cx
                    for y in range(y0, y1):
                        cj = (bj << BRICK_SHIFT) + y
                        dy = (oy + h * cj) - cy
                        for z in range(z0, z1):
                            ck = (bk << BRICK_SHIFT) + z
                            dz = (oz + h * ck) - cz
                            d2 = dx * dx + dy * dy + dz * dz
                            if d2 > r2 or (d2 == r2 and not inclusive):
                                continue
                            out[n, 0] = b
                            out[n, 1] = (x << 6) | (y << 3) | z
                            out[n, 2] = ci
                            out[n, 3] = cj
                            out[n, 4] = ck
                            n += 1
    return n
