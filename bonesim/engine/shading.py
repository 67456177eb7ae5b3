"""Vertex positions, normals and colours of the bone surface: smooth bone,
and thin bone that shows what lies beneath.

:class:`bonesim.engine.surface.Surface` gives every surface voxel a vertex;
this module places each vertex and gives it its normal and its colour, over
the whole surface (:meth:`Shader.shade_all`) or again around the voxels a
drill changed (:meth:`Shader.refresh`). Both evaluate the same functions of
the current grid, so an incrementally updated surface equals a rebuilt one
bit for bit.

Definitions
-----------
Vertex normal, vertex position
    :mod:`bonesim.engine.normals`: the gradient of a Gaussian-smoothed
    density over the 7x7x7 voxels around the vertex's voxel gives the
    normal, and one Newton step along it from the voxel's centre onto the
    smoothed density's level set gives the position (``shift`` voxels
    along the normal, stored per vertex as float32). The physics keeps its
    voxels; only the drawn surface is smooth.
Structure beneath, thickness, tint
    :mod:`bonesim.engine.thin_bone`: rays through the bone along ``-n`` and
    on a cone around it (the estimate the drill sound uses), their
    thickness measured from the vertex, and the blend ``W`` toward the
    structures they meet with the weighted colour ``(R, G, B)`` of those.
Vertex colour
    RGBA uint8: ``c = (1 - W) * colors[label] + (R, G, B)`` per channel,
    rounded half up (``floor(x + 0.5)``, at most 255); alpha 255. With
    ``W = 0`` this is exactly the structure's display colour. The density
    does not darken the colour: a partly drilled voxel shows as a vertex
    sunk into the bone, not as a dark spot.

What a drill changes
--------------------
A vertex's normal and position read the densities within
:data:`NORMAL_RADIUS` voxels (Chebyshev distance) of it; its rays, voxels
within :func:`tint_reach` voxels, and only whether they are bone, which a
lowered density that stays > 0 does not change. So after the voxels
``removed`` (density now 0) and ``touched`` (lowered) changed,
:meth:`Shader.refresh` recomputes

* position, normal and colour of every vertex within ``NORMAL_RADIUS`` of
  any of them (this includes every vertex the tessellation created), and
* the colour of every other bone vertex within :func:`tint_reach` of a
  removed voxel one of whose rays passes within one voxel of a removed
  voxel,

and nothing else changes. Rays are cast only from bone voxels that have a
voxel of a non-bone structure (label, whatever its density: labels never
change) within :func:`~bonesim.engine.thin_bone.near_radius` (a ball);
elsewhere no ray can meet a structure. A static 512-bit mask per brick says
which voxels qualify.

Implementation
--------------
The field (gradient and smoothed density) is computed on dense boxes of
densities, separably and plane by plane along i (a ring of seven planes of
the k and j passes), so the working set stays small: for the full shading
(:mod:`bonesim.engine.shading_full`), the boxes of the bricks (the brick
and a 3-voxel halo, 14^3 voxels) along runs of bricks in x, in parallel
over the runs, which also gives each vertex its slot (the surface's build
hands it the surface voxels as bits); for the refresh, the inputs'
bounding box plus ``2 NORMAL_RADIUS``. The refresh's sets of voxels
(inputs, the vertices to refresh, the removed voxels dilated by one) are bit rows over a window around the inputs
(their bounding box plus ``max(tint_reach, 2 NORMAL_RADIUS)``, at most 64
voxels deep along k; inputs spread too far are split into several
windows), one uint64 per ``(i, j)`` row, obtained by shifts and ORs. Rays
read the grid through its hash table. Since every output is the same
expression of the same inputs in both, a refreshed vertex is bit for bit
what a full shading gives.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit
from numba.cpython.unsafe.numbers import trailing_zeros

from bonesim.errors import BonesimError
from bonesim.engine.shading_full import (ALPHA, F_IN as _F_IN, F_ISO as _F_ISO,
                                         F_ORIGIN as _F_ORIGIN, F_OUT as _F_OUT,
                                         F_SPACING as _F_SPACING, N_F as _N_F, NBR_XM as _NBR_XM,
                                         blend as _blend, shade_all_kernel as _shade_all_kernel)
from bonesim.engine.work_items import new_counter, workers
from bonesim.engine.grid import BRICK, BRICK_MASK, BRICK_SHIFT, find_brick, voxel_offset
from bonesim.engine.normals import (GRAD_EPS, N_FIELD, NORMAL_RADIUS, fallback_normal, i_plane,
                                    kj_plane, unit_normal, vertex_shift, normal_weights,
                                    stencil_weights)
from bonesim.engine.shading_params import ShadingParams, default_shading_path, load_shading
from bonesim.engine.thin_bone import (TP_MAX, TP_TAN, as_bone, near_structure, ray_dir,
                                      structure_bits, tint_vertex, beneath, bone_labels, cone_table,
                                      near_radius, ray_params, tint_reach, tint_weight)

__all__ = ["NORMAL_RADIUS", "GRAD_EPS", "ALPHA", "MAX_REACH_VOXELS",
           "ShadingParams", "default_shading_path", "load_shading", "normal_weights",
           "stencil_weights", "tint_weight", "tint_reach", "bone_labels", "beneath", "Shader",
           ]

#: Largest reach [voxels] of the refresh: ``tint_reach`` must not exceed it
#: (a window is at most 64 voxels deep along k).
MAX_REACH_VOXELS = 28

# bit-row sets of the refresh window
_R_ALL, _R_REM, _R_NRM, _R_TINT, _R_REM1, _R_T0 = range(6)
_N_ROWSETS = 6
#: A refresh window holds at most max(_WIN_MIN_VOXELS, _WIN_VOXELS_PER_INPUT *
#: inputs) voxels; inputs spread further are split into several windows.
_WIN_MIN_VOXELS = 32768
_WIN_VOXELS_PER_INPUT = 128
_WIN_DEPTH = 64
# layout of the float64 constants ``fp`` and int64 slots ``ip`` the kernels take
_I_TINT, _I_REACH, _I_MARGIN, _I_NEED = 0, 1, 2, 3   # need: rows, bricks, f32, vertex list
_I_NV = 7                                               # vertices moved, listed in vlist
_N_I = 8


@njit(cache=True, nogil=True)
def _dilate_rows(rows, src, dst, tmp, wd0, wd1, r, zmask):
    """``dst`` = set ``src`` dilated by ``r`` voxels along each axis (a cube
    of Chebyshev radius r); ``tmp`` is clobbered. Sets are offsets into
    ``rows`` of ``wd0 * wd1`` rows, row ``x * wd1 + y``, bit z."""
    one = np.uint64(1)
    nrow = wd0 * wd1
    for q in range(nrow):
        x = rows[src + q]
        for _ in range(r):
            x = x | (x << one) | (x >> one)
        rows[tmp + q] = x & zmask
    for x in range(wd0):
        base = x * wd1
        for y in range(wd1):
            acc = np.uint64(0)
            for yy in range(max(0, y - r), min(wd1, y + r + 1)):
                acc |= rows[tmp + base + yy]
            rows[dst + base + y] = acc
    for x in range(wd0):
        for y in range(wd1):
            acc = np.uint64(0)
            for xx in range(max(0, x - r), min(wd0, x + r + 1)):
                acc |= rows[dst + xx * wd1 + y]
            rows[tmp + x * wd1 + y] = acc
    for q in range(nrow):
        rows[dst + q] = rows[tmp + q]


# layout of the float64 constants and int64 slots passed to _refresh
@njit(cache=True, nogil=True)
def _refresh(keys, vals, density, label, vmap, bone, near, colors, W, fp, tp, cone, ip, removed,
             touched, rows, wbr, f32, vlist, pos, nrm, shf, col):
    """Refresh the vertices near the inputs (see the module docstring) on one
    window: their bounding box plus ``m = ip[_I_MARGIN]`` voxels. The field
    (normals, positions) is computed on the box of the inputs' bounding box plus ``2
    NORMAL_RADIUS`` (its densities and passes in ``f32``).

    Returns the number of vertices refreshed, -1 if the window is too big
    (at most 64 voxels deep along k, and ``max(_WIN_MIN_VOXELS,
    _WIN_VOXELS_PER_INPUT * inputs, (2 m + 16)**3)`` voxels, which a single
    voxel always fits: split the inputs), -2 if the
    scratch is too small (sizes needed in ``ip[_I_NEED:]``; nothing done).
    The slots of the vertices whose position or normal it recomputed are
    listed in ``vlist[:ip[_I_NV]]`` (their triangles' drawn winding may
    change).
    """
    nr = removed.shape[0]
    nt = touched.shape[0]
    n_in = nr + nt
    if n_in == 0:
        return 0
    tint_on = ip[_I_TINT] != 0
    rt = ip[_I_REACH]
    m = ip[_I_MARGIN]
    lo0 = hi0 = np.int64(removed[0, 0] if nr > 0 else touched[0, 0])
    lo1 = hi1 = np.int64(removed[0, 1] if nr > 0 else touched[0, 1])
    lo2 = hi2 = np.int64(removed[0, 2] if nr > 0 else touched[0, 2])
    for q in range(nr):
        lo0 = min(lo0, removed[q, 0])
        hi0 = max(hi0, removed[q, 0])
        lo1 = min(lo1, removed[q, 1])
        hi1 = max(hi1, removed[q, 1])
        lo2 = min(lo2, removed[q, 2])
        hi2 = max(hi2, removed[q, 2])
    for q in range(nt):
        lo0 = min(lo0, touched[q, 0])
        hi0 = max(hi0, touched[q, 0])
        lo1 = min(lo1, touched[q, 1])
        hi1 = max(hi1, touched[q, 1])
        lo2 = min(lo2, touched[q, 2])
        hi2 = max(hi2, touched[q, 2])
    wlo = np.empty(3, dtype=np.int64)
    wlo[0] = lo0 - m
    wlo[1] = lo1 - m
    wlo[2] = lo2 - m
    wd0 = hi0 - lo0 + 1 + 2 * m
    wd1 = hi1 - lo1 + 1 + 2 * m
    wd2 = hi2 - lo2 + 1 + 2 * m
    if wd2 > _WIN_DEPTH or wd0 * wd1 * wd2 > max(_WIN_MIN_VOXELS, _WIN_VOXELS_PER_INPUT * n_in,
                                                 (2 * m + 16) ** 3):
        return -1
    nrow = wd0 * wd1
    blo0 = wlo[0] >> BRICK_SHIFT
    blo1 = wlo[1] >> BRICK_SHIFT
    blo2 = wlo[2] >> BRICK_SHIFT
    bd0 = ((wlo[0] + wd0 - 1) >> BRICK_SHIFT) - blo0 + 1
    bd1 = ((wlo[1] + wd1 - 1) >> BRICK_SHIFT) - blo1 + 1
    bd2 = ((wlo[2] + wd2 - 1) >> BRICK_SHIFT) - blo2 + 1
    off = m - 2 * NORMAL_RADIUS          # the normals' box: [off, wd - off) of the window
    X = wd0 - 2 * off
    Y = wd1 - 2 * off
    Z = wd2 - 2 * off
    n_box = X * Y * Z
    n_k = Y * (Z - 6)
    n_pl = (Y - 6) * (Z - 6)
    need_f = n_box + 2 * n_k + (21 + N_FIELD) * n_pl
    if rows.shape[0] < _N_ROWSETS * nrow or wbr.shape[0] < bd0 * bd1 * bd2 \
            or f32.shape[0] < need_f or vlist.shape[0] < n_box:
        ip[_I_NEED] = _N_ROWSETS * nrow
        ip[_I_NEED + 1] = bd0 * bd1 * bd2
        ip[_I_NEED + 2] = need_f
        ip[_I_NEED + 3] = n_box
        return -2
    ip[_I_NV] = 0
    ld = f32[:n_box]
    rs = f32[n_box:n_box + n_k]
    rd = f32[n_box + n_k:n_box + 2 * n_k]
    ring = f32[n_box + 2 * n_k:n_box + 2 * n_k + 21 * n_pl]
    g = f32[n_box + 2 * n_k + 21 * n_pl:need_f]
    origin = fp[_F_ORIGIN:_F_ORIGIN + 3]
    spacing = fp[_F_SPACING]
    iso = fp[_F_ISO]
    s_out = fp[_F_OUT]
    s_in = fp[_F_IN]
    one = np.uint64(1)
    zmask = np.uint64(0xFFFFFFFFFFFFFFFF) if wd2 == 64 else (one << np.uint64(wd2)) - one
    A = _R_ALL * nrow
    RM = _R_REM * nrow
    NR = _R_NRM * nrow
    TI = _R_TINT * nrow
    T0 = _R_T0 * nrow
    for q in range(2 * nrow):
        rows[A + q] = np.uint64(0)          # ALL and REM are adjacent
    for q in range(nr):
        r = (removed[q, 0] - wlo[0]) * wd1 + removed[q, 1] - wlo[1]
        bit = one << np.uint64(removed[q, 2] - wlo[2])
        rows[A + r] |= bit
        rows[RM + r] |= bit
    for q in range(nt):
        r = (touched[q, 0] - wlo[0]) * wd1 + touched[q, 1] - wlo[1]
        rows[A + r] |= one << np.uint64(touched[q, 2] - wlo[2])
    R1 = _R_REM1 * nrow
    _dilate_rows(rows, A, NR, T0, wd0, wd1, NORMAL_RADIUS, zmask)
    if tint_on and nr > 0:
        _dilate_rows(rows, RM, TI, T0, wd0, wd1, rt, zmask)
        _dilate_rows(rows, RM, R1, T0, wd0, wd1, 1, zmask)
    else:
        for q in range(nrow):
            rows[TI + q] = np.uint64(0)
    # window bricks
    s = 0
    for bi in range(blo0, blo0 + bd0):
        for bj in range(blo1, blo1 + bd1):
            for bk in range(blo2, blo2 + bd2):
                wbr[s] = find_brick(keys, vals, bi, bj, bk)
                s += 1
    # densities of the normals' box
    for x in range(X):
        i = wlo[0] + off + x
        for y in range(Y):
            j = wlo[1] + off + y
            bbase = ((i >> BRICK_SHIFT) - blo0) * bd1 + (j >> BRICK_SHIFT) - blo1
            ob = ((i & BRICK_MASK) << 6) | ((j & BRICK_MASK) << 3)
            li = (x * Y + y) * Z
            z = 0
            while z < Z:
                k = wlo[2] + off + z
                n = min(Z - z, BRICK - (k & BRICK_MASK))
                b = wbr[bbase * bd2 + (k >> BRICK_SHIFT) - blo2]
                if b >= 0:
                    o = ob | (k & BRICK_MASK)
                    for u in range(n):
                        ld[li + z + u] = density[b, o + u]
                else:
                    for u in range(n):
                        ld[li + z + u] = np.float32(0.0)
                z += n
    ncol = colors.shape[0]
    count = 0
    Zo = Z - 6
    sh = off + 3            # window coordinate of the gradient planes' coordinate 0
    # vertices with a new normal (N), plane by plane of the normals' box
    have = 0
    for xo in range(X - 6):
        x = xo + sh
        any_n = False
        for y in range(wd1):
            if rows[NR + x * wd1 + y] != 0:
                any_n = True
                break
        if not any_n:
            continue
        for pl in range(max(have, xo), xo + 7):
            kj_plane(ld, pl, Y, Z, W, rs, rd, ring, pl % 7)
        have = xo + 7
        i_plane(ring, xo, n_pl, W, g)
        i = wlo[0] + x
        for y in range(wd1):
            bits = rows[NR + x * wd1 + y]
            if bits == 0:
                continue
            j = wlo[1] + y
            bbase = ((i >> BRICK_SHIFT) - blo0) * bd1 + (j >> BRICK_SHIFT) - blo1
            while bits != 0:
                z = np.int64(trailing_zeros(bits))
                bits &= bits - one
                k = wlo[2] + z
                b = wbr[bbase * bd2 + (k >> BRICK_SHIFT) - blo2]
                if b < 0:
                    continue
                o = voxel_offset(i, j, k)
                v = vmap[b, o]
                if v < 0:
                    continue
                q = (y - sh) * Zo + z - sh
                gx = g[q]
                gy = g[n_pl + q]
                gz = g[2 * n_pl + q]
                nx, ny, nz, ok = unit_normal(gx, gy, gz)
                if not ok:
                    nx, ny, nz = fallback_normal(ld, ((x - off) * Y + y - off) * Z + z - off, Y, Z)
                sv = vertex_shift(g[3 * n_pl + q], gx, gy, gz, iso, s_out, s_in)
                nrm[v, 0] = nx
                nrm[v, 1] = ny
                nrm[v, 2] = nz
                pos[v, 0] = origin[0] + spacing * (i + sv * nx)
                pos[v, 1] = origin[1] + spacing * (j + sv * ny)
                pos[v, 2] = origin[2] + spacing * (k + sv * nz)
                shf[v] = sv
                vlist[ip[_I_NV]] = v
                ip[_I_NV] += 1
                lab = np.int64(label[b, o])
                if lab >= ncol:
                    lab = 0
                w = 0.0
                ar = 0.0
                ag = 0.0
                ab = 0.0
                if tint_on:
                    if bone[lab] != 0:
                        if (near[b, o >> 6] >> np.uint64(o & 63)) & one:
                            w, ar, ag, ab = tint_vertex(keys, vals, density, label, bone, colors,
                                                  origin, spacing, tp, cone, i, j, k, nrm[v, 0],
                                                  nrm[v, 1], nrm[v, 2], shf[v])
                cr, cg, cb = _blend(colors[lab, 0], colors[lab, 1], colors[lab, 2], w, ar, ag, ab)
                col[v, 0] = cr
                col[v, 1] = cg
                col[v, 2] = cb
                col[v, 3] = ALPHA
                count += 1
    if not tint_on or nr == 0:
        return count
    # vertices whose field stays but one of whose rays may pass a removed voxel
    reach = tp[TP_MAX] / spacing
    tanc = tp[TP_TAN]
    n_rays = cone.shape[0] + 1
    for x in range(wd0):
        i = wlo[0] + x
        for y in range(wd1):
            r = x * wd1 + y
            bits = rows[TI + r] & ~rows[NR + r]
            if bits == 0:
                continue
            j = wlo[1] + y
            bbase = ((i >> BRICK_SHIFT) - blo0) * bd1 + (j >> BRICK_SHIFT) - blo1
            while bits != 0:
                z = np.int64(trailing_zeros(bits))
                bits &= bits - one
                k = wlo[2] + z
                b = wbr[bbase * bd2 + (k >> BRICK_SHIFT) - blo2]
                if b < 0:
                    continue
                o = voxel_offset(i, j, k)
                v = vmap[b, o]
                if v < 0 or not (near[b, o >> 6] >> np.uint64(o & 63)) & one:
                    continue
                lab = np.int64(label[b, o])
                if lab >= ncol or bone[lab] == 0:
                    continue
                nx = np.float64(nrm[v, 0])
                ny = np.float64(nrm[v, 1])
                nz = np.float64(nrm[v, 2])
                hit = False
                for rq in range(n_rays):
                    if rq == 0:
                        dx, dy, dz = nx, ny, nz
                    else:
                        dx, dy, dz, _ = ray_dir(nx, ny, nz, tanc, cone[rq - 1, 0],
                                                 cone[rq - 1, 1])
                    # the ray's box must meet the inputs' box grown by a voxel
                    ex = i - reach * dx
                    ey = j - reach * dy
                    ez = k - reach * dz
                    if (max(i, ex) < lo0 - 1 or min(i, ex) > hi0 + 1 or max(j, ey) < lo1 - 1
                            or min(j, ey) > hi1 + 1 or max(k, ez) < lo2 - 1
                            or min(k, ez) > hi2 + 1):
                        continue
                    if _ray_meets(rows, R1, wlo, wd0, wd1, wd2, i, j, k, -dx, -dy, -dz, reach):
                        hit = True
                        break
                if not hit:
                    continue
                w, ar, ag, ab = tint_vertex(keys, vals, density, label, bone, colors, origin, spacing,
                                      tp, cone, i, j, k, nrm[v, 0], nrm[v, 1], nrm[v, 2], shf[v])
                cr, cg, cb = _blend(colors[lab, 0], colors[lab, 1], colors[lab, 2], w, ar, ag, ab)
                col[v, 0] = cr
                col[v, 1] = cg
                col[v, 2] = cb
                col[v, 3] = ALPHA
                count += 1
    return count


@njit(cache=True, nogil=True)
def _ray_meets(rows, R1, wlo, wd0, wd1, wd2, i, j, k, dx, dy, dz, reach):
    """Whether the segment from voxel ``(i, j, k)`` along the unit ``d`` up
    to ``reach`` voxels passes near the set ``R1`` (the removed voxels
    dilated by one voxel) of the window. Points every voxel are tested
    (and the segment's end): every sample of the ray lies within half a
    voxel of one, so each of its coordinates is within half a voxel of that
    point's, its voxel within one voxel of that point's, and the test never
    misses a removed voxel the ray reads."""
    one = np.uint64(1)
    n_pts = int(math.ceil(reach))
    for q in range(n_pts + 1):
        t = min(np.float64(q), reach)
        x = int(math.floor(i + t * dx + 0.5)) - wlo[0]
        y = int(math.floor(j + t * dy + 0.5)) - wlo[1]
        z = int(math.floor(k + t * dz + 0.5)) - wlo[2]
        if 0 <= x < wd0 and 0 <= y < wd1 and 0 <= z < wd2:
            if (rows[R1 + x * wd1 + y] >> np.uint64(z)) & one:
                return True
    return False


class Shader:
    """Positions, normals and colours of one surface's vertices (see the
    module docstring).

    Parameters
    ----------
    grid : Grid
        The tissue the surface was built from (its labels and hash table are
        read here; labels never change).
    nbr : (n_bricks, 27) int32
        Each brick's neighbours (``bonesim.engine.surface``'s table).
    colors : (n_labels + 1, 3) uint8
        Display colour per label (checked by the caller).
    bone : (n_labels + 1,) bool or 0/1 array_like, optional
        Which labels are bone. None: no tint (the surface shows the
        structures' own colours).
    params : ShadingParams, optional
        Default: the shipped ``shading.toml``.
    """

    def __init__(self, grid, nbr, colors, bone=None, params: ShadingParams | None = None):
        self.params = load_shading() if params is None else params
        if not isinstance(self.params, ShadingParams):
            raise TypeError(f"shading must be a ShadingParams, got "
                            f"{type(self.params).__name__}")
        p = self.params
        self.colors = colors
        self._nbr = nbr
        self._W = stencil_weights(p.sigma_voxels)
        self.spacing = float(grid.spacing_mm)
        self._origin = np.asarray(grid.origin_mm, dtype=np.float64).copy()
        self.tint_on = bone is not None
        n_rows = colors.shape[0]
        self.bone = as_bone(bone, n_rows) if bone is not None else np.zeros(n_rows, np.uint8)
        self.reach = tint_reach(p, self.spacing) if self.tint_on else 0
        if self.reach > MAX_REACH_VOXELS:
            raise BonesimError(
                f"'start_mm' = {p.start_mm} reaches {self.reach} voxels of "
                f"{self.spacing} mm (at most {MAX_REACH_VOXELS}); lower it", None,
                "thin_bone")
        self.margin = max(self.reach, 2 * NORMAL_RADIUS)
        self._tp = ray_params(p, self.spacing)
        self._cone = cone_table(p)
        self._near = np.zeros((grid.n_bricks, BRICK), dtype=np.uint64)
        if self.tint_on:
            bits = np.empty((grid.n_bricks, BRICK), dtype=np.uint64)
            if structure_bits(grid.label, self.bone, bits):
                # (C order: the warm-up's one-brick grid compiles this layout)
                near_structure(grid.keys, grid.vals, np.ascontiguousarray(grid.bricks), bits,
                                near_radius(p, self.spacing), self._near)
        self._fp = np.zeros(_N_F)
        self._fp[_F_ORIGIN:_F_ORIGIN + 3] = self._origin
        self._fp[_F_SPACING] = self.spacing
        self._fp[_F_ISO] = p.iso_density
        self._fp[_F_OUT] = p.max_out_voxels
        self._fp[_F_IN] = p.max_in_voxels
        self._ip = np.zeros(_N_I, dtype=np.int64)
        self._ip[_I_TINT] = 1 if self.tint_on else 0
        self._ip[_I_REACH] = self.reach
        self._ip[_I_MARGIN] = self.margin
        self._rows = np.zeros(_N_ROWSETS * 1024, dtype=np.uint64)
        self._wbr = np.zeros(64, dtype=np.int32)
        self._f32 = np.zeros(1 << 16, dtype=np.float32)
        self._vlist = np.zeros(1 << 12, dtype=np.int32)

    @property
    def normal_reach(self) -> int:
        """Voxels [Chebyshev] around a changed voxel whose normals and
        positions may change."""
        return NORMAL_RADIUS

    def shade_all(self, grid, srf, voff, vmap, ijk, pos, nrm, shift, col) -> int:
        """Give every surface voxel its vertex slot and the vertex its voxel,
        position, normal, shift and colour; returns the number of vertices.

        Parameters
        ----------
        grid : Grid
        srf : (n_bricks, 64) uint8
            Surface voxels: bit ``z`` of ``srf[b, 8 x + y]`` set where voxel
            ``(x, y, z)`` of brick ``b`` (brick-relative) is one.
        voff : (n_bricks + 1,) int64
            Slot of brick ``b``'s first vertex; its vertices take the slots
            ``voff[b] .. voff[b + 1] - 1`` in ``(x, y, z)`` order (so
            ``voff[b + 1] - voff[b]`` is its number of surface voxels).
        vmap : (n_bricks, 512) int32
            Written: vertex slot per voxel, -1 for none.
        ijk : (vcap, 3) int32
            Written: each vertex's voxel ``(i, j, k)``.
        pos, nrm : (vcap, 3) float32
            Written: positions [mm] and unit normals.
        shift : (vcap,) float32
            Written: each vertex's offset from its voxel's centre along its
            normal [voxels].
        col : (vcap, 4) uint8
            Written: RGBA.
        """
        if srf.shape != (grid.n_bricks, BRICK * BRICK) or srf.dtype != np.uint8:
            raise ValueError(f"srf must be a ({grid.n_bricks}, 64) uint8 array")
        if voff.shape != (grid.n_bricks + 1,) or voff[-1] > pos.shape[0]:
            raise ValueError("voff must hold n_bricks + 1 slots within the vertex arrays")
        # the runs of bricks along +x: from each brick without a -x neighbour
        starts = np.flatnonzero(self._nbr[:, _NBR_XM] < 0)
        counts = np.zeros(starts.shape[0], dtype=np.int64)
        _shade_all_kernel(grid.keys, grid.vals, grid.density_ro, grid.label, self._nbr,
                          grid.bricks, srf, voff, self.bone, self.tint_on, self._near,
                          self.colors, self._W, self._fp, self._tp, self._cone, vmap, ijk, pos,
                          nrm, shift, col, starts, counts, new_counter(), workers())
        return int(counts.sum())

    def refresh(self, grid, vmap, pos, nrm, shift, col, removed, touched, moved=None) -> int:
        """Recompute what ``removed`` and ``touched`` (int32 (n, 3) C arrays,
        validated by the caller) can have changed (arrays as for
        :meth:`shade_all`); returns the number of vertices refreshed (a
        vertex near several windows counts once per window).

        ``moved(slots)``, if given, is called after each window with the
        (int32) slots of the vertices whose position or normal that window
        recomputed (a view of scratch memory, valid during the call)."""
        if removed.shape[0] == 0 and touched.shape[0] == 0:
            return 0
        n = 0
        stack = [(removed, touched)]
        while stack:
            rem, tch = stack.pop()
            while True:
                got = _refresh(grid.keys, grid.vals, grid.density_ro, grid.label, vmap, self.bone,
                               self._near, self.colors, self._W, self._fp, self._tp, self._cone,
                               self._ip, rem, tch, self._rows, self._wbr, self._f32,
                               self._vlist, pos, nrm, shift, col)
                if got != -2:
                    break
                need = self._ip[_I_NEED:_I_NEED + 4].tolist()
                for name, k in (("_rows", 0), ("_wbr", 1), ("_f32", 2), ("_vlist", 3)):
                    cur = getattr(self, name)
                    if cur.shape[0] < need[k]:
                        n_new = max(need[k], 2 * cur.shape[0])
                        setattr(self, name, np.zeros((n_new,) + cur.shape[1:], dtype=cur.dtype))
            if got >= 0:
                n += got
                if moved is not None:
                    moved(self._vlist[:self._ip[_I_NV]])
            else:
                stack.extend(_split(rem, tch, self.margin))
        return int(n)


def _split(rem, tch, margin):
    """Two non-empty halves of inputs that do not fit one window (so their
    bounding box is not a single voxel), split across the middle of their
    bounding box: along k if a window of ``margin`` around it is deeper than
    64 voxels, else along its longest axis."""
    both = np.concatenate([rem, tch]) if tch.shape[0] else rem
    lo = both.min(axis=0)
    hi = both.max(axis=0)
    ax = 2 if hi[2] - lo[2] + 1 + 2 * margin > _WIN_DEPTH else int(np.argmax(hi - lo))
    mid = (int(lo[ax]) + int(hi[ax])) // 2
    out = []
    for lower in (True, False):
        out.append((np.ascontiguousarray(rem[(rem[:, ax] <= mid) == lower]),
                    np.ascontiguousarray(tch[(tch[:, ax] <= mid) == lower])))
    return out
