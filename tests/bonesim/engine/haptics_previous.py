"""The per-sample haptic kernel as it was before the row walk (a frozen
copy, for the tests only): the slow reference that the kernel of
:mod:`bonesim.engine.haptics` must match bit for bit.

Recorded sessions replay bit for bit, so the faster kernel (per-row voxel
coordinates computed once, a branch-free dirty list, run-length contact
counts, a gather by brick runs) keeps every float operation and the order of
every nonzero term. This is the kernel of commit b1e31c9, verbatim except for
its name and ``cache=False``.
"""
from __future__ import annotations

import types

import numpy as np
from numba import njit

from bonesim.engine.events import CONTACT as _EV_CONTACT
from bonesim.engine.events import INJURY as _EV_INJURY
from bonesim.engine.events import REMOVED as _EV_REMOVED
from bonesim.engine.grid import BRICK_SHIFT, voxel_offset
from bonesim.engine.haptics import (O_N_REMOVED, O_N_TOUCHED, P_H3, P_INV_VOXEL_VOL,
                                    P_RADIUS, _label_body, block_bricks, force_law,
                                    push_event_kernel, tool_frame)
from bonesim.engine.haptics_rows import haptic_rows_kernel

__all__ = ["previous_haptic_kernel", "previous_rows_kernel"]


@njit(cache=False, nogil=True, inline="always")
def _gather(density, label, body, group, gsel, lo0, lo1, lo2, b0, b1, b2, n_vox, lbrick,
            ldens, llab):
    """Copy the burr's block of voxels into dense local scratch: density (0
    where the voxel's body is not in group ``gsel``; ``gsel < 0``: every
    body) and label. The one-body step takes the first loop only."""
    nn = n_vox * n_vox
    for x in range(n_vox):
        i = lo0 + x
        bx = (i >> BRICK_SHIFT) - b0
        for y in range(n_vox):
            j = lo1 + y
            by = (j >> BRICK_SHIFT) - b1
            base = x * nn + y * n_vox
            for z in range(n_vox):
                k = lo2 + z
                b = lbrick[bx, by, (k >> BRICK_SHIFT) - b2]
                if b >= 0:
                    off = voxel_offset(i, j, k)
                    ldens[base + z] = density[b, off]
                    llab[base + z] = label[b, off]
                else:
                    ldens[base + z] = 0.0
                    llab[base + z] = 0
    if gsel < 0:
        return
    # bodies of other groups are not there for this pass
    for x in range(n_vox):
        i = lo0 + x
        bx = (i >> BRICK_SHIFT) - b0
        for y in range(n_vox):
            j = lo1 + y
            by = (j >> BRICK_SHIFT) - b1
            base = x * nn + y * n_vox
            for z in range(n_vox):
                if ldens[base + z] > 0.0:
                    k = lo2 + z
                    b = lbrick[bx, by, (k >> BRICK_SHIFT) - b2]
                    if group[body[b, voxel_offset(i, j, k)]] != gsel:
                        ldens[base + z] = 0.0


@njit(cache=False, nogil=True)
def begin_pass(keys, vals, density, label, body, origin, spacing, params, pos, axis, group,
           gsel, first, last, R, n_vox, lbrick, ldens, llab, contact, prev_contact, lost,
           out):
    """Start of a pass (as in :func:`haptic_kernel`): clear the outputs, build
    the tool frame ``R`` and gather the burr's block into ``ldens``/``llab``.

    Returns ``(lo0, lo1, lo2, any_brick)``: the block's first voxel and whether
    any brick is allocated there (if not, the pass is over).
    """
    for q in range(out.shape[0]):
        out[q] = 0.0
    if first:
        for q in range(contact.shape[0]):
            contact[q] = 0
            lost[q] = 0
    tool_frame(axis, R)
    # local block of voxels around the burr
    lo0, lo1, lo2, any_brick = block_bricks(keys, vals, pos, params[P_RADIUS], origin,
                                            spacing, lbrick)
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    if not any_brick:
        if last:
            for q in range(prev_contact.shape[0]):
                prev_contact[q] = 0
        return lo0, lo1, lo2, False
    # gather the block's density and labels into dense local scratch
    _gather(density, label, body, group, gsel, lo0, lo1, lo2, b0, b1, b2, n_vox, lbrick,
            ldens, llab)
    return lo0, lo1, lo2, True


