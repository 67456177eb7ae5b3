"""The full shading of a surface's vertices (:meth:`bonesim.engine.shading.Shader.shade_all`):
slots, voxels, positions, normals and colours of every vertex in one
parallel pass over the bricks, as :mod:`bonesim.engine.shading` defines
them, bit for bit what its refresh gives.

The field (:mod:`bonesim.engine.normals`) is computed along *runs* of
bricks in x (each brick without a -x neighbour starts one, and the run
follows the +x neighbours): plane by plane, the densities of a plane of
the brick's box (the brick and a :data:`HALO`-voxel halo) are gathered and
passed along k and j once (:func:`bonesim.engine.normals.kj_flat`) into
rings of seven planes, and the i pass is taken at each vertex; a brick's
box shares six planes with the next one's, so a plane is computed once per
run. The runs are the work items, handed out one at a time
(:mod:`bonesim.engine.work_items`); each writes only its own bricks'
vertices and map entries.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from bonesim.engine.grid import BRICK, BRICK_MASK, BRICK_SHIFT
from bonesim.engine.normals import (FLAT_EDGE, FLAT_PLANE, NORMAL_RADIUS, fallback_normal,
                                    i_point, kj_flat, unit_normal, vertex_shift)
from bonesim.engine.thin_bone import tint_vertex
from bonesim.engine.work_items import take_item

__all__ = ["ALPHA", "HALO", "BOX_EDGE"]

#: Alpha of every vertex colour.
ALPHA = 255
#: Halo [voxels] of a brick's box: the normal stencil's half-width.
HALO = NORMAL_RADIUS
#: Edge of a brick's box [voxels].
BOX_EDGE = BRICK + 2 * HALO
_HALO = HALO
_LB = BOX_EDGE
# layout of the float64 constants ``fp`` the shading kernels take: origin (3),
# spacing, the [surface] iso level and the longest moves out and in
F_ORIGIN, F_SPACING, F_ISO, F_OUT, F_IN = 0, 3, 4, 5, 6
N_F = 7


# The hot loops below call only helpers on scalars: a numba helper taking
# arrays, inlined or not, costs reference counting on every call (some 30 ns
# per vertex); helpers with arrays are called in rare branches only.
@njit(cache=True, nogil=True, inline="always")
def blend(r0, g0, b0, w, ar, ag, ab):
    """RGB (uint8) of the colour ``(r0, g0, b0)`` blended with weight ``w``
    toward the weighted structure colour ``(ar, ag, ab)`` (module docstring).
    Without a blend (``w``, ``ar``, ``ag``, ``ab`` all 0, most vertices) the
    formula gives the colour itself (``floor(c + 0.5) = c`` for an integer
    ``c``), returned at once."""
    if w == 0.0 and ar == 0.0 and ag == 0.0 and ab == 0.0:
        return np.uint8(r0), np.uint8(g0), np.uint8(b0)
    r = np.floor(np.float64(r0) * (1.0 - w) + ar + 0.5)
    g = np.floor(np.float64(g0) * (1.0 - w) + ag + 0.5)
    b = np.floor(np.float64(b0) * (1.0 - w) + ab + 0.5)
    return np.uint8(min(r, 255.0)), np.uint8(min(g, 255.0)), np.uint8(min(b, 255.0))


@njit(cache=True, nogil=True)
def _gather_plane(density, nbr, b, x, out, s):
    """Densities of the plane ``x`` (brick-relative, ``-_HALO .. BRICK - 1 +
    _HALO``) of brick ``b``'s box (the brick and a ``_HALO``-voxel halo) into
    ``out[s:s + LB * LB]`` (voxel ``(x, y, z)`` of the brick at ``s + (y + H)
    * LB + z + H``). Each row along z is three contiguous copies: the last
    ``H`` voxels of the brick below, the brick's 8, the first ``H`` of the
    brick above; the three bricks are looked up once for the rows of each
    of the three bricks along y."""
    sx = ((x >> BRICK_SHIFT) + 1) * 9
    ox = (x & BRICK_MASK) << 6
    for gy in range(3):                        # the bricks below, at and above along y
        y0 = 0 if gy == 0 else (_HALO if gy == 1 else _HALO + BRICK)
        y1 = _HALO if gy == 0 else (_HALO + BRICK if gy == 1 else _LB)
        sy = sx + gy * 3
        n_lo = nbr[b, sy]
        n_mid = nbr[b, sy + 1]
        n_hi = nbr[b, sy + 2]
        for ly in range(y0, y1):
            oy = ox | (((ly - _HALO) & BRICK_MASK) << 3)
            t = s + ly * _LB
            if n_lo >= 0:
                for q in range(_HALO):
                    out[t + q] = density[n_lo, oy + BRICK - _HALO + q]
            else:
                for q in range(_HALO):
                    out[t + q] = np.float32(0.0)
            t += _HALO
            if n_mid >= 0:
                for q in range(BRICK):
                    out[t + q] = density[n_mid, oy + q]
            else:
                for q in range(BRICK):
                    out[t + q] = np.float32(0.0)
            t += BRICK
            if n_hi >= 0:
                for q in range(_HALO):
                    out[t + q] = density[n_hi, oy + q]
            else:
                for q in range(_HALO):
                    out[t + q] = np.float32(0.0)


#: Slots of a brick's neighbours along -x and +x in the neighbour table.
NBR_XM = 4
_NBR_XP = 22


@njit(cache=True, nogil=True)
def _shade_run(keys, vals, density, label, nbr, bricks, srf, voff, bone, tint_on, near,
               colors, W, fp, tp, cone, vmap, ijk, pos, nrm, shf, col, b, dring, rs, rd, ring,
               nb27):
    """:func:`shade_all_kernel` of the run of bricks along +x that starts at
    brick ``b``; returns its number of vertices. Run plane ``P`` is the
    plane ``8 r + P - _HALO`` (brick-relative x) of the run's ``r``-th brick;
    its densities and k and j passes (:func:`kj_flat`) are kept in slot ``P
    % 7`` of the rings ``dring`` (``(7, LB, LB)``) and ``ring``, so each
    plane along the run is computed once (the box of a brick shares six
    planes with the next one's). ``rs``, ``rd``: :func:`kj_flat`'s scratch;
    ``nb27``: :func:`fallback_normal`'s."""
    ncol = colors.shape[0]
    one = np.uint64(1)
    n_pl = BRICK * BRICK
    pl_sz = _LB * _LB
    origin = fp[F_ORIGIN:F_ORIGIN + 3]
    spacing = fp[F_SPACING]
    iso = fp[F_ISO]
    s_out = fp[F_OUT]
    s_in = fp[F_IN]
    w0, w1, w2, w3, w4, w5, w6 = W[0], W[1], W[2], W[3], W[4], W[5], W[6]
    n = 0
    have = 0                  # run planes below this one are in the rings
    r = 0
    while b >= 0:
        v = voff[b]
        if voff[b + 1] == v:
            for o in range(BRICK * n_pl):
                vmap[b, o] = -1
            b = nbr[b, _NBR_XP]
            r += 1
            continue
        bi = bricks[b, 0] << BRICK_SHIFT
        bj = bricks[b, 1] << BRICK_SHIFT
        bk = bricks[b, 2] << BRICK_SHIFT
        for x in range(BRICK):
            any_v = 0
            for y in range(BRICK):
                any_v |= srf[b, x * BRICK + y]
            if any_v == 0:
                for o in range(x * n_pl, (x + 1) * n_pl):
                    vmap[b, o] = -1
                continue
            first = BRICK * r + x            # run planes first .. first + 6
            for pl in range(max(have, first), first + 7):
                sl = pl % 7
                _gather_plane(density, nbr, b, pl - _HALO - BRICK * r, dring, sl * pl_sz)
                kj_flat(dring, sl, W, rs, rd, ring, sl)
            have = first + 7
            i = bi + x
            for y in range(BRICK):
                bits = srf[b, x * BRICK + y]
                j = bj + y
                for z in range(BRICK):
                    o = (x << 6) | (y << 3) | z
                    if not (bits >> z) & 1:
                        vmap[b, o] = -1
                        continue
                    vmap[b, o] = v
                    k = bk + z
                    ijk[v, 0] = i
                    ijk[v, 1] = j
                    ijk[v, 2] = k
                    q = (y << 3) | z
                    # the i-pass at this vertex only (same bits as i_plane)
                    gx, gy, gz, fq = i_point(ring, first, FLAT_PLANE, w0, w1, w2, w3, w4, w5, w6,
                                             y * FLAT_EDGE + z)
                    nx, ny, nz, ok = unit_normal(gx, gy, gz)
                    if not ok:
                        for a in range(3):
                            sa = (((first + 2 + a) % 7) * pl_sz + (y + _HALO - 1) * _LB + z
                                  + _HALO - 1)
                            for c in range(3):
                                for d in range(3):
                                    nb27[(a * 3 + c) * 3 + d] = dring[sa + c * _LB + d]
                        nx, ny, nz = fallback_normal(nb27, 13, 3, 3)
                    sh = vertex_shift(fq, gx, gy, gz, iso, s_out, s_in)
                    nrm[v, 0] = nx
                    nrm[v, 1] = ny
                    nrm[v, 2] = nz
                    pos[v, 0] = origin[0] + spacing * (i + sh * nx)
                    pos[v, 1] = origin[1] + spacing * (j + sh * ny)
                    pos[v, 2] = origin[2] + spacing * (k + sh * nz)
                    shf[v] = sh
                    lab = np.int64(label[b, o])
                    if lab >= ncol:
                        lab = 0
                    w = 0.0
                    ar = 0.0
                    ag = 0.0
                    ab = 0.0
                    if tint_on:
                        if bone[lab] != 0:
                            if (near[b, x] >> np.uint64(q)) & one:
                                w, ar, ag, ab = tint_vertex(keys, vals, density, label, bone,
                                                            colors, origin, spacing, tp, cone,
                                                            i, j, k, nrm[v, 0], nrm[v, 1],
                                                            nrm[v, 2], shf[v])
                    cr, cg, cb = blend(colors[lab, 0], colors[lab, 1], colors[lab, 2], w, ar,
                                        ag, ab)
                    col[v, 0] = cr
                    col[v, 1] = cg
                    col[v, 2] = cb
                    col[v, 3] = ALPHA
                    v += 1
                    n += 1
        b = nbr[b, _NBR_XP]
        r += 1
    return n


@njit(cache=True, nogil=True, parallel=True)
def shade_all_kernel(keys, vals, density, label, nbr, bricks, srf, voff, bone, tint_on, near,
                      colors, W, fp, tp, cone, vmap, ijk, pos, nrm, shf, col, starts, counts,
                      counter, n_workers):
    """Vertex slots, voxels, positions, normals and colours of every vertex:
    brick ``b``'s surface voxels (the bits ``srf[b, 8 x + y]``, bit z) get
    the slots ``voff[b]...`` in (x, y, z) order, the other voxels of
    ``vmap[b]`` -1. Work item ``q`` is the run of bricks along +x from brick
    ``starts[q]`` (:func:`_shade_run`), taken from ``counter`` by
    ``n_workers`` workers (:mod:`bonesim.engine.work_items`); ``counts[q]``:
    its vertices."""
    n_items = starts.shape[0]
    for _ in prange(n_workers):
        dring = np.empty(7 * _LB * _LB, dtype=np.float32)
        rs = np.zeros(_LB * _LB, dtype=np.float32)
        rd = np.zeros(_LB * _LB, dtype=np.float32)
        ring = np.empty(21 * FLAT_PLANE, dtype=np.float32)
        nb27 = np.empty(27, dtype=np.float32)
        while True:
            it = take_item(counter)
            if it >= n_items:
                break
            counts[it] = _shade_run(keys, vals, density, label, nbr, bricks, srf, voff, bone,
                                    tint_on, near, colors, W, fp, tp, cone, vmap, ijk, pos, nrm,
                                    shf, col, starts[it], dring, rs, rd, ring, nb27)
