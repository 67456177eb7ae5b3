"""Smooth vertex normals and sub-voxel vertex positions: a Gaussian-smoothed
density over 7x7x7 voxels and its gradient, evaluated separably on dense
boxes of densities.

Definition
----------
Voxel ``(i, j, k)`` (case frame, LPS) has density ``d(i, j, k)`` (0 where
no brick is allocated).

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
    ``D[1] (v1 - v-1) + ...``; see :func:`kj_plane`), so a configuration
    symmetric about the vertex gives an exactly zero component. If ``|g| <=``
    :data:`GRAD_EPS` the normal is the normalised sum of the offsets
    ``(di, dj, dk)`` toward the empty 26-neighbours, and if that sum is zero
    too, ``+z``. Normals are stored as float32.
Smoothed density
    ``f = sum_a S[a] sum_b S[b] sum_c S[c] d(i + a, j + b, k + c)``, the
    same Gaussian without derivative (evaluated like ``g``: float32,
    separably, symmetric terms folded). The density is the fraction of a
    voxel's material left (1 intact, partly drilled in between), so ``f``
    is a smoothed partial-volume occupancy.
Vertex position
    The vertex of voxel ``(i, j, k)`` sits on the level set ``f = iso`` of
    that field, reached by one Newton step along the normal from the
    voxel's centre ``c``::

        s = clip((f - iso) / |g|, -max_in, max_out)      [voxels]
        p = origin_mm + spacing_mm * ((i, j, k) + s n)   [mm]

    (``s = 0`` when ``|g| <=`` :data:`GRAD_EPS`; ``iso``, ``max_in`` and
    ``max_out`` are ``[surface]`` of the shading file). A flat face of
    intact bone lies about half a voxel outside its voxels' centres, where
    the voxels end; a partly drilled voxel's vertex sinks as its density
    falls, so a drilled floor is as smooth as the burr left it, not a
    staircase of voxel centres. The clip keeps thin plates (where ``f``
    never reaches ``iso``) from collapsing: each face moves at most
    ``max_in`` into the bone. :func:`vertex_shift` computes ``s`` in
    float64 from the float32 ``f`` and ``g``.

The kernels (:func:`kj_plane`, :func:`i_plane` and its one-point form
:func:`i_point`, :func:`unit_normal`,
:func:`fallback_normal`) are used by :mod:`bonesim.engine.shading` for the full
shading and for the refresh alike, so both give the same bits; the full
shading's k and j passes are :func:`kj_flat`, :func:`kj_plane` over a
brick's plane as one long row (the same operations on the same values).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["NORMAL_RADIUS", "GRAD_EPS", "N_FIELD", "FLAT_EDGE", "FLAT_PLANE", "normal_weights",
           "stencil_weights"]

#: Half-width [voxels] of the normal stencil (7x7x7 voxels; the kernels are
#: written out for this value).
NORMAL_RADIUS = 3
#: Gradients with a norm at most this [density per voxel] are treated as zero
#: (fallback normal).
GRAD_EPS = 1e-6
#: Components of the field per voxel that :func:`i_plane` writes: the
#: gradient's three and the smoothed density.
N_FIELD = 4


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


@njit(cache=True, nogil=True)
def kj_plane(d, x, Y, Z, W, rs, rd, ring, slot):
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


#: Edge of the square planes :func:`kj_flat` takes: a brick (8 voxels) and
#: ``NORMAL_RADIUS`` voxels on each side.
FLAT_EDGE = 8 + 2 * NORMAL_RADIUS
#: Values per component and plane that :func:`kj_flat` writes to its ring:
#: ``8`` rows (y) of ``FLAT_EDGE`` (z; the first 8 are the brick's).
FLAT_PLANE = 8 * FLAT_EDGE
_FLAT_Z = FLAT_EDGE * FLAT_EDGE - 2 * NORMAL_RADIUS


@njit(cache=True, nogil=True)
def kj_flat(d, x, W, rs, rd, ring, slot):
    """:func:`kj_plane` of plane ``x`` of a box of ``(., FLAT_EDGE,
    FLAT_EDGE)`` densities (a brick and its halo), computed over the plane
    as one flat row so that the loops are long and vectorise: the k pass
    ``rs[y * E + z]``, ``rd[y * E + z]`` (``E = FLAT_EDGE``; ``rs``, ``rd``:
    ``E * E`` float32, their last ``2 R`` entries never written: allocate
    them zeroed), the j pass into slot ``slot`` of ``ring`` (component ``c``
    at ``(3 slot + c) FLAT_PLANE + y E + z``). The values at ``z < 8`` are
    those of :func:`kj_plane` bit for bit (the same float32 operations in
    the same order on the same densities); those at ``z >= 8`` mix
    neighbouring rows and are never read (:func:`i_point` with ``n_pl =
    FLAT_PLANE``, ``q = y E + z``)."""
    e = FLAT_EDGE
    s0 = W[0]
    s1 = W[1]
    s2 = W[2]
    s3 = W[3]
    d1 = W[4]
    d2 = W[5]
    d3 = W[6]
    v = d[x * e * e:(x + 1) * e * e]
    for q in range(_FLAT_Z):
        rs[q] = (s0 * v[q + 3] + s1 * (v[q + 2] + v[q + 4]) + s2 * (v[q + 1] + v[q + 5])
                 + s3 * (v[q] + v[q + 6]))
    for q in range(_FLAT_Z):
        rd[q] = d1 * (v[q + 4] - v[q + 2]) + d2 * (v[q + 5] - v[q + 1]) + d3 * (v[q + 6] - v[q])
    tb = 3 * slot * FLAT_PLANE
    o = ring[tb:tb + FLAT_PLANE]
    for q in range(FLAT_PLANE):
        o[q] = (s0 * rs[q + 3 * e] + s1 * (rs[q + 2 * e] + rs[q + 4 * e])
                + s2 * (rs[q + e] + rs[q + 5 * e]) + s3 * (rs[q] + rs[q + 6 * e]))
    o = ring[tb + FLAT_PLANE:tb + 2 * FLAT_PLANE]
    for q in range(FLAT_PLANE):
        o[q] = (d1 * (rs[q + 4 * e] - rs[q + 2 * e]) + d2 * (rs[q + 5 * e] - rs[q + e])
                + d3 * (rs[q + 6 * e] - rs[q]))
    o = ring[tb + 2 * FLAT_PLANE:tb + 3 * FLAT_PLANE]
    for q in range(FLAT_PLANE):
        o[q] = (s0 * rd[q + 3 * e] + s1 * (rd[q + 2 * e] + rd[q + 4 * e])
                + s2 * (rd[q + e] + rd[q + 5 * e]) + s3 * (rd[q] + rd[q + 6 * e]))


@njit(cache=True, nogil=True)
def i_plane(ring, first, n_pl, W, g):
    """Pass along i: the gradient and smoothed density of the plane between
    the ring's planes ``first .. first + 6`` (slot ``p % 7`` holds plane
    ``p``, see :func:`kj_plane`): ``g[0:n]`` = D-pass of ``tx``, ``g[n:2n]``
    and ``g[2n:3n]`` the S-passes of ``ty`` and ``tz``, ``g[3n:4n]`` the
    S-pass of ``tx`` (``f``) (``n = Yo Zo``, float32, left to right as in
    :func:`kj_plane`; ``g`` holds :data:`N_FIELD` ``n`` values)."""
    s0 = W[0]
    s1 = W[1]
    s2 = W[2]
    s3 = W[3]
    d1 = W[4]
    d2 = W[5]
    d3 = W[6]
    for c in range(4):
        src = c if c < 3 else 0             # f: the S-pass of tx
        a0 = ring[(3 * ((first + 0) % 7) + src) * n_pl:(3 * ((first + 0) % 7) + src + 1) * n_pl]
        a1 = ring[(3 * ((first + 1) % 7) + src) * n_pl:(3 * ((first + 1) % 7) + src + 1) * n_pl]
        a2 = ring[(3 * ((first + 2) % 7) + src) * n_pl:(3 * ((first + 2) % 7) + src + 1) * n_pl]
        a3 = ring[(3 * ((first + 3) % 7) + src) * n_pl:(3 * ((first + 3) % 7) + src + 1) * n_pl]
        a4 = ring[(3 * ((first + 4) % 7) + src) * n_pl:(3 * ((first + 4) % 7) + src + 1) * n_pl]
        a5 = ring[(3 * ((first + 5) % 7) + src) * n_pl:(3 * ((first + 5) % 7) + src + 1) * n_pl]
        a6 = ring[(3 * ((first + 6) % 7) + src) * n_pl:(3 * ((first + 6) % 7) + src + 1) * n_pl]
        o = g[c * n_pl:(c + 1) * n_pl]
        if c == 0:
            for q in range(n_pl):
                o[q] = d1 * (a4[q] - a2[q]) + d2 * (a5[q] - a1[q]) + d3 * (a6[q] - a0[q])
        else:
            for q in range(n_pl):
                o[q] = (s0 * a3[q] + s1 * (a2[q] + a4[q]) + s2 * (a1[q] + a5[q])
                        + s3 * (a0[q] + a6[q]))


@njit(cache=True, nogil=True, inline="always")
def i_point(ring, first, n_pl, s0, s1, s2, s3, d1, d2, d3, q):
    """:func:`i_plane` at one point ``q`` of the plane only: ``(gx, gy, gz,
    f)``, the same float32 operations in the same order (so the same
    bits), for planes where few points are wanted."""
    b0 = 3 * ((first + 0) % 7) * n_pl + q
    b1 = 3 * ((first + 1) % 7) * n_pl + q
    b2 = 3 * ((first + 2) % 7) * n_pl + q
    b4 = 3 * ((first + 4) % 7) * n_pl + q
    b5 = 3 * ((first + 5) % 7) * n_pl + q
    b6 = 3 * ((first + 6) % 7) * n_pl + q
    b3 = 3 * ((first + 3) % 7) * n_pl + q
    gx = d1 * (ring[b4] - ring[b2]) + d2 * (ring[b5] - ring[b1]) + d3 * (ring[b6] - ring[b0])
    o = n_pl
    gy = (s0 * ring[b3 + o] + s1 * (ring[b2 + o] + ring[b4 + o])
          + s2 * (ring[b1 + o] + ring[b5 + o]) + s3 * (ring[b0 + o] + ring[b6 + o]))
    o = 2 * n_pl
    gz = (s0 * ring[b3 + o] + s1 * (ring[b2 + o] + ring[b4 + o])
          + s2 * (ring[b1 + o] + ring[b5 + o]) + s3 * (ring[b0 + o] + ring[b6 + o]))
    f = (s0 * ring[b3] + s1 * (ring[b2] + ring[b4]) + s2 * (ring[b1] + ring[b5])
         + s3 * (ring[b0] + ring[b6]))
    return gx, gy, gz, f


@njit(cache=True, nogil=True, inline="always")
def unit_normal(gx, gy, gz):
    """``(-g / |g|, True)`` in float64, or ``(+z, False)`` when ``|g| <=
    GRAD_EPS`` (then :func:`fallback_normal` decides)."""
    gx = np.float64(gx)
    gy = np.float64(gy)
    gz = np.float64(gz)
    g = math.sqrt(gx * gx + gy * gy + gz * gz)
    if g > GRAD_EPS:
        return -gx / g, -gy / g, -gz / g, True
    return 0.0, 0.0, 1.0, False


@njit(cache=True, nogil=True, inline="always")
def vertex_shift(f, gx, gy, gz, iso, max_out, max_in):
    """Newton step ``s`` [voxels] from a voxel centre to the level set
    ``f = iso`` along the normal ``-g / |g|`` (module docstring), in
    float64 from the float32 field values; 0 when ``|g| <= GRAD_EPS``."""
    gx = np.float64(gx)
    gy = np.float64(gy)
    gz = np.float64(gz)
    g = math.sqrt(gx * gx + gy * gy + gz * gz)
    if not g > GRAD_EPS:
        return 0.0
    s = (np.float64(f) - iso) / g
    return min(max(s, -max_in), max_out)


@njit(cache=True, nogil=True)
def fallback_normal(d, c0, Y, Z):
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
