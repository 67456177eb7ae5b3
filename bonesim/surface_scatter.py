"""Incremental update of the hybrid surface for scattered removals: the cells
and vertices around each removed or touched voxel are re-planned through
hash sets (:meth:`bonesim.surface.Surface.update`)."""
from __future__ import annotations


import numpy as np
from numba import njit

from bonesim.grid import (BRICK_SHIFT, find_brick, voxel_offset)
from .surface_tables import (AFFECTED_CELL_OFFSETS, MAX_PER_CELL, QUAL_KEY, QUAL_N,
                             QUAL_NMIN, TRIPLE_CORNERS, TRIPLE_FACE, _S_CELLS, _S_ERR,
                             _S_NEED_T, _S_NEED_V, _S_STATUS, _S_T_ADD, _S_T_DEL,
                             _S_V_ADD, _S_V_DEL, _T_ALIVE, _T_HW, _T_NFREE, _V_ALIVE,
                             _V_HW, _V_NFREE, _nb_slot, _slot_of)

__all__ = ["WINDOW_VOXELS_PER_INPUT"]

# ----------------------------------------------------------------------------
# Incremental update
# ----------------------------------------------------------------------------
# The update is split into small kernels, one loop nest each: a call to a
# non-inlined function inside a hot loop makes LLVM reload every array
# descriptor after it and slows the whole loop down several times.

#: Margin [voxels] around the inputs of an update covered by its window.
_WINDOW_MARGIN = 3
#: An update deduplicates cells and voxels with a dense window of flags over
#: the bounding box of its inputs (plus margin) when that box holds at most
#: this many voxels per input voxel (or 32768 in all); otherwise with hash sets.
WINDOW_VOXELS_PER_INPUT = 512


@njit(cache=True, nogil=True, inline="always")
def _hslot(key, mask):
    h = np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)
    return np.int64((h >> np.uint64(29)) & np.uint64(mask))


@njit(cache=True, nogil=True)
def _hset_new(n):
    cap = 64
    while cap < 2 * n:
        cap *= 2
    return np.full(cap, -1, dtype=np.int64)


@njit(cache=True, nogil=True, inline="always")
def _hset_add(h, key):
    """Insert ``key`` (>= 0) into the open-addressing set ``h``; True if new."""
    mask = h.shape[0] - 1
    s = _hslot(key, mask)
    while True:
        k = h[s]
        if k == key:
            return False
        if k == -1:
            h[s] = key
            return True
        s = (s + 1) & mask


@njit(cache=True, nogil=True, inline="always")
def _vkey(i, j, k):
    # voxel coordinates packed like brick keys (non-negative for |coord| < 2**20)
    return ((np.int64(i) + (1 << 20)) << 42) | ((np.int64(j) + (1 << 20)) << 21) \
        | (np.int64(k) + (1 << 20))


@njit(cache=True, nogil=True, inline="always")
def _mark(use_win, flags, bit, wlo, wd, h, i, j, k):
    """Mark voxel (i, j, k) in the window flags (or hash set); True if it
    was not marked before."""
    if use_win:
        idx = ((i - wlo[0]) * wd[1] + (j - wlo[1])) * wd[2] + (k - wlo[2])
        f = flags[idx]
        if f & bit:
            return False
        flags[idx] = f | bit
        return True
    return _hset_add(h, _vkey(i, j, k))


@njit(cache=True, nogil=True, inline="always")
def _occ_near(density, nbr, b, qi, qj, qk, i, j, k):
    """Is voxel (i, j, k), within one brick of voxel q (brick b), occupied?"""
    nb = nbr[b, _nb_slot(qi, qj, qk, i, j, k)]
    if nb < 0:
        return False
    return density[nb, voxel_offset(i, j, k)] > 0


@njit(cache=True, nogil=True, inline="always")
def _vmap_near(vmap, nbr, b, qi, qj, qk, i, j, k):
    nb = nbr[b, _nb_slot(qi, qj, qk, i, j, k)]
    if nb < 0:
        return -1
    return vmap[nb, voxel_offset(i, j, k)]


@njit(cache=True, nogil=True)
def _window_bricks(keys, vals, blo, bd):
    wbr = np.empty(bd[0] * bd[1] * bd[2], dtype=np.int32)
    s = 0
    for bi in range(blo[0], blo[0] + bd[0]):
        for bj in range(blo[1], blo[1] + bd[1]):
            for bk in range(blo[2], blo[2] + bd[2]):
                wbr[s] = find_brick(keys, vals, bi, bj, bk)
                s += 1
    return wbr


