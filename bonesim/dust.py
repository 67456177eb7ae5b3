"""Bone dust as an Eulerian density field on a growing hashed brick grid.

No particles: dust is an amount per cell of the bone grid's lattice (cell
``(i, j, k)`` is bone voxel ``(i, j, k)``, centre ``origin_mm + spacing_mm *
(i, j, k)`` [mm]), moved between face-adjacent cells by a few local rules.

Units and storage
-----------------
A cell's *density* is the dust it holds in *cells*: 1.0 (:data:`FULL`) means
the cell is packed full; its volume is ``density * spacing_mm**3`` [mm^3].
Removed bone becomes ``bulking`` cells of dust per removed voxel (loose chips
take more room than the solid bone they came from; see :class:`DustParams`).

Densities are stored in fixed point, as int32 multiples of ``1 / Q`` cells
(``Q = 2**20``). Every rule moves an integer amount from one cell to another,
so

* mass is conserved *exactly*: ``total == added - suctioned`` holds as an
  integer identity at all times (:meth:`DustGrid.totals_q`), not only up to
  rounding;
* scattering moves is order independent (integer addition commutes), so the
  result does not depend on the hash table's layout or the brick order.

A cell holds at most ``2**31 / Q = 2048`` cells of dust.

Grid
----
Cells are grouped in bricks of ``8**3`` like :mod:`bonesim.grid` (same
``pack_brick_key`` / ``voxel_offset`` layout), found through an
open-addressing table that *grows*: dust appears where bone is removed and
falls into empty space, so bricks are inserted at run time. Each brick keeps
the indices of its six face neighbours (``nbr``, -1 if absent), so the
kernels step across brick faces without hashing.

Allocation happens only in Python (:meth:`DustGrid._reserve`): the kernels
take bricks from a preallocated pool; when the pool is short, a stage of the
step kernel stops *before* changing anything and reports how many bricks it
needs, the wrapper recycles dead bricks (no dust, no dusty face neighbour)
or, if that is not enough, grows every array, and calls the kernel again
from the same stage.

Before each transport rule runs, every brick holding dust has its face
neighbours that touch the domain allocated (the halo), so a rule can always
write one cell further.

Domain
------
Dust lives in a box of cells ``[lo, hi)`` (``bounds_vox``; by default the
bone grid's volume ``[0, shape)``). A *wall* cell is one outside that box or
one holding bone (bone density > 0 in the bone grid passed to
:meth:`DustGrid.step`). Rules 1-2 never move dust into a wall, nor out of one
(dust added to a cell that is still bone stays put until the bone goes).

One step (:meth:`DustGrid.step`)
--------------------------------
Let ``g`` be the unit gravity vector; its *dominant axis* ``a*`` is the axis of
its largest component, and "down" is the neighbour along ``a*`` in the
direction of ``g``. A cell's *room* is ``1 - density`` (negative if overfull).
``dt`` is the step [s]. All amounts are in fixed point and every product is
rounded down (``floor(x * y)`` below means ``(x * y_fixed) >> 16`` with
``y`` in 16-bit fixed point).

1. **Gravity** (``settle_rate`` [cells/s]). With ``split_gravity`` (default)
   gravity is shared among the axes: axis ``a`` with ``|g_a| > 1e-6`` gets the
   weight ``w_a = |g_a| / sum_b |g_b|`` and the neighbour ``n_a = c +
   sign(g_a) e_a``; otherwise only the dominant axis is used, with weight 1.
   Each cell ``c`` sends along each of its axes

   ``f_a = floor(w_a * min(d(c), settle_rate * dt, room(n_a)))``

   into ``n_a`` unless either is a wall. A cell receives from at most one
   source per axis, each bounded by ``w_a * room``, so gravity never pushes a
   cell past full, and ``sum_a f_a <= d(c)``.
2. **Piling and spilling** (``spill_rate`` [1/s], ``repose`` [cells]). With
   ``k = min(spill_rate * dt, 0.2)``, a non-wall cell is a *source* if it is
   overfull (density > 1), or if it holds more than ``repose`` and is
   *supported*: the cell below is a wall or holds at least a full cell. A
   source sends to each non-wall lateral neighbour ``n`` (the four face
   neighbours perpendicular to ``a*``)

   ``f = min(floor(k * (d(c) - d(n) - repose)), floor(room(n) / 5))``

   when positive: dust runs down the slope of a pile until side-by-side cells
   differ by at most ``repose`` (0 levels the dust flat; larger values leave
   steeper piles), and spills over edges, to fall in the next step. An
   overfull source also pushes ``min(floor(k * (d(c) - 1)), floor(room(up) /
   5))`` into the non-wall cell above it (against ``a*``): a packed hole
   overflows upward and the dust spills over its rim. A cell receives from at
   most five sources (four sides and below), each bounded by a fifth of its
   room, and ``k <= 0.2`` keeps a source's outflow within ``d(c)``. (A fifth of
   a room under 5 fixed-point units rounds to 0, so an overfull cell walled in
   by cells that full can keep an excess of a few units, < 1e-4 cells.)
3. **Tool push** (``push_search`` [cells]). Every cell whose centre is
   strictly inside the tool sphere (distance < radius) is emptied into one
   cell just outside it, radially: the first cell, for ``t = 0 ..
   push_search - 1``, containing the point at distance ``radius + (t + 1/2)
   * spacing`` from the tool centre along the ray from the centre through the
   cell (straight up, ``-g``, for the centre cell), whose centre is not
   inside the sphere and that is not a wall. If there is none (the tool is
   buried in bone) the dust stays. The push may overfill its targets; rule 2
   of later steps sheds the excess.
4. **Suction** (``suction_rate`` [cells/s]). Every cell whose centre lies
   within the suction radius of the suction tip loses ``min(d, suction_rate
   * dt)``; the amount is counted (:attr:`DustGrid.suctioned_cells`).

Rules 1 and 2 are Jacobi updates: every flux is computed from the densities
at the start of the rule and applied to a second buffer. Rules 3 and 4 only
move dust out of cells they do not write into, so they work in place.

Cost
----
Rules 1-2 visit the bricks that hold dust (their fluxes reach into the face
neighbours); rules 3-4 visit the bricks under the tool and the suction tip.
Within a brick, each direction is one branch-free loop over the cells whose
neighbour lies in the same brick (it vectorizes) plus the 64 cells of the face
toward the neighbour brick.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .grid import (BRICK, BRICK_SHIFT, BRICK_VOXELS, _hash_slot, find_brick, gather_box,
                   pack_brick_key, voxel_offset)

#: Fixed-point units per full cell of dust.
Q_SHIFT = 20
Q = 1 << Q_SHIFT
#: A full cell [cells].
FULL = 1.0
_FULL_Q = Q
#: Fixed-point shift of the rule weights (gravity shares, spill fraction).
_W_SHIFT = 16
_W_ONE = 1 << _W_SHIFT
#: A fifth in fixed point (rounded down): the share of a cell's room that
#: each of its (at most five) spill sources may fill.
_ROOM_SHARE = _W_ONE // 5
#: Largest spill fraction per step (explicit-diffusion stability bound 1/5).
MAX_SPILL_FRACTION = 0.2
#: Largest fixed-point rate per step, to keep products inside int64.
_MAX_RATE_Q = 1 << 40
#: Gravity components smaller than this do not move dust.
_MIN_GRAVITY_COMPONENT = 1e-6

# counters (int64 array ``ctr``)
(C_NFREE, C_HW, C_CUR, C_ADDED, C_SUCKED, C_NEED, C_NALIVE, C_PUSHED,
 C_SUCKED_STEP) = range(9)
_N_CTR = 9
# integer step parameters (int64 array ``ip``)
(I_RATE, I_KQ, I_REPOSE, I_NG, I_DOM, I_DSGN, I_LAT0, I_LAT1, I_SEARCH,
 I_SRATE, I_TOOL, I_SUCTION, I_GAX, I_GSG, I_GWQ) = (0, 1, 2, 3, 4, 5, 6, 7, 8,
                                                      9, 10, 11, 12, 15, 18)
_N_IP = 21
# float step parameters (float64 array ``fp``)
(F_TX, F_TY, F_TZ, F_TR, F_SX, F_SY, F_SZ, F_SR, F_OX, F_OY, F_OZ, F_H,
 F_UX, F_UY, F_UZ) = range(15)
_N_FP = 15
# step stages (a kernel that runs out of bricks returns the stage to resume)
STAGE_GRAVITY, STAGE_SPILL, STAGE_TOOL, STAGE_SUCTION, STAGE_DONE = range(5)


@dataclass(frozen=True)
class DustParams:
    """Constants of the dust model.

    Attributes
    ----------
    bulking : float
        Dust volume per volume of bone removed [-]: one removed voxel becomes
        ``bulking`` cells of dust. Drilled bone leaves chips and powder that
        pack loosely (roughly 35-45 % voids), so 1.6 by default.
    settle_rate : float
        Most dust that gravity moves across one cell face per second
        [cells/s].
    spill_rate : float
        Fraction of the excess density difference a supported cell passes to
        a lateral neighbour per second [1/s] (at most 0.2 per step).
    repose : float
        Density difference between side-by-side cells that stands without
        spilling [cells], in ``[0, 1)``: the steepness of piles.
    suction_rate : float
        Default suction rate: dust removed per second from each cell within
        the suction radius [cells/s].
    push_search : int
        How many cells beyond the tool surface the push looks for a free
        cell [cells].
    split_gravity : bool
        Share gravity among the axes by the components of ``g`` (True), or
        move dust along the dominant axis only (False).
    sprite_threshold : float
        Cells with more dust than this are rendered [cells].
    initial_bricks : int
        Size of the brick pool at construction (it grows as needed).
    """

    bulking: float = 1.6
    settle_rate: float = 40.0
    spill_rate: float = 40.0
    repose: float = 0.5
    suction_rate: float = 200.0
    push_search: int = 3
    split_gravity: bool = True
    sprite_threshold: float = 0.02
    initial_bricks: int = 64

    def __post_init__(self):
        for name in ("bulking", "settle_rate", "spill_rate", "suction_rate",
                     "sprite_threshold"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"DustParams.{name} must be finite and >= 0, got {v}")
        if not (0.0 <= self.repose < 1.0):
            raise ValueError(f"DustParams.repose must lie in [0, 1), got {self.repose}")
        if int(self.push_search) != self.push_search or self.push_search < 1:
            raise ValueError(f"DustParams.push_search must be a positive integer, "
                             f"got {self.push_search}")
        if int(self.initial_bricks) != self.initial_bricks or self.initial_bricks < 1:
            raise ValueError("DustParams.initial_bricks must be a positive integer")


# ====================================================================== table
@njit(cache=True, nogil=True)
def _table_insert(keys, vals, key, b):
    mask = keys.shape[0] - 1
    s = _hash_slot(key, mask)
    while keys[s] != -1:
        s = (s + 1) & mask
    keys[s] = key
    vals[s] = b


@njit(cache=True, nogil=True)
def _table_remove(keys, vals, key):
    """Delete ``key`` (which must be present) by backward-shift deletion."""
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


@njit(cache=True, nogil=True)
def _rehash(keys, vals, bcoord, alive, hw):
    for b in range(hw):
        if alive[b]:
            _table_insert(keys, vals,
                          pack_brick_key(bcoord[b, 0], bcoord[b, 1], bcoord[b, 2]), b)


@njit(cache=True, nogil=True, inline="always")
def _brick_in_domain(bi, bj, bk, bounds):
    return ((bi << BRICK_SHIFT) < bounds[3] and (bi << BRICK_SHIFT) + BRICK > bounds[0]
            and (bj << BRICK_SHIFT) < bounds[4] and (bj << BRICK_SHIFT) + BRICK > bounds[1]
            and (bk << BRICK_SHIFT) < bounds[5] and (bk << BRICK_SHIFT) + BRICK > bounds[2])


@njit(cache=True, nogil=True)
def _insert_brick(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                  bkeys, bvals, bi, bj, bk):
    """Take a brick from the pool for ``(bi, bj, bk)`` (absent; pool not empty),
    zero it in both buffers, link its face neighbours and its bone brick."""
    n = ctr[C_NFREE] - 1
    b = free[n]
    ctr[C_NFREE] = n
    if b + 1 > ctr[C_HW]:
        ctr[C_HW] = b + 1
    ctr[C_NALIVE] += 1
    _table_insert(keys, vals, pack_brick_key(bi, bj, bk), b)
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
def _ensure_bricks(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
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
            _insert_brick(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                          bkeys, bvals, coords[q, 0], coords[q, 1], coords[q, 2])
    return 0


@njit(cache=True, nogil=True)
def _recycle(keys, vals, bcoord, nbr, alive, bmass, free, ctr):
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
        _table_remove(keys, vals, pack_brick_key(bcoord[b, 0], bcoord[b, 1], bcoord[b, 2]))
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
def _refresh_bone_bricks(bcoord, alive, hw, bkeys, bvals, bone_b):
    for b in range(hw):
        if alive[b]:
            bone_b[b] = find_brick(bkeys, bvals, bcoord[b, 0], bcoord[b, 1], bcoord[b, 2])


# ================================================================ step rules
@njit(cache=True, nogil=True)
def _collect_active(alive, bmass, hw, active):
    n = 0
    for b in range(hw):
        if alive[b] and bmass[b] != 0:
            active[n] = b
            n += 1
    return n


@njit(cache=True, nogil=True)
def _halo(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr, bkeys, bvals,
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
            if _brick_in_domain(ni, nj, nk, bounds):
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
            if _brick_in_domain(ni, nj, nk, bounds):
                _insert_brick(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free,
                              ctr, bkeys, bvals, ni, nj, nk)
    return 0


# Per-brick neighbourhood scratch ``sc`` (int64): for face direction ``dd``
# (-x, +x, -y, +y, -z, +z): ``sc[dd]`` the neighbour brick, ``sc[6 + dd]`` its
# bone brick, ``sc[12 + dd]`` 1 if the cells across that face may take dust
# (brick allocated, face inside the domain); ``sc[18]`` the brick's own bone
# brick, ``sc[19]`` 1 if the whole brick lies in the domain, ``sc[20 + a]`` its
# first cell along axis ``a``.
#
# The rules work brick by brick: a wall mask of the brick (outside the domain
# or bone), then for each direction the fluxes between cells of the brick in
# branch-free loops over the 512 cells (so that they vectorize), and the 64
# cells of the face toward the neighbour brick one by one. The hot loops take
# no array argument of an inlined helper (that costs reference counting per
# call).
_SC_SIZE = 24


@njit(cache=True, nogil=True)
def _load_brick(b, nbr, bone_b, bcoord, bounds, bone_dens, sc, wall):
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
    if bb >= 0:
        bd = bone_dens[bb]
        for off in range(BRICK_VOXELS):
            wall[off] = bd[off] > 0.0
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
    room = _FULL_Q - dn
    m = d if d < rate else rate
    if room < m:
        m = room
    return (w * m) >> _W_SHIFT


@njit(cache=True, nogil=True, inline="always")
def _spill_flux(excess, dn, kq):
    r5 = ((_FULL_Q - dn) * _ROOM_SHARE) >> _W_SHIFT
    f = (excess * kq) >> _W_SHIFT
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
def _gravity(src, dst, nbr, bcoord, bone_b, bone_dens, active, n_active, bounds, ip,
             bmass, sc, wall, flux):
    """Rule 1 (Jacobi, ``src`` -> ``dst``; ``dst`` holds a copy of ``src``)."""
    rate = ip[I_RATE]
    ng = ip[I_NG]
    if rate <= 0:
        return
    for t in range(n_active):
        b = np.int64(active[t])
        _load_brick(b, nbr, bone_b, bcoord, bounds, bone_dens, sc, wall)
        srow = src[b]
        drow = dst[b]
        lo_d = np.int64(_FULL_Q)
        for off in range(BRICK_VOXELS):
            lo_d = min(lo_d, np.int64(srow[off]))
        inner = lo_d < _FULL_Q            # else no cell of the brick has room
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
                    if wall[off] or (bbn >= 0 and bone_dens[bbn, noff] > 0.0):
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
def _spill(src, dst, nbr, bcoord, bone_b, bone_dens, active, n_active, bounds, ip, bmass,
           sc, wall, elig, flux):
    """Rule 2 (Jacobi, ``src`` -> ``dst``; ``dst`` holds a copy of ``src``)."""
    kq = ip[I_KQ]
    repose = ip[I_REPOSE]
    dom = ip[I_DOM]
    dsgn = ip[I_DSGN]
    if kq <= 0:
        return
    for t in range(n_active):
        b = np.int64(active[t])
        _load_brick(b, nbr, bone_b, bcoord, bounds, bone_dens, sc, wall)
        srow = src[b]
        drow = dst[b]
        # eligible sources: above the repose, not in a wall, and overfull or
        # supported (the cell below is a wall or full)
        lo_d = np.int64(_FULL_Q)
        hi_d = np.int64(0)
        for off in range(BRICK_VOXELS):
            v = np.int64(srow[off])
            elig[off] = (v > _FULL_Q) & (wall[off] == 0)
            lo_d = min(lo_d, v)
            hi_d = max(hi_d, v)
        delta, edge, sh, o0, o1 = _dir_geometry(dom, dsgn)
        ss = srow[o0:o1]
        sn = srow[o0 + delta:o1 + delta]
        ws = wall[o0:o1]
        wn = wall[o0 + delta:o1 + delta]
        el = elig[o0:o1]
        for i in range(el.shape[0]):
            sup = (wn[i] != 0) | (sn[i] >= _FULL_Q)
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
                if okx == 0 or (bbn >= 0 and bone_dens[bbn, noff] > 0.0) \
                        or src[nb, noff] >= _FULL_Q:
                    elig[off] = 1
        n_elig = 0
        for off in range(BRICK_VOXELS):
            n_elig += elig[off]
        if n_elig == 0:
            continue
        # nothing overfull and no difference above the repose: no flux between
        # cells of this brick (only across its faces)
        inner = hi_d > _FULL_Q or hi_d - lo_d > repose
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
                    excess = d - dn - repose if lateral else d - _FULL_Q
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
                    if bbn >= 0 and bone_dens[bbn, noff] > 0.0:
                        continue
                    d = np.int64(srow[off])
                    dn = np.int64(src[nb, noff])
                    excess = d - dn - repose if lateral else d - _FULL_Q
                    f = _spill_flux(excess, dn, kq)
                    if f > 0:
                        drow[off] -= f
                        dst[nb, noff] += f
                        moved += f
            bmass[b] -= moved
            bmass[nb] += moved


@njit(cache=True, nogil=True)
def _jacobi(rule, keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
            bkeys, bvals, bone_dens, active, bounds, ip, sc, wall, elig, flux):
    """Run rule 1 (``rule == 0``) or 2 as a Jacobi update of the current buffer.

    Returns 0, or (changing nothing) the bricks the halo needs."""
    n_active = _collect_active(alive, bmass, ctr[C_HW], active)
    need = _halo(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr, bkeys,
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
        _gravity(src, dst, nbr, bcoord, bone_b, bone_dens, active, n_active, bounds, ip,
                 bmass, sc, wall, flux)
    else:
        _spill(src, dst, nbr, bcoord, bone_b, bone_dens, active, n_active, bounds, ip,
               bmass, sc, wall, elig, flux)
    # keep "no dust => zero in both buffers": bricks emptied by the rule
    for t in range(n_active):
        b = active[t]
        if bmass[b] == 0:
            for o in range(BRICK_VOXELS):
                src[b, o] = 0
    ctr[C_CUR] = 1 - cur
    return 0


@njit(cache=True, nogil=True, inline="always")
def _cell_range(c, r, o, h):
    """Cells whose centres may lie within ``r`` of ``c`` along one axis."""
    return (int(math.floor((c - r - o) / h)) - 1, int(math.floor((c + r - o) / h)) + 2)


@njit(cache=True, nogil=True, inline="always")
def _cell_ok(ci, cj, ck, lo0, lo1, lo2, hi0, hi1, hi2):
    return lo0 <= ci < hi0 and lo1 <= cj < hi1 and lo2 <= ck < hi2


@njit(cache=True, nogil=True)
def _bone_at(bkeys, bvals, bone_dens, i, j, k):
    bb = find_brick(bkeys, bvals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
    return bb >= 0 and bone_dens[bb, voxel_offset(i, j, k)] > 0.0


@njit(cache=True, nogil=True)
def _push_target(ci, cj, ck, fp, search, bounds, bkeys, bvals, bone_dens):
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
        if _bone_at(bkeys, bvals, bone_dens, ti, tj, tk):
            continue
        return True, ti, tj, tk
    return False, 0, 0, 0


@njit(cache=True, nogil=True)
def _tool_push(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
               bkeys, bvals, bone_dens, bounds, ip, fp):
    """Rule 3, in place on the current buffer.

    Returns 0, or (changing nothing) an upper bound on the bricks needed for
    push targets."""
    rad = fp[F_TR]
    ctr[C_PUSHED] = 0
    if ip[I_TOOL] == 0 or rad <= 0.0:
        return 0
    h = fp[F_H]
    r2 = rad * rad
    search = ip[I_SEARCH]
    i0, i1 = _cell_range(fp[F_TX], rad, fp[F_OX], h)
    j0, j1 = _cell_range(fp[F_TY], rad, fp[F_OY], h)
    k0, k1 = _cell_range(fp[F_TZ], rad, fp[F_OZ], h)
    cur = ctr[C_CUR]
    den = dens[cur]
    oth = dens[1 - cur]
    # pass 0: count missing target bricks, pass 1: allocate them, pass 2: move
    need = 0
    for mode in range(3):
        if mode == 1 and need == 0:
            continue                      # every target brick exists
        need = 0
        for bi in range(i0 >> BRICK_SHIFT, ((i1 - 1) >> BRICK_SHIFT) + 1):
            for bj in range(j0 >> BRICK_SHIFT, ((j1 - 1) >> BRICK_SHIFT) + 1):
                for bk in range(k0 >> BRICK_SHIFT, ((k1 - 1) >> BRICK_SHIFT) + 1):
                    b = find_brick(keys, vals, bi, bj, bk)
                    if b < 0 or bmass[b] == 0:
                        continue
                    for x in range(BRICK):
                        ci = (bi << BRICK_SHIFT) + x
                        if ci < i0 or ci >= i1:
                            continue
                        dx = (fp[F_OX] + h * ci) - fp[F_TX]
                        for y in range(BRICK):
                            cj = (bj << BRICK_SHIFT) + y
                            if cj < j0 or cj >= j1:
                                continue
                            dy = (fp[F_OY] + h * cj) - fp[F_TY]
                            for z in range(BRICK):
                                ck = (bk << BRICK_SHIFT) + z
                                if ck < k0 or ck >= k1:
                                    continue
                                off = (x << 6) | (y << 3) | z
                                d = np.int64(den[b, off])
                                if d <= 0:
                                    continue
                                dz = (fp[F_OZ] + h * ck) - fp[F_TZ]
                                if dx * dx + dy * dy + dz * dz >= r2:
                                    continue
                                ok, ti, tj, tk = _push_target(ci, cj, ck, fp, search,
                                                              bounds, bkeys, bvals,
                                                              bone_dens)
                                if not ok:
                                    continue
                                tb = find_brick(keys, vals, ti >> BRICK_SHIFT,
                                                tj >> BRICK_SHIFT, tk >> BRICK_SHIFT)
                                if mode == 0:
                                    if tb < 0:
                                        need += 1
                                elif mode == 1:
                                    if tb < 0:
                                        _insert_brick(keys, vals, bcoord, nbr, alive, dens,
                                                      bmass, bone_b, free, ctr, bkeys,
                                                      bvals, ti >> BRICK_SHIFT,
                                                      tj >> BRICK_SHIFT, tk >> BRICK_SHIFT)
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


@njit(cache=True, nogil=True)
def _suction(keys, vals, dens, bmass, ctr, ip, fp):
    """Rule 4, in place on the current buffer."""
    ctr[C_SUCKED_STEP] = 0
    rad = fp[F_SR]
    rate = ip[I_SRATE]
    if ip[I_SUCTION] == 0 or rad <= 0.0 or rate <= 0:
        return
    h = fp[F_H]
    r2 = rad * rad
    i0, i1 = _cell_range(fp[F_SX], rad, fp[F_OX], h)
    j0, j1 = _cell_range(fp[F_SY], rad, fp[F_OY], h)
    k0, k1 = _cell_range(fp[F_SZ], rad, fp[F_OZ], h)
    cur = ctr[C_CUR]
    den = dens[cur]
    oth = dens[1 - cur]
    total = np.int64(0)
    for bi in range(i0 >> BRICK_SHIFT, ((i1 - 1) >> BRICK_SHIFT) + 1):
        for bj in range(j0 >> BRICK_SHIFT, ((j1 - 1) >> BRICK_SHIFT) + 1):
            for bk in range(k0 >> BRICK_SHIFT, ((k1 - 1) >> BRICK_SHIFT) + 1):
                b = find_brick(keys, vals, bi, bj, bk)
                if b < 0 or bmass[b] == 0:
                    continue
                for x in range(BRICK):
                    ci = (bi << BRICK_SHIFT) + x
                    if ci < i0 or ci >= i1:
                        continue
                    dx = (fp[F_OX] + h * ci) - fp[F_SX]
                    for y in range(BRICK):
                        cj = (bj << BRICK_SHIFT) + y
                        if cj < j0 or cj >= j1:
                            continue
                        dy = (fp[F_OY] + h * cj) - fp[F_SY]
                        for z in range(BRICK):
                            ck = (bk << BRICK_SHIFT) + z
                            if ck < k0 or ck >= k1:
                                continue
                            off = (x << 6) | (y << 3) | z
                            d = np.int64(den[b, off])
                            if d <= 0:
                                continue
                            dz = (fp[F_OZ] + h * ck) - fp[F_SZ]
                            if dx * dx + dy * dy + dz * dz > r2:
                                continue
                            f = d if d < rate else rate
                            den[b, off] = d - f
                            bmass[b] -= f
                            total += f
                if bmass[b] == 0:
                    for o in range(BRICK_VOXELS):
                        oth[b, o] = 0
    ctr[C_SUCKED] += total
    ctr[C_SUCKED_STEP] = total


@njit(cache=True, nogil=True)
def _step_kernel(stage, keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                 bkeys, bvals, bone_dens, active, bounds, ip, fp, sc, wall, elig, flux):
    """Rules 1-4 from ``stage`` on. Returns :data:`STAGE_DONE`, or the stage to
    resume at after the wrapper has made ``ctr[C_NEED]`` bricks available."""
    ctr[C_NEED] = 0
    if stage <= STAGE_GRAVITY:
        need = _jacobi(0, keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                       bkeys, bvals, bone_dens, active, bounds, ip, sc, wall, elig,
                       flux)
        if need:
            ctr[C_NEED] = need
            return STAGE_GRAVITY
    if stage <= STAGE_SPILL:
        need = _jacobi(1, keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                       bkeys, bvals, bone_dens, active, bounds, ip, sc, wall, elig,
                       flux)
        if need:
            ctr[C_NEED] = need
            return STAGE_SPILL
    if stage <= STAGE_TOOL:
        need = _tool_push(keys, vals, bcoord, nbr, alive, dens, bmass, bone_b, free, ctr,
                          bkeys, bvals, bone_dens, bounds, ip, fp)
        if need:
            ctr[C_NEED] = need
            return STAGE_TOOL
    _suction(keys, vals, dens, bmass, ctr, ip, fp)
    return STAGE_DONE


# ============================================================ add and output
@njit(cache=True, nogil=True)
def _add(keys, vals, dens, bmass, ctr, ijk, amount_q):
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
def _count_above(alive, bmass, hw, den, thr):
    n = 0
    for b in range(hw):
        if not alive[b] or bmass[b] == 0:
            continue
        for o in range(BRICK_VOXELS):
            if den[b, o] > thr:
                n += 1
    return n


@njit(cache=True, nogil=True)
def _fill_sprites(alive, bmass, hw, den, thr, bcoord, origin, h, pos, val):
    n = 0
    inv_q = 1.0 / _FULL_Q
    for b in range(hw):
        if not alive[b] or bmass[b] == 0:
            continue
        x0 = bcoord[b, 0] << BRICK_SHIFT
        y0 = bcoord[b, 1] << BRICK_SHIFT
        z0 = bcoord[b, 2] << BRICK_SHIFT
        for o in range(BRICK_VOXELS):
            v = den[b, o]
            if v > thr:
                pos[n, 0] = origin[0] + h * (x0 + (o >> 6))
                pos[n, 1] = origin[1] + h * (y0 + ((o >> 3) & 7))
                pos[n, 2] = origin[2] + h * (z0 + (o & 7))
                val[n] = v * inv_q
                n += 1
    return n


@njit(cache=True, nogil=True)
def _recount(alive, hw, den):
    t = np.int64(0)
    for b in range(hw):
        if alive[b]:
            for o in range(BRICK_VOXELS):
                t += den[b, o]
    return t


# ================================================================ python API
def _vec3(v, name) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {v!r}")
    return a


def _nonneg(v, name) -> float:
    v = float(v)
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be finite and >= 0, got {v}")
    return v


def _to_q(x: float) -> int:
    return int(min(round(x * Q), _MAX_RATE_Q))


class DustGrid:
    """Bone dust density on a growing hashed brick grid.

    Parameters
    ----------
    spacing_mm : float
        Cell edge, the bone grid's voxel edge [mm].
    origin_mm : (3,) float
        Case-frame centre of cell (0, 0, 0), the bone grid's origin [mm].
    gravity : (3,) float
        Direction of gravity in the case frame (normalised here).
    params : DustParams, optional
        Model constants (default :class:`DustParams()`).
    bounds_vox : ((3,) int, (3,) int), optional
        Domain ``[lo, hi)`` in cells; dust never moves outside it. Default:
        the volume ``[0, shape)`` of the bone grid first passed to
        :meth:`step`.

    Attributes
    ----------
    spacing_mm : float
        Cell edge [mm].
    origin_mm : (3,) float64
        Centre of cell (0, 0, 0) [mm].
    gravity : (3,) float64
        Unit gravity vector (case frame).
    bounds : (6,) int64
        Domain ``lo, hi`` [cells] (valid once set).
    keys, vals : (table,) int64 / int32
        Brick hash table (``-1`` empty), as in :mod:`bonesim.grid`.
    bcoord : (pool, 3) int32
        Brick coordinates of each pool slot.
    nbr : (pool, 6) int32
        Face neighbours ``-x, +x, -y, +y, -z, +z`` of each brick (-1 absent).
    dens : (2, pool, 512) int32
        The two density buffers, in units of ``1 / Q`` cells;
        ``dens[ctr[C_CUR]]`` is current.
    bmass : (pool,) int64
        Dust per brick [1/Q cells]; 0 means the brick is zero in both buffers.
    """

    def __init__(self, spacing_mm, origin_mm, gravity, params: DustParams | None = None,
                 *, bounds_vox=None):
        self.spacing_mm = _nonneg(spacing_mm, "spacing_mm")
        if not self.spacing_mm > 0:
            raise ValueError("spacing_mm must be positive")
        self.origin_mm = _vec3(origin_mm, "origin_mm")
        self.params = DustParams() if params is None else params
        if not isinstance(self.params, DustParams):
            raise TypeError("params must be a DustParams")
        self.bounds = np.zeros(6, dtype=np.int64)
        self._bounds_set = False
        if bounds_vox is not None:
            self.set_bounds(*bounds_vox)
        self._ip = np.zeros(_N_IP, dtype=np.int64)
        self._fp = np.zeros(_N_FP, dtype=np.float64)
        self._sc = np.zeros(_SC_SIZE, dtype=np.int64)
        self._wall = np.zeros(BRICK_VOXELS, dtype=np.uint8)
        self._elig = np.zeros(BRICK_VOXELS, dtype=np.uint8)
        self._flux = np.zeros(BRICK_VOXELS, dtype=np.int64)
        self.set_gravity(gravity)
        self._ctr = np.zeros(_N_CTR, dtype=np.int64)
        self._alloc(int(self.params.initial_bricks))
        self._no_bone = (np.full(16, -1, np.int64), np.full(16, -1, np.int32))
        self._bkeys, self._bvals = self._no_bone
        self._bone_src = None
        self._no_bone_dens = np.zeros((1, BRICK_VOXELS), np.float32)

    @classmethod
    def for_grid(cls, grid, gravity, params: DustParams | None = None) -> "DustGrid":
        """A dust grid on ``grid``'s lattice with the domain ``[0, grid.shape)``."""
        return cls(grid.spacing_mm, grid.origin_mm, gravity, params,
                   bounds_vox=((0, 0, 0), grid.shape))

    # ------------------------------------------------------------ settings
    def set_bounds(self, lo, hi) -> None:
        """Set the domain ``[lo, hi)`` [cells]."""
        lo = np.asarray(lo, dtype=np.int64).reshape(3)
        hi = np.asarray(hi, dtype=np.int64).reshape(3)
        if (hi <= lo).any() or (np.abs(np.concatenate([lo, hi])) >= (1 << 22)).any():
            raise ValueError(f"bad dust domain [{lo}, {hi})")
        self.bounds[:3] = lo
        self.bounds[3:] = hi
        self._bounds_set = True

    def set_gravity(self, gravity) -> None:
        """Set the gravity direction (case frame; any non-zero length)."""
        g = _vec3(gravity, "gravity")
        n = float(np.linalg.norm(g))
        if not n > 0:
            raise ValueError("gravity must be non-zero")
        g = g / n
        self.gravity = g
        ip = self._ip
        dom = int(np.argmax(np.abs(g)))
        ip[I_DOM] = dom
        ip[I_DSGN] = 1 if g[dom] > 0 else -1
        lat = [a for a in range(3) if a != dom]
        ip[I_LAT0], ip[I_LAT1] = lat
        axes = [a for a in range(3) if abs(g[a]) > _MIN_GRAVITY_COMPONENT] \
            if self.params.split_gravity else [dom]
        tot = sum(abs(g[a]) for a in axes)
        ip[I_NG] = len(axes)
        for q in range(3):
            ip[I_GAX + q] = ip[I_GSG + q] = ip[I_GWQ + q] = 0
        for q, a in enumerate(axes):
            ip[I_GAX + q] = a
            ip[I_GSG + q] = 1 if g[a] > 0 else -1
            ip[I_GWQ + q] = int(math.floor(abs(g[a]) / tot * _W_ONE)) if len(axes) > 1 \
                else _W_ONE
        self._fp[F_UX:F_UZ + 1] = -g

    # ------------------------------------------------------------ storage
    def _alloc(self, n: int) -> None:
        tcap = 16
        while tcap < 2 * n:
            tcap *= 2
        self.keys = np.full(tcap, -1, dtype=np.int64)
        self.vals = np.full(tcap, -1, dtype=np.int32)
        self.bcoord = np.zeros((n, 3), dtype=np.int32)
        self.nbr = np.full((n, 6), -1, dtype=np.int32)
        self.alive = np.zeros(n, dtype=np.uint8)
        self.dens = np.zeros((2, n, BRICK_VOXELS), dtype=np.int32)
        self.bmass = np.zeros(n, dtype=np.int64)
        self.bone_b = np.full(n, -1, dtype=np.int32)
        self.free = np.arange(n - 1, -1, -1, dtype=np.int32)      # pops 0, 1, 2, ...
        self._active = np.zeros(n, dtype=np.int32)
        self._ctr[C_NFREE] = n

    def _grow(self, need: int) -> None:
        """Enlarge the pool so that at least ``need`` bricks are free."""
        old = self.pool_size
        n = max(2 * old, old + need - int(self._ctr[C_NFREE]))
        tcap = 16
        while tcap < 2 * n:
            tcap *= 2
        hw = int(self._ctr[C_HW])
        keys = np.full(tcap, -1, dtype=np.int64)
        vals = np.full(tcap, -1, dtype=np.int32)
        _rehash(keys, vals, self.bcoord, self.alive, hw)
        self.keys, self.vals = keys, vals

        def grown(a, fill, axis=0):
            shape = list(a.shape)
            shape[axis] = n
            out = np.full(shape, fill, dtype=a.dtype)
            idx = [slice(None)] * a.ndim
            idx[axis] = slice(0, old)
            out[tuple(idx)] = a
            return out

        self.bcoord = grown(self.bcoord, 0)
        self.nbr = grown(self.nbr, -1)
        self.alive = grown(self.alive, 0)
        self.dens = grown(self.dens, 0, axis=1)
        self.bmass = grown(self.bmass, 0)
        self.bone_b = grown(self.bone_b, -1)
        nf = int(self._ctr[C_NFREE])
        free = np.zeros(n, dtype=np.int32)
        free[:n - old] = np.arange(n - 1, old - 1, -1, dtype=np.int32)
        free[n - old:n - old + nf] = self.free[:nf]                # old free slots first
        self.free = free
        self._ctr[C_NFREE] = nf + n - old
        self._active = np.zeros(n, dtype=np.int32)

    def _reserve(self, need: int) -> None:
        """Make ``need`` bricks free: recycle dead bricks, else grow."""
        if need <= self._ctr[C_NFREE]:
            return
        _recycle(self.keys, self.vals, self.bcoord, self.nbr, self.alive, self.bmass,
                 self.free, self._ctr)
        if need > self._ctr[C_NFREE]:
            self._grow(need)

    def recycle(self) -> int:
        """Return bricks without dust (and without dusty neighbours) to the pool;
        returns how many."""
        return int(_recycle(self.keys, self.vals, self.bcoord, self.nbr, self.alive,
                            self.bmass, self.free, self._ctr))

    def _use_bone(self, grid) -> None:
        """Point the per-brick bone-brick cache at ``grid`` (None: no bone)."""
        src = None if grid is None else grid.keys
        if src is self._bone_src:
            return
        if grid is not None:
            if abs(grid.spacing_mm - self.spacing_mm) > 1e-9 * self.spacing_mm or \
                    not np.allclose(grid.origin_mm, self.origin_mm, rtol=0, atol=1e-9):
                raise ValueError("the bone grid's lattice differs from the dust grid's "
                                 "(spacing_mm / origin_mm)")
            self._bkeys, self._bvals = grid.keys, grid.vals
        else:
            self._bkeys, self._bvals = self._no_bone
        self._bone_src = src
        _refresh_bone_bricks(self.bcoord, self.alive, int(self._ctr[C_HW]), self._bkeys,
                             self._bvals, self.bone_b)

    # ------------------------------------------------------------ queries
    @property
    def pool_size(self) -> int:
        """Bricks allocated in memory (alive or free)."""
        return int(self.bcoord.shape[0])

    @property
    def n_bricks(self) -> int:
        """Bricks in the table."""
        return int(self._ctr[C_NALIVE])

    @property
    def n_active_bricks(self) -> int:
        """Bricks holding dust."""
        return int(np.count_nonzero(self.bmass[:int(self._ctr[C_HW])]))

    @property
    def density_q(self) -> np.ndarray:
        """The current buffer (pool, 512) int32 [1/Q cells] (a view)."""
        return self.dens[int(self._ctr[C_CUR])]

    def totals_q(self) -> tuple[int, int, int]:
        """``(total, added, suctioned)`` dust [1/Q cells], exact integers;
        ``total == added - suctioned`` always."""
        hw = int(self._ctr[C_HW])
        return (int(self.bmass[:hw].sum()), int(self._ctr[C_ADDED]),
                int(self._ctr[C_SUCKED]))

    def recount_q(self) -> int:
        """Total dust summed cell by cell [1/Q cells] (checks the per-brick totals)."""
        return int(_recount(self.alive, int(self._ctr[C_HW]), self.density_q))

    @property
    def total_cells(self) -> float:
        """Dust present [cells] (times ``spacing_mm**3`` for mm^3)."""
        return self.totals_q()[0] / Q

    @property
    def added_cells(self) -> float:
        """Dust added so far [cells]."""
        return int(self._ctr[C_ADDED]) / Q

    @property
    def suctioned_cells(self) -> float:
        """Dust removed by suction so far [cells]."""
        return int(self._ctr[C_SUCKED]) / Q

    @property
    def last_pushed_cells(self) -> float:
        """Dust the tool pushed out of its sphere in the last step [cells]."""
        return int(self._ctr[C_PUSHED]) / Q

    def to_dense(self, lo=None, shape=None) -> np.ndarray:
        """Dense copy of a box of densities [cells] (float64, exact).

        Parameters
        ----------
        lo : (3,) int, optional
            First cell of the box (default the domain's ``lo``).
        shape : (3,) int, optional
            Box extent [cells] (default the domain's extent).
        """
        if lo is None or shape is None:
            if not self._bounds_set:
                raise ValueError("give lo and shape: the domain is not set yet")
        lo = self.bounds[:3] if lo is None else np.asarray(lo, dtype=np.int64).reshape(3)
        shape = tuple(self.bounds[3:] - self.bounds[:3]) if shape is None else shape
        out = np.zeros(tuple(int(s) for s in shape), dtype=np.int32)
        gather_box(self.keys, self.vals, self.density_q, out, *map(int, lo))
        return out.astype(np.float64) / Q

    def sprites(self, threshold: float | None = None):
        """Dusty cells for rendering as alpha-blended sprites.

        Parameters
        ----------
        threshold : float, optional
            Cells holding more than this are returned [cells] (default
            ``params.sprite_threshold``).

        Returns
        -------
        positions : (n, 3) float32
            Cell centres, case frame [mm].
        density : (n,) float32
            Dust per cell [cells] (1 full; may exceed 1 briefly where dust was
            just added or pushed): size/opacity of the sprite.
        """
        thr = self.params.sprite_threshold if threshold is None else \
            _nonneg(threshold, "threshold")
        tq = int(math.floor(thr * Q))
        hw = int(self._ctr[C_HW])
        den = self.density_q
        n = _count_above(self.alive, self.bmass, hw, den, tq)
        pos = np.empty((n, 3), dtype=np.float32)
        val = np.empty(n, dtype=np.float32)
        _fill_sprites(self.alive, self.bmass, hw, den, tq, self.bcoord, self.origin_mm,
                      self.spacing_mm, pos, val)
        return pos, val

    # ------------------------------------------------------------ updates
    def add_removed(self, ijk, amount=None) -> None:
        """Turn removed bone into dust in its cell.

        Parameters
        ----------
        ijk : (n, 3) int
            Removed voxels (e.g. the ``ijk`` column of the ``removed`` ring);
            repeats add up.
        amount : float or (n,) float, optional
            Dust per voxel [cells] (default ``params.bulking``), in [0, 64].
        """
        ijk = np.asarray(ijk)
        if ijk.size == 0:
            return
        if ijk.ndim != 2 or ijk.shape[1] != 3 or not np.issubdtype(ijk.dtype, np.integer):
            raise ValueError(f"ijk must be an (n, 3) integer array, got {ijk.shape} "
                             f"{ijk.dtype}")
        if np.abs(ijk).max() >= (1 << 22):
            raise ValueError("cell coordinates out of range")
        ijk = np.ascontiguousarray(ijk, dtype=np.int64)
        if self._bounds_set:
            lo, hi = self.bounds[:3], self.bounds[3:]
            if ((ijk < lo) | (ijk >= hi)).any():
                raise ValueError("dust added outside the domain")
        amt = self.params.bulking if amount is None else amount
        amt = np.broadcast_to(np.asarray(amt, dtype=np.float64), (len(ijk),))
        if not np.isfinite(amt).all() or (amt < 0).any() or (amt > 64).any():
            raise ValueError("amount must lie in [0, 64] cells per voxel")
        amount_q = np.round(amt * Q).astype(np.int64)
        coords = np.unique(ijk >> BRICK_SHIFT, axis=0)
        while True:
            need = _ensure_bricks(self.keys, self.vals, self.bcoord, self.nbr, self.alive,
                                  self.dens, self.bmass, self.bone_b, self.free, self._ctr,
                                  self._bkeys, self._bvals, coords)
            if not need:
                break
            self._reserve(int(need))
        _add(self.keys, self.vals, self.dens, self.bmass, self._ctr, ijk, amount_q)

    def drain(self, cursor, amount=None) -> int:
        """Add the dust of every removal a cursor on a ``removed`` ring has not
        seen yet (see :mod:`bonesim.events`); returns how many voxels."""
        rec = cursor.drain()
        self.add_removed(rec["ijk"], amount)
        return int(len(rec["ijk"]))

    def step(self, bone_grid, dt, tool_pos_mm=None, tool_radius_mm=0.0,
             suction_pos_mm=None, suction_radius_mm=0.0, suction_rate=None) -> float:
        """Advance the dust by ``dt``: gravity, spilling, tool push, suction.

        Parameters
        ----------
        bone_grid : bonesim.grid.Grid or None
            Current bone (cells with density > 0 are walls); same lattice.
            None: no bone.
        dt : float
            Step [s], >= 0.
        tool_pos_mm : (3,) float, optional
            Burr centre [mm]; no push if None.
        tool_radius_mm : float
            Burr radius [mm].
        suction_pos_mm : (3,) float, optional
            Suction tip [mm]; no suction if None.
        suction_radius_mm : float
            Suction reach [mm].
        suction_rate : float, optional
            Dust removed per second from each cell in reach [cells/s]
            (default ``params.suction_rate``).

        Returns
        -------
        float
            Dust removed by suction in this step [cells].
        """
        dt = _nonneg(dt, "dt")
        if not self._bounds_set:
            if bone_grid is None:
                raise ValueError("no domain: pass bounds_vox or a bone grid")
            self.set_bounds((0, 0, 0), bone_grid.shape)
        self._use_bone(bone_grid)
        bone_dens = self._no_bone_dens if bone_grid is None else bone_grid.density
        p = self.params
        ip, fp = self._ip, self._fp
        ip[I_RATE] = _to_q(p.settle_rate * dt)
        ip[I_KQ] = int(math.floor(min(p.spill_rate * dt, MAX_SPILL_FRACTION) * _W_ONE))
        ip[I_REPOSE] = _to_q(p.repose)
        ip[I_SEARCH] = int(p.push_search)
        rate = p.suction_rate if suction_rate is None else _nonneg(suction_rate,
                                                                  "suction_rate")
        ip[I_SRATE] = _to_q(rate * dt)
        ip[I_TOOL] = 0 if tool_pos_mm is None else 1
        if tool_pos_mm is not None:
            fp[F_TX:F_TZ + 1] = _vec3(tool_pos_mm, "tool_pos_mm")
            fp[F_TR] = _nonneg(tool_radius_mm, "tool_radius_mm")
        ip[I_SUCTION] = 0 if suction_pos_mm is None else 1
        if suction_pos_mm is not None:
            fp[F_SX:F_SZ + 1] = _vec3(suction_pos_mm, "suction_pos_mm")
            fp[F_SR] = _nonneg(suction_radius_mm, "suction_radius_mm")
        fp[F_OX:F_OZ + 1] = self.origin_mm
        fp[F_H] = self.spacing_mm
        stage = STAGE_GRAVITY
        while True:
            stage = _step_kernel(stage, self.keys, self.vals, self.bcoord, self.nbr,
                                 self.alive, self.dens, self.bmass, self.bone_b, self.free,
                                 self._ctr, self._bkeys, self._bvals, bone_dens,
                                 self._active, self.bounds, ip, fp, self._sc,
                                 self._wall, self._elig, self._flux)
            if stage == STAGE_DONE:
                break
            self._reserve(int(self._ctr[C_NEED]))
        return int(self._ctr[C_SUCKED_STEP]) / Q


def warmup() -> None:
    """Compile (or load from the cache) every kernel of this module.

    The step is compiled for a writable bone density array (the run's
    :class:`~bonesim.model.State` grid); a read-only one (e.g. the
    :class:`~bonesim.model.Model`'s initial grid) is another numba type and
    compiles its own specialization (~10 s) on first use.
    """
    from .grid import Grid

    lab = np.zeros((20, 20, 20), dtype=np.uint8)
    lab[:, :, :3] = 1
    for grid in (Grid.from_dense(lab, spacing_mm=0.5), None):
        dust = DustGrid(0.5, (0.0, 0.0, 0.0), (0.0, 0.0, -1.0),
                        DustParams(initial_bricks=1), bounds_vox=((0, 0, 0), (20, 20, 20)))
        dust.add_removed(np.array([[5, 5, 9], [9, 9, 9]], dtype=np.int32))
        for _ in range(3):
            dust.step(grid, 0.01, (2.5, 2.5, 4.5), 1.0, (4.5, 4.5, 4.5), 1.0)
        dust.sprites()
        dust.to_dense()
        dust.recount_q()
        dust.recycle()
