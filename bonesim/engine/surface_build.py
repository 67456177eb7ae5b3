"""From-scratch tessellation kernels of the hybrid surface: per brick, count,
place the vertices and emit the triangles (:meth:`bonesim.engine.surface.Surface.build`),
on bit rows of occupancy (below)."""
from __future__ import annotations


import numpy as np
from numba import njit, prange
from numba.cpython.unsafe.numbers import trailing_zeros

from bonesim.engine.grid import (BRICK, BRICK_MASK, BRICK_SHIFT, BRICK_VOXELS)
from bonesim.engine.surface_tables import (QUAL_KEY, QUAL_N, TRIPLE_CORNERS, TRIPLE_FACE,
                                           TR_FILL, TR_KEY, TR_WIDTH, flip_of, neighbours_of)
from bonesim.engine.work_items import take_item

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
#: Bricks per work item of the build's parallel kernels (handed out one at
#: a time to the workers, :mod:`bonesim.engine.work_items`).
CHUNK = 32
_L = BRICK + 2         # local box: brick plus a one-voxel halo on each side
_FULL_ROW = (1 << _L) - 1
_INNER = ((1 << BRICK) - 1) << 1   # local bits 1..8: the brick's own voxels
#: Number of set bits of each byte.
_POP8 = np.array([bin(v).count("1") for v in range(256)], dtype=np.int64)


def _owned_tables():
    """What a cell owns, by its code and its *low mask* (bit ``a`` set when
    the four voxels just below its minimum face along ``a`` are empty, so
    that its triples in that face belong to the cell below): the number of
    triangles (``(256, 8)`` int8) and their keys in ``QUAL_KEY`` order
    (``(256, 8, 4)`` int16, -1 after)."""
    n = np.zeros((256, 8), dtype=np.int8)
    keys = np.full((256, 8, QUAL_KEY.shape[1]), -1, dtype=np.int16)
    for code in range(256):
        for low in range(8):
            c = 0
            for q in range(int(QUAL_N[code])):
                key = int(QUAL_KEY[code, q])
                f = int(TRIPLE_FACE[key >> 1])
                if 0 <= f < 3 and (low >> f) & 1:
                    continue
                keys[code, low, c] = key
                c += 1
            n[code, low] = c
    return n, keys


_OWN_N, _OWN_KEY = _owned_tables()


@njit(cache=True, nogil=True, inline="always")
def _occupancy_of(density, b, om):
    """``om[b, :]``: brick ``b``'s row of :func:`occupancy_bits`."""
    for w in range(BRICK):
        acc = 0
        for u in range(64):
            if density[b, w * 64 + u] > 0:
                acc |= 1 << u
        om[b, w] = acc


@njit(cache=True, nogil=True, parallel=True)
def occupancy_bits(density, om):
    """``om[b, x]``: bit ``8 y + z`` set where voxel ``(x, y, z)`` of brick
    ``b`` has density > 0 (``om``: (n_bricks, 8) int64)."""
    for b in prange(density.shape[0]):
        _occupancy_of(density, b, om)


@njit(cache=True, nogil=True, parallel=True)
def build_prepare(keys, vals, bricks, density, nbr, om, counter, n_workers):
    """:func:`bonesim.engine.surface_tables.brick_neighbours` into ``nbr``
    and :func:`occupancy_bits` into ``om``, in one parallel pass (work items
    of ``CHUNK`` bricks taken from ``counter``)."""
    nb_tot = bricks.shape[0]
    n_chunks = (nb_tot + CHUNK - 1) // CHUNK
    for _ in prange(n_workers):
        while True:
            ch = take_item(counter)
            if ch >= n_chunks:
                break
            for b in range(ch * CHUNK, min(nb_tot, (ch + 1) * CHUNK)):
                neighbours_of(keys, vals, bricks, b, nbr)
                _occupancy_of(density, b, om)


@njit(cache=True, nogil=True)
def _gather_rows(om, nbr, b, rows):
    """Occupancy bit rows of brick ``b`` plus a one-voxel halo into ``rows``
    (``(10, 10)`` int64, see above). Returns ``(anything occupied in the
    brick and its upper halo, the whole box occupied)``. The three words a
    row takes bits from (bricks below, at and above along z) are read once
    for the rows of each brick along y (a missing brick reads as 0)."""
    up = 0
    full = _FULL_ROW
    for lx in range(_L):
        x = lx - 1
        sx = ((x >> BRICK_SHIFT) + 1) * 9
        wx = x & BRICK_MASK
        for gy in range(3):                      # the bricks below, at and above along y
            sy = sx + gy * 3
            nb = nbr[b, sy]
            w0 = om[nb, wx] if nb >= 0 else 0
            nb = nbr[b, sy + 1]
            w1 = om[nb, wx] if nb >= 0 else 0
            nb = nbr[b, sy + 2]
            w2 = om[nb, wx] if nb >= 0 else 0
            l0 = 0 if gy == 0 else (1 if gy == 1 else _L - 1)
            l1 = 1 if gy == 0 else (_L - 1 if gy == 1 else _L)
            for ly in range(l0, l1):
                sh = ((ly - 1) & BRICK_MASK) << 3
                r = (((w0 >> (sh + 7)) & 1) | (((w1 >> sh) & 0xFF) << 1)
                     | (((w2 >> sh) & 1) << 9))
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


