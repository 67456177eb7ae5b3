"""From-scratch tessellation kernels of the hybrid surface: per brick, count,
place the vertices and emit the triangles (:meth:`bonesim.engine.surface.Surface.build`)."""
from __future__ import annotations


import numpy as np
from numba import njit, prange

from bonesim.engine.grid import (BRICK, BRICK_MASK, BRICK_SHIFT, BRICK_VOXELS)
from bonesim.engine.surface_tables import (QUAL_KEY, QUAL_N, QUAL_NMIN, TRIPLE_CORNERS, TRIPLE_FACE,
                                           LOW_HALF_X, LOW_HALF_Y, LOW_HALF_Z, TR_KEY)

__all__ = []

# ----------------------------------------------------------------------------
# Full tessellation, per brick
# ----------------------------------------------------------------------------
CHUNK = 32            # bricks per parallel work item
_L = BRICK + 2         # local box: brick plus a one-voxel halo on each side


@njit(cache=True, nogil=True)
def _gather_local(density, nbr, b, loc):
    """Copy the densities of brick ``b`` plus a one-voxel halo into ``loc``
    (``(10, 10, 10)``; ``loc[x + 1, y + 1, z + 1]`` is voxel ``(x, y, z)`` of
    the brick). Returns ``(occupied in the brick and its upper halo,
    occupied in the whole box)``."""
    n_up = 0
    n_all = 0
    for lx in range(_L):
        x = lx - 1
        sx = ((x >> BRICK_SHIFT) + 1) * 9
        ox = (x & BRICK_MASK) << 6
        for ly in range(_L):
            y = ly - 1
            sy = sx + ((y >> BRICK_SHIFT) + 1) * 3
            oy = ox | ((y & BRICK_MASK) << 3)
            for lz in range(_L):
                z = lz - 1
                nb = nbr[b, sy + (z >> BRICK_SHIFT) + 1]
                if nb >= 0:
                    d = density[nb, oy | (z & BRICK_MASK)]
                else:
                    d = np.float32(0.0)
                loc[lx, ly, lz] = d
                if d > 0:
                    n_all += 1
                    if lx > 0 and ly > 0 and lz > 0:
                        n_up += 1
    return n_up, n_all


@njit(cache=True, nogil=True)
def _local_codes(loc, codes):
    """Occupancy code of each cell with minimum corner at local (0..8)^3."""
    for x in range(_L - 1):
        for y in range(_L - 1):
            for z in range(_L - 1):
                c = 0
                for cn in range(8):
                    if loc[x + (cn >> 2), y + ((cn >> 1) & 1), z + (cn & 1)] > 0:
                        c |= 1 << cn
                codes[x, y, z] = c


@njit(cache=True, nogil=True, inline="always")
def _is_surface_local(loc, x, y, z):
    if not loc[x, y, z] > 0:
        return False
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-1, 2):
                if not loc[x + a, y + b, z + c] > 0:
                    return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _owned_count(codes, x, y, z):
    code = codes[x, y, z]
    n = QUAL_N[code]
    if n > 0:
        if codes[x - 1, y, z] & LOW_HALF_X == 0:
            n -= QUAL_NMIN[code, 0]
        if codes[x, y - 1, z] & LOW_HALF_Y == 0:
            n -= QUAL_NMIN[code, 1]
        if codes[x, y, z - 1] & LOW_HALF_Z == 0:
            n -= QUAL_NMIN[code, 2]
    return n


@njit(cache=True, nogil=True, parallel=True)
def build_count(density, nbr, nv, nt):
    nb_tot = nbr.shape[0]
    n_chunks = (nb_tot + CHUNK - 1) // CHUNK
    for ch in prange(n_chunks):
        loc = np.empty((_L, _L, _L), dtype=np.float32)
        codes = np.empty((_L - 1, _L - 1, _L - 1), dtype=np.int64)
        for b in range(ch * CHUNK, min(nb_tot, (ch + 1) * CHUNK)):
            n_up, n_all = _gather_local(density, nbr, b, loc)
            if n_up == 0 or n_all == _L * _L * _L:
                nv[b] = 0
                nt[b] = 0
                continue
            cv = 0
            for x in range(1, _L - 1):
                for y in range(1, _L - 1):
                    for z in range(1, _L - 1):
                        if _is_surface_local(loc, x, y, z):
                            cv += 1
            _local_codes(loc, codes)
            ct = 0
            for x in range(1, _L - 1):
                for y in range(1, _L - 1):
                    for z in range(1, _L - 1):
                        ct += _owned_count(codes, x, y, z)
            nv[b] = cv
            nt[b] = ct


