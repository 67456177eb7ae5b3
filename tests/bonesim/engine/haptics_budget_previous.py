"""The fixed-budget haptic step as it was before its speed-up (a frozen
copy, for the tests only): the reference that the kernel of
:mod:`bonesim.engine.haptics_budget` must match bit for bit.

Recorded sessions replay bit for bit, so the faster kernel keeps every float
operation and the order of every nonzero term. These are the kernels of
commit 3e71246, verbatim except for their names and ``cache=False``.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from bonesim.engine.events import CONTACT as _EV_CONTACT
from bonesim.engine.events import INJURY as _EV_INJURY
from bonesim.engine.events import REMOVED as _EV_REMOVED
from bonesim.engine.grid import BRICK, BRICK_SHIFT, voxel_offset
from bonesim.engine.haptics import (P_RADIUS, O_N_REMOVED, O_N_TOUCHED, block_bricks,
                                    force_law, push_event_kernel, tool_frame)

__all__ = ["previous_budget_kernel"]


# ------------------------------------------------------------------ kernels
@njit(cache=False, nogil=True, inline="always")
def previous_same_pose(pose_m, a, b):
    if a == b:
        return True
    for r in range(3):
        for c in range(4):
            if pose_m[a, r, c] != pose_m[b, r, c]:
                return False
    return True


@njit(cache=False, nogil=True)
def previous_flush_cell(b, cq, cell, cs, bricks, density, label, body, touched_flag, removal,
                        pose_m,
                dose, thr, occ, rep, t, lost, lab_body, ev_kind, ev_body, ev_label, ev_t,
                ev_ijk, ev_n, ev_value, ev_head, tch_ijk, tch_head, counts):
    """Apply cell ``cq`` of brick ``b``'s dose to its voxels (see the module
    notes); recount its occupancy and threshold. ``counts[0:2]`` += removed,
    newly touched."""
    amount = dose[b, cq]
    dose[b, cq] = 0.0
    owner = rep[b, cq]
    n = BRICK >> cs
    ci = cq // (n * n)
    cj = (cq // n) % n
    ck = cq % n
    i0 = bricks[b, 0] * BRICK + (ci << cs)
    j0 = bricks[b, 1] * BRICK + (cj << cs)
    k0 = bricks[b, 2] * BRICK + (ck << cs)
    tcap = tch_ijk.shape[0] - 1
    n_occ = 0
    t_min = np.inf
    for x in range(cell):
        i = i0 + x
        for y in range(cell):
            j = j0 + y
            for z in range(cell):
                k = k0 + z
                off = voxel_offset(i, j, k)
                d = density[b, off]
                if d <= 0.0:
                    continue
                lab = label[b, off]
                m = removal[lab]
                bod = body[b, off]
                if m <= 0.0 or amount <= 0.0 or not previous_same_pose(pose_m, bod, owner):
                    n_occ += 1
                    if m > 0.0 and np.float64(d) / m < t_min:
                        t_min = np.float64(d) / m
                    continue
                nd = d - amount * m
                if nd <= 0.0:
                    density[b, off] = 0.0
                    lost[lab] += 1
                    lab_body[lab] = bod
                    push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                      ev_head, _EV_REMOVED, bod, lab, t, i, j, k, 0,
                                      0.0, 0.0, 0.0)
                    counts[0] += 1
                else:
                    df = np.float32(nd)
                    density[b, off] = df
                    n_occ += 1
                    if np.float64(df) / m < t_min:
                        t_min = np.float64(df) / m
                    if touched_flag[b, off] == 0:
                        touched_flag[b, off] = 1
                        h = tch_head[0] & tcap
                        tch_ijk[h, 0], tch_ijk[h, 1], tch_ijk[h, 2] = i, j, k
                        tch_head[0] += 1
                        counts[1] += 1
    occ[b, cq] = n_occ
    thr[b, cq] = t_min


@njit(cache=False, nogil=True)
def previous_flush_kernel(budget_vox, cell, cs, bricks, density, label, body, touched_flag,
                          removal,
                 pose_m, dose, thr, occ, queued, rep, queue, qhead, t, lost, lab_body,
                 ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                 tch_ijk, tch_head, counts):
    """Flush queued cells in order until ``budget_vox`` voxels were visited
    (the cell in hand is finished); ``counts[0:2]`` += removed, touched."""
    cpb = dose.shape[1]
    cap = queue.shape[0]
    c3 = cell * cell * cell
    visited = 0
    while qhead[0] < qhead[1] and visited < budget_vox:
        q = queue[qhead[0] % cap]
        qhead[0] += 1
        b = q // cpb
        cq = q % cpb
        queued[b, cq] = 0
        visited += c3
        previous_flush_cell(b, cq, cell, cs, bricks, density, label, body, touched_flag, removal,
                    pose_m, dose, thr, occ, rep, t, lost, lab_body, ev_kind, ev_body,
                    ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head, tch_ijk, tch_head,
                    counts)


@njit(cache=False, nogil=True)
def previous_dose_cells(pos, axis, radius, origin, spacing, scale, lat, lo0, lo1, lo2, lbrick,
                        cell,
                cs, owner, bricks, density, label, body, touched_flag, removal, pose_m, dose,
                thr, occ, queued, rep, queue, qhead, t, lost, lab_body, ev_kind, ev_body,
                ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head, tch_ijk, tch_head, counts):
    """Add ``scale x lat`` to every bone-holding cell whose centre lies in
    the burr; queue the cells whose dose reaches their threshold."""
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    nbk = lbrick.shape[0]
    n = BRICK >> cs
    cpb = dose.shape[1]
    cap = queue.shape[0]
    cw = cell * spacing                       # cell edge [mm]
    half = 0.5 * (cell - 1) * spacing         # cell centre past its first voxel [mm]
    r2 = radius * radius
    nl = lat.shape[0] - 1
    # cell C's centre: origin + cw C + half
    ci_lo = int(np.ceil((pos[0] - radius - origin[0] - half) / cw))
    ci_hi = int(np.floor((pos[0] + radius - origin[0] - half) / cw))
    cj_lo = int(np.ceil((pos[1] - radius - origin[1] - half) / cw))
    cj_hi = int(np.floor((pos[1] + radius - origin[1] - half) / cw))
    for ci in range(ci_lo, ci_hi + 1):
        ox = origin[0] + cw * ci + half - pos[0]
        i0 = ci << cs
        bx = (i0 >> BRICK_SHIFT) - b0
        if bx < 0 or bx >= nbk:
            continue
        for cj in range(cj_lo, cj_hi + 1):
            oy = origin[1] + cw * cj + half - pos[1]
            rz2 = r2 - ox * ox - oy * oy
            if rz2 < 0.0:
                continue
            j0 = cj << cs
            by = (j0 >> BRICK_SHIFT) - b1
            if by < 0 or by >= nbk:
                continue
            rz = np.sqrt(rz2)
            ck_lo = int(np.ceil((pos[2] - rz - origin[2] - half) / cw))
            ck_hi = int(np.floor((pos[2] + rz - origin[2] - half) / cw))
            for ck in range(ck_lo, ck_hi + 1):
                k0 = ck << cs
                bz = (k0 >> BRICK_SHIFT) - b2
                if bz < 0 or bz >= nbk:
                    continue
                b = lbrick[bx, by, bz]
                if b < 0:
                    continue
                cq = ((((i0 & 7) >> cs) * n) + ((j0 & 7) >> cs)) * n + ((k0 & 7) >> cs)
                if occ[b, cq] <= 0:
                    continue
                oz = origin[2] + cw * ck + half - pos[2]
                rr = np.sqrt(ox * ox + oy * oy + oz * oz)
                u = 0.0
                if rr > 0.0:
                    u = abs(ox * axis[0] + oy * axis[1] + oz * axis[2]) / rr
                    if u > 1.0:
                        u = 1.0
                x = u * nl
                q = int(x)
                if q >= nl:
                    w = lat[nl]
                else:
                    w = lat[q] + (x - q) * (lat[q + 1] - lat[q])
                a = w * scale
                if a <= 0.0:
                    continue
                if dose[b, cq] > 0.0 and rep[b, cq] != owner:
                    previous_flush_cell(b, cq, cell, cs, bricks, density, label, body,
                                        touched_flag,
                                removal, pose_m, dose, thr, occ, rep, t, lost, lab_body,
                                ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                ev_head, tch_ijk, tch_head, counts)
                rep[b, cq] = owner
                dose[b, cq] += a
                if queued[b, cq] == 0 and dose[b, cq] >= thr[b, cq]:
                    queued[b, cq] = 1
                    queue[qhead[1] % cap] = b * cpb + cq
                    qhead[1] += 1


@njit(cache=False, nogil=True)
def previous_budget_kernel(keys, vals, bricks, density, label, body, touched_flag, origin, spacing,
                  stiff, removal, injury, samples, row_head, row_off, h, params, lat,
                  budget_vox, cell, cs,
                  pos, axis, drill, direction, speed_factor, dt, t,
                  group, gsel, owner, first, last, case_pos, pose_m,
                  R, lbrick, contact, prev_contact, lost, lab_body, onset_body,
                  dose, thr, occ, queued, rep, queue, qhead, counts,
                  ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                  tch_ijk, tch_head, out):
    """One haptic pass of the fixed-budget step (see the module notes).

    Parameters as :func:`bonesim.engine.haptics.haptic_kernel`, except:

    bricks : (n_bricks, 3) int32
        Brick coordinates (:attr:`bonesim.engine.grid.Grid.bricks`).
    samples : (n, 5) float32
        The budget stencil's packed rows (spacing ``h``; ``params[P_H3]`` is ``h^3``).
    row_head, row_off : arrays
        The stencil's lattice rows along the tool axis
        (:attr:`bonesim.engine.haptics.Stencil.row_head`, ``row_off``): the
        samples are visited row by row, each voxel coordinate stepping by
        ``h`` along the axis (a sample within float rounding of a voxel face
        may land on its other side than a per-sample sum would put it).
    h : float
        The lattice spacing [mm].
    lat : (LAT_TABLE,) float64
        The burr's latitude table (:func:`lat_table`).
    budget_vox : int
        The step's removal budget [voxels] (:func:`removal_budget`).
    cell, cs : int
        Removal cell edge [voxels] and its log2.
    gsel : int
        As the per-voxel kernel's; -2: sample nothing (the step of a burr
        out of every body's reach only flushes).
    owner : int
        The body whose frame this pass runs in (its doses are flushed onto
        the voxels of bodies at its pose).
    pose_m : (max_bodies, 3, 4) float64
        Body poses (equal poses share doses).
    onset_body : (n_labels + 1,) int32
        Scratch: the body of the first immersed sample per label.
    dose, thr, occ, queued, rep, queue, qhead :
        The :class:`BudgetState` arrays (modified).
    counts : (2,) int64
        Scratch.

    The pass also flushes the queue when ``last`` (once per step).
    """
    for q in range(out.shape[0]):
        out[q] = 0.0
    if first:
        for q in range(contact.shape[0]):
            contact[q] = 0
            lost[q] = 0
    counts[0] = 0
    counts[1] = 0
    tool_frame(axis, R)
    radius = params[P_RADIUS]
    lo0, lo1, lo2, any_brick = block_bricks(keys, vals, pos, radius, origin, spacing, lbrick)
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    ncell = BRICK >> cs
    sux = suy = suz = 0.0
    stx = sty = 0.0
    wsum = 0.0
    n_imm = 0
    if any_brick and gsel != -2:              # -2: a pass that only flushes
        inv = 1.0 / spacing
        c0 = (pos[0] - origin[0]) * inv + 0.5 - lo0
        c1 = (pos[1] - origin[1]) * inv + 0.5 - lo1
        c2 = (pos[2] - origin[2]) * inv + 0.5 - lo2
        r00, r01, r02 = R[0, 0] * inv, R[0, 1] * inv, R[0, 2] * inv
        r10, r11, r12 = R[1, 0] * inv, R[1, 1] * inv, R[1, 2] * inv
        r20, r21, r22 = R[2, 0] * inv, R[2, 1] * inv, R[2, 2] * inv
        # the lattice's rows along the tool axis: a row's samples sit
        # h apart, so each voxel coordinate is the row's first plus k steps
        d0, d1, d2 = r02 * h, r12 * h, r22 * h
        s = 0
        for r in range(row_head.shape[0]):
            ox = row_head[r, 0]
            oy = row_head[r, 1]
            oz = row_head[r, 2]
            a0 = c0 + r00 * ox + r01 * oy + r02 * oz
            a1 = c1 + r10 * ox + r11 * oy + r12 * oz
            a2 = c2 + r20 * ox + r21 * oy + r22 * oz
            n = row_off[r, 1]
            for q in range(n):
                i = lo0 + int(a0 + d0 * q)
                j = lo1 + int(a1 + d1 * q)
                k = lo2 + int(a2 + d2 * q)
                b = lbrick[(i >> BRICK_SHIFT) - b0, (j >> BRICK_SHIFT) - b1,
                           (k >> BRICK_SHIFT) - b2]
                if b < 0:
                    continue
                # a cell known empty (the counts are exact or stale upward)
                # needs no density read: the drilled cavity costs one small read
                if occ[b, ((((i & 7) >> cs) * ncell) + ((j & 7) >> cs)) * ncell
                       + ((k & 7) >> cs)] <= 0:
                    continue
                off = voxel_offset(i, j, k)
                if density[b, off] <= 0.0:
                    continue
                if gsel >= 0 and group[body[b, off]] != gsel:
                    continue
                lab = label[b, off]
                w = stiff[lab]
                n_imm += 1
                wsum += w
                if contact[lab] == 0:
                    onset_body[lab] = body[b, off]
                contact[lab] += 1
                wr = w * np.float64(samples[s + q, 3])
                sux += wr * ox
                suy += wr * oy
                suz += wr * np.float64(samples[s + q, 2])
                stx += w * oy
                sty -= w * ox
            s += n
    # force: the per-voxel kernel's law
    mag = force_law(params, R, sux, suy, suz, stx, sty, wsum, n_imm, drill, direction,
                    speed_factor, out)
    # removal: dose the burr's cells, then flush within the budget
    scale = mag * speed_factor * dt
    if drill and any_brick and n_imm > 0 and scale > 0.0:
        previous_dose_cells(pos, axis, radius, origin, spacing, scale, lat, lo0, lo1, lo2, lbrick,
                    cell, cs, owner, bricks, density, label, body, touched_flag, removal,
                    pose_m, dose, thr, occ, queued, rep, queue, qhead, t, lost, lab_body,
                    ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                    tch_ijk, tch_head, counts)
    if last:
        previous_flush_kernel(budget_vox, cell, cs, bricks, density, label, body, touched_flag,
                     removal, pose_m, dose, thr, occ, queued, rep, queue, qhead, t, lost,
                     lab_body, ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                     ev_head, tch_ijk, tch_head, counts)
    out[O_N_REMOVED] = counts[0]
    out[O_N_TOUCHED] = counts[1]
    if not last:
        return
    for lab in range(contact.shape[0]):
        touching = drill and contact[lab] > 0
        if injury[lab]:
            if touching and prev_contact[lab] == 0:
                push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                  ev_head, _EV_CONTACT, onset_body[lab], lab, t, 0, 0, 0, 0,
                                  case_pos[0], case_pos[1], case_pos[2])
            if lost[lab] > 0:
                push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                  ev_head, _EV_INJURY, lab_body[lab], lab, t, 0, 0, 0,
                                  lost[lab], case_pos[0], case_pos[1], case_pos[2])
        prev_contact[lab] = 1 if touching else 0