@njit(cache=True, nogil=True, inline="always")
def _low_mask(bx, by, bz, z):
    """Low mask (see :func:`_owned_tables`) of the cell at local z, from the
    rows below its minimum faces: ``bx`` (the two rows at x - 1), ``by``
    (at y - 1) and ``bz`` (its own four rows, one voxel lower)."""
    return ((1 if (bx >> z) & 3 == 0 else 0) | (2 if (by >> z) & 3 == 0 else 0)
            | (4 if (bz >> (z - 1)) & 1 == 0 else 0))


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
            while m != 0:
                z = np.int64(trailing_zeros(m))
                m &= m - 1
                ct += _OWN_N[_cell_code(r00, r01, r10, r11, z), _low_mask(bx, by, bz, z)]
    return ct


@njit(cache=True, nogil=True)
def _count_chunk(om, nbr, nv, nt, srf_all, ch, rows, ez, srf):
    """:func:`build_count` of work item ``ch`` (scratch ``rows``, ``ez``,
    ``srf``)."""
    nb_tot = nbr.shape[0]
    for b in range(ch * CHUNK, min(nb_tot, (ch + 1) * CHUNK)):
        up, full = _gather_rows(om, nbr, b, rows)
        if not up or full:
            nv[b] = 0
            nt[b] = 0
            for q in range(BRICK * BRICK):
                srf_all[b, q] = 0
            continue
        nv[b] = _surface_rows(rows, ez, srf)
        for x in range(BRICK):
            for y in range(BRICK):
                srf_all[b, x * BRICK + y] = srf[x, y]
        nt[b] = _owned_total(rows)


@njit(cache=True, nogil=True, parallel=True)
def build_count(om, nbr, nv, nt, srf_all, counter, n_workers):
    """Vertices ``nv[b]`` and owned triangles ``nt[b]`` of every brick, and
    its surface voxels as bits: ``srf_all[b, 8 x + y]`` bit ``z`` set where
    brick voxel ``(x, y, z)`` is a surface voxel (``srf_all``: (n_bricks,
    64) uint8). Work items of ``CHUNK`` bricks are taken from ``counter``
    by ``n_workers`` workers."""
    n_chunks = (nbr.shape[0] + CHUNK - 1) // CHUNK
    for _ in prange(n_workers):
        rows = np.empty((_L, _L), dtype=np.int64)
        ez = np.empty((_L, _L), dtype=np.int64)
        srf = np.empty((BRICK, BRICK), dtype=np.int64)
        while True:
            ch = take_item(counter)
            if ch >= n_chunks:
                break
            _count_chunk(om, nbr, nv, nt, srf_all, ch, rows, ez, srf)


@njit(cache=True, nogil=True)
def _gather_slots(vmap, nbr, b, loc):
    """Vertex slots of brick ``b``'s voxels and of the one-voxel layer above
    it along each axis into ``loc`` (flat ``(9, 9, 9)`` int32, brick-relative
    ``(x, y, z)`` at ``(9 x + y) 9 + z``; -1 where no vertex or brick): the
    corners of the brick's cells. The two bricks a row reads (at and above
    along z) are looked up once per brick along x and y."""
    for gx in range(2):                        # the brick itself, the one above along x
        x0 = 0 if gx == 0 else BRICK
        x1 = BRICK if gx == 0 else BRICK + 1
        for gy in range(2):
            y0 = 0 if gy == 0 else BRICK
            y1 = BRICK if gy == 0 else BRICK + 1
            sl = 9 * (gx + 1) + 3 * (gy + 1)
            n_at = nbr[b, sl + 1]
            n_up = nbr[b, sl + 2]
            for rx in range(x0, x1):
                for ry in range(y0, y1):
                    s = (rx * (BRICK + 1) + ry) * (BRICK + 1)
                    oy = ((rx & BRICK_MASK) << 6) | ((ry & BRICK_MASK) << 3)
                    if n_at >= 0:
                        for q in range(BRICK):
                            loc[s + q] = vmap[n_at, oy + q]
                    else:
                        for q in range(BRICK):
                            loc[s + q] = -1
                    loc[s + BRICK] = vmap[n_up, oy] if n_up >= 0 else -1


def _key_corner_offsets():
    """(2 N_TRIPLES, 3) int64: for key ``2 tid + flip``, the offsets in the
    :func:`_gather_slots` layout of its corners in winding order from the
    cell's minimum corner (``(c0, c1, c2)``, or ``(c0, c2, c1)`` if
    flipped)."""
    out = np.zeros((2 * TRIPLE_CORNERS.shape[0], 3), dtype=np.int64)
    for key in range(out.shape[0]):
        for s in range(3):
            cs = 3 - s if key & 1 and s > 0 else s
            cn = int(TRIPLE_CORNERS[key >> 1, cs])
            out[key, s] = ((cn >> 2) * (BRICK + 1) + ((cn >> 1) & 1)) * (BRICK + 1) + (cn & 1)
    return out