@njit(cache=True, nogil=True, parallel=True)
def build_vertices(density, nbr, bricks, origin, spacing, voff, vmap, pos, vijk):
    nb_tot = nbr.shape[0]
    n_chunks = (nb_tot + CHUNK - 1) // CHUNK
    for ch in prange(n_chunks):
        loc = np.empty((_L, _L, _L), dtype=np.float32)
        for b in range(ch * CHUNK, min(nb_tot, (ch + 1) * CHUNK)):
            for o in range(BRICK_VOXELS):
                vmap[b, o] = -1
            if voff[b + 1] == voff[b]:
                continue
            _gather_local(density, nbr, b, loc)
            v = voff[b]
            bi = bricks[b, 0] << BRICK_SHIFT
            bj = bricks[b, 1] << BRICK_SHIFT
            bk = bricks[b, 2] << BRICK_SHIFT
            for x in range(1, _L - 1):
                for y in range(1, _L - 1):
                    for z in range(1, _L - 1):
                        if not _is_surface_local(loc, x, y, z):
                            continue
                        o = ((x - 1) << 6) | ((y - 1) << 3) | (z - 1)
                        i = bi + x - 1
                        j = bj + y - 1
                        k = bk + z - 1
                        vmap[b, o] = v
                        vijk[v, 0] = i
                        vijk[v, 1] = j
                        vijk[v, 2] = k
                        pos[v, 0] = origin[0] + spacing * i
                        pos[v, 1] = origin[1] + spacing * j
                        pos[v, 2] = origin[2] + spacing * k
                        v += 1


@njit(cache=True, nogil=True, parallel=True)
def build_triangles(density, nbr, toff, vmap, trec, err):
    nb_tot = nbr.shape[0]
    n_chunks = (nb_tot + CHUNK - 1) // CHUNK
    for ch in prange(n_chunks):
        loc = np.empty((_L, _L, _L), dtype=np.float32)
        codes = np.empty((_L - 1, _L - 1, _L - 1), dtype=np.int64)
        for b in range(ch * CHUNK, min(nb_tot, (ch + 1) * CHUNK)):
            if toff[b + 1] == toff[b]:
                continue
            _gather_local(density, nbr, b, loc)
            _local_codes(loc, codes)
            t = toff[b]
            for x in range(1, _L - 1):
                for y in range(1, _L - 1):
                    for z in range(1, _L - 1):
                        code = codes[x, y, z]
                        n = QUAL_N[code]
                        if n == 0:
                            continue
                        low0 = codes[x - 1, y, z] & LOW_HALF_X == 0
                        low1 = codes[x, y - 1, z] & LOW_HALF_Y == 0
                        low2 = codes[x, y, z - 1] & LOW_HALF_Z == 0
                        for q in range(n):
                            key = QUAL_KEY[code, q]
                            tid = key >> 1
                            f = TRIPLE_FACE[tid]
                            if (f == 0 and low0) or (f == 1 and low1) or (f == 2 and low2):
                                continue
                            for s in range(3):
                                cs = s
                                if key & 1 and s > 0:
                                    cs = 3 - s
                                cn = TRIPLE_CORNERS[tid, cs]
                                # brick-relative coordinates of the corner (0..8)
                                rx = x - 1 + (cn >> 2)
                                ry = y - 1 + ((cn >> 1) & 1)
                                rz = z - 1 + (cn & 1)
                                nb = nbr[b, ((rx >> BRICK_SHIFT) + 1) * 9
                                         + ((ry >> BRICK_SHIFT) + 1) * 3
                                         + (rz >> BRICK_SHIFT) + 1]
                                v = -1
                                if nb >= 0:
                                    v = vmap[nb, ((rx & BRICK_MASK) << 6)
                                             | ((ry & BRICK_MASK) << 3) | (rz & BRICK_MASK)]
                                if v < 0:
                                    err[ch] += 1
                                trec[t, s] = v
                            trec[t, TR_KEY] = key
                            t += 1
