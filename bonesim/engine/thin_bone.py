"""Thin bone that shows what lies beneath: per bone vertex, the thickness of
the bone over a non-bone structure (sigmoid sinus, dura, facial nerve...)
and the weight with which the vertex takes on that structure's colour.

Definitions
-----------
Bone and the structure beneath
    A voxel is *bone* when its density is > 0 and its label is one of the
    bone labels given to :meth:`Surface.build` (structures of kind
    ``"bone"``, :func:`bone_labels`). From the centre ``p`` of a bone
    vertex, a ray along ``-n`` (``n`` as stored, float32) is marched through
    the grid by :func:`bonesim.engine.thickness.exit_ray`, the estimate the drill
    sound uses (steps of ``STEP_FRACTION`` voxel, nearest-voxel samples,
    bisection), up to ``[thin_bone] start_mm``. If it leaves the bone into
    an occupied voxel of a non-bone structure ``s``, a second ray along
    ``+n`` measures the bone behind ``p`` and the *thickness* is the chord
    ``t = min(s_in + s_back, start_mm)``; a slab of ``N`` voxels measured
    along its normal reads ``N * spacing_mm`` (exactly at 0.5 or 0.25 mm
    voxels, else to the bisection's precision). Otherwise (the ray reaches
    empty space, or no exit within ``start_mm``) there is no structure
    beneath.
Tint weight
    ``w(t) = max_weight * x**2 * (3 - 2 x)`` with ``x = clip((start_mm - t)
    / (start_mm - full_mm), 0, 1)``: 0 at ``start_mm`` and above, rising
    smoothly to ``max_weight`` at ``full_mm`` and below
    (:func:`tint_weight`). ``w = 0`` without a structure beneath, at vertices
    that are not bone, and when no bone labels were given.

Static mask
    A ray can only meet a structure voxel within :func:`tint_reach` voxels
    (Chebyshev) of its start; :func:`_near_structure` marks, per brick as a
    512-bit mask, the voxels with a voxel of a non-bone label that close
    (labels never change, so the mask holds for the grid's life), and rays
    are cast from those voxels only.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from bonesim.engine.grid import BRICK, find_brick
from bonesim.engine.shading_params import ShadingParams, load_shading
from bonesim.engine.thickness import STEP_FRACTION, exit_ray

__all__ = ["tint_reach", "bone_labels", "tint_weight", "beneath"]


def tint_reach(params: ShadingParams, spacing_mm: float) -> int:
    """Chebyshev distance [voxels] within which a vertex's rays sample:
    ``floor(start_mm / spacing_mm + 0.5) + 1`` (samples lie closer than
    ``start_mm``; the ``+ 1`` covers rounding)."""
    return int(math.floor(params.start_mm / float(spacing_mm) + 0.5)) + 1


def bone_labels(structures) -> np.ndarray:
    """(n + 1,) uint8 mask of the grid labels that are bone: 1 for label
    ``s >= 1`` when ``structures[s - 1].kind == "bone"``, 0 for label 0."""
    out = np.zeros(len(structures) + 1, dtype=np.uint8)
    for s, st in enumerate(structures, start=1):
        out[s] = 1 if st.kind == "bone" else 0
    return out


@njit(cache=True, nogil=True, inline="always")
def _tint_weight(t, start, full, wmax):
    if t >= start:
        return 0.0
    if t <= full:
        return wmax
    x = (start - t) / (start - full)
    return wmax * x * x * (3.0 - 2.0 * x)


def tint_weight(t_mm, params: ShadingParams | None = None):
    """Blend weight toward the structure beneath at bone thickness ``t_mm`` [mm].

    Parameters
    ----------
    t_mm : float or array_like
        Thickness [mm].
    params : ShadingParams, optional
        Default: :func:`load_shading` ``()``.

    Returns
    -------
    float or ndarray
        ``w(t)`` of the module docstring, in ``[0, max_weight]``.
    """
    p = load_shading() if params is None else params
    t = np.asarray(t_mm, dtype=np.float64)
    out = np.array([_tint_weight(float(v), p.start_mm, p.full_mm, p.max_weight)
                    for v in t.reshape(-1)]).reshape(t.shape)
    return float(out) if out.ndim == 0 else out


@njit(cache=True, nogil=True, inline="always")
def _beneath_at(keys, vals, density, label, bone, origin, spacing, step, max_mm,
                i, j, k, nx, ny, nz):
    """(thickness [mm], structure label) beneath the bone voxel ``(i, j, k)``
    along ``-n``; label 0 when no structure is met (thickness ``max_mm``)."""
    inv_h = 1.0 / spacing
    px = origin[0] + spacing * i
    py = origin[1] + spacing * j
    pz = origin[2] + spacing * k
    s_in, met = exit_ray(keys, vals, density, label, bone, True, origin, inv_h,
                         px, py, pz, -nx, -ny, -nz, step, max_mm, True)
    if met == 0:
        return max_mm, 0
    s_back, _ = exit_ray(keys, vals, density, label, bone, True, origin, inv_h,
                         px, py, pz, nx, ny, nz, step, max_mm)
    return min(s_in + s_back, max_mm), met


@njit(cache=True, nogil=True)
def _tint(keys, vals, density, label, bone, origin, spacing, tp, i, j, k, nx, ny, nz):
    """(structure label, weight) of the bone vertex at voxel ``(i, j, k)``
    with the (float32) normal ``n``; ``tp``: ray step, start_mm, full_mm,
    max_weight. Structure 0 and weight 0 when none is met."""
    t, met = _beneath_at(keys, vals, density, label, bone, origin, spacing, tp[0], tp[1],
                         i, j, k, np.float64(nx), np.float64(ny), np.float64(nz))
    if met == 0:
        return 0, 0.0
    return met, _tint_weight(t, tp[1], tp[2], tp[3])


@njit(cache=True, nogil=True)
def _structure_bits(label, bone, bits):
    """``bits[b]``: 512-bit mask of the voxels of brick ``b`` whose label is
    neither 0 nor bone (bit ``o & 63`` of word ``o >> 6``, so word ``x``
    holds the ``(y, z)`` plane ``x`` of the brick, bit ``8 y + z``).
    Returns whether any is set."""
    anything = False
    for b in range(label.shape[0]):
        for w in range(BRICK):
            acc = np.uint64(0)
            for u in range(64):
                lab = label[b, w * 64 + u]
                if lab != 0 and (lab >= bone.shape[0] or bone[lab] == 0):
                    acc |= np.uint64(1) << np.uint64(u)
            bits[b, w] = acc
            if acc != 0:
                anything = True
    return anything


@njit(cache=True, nogil=True, parallel=True)
def _near_structure(keys, vals, bricks, bits, reach, near):
    """``near[b]``: 512-bit mask (as in :func:`_structure_bits`) of the
    voxels within ``reach`` voxels (Chebyshev) of a structure voxel of
    ``bits``. Labels never change, so this holds for the grid's whole
    life."""
    n = bricks.shape[0]
    L = BRICK + 2 * reach                 # at most 8 + 2 * 28 = 64 bits
    one = np.uint64(1)
    full = np.uint64(0xFFFFFFFFFFFFFFFF) if L == 64 else (one << np.uint64(L)) - one
    byte = np.uint64(0xFF)
    nbb = (reach + BRICK - 1) // BRICK    # bricks the box reaches on each side
    for b in prange(n):
        for w in range(BRICK):
            near[b, w] = np.uint64(0)
        rows = np.zeros(L * L, dtype=np.uint64)
        anything = False
        for di in range(-nbb, nbb + 1):
            for dj in range(-nbb, nbb + 1):
                for dk in range(-nbb, nbb + 1):
                    nb = find_brick(keys, vals, bricks[b, 0] + di, bricks[b, 1] + dj,
                                    bricks[b, 2] + dk)
                    if nb < 0:
                        continue
                    # box row (x, y), bit z  <->  voxel (x - reach, ...) of brick b
                    zs = dk * BRICK + reach
                    for x in range(BRICK):
                        w = bits[nb, x]
                        if w == 0:
                            continue
                        bx = di * BRICK + x + reach
                        if bx < 0 or bx >= L:
                            continue
                        for y in range(BRICK):
                            by = dj * BRICK + y + reach
                            r = (w >> np.uint64(8 * y)) & byte
                            if r == 0 or by < 0 or by >= L:
                                continue
                            if zs >= 0:
                                r = r << np.uint64(zs)
                            else:
                                r = r >> np.uint64(-zs)
                            rows[bx * L + by] |= r & full
                            anything = True
        if not anything:
            continue
        tmp = np.zeros(L * L, dtype=np.uint64)
        for q in range(L * L):                  # along k
            v = rows[q]
            for _ in range(reach):
                v = v | (v << one) | (v >> one)
            rows[q] = v & full
        for x in range(L):                      # along j
            for y in range(reach, reach + BRICK):
                acc = np.uint64(0)
                for yy in range(y - reach, y + reach + 1):
                    acc |= rows[x * L + yy]
                tmp[x * L + y] = acc
        for x in range(reach, reach + BRICK):   # along i, and out
            for y in range(reach, reach + BRICK):
                acc = np.uint64(0)
                for xx in range(x - reach, x + reach + 1):
                    acc |= tmp[xx * L + y]
                row = (acc >> np.uint64(reach)) & byte
                near[b, x - reach] |= row << np.uint64(8 * (y - reach))


@njit(cache=True, nogil=True)
def _beneath_many(keys, vals, density, label, bone, origin, spacing, step, max_mm, ijk,
                  nrm, t_out, s_out):
    for q in range(ijk.shape[0]):
        t, s = _beneath_at(keys, vals, density, label, bone, origin, spacing, step, max_mm,
                           ijk[q, 0], ijk[q, 1], ijk[q, 2], np.float64(nrm[q, 0]),
                           np.float64(nrm[q, 1]), np.float64(nrm[q, 2]))
        t_out[q] = t
        s_out[q] = s


def _as_bone(bone, n_rows):
    b = np.asarray(bone)
    if b.shape != (n_rows,):
        raise ValueError(f"bone must have one entry per colour row ({n_rows}), got shape "
                         f"{b.shape}")
    if b.dtype != np.bool_ and not np.issubdtype(b.dtype, np.integer):
        raise TypeError(f"bone must hold booleans or 0/1, got {b.dtype}")
    if not np.isin(b, (0, 1)).all():
        raise ValueError("bone must hold booleans or 0/1")
    out = b.astype(np.uint8)
    out[0] = 0                      # label 0 is empty space
    return out


def beneath(grid, ijk, normals, bone, params: ShadingParams | None = None):
    """Thickness and structure beneath bone voxels (see the module docstring).

    Parameters
    ----------
    grid : Grid
        The tissue.
    ijk : (n, 3) int array_like
        Voxels (bone surface voxels, usually).
    normals : (n, 3) array_like
        Unit outward normals; rays go along ``-normals`` (cast to float32
        first, as stored on a surface).
    bone : (n_labels + 1,) bool or 0/1 array_like
        Which labels are bone (:func:`bone_labels`).
    params : ShadingParams, optional
        Default: the shipped file; rays stop at ``start_mm``.

    Returns
    -------
    thickness : (n,) float64
        Chord through the bone [mm] where a structure is met, else
        ``start_mm``.
    structure : (n,) int64
        Label of the structure met, 0 for none.
    """
    p = load_shading() if params is None else params
    ijk = np.ascontiguousarray(np.asarray(ijk).reshape(-1, 3), dtype=np.int64)
    nrm = np.ascontiguousarray(np.asarray(normals, dtype=np.float32).reshape(-1, 3))
    if nrm.shape[0] != ijk.shape[0]:
        raise ValueError("ijk and normals must have the same length")
    bone_u8 = _as_bone(bone, len(bone))
    if grid.label.size and int(grid.label.max()) >= len(bone_u8):
        raise ValueError(f"bone has {len(bone_u8)} entries but the grid uses label "
                         f"{int(grid.label.max())}")
    t = np.empty(ijk.shape[0])
    s = np.empty(ijk.shape[0], dtype=np.int64)
    _beneath_many(grid.keys, grid.vals, grid.density, grid.label, bone_u8,
                  np.asarray(grid.origin_mm, dtype=np.float64), float(grid.spacing_mm),
                  STEP_FRACTION * float(grid.spacing_mm), p.start_mm, ijk, nrm, t, s)
    return t, s
