"""The fixed-budget step's flush (:mod:`bonesim.engine.haptics_budget`):
a queued removal cell's dose applied to its voxels, and the queue flushed in
order within the step's removal budget.

A cell's voxels each lose ``dose x`` their material's removal factor; a
voxel reaching 0 is removed (a ``REMOVED`` tissue event, its label's loss
counted for injuries), one that keeps density is published to the touched
ring; the cell's occupancy and threshold are recounted. Only voxels of
bodies at the pose of the body whose pass gave the dose are touched. The
kernels allocate nothing and are deterministic.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from bonesim.engine.events import N_VALUE as _N_VALUE
from bonesim.engine.events import REMOVED as _EV_REMOVED
from bonesim.engine.grid import BRICK, BRICK_SHIFT, voxel_offset

__all__ = ["flush_cell", "flush_kernel"]


@njit(cache=True, nogil=True, inline="always")
def _same_pose(pose_m, a, b):
    if a == b:
        return True
    for r in range(3):
        for c in range(4):
            if pose_m[a, r, c] != pose_m[b, r, c]:
                return False
    return True


@njit(cache=True, nogil=True)
def flush_cell(b, cq, cell, cs, bricks, density, label, body, touched_flag, removal, pose_m,
               dose, thr, occ, rep, t, lost, lab_body, ev_kind, ev_body, ev_label, ev_t,
               ev_ijk, ev_n, ev_value, ev_head, tch_ijk, tch_head, counts):
    """Apply cell ``cq`` of brick ``b``'s dose to its voxels (see the module
    notes and :mod:`bonesim.engine.haptics_budget`'s); recount its occupancy
    and threshold. ``counts[0:2]`` += removed, newly touched."""
    amount = dose[b, cq]
    dose[b, cq] = 0.0
    owner = rep[b, cq]
    # the cell's place in its brick: ``cq = (ci n + cj) n + ck``, ``n = 8 >> cs``
    # a power of two (shifts, not divisions; ``cq >= 0``)
    ns = BRICK_SHIFT - cs
    ci = cq >> (2 * ns)
    cj = (cq >> ns) & ((1 << ns) - 1)
    ck = cq & ((1 << ns) - 1)
    i0 = bricks[b, 0] * BRICK + (ci << cs)
    j0 = bricks[b, 1] * BRICK + (cj << cs)
    k0 = bricks[b, 2] * BRICK + (ck << cs)
    tcap = tch_ijk.shape[0] - 1
    n_occ = 0
    t_min = np.inf
    n_rem = 0
    n_tch = 0
    # the cell lies in one brick: its voxels' offsets step from the first's
    # (unsigned: no negative-index wrapping)
    ub = np.uint64(b)
    base = np.uint64(voxel_offset(i0, j0, k0))
    eh = ev_head[0]
    emask = ev_kind.shape[0] - 1
    evf = ev_value.reshape(ev_value.size)      # (capacity * N_VALUE,): rows of N_VALUE
    run_lab = 0
    run_n = 0
    for x in range(cell):
        i = i0 + x
        bx = base + np.uint64(x << 6)
        for y in range(cell):
            j = j0 + y
            by = bx + np.uint64(y << 3)
            for z in range(cell):
                off = by + np.uint64(z)
                d = density[ub, off]
                if d <= 0.0:
                    continue
                lab = label[ub, off]
                m = removal[lab]
                bod = body[ub, off]
                if m <= 0.0 or amount <= 0.0 or not _same_pose(pose_m, bod, owner):
                    n_occ += 1
                    if m > 0.0 and np.float64(d) / m < t_min:
                        t_min = np.float64(d) / m
                    continue
                nd = d - amount * m
                if nd <= 0.0:
                    density[ub, off] = 0.0
                    # ``lost`` counted by runs of one label (no chain through
                    # memory from one removal to the next)
                    if lab != run_lab:
                        if run_n > 0:
                            lost[run_lab] += run_n
                        run_lab = lab
                        run_n = 0
                    run_n += 1
                    lab_body[lab] = bod
                    # push_event_kernel's record, the head kept in hand
                    h = np.uint64(eh & emask)
                    ev_kind[h] = _EV_REMOVED
                    ev_body[h] = bod
                    ev_label[h] = lab
                    ev_t[h] = t
                    ev_ijk[h, 0] = i
                    ev_ijk[h, 1] = j
                    ev_ijk[h, 2] = k0 + z
                    ev_n[h] = 0
                    hv = h * np.uint64(_N_VALUE)
                    for v in range(_N_VALUE):
                        evf[hv + np.uint64(v)] = 0.0
                    eh += 1
                    n_rem += 1
                else:
                    df = np.float32(nd)
                    density[ub, off] = df
                    n_occ += 1
                    if np.float64(df) / m < t_min:
                        t_min = np.float64(df) / m
                    if touched_flag[ub, off] == 0:
                        touched_flag[ub, off] = 1
                        h = tch_head[0] & tcap
                        tch_ijk[h, 0], tch_ijk[h, 1], tch_ijk[h, 2] = i, j, k0 + z
                        tch_head[0] += 1
                        n_tch += 1
    if run_n > 0:
        lost[run_lab] += run_n
    ev_head[0] = eh                              # the head moves last
    counts[0] += n_rem
    counts[1] += n_tch
    occ[b, cq] = n_occ
    thr[b, cq] = t_min


@njit(cache=True, nogil=True)
def flush_kernel(budget_vox, cell, cs, bricks, density, label, body, touched_flag, removal,
                 pose_m, dose, thr, occ, queued, rep, queue, qhead, t, lost, lab_body,
                 ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                 tch_ijk, tch_head, counts):
    """Flush queued cells in order until ``budget_vox`` voxels were visited
    (the cell in hand is finished); ``counts[0:2]`` += removed, touched."""
    cpb = dose.shape[1]
    cps = 3 * (BRICK_SHIFT - cs)              # cpb = (8 >> cs)^3 = 1 << cps
    cap = queue.shape[0]
    c3 = cell * cell * cell
    visited = 0
    while qhead[0] < qhead[1] and visited < budget_vox:
        q = queue[qhead[0] % cap]
        qhead[0] += 1
        b = q >> cps                  # q // cpb, q % cpb (cpb a power of two, q >= 0)
        cq = q & (cpb - 1)
        queued[b, cq] = 0
        visited += c3
        flush_cell(b, cq, cell, cs, bricks, density, label, body, touched_flag, removal,
                    pose_m, dose, thr, occ, rep, t, lost, lab_body, ev_kind, ev_body,
                    ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head, tch_ijk, tch_head,
                    counts)
