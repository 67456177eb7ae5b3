"""From-scratch tessellation kernels of the hybrid surface: per brick, count,
place the vertices and emit the triangles (:meth:`bonesim.engine.surface.Surface.build`),
on bit rows of occupancy (below)."""
from __future__ import annotations


import numpy as np
from numba import njit, prange

from bonesim.engine.grid import (BRICK, BRICK_MASK, BRICK_SHIFT, BRICK_VOXELS)
from bonesim.engine.surface_tables import (QUAL_KEY, QUAL_N, QUAL_NMIN, TRIPLE_CORNERS, TRIPLE_FACE,
                                           TR_KEY, flip_of)

__all__ = []

# ----------------------------------------------------------------------------
# Full tessellation, per brick
# ----------------------------------------------------------------------------
# Occupancy is read as bits. ``occupancy_bits`` packs each brick's 512
# voxels into 8 int64 words (word x holds the brick's (y, z) plane x, bit
# 8 y + z). A brick and its one-voxel halo are then ``rows[lx, ly]``
# (``(10, 10)`` int64, bit ``lz``; local ``l = brick coordinate + 1``),
# gathered with three word reads per row. From the rows, with shifts and
# ANDs: the surface voxels (occupied, not all 26 neighbours occupied), the
# code of a cell (its 8 corners: 2 bits of each of 4 rows), the ownership
# tests (the 4 voxels below a cell's minimum face) and the cells that can
# own a triangle (neither all empty nor all occupied). Vertices and
# triangles come out in the order of the definition's loops, brick by brick
# and (x, y, z) within a brick, whatever the number of threads.
CHUNK = 32            # bricks per parallel work item
#: Work items a thread takes at a time in the build's parallel loops
#: (``numba.parallel_chunksize``; dynamic scheduling).
PARALLEL_CHUNKSIZE = 4
_L = BRICK + 2         # local box: brick plus a one-voxel halo on each side
_FULL_ROW = (1 << _L) - 1
_INNER = ((1 << BRICK) - 1) << 1   # local bits 1..8: the brick's own voxels
#: Number of set bits of each byte.
_POP8 = np.array([bin(v).count("1") for v in range(256)], dtype=np.int64)


@njit(cache=True, nogil=True, parallel=True)
def occupancy_bits(density, om):
    """``om[b, x]``: bit ``8 y + z`` set where voxel ``(x, y, z)`` of brick
    ``b`` has density > 0 (``om``: (n_bricks, 8) int64)."""
    for b in prange(density.shape[0]):
        for w in range(BRICK):
            acc = 0
            for u in range(64):
                if density[b, w * 64 + u] > 0:
                    acc |= 1 << u
            om[b, w] = acc


@njit(cache=True, nogil=True)
def _gather_rows(om, nbr, b, rows):
    """Occupancy bit rows of brick ``b`` plus a one-voxel halo into ``rows``
    (``(10, 10)`` int64, see above). Returns ``(anything occupied in the
    brick and its upper halo, the whole box occupied)``."""
    up = 0
    full = _FULL_ROW
    for lx in range(_L):
        x = lx - 1
        sx = ((x >> BRICK_SHIFT) + 1) * 9
        wx = x & BRICK_MASK
        for ly in range(_L):
            y = ly - 1
            sy = sx + ((y >> BRICK_SHIFT) + 1) * 3
            sh = (y & BRICK_MASK) << 3
            r = 0
            nb = nbr[b, sy]
            if nb >= 0:
                r = (om[nb, wx] >> (sh + 7)) & 1
            nb = nbr[b, sy + 1]
            if nb >= 0:
                r |= ((om[nb, wx] >> sh) & 0xFF) << 1
            nb = nbr[b, sy + 2]
            if nb >= 0:
                r |= ((om[nb, wx] >> sh) & 1) << 9
            rows[lx, ly] = r
            full &= r
            if lx > 0 and ly > 0:
                up |= r
    return (up & ~1) != 0, full == _FULL_ROW


