"""The hybrid surface's geometry tables (qualifying triples per cell code,
their faces and keys) built from the definition at import, and the
triangle/vertex record layouts shared by its kernels (:mod:`bonesim.engine.surface`)."""
from __future__ import annotations

import itertools

import numpy as np
from numba import njit, prange

from bonesim.engine.grid import find_brick
from bonesim.engine.shading import (NORMAL_RADIUS)

__all__ = ["MAX_PER_CELL", "RESHADE_REACH", "CORNER_OFFSETS", "TRIPLE_CORNERS",
           "N_TRIPLES", "qualifying_triples", "TRIPLE_FACE", "QUAL_N", "QUAL_KEY",
           "QUAL_NMIN"]


#: Most triples that qualify in one cell (checked when the table is built).
MAX_PER_CELL = 4
#: Chebyshev distance [voxels] from a removed or touched voxel within which
#: :meth:`Surface.update` may move vertices and change their normals (colours can change
#: further, up to the thin-bone tint's reach); for a renderer tracking
#: which vertices changed.
RESHADE_REACH = NORMAL_RADIUS

# ----------------------------------------------------------------------------
# Geometry tables, built from the definition at import.
# ----------------------------------------------------------------------------
#: (8, 3) int32: offset of each cell corner from the cell's minimum corner.
CORNER_OFFSETS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)],
                          dtype=np.int32)
#: (56, 3) int32: the three corners (ascending) of each triple id.
TRIPLE_CORNERS = np.array(list(itertools.combinations(range(8), 3)), dtype=np.int32)
N_TRIPLES = TRIPLE_CORNERS.shape[0]
# Code bits of the corners with coordinate 0 along x, y, z (a cell's low half):
# the cell below C along that axis has its far half empty iff its code has
# none of these bits.
LOW_HALF_X = 0x0F
LOW_HALF_Y = 0x33
LOW_HALF_Z = 0x55


def _triple_face(t):
    """-1 for a triple inside the cell, ``a`` if it lies in the minimum face
    along axis ``a``, ``3 + a`` if in the maximum face."""
    offs = [tuple(int(v) for v in CORNER_OFFSETS[c]) for c in t]
    for a in range(3):
        vals = {o[a] for o in offs}
        if len(vals) == 1:
            return a if vals.pop() == 0 else 3 + a
    return -1


def _qualify(code, t):
    """Orientation (+1: right-hand normal of the ascending triple, -1:
    opposite) if triple ``t`` qualifies in a cell of occupancy ``code``,
    else ``None``. Direct transcription of the definition."""
    if any(not (code >> c) & 1 for c in t):
        return None
    p = [tuple(int(v) for v in CORNER_OFFSETS[c]) for c in t]
    u = [p[1][i] - p[0][i] for i in range(3)]
    w = [p[2][i] - p[0][i] for i in range(3)]
    n = (u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0])
    side = {}
    for c in range(8):
        if c in t:
            continue
        o = CORNER_OFFSETS[c]
        side[c] = sum(n[i] * (int(o[i]) - p[0][i]) for i in range(3))
    coplanar = [c for c, s in side.items() if s == 0]
    if coplanar:                                   # a quad: face or diagonal rectangle
        (c4,) = coplanar
        if (code >> c4) & 1:
            quad = sorted(list(t) + [c4])
            low = quad[0]
            far = max(quad, key=lambda c: sum((int(CORNER_OFFSETS[c][i])
                                               - int(CORNER_OFFSETS[low][i])) ** 2
                                              for i in range(3)))
            if not (low in t and far in t):
                return None
    occ_pos = any((code >> c) & 1 and s > 0 for c, s in side.items())
    occ_neg = any((code >> c) & 1 and s < 0 for c, s in side.items())
    emp_pos = any(not (code >> c) & 1 and s > 0 for c, s in side.items())
    emp_neg = any(not (code >> c) & 1 and s < 0 for c, s in side.items())
    if occ_pos and occ_neg:
        return None
    if occ_neg:
        return 1 if emp_pos else None
    if occ_pos:
        return -1 if emp_neg else None
    if emp_pos and emp_neg:                        # one-voxel sheet
        first = next(x for x in n if x != 0)
        return -1 if first > 0 else 1
    return 1 if emp_pos else -1


