"""The brick hash table and the sphere-over-voxels walk shared by the bone
grid (:mod:`bonesim.engine.grid`) and the dust grid (:mod:`bonesim.physics.dust`).

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
Voxel ``(i, j, k)`` has its centre at ``origin + h * (i, j, k)`` [mm]. A
kernel that visits the voxels whose centres lie within a radius ``r`` of a
point ``c`` takes, per axis, the range :func:`sphere_voxel_range` (which
holds every such voxel), walks the bricks that range touches, and in each
brick the voxels of :func:`brick_voxel_span`; the distance test (inclusive
or strict, as its rule says) is its own. All helpers are inlined into the
caller (``inline="always"``), so a hot loop pays no call.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["BRICK", "BRICK_SHIFT", "BRICK_MASK", "BRICK_VOXELS", "EMPTY_KEY",
           "pack_brick_key", "find_brick", "table_insert", "table_remove",
           "sphere_voxel_range", "brick_voxel_span"]

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