@njit(cache=True, nogil=True)
def _surface_rows(rows, ez, srf):
    """``srf[x, y]``: bit z set where brick voxel ``(x, y, z)`` is a surface
    voxel (occupied, with an empty voxel among its 26 neighbours). Returns
    their number."""
    for lx in range(_L):
        for ly in range(_L):
            r = rows[lx, ly]
            ez[lx, ly] = r & (r >> 1) & (r << 1)
    n = 0
    for x in range(BRICK):
        for y in range(BRICK):
            e = _FULL_ROW
            for dx in range(3):
                for dy in range(3):
                    e &= ez[x + dx, y + dy]
            s = ((rows[x + 1, y + 1] & ~e) >> 1) & 0xFF
            srf[x, y] = s
            n += _POP8[s]
    return n


@njit(cache=True, nogil=True, inline="always")
def _cell_code(r00, r01, r10, r11, z):
    """Code of the cell whose corners' rows are ``r{dx}{dy}``, at local z."""
    return (((r00 >> z) & 3) | (((r01 >> z) & 3) << 2) | (((r10 >> z) & 3) << 4)
            | (((r11 >> z) & 3) << 6))


@njit(cache=True, nogil=True, inline="always")
def _mixed(r00, r01, r10, r11):
    """Bits z (1..8) of the cells at local (x, y, z) with corners both
    occupied and empty (the only ones that can own a triangle)."""
    a = r00 | r01 | r10 | r11
    al = r00 & r01 & r10 & r11
    return (a | (a >> 1)) & ~(al & (al >> 1)) & _INNER


@njit(cache=True, nogil=True)
def _owned_total(rows):
    """Triangles the cells of the brick own."""
    ct = 0
    for x in range(1, _L - 1):
        for y in range(1, _L - 1):
            r00 = rows[x, y]
            r01 = rows[x, y + 1]
            r10 = rows[x + 1, y]
            r11 = rows[x + 1, y + 1]
            m = _mixed(r00, r01, r10, r11)
            if m == 0:
                continue
            bx = rows[x - 1, y] | rows[x - 1, y + 1]
            by = rows[x, y - 1] | rows[x + 1, y - 1]
            bz = r00 | r01 | r10 | r11
            for z in range(1, _L - 1):
                if not (m >> z) & 1:
                    continue
                code = _cell_code(r00, r01, r10, r11, z)
                n = QUAL_N[code]
                if n > 0:
                    if (bx >> z) & 3 == 0:
                        n -= QUAL_NMIN[code, 0]
                    if (by >> z) & 3 == 0:
                        n -= QUAL_NMIN[code, 1]
                    if (bz >> (z - 1)) & 1 == 0:
                        n -= QUAL_NMIN[code, 2]
                    ct += n
    return ct


@njit(cache=True, nogil=True, parallel=True)
def build_count(om, nbr, nv, nt):
    """Vertices ``nv[b]`` and owned triangles ``nt[b]`` of every brick."""
    nb_tot = nbr.shape[0]
    n_chunks = (nb_tot + CHUNK - 1) // CHUNK
    for ch in prange(n_chunks):
        rows = np.empty((_L, _L), dtype=np.int64)
        ez = np.empty((_L, _L), dtype=np.int64)
        srf = np.empty((BRICK, BRICK), dtype=np.int64)
        for b in range(ch * CHUNK, min(nb_tot, (ch + 1) * CHUNK)):
            up, full = _gather_rows(om, nbr, b, rows)
            if not up or full:
                nv[b] = 0
                nt[b] = 0
                continue
            nv[b] = _surface_rows(rows, ez, srf)
            nt[b] = _owned_total(rows)


