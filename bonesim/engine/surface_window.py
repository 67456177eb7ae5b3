"""Incremental update of the hybrid surface on one window: the box around
a set of removed voxels is gathered into dense bit rows and re-planned
there. :mod:`bonesim.engine.surface_tiles` tiles any input into such
windows (:meth:`bonesim.engine.surface.Surface.update`)."""
from __future__ import annotations


import numpy as np
from numba import njit
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros

from bonesim.engine.grid import (BRICK, BRICK_MASK, BRICK_SHIFT, find_brick, voxel_offset)
from bonesim.engine.surface_tables import (N_TRIPLES, QUAL_KEY, QUAL_N, TRIPLE_CORNERS, TRIPLE_FACE,
                                           S_CELLS, S_ERR, S_NEED_T, S_NEED_V,
                                           S_T_ADD, S_T_DEL, S_V_ADD, S_V_DEL, TR_KEY, TR_NEXT,
                                           TR_ONEXT, T_ALIVE, T_HW, T_NFREE, VR_HEAD, VR_OHEAD,
                                           V_ALIVE, V_HW, V_NFREE)

__all__ = ["WINDOW_DEPTH", "WINDOW_MARGIN"]

# ----------------------------------------------------------------------------
# Incremental update on one window
# ----------------------------------------------------------------------------
# The update works on dense copies of a small box around its inputs instead
# of looking voxels up one by one:
#
# * the window is the inputs' bounding box plus WINDOW_MARGIN voxels (every
#   voxel an update reads lies within 2 voxels of an input);
# * sets of voxels / cells are bit rows: one uint64 per (x, y) row of the
#   window, bit z for voxel (or cell minimum corner) z along k. Rows are
#   stored with two guard rows / columns on each side (row index
#   ``(x + 2) * (wd1 + 4) + y + 2``), so neighbouring rows can be read
#   without bounds checks. The sets the update needs (cells to re-evaluate,
#   voxels that may join or leave the surface, voxels to read) are
#   dilations of the set of inputs, a few shifts and ORs per row, and they
#   are visited in (i, j, k) order;
# * the densities and the voxel -> vertex map of the voxels it reads are
#   gathered once into local arrays laid out like the rows (voxel
#   ``row * wd2 + z``), with the occupancy as bit rows, so a cell's code is
#   a handful of shifts.
#
# Cells to re-evaluate: the 8 cells containing a source (their code may have
# changed) and the 12 cells whose minimum face has a source just below it
# (their ownership test reads it). A cell's owned triangles depend on
# nothing else, so no other cell can gain or lose one. Sources are the
# removed voxels that are empty now (those outside any brick included:
# re-evaluating a cell is harmless).
#
# Scratch memory lives in the Surface and grows on demand (status 2).
#
# Vertices dropped are those of the sources (every voxel emptied since the
# last update is listed, so every emptied voxel that had a vertex is a
# source); all cells containing a source are re-evaluated in the same
# window, so its triangles are gone first. Vertices created are the occupied
# voxels next to a source without one.

#: Margin [voxels] of the window around the inputs.
WINDOW_MARGIN = 2
#: Guard rows / columns around the window's bit rows.
_GUARD = 2
#: Deepest window along k [voxels]: one uint64 bit row per (i, j).
WINDOW_DEPTH = 64
# bit-row sets (_R_T0.. are temporaries of the dilations)
(_R_REM, _R_SRC, _R_AFF, _R_CELL, _R_TOPO, _R_OCC, _R_HASV, _R_NEED,
 _R_DIRTY, _R_LIST, _R_T0, _R_T1, _R_T2, _R_T3, _R_T4) = range(15)
N_ROWSETS = 15
# per-slot bit masks of the qualifying triples lying in the minimum face along a
_QUAL_FMASK = np.zeros((256, 3), dtype=np.uint8)
for _code in range(256):
    for _s in range(int(QUAL_N[_code])):
        _f = int(TRIPLE_FACE[int(QUAL_KEY[_code, _s]) >> 1])
        if 0 <= _f < 3:
            _QUAL_FMASK[_code, _f] |= 1 << _s
