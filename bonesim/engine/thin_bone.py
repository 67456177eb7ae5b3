"""Thin bone that shows what lies beneath: per bone vertex, the thickness of
the bone over a non-bone structure (sigmoid sinus, dura, facial nerve...)
and how much of that structure's colour the vertex takes on.

Definitions
-----------
Bone and the structure beneath
    A voxel is *bone* when its density is > 0 and its label is one of the
    bone labels given to :meth:`Surface.build` (structures of kind
    ``"bone"``, :func:`bone_labels`).
Rays
    From the centre ``c`` of a bone vertex's voxel, rays go into the bone
    along ``-d_q`` for ``q = 0 .. K`` (``K = [thin_bone] cone_rays``): ``d_0
    = n`` (the stored float32 normal, in float64) and, on a cone of
    half-angle ``alpha = cone_deg`` around it, ``d_q = (n + tan(alpha)
    (cos(phi_q) b1 + sin(phi_q) b2)) / m_q`` with ``phi_q = 2 pi (q - 1) /
    K``, ``(b1, b2)`` the orthonormal basis of the plane normal to ``n`` of
    :func:`_basis` (Frisvad's, continuous in ``n`` except at ``n = -z``),
    ``m_q`` the norm of the sum (so ``d_q . n = 1 / m_q``; ``m_0 = 1``).
    Each ray is marched by :func:`_march` (the drill sound's estimate,
    :func:`bonesim.engine.thickness.exit_ray`, with coarser steps: samples
    every :data:`TINT_STEP_FRACTION` voxel at the nearest voxel, then
    :data:`TINT_BISECT_ITERS` bisections of the last step, ``1/64`` voxel:
    plenty for a colour) up to ``start_mm`` (:func:`ray_length_mm`).
Thickness along a ray
    If the ray leaves the bone into an occupied voxel of a non-bone
    structure ``s_q`` at distance ``e_q`` from ``c``, the bone along it,
    measured from the vertex's surface, is ``t_q = max(0, e_q + spacing_mm
    * shift * m_q)``: the vertex lies ``shift`` voxels out of ``c`` along
    ``n`` (:mod:`bonesim.engine.normals`), which a plane through it puts
    ``shift * m_q`` voxels out along ``d_q``. A slab of ``N`` voxels whose
    vertex sits on the voxels' face (``shift = 1/2``) reads ``N *
    spacing_mm`` along its normal (to the bisection's precision). A ray
    that reaches empty space, or no exit in time, meets no structure (``s_q = 0``).
Tint weight and colour
    ``w(t) = max_weight * x**2 * (3 - 2 x)`` with ``x = clip((start_mm - t)
    / (start_mm - full_mm), 0, 1)`` (:func:`tint_weight`): 0 at ``start_mm``
    and above, rising smoothly to ``max_weight`` at ``full_mm`` and below.
    ``w_q = w(t_q)`` where ``s_q`` is a structure, else 0. The vertex's
    colour (:mod:`bonesim.engine.shading`) is its own blended toward the
    rays' structures: ``W = sum w_q / (K + 1)`` of its own and ``sum w_q
    colors[s_q] / (K + 1)`` of theirs. Averaging over the cone is what
    makes the tint a band that deepens smoothly as the bone thins: one ray
    alone follows the voxel staircase of the structure's wall, and
    neighbouring vertices would disagree by a voxel's worth of thickness.
    Without bone labels, at vertices that are not bone, and where no ray
    meets a structure, ``W = 0``.

Static mask
    A ray's samples lie within ``start_mm`` of its start and each reads the
    voxel whose centre is nearest, so a ray can only meet a structure voxel
    whose centre lies within :func:`near_radius` ``= start_mm / spacing_mm +
    sqrt(3) / 2`` voxels (Euclidean) of its start. :func:`near_structure`
    marks, per brick as a 512-bit mask, the voxels with a voxel of a
    non-bone label that close (labels never change, so the mask holds for
    the grid's life), and rays are cast from those voxels only. (A ball, not
    the cube of :func:`tint_reach`: a third fewer vertices cast rays.)
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from bonesim.engine.grid import BRICK, BRICK_SHIFT, find_brick, voxel_offset
from bonesim.engine.kernel_args import filled
from bonesim.engine.shading_params import ShadingParams, load_shading

__all__ = ["TINT_STEP_FRACTION", "TINT_BISECT_ITERS", "tint_reach", "near_radius",
           "ray_length_mm",
           "cone_table", "ray_params", "bone_labels", "tint_weight", "beneath"]


def tint_reach(params: ShadingParams, spacing_mm: float) -> int:
    """Chebyshev distance [voxels] within which a vertex's rays sample:
    ``floor(start_mm / spacing_mm + 0.5) + 1`` (samples lie closer than
    ``start_mm``, :func:`ray_length_mm`; the ``+ 1`` covers rounding)."""
    return int(math.floor(params.start_mm / float(spacing_mm) + 0.5)) + 1


def near_radius(params: ShadingParams, spacing_mm: float) -> float:
    """Euclidean distance [voxels] from a ray's start within which every
    voxel centre its samples read lies: ``ray_length_mm / spacing_mm +
    sqrt(3) / 2`` (a sample is at most half a voxel's diagonal from the
    nearest centre). Its floor is at most :func:`tint_reach`."""
    return ray_length_mm(params, spacing_mm) / float(spacing_mm) + 0.5 * math.sqrt(3.0)


def ray_length_mm(params: ShadingParams, spacing_mm: float) -> float:
    """How far [mm] the thin-bone rays march from a voxel centre:
    ``start_mm``. (A vertex sunk ``max_in_voxels`` into its voxel measures
    from up to ``max_in_voxels * m_q`` voxels inside the centre, so bone up
    to that much thinner than ``start_mm``, where the weight is still below
    a hundredth of ``max_weight``, reads as thick; the rays, and so the
    refresh's reach and a fragment's margin, stay as short as they can.)"""
    return float(params.start_mm)


def cone_table(params: ShadingParams) -> np.ndarray:
    """(K, 2) float64 ``cos(phi_q), sin(phi_q)`` of the cone's rays
    ``q = 1 .. K`` (module docstring), ``K = cone_rays``."""
    k = int(params.cone_rays)
    phi = 2.0 * np.pi * np.arange(k, dtype=np.float64) / max(k, 1)
    return np.ascontiguousarray(np.stack([np.cos(phi), np.sin(phi)], axis=1).reshape(k, 2))


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


#: Step of the thin-bone rays as a fraction of the voxel edge. Samples every
#: half voxel read every voxel a ray passes through except where it only
#: grazes a corner (a one-voxel gap crossed on the diagonal), which is no
#: matter for a colour; half the drill sound's samples.
TINT_STEP_FRACTION = 0.5
#: Bisections of the last step where a thin-bone ray leaves the bone: its
#: exit is then known to ``TINT_STEP_FRACTION / 2**TINT_BISECT_ITERS`` voxel.
TINT_BISECT_ITERS = 5
_NO_BRICK = -2


@njit(cache=True, nogil=True)
def _march(keys, vals, density, label, bone, origin, inv_h, px, py, pz, dx, dy, dz, step,
           max_mm):
    """March from ``p`` along the unit ``d`` [mm] until the ray leaves the
    bone: ``(distance [mm], label)`` of the occupied non-bone voxel it
    enters, ``(max_mm, 0)`` if it enters empty space, ``(max_mm, -1)`` if it
    is still in bone at ``max_mm``.

    Samples every ``step`` [mm] and at ``max_mm``, at the nearest voxel
    centre; *bone* is
    density > 0 and a label ``l`` with ``bone[l] != 0``. At the first sample
    not in bone the last step is bisected :data:`TINT_BISECT_ITERS` times
    and the middle of the last bracket returned. The brick of the last
    sample is cached (consecutive samples mostly share it)."""
    cbi = cbj = cbk = np.int64(0)
    cb = np.int64(_NO_BRICK)
    lo = 0.0
    hi = min(step, max_mm)
    marching = True
    met = 0
    iters = 0
    while True:
        t = hi if marching else 0.5 * (lo + hi)
        i = int(math.floor((px + t * dx - origin[0]) * inv_h + 0.5))
        j = int(math.floor((py + t * dy - origin[1]) * inv_h + 0.5))
        k = int(math.floor((pz + t * dz - origin[2]) * inv_h + 0.5))
        bi, bj, bk = i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT
        if bi != cbi or bj != cbj or bk != cbk or cb == _NO_BRICK:
            cbi, cbj, cbk = bi, bj, bk
            cb = np.int64(find_brick(keys, vals, bi, bj, bk))
        inside = False
        lab = 0
        if cb >= 0:
            o = voxel_offset(i, j, k)
            if density[cb, o] > 0.0:
                lab = np.int64(label[cb, o])
                inside = bone[lab] != 0
        if marching:
            if inside:
                if hi >= max_mm:
                    return max_mm, -1           # still in bone: thick
                lo = hi
                hi = min(hi + step, max_mm)
            else:
                if lab == 0:
                    return max_mm, 0            # empty space: no structure beneath
                marching = False
                met = lab
        else:
            if inside:
                lo = t
            else:
                hi = t
            iters += 1
            if iters == TINT_BISECT_ITERS:
                return 0.5 * (lo + hi), met


# layout of the ray parameters ``tp`` (float64) the kernels take
TP_STEP, TP_START, TP_FULL, TP_WMAX, TP_TAN, TP_MAX = range(6)
N_TP = 6


def ray_params(params: ShadingParams, spacing_mm: float) -> np.ndarray:
    """(N_TP,) float64 ``tp`` of the kernels: ray step [mm], ``start_mm``,
    ``full_mm``, ``max_weight``, ``tan(cone_deg)``, ray length [mm]."""
    tp = np.zeros(N_TP)
    tp[TP_STEP] = TINT_STEP_FRACTION * float(spacing_mm)
    tp[TP_START] = params.start_mm
    tp[TP_FULL] = params.full_mm
    tp[TP_WMAX] = params.max_weight
    tp[TP_TAN] = math.tan(math.radians(params.cone_deg))
    tp[TP_MAX] = ray_length_mm(params, spacing_mm)
    return tp


@njit(cache=True, nogil=True, inline="always")
def _basis(nx, ny, nz):
    """Orthonormal ``b1, b2`` normal to the unit ``n`` (Frisvad 2012),
    continuous in ``n`` except at ``n = -z``."""
    if nz < -0.9999999:
        return 0.0, -1.0, 0.0, -1.0, 0.0, 0.0
    a = 1.0 / (1.0 + nz)
    b = -nx * ny * a
    return 1.0 - nx * nx * a, b, -nx, b, 1.0 - ny * ny * a, -ny


@njit(cache=True, nogil=True, inline="always")
def ray_dir(nx, ny, nz, tanc, cq, sq):
    """Unit direction ``d`` of a cone ray (module docstring) and ``m = 1 /
    (d . n)``; ``tanc = 0`` gives ``(n, 1)``."""
    b1x, b1y, b1z, b2x, b2y, b2z = _basis(nx, ny, nz)
    dx = nx + tanc * (cq * b1x + sq * b2x)
    dy = ny + tanc * (cq * b1y + sq * b2y)
    dz = nz + tanc * (cq * b1z + sq * b2z)
    m = math.sqrt(dx * dx + dy * dy + dz * dz)
    return dx / m, dy / m, dz / m, m


@njit(cache=True, nogil=True, inline="always")
def _ray_thickness(keys, vals, density, label, bone, origin, spacing, tp, i, j, k,
                   dx, dy, dz, m, shift):
    """(thickness [mm], structure label) along ``-d`` from the centre of bone
    voxel ``(i, j, k)``, measured from the vertex ``shift`` voxels out along
    its normal (module docstring); ``(start_mm, 0)`` when the ray reaches
    empty space, ``(start_mm, -1)`` when it is still in bone at its end."""
    px = origin[0] + spacing * i
    py = origin[1] + spacing * j
    pz = origin[2] + spacing * k
    e, met = _march(keys, vals, density, label, bone, origin, 1.0 / spacing, px, py, pz,
                    -dx, -dy, -dz, tp[TP_STEP], tp[TP_MAX])
    if met <= 0:
        return tp[TP_START], met
    return max(0.0, e + spacing * shift * m), met


@njit(cache=True, nogil=True)
def tint_vertex(keys, vals, density, label, bone, colors, origin, spacing, tp, cone, i, j, k,
          nx, ny, nz, shift):
    """``(W, R, G, B)`` of the bone vertex at voxel ``(i, j, k)`` with the
    (float32) normal ``n`` and ``shift``: the blend weight toward the
    structures beneath and their colours, weighted, both averaged over the
    rays (module docstring). All 0 when no ray meets a structure."""
    nx = np.float64(nx)
    ny = np.float64(ny)
    nz = np.float64(nz)
    shift = np.float64(shift)
    ncol = colors.shape[0]
    wsum = 0.0
    ar = 0.0
    ag = 0.0
    ab = 0.0
    n_rays = cone.shape[0] + 1
    for q in range(n_rays):
        if q == 0:
            dx, dy, dz, m = nx, ny, nz, 1.0
        else:
            dx, dy, dz, m = ray_dir(nx, ny, nz, tp[TP_TAN], cone[q - 1, 0], cone[q - 1, 1])
        t, met = _ray_thickness(keys, vals, density, label, bone, origin, spacing, tp,
                                i, j, k, dx, dy, dz, m, shift)
        if met <= 0 or met >= ncol:
            continue
        w = _tint_weight(t, tp[TP_START], tp[TP_FULL], tp[TP_WMAX])
        wsum += w
        ar += w * np.float64(colors[met, 0])
        ag += w * np.float64(colors[met, 1])
        ab += w * np.float64(colors[met, 2])
    inv = 1.0 / n_rays
    return wsum * inv, ar * inv, ag * inv, ab * inv


@njit(cache=True, nogil=True)
def structure_bits(label, bone, bits):
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
def near_structure(keys, vals, bricks, bits, radius, near):
    """``near[b]``: 512-bit mask (as in :func:`structure_bits`) of the
    voxels within ``radius`` voxels (Euclidean, centre to centre) of a
    structure voxel of ``bits``. Labels never change, so this holds for the
    grid's whole life.

    Per brick, the structure bits of the box of the brick plus ``r =
    floor(radius)`` voxels on each side are gathered as bit rows along k
    (``L = 8 + 2 r <= 64`` bits), dilated along k by each half-length ``h``
    a ball's chord can have, and ORed into each output row from the rows at
    offsets ``(dx, dy)``, each dilated by ``h = floor(sqrt(radius**2 - dx**2
    - dy**2))``: the union of the balls."""
    n = bricks.shape[0]
    reach = int(math.floor(radius))
    L = BRICK + 2 * reach                 # at most 8 + 2 * 28 = 64 bits
    r2 = radius * radius
    full = np.uint64(0xFFFFFFFFFFFFFFFF) if L == 64 else (np.uint64(1) << np.uint64(L)) - \
        np.uint64(1)
    one = np.uint64(1)
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
        # zd[h]: the rows dilated by h along k
        zd = np.empty((reach + 1) * L * L, dtype=np.uint64)
        for q in range(L * L):
            v = rows[q]
            zd[q] = v
            for h in range(1, reach + 1):
                v = (v | (v << one) | (v >> one)) & full
                zd[h * L * L + q] = v
        for x in range(reach, reach + BRICK):
            for y in range(reach, reach + BRICK):
                acc = np.uint64(0)
                for dx in range(-reach, reach + 1):
                    for dy in range(-reach, reach + 1):
                        rest = r2 - dx * dx - dy * dy
                        if rest < 0.0:
                            continue
                        h = min(int(math.floor(math.sqrt(rest))), reach)
                        acc |= zd[h * L * L + (x + dx) * L + y + dy]
                row = (acc >> np.uint64(reach)) & byte
                near[b, x - reach] |= row << np.uint64(8 * (y - reach))


@njit(cache=True, nogil=True)
def _beneath_many(keys, vals, density, label, bone, origin, spacing, tp, ijk, nrm, shift,
                  t_out, s_out):
    for q in range(ijk.shape[0]):
        t, s = _ray_thickness(keys, vals, density, label, bone, origin, spacing, tp,
                              ijk[q, 0], ijk[q, 1], ijk[q, 2], np.float64(nrm[q, 0]),
                              np.float64(nrm[q, 1]), np.float64(nrm[q, 2]), 1.0,
                              np.float64(shift[q]))
        t_out[q] = t
        s_out[q] = max(s, 0)


def as_bone(bone, n_rows):
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


def beneath(grid, ijk, normals, bone, params: ShadingParams | None = None, shift=0.5):
    """Thickness and structure beneath bone voxels along their normals: the
    central ray of the module docstring.

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
        Default: the shipped file.
    shift : float or (n,) array_like
        Where each vertex lies along its normal from its voxel's centre
        [voxels] (cast to float32 first, as stored; default 1/2: on the
        voxel's face, so a slab of ``N`` voxels reads ``N * spacing_mm``).

    Returns
    -------
    thickness : (n,) float64
        ``t_0`` [mm] where a structure is met, else ``start_mm``.
    structure : (n,) int64
        Label of the structure met, 0 for none.
    """
    p = load_shading() if params is None else params
    ijk = np.ascontiguousarray(np.asarray(ijk).reshape(-1, 3), dtype=np.int64)
    nrm = np.ascontiguousarray(np.asarray(normals, dtype=np.float32).reshape(-1, 3))
    if nrm.shape[0] != ijk.shape[0]:
        raise ValueError("ijk and normals must have the same length")
    sh = filled(shift, (ijk.shape[0],), np.float32)
    bone_u8 = as_bone(bone, len(bone))
    if grid.label.size and int(grid.label.max()) >= len(bone_u8):
        raise ValueError(f"bone has {len(bone_u8)} entries but the grid uses label "
                         f"{int(grid.label.max())}")
    t = np.empty(ijk.shape[0])
    s = np.empty(ijk.shape[0], dtype=np.int64)
    _beneath_many(grid.keys, grid.vals, grid.density_ro, grid.label, bone_u8,
                  np.asarray(grid.origin_mm, dtype=np.float64), float(grid.spacing_mm),
                  ray_params(p, grid.spacing_mm), ijk, nrm, sh, t, s)
    return t, s