@njit(cache=True, nogil=True, parallel=True)
def build_vertices(om, nbr, bricks, origin, spacing, voff, vmap, pos, vijk):
    """Vertex slots ``voff[b]...`` of brick ``b``'s surface voxels in
    (x, y, z) order: ``vmap``, voxel and voxel-centre position."""
    nb_tot = nbr.shape[0]
    n_chunks = (nb_tot + CHUNK - 1) // CHUNK
    for ch in prange(n_chunks):
        rows = np.empty((_L, _L), dtype=np.int64)
        ez = np.empty((_L, _L), dtype=np.int64)
        srf = np.empty((BRICK, BRICK), dtype=np.int64)
        for b in range(ch * CHUNK, min(nb_tot, (ch + 1) * CHUNK)):
            for o in range(BRICK_VOXELS):
                vmap[b, o] = -1
            if voff[b + 1] == voff[b]:
                continue
            _gather_rows(om, nbr, b, rows)
            _surface_rows(rows, ez, srf)
            v = voff[b]
            bi = bricks[b, 0] << BRICK_SHIFT
            bj = bricks[b, 1] << BRICK_SHIFT
            bk = bricks[b, 2] << BRICK_SHIFT
            for x in range(BRICK):
                for y in range(BRICK):
                    s = srf[x, y]
                    if s == 0:
                        continue
                    for z in range(BRICK):
                        if not (s >> z) & 1:
                            continue
                        i = bi + x
                        j = bj + y
                        k = bk + z
                        vmap[b, (x << 6) | (y << 3) | z] = v
                        vijk[v, 0] = i
                        vijk[v, 1] = j
                        vijk[v, 2] = k
                        pos[v, 0] = origin[0] + spacing * i
                        pos[v, 1] = origin[1] + spacing * j
                        pos[v, 2] = origin[2] + spacing * k
                        v += 1


@njit(cache=True, nogil=True, parallel=True)
def build_triangles(om, nbr, toff, vmap, pos, nrm, trec, tflip, err):
    """Triangle records ``toff[b]...`` of the triangles brick ``b``'s cells
    own, in (x, y, z, qualifying-triple) order (corners and key; the list
    links are :func:`bonesim.engine.surface_tables.link_all`'s), and their
    drawn winding ``tflip`` from the shaded ``pos``
    and ``nrm`` (:func:`bonesim.engine.surface_tables.flip_of`);
    ``err[chunk]`` counts corners without a vertex."""
    nb_tot = nbr.shape[0]
    n_chunks = (nb_tot + CHUNK - 1) // CHUNK
    for ch in prange(n_chunks):
        rows = np.empty((_L, _L), dtype=np.int64)
        for b in range(ch * CHUNK, min(nb_tot, (ch + 1) * CHUNK)):
            if toff[b + 1] == toff[b]:
                continue
            _gather_rows(om, nbr, b, rows)
            t = toff[b]
            for x in range(1, _L - 1):
                for y in range(1, _L - 1):
                    r00 = rows[x, y]
                    r01 = rows[x, y + 1]
                    r10 = rows[x + 1, y]
                    r11 = rows[x + 1, y + 1]
                    m = _mixed(r00, r01, r10, r11)
                    if m == 0:
                        continue
                    bx = rows[x - 1, y] | rows[x - 1, y + 1]
                    by = rows[x, y - 1] | rows[x + 1, y - 1]
                    bz = r00 | r01 | r10 | r11
                    for z in range(1, _L - 1):
                        if not (m >> z) & 1:
                            continue
                        code = _cell_code(r00, r01, r10, r11, z)
                        n = QUAL_N[code]
                        if n == 0:
                            continue
                        low0 = (bx >> z) & 3 == 0
                        low1 = (by >> z) & 3 == 0
                        low2 = (bz >> (z - 1)) & 1 == 0
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
                            trec[t, TR_KEY] = key      # the list links: link_all
                            if trec[t, 0] >= 0 and trec[t, 1] >= 0 and trec[t, 2] >= 0:
                                tflip[t] = 1 if flip_of(trec, t, pos, nrm) else 0
                            t += 1