_QUAL_ALL = np.array([(1 << int(n)) - 1 for n in QUAL_N], dtype=np.uint8)
_POP4 = np.array([bin(m).count("1") for m in range(16)], dtype=np.int32)
# _KEY_SLOT[code, key]: slot s with QUAL_KEY[code, s] == key, or -1
_KEY_SLOT = np.full((256, 2 * N_TRIPLES), -1, dtype=np.int8)
for _code in range(256):
    for _s in range(int(QUAL_N[_code])):
        _KEY_SLOT[_code, int(QUAL_KEY[_code, _s])] = _s


@njit(cache=True, nogil=True)
def _fw_mark(removed, wlo, w1, rows, nr_p):
    """REM bit rows: the removed voxels."""
    rem0 = _R_REM * nr_p
    for r in range(nr_p):
        rows[rem0 + r] = np.uint64(0)
    for q in range(removed.shape[0]):
        row = (removed[q, 0] - wlo[0] + _GUARD) * w1 + (removed[q, 1] - wlo[1] + _GUARD)
        rows[rem0 + row] |= np.uint64(1) << np.uint64(removed[q, 2] - wlo[2])


@njit(cache=True, nogil=True)
def _fw_need(rows, nr_p, w0, w1):
    """NEED: the voxels within 2 (along each axis) of a removed voxel."""
    one = np.uint64(1)
    two = np.uint64(2)
    E = _R_REM * nr_p
    N = _R_NEED * nr_p
    T0 = _R_T0 * nr_p
    T1 = _R_T1 * nr_p
    for r in range(nr_p):
        e = rows[E + r]
        rows[T0 + r] = e | (e >> one) | (e >> two) | (e << one) | (e << two)
    for x in range(w0):
        for r in range(x * w1 + 2, x * w1 + w1 - 2):
            rows[T1 + r] = (rows[T0 + r - 2] | rows[T0 + r - 1] | rows[T0 + r]
                            | rows[T0 + r + 1] | rows[T0 + r + 2])
    for x in range(2, w0 - 2):
        for r in range(x * w1 + 2, x * w1 + w1 - 2):
            rows[N + r] = (rows[T1 + r - 2 * w1] | rows[T1 + r - w1] | rows[T1 + r]
                           | rows[T1 + r + w1] | rows[T1 + r + 2 * w1])


@njit(cache=True, nogil=True)
def _fw_dilate(rows, nr_p, w0, w1):
    """SRC = REM minus OCC; from it: AFF (cells to re-evaluate), CELL (cells
    containing a source) and TOPO (3x3x3 of the sources). See the comment
    above."""
    one = np.uint64(1)
    M = _R_REM * nr_p
    O = _R_OCC * nr_p
    S = _R_SRC * nr_p
    A = _R_AFF * nr_p
    C = _R_CELL * nr_p
    T = _R_TOPO * nr_p
    K1 = _R_T0 * nr_p           # cells along k containing a source: k in {p - 1, p}
    K3S = _R_T1 * nr_p          # sources dilated by 1 along k
    CJ = _R_T2 * nr_p           # K1 dilated to cells along j
    J3S = _R_T3 * nr_p          # K3S dilated by 1 along j
    SJ = _R_T4 * nr_p           # sources dilated to cells along j
    for r in range(nr_p):
        s = rows[M + r] & ~rows[O + r]      # (OCC is stale where REM is 0)
        rows[S + r] = s
        rows[K1 + r] = s | (s >> one)
        rows[K3S + r] = s | (s >> one) | (s << one)
    for x in range(w0):
        for r in range(x * w1 + 2, x * w1 + w1 - 2):
            rows[CJ + r] = rows[K1 + r] | rows[K1 + r + 1]
            rows[J3S + r] = rows[K3S + r - 1] | rows[K3S + r] | rows[K3S + r + 1]
            rows[SJ + r] = rows[S + r] | rows[S + r + 1]
    for x in range(2, w0 - 2):
        for r in range(x * w1 + 2, x * w1 + w1 - 2):
            c = rows[CJ + r] | rows[CJ + r + w1]
            rows[C + r] = c
            rows[A + r] = (c | rows[CJ + r - w1]                        # + face along i
                           | rows[K1 + r - 1] | rows[K1 + r + w1 - 1]   # + face along j
                           | ((rows[SJ + r] | rows[SJ + r + w1]) << one))  # along k
            rows[T + r] = rows[J3S + r - w1] | rows[J3S + r] | rows[J3S + r + w1]


