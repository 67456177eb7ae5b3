"""Brick pool and hash table of :class:`bonesim.physics.dust.DustGrid` (numba kernels).

Dust cells are grouped in bricks of ``8**3`` like :mod:`bonesim.engine.grid` (same
``pack_brick_key`` / ``voxel_offset`` layout), found through the same
open-addressing table (:mod:`bonesim.engine.brick_hash`), which here grows at run
time and also loses bricks; each brick keeps the indices of
its six face neighbours. This module holds the fixed-point constants, the
layout of the counter and parameter arrays shared by every dust kernel, and
the kernels that insert, link and recycle bricks. See :mod:`bonesim.physics.dust.grid`
for the model.
"""
from __future__ import annotations

from numba import njit

from bonesim.engine.brick_hash import (BRICK, BRICK_SHIFT, BRICK_VOXELS, find_brick, pack_brick_key,
                                       table_insert, table_remove)

__all__ = ["Q_SHIFT", "Q", "FULL", "MAX_SPILL_FRACTION", "C_NFREE", "C_HW", "C_CUR",
           "C_ADDED", "C_SUCKED", "C_NEED", "C_NALIVE", "C_PUSHED", "C_SUCKED_STEP",
           "C_WETTED", "I_RATE", "I_KQ", "I_REPOSE", "I_NG", "I_DOM", "I_DSGN",
           "I_LAT0", "I_LAT1", "I_SEARCH", "I_SRATE", "I_TOOL", "I_SUCTION", "I_GAX",
           "I_GSG", "I_GWQ", "I_WRATE", "F_TX", "F_TY", "F_TZ", "F_TR", "F_SX", "F_SY",
           "F_SZ", "F_SR", "F_OX", "F_OY", "F_OZ", "F_H", "F_UX", "F_UY", "F_UZ",
           "F_WX", "F_WY", "F_WZ", "F_WR", "STAGE_GRAVITY", "STAGE_SPILL", "STAGE_TOOL",
           "STAGE_SUCTION", "STAGE_DONE"]

#: Fixed-point units per full cell of dust.
Q_SHIFT = 20
Q = 1 << Q_SHIFT
#: A full cell [cells].
FULL = 1.0
FULL_Q = Q
#: Fixed-point shift of the rule weights (gravity shares, spill fraction).
W_SHIFT = 16
W_ONE = 1 << W_SHIFT
#: A fifth in fixed point (rounded down): the share of a cell's room that
#: each of its (at most five) spill sources may fill.
ROOM_SHARE = W_ONE // 5
#: Largest spill fraction per step (explicit-diffusion stability bound 1/5).
MAX_SPILL_FRACTION = 0.2
#: Largest fixed-point rate per step, to keep products inside int64.
MAX_RATE_Q = 1 << 40
#: Gravity components smaller than this do not move dust.
MIN_GRAVITY_COMPONENT = 1e-6

# counters (int64 array ``ctr``)
(C_NFREE, C_HW, C_CUR, C_ADDED, C_SUCKED, C_NEED, C_NALIVE, C_PUSHED,
 C_SUCKED_STEP, C_WETTED) = range(10)
N_CTR = 10
# integer step parameters (int64 array ``ip``)
(I_RATE, I_KQ, I_REPOSE, I_NG, I_DOM, I_DSGN, I_LAT0, I_LAT1, I_SEARCH,
 I_SRATE, I_TOOL, I_SUCTION, I_GAX, I_GSG, I_GWQ) = (0, 1, 2, 3, 4, 5, 6, 7, 8,
                                                      9, 10, 11, 12, 15, 18)
I_WRATE = 21
N_IP = 22
# float step parameters (float64 array ``fp``)
(F_TX, F_TY, F_TZ, F_TR, F_SX, F_SY, F_SZ, F_SR, F_OX, F_OY, F_OZ, F_H,
 F_UX, F_UY, F_UZ, F_WX, F_WY, F_WZ, F_WR) = range(19)
N_FP = 19
# step stages (a kernel that runs out of bricks returns the stage to resume)
STAGE_GRAVITY, STAGE_SPILL, STAGE_TOOL, STAGE_SUCTION, STAGE_DONE = range(5)


