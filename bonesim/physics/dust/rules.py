"""Transport rules of :class:`bonesim.physics.dust.DustGrid` (numba kernels).

Gravity, piling and spilling, the tool's push, suction and irrigation's
wetting, plus adding dust, all as integer moves between cells in fixed point
(see :mod:`bonesim.physics.dust.grid` for the rules and their exact formulas, and
:mod:`bonesim.physics.dust.bricks` for the storage they work on).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.physics.dust.bricks import (FULL_Q, ROOM_SHARE, W_SHIFT, C_ADDED, C_CUR, C_HW, C_NEED,
                                         C_NFREE, C_PUSHED, C_SUCKED, C_SUCKED_STEP, C_WETTED, F_H, F_OX,
                                         F_OY, F_OZ, F_SR, F_SX, F_SY, F_SZ, F_TR, F_TX, F_TY, F_TZ, F_UX,
                                         F_UY, F_UZ, F_WR, F_WX, F_WY, F_WZ, I_DOM, I_DSGN, I_GAX, I_GSG,
                                         I_GWQ, I_KQ, I_LAT0, I_LAT1, I_NG, I_RATE, I_REPOSE, I_SEARCH,
                                         I_SRATE, I_SUCTION, I_TOOL, I_WRATE, STAGE_DONE, STAGE_GRAVITY,
                                         STAGE_SPILL, STAGE_TOOL, brick_in_domain, insert_brick)
from bonesim.engine.brick_hash import SC_BRICK, SC_I, SC_J, SC_K, SC_OFF, sphere_cells
from bonesim.engine.grid import BRICK, BRICK_SHIFT, BRICK_VOXELS, find_brick, voxel_offset

__all__ = []


# ================================================================ step rules
@njit(cache=True, nogil=True)
def collect_active(alive, bmass, hw, active):
    n = 0
    for b in range(hw):
        if alive[b] and bmass[b] != 0:
            active[n] = b
            n += 1
    return n


@njit(cache=True, nogil=True)
def add_halo(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr, bkeys, bvals,
          active, n_active, bounds):
    """Allocate the missing in-domain face neighbours of the active bricks.

    Returns 0, or (allocating nothing) an upper bound on the bricks needed."""
    need = 0
    for t in range(n_active):
        b = active[t]
        for d in range(6):
            if nbr[b, d] >= 0:
                continue
            a = d >> 1
            s = 1 if d & 1 else -1
            ni = bcoord[b, 0] + (s if a == 0 else 0)
            nj = bcoord[b, 1] + (s if a == 1 else 0)
            nk = bcoord[b, 2] + (s if a == 2 else 0)
            if brick_in_domain(ni, nj, nk, bounds):
                need += 1
    if need == 0:
        return 0
    if need > ctr[C_NFREE]:
        return need
    for t in range(n_active):
        b = active[t]
        for d in range(6):
            if nbr[b, d] >= 0:
                continue
            a = d >> 1
            s = 1 if d & 1 else -1
            ni = bcoord[b, 0] + (s if a == 0 else 0)
            nj = bcoord[b, 1] + (s if a == 1 else 0)
            nk = bcoord[b, 2] + (s if a == 2 else 0)
            if brick_in_domain(ni, nj, nk, bounds):
                insert_brick(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free,
                              ctr, bkeys, bvals, ni, nj, nk)
    return 0


# Per-brick neighbourhood scratch ``sc`` (int64): for face direction ``dd``
# (-x, +x, -y, +y, -z, +z): ``sc[dd]`` the neighbour brick, ``sc[6 + dd]`` its
# bone brick, ``sc[12 + dd]`` 1 if the cells across that face may take dust
# (brick allocated, face inside the domain); ``sc[18]`` the brick's own bone
# brick, ``sc[19]`` 1 if the whole brick lies in the domain, ``sc[20 + a]`` its
# first cell along axis ``a``.
#
# Bone cells are walls: cells with bone density > 0 whose body ``bone_body``
# (laid out like ``bone_dens``) has ``wall_body[body] != 0``; an empty
# ``wall_body`` makes every bone cell a wall without reading ``bone_body``
# (the one-body path, exactly as before bodies).
#
# The rules work brick by brick: a wall mask of the brick (outside the domain
# or bone), then for each direction the fluxes between cells of the brick in
# branch-free loops over the 512 cells (so that they vectorize), and the 64
# cells of the face toward the neighbour brick one by one. The hot loops take
# no array argument of an inlined helper (that costs reference counting per
# call).
SC_SIZE = 24


@njit(cache=True, nogil=True)
def load_brick(b, nbr, bone_b, bcoord, bounds, bone_dens, bone_body, wall_body, sc, wall):
    """Fill ``sc`` for brick ``b`` and its wall mask (1 = outside the domain or
    bone)."""
    inside = 1
    for a in range(3):
        base = np.int64(bcoord[b, a]) << BRICK_SHIFT
        sc[20 + a] = base
        if base < bounds[a] or base + BRICK > bounds[3 + a]:
            inside = 0
    sc[19] = inside
    bb = np.int64(bone_b[b])
    sc[18] = bb
    for dd in range(6):
        a = dd >> 1
        m = np.int64(nbr[b, dd])
        sc[dd] = m
        sc[6 + dd] = bone_b[m] if m >= 0 else -1
        c = sc[20 + a] + (BRICK if dd & 1 else -1)
        sc[12 + dd] = 1 if (m >= 0 and bounds[a] <= c < bounds[3 + a]) else 0
    if bb >= 0 and wall_body.shape[0] == 0:
        bd = bone_dens[bb]
        for off in range(BRICK_VOXELS):
            wall[off] = bd[off] > 0.0
    elif bb >= 0:
        bd = bone_dens[bb]
        bbody = bone_body[bb]
        for off in range(BRICK_VOXELS):
            wall[off] = (bd[off] > 0.0) & (wall_body[bbody[off]] != 0)
    else:
        for off in range(BRICK_VOXELS):
            wall[off] = 0
    if inside == 0:
        x0, y0, z0 = sc[20], sc[21], sc[22]
        for off in range(BRICK_VOXELS):
            if not (bounds[0] <= x0 + (off >> 6) < bounds[3]
                    and bounds[1] <= y0 + ((off >> 3) & 7) < bounds[4]
                    and bounds[2] <= z0 + (off & 7) < bounds[5]):
                wall[off] = 1


@njit(cache=True, nogil=True, inline="always")
def _dir_geometry(a, s):
    """For moves along axis ``a``, direction ``s``: offset step, the local
    coordinate of the cells on the far face, shift of that coordinate, and the
    range ``[o0, o1)`` of offsets whose in-brick neighbour stays in [0, 512)."""
    sh = 6 - 3 * a
    st = np.int64(1) << sh
    if s > 0:
        return st, np.int64(7), sh, np.int64(0), BRICK_VOXELS - st
    return -st, np.int64(0), sh, st, np.int64(BRICK_VOXELS)


@njit(cache=True, nogil=True, inline="always")
def _face_off(a, edge, u, v):
    """Offset of cell ``(u, v)`` of the brick face ``loc_a == edge``."""
    if a == 0:
        return (edge << 6) | (u << 3) | v
    if a == 1:
        return (u << 6) | (edge << 3) | v
    return (u << 6) | (v << 3) | edge


@njit(cache=True, nogil=True, inline="always")
def _gravity_flux(d, dn, rate, w):
    room = FULL_Q - dn
    m = d if d < rate else rate
    if room < m:
        m = room
    return (w * m) >> W_SHIFT


@njit(cache=True, nogil=True, inline="always")
def _spill_flux(excess, dn, kq):
    r5 = ((FULL_Q - dn) * ROOM_SHARE) >> W_SHIFT
    f = (excess * kq) >> W_SHIFT
    return f if f < r5 else r5


@njit(cache=True, nogil=True, inline="always")
def _apply_inside(drow, flux, o0, o1, delta):
    """Apply the in-brick fluxes ``flux[o0:o1]`` of one direction to ``drow``."""
    fl = flux[o0:o1]
    ds = drow[o0:o1]
    for q in range(fl.shape[0]):
        ds[q] -= fl[q]
    dn = drow[o0 + delta:o1 + delta]
    for q in range(fl.shape[0]):
        dn[q] += fl[q]


@njit(cache=True, nogil=True)
def _gravity(src, dst, nbr, bcoord, bone_b, bone_dens, bone_body, wall_body, active,
             n_active, bounds, ip, bmass, sc, wall, flux):
    """Rule 1 (Jacobi, ``src`` -> ``dst``; ``dst`` holds a copy of ``src``)."""
    allw = wall_body.shape[0] == 0
    rate = ip[I_RATE]
    ng = ip[I_NG]
    if rate <= 0:
        return
    for t in range(n_active):
        b = np.int64(active[t])
        load_brick(b, nbr, bone_b, bcoord, bounds, bone_dens, bone_body, wall_body, sc, wall)
        srow = src[b]
        drow = dst[b]
        lo_d = np.int64(FULL_Q)
        for off in range(BRICK_VOXELS):
            lo_d = min(lo_d, np.int64(srow[off]))
        inner = lo_d < FULL_Q            # else no cell of the brick has room
        for q in range(ng):
            a = ip[I_GAX + q]
            s = ip[I_GSG + q]
            w = ip[I_GWQ + q]
            delta, edge, sh, o0, o1 = _dir_geometry(a, s)
            if inner:
                # inside the brick: 1-D views indexed from 0, so that the loop
                # has no negative-index handling and vectorizes
                ss = srow[o0:o1]
                sn = srow[o0 + delta:o1 + delta]
                ws = wall[o0:o1]
                wn = wall[o0 + delta:o1 + delta]
                fl = flux[o0:o1]
                for i in range(fl.shape[0]):
                    f = _gravity_flux(np.int64(ss[i]), np.int64(sn[i]), rate, w)
                    ok = (f > 0) & ((((o0 + i) >> sh) & 7) != edge) & (ws[i] == 0) & \
                        (wn[i] == 0)
                    fl[i] = f if ok else 0
                _apply_inside(drow, flux, o0, o1, delta)
            # across the face
            dd = 2 * a + (1 if s > 0 else 0)
            if sc[12 + dd] == 0:
                continue
            nb = sc[dd]
            bbn = sc[6 + dd]
            moved = np.int64(0)
            for u in range(BRICK):
                for v in range(BRICK):
                    off = _face_off(a, edge, u, v)
                    noff = off - 7 * delta
                    if wall[off] or (bbn >= 0 and bone_dens[bbn, noff] > 0.0 and (
                            allw or wall_body[bone_body[bbn, noff]] != 0)):
                        continue
                    f = _gravity_flux(np.int64(srow[off]), np.int64(src[nb, noff]),
                                      rate, w)
                    if f > 0:
                        drow[off] -= f
                        dst[nb, noff] += f
                        moved += f
            bmass[b] -= moved
            bmass[nb] += moved


@njit(cache=True, nogil=True)
def _spill(src, dst, nbr, bcoord, bone_b, bone_dens, bone_body, wall_body, active,
           n_active, bounds, ip, bmass, sc, wall, elig, flux):
    """Rule 2 (Jacobi, ``src`` -> ``dst``; ``dst`` holds a copy of ``src``)."""
    allw = wall_body.shape[0] == 0
    kq = ip[I_KQ]
    repose = ip[I_REPOSE]
    dom = ip[I_DOM]
    dsgn = ip[I_DSGN]
    if kq <= 0:
        return
    for t in range(n_active):
        b = np.int64(active[t])
        load_brick(b, nbr, bone_b, bcoord, bounds, bone_dens, bone_body, wall_body, sc, wall)
        srow = src[b]
        drow = dst[b]
        # eligible sources: above the repose, not in a wall, and overfull or
        # supported (the cell below is a wall or full)
        lo_d = np.int64(FULL_Q)
        hi_d = np.int64(0)
        for off in range(BRICK_VOXELS):
            v = np.int64(srow[off])
            elig[off] = (v > FULL_Q) & (wall[off] == 0)
            lo_d = min(lo_d, v)
            hi_d = max(hi_d, v)
        delta, edge, sh, o0, o1 = _dir_geometry(dom, dsgn)
        ss = srow[o0:o1]
        sn = srow[o0 + delta:o1 + delta]
        ws = wall[o0:o1]
        wn = wall[o0 + delta:o1 + delta]
        el = elig[o0:o1]
        for i in range(el.shape[0]):
            sup = (wn[i] != 0) | (sn[i] >= FULL_Q)
            e = sup & (ss[i] > repose) & (ws[i] == 0) & ((((o0 + i) >> sh) & 7) != edge)
            el[i] = el[i] | e
        dd = 2 * dom + (1 if dsgn > 0 else 0)
        nb = sc[dd]
        bbn = sc[6 + dd]
        okx = sc[12 + dd]
        for u in range(BRICK):
            for v in range(BRICK):
                off = _face_off(dom, edge, u, v)
                noff = off - 7 * delta
                if wall[off] or srow[off] <= repose:
                    continue
                if okx == 0 or (bbn >= 0 and bone_dens[bbn, noff] > 0.0 and (
                        allw or wall_body[bone_body[bbn, noff]] != 0)) \
                        or src[nb, noff] >= FULL_Q:
                    elig[off] = 1
        n_elig = 0
        for off in range(BRICK_VOXELS):
            n_elig += elig[off]
        if n_elig == 0:
            continue
        # nothing overfull and no difference above the repose: no flux between
        # cells of this brick (only across its faces)
        inner = hi_d > FULL_Q or hi_d - lo_d > repose
        # four lateral directions, then up (overfull cells only)
        for q in range(5):
            lateral = q < 4
            if lateral:
                a = ip[I_LAT0] if q < 2 else ip[I_LAT1]
                s = np.int64(1) if q & 1 else np.int64(-1)
            else:
                a = dom
                s = -dsgn
            delta, edge, sh, o0, o1 = _dir_geometry(a, s)
            if inner:
                ss = srow[o0:o1]
                sn = srow[o0 + delta:o1 + delta]
                wn = wall[o0 + delta:o1 + delta]
                el = elig[o0:o1]
                fl = flux[o0:o1]
                for i in range(fl.shape[0]):
                    d = np.int64(ss[i])
                    dn = np.int64(sn[i])
                    excess = d - dn - repose if lateral else d - FULL_Q
                    f = _spill_flux(excess, dn, kq)
                    ok = (f > 0) & (el[i] != 0) & ((((o0 + i) >> sh) & 7) != edge) & \
                        (wn[i] == 0)
                    fl[i] = f if ok else 0
                _apply_inside(drow, flux, o0, o1, delta)
            dd = 2 * a + (1 if s > 0 else 0)
            if sc[12 + dd] == 0:
                continue
            nb = sc[dd]
            bbn = sc[6 + dd]
            moved = np.int64(0)
            for u in range(BRICK):
                for v in range(BRICK):
                    off = _face_off(a, edge, u, v)
                    if elig[off] == 0:
                        continue
                    noff = off - 7 * delta
                    if bbn >= 0 and bone_dens[bbn, noff] > 0.0 and \
                            (allw or wall_body[bone_body[bbn, noff]] != 0):
                        continue
                    d = np.int64(srow[off])
                    dn = np.int64(src[nb, noff])
                    excess = d - dn - repose if lateral else d - FULL_Q
                    f = _spill_flux(excess, dn, kq)
                    if f > 0:
                        drow[off] -= f
                        dst[nb, noff] += f
                        moved += f
            bmass[b] -= moved
            bmass[nb] += moved


@njit(cache=True, nogil=True)
def _jacobi(rule, keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
            bkeys, bvals, bone_dens, bone_body, wall_body, active, bounds, ip, sc, wall, elig,
            flux):
    """Run rule 1 (``rule == 0``) or 2 as a Jacobi update of the current buffer.

    Returns 0, or (changing nothing) the bricks the halo needs."""
    n_active = collect_active(alive, bmass, ctr[C_HW], active)
    need = add_halo(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr, bkeys,
                 bvals, active, n_active, bounds)
    if need:
        return need
    cur = ctr[C_CUR]
    src = dens[cur]
    dst = dens[1 - cur]
    # dst holds stale values only in bricks with dust (bricks without dust are
    # zero in both buffers): copy the active bricks
    for t in range(n_active):
        b = active[t]
        for o in range(BRICK_VOXELS):
            dst[b, o] = src[b, o]
    if rule == 0:
        _gravity(src, dst, nbr, bcoord, bone_b, bone_dens, bone_body, wall_body, active,
                 n_active, bounds, ip, bmass, sc, wall, flux)
    else:
        _spill(src, dst, nbr, bcoord, bone_b, bone_dens, bone_body, wall_body, active,
               n_active, bounds, ip, bmass, sc, wall, elig, flux)
    # keep "no dust => zero in both buffers": bricks emptied by the rule
    for t in range(n_active):
        b = active[t]
        if bmass[b] == 0:
            for o in range(BRICK_VOXELS):
                src[b, o] = 0
    ctr[C_CUR] = 1 - cur
    return 0


@njit(cache=True, nogil=True, inline="always")
def _cell_ok(ci, cj, ck, lo0, lo1, lo2, hi0, hi1, hi2):
    return lo0 <= ci < hi0 and lo1 <= cj < hi1 and lo2 <= ck < hi2


@njit(cache=True, nogil=True)
def bone_at(bkeys, bvals, bone_dens, bone_body, wall_body, i, j, k):
    bb = find_brick(bkeys, bvals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
    if bb < 0:
        return False
    off = voxel_offset(i, j, k)
    return bone_dens[bb, off] > 0.0 and (wall_body.shape[0] == 0
                                         or wall_body[bone_body[bb, off]] != 0)


@njit(cache=True, nogil=True)
def _push_target(ci, cj, ck, fp, search, bounds, bkeys, bvals, bone_dens, bone_body, wall_body):
    """Cell that the tool pushes the dust of cell ``(ci, cj, ck)`` into (rule
    3); ``ok`` False when no free cell lies within ``search`` cells."""
    px, py, pz, rad = fp[F_TX], fp[F_TY], fp[F_TZ], fp[F_TR]
    ox, oy, oz, h = fp[F_OX], fp[F_OY], fp[F_OZ], fp[F_H]
    dx = (ox + h * ci) - px
    dy = (oy + h * cj) - py
    dz = (oz + h * ck) - pz
    r = math.sqrt(dx * dx + dy * dy + dz * dz)
    if r > 0.0:
        ux, uy, uz = dx / r, dy / r, dz / r
    else:
        ux, uy, uz = fp[F_UX], fp[F_UY], fp[F_UZ]
    r2 = rad * rad
    for t in range(search):
        dist = rad + (t + 0.5) * h
        ti = int(math.floor((px + ux * dist - ox) / h + 0.5))
        tj = int(math.floor((py + uy * dist - oy) / h + 0.5))
        tk = int(math.floor((pz + uz * dist - oz) / h + 0.5))
        ex = (ox + h * ti) - px
        ey = (oy + h * tj) - py
        ez = (oz + h * tk) - pz
        if ex * ex + ey * ey + ez * ez < r2:
            continue
        if not _cell_ok(ti, tj, tk, bounds[0], bounds[1], bounds[2], bounds[3], bounds[4],
                        bounds[5]):
            continue
        if bone_at(bkeys, bvals, bone_dens, bone_body, wall_body, ti, tj, tk):
            continue
        return True, ti, tj, tk
    return False, 0, 0, 0


@njit(cache=True, nogil=True)
def _tool_push(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
               bkeys, bvals, bone_dens, bone_body, wall_body, bounds, ip, fp, cells):
    """Rule 3, in place on the current buffer.

    Returns 0, or (changing nothing) an upper bound on the bricks needed for
    push targets."""
    rad = fp[F_TR]
    ctr[C_PUSHED] = 0
    if ip[I_TOOL] == 0 or rad <= 0.0:
        return 0
    search = ip[I_SEARCH]
    m = sphere_cells(keys, vals, bmass, fp[F_TX], fp[F_TY], fp[F_TZ], rad, fp[F_OX],
                     fp[F_OY], fp[F_OZ], fp[F_H], False, cells)
    cur = ctr[C_CUR]
    den = dens[cur]
    oth = dens[1 - cur]
    # pass 0: count missing target bricks, pass 1: allocate them, pass 2: move.
    # Targets lie outside the sphere, so no pass moves dust into a listed cell.
    need = 0
    for mode in range(3):
        if mode == 1 and need == 0:
            continue                      # every target brick exists
        need = 0
        for q in range(m):
            b = cells[q, SC_BRICK]
            off = cells[q, SC_OFF]
            d = np.int64(den[b, off])
            if d <= 0:
                continue
            ok, ti, tj, tk = _push_target(cells[q, SC_I], cells[q, SC_J], cells[q, SC_K], fp,
                                          search, bounds, bkeys, bvals, bone_dens, bone_body,
                                          wall_body)
            if not ok:
                continue
            tb = find_brick(keys, vals, ti >> BRICK_SHIFT, tj >> BRICK_SHIFT, tk >> BRICK_SHIFT)
            if mode == 0:
                if tb < 0:
                    need += 1
            elif mode == 1:
                if tb < 0:
                    insert_brick(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free,
                                  ctr, bkeys, bvals, ti >> BRICK_SHIFT, tj >> BRICK_SHIFT,
                                  tk >> BRICK_SHIFT)
            else:
                toff = voxel_offset(ti, tj, tk)
                den[b, off] = 0
                den[tb, toff] += d
                ctr[C_PUSHED] += d
                if tb != b:
                    bmass[b] -= d
                    bmass[tb] += d
                    if bmass[b] == 0:
                        for o in range(BRICK_VOXELS):
                            oth[b, o] = 0
        if mode == 0 and need > ctr[C_NFREE]:
            return need
    return 0


@njit(cache=True, nogil=True, inline="always")
def _take_sphere(keys, vals, den, oth, bmass, cx, cy, cz, rad, fp, rate, cells, out_ijk, out_q):
    """Suction's and wetting's rule on the cells of a sphere (centre ``c``
    [mm], radius ``rad`` [mm], listed by :func:`sphere_cells` into ``cells``):
    every cell whose centre lies within ``rad`` loses ``min(d, rate)`` of its
    dust ``d``. A brick left empty has its other buffer cleared. With
    ``out_q`` of length > 0 the cells and amounts taken are listed in
    ``out_ijk`` / ``out_q`` (which must hold every cell of the sphere).

    Returns ``(total taken, cells listed)``."""
    m = sphere_cells(keys, vals, bmass, cx, cy, cz, rad, fp[F_OX], fp[F_OY], fp[F_OZ],
                     fp[F_H], True, cells)
    listing = out_q.shape[0] > 0
    total = np.int64(0)
    n = 0
    for q in range(m):
        b = cells[q, SC_BRICK]
        off = cells[q, SC_OFF]
        d = np.int64(den[b, off])
        if d > 0:
            f = d if d < rate else rate
            den[b, off] = d - f
            bmass[b] -= f
            total += f
            if listing:
                out_ijk[n, 0] = cells[q, SC_I]
                out_ijk[n, 1] = cells[q, SC_J]
                out_ijk[n, 2] = cells[q, SC_K]
                out_q[n] = f
                n += 1
        if (q == m - 1 or cells[q + 1, SC_BRICK] != b) and bmass[b] == 0:
            for o in range(BRICK_VOXELS):     # the brick's last listed cell
                oth[b, o] = 0
    return total, n


@njit(cache=True, nogil=True)
def _suction(keys, vals, dens, bmass, ctr, ip, fp, cells):
    """Rule 4, in place on the current buffer."""
    ctr[C_SUCKED_STEP] = 0
    rad = fp[F_SR]
    rate = ip[I_SRATE]
    if ip[I_SUCTION] == 0 or rad <= 0.0 or rate <= 0:
        return
    total, _ = _take_sphere(keys, vals, dens[ctr[C_CUR]], dens[1 - ctr[C_CUR]], bmass,
                            fp[F_SX], fp[F_SY], fp[F_SZ], rad, fp, rate, cells,
                            np.empty((0, 3), np.int64), np.empty(0, np.int64))  # no listing
    ctr[C_SUCKED] += total
    ctr[C_SUCKED_STEP] = total


@njit(cache=True, nogil=True)
def step_kernel(stage, keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                 bkeys, bvals, bone_dens, bone_body, wall_body, active, bounds, ip, fp, sc, wall,
                 elig, flux, cells):
    """Rules 1-4 from ``stage`` on. Returns :data:`STAGE_DONE`, or the stage to
    resume at after the wrapper has made ``ctr[C_NEED]`` bricks available.
    ``cells``: scratch of :func:`sphere_cells` for the tool and suction radii."""
    ctr[C_NEED] = 0
    if stage <= STAGE_GRAVITY:
        need = _jacobi(0, keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                       bkeys, bvals, bone_dens, bone_body, wall_body, active, bounds, ip, sc,
                       wall, elig, flux)
        if need:
            ctr[C_NEED] = need
            return STAGE_GRAVITY
    if stage <= STAGE_SPILL:
        need = _jacobi(1, keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                       bkeys, bvals, bone_dens, bone_body, wall_body, active, bounds, ip, sc,
                       wall, elig, flux)
        if need:
            ctr[C_NEED] = need
            return STAGE_SPILL
    if stage <= STAGE_TOOL:
        need = _tool_push(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                          bkeys, bvals, bone_dens, bone_body, wall_body, bounds, ip, fp, cells)
        if need:
            ctr[C_NEED] = need
            return STAGE_TOOL
    _suction(keys, vals, dens, bmass, ctr, ip, fp, cells)
    return STAGE_DONE


# ============================================================ add and output
@njit(cache=True, nogil=True)
def add_dust(keys, vals, dens, bmass, ctr, ijk, amount_q):
    """Add ``amount_q[q]`` units to cell ``ijk[q]`` (bricks allocated)."""
    cur = ctr[C_CUR]
    den = dens[cur]
    for q in range(ijk.shape[0]):
        i, j, k = ijk[q, 0], ijk[q, 1], ijk[q, 2]
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        a = amount_q[q]
        den[b, voxel_offset(i, j, k)] += a
        bmass[b] += a
        ctr[C_ADDED] += a


@njit(cache=True, nogil=True)
def recount(alive, hw, den):
    t = np.int64(0)
    for b in range(hw):
        if alive[b]:
            for o in range(BRICK_VOXELS):
                t += den[b, o]
    return t


@njit(cache=True, nogil=True)
def wet_out(keys, vals, dens, bmass, ctr, ip, fp, cells, out_ijk, out_q):
    """Rule 5 (wetting), in place on the current buffer: every cell whose
    centre lies within the irrigation radius of its centre loses
    ``min(d, wet_rate)``; the cells and amounts are written to ``out_ijk``
    (n, 3) / ``out_q`` (n,) for the wet species, and counted in
    ``ctr[C_WETTED]``. ``out`` must hold every cell of the sphere's box.

    Returns the number of cells written."""
    rad = fp[F_WR]
    rate = ip[I_WRATE]
    if rad <= 0.0 or rate <= 0:
        return 0
    total, n = _take_sphere(keys, vals, dens[ctr[C_CUR]], dens[1 - ctr[C_CUR]], bmass,
                            fp[F_WX], fp[F_WY], fp[F_WZ], rad, fp, rate, cells, out_ijk,
                            out_q)
    ctr[C_WETTED] += total
    return n