@njit(cache=True, nogil=True)
def _fw_gather(density, vmap, wbr, wlo, wd, blo, bd, ld, lv, rows, nr_p):
    """Densities and vertex slots of the voxels in NEED (elsewhere ``ld``
    and ``lv`` are left stale), occupancy and has-vertex bit rows of the
    window."""
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    occ0 = _R_OCC * nr_p
    hv0 = _R_HASV * nr_p
    need0 = _R_NEED * nr_p
    for x in range(wd0):
        i = wlo[0] + x
        for y in range(wd1):
            j = wlo[1] + y
            r = (x + _GUARD) * w1 + y + _GUARD
            need = rows[need0 + r]
            if need == 0:
                rows[occ0 + r] = np.uint64(0)
                rows[hv0 + r] = np.uint64(0)
                continue
            zlo = np.int64(trailing_zeros(need))
            zhi = 64 - np.int64(leading_zeros(need))
            bbase = (((i >> BRICK_SHIFT) - blo[0]) * bd[1] + ((j >> BRICK_SHIFT) - blo[1])) * bd[2]
            ob = ((i & BRICK_MASK) << 6) | ((j & BRICK_MASK) << 3)
            li = r * wd2
            occ = np.uint64(0)
            hv = np.uint64(0)
            z = zlo
            while z < zhi:
                k = wlo[2] + z
                n = min(zhi - z, BRICK - (k & BRICK_MASK))
                b = wbr[bbase + (k >> BRICK_SHIFT) - blo[2]]
                if b >= 0:
                    ub = np.uint64(b)
                    o = np.uint64(ob | (k & BRICK_MASK))
                    lz = np.uint64(li + z)
                    for u in range(n):
                        uu = np.uint64(u)
                        d = density[ub, o + uu]
                        vv = vmap[ub, o + uu]
                        ld[lz + uu] = d
                        lv[lz + uu] = vv
                        occ |= np.uint64(d > 0) << np.uint64(z + u)
                        hv |= np.uint64(vv >= 0) << np.uint64(z + u)
                else:
                    for u in range(n):
                        ld[li + z + u] = np.float32(0.0)
                        lv[li + z + u] = -1
                z += n
            rows[occ0 + r] = occ
            rows[hv0 + r] = hv