@njit(cache=True, nogil=True)
def _items_bricks(use_win, wbr, blo, bd, keys, vals, items, n, out):
    """Brick index (-1 if absent) of the first ``n`` voxels of ``items``."""
    if use_win:
        for q in range(n):
            out[q] = wbr[(((items[q, 0] >> BRICK_SHIFT) - blo[0]) * bd[1]
                          + ((items[q, 1] >> BRICK_SHIFT) - blo[1])) * bd[2]
                         + ((items[q, 2] >> BRICK_SHIFT) - blo[2])]
    else:
        for q in range(n):
            out[q] = find_brick(keys, vals, items[q, 0] >> BRICK_SHIFT,
                                items[q, 1] >> BRICK_SHIFT, items[q, 2] >> BRICK_SHIFT)


@njit(cache=True, nogil=True)
def _collect(removed, touched, rbrick, density, use_win, flags, wlo, wd, hc, hv, cells, cand):
    """Sources (removed voxels that are empty now), the cells whose owned
    triangles may change (32 per source) and the voxels to revisit (the
    3x3x3 neighbourhoods of all inputs, those next to a source first).

    Returns ``(n_cells, n_candidates, n_topology_candidates)``.
    """
    nr = removed.shape[0]
    ntch = touched.shape[0]
    n_aff = AFFECTED_CELL_OFFSETS.shape[0]
    is_src = np.zeros(nr, dtype=np.uint8)
    for r in range(nr):
        b = rbrick[r]
        if b >= 0 and not density[b, voxel_offset(removed[r, 0], removed[r, 1],
                                                  removed[r, 2])] > 0:
            is_src[r] = 1
    nc = 0
    ncand = 0
    for r in range(nr):
        if not is_src[r]:
            continue
        pi = removed[r, 0]
        pj = removed[r, 1]
        pk = removed[r, 2]
        for o in range(n_aff):
            ci = pi + AFFECTED_CELL_OFFSETS[o, 0]
            cj = pj + AFFECTED_CELL_OFFSETS[o, 1]
            ck = pk + AFFECTED_CELL_OFFSETS[o, 2]
            if _mark(use_win, flags, 1, wlo, wd, hc, ci, cj, ck):
                cells[nc, 0] = ci
                cells[nc, 1] = cj
                cells[nc, 2] = ck
                nc += 1
        for a in range(-1, 2):
            for bb in range(-1, 2):
                for cc in range(-1, 2):
                    if _mark(use_win, flags, 2, wlo, wd, hv, pi + a, pj + bb, pk + cc):
                        cand[ncand, 0] = pi + a
                        cand[ncand, 1] = pj + bb
                        cand[ncand, 2] = pk + cc
                        ncand += 1
    n_topo = ncand
    for r in range(nr + ntch):
        if r < nr:
            if is_src[r]:
                continue
            pi = removed[r, 0]
            pj = removed[r, 1]
            pk = removed[r, 2]
        else:
            pi = touched[r - nr, 0]
            pj = touched[r - nr, 1]
            pk = touched[r - nr, 2]
        for a in range(-1, 2):
            for bb in range(-1, 2):
                for cc in range(-1, 2):
                    if _mark(use_win, flags, 2, wlo, wd, hv, pi + a, pj + bb, pk + cc):
                        cand[ncand, 0] = pi + a
                        cand[ncand, 1] = pj + bb
                        cand[ncand, 2] = pk + cc
                        ncand += 1
    return nc, ncand, n_topo


