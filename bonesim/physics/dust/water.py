"""Irrigation water: pours from the irrigator, carries the wet dust, drains
down, pools, and is taken up by suction.

Extends :class:`bonesim.physics.dust.DustGrid` (its wet species is the dust
the water carries) with a third species on the same lattice: **water**
(``dust.water``, a :class:`DustGrid` holding cells of water in the same fixed
point, made by the first irrigated step). A cell holds at most one full cell
of water; water does not limit the dust's room nor the dust the water's
(water fills the pores of the dust). Walls are those of the dust (bone of
the bodies at the identity pose, the domain's faces).

Rules, run by :meth:`DustGrid.step` after the dry species' rules 1-4 and the
spray's wetting (rule 5), before the wet species' step; ``dt`` the step [s],
constants in :class:`~bonesim.physics.dust.params.DustParams`:

6. **Pouring** (``water_flow_mm3_s`` [mm^3/s], i.e. ``water_flow_mm3_s /
   spacing_mm**3`` cells/s). While irrigating, the cell of the
   irrigation tip (or, if that is bone, the first free cell above it, up to
   :data:`POUR_SEARCH` cells against gravity's dominant axis) gains
   ``min(flow * dt, room)`` of water, ``room`` = 1 - its water.
7. **Draining and pooling, carrying the dust** (``water_settle_rate``
   [cells/s], ``water_spread_rate`` [1/s]). Two Jacobi updates of the water,
   like rules 1-2 of the dust with the dominant axis of gravity only and no
   angle of repose: (a) each cell sends ``min(w, water_settle_rate * dt,
   room(below))`` to the free cell below; (b) each *supported* cell (below
   is a wall or holds a full cell of water) sends ``min(floor(k (w - w_n)),
   floor(room(n) / 5))`` to each free lateral neighbour ``n`` with less
   water, ``k = min(water_spread_rate * dt, 0.2)``. With every move of
   ``f`` water out of a cell holding ``w`` water and ``s`` wet dust, the
   dust ``floor(s f / w)`` goes along, up to the dust's room in the target
   (``1 - s_n``; a fifth of it in (b)) and to the dust still in the cell:
   the dust moves with the water and settles out where it cannot go on.
8. **Tool push and suction of water** (``water_suction_rate`` [cells/s]):
   rules 3 and 4 of the dust, applied to the water.
9. **Soaking** (``wetting_rate`` [cells/s]). Dry dust in a cell holding at
   least ``soak_water`` cells of water turns wet at ``wetting_rate``.

All moves are integer: ``total == added - suctioned`` holds exactly for the
water (:func:`water_totals_q`) as for the dust
(:meth:`DustGrid.totals_q`), and no rule makes an amount negative. The
kernels allocate nothing; bricks come from the species' pools as for the
dust (a kernel that needs more stops before changing anything).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numba import njit

from bonesim.engine.grid import BRICK, BRICK_SHIFT, BRICK_VOXELS, find_brick, voxel_offset
from bonesim.physics.dust.bricks import (FULL_Q, ROOM_SHARE, W_ONE, W_SHIFT, C_ADDED,
                                         C_CUR, C_HW, C_NEED, C_NFREE, C_SUCKED, C_SUCKED_STEP,
                                         C_WETTED, F_H, F_OX, F_OZ, F_SR, F_SX, F_SZ, F_TR,
                                         F_TX, F_TZ, I_DOM, I_DSGN, I_LAT0, I_LAT1, I_SRATE,
                                         I_SUCTION, I_TOOL, MAX_SPILL_FRACTION, Q,
                                         STAGE_DONE, STAGE_TOOL, brick_in_domain,
                                         insert_brick)
from bonesim.physics.dust.rules import (bone_at, collect_active, add_halo, load_brick,
                                        step_kernel)
from bonesim.physics.dust.sprites import DustSprites, gather_sprites

__all__ = ["POUR_SEARCH", "step_water", "water_totals_q", "water_cells", "water_sprites"]

#: Cells above a bone-filled tip cell that pouring looks for a free one [cells].
POUR_SEARCH = 8


# ================================================================ kernels
@njit(cache=True, nogil=True)
def _ensure_wet(bcoord, alive, bmass, hw, active, bounds, wkeys, wvals, wbcoord, wnbr,
                walive, wdens, wbmass, wbone_b, wfree, wctr, bkeys, bvals):
    """Allocate the wet-dust bricks at every water brick holding water and
    its in-domain face neighbours. Returns 0, or (allocating nothing) an
    upper bound on the bricks the wet species needs."""
    n = collect_active(alive, bmass, hw, active)
    for mode in range(2):
        need = 0
        for t in range(n):
            b = active[t]
            for d in range(7):
                bi, bj, bk = bcoord[b, 0], bcoord[b, 1], bcoord[b, 2]
                if d < 6:
                    s = 1 if d & 1 else -1
                    a = d >> 1
                    bi += s if a == 0 else 0
                    bj += s if a == 1 else 0
                    bk += s if a == 2 else 0
                if not brick_in_domain(bi, bj, bk, bounds):
                    continue
                if find_brick(wkeys, wvals, bi, bj, bk) >= 0:
                    continue
                if mode == 0:
                    need += 1
                else:
                    insert_brick(wkeys, wvals, wbcoord, wnbr, walive, wdens, wbmass,
                                  wbone_b, wfree, wctr, bkeys, bvals, bi, bj, bk)
        if mode == 0 and need > wctr[C_NFREE]:
            return need
    return 0


@njit(cache=True, nogil=True, inline="always")
def _across(off, d):
    """For the face neighbour ``d`` (-x, +x, -y, +y, -z, +z) of cell ``off``:
    whether it lies in the next brick, and its offset. (No array arguments:
    an inlined helper taking arrays costs reference counting per call.)"""
    a = d >> 1
    sh = 6 - 3 * a
    loc = (off >> sh) & 7
    if d & 1:
        if loc < BRICK - 1:
            return False, off + (1 << sh)
        return True, off - ((BRICK - 1) << sh)
    if loc > 0:
        return False, off - (1 << sh)
    return True, off + ((BRICK - 1) << sh)


@njit(cache=True, nogil=True)
def _carry(stage, bcoord, nbr, alive, dens, bmass, ctr, active, bone_b, wkeys, wvals, walive,
           wdens, wbmass, wctr, wactive, bounds, bone_dens, bone_body, wall_body, ip, rate,
           kq, wb, sc, wall):
    """Rule 7 (a) (``stage`` 0) or (b) as one Jacobi update of the water and
    the wet dust (``wb``: (7,) scratch for the wet bricks of a brick and its
    face neighbours; ``sc``, ``wall``: the scratch of :func:`load_brick`).
    The bricks must be allocated (halo, :func:`_ensure_wet`)."""
    n = collect_active(alive, bmass, ctr[C_HW], active)
    nw = collect_active(walive, wbmass, wctr[C_HW], wactive)
    cur = ctr[C_CUR]
    src = dens[cur]
    dst = dens[1 - cur]
    wcur = wctr[C_CUR]
    wsrc = wdens[wcur]
    wdst = wdens[1 - wcur]
    for t in range(n):
        b = active[t]
        for o in range(BRICK_VOXELS):
            dst[b, o] = src[b, o]
    for t in range(nw):
        b = wactive[t]
        for o in range(BRICK_VOXELS):
            wdst[b, o] = wsrc[b, o]
    dom = ip[I_DOM]
    down = 2 * dom + (1 if ip[I_DSGN] > 0 else 0)
    lat0, lat1 = ip[I_LAT0], ip[I_LAT1]
    for t in range(n):
        b = active[t]
        load_brick(b, nbr, bone_b, bcoord, bounds, bone_dens, bone_body, wall_body, sc, wall)
        wb[6] = find_brick(wkeys, wvals, bcoord[b, 0], bcoord[b, 1], bcoord[b, 2])
        for d in range(6):
            m = nbr[b, d]
            wb[d] = find_brick(wkeys, wvals, bcoord[m, 0], bcoord[m, 1], bcoord[m, 2]) \
                if m >= 0 else -1
        allw = wall_body.shape[0] == 0
        wself = wb[6]
        for off in range(BRICK_VOXELS):
            w = np.int64(src[b, off])
            if w <= 0:
                continue
            if stage == 1:
                # spreads only when supported: below a wall or a full cell of water
                far, noff = _across(off, down)
                if far:
                    nb = np.int64(nbr[b, down])
                    free = nb >= 0 and sc[12 + down] != 0
                    if free:
                        bbn = sc[6 + down]
                        free = not (bbn >= 0 and bone_dens[bbn, noff] > 0.0 and (
                            allw or wall_body[bone_body[bbn, noff]] != 0))
                else:
                    nb = b
                    free = wall[noff] == 0
                if free and src[nb, noff] < FULL_Q:
                    continue
            s = np.int64(wsrc[wself, off]) if wself >= 0 else np.int64(0)
            left = s
            for q in range(4 if stage == 1 else 1):
                if stage == 0:
                    d = down
                elif q < 2:
                    d = 2 * lat0 + q
                else:
                    d = 2 * lat1 + q - 2
                far, noff = _across(off, d)
                if far:
                    nb = np.int64(nbr[b, d])
                    if nb < 0 or sc[12 + d] == 0:
                        continue
                    bbn = sc[6 + d]
                    if bbn >= 0 and bone_dens[bbn, noff] > 0.0 and (
                            allw or wall_body[bone_body[bbn, noff]] != 0):
                        continue
                    wn_b = wb[d]
                else:
                    nb = b
                    if wall[noff] != 0:
                        continue
                    wn_b = wself
                wn = np.int64(src[nb, noff])
                if stage == 0:
                    f = min(w, rate, FULL_Q - wn)
                else:
                    if wn >= w:
                        continue
                    f = min(((w - wn) * kq) >> W_SHIFT,
                            ((FULL_Q - wn) * ROOM_SHARE) >> W_SHIFT)
                if f <= 0:
                    continue
                dst[b, off] -= f
                dst[nb, noff] += f
                bmass[b] -= f
                bmass[nb] += f
                if left > 0 and wn_b >= 0:
                    fd = (s * f) // w

                    # the dust goes as far as its room lets it (one source
                    # below, five at most beside): the rest settles out
                    room = FULL_Q - np.int64(wsrc[wn_b, noff])
                    if stage == 1:
                        room = (room * ROOM_SHARE) >> W_SHIFT
                    fd = min(fd, room, left)
                    if fd > 0:
                        left -= fd
                        wdst[wself, off] -= fd
                        wdst[wn_b, noff] += fd
                        wbmass[wself] -= fd
                        wbmass[wn_b] += fd
    # "no amount => zero in both buffers" for bricks the update emptied
    for t in range(n):
        b = active[t]
        if bmass[b] == 0:
            for o in range(BRICK_VOXELS):
                src[b, o] = 0
    for t in range(nw):
        b = wactive[t]
        if wbmass[b] == 0:
            for o in range(BRICK_VOXELS):
                wsrc[b, o] = 0
    ctr[C_CUR] = 1 - cur
    wctr[C_CUR] = 1 - wcur


@njit(cache=True, nogil=True)
def _soak(bcoord, alive, dens, bmass, ctr, active, min_q, rate, keys, vals, ddens, dbmass,
          dctr, wkeys, wvals, wdens, wbmass, wctr):
    """Rule 9, in place on the current buffers: dry dust turns wet in every
    cell with at least ``min_q`` water (wet bricks allocated)."""
    if rate <= 0:
        return
    n = collect_active(alive, bmass, ctr[C_HW], active)
    src = dens[ctr[C_CUR]]
    dcur = ddens[dctr[C_CUR]]
    doth = ddens[1 - dctr[C_CUR]]
    wcur = wdens[wctr[C_CUR]]
    for t in range(n):
        b = active[t]
        db = find_brick(keys, vals, bcoord[b, 0], bcoord[b, 1], bcoord[b, 2])
        if db < 0 or dbmass[db] == 0:
            continue
        wb = find_brick(wkeys, wvals, bcoord[b, 0], bcoord[b, 1], bcoord[b, 2])
        if wb < 0:           # water pushed beyond the bricks prepared for it
            continue
        for off in range(BRICK_VOXELS):
            if src[b, off] < min_q:
                continue
            d = np.int64(dcur[db, off])
            if d <= 0:
                continue
            f = d if d < rate else rate
            dcur[db, off] -= f
            dbmass[db] -= f
            wcur[wb, off] += f
            wbmass[wb] += f
            dctr[C_WETTED] += f
        if dbmass[db] == 0:
            for o in range(BRICK_VOXELS):
                doth[db, o] = 0


# ================================================================ python
def water_grid(dust):
    """The water species of ``dust``, made on first use."""
    if dust.water is None:
        p = dust.params
        wp = replace(p, settle_rate=p.water_settle_rate, spill_rate=p.water_spread_rate,
                     repose=0.0, suction_rate=p.water_suction_rate)
        w = type(dust)(dust.spacing_mm, dust.origin_mm, dust.gravity, wp, _wet_species=True)
        w.set_bounds(dust.bounds[:3], dust.bounds[3:])
        w.time_s = dust.time_s
        dust.water = w
    return dust.water


def _pour(dust, water, bone_grid, walls, pos_mm, dt) -> None:
    """Rule 6."""
    p = dust.params
    cell = np.floor((np.asarray(pos_mm, float) - dust.origin_mm) / dust.spacing_mm + 0.5)
    cell = cell.astype(np.int64)
    dom, dsgn = int(dust._ip[I_DOM]), int(dust._ip[I_DSGN])
    lo, hi = dust.bounds[:3], dust.bounds[3:]
    bkeys, bvals = water._bkeys, water._bvals
    dens = water._no_bone_dens if bone_grid is None else bone_grid.density
    for _ in range(POUR_SEARCH + 1):
        if ((cell < lo) | (cell >= hi)).any():
            return
        if not bone_at(bkeys, bvals, dens, walls[0], walls[1], *(int(c) for c in cell)):
            break
        cell[dom] -= dsgn
    else:
        return
    have = 0
    b = find_brick(water.keys, water.vals, *(int(c) >> BRICK_SHIFT for c in cell))
    if b >= 0:
        have = int(water.density_q[b, voxel_offset(*(int(c) for c in cell))])
    flow = p.water_flow_mm3_s / dust.spacing_mm ** 3          # [cells/s]
    amount = min(int(round(flow * dt * Q)), FULL_Q - have)
    if amount > 0:
        water._add_q(cell.reshape(1, 3), np.array([amount], np.int64))


def step_water(dust, bone_grid, walls, dt, irrigation_pos_mm, tool_pos_mm, tool_radius_mm,
               suction_pos_mm, suction_radius_mm) -> float:
    """Rules 6-9 of the module docstring on ``dust`` (called by
    :meth:`DustGrid.step`, after rule 5 and before the wet species' step).

    Parameters
    ----------
    dust : DustGrid
        The dry species (its ``wet`` and ``water`` are made as needed).
    bone_grid : Grid or None
        The bone (walls), as for the dust.
    walls : tuple
        ``(bone_body, wall_body)`` of :func:`bonesim.physics.dust.bodies.wall_arrays`.
    dt : float
        Step [s].
    irrigation_pos_mm : (3,) float or None
        Where the irrigation water pours [mm]; None: none pours.
    tool_pos_mm, tool_radius_mm, suction_pos_mm, suction_radius_mm
        As for :meth:`DustGrid.step`.

    Returns
    -------
    float
        Water taken by suction in this step [cells].
    """
    if irrigation_pos_mm is None and dust.water is None:
        return 0.0
    water = water_grid(dust)
    wet = dust._wet_grid()
    if not np.array_equal(water.gravity, dust.gravity):
        water.set_gravity(dust.gravity)
    if not np.array_equal(water.bounds, dust.bounds):
        water.set_bounds(dust.bounds[:3], dust.bounds[3:])
    p = water.params
    water._use_bone(bone_grid)
    wet._use_bone(bone_grid)
    bone_dens = water._no_bone_dens if bone_grid is None else bone_grid.density
    if irrigation_pos_mm is not None:
        _pour(dust, water, bone_grid, walls, irrigation_pos_mm, dt)
    rate = int(min(round(p.settle_rate * dt * Q), 1 << 40))
    kq = int(math.floor(min(p.spill_rate * dt, MAX_SPILL_FRACTION) * W_ONE))
    for stage in (0, 1):
        while True:            # water's halo, then the wet bricks under the water
            need = add_halo(water.keys, water.vals, water.bcoord, water.nbr, water.alive,
                         water.dens, water.bmass, water.bone_b, water.free, water._ctr,
                         water._bkeys, water._bvals, water._active,
                         collect_active(water.alive, water.bmass, water._ctr[C_HW],
                                         water._active), water.bounds)
            if need:
                water._reserve(int(need))
                continue
            need = _ensure_wet(water.bcoord, water.alive, water.bmass, water._ctr[C_HW],
                               water._active, water.bounds, wet.keys, wet.vals, wet.bcoord,
                               wet.nbr, wet.alive, wet.dens, wet.bmass, wet.bone_b, wet.free,
                               wet._ctr, wet._bkeys, wet._bvals)
            if need:
                wet._reserve(int(need))
                continue
            break
        if len(wet._active) < wet.pool_size:
            wet._active = np.zeros(wet.pool_size, np.int32)
        _carry(stage, water.bcoord, water.nbr, water.alive, water.dens, water.bmass,
               water._ctr, water._active, water.bone_b, wet.keys, wet.vals, wet.alive,
               wet.dens, wet.bmass, wet._ctr, wet._active, water.bounds, bone_dens, walls[0],
               walls[1], water._ip, rate, kq, _scratch(water), water._sc, water._wall)
    # rules 3-4 on the water (the dust's kernel from its tool stage on)
    _push_and_suck(water, bone_dens, walls, dt, tool_pos_mm, tool_radius_mm, suction_pos_mm,
                   suction_radius_mm)
    water.time_s = dust.time_s + dt
    # rule 9
    _soak(water.bcoord, water.alive, water.dens, water.bmass, water._ctr, water._active,
          int(round(p.soak_water * Q)), int(min(round(p.wetting_rate * dt * Q), 1 << 40)),
          dust.keys, dust.vals, dust.dens, dust.bmass, dust._ctr, wet.keys, wet.vals,
          wet.dens, wet.bmass, wet._ctr)
    return int(water._ctr[C_SUCKED_STEP]) / Q


def _push_and_suck(water, bone_dens, walls, dt, tool_pos_mm, tool_radius_mm, suction_pos_mm,
                   suction_radius_mm) -> None:
    """Rules 3-4 of the dust (:mod:`bonesim.physics.dust.grid`) on the water."""
    ip, fp = water._ip, water._fp
    ip[I_SRATE] = int(min(round(water.params.suction_rate * dt * Q), 1 << 40))
    ip[I_TOOL] = 0 if tool_pos_mm is None else 1
    if tool_pos_mm is not None:
        fp[F_TX:F_TZ + 1] = tool_pos_mm
        fp[F_TR] = float(tool_radius_mm)
    ip[I_SUCTION] = 0 if suction_pos_mm is None else 1
    if suction_pos_mm is not None:
        fp[F_SX:F_SZ + 1] = suction_pos_mm
        fp[F_SR] = float(suction_radius_mm)
    fp[F_OX:F_OZ + 1] = water.origin_mm
    fp[F_H] = water.spacing_mm
    water._sphere_scratch(fp[F_TR] if ip[I_TOOL] else 0.0, fp[F_SR] if ip[I_SUCTION] else 0.0)
    stage = STAGE_TOOL
    while True:
        stage = step_kernel(stage, water.keys, water.vals, water.bcoord, water.nbr, water.alive,
                             water.dens, water.bmass, water.bone_b, water.free, water._ctr,
                             water._bkeys, water._bvals, bone_dens, walls[0], walls[1],
                             water._active, water.bounds, ip, fp, water._sc, water._wall,
                             water._elig, water._flux, water._cells)
        if stage == STAGE_DONE:
            break
        water._reserve(int(water._ctr[C_NEED]))


def _scratch(water) -> np.ndarray:
    s = getattr(water, "_wb", None)
    if s is None:
        s = water._wb = np.zeros(7, np.int64)
    return s


def water_totals_q(dust) -> tuple[int, int, int]:
    """``(total, added, suctioned)`` water [1/Q cells], exact integers;
    ``total == added - suctioned`` always. Zeros before any irrigation."""
    w = dust.water
    if w is None:
        return 0, 0, 0
    return w._own_mass_q(), int(w._ctr[C_ADDED]), int(w._ctr[C_SUCKED])


def water_cells(dust) -> float:
    """Water present [cells] (times ``spacing_mm**3`` for mm^3)."""
    return water_totals_q(dust)[0] / Q


def water_sprites(dust, threshold: float | None = None) -> DustSprites:
    """The top layer of the water (pool surfaces and running water) for the
    view, as :meth:`DustGrid.sprites` lists dust (``wet`` all 0). Empty
    before any irrigation."""
    w = dust.water
    p = dust.params
    if w is None:
        z = np.zeros(0, np.float32)
        return DustSprites(np.zeros((0, 3), np.float32), z, float(dust.spacing_mm), z,
                           np.zeros(0, np.uint8))
    thr = p.sprite_threshold if threshold is None else float(threshold)
    return gather_sprites((w,), int(math.floor(thr * Q)), int(math.floor(p.sprite_cover * Q)),
                          int(dust._ip[I_DOM]), int(dust._ip[I_DSGN]), True,
                          float(dust.time_s), dust.origin_mm, dust.spacing_mm, 0.0)