@njit(cache=True, nogil=True)
def _fw_plan(rows, nr_p, wd, lcode, lact, clist):
    """Code and active slots of every cell to re-evaluate; list the cells that
    own or may own a triangle (LIST bits, ``clist``). Returns ``(n_listed,
    bound on triangles to add, vertices to add, vertices to drop, cells
    visited)``."""
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    one = np.uint64(1)
    three = np.uint64(3)
    A = _R_AFF * nr_p
    C = _R_CELL * nr_p
    O = _R_OCC * nr_p
    H = _R_HASV * nr_p
    T = _R_TOPO * nr_p
    S = _R_SRC * nr_p
    L = _R_LIST * nr_p
    for r in range(nr_p):
        rows[L + r] = np.uint64(0)
    nl = 0
    tbound = 0
    ncells = 0
    nvadd = 0
    nvdel = 0
    # unsigned indices below: no negative-index fix-ups
    uw1 = np.uint64(w1)
    uwd2 = np.uint64(wd2)
    for x in range(wd0):
        for r in range((x + _GUARD) * w1 + _GUARD, (x + _GUARD) * w1 + _GUARD + wd1):
            ur = np.uint64(r)
            uO = np.uint64(O) + ur
            uH = np.uint64(H) + ur
            # vertices to create / drop
            tb = rows[np.uint64(T) + ur]
            if tb != 0:
                hv = rows[uH]
                add = tb & rows[uO] & ~hv
                dele = rows[np.uint64(S) + ur] & hv
                while add != 0:
                    add &= add - one
                    nvadd += 1
                while dele != 0:
                    dele &= dele - one
                    nvdel += 1
            bits = rows[np.uint64(A) + ur]
            if bits == 0:
                continue
            lbits = np.uint64(0)
            cbits = rows[np.uint64(C) + ur]
            o00 = rows[uO]
            o01 = rows[uO + one]
            o10 = rows[uO + uw1]
            o11 = rows[uO + uw1 + one]
            ox = rows[uO - uw1] | rows[uO - uw1 + one]          # x - 1 plane
            oy = rows[uO - one] | rows[uO + uw1 - one]          # y - 1 plane
            oz = o00 | o01 | o10 | o11
            hv = rows[uH] | rows[uH + one] | rows[uH + uw1]
            # cells with all corners empty or all occupied own no triangle:
            # unless a corner 0..5 has a vertex (old triangles), skip them
            oa = o00 & o01 & o10 & o11
            mixed = (oz | (oz >> one)) & ~(oa & (oa >> one))
            bits &= mixed | hv | (hv >> one)
            while bits != 0:
                z = trailing_zeros(bits)
                bits &= bits - one
                ncells += 1
                zz = np.uint64(z)
                code = (((o00 >> zz) & three) | (((o01 >> zz) & three) << np.uint64(2))
                        | (((o10 >> zz) & three) << np.uint64(4))
                        | (((o11 >> zz) & three) << np.uint64(6)))
                act = np.int64(_QUAL_ALL[code])
                lowm = np.int64(0)      # slots dropped by the ownership test
                if act != 0:
                    if (ox >> zz) & three == 0:
                        lowm |= np.int64(_QUAL_FMASK[code, 0])
                    if (oy >> zz) & three == 0:
                        lowm |= np.int64(_QUAL_FMASK[code, 1])
                    if (oz >> (zz - one)) & one == 0:
                        lowm |= np.int64(_QUAL_FMASK[code, 2])
                    act &= ~lowm
                if (cbits >> zz) & one == 0 and lowm == 0:
                    # no source in the cell: same code as before the batch;
                    # its ownership tests read voxels that were occupied
                    # before if they are now, so if all of them pass now
                    # they passed before: nothing changed
                    continue
                if act == 0 and (hv >> zz) & three == 0:
                    continue            # owns nothing and will own nothing
                li = ur * uwd2 + z
                lcode[li] = code
                lact[li] = act
                clist[nl] = li
                nl += 1
                tbound += _POP4[act]
                lbits |= one << zz
            rows[np.uint64(L) + ur] = lbits
    return nl, tbound, nvadd, nvdel, ncells