_KEY_CORNERS = _key_corner_offsets()


@njit(cache=True, nogil=True)
def _triangles_chunk(om, nbr, toff, vmap, pos, nrm, trec, tflip, err, ch, rows, loc):
    """:func:`build_triangles` of work item ``ch`` (scratch ``rows``,
    ``loc``)."""
    nb_tot = nbr.shape[0]
    kc = _KEY_CORNERS
    for b in range(ch * CHUNK, min(nb_tot, (ch + 1) * CHUNK)):
        if toff[b + 1] == toff[b]:
            continue
        _gather_rows(om, nbr, b, rows)
        _gather_slots(vmap, nbr, b, loc)
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
                cbase = ((x - 1) * (BRICK + 1) + y - 1) * (BRICK + 1) - 1
                while m != 0:
                    z = np.int64(trailing_zeros(m))
                    m &= m - 1
                    code = _cell_code(r00, r01, r10, r11, z)
                    low = _low_mask(bx, by, bz, z)
                    for q in range(_OWN_N[code, low]):
                        key = np.int64(_OWN_KEY[code, low, q])
                        c = cbase + z
                        v0 = loc[c + kc[key, 0]]
                        v1 = loc[c + kc[key, 1]]
                        v2 = loc[c + kc[key, 2]]
                        trec[t, 0] = v0
                        trec[t, 1] = v1
                        trec[t, 2] = v2
                        trec[t, TR_KEY] = key      # the list links: link_all
                        if v0 >= 0 and v1 >= 0 and v2 >= 0:
                            tflip[t] = 1 if flip_of(trec, t, pos, nrm) else 0
                        else:
                            err[ch] += 1
                        t += 1


#: Rows per work item of the record fills that :func:`build_triangles` does
#: besides the triangles.
FILL_ROWS = 1 << 16


@njit(cache=True, nogil=True)
def _fill_chunk(trec, n_t, vrec, alive, n_v, q, n_tf):
    """Fill item ``q`` of :func:`build_triangles`: rows of the spare
    triangle records (``q < n_tf``) or of the vertex records and flags."""
    if q < n_tf:
        for t in range(n_t + q * FILL_ROWS, min(trec.shape[0], n_t + (q + 1) * FILL_ROWS)):
            for c in range(TR_WIDTH):
                trec[t, c] = TR_FILL[c]
        return
    q -= n_tf
    for v in range(q * FILL_ROWS, min(vrec.shape[0], (q + 1) * FILL_ROWS)):
        vrec[v, 0] = -1
        vrec[v, 1] = -1
        alive[v] = 1 if v < n_v else 0


@njit(cache=True, nogil=True, parallel=True)
def build_triangles(om, nbr, toff, vmap, pos, nrm, trec, tflip, err, vrec, alive, n_v, counter,
                    n_workers):
    """Triangle records ``toff[b]...`` of the triangles brick ``b``'s cells
    own, in (x, y, z, qualifying-triple) order (corners and key; the list
    links are :func:`bonesim.engine.surface_tables.link_all`'s), and their
    drawn winding ``tflip`` from the shaded ``pos``
    and ``nrm`` (:func:`bonesim.engine.surface_tables.flip_of`);
    ``err[chunk]`` counts triangles with a corner without a vertex. The
    corners' vertex slots are read from a per-brick copy of ``vmap``
    (:func:`_gather_slots`). Besides, the records the triangles leave: the
    spare triangle records (rows ``toff[-1]...``) get ``TR_FILL``, every
    vertex record ``vrec`` -1 (empty lists, for ``link_all``), ``alive`` 1
    for the ``n_v`` vertices and 0 after. Work items (``CHUNK`` bricks, then
    ``FILL_ROWS`` rows of the fills) are taken from ``counter`` by
    ``n_workers`` workers."""
    n_chunks = (nbr.shape[0] + CHUNK - 1) // CHUNK
    n_t = toff[toff.shape[0] - 1]
    n_tf = (trec.shape[0] - n_t + FILL_ROWS - 1) // FILL_ROWS
    n_items = n_chunks + n_tf + (vrec.shape[0] + FILL_ROWS - 1) // FILL_ROWS
    for _ in prange(n_workers):
        rows = np.empty((_L, _L), dtype=np.int64)
        loc = np.empty((BRICK + 1) ** 3, dtype=np.int32)
        while True:
            ch = take_item(counter)
            if ch >= n_items:
                break
            if ch < n_chunks:
                _triangles_chunk(om, nbr, toff, vmap, pos, nrm, trec, tflip, err, ch, rows, loc)
            else:
                _fill_chunk(trec, n_t, vrec, alive, n_v, ch - n_chunks, n_tf)