@njit(cache=True, nogil=True)
def _plan_cells(density, nbr, vmap, ohead, onext, ttid, cells, cbrick, nc,
                newk, nnew, oldk, oldt, nold, stats):
    """Triangles each affected cell owns now (``oldk/oldt``) and should own
    (``newk``). Returns ``(n_to_add, n_to_drop)``."""
    vc = np.empty(8, dtype=np.int32)
    n_tadd = 0
    n_tdel = 0
    for c in range(nc):
        nnew[c] = 0
        nold[c] = 0
        b = cbrick[c]
        if b < 0:
            continue              # no corner of this cell was ever tissue
        ci = cells[c, 0]
        cj = cells[c, 1]
        ck = cells[c, 2]
        code = 0
        for cn in range(8):
            i = ci + (cn >> 2)
            j = cj + ((cn >> 1) & 1)
            k = ck + (cn & 1)
            nb = nbr[b, _nb_slot(ci, cj, ck, i, j, k)]
            vc[cn] = -1
            if nb >= 0:
                o = voxel_offset(i, j, k)
                if density[nb, o] > 0:
                    code |= 1 << cn
                vc[cn] = vmap[nb, o]
        n = QUAL_N[code]
        m = 0
        if n > 0:
            low0 = False
            low1 = False
            low2 = False
            if QUAL_NMIN[code, 0] > 0:
                low0 = True
                for u in range(2):
                    for w in range(2):
                        if _occ_near(density, nbr, b, ci, cj, ck, ci - 1, cj + u, ck + w):
                            low0 = False
            if QUAL_NMIN[code, 1] > 0:
                low1 = True
                for u in range(2):
                    for w in range(2):
                        if _occ_near(density, nbr, b, ci, cj, ck, ci + u, cj - 1, ck + w):
                            low1 = False
            if QUAL_NMIN[code, 2] > 0:
                low2 = True
                for u in range(2):
                    for w in range(2):
                        if _occ_near(density, nbr, b, ci, cj, ck, ci + u, cj + w, ck - 1):
                            low2 = False
            for q in range(n):
                key = QUAL_KEY[code, q]
                f = TRIPLE_FACE[key >> 1]
                if (f == 0 and low0) or (f == 1 and low1) or (f == 2 and low2):
                    continue
                newk[c, m] = key
                m += 1
        nnew[c] = m
        # Triangles this cell owns now: each one is on the owner list of
        # the vertex at the first corner c0 of its triple (c0 <= 5).
        mo = 0
        for cn in range(6):
            v = vc[cn]
            if v < 0:
                continue
            t = ohead[v]
            while t >= 0:
                key = ttid[t]
                if TRIPLE_CORNERS[key >> 1, 0] == cn:
                    if mo == oldt.shape[1]:
                        stats[_S_ERR] += 1
                    else:
                        oldt[c, mo] = t
                        oldk[c, mo] = key
                        mo += 1
                t = onext[t]
        nold[c] = mo
        # keys present in both lists stay; mark them by negating the old key
        for y in range(mo):
            for x in range(m):
                if oldk[c, y] == newk[c, x]:
                    oldk[c, y] = -1 - oldk[c, y]
                    newk[c, x] = -1 - newk[c, x]
                    break
        for x in range(m):
            if newk[c, x] >= 0:
                n_tadd += 1
        for y in range(mo):
            if oldk[c, y] >= 0:
                n_tdel += 1
    return n_tadd, n_tdel


@njit(cache=True, nogil=True)
def _plan_vertices(density, vmap, cand, qbrick, n_topo, qstat):
    """Vertices to create (``qstat`` 1) or drop (2) among the voxels next to
    a source. Every occupied 26-neighbour of an empty voxel is a surface
    voxel, so no neighbourhood test is needed. Returns ``(n_add, n_drop)``."""
    n_vadd = 0
    n_vdel = 0
    for q in range(n_topo):
        qstat[q] = 0
        b = qbrick[q]
        if b < 0:
            continue
        o = voxel_offset(cand[q, 0], cand[q, 1], cand[q, 2])
        occ = density[b, o] > 0
        if occ and vmap[b, o] < 0:
            qstat[q] = 1
            n_vadd += 1
        elif not occ and vmap[b, o] >= 0:
            qstat[q] = 2
            n_vdel += 1
    return n_vadd, n_vdel


@njit(cache=True, nogil=True, inline="always")
def _unlink(t, v, vhead, tri, tnext):
    """Remove triangle t from vertex v's list; False if it was not there."""
    prev = -1
    prev_s = 0
    cur = vhead[v]
    while cur >= 0 and cur != t:
        prev = cur
        prev_s = _slot_of(tri, cur, v)
        cur = tnext[cur, prev_s]
    if cur < 0:
        return False
    nxt = tnext[t, _slot_of(tri, t, v)]
    if prev < 0:
        vhead[v] = nxt
    else:
        tnext[prev, prev_s] = nxt
    return True