@njit(cache=True, nogil=True)
def _fw_cells(clist, nl, wd, ld, lv, lcode, lact, rows, nr_p, trec, vrec, tfree, cnt, stats):
    """Drop the triangles the listed cells own but should not own.

    Every triangle a listed cell owns is on the owner list of the vertex at
    its corner ``c0``; each such list is walked once (vertices in (i, j, k)
    order). A dropped triangle leaves its owner list, its slot is freed and
    its key set to -1; it stays on the vertex lists of its corners, which
    are marked DIRTY (see :func:`_fw_unlink_dead`). ``lact`` holds the
    active slots of a listed cell in bits 0-3 and collects the slots it
    still owns in bits 4-7; on return it holds the slots to add, and the
    list is compacted to the cells with something to add.
    Returns ``(new list length, dead list entries)``."""
    one = np.uint64(1)
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    sx = w1 * wd2
    D = _R_DIRTY * nr_p
    L = _R_LIST * nr_p
    H = _R_HASV * nr_p
    for r in range(nr_p):
        rows[D + r] = np.uint64(0)
    n_dead = 0
    # unsigned indices below (all in range): no negative-index fix-ups
    uw1 = np.uint64(w1)
    uwd2 = np.uint64(wd2)
    usx = np.uint64(sx)
    uL = np.uint64(L)
    for x in range(wd0):
        for r in range((x + _GUARD) * w1 + _GUARD, (x + _GUARD) * w1 + _GUARD + wd1):
            ur = np.uint64(r)
            # vertices at corner 0..5 of a listed cell
            lw = rows[uL + ur] | rows[uL + ur - one] | rows[uL + ur - uw1]
            vw = (lw | (lw << one)) & rows[np.uint64(H) + ur]
            while vw != 0:
                z = trailing_zeros(vw)
                vw &= vw - one
                v = np.uint64(lv[ur * uwd2 + z])
                prev = -1
                t = vrec[v, VR_OHEAD]
                while t >= 0:
                    ut = np.uint64(t)
                    nxt = trec[ut, TR_ONEXT]
                    key = np.uint64(trec[ut, TR_KEY])
                    c0 = np.uint64(TRIPLE_CORNERS[key >> one, 0])
                    urc = ur - (c0 >> np.uint64(2)) * uw1 - ((c0 >> one) & one)
                    zc = z - (c0 & one)
                    if (rows[uL + urc] >> zc) & one == 0:
                        prev = t                # owner not listed: unchanged
                        t = nxt
                        continue
                    li = urc * uwd2 + zc
                    ah = np.int64(lact[li])
                    slot = _KEY_SLOT[lcode[li], key]
                    if slot >= 0 and (ah >> slot) & 1 and not (ah >> (slot + 4)) & 1:
                        lact[li] = ah | (np.int64(16) << slot)
                        prev = t
                        t = nxt
                        continue
                    # drop t: off the owner list (we hold its predecessor); the
                    # vertex lists of its surviving corners are cleaned later
                    # (an emptied corner's vertex goes with all its triangles:
                    # its list is dropped whole in _fw_vertices)
                    if prev < 0:
                        vrec[v, VR_OHEAD] = nxt
                    else:
                        trec[prev, TR_ONEXT] = nxt
                    tid = key >> one
                    for s in range(3):
                        c = np.uint64(TRIPLE_CORNERS[tid, s])
                        ca = c >> np.uint64(2)
                        cb = (c >> one) & one
                        cc = c & one
                        if not ld[li + ca * usx + cb * uwd2 + cc] > 0:
                            continue
                        rows[np.uint64(D) + urc + ca * uw1 + cb] |= one << (zc + cc)
                        n_dead += 1
                    trec[t, TR_KEY] = -1
                    tfree[cnt[T_NFREE]] = t
                    cnt[T_NFREE] += 1
                    cnt[T_ALIVE] -= 1
                    stats[S_T_DEL] += 1
                    t = nxt
    na = 0
    for q in range(nl):
        li = clist[q]
        ah = np.int64(lact[li])
        rest = ah & ~(ah >> 4) & 15
        if rest != 0:
            lact[li] = rest
            clist[na] = li
            na += 1
    return na, n_dead


@njit(cache=True, nogil=True)
def _fw_unlink_dead(rows, nr_p, wd, lv, trec, vrec):
    """Splice the dead triangles (key -1) out of the vertex lists of the
    DIRTY voxels, one walk per list. Returns the number of entries removed."""
    one = np.uint64(1)
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    D = _R_DIRTY * nr_p
    n = 0
    for x in range(wd0):
        for r in range((x + _GUARD) * w1 + _GUARD, (x + _GUARD) * w1 + _GUARD + wd1):
            bits = rows[D + r]
            while bits != 0:
                z = trailing_zeros(bits)
                bits &= bits - one
                v = lv[r * wd2 + z]
                prev = -1
                prev_s = 0
                cur = vrec[v, VR_HEAD]
                while cur >= 0:
                    s = 0 if trec[cur, 0] == v else (1 if trec[cur, 1] == v else 2)
                    nxt = trec[cur, TR_NEXT + s]
                    if trec[cur, TR_KEY] < 0:
                        if prev < 0:
                            vrec[v, VR_HEAD] = nxt
                        else:
                            trec[prev, TR_NEXT + prev_s] = nxt
                        n += 1
                    else:
                        prev = cur
                        prev_s = s
                    cur = nxt
    return n