@njit(cache=False, nogil=True)
def remove_voxels(density, label, body, touched_flag, acc, dirty, n_dirty, scale, lo0, lo1,
                  lo2, n_vox, lbrick, t, lost, lab_body, ev_kind, ev_body, ev_label, ev_t,
                  ev_ijk, ev_n, ev_value, ev_head, tch_ijk, tch_head):
    """Voxel removal: take each local voxel's accumulated removal weight
    ``acc[dirty[:n_dirty]]`` times ``scale`` from its density (the weights are
    cleared). A voxel whose density reaches 0 is removed: counted in
    ``lost`` per label (``lab_body``: its body), published as a ``REMOVED``
    event at time ``t`` [s]; one that keeps some density is published once
    in the touched ring (until a consumer clears its flag). ``lo0..lo2`` is
    the local block's first voxel, ``n_vox`` its edge, ``lbrick`` its bricks.

    Returns
    -------
    (int, int)
        Voxels removed and newly touched.
    """
    nn = n_vox * n_vox
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    n_rem = 0
    n_tch = 0
    tcap = tch_ijk.shape[0] - 1
    for q in range(n_dirty):
        li = dirty[q]
        amount = acc[li] * scale
        acc[li] = 0.0
        if amount <= 0.0:
            continue
        i = lo0 + li // nn
        j = lo1 + (li // n_vox) % n_vox
        k = lo2 + li % n_vox
        b = lbrick[(i >> BRICK_SHIFT) - b0, (j >> BRICK_SHIFT) - b1, (k >> BRICK_SHIFT) - b2]
        off = voxel_offset(i, j, k)
        d = density[b, off] - amount
        if d <= 0.0:
            density[b, off] = 0.0
            lab = label[b, off]
            lost[lab] += 1
            bod = body[b, off]
            lab_body[lab] = bod
            push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                        _EV_REMOVED, bod, lab, t, i, j, k, 0, 0.0, 0.0, 0.0)
            n_rem += 1
        else:
            density[b, off] = np.float32(d)
            if touched_flag[b, off] == 0:
                touched_flag[b, off] = 1
                h = tch_head[0] & tcap
                tch_ijk[h, 0], tch_ijk[h, 1], tch_ijk[h, 2] = i, j, k
                tch_head[0] += 1
                n_tch += 1
    return n_rem, n_tch


@njit(cache=False, nogil=True)
def finish_pass(density, label, body, touched_flag, injury, params, drill, direction,
            speed_factor, dt, t, last, case_pos, R, n_vox, lo0, lo1, lo2, lbrick, ldens,
            llab, acc, dirty, n_dirty, contact, prev_contact, lost, lab_body,
            ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
            tch_ijk, tch_head, out, sux, suy, suz, stx, sty, wsum, n_imm):
    """End of a pass (as in :func:`haptic_kernel`): force from the summed
    samples, removal of the accumulated amounts and the pass's events.

    ``sux, suy, suz`` are the stiffness-weighted unit vectors summed in the
    tool frame, ``stx, sty`` the weighted lever ``(o_y, -o_x)`` [mm], ``wsum``
    the weighted count and ``n_imm`` the immersed samples; ``acc[dirty[:n_dirty]]``
    the removal weights per local voxel (see :func:`haptic_kernel`).
    """
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    h3 = params[P_H3]
    mag = force_law(params, R, sux, suy, suz, stx, sty, wsum, n_imm, drill, direction,
                    speed_factor, out)
    # removal: each immersed sample took lat*m*f*phi*dt of its voxel's share
    scale = mag * speed_factor * dt * h3 * params[P_INV_VOXEL_VOL]
    n_rem, n_tch = remove_voxels(density, label, body, touched_flag, acc, dirty, n_dirty,
                                 scale, lo0, lo1, lo2, n_vox, lbrick, t, lost, lab_body,
                                 ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                 ev_head, tch_ijk, tch_head)
    out[O_N_REMOVED] = n_rem
    out[O_N_TOUCHED] = n_tch
    if not last:
        return
    # injuries, once per step over all passes
    for lab in range(contact.shape[0]):
        touching = drill and contact[lab] > 0
        if injury[lab]:
            if touching and prev_contact[lab] == 0:
                bod = _label_body(lo0, lo1, lo2, b0, b1, b2, n_vox, lbrick, ldens, llab,
                                  body, lab)
                push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                            ev_head, _EV_CONTACT, bod, lab, t, 0, 0, 0, 0,
                            case_pos[0], case_pos[1], case_pos[2])
            if lost[lab] > 0:
                push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                            ev_head, _EV_INJURY, lab_body[lab], lab, t, 0, 0, 0, lost[lab],
                            case_pos[0], case_pos[1], case_pos[2])
        prev_contact[lab] = 1 if touching else 0