def qualifying_triples(code):
    """Triples that qualify in a cell of occupancy ``code``.

    Returns
    -------
    list of (tid, oriented corners)
        ``oriented corners`` is a 3-tuple of corner indices in winding order.
    """
    out = []
    for tid in range(N_TRIPLES):
        t = tuple(int(c) for c in TRIPLE_CORNERS[tid])
        o = _qualify(code, t)
        if o is not None:
            out.append((tid, t if o > 0 else (t[0], t[2], t[1])))
    return out


def _build_tables():
    face = np.array([_triple_face(TRIPLE_CORNERS[t]) for t in range(N_TRIPLES)], dtype=np.int8)
    qn = np.zeros(256, dtype=np.int32)
    qkey = np.full((256, MAX_PER_CELL), -1, dtype=np.int16)
    qnmin = np.zeros((256, 3), dtype=np.int32)
    for code in range(256):
        q = qualifying_triples(code)
        if len(q) > MAX_PER_CELL:
            raise AssertionError("qualifying-triple bound violated")
        qn[code] = len(q)
        for s, (tid, oc) in enumerate(q):
            flip = 0 if oc == tuple(TRIPLE_CORNERS[tid]) else 1
            qkey[code, s] = 2 * tid + flip
            if 0 <= face[tid] < 3:
                qnmin[code, face[tid]] += 1
    return face, qn, qkey, qnmin


#: (56,) int8: -1 interior triple, a = min face along axis a, 3 + a = max face.
TRIPLE_FACE, QUAL_N, QUAL_KEY, QUAL_NMIN = _build_tables()
# QUAL_N[code]: number of qualifying triples; QUAL_KEY[code, s] = 2 * tid + flip
# (flip 1: winding (c0, c2, c1)); QUAL_NMIN[code, a]: how many of them lie in
# the minimum face along a.


# Triangle records: Surface._trec is (tcap, 8) int32, one 32-byte row per
# triangle slot holding everything the update reads about it, so a step along
# a list touches one cache line: corners (tri), key, the next triangle on
# each corner's vertex list (tnext) and on the owner list.
TR_KEY = 3
TR_NEXT = 4
TR_ONEXT = 7
TR_WIDTH = 8
TR_FILL = np.array([0, 0, 0, -1, -1, -1, -1, -1], dtype=np.int32)
# Vertex records: Surface._vrec is (vcap, 2) int32: head of the vertex list
# (vhead) and of the owner list.
VR_HEAD = 0
VR_OHEAD = 1

# counters kept in Surface._cnt
V_HW, V_NFREE, T_HW, T_NFREE, V_ALIVE, T_ALIVE = range(6)
# status / statistics slots of the update kernel (S_RESUME: where an update
# that stopped for room goes on)
(S_STATUS, S_NEED_V, S_NEED_T, S_V_ADD, S_V_DEL, S_T_ADD, S_T_DEL,
 _S_RESHADE, S_CELLS, S_ERR, S_RESUME) = range(11)
N_STATS = 11


# ----------------------------------------------------------------------------
# Small kernels of the surface's lists
# ----------------------------------------------------------------------------
@njit(cache=True, nogil=True, inline="always")
def neighbours_of(keys, vals, bricks, b, out):
    """``out[b, :]``: brick ``b``'s row of :func:`brick_neighbours`."""
    s = 0
    for di in range(-1, 2):
        for dj in range(-1, 2):
            for dk in range(-1, 2):
                out[b, s] = find_brick(keys, vals, bricks[b, 0] + di,
                                       bricks[b, 1] + dj, bricks[b, 2] + dk)
                s += 1