@njit(cache=True, nogil=True)
def _fw_vertices(rows, nr_p, wd, wlo, wbr, blo, bd, lv, origin, spacing, vmap, pos, vijk,
                 valive, vrec, vfree, cnt, stats):
    """Drop the vertices of the sources, then create those of new surface
    voxels (which so reuse the slots just freed, whose
    lines are in cache); HASV becomes the set of voxels with a vertex after
    the edit."""
    one = np.uint64(1)
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    T = _R_TOPO * nr_p
    O = _R_OCC * nr_p
    H = _R_HASV * nr_p
    S = _R_SRC * nr_p
    for create in range(2):
        for x in range(wd0):
            i = wlo[0] + x
            for y in range(wd1):
                r = (x + _GUARD) * w1 + y + _GUARD
                hv = rows[H + r]
                if create:
                    chg = rows[T + r] & rows[O + r] & ~hv
                else:
                    chg = rows[S + r] & hv
                if chg == 0:
                    continue
                rows[H + r] = hv ^ chg
                j = wlo[1] + y
                bbase = (((i >> BRICK_SHIFT) - blo[0]) * bd[1]
                         + ((j >> BRICK_SHIFT) - blo[1])) * bd[2]
                while chg != 0:
                    z = trailing_zeros(chg)
                    chg &= chg - one
                    k = wlo[2] + z
                    b = wbr[bbase + (k >> BRICK_SHIFT) - blo[2]]
                    o = voxel_offset(i, j, k)
                    li = r * wd2 + z
                    if create:                              # became surface
                        if cnt[V_NFREE] > 0:
                            cnt[V_NFREE] -= 1
                            v = vfree[cnt[V_NFREE]]
                        else:
                            v = cnt[V_HW]
                            cnt[V_HW] += 1
                        vmap[b, o] = v
                        lv[li] = v
                        vijk[v, 0] = i
                        vijk[v, 1] = j
                        vijk[v, 2] = k
                        pos[v, 0] = origin[0] + spacing * i
                        pos[v, 1] = origin[1] + spacing * j
                        pos[v, 2] = origin[2] + spacing * k
                        vrec[v, VR_HEAD] = -1
                        vrec[v, VR_OHEAD] = -1
                        valive[v] = 1
                        cnt[V_ALIVE] += 1
                        stats[S_V_ADD] += 1
                    else:                                   # a source
                        v = lv[li]
                        if vrec[v, VR_OHEAD] >= 0:
                            stats[S_ERR] += 1
                        vrec[v, VR_HEAD] = -1              # its triangles are all gone
                        vmap[b, o] = -1
                        lv[li] = -1
                        valive[v] = 0
                        vfree[cnt[V_NFREE]] = v
                        cnt[V_NFREE] += 1
                        cnt[V_ALIVE] -= 1
                        stats[S_V_DEL] += 1


@njit(cache=True, nogil=True)
def _fw_add(clist, na, wd, lv, lcode, lact, trec, vrec, tfree, cnt, stats):
    sy = wd[2]
    sx = (wd[1] + 2 * _GUARD) * wd[2]
    for q in range(na):
        li = clist[q]
        code = lcode[li]
        rest = np.int64(lact[li])
        for slot in range(QUAL_N[code]):
            if not (rest >> slot) & 1:
                continue
            key = QUAL_KEY[code, slot]
            if cnt[T_NFREE] > 0:
                cnt[T_NFREE] -= 1
                t = tfree[cnt[T_NFREE]]
            else:
                t = cnt[T_HW]
                cnt[T_HW] += 1
            tid = key >> 1
            for s in range(3):
                cs = s
                if key & 1 and s > 0:
                    cs = 3 - s
                cn = TRIPLE_CORNERS[tid, cs]
                v = lv[li + (cn >> 2) * sx + ((cn >> 1) & 1) * sy + (cn & 1)]
                if v < 0:
                    stats[S_ERR] += 1
                    v = 0
                trec[t, s] = v
                trec[t, TR_NEXT + s] = vrec[v, VR_HEAD]
                vrec[v, VR_HEAD] = t
            trec[t, TR_KEY] = key
            v = trec[t, 0]
            trec[t, TR_ONEXT] = vrec[v, VR_OHEAD]
            vrec[v, VR_OHEAD] = t
            cnt[T_ALIVE] += 1
            stats[S_T_ADD] += 1


