"""The haptic pass for finely sampled burrs: one density lookup per voxel a
lattice row of samples crosses.

At high oversampling a voxel holds many of the burr's samples (64 at 4x), and
:func:`bonesim.engine.haptics.haptic_kernel`'s per-sample work (the sample's voxel
index: 9 multiply-adds and 3 truncations, then a lookup) dominates the step.
:func:`haptic_rows_kernel` visits the same samples as **rows**: the stencil's
samples with equal tool-frame ``(o_x, o_y)`` lie on a line along the drill
axis, ``h`` apart (:class:`bonesim.engine.haptics.Stencil`'s ``row_*`` arrays). In
local voxel coordinates the row's sample ``k`` sits at ``a + b k`` (``a``
the first sample, ``b = R[:, 2] h / voxel`` the same for every row), so each
voxel coordinate is a monotone step function of ``k`` and the row splits into
runs of samples in one voxel. A 3D DDA (Amanatides and Woo, in sample
indices) walks these runs: per axis, the index of the next sample past the
next voxel boundary is ``ceil((v + 1 - a_i) / b_i)`` (``b_i > 0``), and the
run ends at the smallest of the three. Each run costs one density lookup;
everything the pass sums over its samples comes from the row's prefix sums:

* the unit vectors ``o / |o|``: ``(o_x, o_y)`` are constant along the row,
  so they sum to ``(o_x S_1/|o|, o_y S_1/|o|, S_{o_z/|o|})``;
* the lever ``(o_y, -o_x)`` sums to ``count (o_y, -o_x)``;
* the removal weight sums to ``S_lat``.

The row's first and last samples are put in voxels by truncation, exactly as
the per-sample kernel does, and the walk takes exactly the voxel steps
between them, so it never leaves the burr's local block. A sample's voxel can
differ from the per-sample kernel's only when the sample lies within floating
point distance of a voxel boundary (``a + b k`` against ``c + R o``; the
row's samples sit exactly ``h`` apart while ``packed`` rounds each offset to
float32: below 1e-6 voxel).

The pass's start (block gather) and end (force, removal, events) are the
same as in :func:`bonesim.engine.haptics.haptic_kernel` (both call
:func:`~bonesim.engine.haptics.begin_pass` and
:func:`~bonesim.engine.haptics.finish_pass`; numba's cache does not see a
change there, so a change of those two must come with a change of this
file, which recompiles this kernel); only the sum over samples differs,
so summation order (and so the last bits) differs from the per-sample kernel:
the oversampling that recorded sessions use keeps the per-sample kernel (see
:data:`ROWS_MIN_OVERSAMPLE`). The kernel allocates nothing and is
deterministic.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from bonesim.engine.haptics import begin_pass, finish_pass, local_frame

__all__ = ["ROWS_MIN_OVERSAMPLE", "haptic_rows_kernel"]

#: Oversampling from which :func:`bonesim.engine.model.step` takes the row pass
#: (where the fixed budget does not bind, :mod:`bonesim.engine.haptics_budget`:
#: ``voxel / oversample`` at least its finest spacing, so 0.75 mm voxels and
#: coarser at 3x; below, the fixed-budget step runs).
#: Below it the per-sample kernel runs: every recorded session (the default
#: 2x) replays with it bit for bit, and with ~8 samples per voxel the rows
#: gain little there (7 mm burr, half immersed, drill off: 66 against 75 us).
#: At 3x the row pass takes 114 against 184 us, at 4x 185 against 400 us.
ROWS_MIN_OVERSAMPLE = 3


@njit(cache=True, nogil=True, inline="always")
def _next_cross(a, b, ib, v, e, n):
    """Index of the first sample of a row past voxel ``v``'s boundary along
    one axis (``n`` if the row's last voxel ``e`` is reached), clamped to
    ``1 .. n - 1``. The samples sit at ``a + b k`` (voxel units, +1/2 shifted)."""
    if v == e:
        return n
    if b > 0.0:
        x = np.ceil((v + 1 - a) * ib)
    else:
        x = np.floor((v - a) * ib) + 1.0
    if not x >= 1.0:          # also catches NaN
        return 1
    if x > n - 1.0:
        return n - 1
    return int(x)


@njit(cache=True, nogil=True)
def haptic_rows_kernel(keys, vals, density, label, body, touched_flag, origin, spacing,
                       stiff, removal, injury,
                       row_head, row_off, row_sums, h, params,
                       pos, axis, drill, direction, speed_factor, dt, t,
                       group, gsel, first, last, case_pos,
                       R, n_vox, lbrick, ldens, llab, acc, dirty, contact, prev_contact,
                       lost, lab_body,
                       ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                       tch_ijk, tch_head,
                       out):
    """One haptic pass over the stencil's rows: the same pass as
    :func:`bonesim.engine.haptics.haptic_kernel`, with the same arguments except the
    samples.

    Parameters
    ----------
    row_head : (n_rows, 3) float64
        Per row, ``(o_x, o_y, o_z)`` of its first sample, tool frame [mm]
        (:attr:`bonesim.engine.haptics.Stencil.row_head`).
    row_off : (n_rows, 2) int64
        Per row, ``(start, n)``: its ``n`` samples' prefix sums are
        ``row_sums[start:start + n + 1]``.
    row_sums : (m, 3) float64
        Prefix sums of ``(1/|o|, o_z/|o|, lat)`` over a row's samples, each
        row's block starting with zeros (shared by mirror-image rows).
    h : float
        Lattice spacing along a row [mm].

    All other parameters and outputs: see :func:`bonesim.engine.haptics.haptic_kernel`.
    """
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
    (c0, c1, c2, r00, r01, r02, r10, r11, r12, r20, r21, r22) = local_frame(
        pos, origin, spacing, R, lo0, lo1, lo2)
    # one sample's step along a row, local voxel units, and its inverse
    d0, d1, d2 = r02 * h, r12 * h, r22 * h
    id0 = 1.0 / d0 if d0 != 0.0 else 0.0
    id1 = 1.0 / d1 if d1 != 0.0 else 0.0
    id2 = 1.0 / d2 if d2 != 0.0 else 0.0
    s0 = 1 if d0 > 0.0 else -1
    s1 = 1 if d1 > 0.0 else -1
    s2 = 1 if d2 > 0.0 else -1
    for r in range(row_head.shape[0]):
        ox = row_head[r, 0]
        oy = row_head[r, 1]
        oz = row_head[r, 2]
        p = row_off[r, 0]
        n = row_off[r, 1]
        a0 = c0 + r00 * ox + r01 * oy + r02 * oz
        a1 = c1 + r10 * ox + r11 * oy + r12 * oz
        a2 = c2 + r20 * ox + r21 * oy + r22 * oz
        v0, v1, v2 = int(a0), int(a1), int(a2)
        e0 = int(a0 + d0 * (n - 1))
        e1 = int(a1 + d1 * (n - 1))
        e2 = int(a2 + d2 * (n - 1))
        k0 = _next_cross(a0, d0, id0, v0, e0, n)
        k1 = _next_cross(a1, d1, id1, v1, e1, n)
        k2 = _next_cross(a2, d2, id2, v2, e2, n)
        ka = 0
        while True:
            kb = min(k0, min(k1, k2))
            if kb > ka:
                li = (v0 * n_vox + v1) * n_vox + v2
                if ldens[li] > 0.0:
                    lab = llab[li]
                    w = stiff[lab]
                    cnt = kb - ka
                    n_imm += cnt
                    wsum += w * cnt
                    contact[lab] += cnt
                    sr = row_sums[p + kb, 0] - row_sums[p + ka, 0]
                    sux += w * (ox * sr)
                    suy += w * (oy * sr)
                    suz += w * (row_sums[p + kb, 1] - row_sums[p + ka, 1])
                    stx += w * (oy * cnt)
                    sty -= w * (ox * cnt)
                    if drill:
                        am = (row_sums[p + kb, 2] - row_sums[p + ka, 2]) * removal[lab]
                        if am > 0.0:
                            if acc[li] == 0.0:
                                dirty[n_dirty] = li
                                n_dirty += 1
                            acc[li] += am
                ka = kb
            if kb >= n:
                break
            if k0 == kb:
                v0 += s0
                k0 = _next_cross(a0, d0, id0, v0, e0, n)
            if k1 == kb:
                v1 += s1
                k1 = _next_cross(a1, d1, id1, v1, e1, n)
            if k2 == kb:
                v2 += s2
                k2 = _next_cross(a2, d2, id2, v2, e2, n)
    finish_pass(density, label, body, touched_flag, injury, params, drill, direction,
            speed_factor, dt, t, last, case_pos, R, n_vox, lo0, lo1, lo2, lbrick, ldens,
            llab, acc, dirty, n_dirty, contact, prev_contact, lost, lab_body,
            ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
            tch_ijk, tch_head, out, sux, suy, suz, stx, sty, wsum, n_imm)
