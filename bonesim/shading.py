"""Vertex normals and colours of the bone surface: smooth bone, and thin bone
that shows what lies beneath.

:class:`bonesim.surface.Surface` puts a vertex at the centre of every surface
voxel; this module gives each vertex its normal and its colour, over the
whole surface (:meth:`Shader.shade_all`) or again around the voxels a drill
changed (:meth:`Shader.refresh`). Both evaluate the same functions of the
current grid, so an incrementally updated surface equals a rebuilt one bit
for bit.

Definitions
-----------
Voxel ``(i, j, k)`` (case frame, LPS) has its centre at ``origin_mm +
spacing_mm * (i, j, k)`` [mm] and density ``d(i, j, k)`` (0 where no brick
is allocated).

Vertex normal
    ``n = -g / |g|`` (unit, pointing out of the tissue), with ``g`` the
    density gradient by Gaussian derivatives over the 7x7x7 voxels around
    the vertex (offsets ``-R..R``, ``R =`` :data:`NORMAL_RADIUS` ``= 3``)::

        S[c] = exp(-c**2 / (2 sigma**2)) / sum_c exp(-c**2 / (2 sigma**2))
        D[c] = c S[c] / sum_c c**2 S[c]
        g_x = sum_a D[a] sum_b S[b] sum_c S[c] d(i + a, j + b, k + c)

    and likewise ``g_y`` (``D`` along j) and ``g_z`` (``D`` along k);
    ``sigma`` [voxels] is ``[normals] sigma_voxels`` of the shading file. A
    linear density ramp of slope 1 per voxel gives ``|g| = 1``. The sums
    are evaluated separably in float32, innermost along k, then j, then i,
    folding the symmetric terms (``S[0] v0 + S[1] (v-1 + v1) + ...`` and
    ``D[1] (v1 - v-1) + ...``; see :func:`_kj_plane`), so a configuration
    symmetric about the vertex gives an exactly zero component. If ``|g| <=``
    :data:`GRAD_EPS` the normal is the normalised sum of the offsets
    ``(di, dj, dk)`` toward the empty 26-neighbours, and if that sum is zero
    too, ``+z``. Normals are stored as float32.
Bone and the structure beneath
    A voxel is *bone* when its density is > 0 and its label is one of the
    bone labels given to :meth:`Surface.build` (structures of kind
    ``"bone"``, :func:`bone_labels`). From the centre ``p`` of a bone
    vertex, a ray along ``-n`` (``n`` as stored, float32) is marched through
    the grid by :func:`bonesim.thickness.exit_ray`, the estimate the drill
    sound uses (steps of ``STEP_FRACTION`` voxel, nearest-voxel samples,
    bisection), up to ``[thin_bone] start_mm``. If it leaves the bone into
    an occupied voxel of a non-bone structure ``s``, a second ray along
    ``+n`` measures the bone behind ``p`` and the *thickness* is the chord
    ``t = min(s_in + s_back, start_mm)``; a slab of ``N`` voxels measured
    along its normal reads ``N * spacing_mm``. Otherwise (the ray reaches
    empty space, or no exit within ``start_mm``) there is no structure
    beneath.
Tint weight
    ``w(t) = max_weight * x**2 * (3 - 2 x)`` with ``x = clip((start_mm - t)
    / (start_mm - full_mm), 0, 1)``: 0 at ``start_mm`` and above, rising
    smoothly to ``max_weight`` at ``full_mm`` and below
    (:func:`tint_weight`). ``w = 0`` without a structure beneath, at vertices
    that are not bone, and when no bone labels were given.
Vertex colour
    RGBA uint8: ``c = (1 - w) * colors[label] + w * colors[s]`` per channel,
    times ``SHADE_MIN + (1 - SHADE_MIN) * clip(d, 0, 1)`` (``d`` the vertex's
    density), rounded half up (``floor(x + 0.5)``, at most 255); alpha 255.
    With ``w = 0`` this is exactly the structure's shaded display colour.

What a drill changes
--------------------
A vertex's normal reads the densities within :data:`NORMAL_RADIUS` voxels
(Chebyshev distance) of it; its colour its own density; its ray, voxels
within :func:`tint_reach` voxels, and only whether they are bone, which a
lowered density that stays > 0 does not change. So after the voxels
``removed`` (density now 0) and ``touched`` (lowered) changed,
:meth:`Shader.refresh` recomputes

* normal and colour of every vertex within ``NORMAL_RADIUS`` of any of them
  (this includes every vertex the tessellation created), and
* the colour of every vertex within :func:`tint_reach` of a removed voxel
  (with its unchanged normal),

and nothing else changes. A vertex in a brick with no non-bone structure
label within ``tint_reach`` voxels of the brick (labels never change) cannot
meet a structure, and its ray is not cast.

Implementation
--------------
Full shading works per brick in parallel: the brick and a 3-voxel halo are
copied into a dense 14x14x14 box for the normals. The refresh works on a
dense window around the inputs (their bounding box plus ``max(tint_reach,
2 NORMAL_RADIUS)``, at most 64 voxels deep along k; inputs spread too far
are split into several windows): the sets of voxels to refresh are bit rows
(one uint64 per ``(i, j)`` row of the window), dilations of the inputs by a
few shifts and ORs, and the densities the normals read are gathered once.
Rays read the grid through its hash table in both.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from numba import njit, prange
from numba.cpython.unsafe.numbers import trailing_zeros

from .errors import BonesimError
from .grid import BRICK, BRICK_MASK, BRICK_SHIFT, BRICK_VOXELS, find_brick, voxel_offset
from .thickness import STEP_FRACTION, exit_ray
from .tomlfile import check_keys, get_number, read_toml

__all__ = ["NORMAL_RADIUS", "SHADE_MIN", "GRAD_EPS", "ALPHA", "MAX_REACH_VOXELS",
           "ShadingParams", "default_shading_path", "load_shading", "normal_weights",
           "stencil_weights",
           "tint_weight", "tint_reach", "bone_labels", "beneath", "Shader", "warmup"]

#: Half-width [voxels] of the normal stencil (7x7x7 voxels).
NORMAL_RADIUS = 3
#: Darkest shade factor, applied to a voxel of density 0 (density 1 is full colour).
SHADE_MIN = 0.35
#: Gradients with a norm at most this [density per voxel] are treated as zero
#: (fallback normal).
GRAD_EPS = 1e-6
#: Alpha of every vertex colour.
ALPHA = 255
#: Largest reach [voxels] of the refresh: ``tint_reach`` must not exceed it
#: (a window is at most 64 voxels deep along k).
MAX_REACH_VOXELS = 28

_NW = 2 * NORMAL_RADIUS + 1
_HALO = NORMAL_RADIUS
_LB = BRICK + 2 * _HALO          # edge of the per-brick box of the full shading
_CHUNK = 16                      # bricks per parallel work item
# bit-row sets of the refresh window
_R_ALL, _R_REM, _R_NRM, _R_TINT, _R_REM1, _R_T0 = range(6)
_N_ROWSETS = 6
#: A refresh window holds at most max(_WIN_MIN_VOXELS, _WIN_VOXELS_PER_INPUT *
#: inputs) voxels; inputs spread further are split into several windows.
_WIN_MIN_VOXELS = 32768
_WIN_VOXELS_PER_INPUT = 128
_WIN_DEPTH = 64


# ----------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ShadingParams:
    """Tunables of the surface shading (see the module docstring).

    Attributes
    ----------
    sigma_voxels : float
        Standard deviation of the normals' Gaussian [voxels].
    start_mm : float
        Bone thickness at and above which there is no tint [mm].
    full_mm : float
        Thickness at and below which the tint is strongest [mm].
    max_weight : float
        Strongest blend toward the structure's colour, in [0, 1].
    """

    sigma_voxels: float = 2.0
    start_mm: float = 3.0
    full_mm: float = 0.5
    max_weight: float = 0.6

    def __post_init__(self):
        for name in ("sigma_voxels", "start_mm", "full_mm", "max_weight"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"ShadingParams.{name} must be a finite number, got {v!r}")
        if not self.sigma_voxels > 0:
            raise ValueError(f"sigma_voxels must be > 0, got {self.sigma_voxels}")
        if not 0 <= self.full_mm < self.start_mm:
            raise ValueError(f"need 0 <= full_mm < start_mm, got full_mm={self.full_mm}, "
                             f"start_mm={self.start_mm}")
        if not 0 <= self.max_weight <= 1:
            raise ValueError(f"max_weight must be in [0, 1], got {self.max_weight}")


def default_shading_path() -> Path:
    """Path of the shipped ``shading.toml``."""
    return Path(__file__).resolve().parent / "data" / "shading.toml"


def load_shading(path: str | Path | None = None) -> ShadingParams:
    """Read and check a shading file.

    Parameters
    ----------
    path : str or Path, optional
        Default: the shipped ``bonesim/data/shading.toml``.

    Returns
    -------
    ShadingParams

    Raises
    ------
    BonesimError
        If the file is missing or malformed, a table or key is unknown or
        missing, or a value has the wrong type or range.
    """
    if path is None:
        return _default_params()
    return _read_params(Path(path))


@lru_cache(maxsize=1)
def _default_params() -> ShadingParams:
    return _read_params(default_shading_path())


def _read_params(path: Path) -> ShadingParams:
    doc = read_toml(path)
    check_keys(doc, ("normals", "thin_bone"), path, "", required=("normals", "thin_bone"))
    nt = doc["normals"]
    check_keys(nt, ("sigma_voxels",), path, "normals", required=("sigma_voxels",))
    sigma = get_number(nt, "sigma_voxels", path, "normals", minimum=0.1, maximum=10.0)
    tb = doc["thin_bone"]
    keys = ("start_mm", "full_mm", "max_weight")
    check_keys(tb, keys, path, "thin_bone", required=keys)
    start = get_number(tb, "start_mm", path, "thin_bone", minimum=0.0)
    full = get_number(tb, "full_mm", path, "thin_bone", minimum=0.0)
    wmax = get_number(tb, "max_weight", path, "thin_bone", minimum=0.0, maximum=1.0)
    if not math.isfinite(start):
        raise BonesimError(f"'start_mm' must be finite, got {start!r}", path, "thin_bone")
    if not full < start:
        raise BonesimError(f"'full_mm' ({full}) must be below 'start_mm' ({start})",
                           path, "thin_bone")
    return ShadingParams(sigma_voxels=float(sigma), start_mm=float(start),
                         full_mm=float(full), max_weight=float(wmax))


def normal_weights(sigma_voxels: float):
    """Smoothing and derivative weights of the normal stencil.

    Returns
    -------
    S, D : (2 * NORMAL_RADIUS + 1,) float64
        ``S[c + R]`` and ``D[c + R]`` for offsets ``c = -R..R`` (see the
        module docstring): ``sum(S) == 1``, ``sum(c * D) == 1``.
    """
    c = np.arange(-NORMAL_RADIUS, NORMAL_RADIUS + 1, dtype=np.float64)
    s = np.exp(-c * c / (2.0 * float(sigma_voxels) ** 2))
    s /= s.sum()
    d = c * s
    d /= (c * d).sum()
    return s, d


def stencil_weights(sigma_voxels: float) -> np.ndarray:
    """(7,) float32 ``S0, S1, S2, S3, D1, D2, D3``: the weights of
    :func:`normal_weights` at offsets 0..3 (``S[-c] = S[c]``, ``D[-c] =
    -D[c]``, ``D0 = 0``), as the kernels use them."""
    s, d = normal_weights(sigma_voxels)
    r = NORMAL_RADIUS
    return np.array([s[r], s[r + 1], s[r + 2], s[r + 3], d[r + 1], d[r + 2], d[r + 3]],
                    dtype=np.float32)


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


# ----------------------------------------------------------------------------
# Kernels
# ----------------------------------------------------------------------------
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


@njit(cache=True, nogil=True)
def _kj_plane(d, x, Y, Z, W, rs, rd, ring, slot):
    """Passes along k and j of the gradient for plane ``x`` of a dense box.

    ``d`` holds the float32 densities of an ``(X, Y, Z)`` box (flat, z
    fastest); ``W`` the float32 weights ``S0, S1, S2, S3, D1, D2, D3``
    (``Sc = S[R + c]``, ``Dc = D[R + c]``, see :func:`stencil_weights`).
    With ``Yo = Y - 6``, ``Zo = Z - 6``, in float32, left to right::

        rs[y, z] = S0 v0 + S1 (v-1 + v1) + S2 (v-2 + v2) + S3 (v-3 + v3)
        rd[y, z] = D1 (v1 - v-1) + D2 (v2 - v-2) + D3 (v3 - v-3)

    with ``vc = d[x, y, z + 3 + c]`` (``(Y, Zo)`` scratch); then the same
    along j, ``vc = rs[y + 3 + c, z]``: ``tx`` = S-pass of ``rs``, ``ty`` =
    D-pass of ``rs``, ``tz`` = S-pass of ``rd``, each ``(Yo, Zo)``, written
    to slot ``slot`` of ``ring`` (component ``c`` at ``(3 slot + c) Yo
    Zo``). Written out for ``NORMAL_RADIUS = 3``, looping over whole rows so
    that they vectorise.
    """
    Yo = Y - 6
    Zo = Z - 6
    n_pl = Yo * Zo
    s0 = W[0]
    s1 = W[1]
    s2 = W[2]
    s3 = W[3]
    d1 = W[4]
    d2 = W[5]
    d3 = W[6]
    base = x * Y * Z
    for y in range(Y):
        v = d[base + y * Z:base + y * Z + Z]
        o1 = rs[y * Zo:y * Zo + Zo]
        o2 = rd[y * Zo:y * Zo + Zo]
        for z in range(Zo):
            o1[z] = (s0 * v[z + 3] + s1 * (v[z + 2] + v[z + 4]) + s2 * (v[z + 1] + v[z + 5])
                     + s3 * (v[z] + v[z + 6]))
        for z in range(Zo):
            o2[z] = d1 * (v[z + 4] - v[z + 2]) + d2 * (v[z + 5] - v[z + 1]) + d3 * (v[z + 6] - v[z])
    tb = 3 * slot * n_pl
    for y in range(Yo):
        ob = y * Zo
        a = rs[ob:ob + 7 * Zo]
        o = ring[tb + ob:tb + ob + Zo]
        for z in range(Zo):
            o[z] = (s0 * a[z + 3 * Zo] + s1 * (a[z + 2 * Zo] + a[z + 4 * Zo])
                    + s2 * (a[z + Zo] + a[z + 5 * Zo]) + s3 * (a[z] + a[z + 6 * Zo]))
        o = ring[tb + n_pl + ob:tb + n_pl + ob + Zo]
        for z in range(Zo):
            o[z] = (d1 * (a[z + 4 * Zo] - a[z + 2 * Zo]) + d2 * (a[z + 5 * Zo] - a[z + Zo])
                    + d3 * (a[z + 6 * Zo] - a[z]))
        e = rd[ob:ob + 7 * Zo]
        o = ring[tb + 2 * n_pl + ob:tb + 2 * n_pl + ob + Zo]
        for z in range(Zo):
            o[z] = (s0 * e[z + 3 * Zo] + s1 * (e[z + 2 * Zo] + e[z + 4 * Zo])
                    + s2 * (e[z + Zo] + e[z + 5 * Zo]) + s3 * (e[z] + e[z + 6 * Zo]))


@njit(cache=True, nogil=True)
def _i_plane(ring, first, n_pl, W, g):
    """Pass along i: the gradient of the plane between the ring's planes
    ``first .. first + 6`` (slot ``p % 7`` holds plane ``p``, see
    :func:`_kj_plane`): ``g[0:n]`` = D-pass of ``tx``, ``g[n:2n]`` and
    ``g[2n:3n]`` the S-passes of ``ty`` and ``tz`` (``n = Yo Zo``, float32,
    left to right as in :func:`_kj_plane`)."""
    s0 = W[0]
    s1 = W[1]
    s2 = W[2]
    s3 = W[3]
    d1 = W[4]
    d2 = W[5]
    d3 = W[6]
    for c in range(3):
        a0 = ring[(3 * ((first + 0) % 7) + c) * n_pl:(3 * ((first + 0) % 7) + c + 1) * n_pl]
        a1 = ring[(3 * ((first + 1) % 7) + c) * n_pl:(3 * ((first + 1) % 7) + c + 1) * n_pl]
        a2 = ring[(3 * ((first + 2) % 7) + c) * n_pl:(3 * ((first + 2) % 7) + c + 1) * n_pl]
        a3 = ring[(3 * ((first + 3) % 7) + c) * n_pl:(3 * ((first + 3) % 7) + c + 1) * n_pl]
        a4 = ring[(3 * ((first + 4) % 7) + c) * n_pl:(3 * ((first + 4) % 7) + c + 1) * n_pl]
        a5 = ring[(3 * ((first + 5) % 7) + c) * n_pl:(3 * ((first + 5) % 7) + c + 1) * n_pl]
        a6 = ring[(3 * ((first + 6) % 7) + c) * n_pl:(3 * ((first + 6) % 7) + c + 1) * n_pl]
        o = g[c * n_pl:(c + 1) * n_pl]
        if c == 0:
            for q in range(n_pl):
                o[q] = d1 * (a4[q] - a2[q]) + d2 * (a5[q] - a1[q]) + d3 * (a6[q] - a0[q])
        else:
            for q in range(n_pl):
                o[q] = (s0 * a3[q] + s1 * (a2[q] + a4[q]) + s2 * (a1[q] + a5[q])
                        + s3 * (a0[q] + a6[q]))


# The hot loops below call only helpers on scalars: a numba helper taking
# arrays, inlined or not, costs reference counting on every call (some 30 ns
# per vertex); helpers with arrays are called in rare branches only.
@njit(cache=True, nogil=True, inline="always")
def _unit(gx, gy, gz):
    """``(-g / |g|, True)`` in float64, or ``(+z, False)`` when ``|g| <=
    GRAD_EPS`` (then :func:`_fallback_normal` decides)."""
    gx = np.float64(gx)
    gy = np.float64(gy)
    gz = np.float64(gz)
    g = math.sqrt(gx * gx + gy * gy + gz * gz)
    if g > GRAD_EPS:
        return -gx / g, -gy / g, -gz / g, True
    return 0.0, 0.0, 1.0, False


@njit(cache=True, nogil=True)
def _fallback_normal(d, c0, Y, Z):
    """Normal of the box voxel ``d[c0]`` (box ``(., Y, Z)``) without a
    gradient: the normalised sum of the offsets toward its empty
    26-neighbours, or ``+z``."""
    sxx = 0
    syy = 0
    szz = 0
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-1, 2):
                if (a != 0 or b != 0 or c != 0) and not d[c0 + (a * Y + b) * Z + c] > 0:
                    sxx += a
                    syy += b
                    szz += c
    sn = math.sqrt(np.float64(sxx * sxx + syy * syy + szz * szz))
    if sn > 0:
        return sxx / sn, syy / sn, szz / sn
    return 0.0, 0.0, 1.0


@njit(cache=True, nogil=True, inline="always")
def _shade(r0, g0, b0, r1, g1, b1, w, dens):
    """RGB (uint8) of the colour ``(r0, g0, b0)`` blended with weight ``w``
    toward ``(r1, g1, b1)`` and shaded by the density (module docstring)."""
    d = min(max(np.float64(dens), 0.0), 1.0)
    shade = SHADE_MIN + (1.0 - SHADE_MIN) * d
    r = np.floor((np.float64(r0) * (1.0 - w) + np.float64(r1) * w) * shade + 0.5)
    g = np.floor((np.float64(g0) * (1.0 - w) + np.float64(g1) * w) * shade + 0.5)
    b = np.floor((np.float64(b0) * (1.0 - w) + np.float64(b1) * w) * shade + 0.5)
    return np.uint8(min(r, 255.0)), np.uint8(min(g, 255.0)), np.uint8(min(b, 255.0))


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
def _gather_halo(density, nbr, b, box):
    """Densities of brick ``b`` and a ``_HALO``-voxel halo into the flat box
    (voxel ``(x, y, z)`` of the brick at ``((x + H) * LB + y + H) * LB + z + H``)."""
    s = 0
    for lx in range(_LB):
        x = lx - _HALO
        sx = ((x >> BRICK_SHIFT) + 1) * 9
        ox = (x & BRICK_MASK) << 6
        for ly in range(_LB):
            y = ly - _HALO
            sy = sx + ((y >> BRICK_SHIFT) + 1) * 3
            oy = ox | ((y & BRICK_MASK) << 3)
            for lz in range(_LB):
                z = lz - _HALO
                nb = nbr[b, sy + (z >> BRICK_SHIFT) + 1]
                if nb >= 0:
                    box[s] = density[nb, oy | (z & BRICK_MASK)]
                else:
                    box[s] = np.float32(0.0)
                s += 1


@njit(cache=True, nogil=True, parallel=True)
def _shade_all_kernel(keys, vals, density, label, nbr, bricks, vmap, bone, tint_on, near,
                      colors, W, origin, spacing, tp, nrm, col, counts):
    """Normal and colour of every vertex, brick by brick (the brick plus a
    3-voxel halo is the box of the gradient passes, plane by plane)."""
    nb_tot = bricks.shape[0]
    n_chunks = (nb_tot + _CHUNK - 1) // _CHUNK
    ncol = colors.shape[0]
    one = np.uint64(1)
    n_pl = BRICK * BRICK
    for ch in prange(n_chunks):
        box = np.empty(_LB * _LB * _LB, dtype=np.float32)
        rs = np.empty(_LB * BRICK, dtype=np.float32)
        rd = np.empty(_LB * BRICK, dtype=np.float32)
        ring = np.empty(21 * n_pl, dtype=np.float32)
        g = np.empty(3 * n_pl, dtype=np.float32)
        n = 0
        for b in range(ch * _CHUNK, min(nb_tot, (ch + 1) * _CHUNK)):
            gathered = False
            have = 0
            bi = bricks[b, 0] << BRICK_SHIFT
            bj = bricks[b, 1] << BRICK_SHIFT
            bk = bricks[b, 2] << BRICK_SHIFT
            for x in range(BRICK):
                any_v = False
                for o in range(x * n_pl, (x + 1) * n_pl):
                    if vmap[b, o] >= 0:
                        any_v = True
                        break
                if not any_v:
                    continue
                if not gathered:
                    _gather_halo(density, nbr, b, box)
                    gathered = True
                for pl in range(max(have, x), x + 7):
                    _kj_plane(box, pl, _LB, _LB, W, rs, rd, ring, pl % 7)
                have = x + 7
                _i_plane(ring, x, n_pl, W, g)
                for q in range(n_pl):
                    o = x * n_pl + q
                    v = vmap[b, o]
                    if v < 0:
                        continue
                    y = q >> 3
                    z = q & BRICK_MASK
                    nx, ny, nz, ok = _unit(g[q], g[n_pl + q], g[2 * n_pl + q])
                    if not ok:
                        nx, ny, nz = _fallback_normal(box, ((x + _HALO) * _LB + y + _HALO) * _LB
                                                      + z + _HALO, _LB, _LB)
                    nrm[v, 0] = nx
                    nrm[v, 1] = ny
                    nrm[v, 2] = nz
                    lab = np.int64(label[b, o])
                    if lab >= ncol:
                        lab = 0
                    met = 0
                    w = 0.0
                    if tint_on:
                        if bone[lab] != 0:
                            if (near[b, x] >> np.uint64(q)) & one:
                                met, w = _tint(keys, vals, density, label, bone, origin,
                                               spacing, tp, bi + x, bj + y, bk + z, nrm[v, 0],
                                               nrm[v, 1], nrm[v, 2])
                                if met >= ncol:
                                    met = 0
                    cr, cg, cb = _shade(colors[lab, 0], colors[lab, 1], colors[lab, 2],
                                        colors[met, 0], colors[met, 1], colors[met, 2], w,
                                        density[b, o])
                    col[v, 0] = cr
                    col[v, 1] = cg
                    col[v, 2] = cb
                    col[v, 3] = ALPHA
                    n += 1
        counts[ch] = n


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
_F_ORIGIN, _F_SPACING, _F_TP, _F_W = 0, 3, 4, 8          # origin (3), spacing, tp (4), W (7)
_N_F = 15
_I_TINT, _I_REACH, _I_MARGIN, _I_NEED = 0, 1, 2, 3        # need: rows, bricks, f32
_N_I = 6


@njit(cache=True, nogil=True)
def _refresh(keys, vals, density, label, vmap, bone, near, colors, fp, ip, removed, touched,
             rows, wbr, f32, nrm, col):
    """Refresh the vertices near the inputs (see the module docstring) on one
    window: their bounding box plus ``m = ip[_I_MARGIN]`` voxels. The normals
    are computed on the box of the inputs' bounding box plus ``2
    NORMAL_RADIUS`` (its densities and passes in ``f32``).

    Returns the number of vertices refreshed, -1 if the window is too big
    (at most 64 voxels deep along k, and ``max(_WIN_MIN_VOXELS,
    _WIN_VOXELS_PER_INPUT * inputs, (2 m + 16)**3)`` voxels, which a single
    voxel always fits: split the inputs), -2 if the
    scratch is too small (sizes needed in ``ip[_I_NEED:]``; nothing done).
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
    need_f = n_box + 2 * n_k + 24 * n_pl
    if rows.shape[0] < _N_ROWSETS * nrow or wbr.shape[0] < bd0 * bd1 * bd2 \
            or f32.shape[0] < need_f:
        ip[_I_NEED] = _N_ROWSETS * nrow
        ip[_I_NEED + 1] = bd0 * bd1 * bd2
        ip[_I_NEED + 2] = need_f
        return -2
    ld = f32[:n_box]
    rs = f32[n_box:n_box + n_k]
    rd = f32[n_box + n_k:n_box + 2 * n_k]
    ring = f32[n_box + 2 * n_k:n_box + 2 * n_k + 21 * n_pl]
    g = f32[n_box + 2 * n_k + 21 * n_pl:need_f]
    W = np.empty(7, dtype=np.float32)
    for c in range(7):
        W[c] = np.float32(fp[_F_W + c])
    origin = fp[_F_ORIGIN:_F_ORIGIN + 3]
    spacing = fp[_F_SPACING]
    tp = fp[_F_TP:_F_TP + 4]
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
            _kj_plane(ld, pl, Y, Z, W, rs, rd, ring, pl % 7)
        have = xo + 7
        _i_plane(ring, xo, n_pl, W, g)
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
                nx, ny, nz, ok = _unit(g[q], g[n_pl + q], g[2 * n_pl + q])
                if not ok:
                    nx, ny, nz = _fallback_normal(ld, ((x - off) * Y + y - off) * Z + z - off, Y, Z)
                nrm[v, 0] = nx
                nrm[v, 1] = ny
                nrm[v, 2] = nz
                lab = np.int64(label[b, o])
                if lab >= ncol:
                    lab = 0
                met = 0
                w = 0.0
                if tint_on:
                    if bone[lab] != 0:
                        if (near[b, o >> 6] >> np.uint64(o & 63)) & one:
                            met, w = _tint(keys, vals, density, label, bone, origin, spacing,
                                           tp, i, j, k, nrm[v, 0], nrm[v, 1], nrm[v, 2])
                            if met >= ncol:
                                met = 0
                cr, cg, cb = _shade(colors[lab, 0], colors[lab, 1], colors[lab, 2],
                                    colors[met, 0], colors[met, 1], colors[met, 2], w,
                                    density[b, o])
                col[v, 0] = cr
                col[v, 1] = cg
                col[v, 2] = cb
                col[v, 3] = ALPHA
                count += 1
    if not tint_on or nr == 0:
        return count
    # vertices whose normal stays but whose rays may pass a removed voxel
    reach = tp[1] / spacing
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
                if not _ray_meets(rows, R1, wlo, wd0, wd1, wd2, i, j, k, nrm[v, 0], nrm[v, 1],
                                  nrm[v, 2], reach):
                    continue
                met, w = _tint(keys, vals, density, label, bone, origin, spacing, tp, i, j, k,
                               nrm[v, 0], nrm[v, 1], nrm[v, 2])
                if met >= ncol:
                    met = 0
                cr, cg, cb = _shade(colors[lab, 0], colors[lab, 1], colors[lab, 2],
                                    colors[met, 0], colors[met, 1], colors[met, 2], w,
                                    density[b, o])
                col[v, 0] = cr
                col[v, 1] = cg
                col[v, 2] = cb
                col[v, 3] = ALPHA
                count += 1
    return count