# ====================================================================== table
@njit(cache=True, nogil=True)
def rehash_bricks(keys, vals, bcoord, alive, hw):
    for b in range(hw):
        if alive[b]:
            table_insert(keys, vals,
                          pack_brick_key(bcoord[b, 0], bcoord[b, 1], bcoord[b, 2]), b)


@njit(cache=True, nogil=True, inline="always")
def brick_in_domain(bi, bj, bk, bounds):
    return ((bi << BRICK_SHIFT) < bounds[3] and (bi << BRICK_SHIFT) + BRICK > bounds[0]
            and (bj << BRICK_SHIFT) < bounds[4] and (bj << BRICK_SHIFT) + BRICK > bounds[1]
            and (bk << BRICK_SHIFT) < bounds[5] and (bk << BRICK_SHIFT) + BRICK > bounds[2])


@njit(cache=True, nogil=True)
def insert_brick(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                  bkeys, bvals, bi, bj, bk):
    """Take a brick from the pool for ``(bi, bj, bk)`` (absent; pool not empty),
    zero it in both buffers, link its face neighbours and its bone brick."""
    n = ctr[C_NFREE] - 1
    b = free[n]
    ctr[C_NFREE] = n
    if b + 1 > ctr[C_HW]:
        ctr[C_HW] = b + 1
    ctr[C_NALIVE] += 1
    table_insert(keys, vals, pack_brick_key(bi, bj, bk), b)
    bcoord[b, 0] = bi
    bcoord[b, 1] = bj
    bcoord[b, 2] = bk
    alive[b] = 1
    bmass[b] = 0
    for o in range(BRICK_VOXELS):
        dens[0, b, o] = 0
        dens[1, b, o] = 0
    for d in range(6):
        a = d >> 1
        s = 1 if d & 1 else -1
        ni = bi + s if a == 0 else bi
        nj = bj + s if a == 1 else bj
        nk = bk + s if a == 2 else bk
        m = find_brick(keys, vals, ni, nj, nk)
        nbr[b, d] = m
        if m >= 0:
            nbr[m, d ^ 1] = b
    bone_b[b] = find_brick(bkeys, bvals, bi, bj, bk)
    return b


@njit(cache=True, nogil=True)
def ensure_bricks(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                   bkeys, bvals, coords):
    """Allocate the bricks ``coords`` (n, 3) that are missing.

    Returns 0, or (allocating nothing) an upper bound on the bricks needed
    when the pool holds fewer."""
    need = 0
    for q in range(coords.shape[0]):
        if find_brick(keys, vals, coords[q, 0], coords[q, 1], coords[q, 2]) < 0:
            need += 1
    if need > ctr[C_NFREE]:
        return need
    for q in range(coords.shape[0]):
        if find_brick(keys, vals, coords[q, 0], coords[q, 1], coords[q, 2]) < 0:
            insert_brick(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                          bkeys, bvals, coords[q, 0], coords[q, 1], coords[q, 2])
    return 0


@njit(cache=True, nogil=True)
def recycle_bricks(keys, vals, bcoord, nbr, alive, bmass, free, ctr):
    """Return dead bricks (no dust, no face neighbour with dust) to the pool."""
    hw = ctr[C_HW]
    freed = 0
    for b in range(hw):
        if not alive[b] or bmass[b] != 0:
            continue
        keep = False
        for d in range(6):
            m = nbr[b, d]
            if m >= 0 and bmass[m] != 0:
                keep = True
        if keep:
            continue
        table_remove(keys, vals, pack_brick_key(bcoord[b, 0], bcoord[b, 1], bcoord[b, 2]))
        for d in range(6):
            m = nbr[b, d]
            if m >= 0:
                nbr[m, d ^ 1] = -1
            nbr[b, d] = -1
        alive[b] = 0
        free[ctr[C_NFREE]] = b
        ctr[C_NFREE] += 1
        ctr[C_NALIVE] -= 1
        freed += 1
    return freed


@njit(cache=True, nogil=True)
def refresh_bone_bricks(bcoord, alive, hw, bkeys, bvals, bone_b):
    for b in range(hw):
        if alive[b]:
            bone_b[b] = find_brick(bkeys, bvals, bcoord[b, 0], bcoord[b, 1], bcoord[b, 2])