@njit(cache=True, nogil=True, parallel=True)
def brick_neighbours(keys, vals, bricks):
    """(n_bricks, 27) int32: index of each brick's 26 neighbours and itself
    (slot ``9 * (di + 1) + 3 * (dj + 1) + (dk + 1)``), -1 when absent."""
    n = bricks.shape[0]
    out = np.empty((n, 27), dtype=np.int32)
    for b in prange(n):
        neighbours_of(keys, vals, bricks, b, out)
    return out


@njit(cache=True, nogil=True, inline="always")
def _slot_of(tri, t, v):
    if tri[t, 0] == v:
        return 0
    if tri[t, 1] == v:
        return 1
    return 2


@njit(cache=True, nogil=True)
def triangles_of_vertex(vhead, tri, tnext, v, out):
    """Fill ``out`` with the triangles of vertex ``v``; return their number
    (which may exceed ``out``'s length; then only the first ones are written)."""
    n = 0
    t = vhead[v]
    while t >= 0:
        if n < out.shape[0]:
            out[n] = t
        n += 1
        t = tnext[t, _slot_of(tri, t, v)]
    return n


@njit(cache=True, nogil=True)
def link_all(trec, vrec, n_t):
    for t in range(n_t - 1, -1, -1):
        if trec[t, TR_KEY] < 0:
            continue
        for s in range(3):
            v = trec[t, s]
            trec[t, TR_NEXT + s] = vrec[v, VR_HEAD]
            vrec[v, VR_HEAD] = t
        v = trec[t, 0]
        trec[t, TR_ONEXT] = vrec[v, VR_OHEAD]
        vrec[v, VR_OHEAD] = t


# ----------------------------------------------------------------------------
# The drawn winding (Surface.tflip)
# ----------------------------------------------------------------------------
@njit(cache=True, nogil=True, inline="always")
def _flip(ax, ay, az, bx, by, bz, cx, cy, cz, nx, ny, nz):
    """Whether the face normal ``(b - a) x (c - a)`` points against ``n``
    (the sum of the corners' normals): the triangle is then drawn as
    ``(a, c, b)``."""
    ux, uy, uz = bx - ax, by - ay, bz - az
    wx, wy, wz = cx - ax, cy - ay, cz - az
    return (uy * wz - uz * wy) * nx + (uz * wx - ux * wz) * ny + (ux * wy - uy * wx) * nz < 0.0


@njit(cache=True, nogil=True, inline="always")
def flip_of(trec, t, pos, nrm):
    """:func:`_flip` of triangle record ``t`` (corners ``trec[t, 0:3]``) with
    the vertex positions ``pos`` and normals ``nrm``."""
    a = trec[t, 0]
    b = trec[t, 1]
    c = trec[t, 2]
    return _flip(pos[a, 0], pos[a, 1], pos[a, 2], pos[b, 0], pos[b, 1], pos[b, 2],
                 pos[c, 0], pos[c, 1], pos[c, 2], nrm[a, 0] + nrm[b, 0] + nrm[c, 0],
                 nrm[a, 1] + nrm[b, 1] + nrm[c, 1], nrm[a, 2] + nrm[b, 2] + nrm[c, 2])


@njit(cache=True, nogil=True)
def orient_of(vrec, trec, vlist, pos, nrm, tflip):
    """``tflip`` of every triangle of the vertices ``vlist`` (their vertex
    lists; a triangle met twice is set twice, to the same value)."""
    for q in range(vlist.shape[0]):
        v = vlist[q]
        t = vrec[v, VR_HEAD]
        while t >= 0:
            tflip[t] = 1 if flip_of(trec, t, pos, nrm) else 0
            s = 0 if trec[t, 0] == v else (1 if trec[t, 1] == v else 2)
            t = trec[t, TR_NEXT + s]