@njit(cache=True, nogil=True)
def _ray_meets(rows, R1, wlo, wd0, wd1, wd2, i, j, k, nx, ny, nz, reach):
    """Whether the segment from voxel ``(i, j, k)`` along ``+-n`` up to
    ``reach`` voxels passes near the set ``R1`` (the removed voxels dilated
    by one voxel) of the window. Points every half voxel are tested: every
    sample of the rays lies within a quarter voxel of one, so its voxel is
    within one voxel of that point's, and the test never misses a removed
    voxel a ray reads."""
    one = np.uint64(1)
    n_pts = int(math.ceil(2.0 * reach)) + 1
    for sgn in (-1.0, 1.0):
        for q in range(n_pts + 1):
            t = sgn * min(0.5 * q, reach)
            x = int(math.floor(i + t * nx + 0.5)) - wlo[0]
            y = int(math.floor(j + t * ny + 0.5)) - wlo[1]
            z = int(math.floor(k + t * nz + 0.5)) - wlo[2]
            if 0 <= x < wd0 and 0 <= y < wd1 and 0 <= z < wd2:
                if (rows[R1 + x * wd1 + y] >> np.uint64(z)) & one:
                    return True
    return False


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
                near[b, x - reach] |= ((acc >> np.uint64(reach)) & byte) << np.uint64(8 * (y - reach))