@njit(cache=True, nogil=True)
def _drop_triangles(oldt, oldk, nold, nc, vhead, tri, tnext, ttid, tfree, cnt, stats,
                    ohead, onext):
    for c in range(nc):
        for y in range(nold[c]):
            if oldk[c, y] < 0:
                continue                     # still owned
            t = oldt[c, y]
            for s in range(3):
                if not _unlink(t, tri[t, s], vhead, tri, tnext):
                    stats[_S_ERR] += 1
            v = tri[t, 0]
            prev = -1
            cur = ohead[v]
            while cur >= 0 and cur != t:
                prev = cur
                cur = onext[cur]
            if cur < 0:
                stats[_S_ERR] += 1
            elif prev < 0:
                ohead[v] = onext[t]
            else:
                onext[prev] = onext[t]
            ttid[t] = -1
            tfree[cnt[_T_NFREE]] = t
            cnt[_T_NFREE] += 1
            cnt[_T_ALIVE] -= 1
            stats[_S_T_DEL] += 1


@njit(cache=True, nogil=True)
def _edit_vertices(cand, qbrick, qstat, n_topo, origin, spacing, vmap, pos, vijk,
                   valive, vhead, ohead, vfree, cnt, stats):
    """Drop, then create, the vertices planned in ``qstat``."""
    for q in range(n_topo):
        if qstat[q] != 2:
            continue
        o = voxel_offset(cand[q, 0], cand[q, 1], cand[q, 2])
        v = vmap[qbrick[q], o]
        if vhead[v] >= 0:
            stats[_S_ERR] += 1
        vmap[qbrick[q], o] = -1
        valive[v] = 0
        vfree[cnt[_V_NFREE]] = v
        cnt[_V_NFREE] += 1
        cnt[_V_ALIVE] -= 1
        stats[_S_V_DEL] += 1
    for q in range(n_topo):
        if qstat[q] != 1:
            continue
        if cnt[_V_NFREE] > 0:
            cnt[_V_NFREE] -= 1
            v = vfree[cnt[_V_NFREE]]
        else:
            v = cnt[_V_HW]
            cnt[_V_HW] += 1
        qi = cand[q, 0]
        qj = cand[q, 1]
        qk = cand[q, 2]
        vmap[qbrick[q], voxel_offset(qi, qj, qk)] = v
        vijk[v, 0] = qi
        vijk[v, 1] = qj
        vijk[v, 2] = qk
        pos[v, 0] = origin[0] + spacing * qi
        pos[v, 1] = origin[1] + spacing * qj
        pos[v, 2] = origin[2] + spacing * qk
        vhead[v] = -1
        ohead[v] = -1
        valive[v] = 1
        cnt[_V_ALIVE] += 1
        stats[_S_V_ADD] += 1


@njit(cache=True, nogil=True)
def _add_triangles(cells, cbrick, newk, nnew, nc, nbr, vmap, vhead, tri, tnext, ttid,
                   tfree, cnt, stats, ohead, onext):
    for c in range(nc):
        b = cbrick[c]
        ci = cells[c, 0]
        cj = cells[c, 1]
        ck = cells[c, 2]
        for x in range(nnew[c]):
            key = newk[c, x]
            if key < 0:
                continue                     # already there
            if cnt[_T_NFREE] > 0:
                cnt[_T_NFREE] -= 1
                t = tfree[cnt[_T_NFREE]]
            else:
                t = cnt[_T_HW]
                cnt[_T_HW] += 1
            tid = key >> 1
            for s in range(3):
                cs = s
                if key & 1 and s > 0:
                    cs = 3 - s
                cn = TRIPLE_CORNERS[tid, cs]
                v = _vmap_near(vmap, nbr, b, ci, cj, ck, ci + (cn >> 2),
                               cj + ((cn >> 1) & 1), ck + (cn & 1))
                if v < 0:
                    stats[_S_ERR] += 1
                    v = 0
                tri[t, s] = v
            ttid[t] = key
            for s in range(3):
                v = tri[t, s]
                tnext[t, s] = vhead[v]
                vhead[v] = t
            v = tri[t, 0]
            onext[t] = ohead[v]
            ohead[v] = t
            cnt[_T_ALIVE] += 1
            stats[_S_T_ADD] += 1