@njit(cache=False, nogil=True)
def previous_haptic_kernel(keys, vals, density, label, body, touched_flag, origin, spacing,
                  stiff, removal, injury,
                  samples, params,
                  pos, axis, drill, direction, speed_factor, dt, t,
                  group, gsel, first, last, case_pos,
                  R, n_vox, lbrick, ldens, llab, acc, dirty, contact, prev_contact, lost,
                  lab_body,
                  ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                  tch_ijk, tch_head,
                  out):
    """The per-sample pass (arguments as
    :func:`bonesim.engine.haptics.haptic_kernel`, without ``row_off``)."""
    lo0, lo1, lo2, any_brick = begin_pass(keys, vals, density, label, body, origin, spacing,
                                      params, pos, axis, group, gsel, first, last, R,
                                      n_vox, lbrick, ldens, llab, contact, prev_contact,
                                      lost, out)
    if not any_brick:
        return
    sux = suy = suz = 0.0
    stx = sty = 0.0
    wsum = 0.0
    n_imm = 0
    n_dirty = 0
    inv = 1.0 / spacing
    # tool centre in local block coordinates, shifted by +1/2 so that
    # truncation toward zero rounds to the nearest voxel (all values > 0)
    c0 = (pos[0] - origin[0]) * inv + 0.5 - lo0
    c1 = (pos[1] - origin[1]) * inv + 0.5 - lo1
    c2 = (pos[2] - origin[2]) * inv + 0.5 - lo2
    r00, r01, r02 = R[0, 0] * inv, R[0, 1] * inv, R[0, 2] * inv
    r10, r11, r12 = R[1, 0] * inv, R[1, 1] * inv, R[1, 2] * inv
    r20, r21, r22 = R[2, 0] * inv, R[2, 1] * inv, R[2, 2] * inv
    for s in range(samples.shape[0]):
        ox = np.float64(samples[s, 0])
        oy = np.float64(samples[s, 1])
        oz = np.float64(samples[s, 2])
        li = (int(c0 + r00 * ox + r01 * oy + r02 * oz) * n_vox
              + int(c1 + r10 * ox + r11 * oy + r12 * oz)) * n_vox \
            + int(c2 + r20 * ox + r21 * oy + r22 * oz)
        if ldens[li] <= 0.0:
            continue
        lab = llab[li]
        w = stiff[lab]
        n_imm += 1
        wsum += w
        contact[lab] += 1
        wr = w * np.float64(samples[s, 3])
        sux += wr * ox
        suy += wr * oy
        suz += wr * oz
        stx += w * oy
        sty -= w * ox
        if drill:
            a = np.float64(samples[s, 4]) * removal[lab]
            if a > 0.0:
                if acc[li] == 0.0:
                    dirty[n_dirty] = li
                    n_dirty += 1
                acc[li] += a
    finish_pass(density, label, body, touched_flag, injury, params, drill, direction,
            speed_factor, dt, t, last, case_pos, R, n_vox, lo0, lo1, lo2, lbrick, ldens,
            llab, acc, dirty, n_dirty, contact, prev_contact, lost, lab_body,
            ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
            tch_ijk, tch_head, out, sux, suy, suz, stx, sty, wsum, n_imm)


def _with_previous_pass(kernel):
    """``kernel`` (a numba function calling ``begin_pass``/``finish_pass``)
    compiled again with this module's frozen ``begin_pass``/``finish_pass``."""
    py = kernel.py_func
    glb = dict(py.__globals__)
    glb.update(begin_pass=begin_pass, finish_pass=finish_pass)
    return njit(cache=False, nogil=True)(types.FunctionType(py.__code__, glb, py.__name__))


#: The row kernel (:mod:`bonesim.engine.haptics_rows`, unchanged) on the frozen
#: start and end of a pass: what it computed before them.
previous_rows_kernel = _with_previous_pass(haptic_rows_kernel)