@njit(cache=True, nogil=True)
def _beneath_many(keys, vals, density, label, bone, origin, spacing, step, max_mm, ijk,
                  nrm, t_out, s_out):
    for q in range(ijk.shape[0]):
        t, s = _beneath_at(keys, vals, density, label, bone, origin, spacing, step, max_mm,
                           ijk[q, 0], ijk[q, 1], ijk[q, 2], np.float64(nrm[q, 0]),
                           np.float64(nrm[q, 1]), np.float64(nrm[q, 2]))
        t_out[q] = t
        s_out[q] = s


# ----------------------------------------------------------------------------
# Python front end
# ----------------------------------------------------------------------------
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


class Shader:
    """Normals and colours of one surface's vertices (see the module docstring).

    Parameters
    ----------
    grid : Grid
        The tissue the surface was built from (its labels and hash table are
        read here; labels never change).
    nbr : (n_bricks, 27) int32
        Each brick's neighbours (``bonesim.surface``'s table).
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
        self.colors = colors
        self._nbr = nbr
        self._W = stencil_weights(self.params.sigma_voxels)
        self.spacing = float(grid.spacing_mm)
        self._origin = np.asarray(grid.origin_mm, dtype=np.float64).copy()
        self.tint_on = bone is not None
        n_rows = colors.shape[0]
        self.bone = _as_bone(bone, n_rows) if bone is not None else np.zeros(n_rows, np.uint8)
        self.reach = tint_reach(self.params, self.spacing) if self.tint_on else 0
        if self.reach > MAX_REACH_VOXELS:
            raise BonesimError(
                f"'start_mm' = {self.params.start_mm} reaches {self.reach} voxels of "
                f"{self.spacing} mm (at most {MAX_REACH_VOXELS}); lower it", None,
                "thin_bone")
        self.margin = max(self.reach, 2 * NORMAL_RADIUS)
        self._tp = np.array([STEP_FRACTION * self.spacing, self.params.start_mm,
                             self.params.full_mm, self.params.max_weight])
        self._near = np.zeros((grid.n_bricks, BRICK), dtype=np.uint64)
        if self.tint_on:
            bits = np.empty((grid.n_bricks, BRICK), dtype=np.uint64)
            if _structure_bits(grid.label, self.bone, bits):
                _near_structure(grid.keys, grid.vals, grid.bricks, bits, self.reach,
                                self._near)
        self._fp = np.zeros(_N_F)
        self._fp[_F_ORIGIN:_F_ORIGIN + 3] = self._origin
        self._fp[_F_SPACING] = self.spacing
        self._fp[_F_TP:_F_TP + 4] = self._tp
        self._fp[_F_W:_F_W + 7] = self._W
        self._ip = np.zeros(_N_I, dtype=np.int64)
        self._ip[_I_TINT] = 1 if self.tint_on else 0
        self._ip[_I_REACH] = self.reach
        self._ip[_I_MARGIN] = self.margin
        self._rows = np.zeros(_N_ROWSETS * 1024, dtype=np.uint64)
        self._wbr = np.zeros(64, dtype=np.int32)
        self._f32 = np.zeros(1 << 16, dtype=np.float32)

    @property
    def normal_reach(self) -> int:
        """Voxels [Chebyshev] around a changed voxel whose normals may change."""
        return NORMAL_RADIUS

    def shade_all(self, grid, vmap, nrm, col) -> int:
        """Normal and colour of every vertex of ``vmap``; returns their number."""
        n_chunks = max(1, (grid.n_bricks + _CHUNK - 1) // _CHUNK)
        counts = np.zeros(n_chunks, dtype=np.int64)
        _shade_all_kernel(grid.keys, grid.vals, grid.density, grid.label, self._nbr,
                          grid.bricks, vmap, self.bone, self.tint_on, self._near,
                          self.colors, self._W, self._origin, self.spacing,
                          self._tp, nrm, col, counts)
        return int(counts.sum())

    def refresh(self, grid, vmap, nrm, col, removed, touched) -> int:
        """Recompute what ``removed`` and ``touched`` (int32 (n, 3) C arrays,
        validated by the caller) can have changed; returns the number of
        vertices refreshed (a vertex near several windows counts once per
        window)."""
        if removed.shape[0] == 0 and touched.shape[0] == 0:
            return 0
        n = 0
        stack = [(removed, touched)]
        while stack:
            rem, tch = stack.pop()
            while True:
                got = _refresh(grid.keys, grid.vals, grid.density, grid.label, vmap, self.bone,
                               self._near, self.colors, self._fp, self._ip, rem, tch,
                               self._rows, self._wbr, self._f32, nrm, col)
                if got != -2:
                    break
                need = self._ip[_I_NEED:_I_NEED + 3].tolist()
                for name, k in (("_rows", 0), ("_wbr", 1), ("_f32", 2)):
                    cur = getattr(self, name)
                    if cur.shape[0] < need[k]:
                        n_new = max(need[k], 2 * cur.shape[0])
                        setattr(self, name, np.zeros((n_new,) + cur.shape[1:], dtype=cur.dtype))
            if got >= 0:
                n += got
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


def warmup() -> None:
    """Compile (or load from the cache) this module's kernels on a tiny grid
    (through :func:`bonesim.surface.warmup`, which builds and updates a
    surface with a tint)."""
    from .surface import warmup as surface_warmup

    surface_warmup()