@njit(cache=True, nogil=True)
def _update_kernel(keys, vals, density, nbr, origin, spacing,
                   removed, touched, win_per_input,
                   vmap, pos, vijk, valive, vhead, vfree,
                   tri, tnext, ttid, tfree, cnt, stats, ohead, onext):
    """Re-tessellate around ``removed`` (normals and colours are the shading's).

    A read-only plan (owner cells whose triangles may change, with their old
    and new triangles; vertices to create or drop) is followed, if the
    vertex and triangle arrays have room, by the edit. Without room it sets
    ``stats[_S_STATUS] = 1`` and the number of extra slots needed, and
    changes nothing. Only *sources*, removed voxels that are empty now,
    change the topology.
    """
    for s in range(stats.shape[0]):
        stats[s] = 0
    nr = removed.shape[0]
    ntch = touched.shape[0]
    n_in = nr + ntch
    if n_in == 0:
        return
    n_aff = AFFECTED_CELL_OFFSETS.shape[0]

    # ---- dedup structure: a dense window of flags, or hash sets -----------
    wlo = np.empty(3, dtype=np.int64)
    whi = np.empty(3, dtype=np.int64)
    for a in range(3):
        lo = removed[0, a] if nr > 0 else touched[0, a]
        hi = lo
        for r in range(nr):
            lo = min(lo, removed[r, a])
            hi = max(hi, removed[r, a])
        for r in range(ntch):
            lo = min(lo, touched[r, a])
            hi = max(hi, touched[r, a])
        wlo[a] = lo - _WINDOW_MARGIN
        whi[a] = hi + _WINDOW_MARGIN
    wd = whi - wlo + 1
    vol = wd[0] * wd[1] * wd[2]
    use_win = win_per_input > 0 and vol <= max(32768, win_per_input * n_in)
    blo = wlo >> BRICK_SHIFT
    bd = (whi >> BRICK_SHIFT) - blo + 1
    if use_win:
        flags = np.zeros(vol, dtype=np.uint8)
        wbr = _window_bricks(keys, vals, blo, bd)
        hc = np.empty(1, dtype=np.int64)
        hv = np.empty(1, dtype=np.int64)
    else:
        flags = np.empty(1, dtype=np.uint8)
        wbr = np.empty(1, dtype=np.int32)
        hc = _hset_new(nr * n_aff)
        hv = _hset_new(27 * n_in)

    # ---- plan ----------------------------------------------------------------
    rbrick = np.empty(nr, dtype=np.int32)
    _items_bricks(use_win, wbr, blo, bd, keys, vals, removed, nr, rbrick)
    cells = np.empty((nr * n_aff, 3), dtype=np.int32)
    cand = np.empty((27 * n_in, 3), dtype=np.int32)
    nc, ncand, n_topo = _collect(removed, touched, rbrick, density, use_win, flags,
                                 wlo, wd, hc, hv, cells, cand)
    stats[_S_CELLS] = nc
    cbrick = np.empty(nc, dtype=np.int32)
    _items_bricks(use_win, wbr, blo, bd, keys, vals, cells, nc, cbrick)
    qbrick = np.empty(ncand, dtype=np.int32)
    _items_bricks(use_win, wbr, blo, bd, keys, vals, cand, ncand, qbrick)
    newk = np.empty((nc, MAX_PER_CELL), dtype=np.int16)
    nnew = np.empty(nc, dtype=np.int32)
    oldk = np.empty((nc, 2 * MAX_PER_CELL), dtype=np.int16)
    oldt = np.empty((nc, 2 * MAX_PER_CELL), dtype=np.int32)
    nold = np.empty(nc, dtype=np.int32)
    n_tadd, n_tdel = _plan_cells(density, nbr, vmap, ohead, onext, ttid, cells, cbrick,
                                 nc, newk, nnew, oldk, oldt, nold, stats)
    qstat = np.empty(n_topo, dtype=np.int8)
    n_vadd, n_vdel = _plan_vertices(density, vmap, cand, qbrick, n_topo, qstat)

    # ---- room? -----------------------------------------------------------------
    v_room = cnt[_V_NFREE] + (vijk.shape[0] - cnt[_V_HW]) + n_vdel
    t_room = cnt[_T_NFREE] + (tri.shape[0] - cnt[_T_HW]) + n_tdel
    if n_vadd > v_room or n_tadd > t_room:
        stats[_S_STATUS] = 1
        stats[_S_NEED_V] = max(0, n_vadd - v_room)
        stats[_S_NEED_T] = max(0, n_tadd - t_room)
        return

    # ---- edit: drop triangles, drop/create vertices, add triangles, shade ----
    _drop_triangles(oldt, oldk, nold, nc, vhead, tri, tnext, ttid, tfree, cnt, stats,
                    ohead, onext)
    _edit_vertices(cand, qbrick, qstat, n_topo, origin, spacing, vmap, pos, vijk, valive,
                   vhead, ohead, vfree, cnt, stats)
    _add_triangles(cells, cbrick, newk, nnew, nc, nbr, vmap, vhead, tri, tnext, ttid,
                   tfree, cnt, stats, ohead, onext)