@njit(cache=True, nogil=True)
def window_pass(keys, vals, density, origin, spacing, removed,
                 vmap, pos, vijk, valive, vrec, vfree, trec, tfree, cnt, stats,
                 sf32, si32, su8, su64):
    """The update on dense copies of the window around ``removed`` (see
    above; at least one voxel, coordinates checked by the caller, a window
    at most ``WINDOW_DEPTH`` deep along k).

    Adds its counts to ``stats``. Returns 0 when done, 1 when the vertex /
    triangle arrays are too small (``stats[S_NEED_V]``, ``stats[S_NEED_T]``
    extra slots needed), 2 when the scratch is too small (``stats[S_NEED_V]``
    voxels, ``stats[S_NEED_T]`` rows); then nothing changed.
    """
    nr = removed.shape[0]
    lo0 = hi0 = np.int64(removed[0, 0])
    lo1 = hi1 = np.int64(removed[0, 1])
    lo2 = hi2 = np.int64(removed[0, 2])
    for q in range(nr):
        lo0 = min(lo0, removed[q, 0])
        hi0 = max(hi0, removed[q, 0])
        lo1 = min(lo1, removed[q, 1])
        hi1 = max(hi1, removed[q, 1])
        lo2 = min(lo2, removed[q, 2])
        hi2 = max(hi2, removed[q, 2])
    wlo = np.empty(3, dtype=np.int64)
    wd = np.empty(3, dtype=np.int64)
    blo = np.empty(3, dtype=np.int64)
    bd = np.empty(3, dtype=np.int64)
    wlo[0] = lo0 - WINDOW_MARGIN
    wlo[1] = lo1 - WINDOW_MARGIN
    wlo[2] = lo2 - WINDOW_MARGIN
    wd[0] = hi0 - lo0 + 1 + 2 * WINDOW_MARGIN
    wd[1] = hi1 - lo1 + 1 + 2 * WINDOW_MARGIN
    wd[2] = hi2 - lo2 + 1 + 2 * WINDOW_MARGIN
    for a in range(3):
        blo[a] = wlo[a] >> BRICK_SHIFT
        bd[a] = ((wlo[a] + wd[a] - 1) >> BRICK_SHIFT) - blo[a] + 1
    w0 = wd[0] + 2 * _GUARD
    w1 = wd[1] + 2 * _GUARD
    nr_p = w0 * w1
    vol_p = nr_p * wd[2]
    nwb = bd[0] * bd[1] * bd[2]
    if sf32.shape[0] < vol_p or si32.shape[0] < 2 * vol_p + nwb or su8.shape[0] < 2 * vol_p \
            or su64.shape[0] < N_ROWSETS * nr_p:
        stats[S_NEED_V] = vol_p
        stats[S_NEED_T] = nr_p
        return 2
    ld = sf32
    lv = si32[:vol_p]
    clist = si32[vol_p:2 * vol_p]
    wbr = si32[2 * vol_p:2 * vol_p + nwb]
    lcode = su8[:vol_p]
    lact = su8[vol_p:2 * vol_p]
    s = 0
    for bi in range(blo[0], blo[0] + bd[0]):
        for bj in range(blo[1], blo[1] + bd[1]):
            for bk in range(blo[2], blo[2] + bd[2]):
                wbr[s] = find_brick(keys, vals, bi, bj, bk)
                s += 1

    # ---- plan (read-only) ----------------------------------------------------
    _fw_mark(removed, wlo, w1, su64, nr_p)
    _fw_need(su64, nr_p, w0, w1)
    _fw_gather(density, vmap, wbr, wlo, wd, blo, bd, ld, lv, su64, nr_p)
    _fw_dilate(su64, nr_p, w0, w1)
    nl, tbound, n_vadd, n_vdel, ncells = _fw_plan(su64, nr_p, wd, lcode, lact, clist)

    # ---- room? (triangles: bound, ignoring the ones that will be freed) ------
    v_room = cnt[V_NFREE] + (vijk.shape[0] - cnt[V_HW]) + n_vdel
    t_room = cnt[T_NFREE] + (trec.shape[0] - cnt[T_HW])
    if n_vadd > v_room or tbound > t_room:
        stats[S_NEED_V] = max(0, n_vadd - v_room)
        stats[S_NEED_T] = max(0, tbound - t_room)
        return 1

    # ---- edit ------------------------------------------------------------------
    stats[S_CELLS] += ncells
    na, n_dead = _fw_cells(clist, nl, wd, ld, lv, lcode, lact, su64, nr_p, trec, vrec, tfree,
                           cnt, stats)
    if _fw_unlink_dead(su64, nr_p, wd, lv, trec, vrec) != n_dead:
        stats[S_ERR] += 1
    _fw_vertices(su64, nr_p, wd, wlo, wbr, blo, bd, lv, origin, spacing, vmap, pos, vijk,
                 valive, vrec, vfree, cnt, stats)
    _fw_add(clist, na, wd, lv, lcode, lact, trec, vrec, tfree, cnt, stats)
    return 0
