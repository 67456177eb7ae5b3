"""Hybrid voxel / triangle bone surface: the vertices *are* surface voxels.

This module keeps a triangle mesh of the bone whose vertices sit at the
centres of surface voxels of a :class:`bonesim.grid.Grid`, and updates it in
time proportional to the number of voxels the drill removed.

Definitions
-----------
Voxels are addressed by integer ``(i, j, k)`` along the case frame's
``(x, y, z)`` axes; voxel ``(i, j, k)`` has its centre at
``origin_mm + spacing_mm * (i, j, k)`` [mm].

Occupied voxel
    density > 0. Voxels in bricks the grid did not allocate are empty.
Surface voxel
    an occupied voxel with at least one empty voxel among its 26 neighbours.
    Each surface voxel carries exactly one vertex, at its centre.
Vertex normal, vertex colour
    defined in :mod:`bonesim.shading`: the normal from a Gaussian-derivative
    density gradient over the 7x7x7 voxels around the vertex, the colour the
    structure's display colour shaded by the voxel's density and, where the
    bone over a non-bone structure is thin, blended toward that structure's
    colour (the bone labels are given to :meth:`Surface.build`).
Cell
    the 2x2x2 block of voxels ``m + {0, 1}^3`` named by its minimum corner
    ``m``. Corner ``c`` (0..7) of a cell is the voxel ``m + (c >> 2 & 1,
    c >> 1 & 1, c & 1)``, so corner order is lexicographic ``(i, j, k)``
    order. The cell's *code* is the 8-bit mask of its occupied corners.
Triangle
    three corners of one cell (any three corners of a cell are pairwise
    26-adjacent); a cell has 56 such triples.
Qualifying triple
    triple ``T`` of cell ``C`` *qualifies in C* when its three corners are
    occupied, every occupied corner of ``C`` off ``T``'s plane lies on one
    side of that plane (the "-" side), and at least one *empty* corner of
    ``C`` lies strictly on the other side (the "+" side): ``T`` is a face of
    the convex hull of ``C``'s occupied corners that looks at empty space
    inside ``C``. Its normal points to "+", out of the bone. If no occupied
    corner lies off the plane and empty corners lie on both sides (a sheet
    one voxel thick), "+" is the side whose normal has its first non-zero
    component (in ``x, y, z`` order) *negative*; this matches the rule for
    sheets lying in a cell face below.
Coplanar quads
    when the plane of ``T`` holds four corners of the cell (the six faces and
    the six diagonal rectangles) and all four are occupied, only the two
    triangles that contain the quad's diagonal through its lowest corner
    (lexicographic ``(i, j, k)``) may qualify. The lowest corner is a global
    property of the four voxels, so the two cells sharing a face agree.
Each triangle once
    a triple lying in a face shared by cells ``L`` (below, along the face's
    axis) and ``U = L + e_axis`` is emitted once if it qualifies in either;
    it is *owned* by ``L`` and oriented as in ``L`` if it qualifies there,
    otherwise owned by and oriented as in ``U``. (Qualifying in ``L`` means
    ``L``'s far half is empty, so a face sheet gets the normal ``-e_axis``.)
    All other triples belong to their only cell. The identity of a triangle
    is ``(owner cell, triple id, orientation)``. Every corner of a qualifying
    triple is 26-adjacent to an empty corner of the owner, hence is a surface
    voxel with a vertex; the kernels check this and report a violation.
Winding
    vertices are stored counter-clockwise seen from the "+" side, so the
    right-hand normal ``(b - a) x (c - a)`` points out of the bone.

Implementation
--------------
Everything the kernels need about the 56 triples is precomputed at import,
from the geometric definition above, into a 256-entry table: for each code,
the (at most four) qualifying triples with their orientation. Ownership of
face triples adds one test per axis: a triple in ``C``'s minimum face along
``a`` is dropped from ``C`` when the four voxels just below that face are
empty (then it qualifies in, and belongs to, the lower cell). So the
triangles a cell owns depend only on its own code and on those 3 x 4 voxels.

Full tessellation (:meth:`Surface.build`) works per brick, in parallel: each
brick and its one-voxel halo are gathered into a 10x10x10 array; bricks whose
box is all bone or whose brick-plus-upper-halo is all empty are skipped. A
first pass counts vertices and owned triangles per brick, prefix sums give
every brick its output ranges, a second pass writes vertices (and the
voxel -> vertex map), a third writes triangles.

Incremental update (:meth:`Surface.update`): a removed voxel that is empty
now is a *source*. Only cells containing a source change code, and besides
them only the cells whose minimum face has a source just below it (their
ownership test reads it): 20 cells per source can change what they own.
Only the 26 neighbours of a source can join or leave the surface (and every
occupied neighbour of an empty voxel is a surface voxel). For each affected
cell the kernel compares the triangles it owns now (found through the owner
lists below) with those it should own, drops the difference, drops the
vertices of emptied voxels, creates the vertices of voxels that became
surface and adds the new triangles; then
:meth:`bonesim.shading.Shader.refresh` recomputes the normal and colour of
every vertex the removed and touched voxels can have changed. The old triangles come from the mesh
itself, not from a guess of the old occupancy, so extra entries (voxels
listed twice, still bone, already empty before the batch, or never bone)
are harmless; what must hold is that every voxel whose density changed
since the last update is listed.

When the inputs fit a box of moderate size (the usual case, see
``FAST_MIN_VOXELS``), the update runs on dense copies of that box: sets of
voxels and cells are bit rows (one uint64 per row of the box along k),
obtained from the inputs by a few shifts and ORs, and visited in (i, j, k)
order; the densities, occupancy and vertex slots of the box are gathered
once. Otherwise (inputs spread far apart, or a box deeper than 64 voxels
along k) cells and voxels are deduplicated with a window of flags or hash
sets and visited one by one. Either way the cost is proportional to the
number of input voxels, and the result is the same.

Vertex -> triangles map: every live triangle ``t`` is threaded on three
singly linked lists, one per corner. ``vhead[v]`` is the first triangle of
vertex ``v``'s list, and if ``tri[t, s] == v`` the next one is
``tnext[t, s]`` (``-1`` ends the list). A vertex lies in 8 cells that own at
most 4 triangles each, so a list has at most 32 entries. Adding a triangle
is O(1), removing it walks the lists of its corners (the update removes all
dead triangles of a list in one walk). A second, private list per vertex
(the *owner list*) holds only the triangles whose first vertex ``tri[t, 0]``
it is; since the first vertex is the owner cell's corner ``c0`` of the
triple, the triangles a cell owns are on the owner lists of its corners
0..5. The lists are built in one pass after a full tessellation.

Storage: everything the update reads about a triangle slot (corners, key,
list links) is one 32-byte row of a ``(tcap, 8)`` int32 array, and the two
list heads of a vertex share an 8-byte row, so a step along a list touches
one cache line; ``tri``, ``tri_key``, ``tnext`` and ``vhead`` are views of
these rows.

Voxel -> vertex map: ``vmap`` is an int32 array shaped like the grid's bricks
``(n_bricks, 512)``, ``-1`` where a voxel has no vertex.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros

from bonesim.grid import (BRICK, BRICK_MASK, BRICK_SHIFT, BRICK_VOXELS, Grid,
                          find_brick, voxel_offset)
from bonesim.shading import (GRAD_EPS, NORMAL_RADIUS, SHADE_MIN, Shader, ShadingParams,
                             bone_labels)

__all__ = ["Surface", "CanonicalSurface", "SHADE_MIN", "GRAD_EPS", "RESHADE_REACH", "warmup",
           "qualifying_triples", "CORNER_OFFSETS", "TRIPLE_CORNERS"]

#: Most triples that qualify in one cell (checked when the table is built).
MAX_PER_CELL = 4
#: Chebyshev distance [voxels] from a removed or touched voxel within which
#: :meth:`Surface.update` may change vertex normals (colours can change
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
_LOW_HALF_X = 0x0F
_LOW_HALF_Y = 0x33
_LOW_HALF_Z = 0x55


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


# Offsets (from a removed voxel p) of every cell whose owned triangles may
# change: cells containing p (p - {0,1}^3) and their 6 face neighbours.
_AFFECTED = sorted({tuple(int(x) for x in (-np.array(d) + e))
                    for d in itertools.product((0, 1), repeat=3)
                    for e in [(0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0),
                              (0, 0, 1), (0, 0, -1)]})
AFFECTED_CELL_OFFSETS = np.array(_AFFECTED, dtype=np.int32)

# Triangle records: Surface._trec is (tcap, 8) int32, one 32-byte row per
# triangle slot holding everything the update reads about it, so a step along
# a list touches one cache line: corners (tri), key, the next triangle on
# each corner's vertex list (tnext) and on the owner list.
_TR_KEY = 3
_TR_NEXT = 4
_TR_ONEXT = 7
_TR_WIDTH = 8
_TR_FILL = np.array([0, 0, 0, -1, -1, -1, -1, -1], dtype=np.int32)
# Vertex records: Surface._vrec is (vcap, 2) int32: head of the vertex list
# (vhead) and of the owner list.
_VR_HEAD = 0
_VR_OHEAD = 1

# counters kept in Surface._cnt
_V_HW, _V_NFREE, _T_HW, _T_NFREE, _V_ALIVE, _T_ALIVE = range(6)
# status / statistics slots of the update kernel
(_S_STATUS, _S_NEED_V, _S_NEED_T, _S_V_ADD, _S_V_DEL, _S_T_ADD, _S_T_DEL,
 _S_RESHADE, _S_CELLS, _S_ERR) = range(10)
_N_STATS = 10


# ----------------------------------------------------------------------------
# Small kernels shared by both paths
# ----------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _brick_neighbours(keys, vals, bricks):
    """(n_bricks, 27) int32: index of each brick's 26 neighbours and itself
    (slot ``9 * (di + 1) + 3 * (dj + 1) + (dk + 1)``), -1 when absent."""
    n = bricks.shape[0]
    out = np.empty((n, 27), dtype=np.int32)
    for b in range(n):
        s = 0
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    out[b, s] = find_brick(keys, vals, bricks[b, 0] + di,
                                           bricks[b, 1] + dj, bricks[b, 2] + dk)
                    s += 1
    return out


@njit(cache=True, nogil=True, inline="always")
def _nb_slot(qi, qj, qk, i, j, k):
    """Slot in the 27-neighbour row of voxel q's brick that holds voxel (i, j, k)."""
    return (((i >> BRICK_SHIFT) - (qi >> BRICK_SHIFT) + 1) * 9
            + ((j >> BRICK_SHIFT) - (qj >> BRICK_SHIFT) + 1) * 3
            + ((k >> BRICK_SHIFT) - (qk >> BRICK_SHIFT) + 1))


@njit(cache=True, nogil=True, inline="always")
def _slot_of(tri, t, v):
    if tri[t, 0] == v:
        return 0
    if tri[t, 1] == v:
        return 1
    return 2


@njit(cache=True, nogil=True)
def _triangles_of_vertex(vhead, tri, tnext, v, out):
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
def _link_all(trec, vrec, n_t):
    for t in range(n_t - 1, -1, -1):
        if trec[t, _TR_KEY] < 0:
            continue
        for s in range(3):
            v = trec[t, s]
            trec[t, _TR_NEXT + s] = vrec[v, _VR_HEAD]
            vrec[v, _VR_HEAD] = t
        v = trec[t, 0]
        trec[t, _TR_ONEXT] = vrec[v, _VR_OHEAD]
        vrec[v, _VR_OHEAD] = t


# ----------------------------------------------------------------------------
# Full tessellation, per brick
# ----------------------------------------------------------------------------
_CHUNK = 32            # bricks per parallel work item
_L = BRICK + 2         # local box: brick plus a one-voxel halo on each side


@njit(cache=True, nogil=True)
def _gather_local(density, nbr, b, loc):
    """Copy the densities of brick ``b`` plus a one-voxel halo into ``loc``
    (``(10, 10, 10)``; ``loc[x + 1, y + 1, z + 1]`` is voxel ``(x, y, z)`` of
    the brick). Returns ``(occupied in the brick and its upper halo,
    occupied in the whole box)``."""
    n_up = 0
    n_all = 0
    for lx in range(_L):
        x = lx - 1
        sx = ((x >> BRICK_SHIFT) + 1) * 9
        ox = (x & BRICK_MASK) << 6
        for ly in range(_L):
            y = ly - 1
            sy = sx + ((y >> BRICK_SHIFT) + 1) * 3
            oy = ox | ((y & BRICK_MASK) << 3)
            for lz in range(_L):
                z = lz - 1
                nb = nbr[b, sy + (z >> BRICK_SHIFT) + 1]
                if nb >= 0:
                    d = density[nb, oy | (z & BRICK_MASK)]
                else:
                    d = np.float32(0.0)
                loc[lx, ly, lz] = d
                if d > 0:
                    n_all += 1
                    if lx > 0 and ly > 0 and lz > 0:
                        n_up += 1
    return n_up, n_all


@njit(cache=True, nogil=True)
def _local_codes(loc, codes):
    """Occupancy code of each cell with minimum corner at local (0..8)^3."""
    for x in range(_L - 1):
        for y in range(_L - 1):
            for z in range(_L - 1):
                c = 0
                for cn in range(8):
                    if loc[x + (cn >> 2), y + ((cn >> 1) & 1), z + (cn & 1)] > 0:
                        c |= 1 << cn
                codes[x, y, z] = c


@njit(cache=True, nogil=True, inline="always")
def _is_surface_local(loc, x, y, z):
    if not loc[x, y, z] > 0:
        return False
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-1, 2):
                if not loc[x + a, y + b, z + c] > 0:
                    return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _owned_count(codes, x, y, z):
    code = codes[x, y, z]
    n = QUAL_N[code]
    if n > 0:
        if codes[x - 1, y, z] & _LOW_HALF_X == 0:
            n -= QUAL_NMIN[code, 0]
        if codes[x, y - 1, z] & _LOW_HALF_Y == 0:
            n -= QUAL_NMIN[code, 1]
        if codes[x, y, z - 1] & _LOW_HALF_Z == 0:
            n -= QUAL_NMIN[code, 2]
    return n


@njit(cache=True, nogil=True, parallel=True)
def _build_count(density, nbr, nv, nt):
    nb_tot = nbr.shape[0]
    n_chunks = (nb_tot + _CHUNK - 1) // _CHUNK
    for ch in prange(n_chunks):
        loc = np.empty((_L, _L, _L), dtype=np.float32)
        codes = np.empty((_L - 1, _L - 1, _L - 1), dtype=np.int64)
        for b in range(ch * _CHUNK, min(nb_tot, (ch + 1) * _CHUNK)):
            n_up, n_all = _gather_local(density, nbr, b, loc)
            if n_up == 0 or n_all == _L * _L * _L:
                nv[b] = 0
                nt[b] = 0
                continue
            cv = 0
            for x in range(1, _L - 1):
                for y in range(1, _L - 1):
                    for z in range(1, _L - 1):
                        if _is_surface_local(loc, x, y, z):
                            cv += 1
            _local_codes(loc, codes)
            ct = 0
            for x in range(1, _L - 1):
                for y in range(1, _L - 1):
                    for z in range(1, _L - 1):
                        ct += _owned_count(codes, x, y, z)
            nv[b] = cv
            nt[b] = ct


@njit(cache=True, nogil=True, parallel=True)
def _build_vertices(density, nbr, bricks, origin, spacing, voff, vmap, pos, vijk):
    nb_tot = nbr.shape[0]
    n_chunks = (nb_tot + _CHUNK - 1) // _CHUNK
    for ch in prange(n_chunks):
        loc = np.empty((_L, _L, _L), dtype=np.float32)
        for b in range(ch * _CHUNK, min(nb_tot, (ch + 1) * _CHUNK)):
            for o in range(BRICK_VOXELS):
                vmap[b, o] = -1
            if voff[b + 1] == voff[b]:
                continue
            _gather_local(density, nbr, b, loc)
            v = voff[b]
            bi = bricks[b, 0] << BRICK_SHIFT
            bj = bricks[b, 1] << BRICK_SHIFT
            bk = bricks[b, 2] << BRICK_SHIFT
            for x in range(1, _L - 1):
                for y in range(1, _L - 1):
                    for z in range(1, _L - 1):
                        if not _is_surface_local(loc, x, y, z):
                            continue
                        o = ((x - 1) << 6) | ((y - 1) << 3) | (z - 1)
                        i = bi + x - 1
                        j = bj + y - 1
                        k = bk + z - 1
                        vmap[b, o] = v
                        vijk[v, 0] = i
                        vijk[v, 1] = j
                        vijk[v, 2] = k
                        pos[v, 0] = origin[0] + spacing * i
                        pos[v, 1] = origin[1] + spacing * j
                        pos[v, 2] = origin[2] + spacing * k
                        v += 1


@njit(cache=True, nogil=True, parallel=True)
def _build_triangles(density, nbr, toff, vmap, trec, err):
    nb_tot = nbr.shape[0]
    n_chunks = (nb_tot + _CHUNK - 1) // _CHUNK
    for ch in prange(n_chunks):
        loc = np.empty((_L, _L, _L), dtype=np.float32)
        codes = np.empty((_L - 1, _L - 1, _L - 1), dtype=np.int64)
        for b in range(ch * _CHUNK, min(nb_tot, (ch + 1) * _CHUNK)):
            if toff[b + 1] == toff[b]:
                continue
            _gather_local(density, nbr, b, loc)
            _local_codes(loc, codes)
            t = toff[b]
            for x in range(1, _L - 1):
                for y in range(1, _L - 1):
                    for z in range(1, _L - 1):
                        code = codes[x, y, z]
                        n = QUAL_N[code]
                        if n == 0:
                            continue
                        low0 = codes[x - 1, y, z] & _LOW_HALF_X == 0
                        low1 = codes[x, y - 1, z] & _LOW_HALF_Y == 0
                        low2 = codes[x, y, z - 1] & _LOW_HALF_Z == 0
                        for q in range(n):
                            key = QUAL_KEY[code, q]
                            tid = key >> 1
                            f = TRIPLE_FACE[tid]
                            if (f == 0 and low0) or (f == 1 and low1) or (f == 2 and low2):
                                continue
                            for s in range(3):
                                cs = s
                                if key & 1 and s > 0:
                                    cs = 3 - s
                                cn = TRIPLE_CORNERS[tid, cs]
                                # brick-relative coordinates of the corner (0..8)
                                rx = x - 1 + (cn >> 2)
                                ry = y - 1 + ((cn >> 1) & 1)
                                rz = z - 1 + (cn & 1)
                                nb = nbr[b, ((rx >> BRICK_SHIFT) + 1) * 9
                                         + ((ry >> BRICK_SHIFT) + 1) * 3
                                         + (rz >> BRICK_SHIFT) + 1]
                                v = -1
                                if nb >= 0:
                                    v = vmap[nb, ((rx & BRICK_MASK) << 6)
                                             | ((ry & BRICK_MASK) << 3) | (rz & BRICK_MASK)]
                                if v < 0:
                                    err[ch] += 1
                                trec[t, s] = v
                            trec[t, _TR_KEY] = key
                            t += 1


# ----------------------------------------------------------------------------
# Incremental update
# ----------------------------------------------------------------------------
# The update is split into small kernels, one loop nest each: a call to a
# non-inlined function inside a hot loop makes LLVM reload every array
# descriptor after it and slows the whole loop down several times.

#: Margin [voxels] around the inputs of an update covered by its window.
_WINDOW_MARGIN = 3
#: An update deduplicates cells and voxels with a dense window of flags over
#: the bounding box of its inputs (plus margin) when that box holds at most
#: this many voxels per input voxel (or 32768 in all); otherwise with hash sets.
WINDOW_VOXELS_PER_INPUT = 512


@njit(cache=True, nogil=True, inline="always")
def _hslot(key, mask):
    h = np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)
    return np.int64((h >> np.uint64(29)) & np.uint64(mask))


@njit(cache=True, nogil=True)
def _hset_new(n):
    cap = 64
    while cap < 2 * n:
        cap *= 2
    return np.full(cap, -1, dtype=np.int64)


@njit(cache=True, nogil=True, inline="always")
def _hset_add(h, key):
    """Insert ``key`` (>= 0) into the open-addressing set ``h``; True if new."""
    mask = h.shape[0] - 1
    s = _hslot(key, mask)
    while True:
        k = h[s]
        if k == key:
            return False
        if k == -1:
            h[s] = key
            return True
        s = (s + 1) & mask


@njit(cache=True, nogil=True, inline="always")
def _vkey(i, j, k):
    # voxel coordinates packed like brick keys (non-negative for |coord| < 2**20)
    return ((np.int64(i) + (1 << 20)) << 42) | ((np.int64(j) + (1 << 20)) << 21) \
        | (np.int64(k) + (1 << 20))


@njit(cache=True, nogil=True, inline="always")
def _mark(use_win, flags, bit, wlo, wd, h, i, j, k):
    """Mark voxel (i, j, k) in the window flags (or hash set); True if it
    was not marked before."""
    if use_win:
        idx = ((i - wlo[0]) * wd[1] + (j - wlo[1])) * wd[2] + (k - wlo[2])
        f = flags[idx]
        if f & bit:
            return False
        flags[idx] = f | bit
        return True
    return _hset_add(h, _vkey(i, j, k))


@njit(cache=True, nogil=True, inline="always")
def _occ_near(density, nbr, b, qi, qj, qk, i, j, k):
    """Is voxel (i, j, k), within one brick of voxel q (brick b), occupied?"""
    nb = nbr[b, _nb_slot(qi, qj, qk, i, j, k)]
    if nb < 0:
        return False
    return density[nb, voxel_offset(i, j, k)] > 0


@njit(cache=True, nogil=True, inline="always")
def _vmap_near(vmap, nbr, b, qi, qj, qk, i, j, k):
    nb = nbr[b, _nb_slot(qi, qj, qk, i, j, k)]
    if nb < 0:
        return -1
    return vmap[nb, voxel_offset(i, j, k)]


@njit(cache=True, nogil=True)
def _window_bricks(keys, vals, blo, bd):
    wbr = np.empty(bd[0] * bd[1] * bd[2], dtype=np.int32)
    s = 0
    for bi in range(blo[0], blo[0] + bd[0]):
        for bj in range(blo[1], blo[1] + bd[1]):
            for bk in range(blo[2], blo[2] + bd[2]):
                wbr[s] = find_brick(keys, vals, bi, bj, bk)
                s += 1
    return wbr


@njit(cache=True, nogil=True)
def _items_bricks(use_win, wbr, blo, bd, keys, vals, items, n, out):
    """Brick index (-1 if absent) of the first ``n`` voxels of ``items``."""
    if use_win:
        for q in range(n):
            out[q] = wbr[(((items[q, 0] >> BRICK_SHIFT) - blo[0]) * bd[1]
                          + ((items[q, 1] >> BRICK_SHIFT) - blo[1])) * bd[2]
                         + ((items[q, 2] >> BRICK_SHIFT) - blo[2])]
    else:
        for q in range(n):
            out[q] = find_brick(keys, vals, items[q, 0] >> BRICK_SHIFT,
                                items[q, 1] >> BRICK_SHIFT, items[q, 2] >> BRICK_SHIFT)


@njit(cache=True, nogil=True)
def _collect(removed, touched, rbrick, density, use_win, flags, wlo, wd, hc, hv, cells, cand):
    """Sources (removed voxels that are empty now), the cells whose owned
    triangles may change (32 per source) and the voxels to revisit (the
    3x3x3 neighbourhoods of all inputs, those next to a source first).

    Returns ``(n_cells, n_candidates, n_topology_candidates)``.
    """
    nr = removed.shape[0]
    ntch = touched.shape[0]
    n_aff = AFFECTED_CELL_OFFSETS.shape[0]
    is_src = np.zeros(nr, dtype=np.uint8)
    for r in range(nr):
        b = rbrick[r]
        if b >= 0 and not density[b, voxel_offset(removed[r, 0], removed[r, 1],
                                                  removed[r, 2])] > 0:
            is_src[r] = 1
    nc = 0
    ncand = 0
    for r in range(nr):
        if not is_src[r]:
            continue
        pi = removed[r, 0]
        pj = removed[r, 1]
        pk = removed[r, 2]
        for o in range(n_aff):
            ci = pi + AFFECTED_CELL_OFFSETS[o, 0]
            cj = pj + AFFECTED_CELL_OFFSETS[o, 1]
            ck = pk + AFFECTED_CELL_OFFSETS[o, 2]
            if _mark(use_win, flags, 1, wlo, wd, hc, ci, cj, ck):
                cells[nc, 0] = ci
                cells[nc, 1] = cj
                cells[nc, 2] = ck
                nc += 1
        for a in range(-1, 2):
            for bb in range(-1, 2):
                for cc in range(-1, 2):
                    if _mark(use_win, flags, 2, wlo, wd, hv, pi + a, pj + bb, pk + cc):
                        cand[ncand, 0] = pi + a
                        cand[ncand, 1] = pj + bb
                        cand[ncand, 2] = pk + cc
                        ncand += 1
    n_topo = ncand
    for r in range(nr + ntch):
        if r < nr:
            if is_src[r]:
                continue
            pi = removed[r, 0]
            pj = removed[r, 1]
            pk = removed[r, 2]
        else:
            pi = touched[r - nr, 0]
            pj = touched[r - nr, 1]
            pk = touched[r - nr, 2]
        for a in range(-1, 2):
            for bb in range(-1, 2):
                for cc in range(-1, 2):
                    if _mark(use_win, flags, 2, wlo, wd, hv, pi + a, pj + bb, pk + cc):
                        cand[ncand, 0] = pi + a
                        cand[ncand, 1] = pj + bb
                        cand[ncand, 2] = pk + cc
                        ncand += 1
    return nc, ncand, n_topo


@njit(cache=True, nogil=True)
def _plan_cells(density, nbr, vmap, ohead, onext, ttid, cells, cbrick, nc,
                newk, nnew, oldk, oldt, nold, stats):
    """Triangles each affected cell owns now (``oldk/oldt``) and should own
    (``newk``). Returns ``(n_to_add, n_to_drop)``."""
    vc = np.empty(8, dtype=np.int32)
    n_tadd = 0
    n_tdel = 0
    for c in range(nc):
        nnew[c] = 0
        nold[c] = 0
        b = cbrick[c]
        if b < 0:
            continue              # no corner of this cell was ever tissue
        ci = cells[c, 0]
        cj = cells[c, 1]
        ck = cells[c, 2]
        code = 0
        for cn in range(8):
            i = ci + (cn >> 2)
            j = cj + ((cn >> 1) & 1)
            k = ck + (cn & 1)
            nb = nbr[b, _nb_slot(ci, cj, ck, i, j, k)]
            vc[cn] = -1
            if nb >= 0:
                o = voxel_offset(i, j, k)
                if density[nb, o] > 0:
                    code |= 1 << cn
                vc[cn] = vmap[nb, o]
        n = QUAL_N[code]
        m = 0
        if n > 0:
            low0 = False
            low1 = False
            low2 = False
            if QUAL_NMIN[code, 0] > 0:
                low0 = True
                for u in range(2):
                    for w in range(2):
                        if _occ_near(density, nbr, b, ci, cj, ck, ci - 1, cj + u, ck + w):
                            low0 = False
            if QUAL_NMIN[code, 1] > 0:
                low1 = True
                for u in range(2):
                    for w in range(2):
                        if _occ_near(density, nbr, b, ci, cj, ck, ci + u, cj - 1, ck + w):
                            low1 = False
            if QUAL_NMIN[code, 2] > 0:
                low2 = True
                for u in range(2):
                    for w in range(2):
                        if _occ_near(density, nbr, b, ci, cj, ck, ci + u, cj + w, ck - 1):
                            low2 = False
            for q in range(n):
                key = QUAL_KEY[code, q]
                f = TRIPLE_FACE[key >> 1]
                if (f == 0 and low0) or (f == 1 and low1) or (f == 2 and low2):
                    continue
                newk[c, m] = key
                m += 1
        nnew[c] = m
        # Triangles this cell owns now: each one is on the owner list of
        # the vertex at the first corner c0 of its triple (c0 <= 5).
        mo = 0
        for cn in range(6):
            v = vc[cn]
            if v < 0:
                continue
            t = ohead[v]
            while t >= 0:
                key = ttid[t]
                if TRIPLE_CORNERS[key >> 1, 0] == cn:
                    if mo == oldt.shape[1]:
                        stats[_S_ERR] += 1
                    else:
                        oldt[c, mo] = t
                        oldk[c, mo] = key
                        mo += 1
                t = onext[t]
        nold[c] = mo
        # keys present in both lists stay; mark them by negating the old key
        for y in range(mo):
            for x in range(m):
                if oldk[c, y] == newk[c, x]:
                    oldk[c, y] = -1 - oldk[c, y]
                    newk[c, x] = -1 - newk[c, x]
                    break
        for x in range(m):
            if newk[c, x] >= 0:
                n_tadd += 1
        for y in range(mo):
            if oldk[c, y] >= 0:
                n_tdel += 1
    return n_tadd, n_tdel


@njit(cache=True, nogil=True)
def _plan_vertices(density, vmap, cand, qbrick, n_topo, qstat):
    """Vertices to create (``qstat`` 1) or drop (2) among the voxels next to
    a source. Every occupied 26-neighbour of an empty voxel is a surface
    voxel, so no neighbourhood test is needed. Returns ``(n_add, n_drop)``."""
    n_vadd = 0
    n_vdel = 0
    for q in range(n_topo):
        qstat[q] = 0
        b = qbrick[q]
        if b < 0:
            continue
        o = voxel_offset(cand[q, 0], cand[q, 1], cand[q, 2])
        occ = density[b, o] > 0
        if occ and vmap[b, o] < 0:
            qstat[q] = 1
            n_vadd += 1
        elif not occ and vmap[b, o] >= 0:
            qstat[q] = 2
            n_vdel += 1
    return n_vadd, n_vdel


@njit(cache=True, nogil=True, inline="always")
def _unlink(t, v, vhead, tri, tnext):
    """Remove triangle t from vertex v's list; False if it was not there."""
    prev = -1
    prev_s = 0
    cur = vhead[v]
    while cur >= 0 and cur != t:
        prev = cur
        prev_s = _slot_of(tri, cur, v)
        cur = tnext[cur, prev_s]
    if cur < 0:
        return False
    nxt = tnext[t, _slot_of(tri, t, v)]
    if prev < 0:
        vhead[v] = nxt
    else:
        tnext[prev, prev_s] = nxt
    return True


@njit(cache=True, nogil=True)
def _drop_triangles(oldt, oldk, nold, nc, vhead, tri, tnext, ttid, tfree, cnt, stats,
                    ohead, onext):
    for c in range(nc):
        for y in range(nold[c]):
            if oldk[c, y] < 0:
                continue                     # still owned
            t = oldt[c, y]
            for s in range(3):
                if not _unlink(t, tri[t, s], vhead, tri, tnext):
                    stats[_S_ERR] += 1
            v = tri[t, 0]
            prev = -1
            cur = ohead[v]
            while cur >= 0 and cur != t:
                prev = cur
                cur = onext[cur]
            if cur < 0:
                stats[_S_ERR] += 1
            elif prev < 0:
                ohead[v] = onext[t]
            else:
                onext[prev] = onext[t]
            ttid[t] = -1
            tfree[cnt[_T_NFREE]] = t
            cnt[_T_NFREE] += 1
            cnt[_T_ALIVE] -= 1
            stats[_S_T_DEL] += 1


@njit(cache=True, nogil=True)
def _edit_vertices(cand, qbrick, qstat, n_topo, origin, spacing, vmap, pos, vijk,
                   valive, vhead, ohead, vfree, cnt, stats):
    """Drop, then create, the vertices planned in ``qstat``."""
    for q in range(n_topo):
        if qstat[q] != 2:
            continue
        o = voxel_offset(cand[q, 0], cand[q, 1], cand[q, 2])
        v = vmap[qbrick[q], o]
        if vhead[v] >= 0:
            stats[_S_ERR] += 1
        vmap[qbrick[q], o] = -1
        valive[v] = 0
        vfree[cnt[_V_NFREE]] = v
        cnt[_V_NFREE] += 1
        cnt[_V_ALIVE] -= 1
        stats[_S_V_DEL] += 1
    for q in range(n_topo):
        if qstat[q] != 1:
            continue
        if cnt[_V_NFREE] > 0:
            cnt[_V_NFREE] -= 1
            v = vfree[cnt[_V_NFREE]]
        else:
            v = cnt[_V_HW]
            cnt[_V_HW] += 1
        qi = cand[q, 0]
        qj = cand[q, 1]
        qk = cand[q, 2]
        vmap[qbrick[q], voxel_offset(qi, qj, qk)] = v
        vijk[v, 0] = qi
        vijk[v, 1] = qj
        vijk[v, 2] = qk
        pos[v, 0] = origin[0] + spacing * qi
        pos[v, 1] = origin[1] + spacing * qj
        pos[v, 2] = origin[2] + spacing * qk
        vhead[v] = -1
        ohead[v] = -1
        valive[v] = 1
        cnt[_V_ALIVE] += 1
        stats[_S_V_ADD] += 1


@njit(cache=True, nogil=True)
def _add_triangles(cells, cbrick, newk, nnew, nc, nbr, vmap, vhead, tri, tnext, ttid,
                   tfree, cnt, stats, ohead, onext):
    for c in range(nc):
        b = cbrick[c]
        ci = cells[c, 0]
        cj = cells[c, 1]
        ck = cells[c, 2]
        for x in range(nnew[c]):
            key = newk[c, x]
            if key < 0:
                continue                     # already there
            if cnt[_T_NFREE] > 0:
                cnt[_T_NFREE] -= 1
                t = tfree[cnt[_T_NFREE]]
            else:
                t = cnt[_T_HW]
                cnt[_T_HW] += 1
            tid = key >> 1
            for s in range(3):
                cs = s
                if key & 1 and s > 0:
                    cs = 3 - s
                cn = TRIPLE_CORNERS[tid, cs]
                v = _vmap_near(vmap, nbr, b, ci, cj, ck, ci + (cn >> 2),
                               cj + ((cn >> 1) & 1), ck + (cn & 1))
                if v < 0:
                    stats[_S_ERR] += 1
                    v = 0
                tri[t, s] = v
            ttid[t] = key
            for s in range(3):
                v = tri[t, s]
                tnext[t, s] = vhead[v]
                vhead[v] = t
            v = tri[t, 0]
            onext[t] = ohead[v]
            ohead[v] = t
            cnt[_T_ALIVE] += 1
            stats[_S_T_ADD] += 1


@njit(cache=True, nogil=True)
def _update_kernel(keys, vals, density, nbr, origin, spacing,
                   removed, touched, win_per_input,
                   vmap, pos, vijk, valive, vhead, vfree,
                   tri, tnext, ttid, tfree, cnt, stats, ohead, onext):
    """Re-tessellate around ``removed`` (normals and colours are the shading's).

    A read-only plan (owner cells whose triangles may change, with their old
    and new triangles; vertices to create or drop) is followed, if the
    vertex and triangle arrays have room, by the edit. Without room it sets
    ``stats[_S_STATUS] = 1`` and the number of extra slots needed, and
    changes nothing. Only *sources*, removed voxels that are empty now,
    change the topology.
    """
    for s in range(stats.shape[0]):
        stats[s] = 0
    nr = removed.shape[0]
    ntch = touched.shape[0]
    n_in = nr + ntch
    if n_in == 0:
        return
    n_aff = AFFECTED_CELL_OFFSETS.shape[0]

    # ---- dedup structure: a dense window of flags, or hash sets -----------
    wlo = np.empty(3, dtype=np.int64)
    whi = np.empty(3, dtype=np.int64)
    for a in range(3):
        lo = removed[0, a] if nr > 0 else touched[0, a]
        hi = lo
        for r in range(nr):
            lo = min(lo, removed[r, a])
            hi = max(hi, removed[r, a])
        for r in range(ntch):
            lo = min(lo, touched[r, a])
            hi = max(hi, touched[r, a])
        wlo[a] = lo - _WINDOW_MARGIN
        whi[a] = hi + _WINDOW_MARGIN
    wd = whi - wlo + 1
    vol = wd[0] * wd[1] * wd[2]
    use_win = win_per_input > 0 and vol <= max(32768, win_per_input * n_in)
    blo = wlo >> BRICK_SHIFT
    bd = (whi >> BRICK_SHIFT) - blo + 1
    if use_win:
        flags = np.zeros(vol, dtype=np.uint8)
        wbr = _window_bricks(keys, vals, blo, bd)
        hc = np.empty(1, dtype=np.int64)
        hv = np.empty(1, dtype=np.int64)
    else:
        flags = np.empty(1, dtype=np.uint8)
        wbr = np.empty(1, dtype=np.int32)
        hc = _hset_new(nr * n_aff)
        hv = _hset_new(27 * n_in)

    # ---- plan ----------------------------------------------------------------
    rbrick = np.empty(nr, dtype=np.int32)
    _items_bricks(use_win, wbr, blo, bd, keys, vals, removed, nr, rbrick)
    cells = np.empty((nr * n_aff, 3), dtype=np.int32)
    cand = np.empty((27 * n_in, 3), dtype=np.int32)
    nc, ncand, n_topo = _collect(removed, touched, rbrick, density, use_win, flags,
                                 wlo, wd, hc, hv, cells, cand)
    stats[_S_CELLS] = nc
    cbrick = np.empty(nc, dtype=np.int32)
    _items_bricks(use_win, wbr, blo, bd, keys, vals, cells, nc, cbrick)
    qbrick = np.empty(ncand, dtype=np.int32)
    _items_bricks(use_win, wbr, blo, bd, keys, vals, cand, ncand, qbrick)
    newk = np.empty((nc, MAX_PER_CELL), dtype=np.int16)
    nnew = np.empty(nc, dtype=np.int32)
    oldk = np.empty((nc, 2 * MAX_PER_CELL), dtype=np.int16)
    oldt = np.empty((nc, 2 * MAX_PER_CELL), dtype=np.int32)
    nold = np.empty(nc, dtype=np.int32)
    n_tadd, n_tdel = _plan_cells(density, nbr, vmap, ohead, onext, ttid, cells, cbrick,
                                 nc, newk, nnew, oldk, oldt, nold, stats)
    qstat = np.empty(n_topo, dtype=np.int8)
    n_vadd, n_vdel = _plan_vertices(density, vmap, cand, qbrick, n_topo, qstat)

    # ---- room? -----------------------------------------------------------------
    v_room = cnt[_V_NFREE] + (vijk.shape[0] - cnt[_V_HW]) + n_vdel
    t_room = cnt[_T_NFREE] + (tri.shape[0] - cnt[_T_HW]) + n_tdel
    if n_vadd > v_room or n_tadd > t_room:
        stats[_S_STATUS] = 1
        stats[_S_NEED_V] = max(0, n_vadd - v_room)
        stats[_S_NEED_T] = max(0, n_tadd - t_room)
        return

    # ---- edit: drop triangles, drop/create vertices, add triangles, shade ----
    _drop_triangles(oldt, oldk, nold, nc, vhead, tri, tnext, ttid, tfree, cnt, stats,
                    ohead, onext)
    _edit_vertices(cand, qbrick, qstat, n_topo, origin, spacing, vmap, pos, vijk, valive,
                   vhead, ohead, vfree, cnt, stats)
    _add_triangles(cells, cbrick, newk, nnew, nc, nbr, vmap, vhead, tri, tnext, ttid,
                   tfree, cnt, stats, ohead, onext)


# ----------------------------------------------------------------------------
# Incremental update, window path
# ----------------------------------------------------------------------------
# When the inputs of an update fit a small box (the usual case: a burr's
# worth of voxels), the update works on dense copies of that box instead of
# looking voxels up one by one:
#
# * the window is the inputs' bounding box plus _FAST_MARGIN voxels (every
#   voxel an update reads lies within 2 voxels of an input);
# * sets of voxels / cells are bit rows: one uint64 per (x, y) row of the
#   window, bit z for voxel (or cell minimum corner) z along k. Rows are
#   stored with two guard rows / columns on each side (row index
#   ``(x + 2) * (wd1 + 4) + y + 2``), so neighbouring rows can be read
#   without bounds checks. The sets the update needs (cells to re-evaluate,
#   voxels that may join or leave the surface, voxels to re-shade, voxels
#   to read) are dilations of the set of inputs, a few shifts and ORs per
#   row, and they are visited in (i, j, k) order;
# * the densities and the voxel -> vertex map of the voxels it reads are
#   gathered once into local arrays laid out like the rows (voxel
#   ``row * wd2 + z``), with the occupancy as bit rows, so a cell's code is
#   a handful of shifts.
#
# Cells to re-evaluate: the 8 cells containing a source (their code may have
# changed) and the 12 cells whose minimum face has a source just below it
# (their ownership test reads it). A cell's owned triangles depend on
# nothing else, so no other cell can gain or lose one. Sources are the
# removed voxels that are empty now (those outside any brick included:
# re-evaluating a cell is harmless).
#
# Scratch memory lives in the Surface and grows on demand (status 2).

#: Margin [voxels] of the window around the inputs.
_FAST_MARGIN = 2
#: Guard rows / columns around the window's bit rows.
_GUARD = 2
#: Voxel coordinates must have a magnitude below this (packed keys, margins).
_COORD_LIMIT = (1 << 20) - 2 * BRICK
#: The window path is taken when the window holds at most
#: ``FAST_MIN_VOXELS + FAST_VOXELS_PER_INPUT * n_inputs`` voxels and is at
#: most 64 voxels deep along k.
FAST_MIN_VOXELS = 32768
FAST_VOXELS_PER_INPUT = 64
# bit-row sets (_R_T0.. are temporaries of the dilations)
(_R_REM, _R_SEED, _R_SRC, _R_AFF, _R_CELL, _R_TOPO, _R_OCC, _R_HASV, _R_NEED,
 _R_DIRTY, _R_LIST, _R_T0, _R_T1, _R_T2, _R_T3, _R_T4) = range(16)
_N_ROWSETS = 16
# per-slot bit masks of the qualifying triples lying in the minimum face along a
_QUAL_FMASK = np.zeros((256, 3), dtype=np.uint8)
for _code in range(256):
    for _s in range(int(QUAL_N[_code])):
        _f = int(TRIPLE_FACE[int(QUAL_KEY[_code, _s]) >> 1])
        if 0 <= _f < 3:
            _QUAL_FMASK[_code, _f] |= 1 << _s
_QUAL_ALL = np.array([(1 << int(n)) - 1 for n in QUAL_N], dtype=np.uint8)
_POP4 = np.array([bin(m).count("1") for m in range(16)], dtype=np.int32)
# _KEY_SLOT[code, key]: slot s with QUAL_KEY[code, s] == key, or -1
_KEY_SLOT = np.full((256, 2 * N_TRIPLES), -1, dtype=np.int8)
for _code in range(256):
    for _s in range(int(QUAL_N[_code])):
        _KEY_SLOT[_code, int(QUAL_KEY[_code, _s])] = _s


@njit(cache=True, nogil=True)
def _fw_mark(removed, touched, wlo, w1, rows, nr_p):
    """REM (removed) and SEED (all inputs) bit rows."""
    rem0 = _R_REM * nr_p
    seed0 = _R_SEED * nr_p
    for r in range(2 * nr_p):
        rows[rem0 + r] = np.uint64(0)       # REM and SEED are adjacent
    nr = removed.shape[0]
    for q in range(nr):
        row = (removed[q, 0] - wlo[0] + _GUARD) * w1 + (removed[q, 1] - wlo[1] + _GUARD)
        bit = np.uint64(1) << np.uint64(removed[q, 2] - wlo[2])
        rows[rem0 + row] |= bit
        rows[seed0 + row] |= bit
    for q in range(touched.shape[0]):
        row = (touched[q, 0] - wlo[0] + _GUARD) * w1 + (touched[q, 1] - wlo[1] + _GUARD)
        rows[seed0 + row] |= np.uint64(1) << np.uint64(touched[q, 2] - wlo[2])


@njit(cache=True, nogil=True)
def _fw_need(rows, nr_p, w0, w1):
    """NEED: the voxels within 2 (along each axis) of an input."""
    one = np.uint64(1)
    two = np.uint64(2)
    E = _R_SEED * nr_p
    N = _R_NEED * nr_p
    T0 = _R_T0 * nr_p
    T1 = _R_T1 * nr_p
    for r in range(nr_p):
        e = rows[E + r]
        rows[T0 + r] = e | (e >> one) | (e >> two) | (e << one) | (e << two)
    for x in range(w0):
        for r in range(x * w1 + 2, x * w1 + w1 - 2):
            rows[T1 + r] = (rows[T0 + r - 2] | rows[T0 + r - 1] | rows[T0 + r]
                            | rows[T0 + r + 1] | rows[T0 + r + 2])
    for x in range(2, w0 - 2):
        for r in range(x * w1 + 2, x * w1 + w1 - 2):
            rows[N + r] = (rows[T1 + r - 2 * w1] | rows[T1 + r - w1] | rows[T1 + r]
                           | rows[T1 + r + w1] | rows[T1 + r + 2 * w1])


@njit(cache=True, nogil=True)
def _fw_dilate(rows, nr_p, w0, w1):
    """SRC = REM minus OCC; from it: AFF (cells to re-evaluate), CELL (cells
    containing a source) and TOPO (3x3x3 of the sources). See the comment
    above."""
    one = np.uint64(1)
    M = _R_REM * nr_p
    O = _R_OCC * nr_p
    S = _R_SRC * nr_p
    A = _R_AFF * nr_p
    C = _R_CELL * nr_p
    T = _R_TOPO * nr_p
    K1 = _R_T0 * nr_p           # cells along k containing a source: k in {p - 1, p}
    K3S = _R_T1 * nr_p          # sources dilated by 1 along k
    CJ = _R_T2 * nr_p           # K1 dilated to cells along j
    J3S = _R_T3 * nr_p          # K3S dilated by 1 along j
    SJ = _R_T4 * nr_p           # sources dilated to cells along j
    for r in range(nr_p):
        s = rows[M + r] & ~rows[O + r]      # (OCC is stale where REM is 0)
        rows[S + r] = s
        rows[K1 + r] = s | (s >> one)
        rows[K3S + r] = s | (s >> one) | (s << one)
    for x in range(w0):
        for r in range(x * w1 + 2, x * w1 + w1 - 2):
            rows[CJ + r] = rows[K1 + r] | rows[K1 + r + 1]
            rows[J3S + r] = rows[K3S + r - 1] | rows[K3S + r] | rows[K3S + r + 1]
            rows[SJ + r] = rows[S + r] | rows[S + r + 1]
    for x in range(2, w0 - 2):
        for r in range(x * w1 + 2, x * w1 + w1 - 2):
            c = rows[CJ + r] | rows[CJ + r + w1]
            rows[C + r] = c
            rows[A + r] = (c | rows[CJ + r - w1]                        # + face along i
                           | rows[K1 + r - 1] | rows[K1 + r + w1 - 1]   # + face along j
                           | ((rows[SJ + r] | rows[SJ + r + w1]) << one))  # along k
            rows[T + r] = rows[J3S + r - w1] | rows[J3S + r] | rows[J3S + r + w1]


@njit(cache=True, nogil=True)
def _fw_gather(density, vmap, wbr, wlo, wd, blo, bd, ld, lv, rows, nr_p):
    """Densities and vertex slots of the voxels in NEED (elsewhere ``ld``
    and ``lv`` are left stale), occupancy and has-vertex bit rows of the
    window."""
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    occ0 = _R_OCC * nr_p
    hv0 = _R_HASV * nr_p
    need0 = _R_NEED * nr_p
    for x in range(wd0):
        i = wlo[0] + x
        for y in range(wd1):
            j = wlo[1] + y
            r = (x + _GUARD) * w1 + y + _GUARD
            need = rows[need0 + r]
            if need == 0:
                rows[occ0 + r] = np.uint64(0)
                rows[hv0 + r] = np.uint64(0)
                continue
            zlo = np.int64(trailing_zeros(need))
            zhi = 64 - np.int64(leading_zeros(need))
            bbase = (((i >> BRICK_SHIFT) - blo[0]) * bd[1] + ((j >> BRICK_SHIFT) - blo[1])) * bd[2]
            ob = ((i & BRICK_MASK) << 6) | ((j & BRICK_MASK) << 3)
            li = r * wd2
            occ = np.uint64(0)
            hv = np.uint64(0)
            z = zlo
            while z < zhi:
                k = wlo[2] + z
                n = min(zhi - z, BRICK - (k & BRICK_MASK))
                b = wbr[bbase + (k >> BRICK_SHIFT) - blo[2]]
                if b >= 0:
                    ub = np.uint64(b)
                    o = np.uint64(ob | (k & BRICK_MASK))
                    lz = np.uint64(li + z)
                    for u in range(n):
                        uu = np.uint64(u)
                        d = density[ub, o + uu]
                        vv = vmap[ub, o + uu]
                        ld[lz + uu] = d
                        lv[lz + uu] = vv
                        occ |= np.uint64(d > 0) << np.uint64(z + u)
                        hv |= np.uint64(vv >= 0) << np.uint64(z + u)
                else:
                    for u in range(n):
                        ld[li + z + u] = np.float32(0.0)
                        lv[li + z + u] = -1
                z += n
            rows[occ0 + r] = occ
            rows[hv0 + r] = hv


@njit(cache=True, nogil=True)
def _fw_plan(rows, nr_p, wd, lcode, lact, clist, stats):
    """Code and active slots of every cell to re-evaluate; list the cells that
    own or may own a triangle (LIST bits, ``clist``). Returns ``(n_listed,
    bound on triangles to add, vertices to add, vertices to drop)``."""
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    one = np.uint64(1)
    three = np.uint64(3)
    A = _R_AFF * nr_p
    C = _R_CELL * nr_p
    O = _R_OCC * nr_p
    H = _R_HASV * nr_p
    T = _R_TOPO * nr_p
    L = _R_LIST * nr_p
    for r in range(nr_p):
        rows[L + r] = np.uint64(0)
    nl = 0
    tbound = 0
    ncells = 0
    nvadd = 0
    nvdel = 0
    # unsigned indices below: no negative-index fix-ups
    uw1 = np.uint64(w1)
    uwd2 = np.uint64(wd2)
    for x in range(wd0):
        for r in range((x + _GUARD) * w1 + _GUARD, (x + _GUARD) * w1 + _GUARD + wd1):
            ur = np.uint64(r)
            uO = np.uint64(O) + ur
            uH = np.uint64(H) + ur
            # vertices to create / drop
            tb = rows[np.uint64(T) + ur]
            if tb != 0:
                occ = rows[uO]
                hv = rows[uH]
                add = tb & occ & ~hv
                dele = tb & ~occ & hv
                while add != 0:
                    add &= add - one
                    nvadd += 1
                while dele != 0:
                    dele &= dele - one
                    nvdel += 1
            bits = rows[np.uint64(A) + ur]
            if bits == 0:
                continue
            lbits = np.uint64(0)
            cbits = rows[np.uint64(C) + ur]
            o00 = rows[uO]
            o01 = rows[uO + one]
            o10 = rows[uO + uw1]
            o11 = rows[uO + uw1 + one]
            ox = rows[uO - uw1] | rows[uO - uw1 + one]          # x - 1 plane
            oy = rows[uO - one] | rows[uO + uw1 - one]          # y - 1 plane
            oz = o00 | o01 | o10 | o11
            hv = rows[uH] | rows[uH + one] | rows[uH + uw1]
            # cells with all corners empty or all occupied own no triangle:
            # unless a corner 0..5 has a vertex (old triangles), skip them
            oa = o00 & o01 & o10 & o11
            mixed = (oz | (oz >> one)) & ~(oa & (oa >> one))
            bits &= mixed | hv | (hv >> one)
            while bits != 0:
                z = trailing_zeros(bits)
                bits &= bits - one
                ncells += 1
                zz = np.uint64(z)
                code = (((o00 >> zz) & three) | (((o01 >> zz) & three) << np.uint64(2))
                        | (((o10 >> zz) & three) << np.uint64(4))
                        | (((o11 >> zz) & three) << np.uint64(6)))
                act = np.int64(_QUAL_ALL[code])
                lowm = np.int64(0)      # slots dropped by the ownership test
                if act != 0:
                    if (ox >> zz) & three == 0:
                        lowm |= np.int64(_QUAL_FMASK[code, 0])
                    if (oy >> zz) & three == 0:
                        lowm |= np.int64(_QUAL_FMASK[code, 1])
                    if (oz >> (zz - one)) & one == 0:
                        lowm |= np.int64(_QUAL_FMASK[code, 2])
                    act &= ~lowm
                if (cbits >> zz) & one == 0 and lowm == 0:
                    # no source in the cell: same code as before the batch;
                    # its ownership tests read voxels that were occupied
                    # before if they are now, so if all of them pass now
                    # they passed before: nothing changed
                    continue
                if act == 0 and (hv >> zz) & three == 0:
                    continue            # owns nothing and will own nothing
                li = ur * uwd2 + z
                lcode[li] = code
                lact[li] = act
                clist[nl] = li
                nl += 1
                tbound += _POP4[act]
                lbits |= one << zz
            rows[np.uint64(L) + ur] = lbits
    stats[_S_CELLS] = ncells
    return nl, tbound, nvadd, nvdel


@njit(cache=True, nogil=True)
def _fw_cells(clist, nl, wd, ld, lv, lcode, lact, rows, nr_p, trec, vrec, tfree, cnt, stats):
    """Drop the triangles the listed cells own but should not own.

    Every triangle a listed cell owns is on the owner list of the vertex at
    its corner ``c0``; each such list is walked once (vertices in (i, j, k)
    order). A dropped triangle leaves its owner list, its slot is freed and
    its key set to -1; it stays on the vertex lists of its corners, which
    are marked DIRTY (see :func:`_fw_unlink_dead`). ``lact`` holds the
    active slots of a listed cell in bits 0-3 and collects the slots it
    still owns in bits 4-7; on return it holds the slots to add, and the
    list is compacted to the cells with something to add.
    Returns ``(new list length, dead list entries)``."""
    one = np.uint64(1)
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    sx = w1 * wd2
    D = _R_DIRTY * nr_p
    L = _R_LIST * nr_p
    H = _R_HASV * nr_p
    for r in range(nr_p):
        rows[D + r] = np.uint64(0)
    n_dead = 0
    # unsigned indices below (all in range): no negative-index fix-ups
    uw1 = np.uint64(w1)
    uwd2 = np.uint64(wd2)
    usx = np.uint64(sx)
    uL = np.uint64(L)
    for x in range(wd0):
        for r in range((x + _GUARD) * w1 + _GUARD, (x + _GUARD) * w1 + _GUARD + wd1):
            ur = np.uint64(r)
            # vertices at corner 0..5 of a listed cell
            lw = rows[uL + ur] | rows[uL + ur - one] | rows[uL + ur - uw1]
            vw = (lw | (lw << one)) & rows[np.uint64(H) + ur]
            while vw != 0:
                z = trailing_zeros(vw)
                vw &= vw - one
                v = np.uint64(lv[ur * uwd2 + z])
                prev = -1
                t = vrec[v, _VR_OHEAD]
                while t >= 0:
                    ut = np.uint64(t)
                    nxt = trec[ut, _TR_ONEXT]
                    key = np.uint64(trec[ut, _TR_KEY])
                    c0 = np.uint64(TRIPLE_CORNERS[key >> one, 0])
                    urc = ur - (c0 >> np.uint64(2)) * uw1 - ((c0 >> one) & one)
                    zc = z - (c0 & one)
                    if (rows[uL + urc] >> zc) & one == 0:
                        prev = t                # owner not listed: unchanged
                        t = nxt
                        continue
                    li = urc * uwd2 + zc
                    ah = np.int64(lact[li])
                    slot = _KEY_SLOT[lcode[li], key]
                    if slot >= 0 and (ah >> slot) & 1 and not (ah >> (slot + 4)) & 1:
                        lact[li] = ah | (np.int64(16) << slot)
                        prev = t
                        t = nxt
                        continue
                    # drop t: off the owner list (we hold its predecessor); the
                    # vertex lists of its surviving corners are cleaned later
                    # (an emptied corner's vertex goes with all its triangles:
                    # its list is dropped whole in _fw_vertices)
                    if prev < 0:
                        vrec[v, _VR_OHEAD] = nxt
                    else:
                        trec[prev, _TR_ONEXT] = nxt
                    tid = key >> one
                    for s in range(3):
                        c = np.uint64(TRIPLE_CORNERS[tid, s])
                        ca = c >> np.uint64(2)
                        cb = (c >> one) & one
                        cc = c & one
                        if not ld[li + ca * usx + cb * uwd2 + cc] > 0:
                            continue
                        rows[np.uint64(D) + urc + ca * uw1 + cb] |= one << (zc + cc)
                        n_dead += 1
                    trec[t, _TR_KEY] = -1
                    tfree[cnt[_T_NFREE]] = t
                    cnt[_T_NFREE] += 1
                    cnt[_T_ALIVE] -= 1
                    stats[_S_T_DEL] += 1
                    t = nxt
    na = 0
    for q in range(nl):
        li = clist[q]
        ah = np.int64(lact[li])
        rest = ah & ~(ah >> 4) & 15
        if rest != 0:
            lact[li] = rest
            clist[na] = li
            na += 1
    return na, n_dead


@njit(cache=True, nogil=True)
def _fw_unlink_dead(rows, nr_p, wd, lv, trec, vrec):
    """Splice the dead triangles (key -1) out of the vertex lists of the
    DIRTY voxels, one walk per list. Returns the number of entries removed."""
    one = np.uint64(1)
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    D = _R_DIRTY * nr_p
    n = 0
    for x in range(wd0):
        for r in range((x + _GUARD) * w1 + _GUARD, (x + _GUARD) * w1 + _GUARD + wd1):
            bits = rows[D + r]
            while bits != 0:
                z = trailing_zeros(bits)
                bits &= bits - one
                v = lv[r * wd2 + z]
                prev = -1
                prev_s = 0
                cur = vrec[v, _VR_HEAD]
                while cur >= 0:
                    s = 0 if trec[cur, 0] == v else (1 if trec[cur, 1] == v else 2)
                    nxt = trec[cur, _TR_NEXT + s]
                    if trec[cur, _TR_KEY] < 0:
                        if prev < 0:
                            vrec[v, _VR_HEAD] = nxt
                        else:
                            trec[prev, _TR_NEXT + prev_s] = nxt
                        n += 1
                    else:
                        prev = cur
                        prev_s = s
                    cur = nxt
    return n


@njit(cache=True, nogil=True)
def _fw_vertices(rows, nr_p, wd, wlo, wbr, blo, bd, lv, origin, spacing, vmap, pos, vijk,
                 valive, vrec, vfree, cnt, stats):
    """Drop the vertices of emptied voxels, then create those of new surface
    voxels (which so reuse the slots just freed, whose lines are in cache);
    HASV becomes the set of voxels with a vertex after the edit."""
    one = np.uint64(1)
    wd0 = wd[0]
    wd1 = wd[1]
    wd2 = wd[2]
    w1 = wd1 + 2 * _GUARD
    T = _R_TOPO * nr_p
    O = _R_OCC * nr_p
    H = _R_HASV * nr_p
    for create in range(2):
        for x in range(wd0):
            i = wlo[0] + x
            for y in range(wd1):
                r = (x + _GUARD) * w1 + y + _GUARD
                occ = rows[O + r]
                hv = rows[H + r]
                if create:
                    chg = rows[T + r] & occ & ~hv
                else:
                    chg = rows[T + r] & ~occ & hv
                if chg == 0:
                    continue
                rows[H + r] = hv ^ chg
                j = wlo[1] + y
                bbase = (((i >> BRICK_SHIFT) - blo[0]) * bd[1]
                         + ((j >> BRICK_SHIFT) - blo[1])) * bd[2]
                while chg != 0:
                    z = trailing_zeros(chg)
                    chg &= chg - one
                    k = wlo[2] + z
                    b = wbr[bbase + (k >> BRICK_SHIFT) - blo[2]]
                    o = voxel_offset(i, j, k)
                    li = r * wd2 + z
                    if create:                              # became surface
                        if cnt[_V_NFREE] > 0:
                            cnt[_V_NFREE] -= 1
                            v = vfree[cnt[_V_NFREE]]
                        else:
                            v = cnt[_V_HW]
                            cnt[_V_HW] += 1
                        vmap[b, o] = v
                        lv[li] = v
                        vijk[v, 0] = i
                        vijk[v, 1] = j
                        vijk[v, 2] = k
                        pos[v, 0] = origin[0] + spacing * i
                        pos[v, 1] = origin[1] + spacing * j
                        pos[v, 2] = origin[2] + spacing * k
                        vrec[v, _VR_HEAD] = -1
                        vrec[v, _VR_OHEAD] = -1
                        valive[v] = 1
                        cnt[_V_ALIVE] += 1
                        stats[_S_V_ADD] += 1
                    else:                                   # emptied
                        v = lv[li]
                        if vrec[v, _VR_OHEAD] >= 0:
                            stats[_S_ERR] += 1
                        vrec[v, _VR_HEAD] = -1              # its triangles are all gone
                        vmap[b, o] = -1
                        lv[li] = -1
                        valive[v] = 0
                        vfree[cnt[_V_NFREE]] = v
                        cnt[_V_NFREE] += 1
                        cnt[_V_ALIVE] -= 1
                        stats[_S_V_DEL] += 1


@njit(cache=True, nogil=True)
def _fw_add(clist, na, wd, lv, lcode, lact, trec, vrec, tfree, cnt, stats):
    sy = wd[2]
    sx = (wd[1] + 2 * _GUARD) * wd[2]
    for q in range(na):
        li = clist[q]
        code = lcode[li]
        rest = np.int64(lact[li])
        for slot in range(QUAL_N[code]):
            if not (rest >> slot) & 1:
                continue
            key = QUAL_KEY[code, slot]
            if cnt[_T_NFREE] > 0:
                cnt[_T_NFREE] -= 1
                t = tfree[cnt[_T_NFREE]]
            else:
                t = cnt[_T_HW]
                cnt[_T_HW] += 1
            tid = key >> 1
            for s in range(3):
                cs = s
                if key & 1 and s > 0:
                    cs = 3 - s
                cn = TRIPLE_CORNERS[tid, cs]
                v = lv[li + (cn >> 2) * sx + ((cn >> 1) & 1) * sy + (cn & 1)]
                if v < 0:
                    stats[_S_ERR] += 1
                    v = 0
                trec[t, s] = v
                trec[t, _TR_NEXT + s] = vrec[v, _VR_HEAD]
                vrec[v, _VR_HEAD] = t
            trec[t, _TR_KEY] = key
            v = trec[t, 0]
            trec[t, _TR_ONEXT] = vrec[v, _VR_OHEAD]
            vrec[v, _VR_OHEAD] = t
            cnt[_T_ALIVE] += 1
            stats[_S_T_ADD] += 1


@njit(cache=True, nogil=True)
def _update_window(keys, vals, density, origin, spacing,
                   removed, touched, win_per_input,
                   vmap, pos, vijk, valive, vrec, vfree,
                   trec, tfree, cnt, stats, sf32, si32, su8, su64):
    """The update on dense copies of the inputs' window (see above).

    Sets ``stats[_S_STATUS]``: 0 done, 1 vertex / triangle arrays too small
    (nothing changed), 2 scratch too small (``stats[_S_NEED_V]`` voxels,
    ``stats[_S_NEED_T]`` rows; nothing changed), 3 window unsuitable (use
    :func:`_update_kernel`; nothing changed), 4 / 5 a removed / touched voxel
    has a coordinate of magnitude ``_COORD_LIMIT`` or more (nothing changed).
    """
    for s in range(stats.shape[0]):
        stats[s] = 0
    nr = removed.shape[0]
    ntch = touched.shape[0]
    n_in = nr + ntch
    if n_in == 0:
        return
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
    if nr > 0 and (min(lo0, lo1, lo2) <= -_COORD_LIMIT or max(hi0, hi1, hi2) >= _COORD_LIMIT):
        stats[_S_STATUS] = 4
        return
    for q in range(ntch):
        lo0 = min(lo0, touched[q, 0])
        hi0 = max(hi0, touched[q, 0])
        lo1 = min(lo1, touched[q, 1])
        hi1 = max(hi1, touched[q, 1])
        lo2 = min(lo2, touched[q, 2])
        hi2 = max(hi2, touched[q, 2])
    if min(lo0, lo1, lo2) <= -_COORD_LIMIT or max(hi0, hi1, hi2) >= _COORD_LIMIT:
        stats[_S_STATUS] = 5
        return
    wlo = np.empty(3, dtype=np.int64)
    wd = np.empty(3, dtype=np.int64)
    blo = np.empty(3, dtype=np.int64)
    bd = np.empty(3, dtype=np.int64)
    wlo[0] = lo0 - _FAST_MARGIN
    wlo[1] = lo1 - _FAST_MARGIN
    wlo[2] = lo2 - _FAST_MARGIN
    wd[0] = hi0 - lo0 + 1 + 2 * _FAST_MARGIN
    wd[1] = hi1 - lo1 + 1 + 2 * _FAST_MARGIN
    wd[2] = hi2 - lo2 + 1 + 2 * _FAST_MARGIN
    for a in range(3):
        blo[a] = wlo[a] >> BRICK_SHIFT
        bd[a] = ((wlo[a] + wd[a] - 1) >> BRICK_SHIFT) - blo[a] + 1
    vol = wd[0] * wd[1] * wd[2]
    if (win_per_input <= 0 or wd[2] > 64
            or vol > FAST_MIN_VOXELS + FAST_VOXELS_PER_INPUT * n_in):
        stats[_S_STATUS] = 3
        return
    w0 = wd[0] + 2 * _GUARD
    w1 = wd[1] + 2 * _GUARD
    nr_p = w0 * w1
    vol_p = nr_p * wd[2]
    nwb = bd[0] * bd[1] * bd[2]
    if sf32.shape[0] < vol_p or si32.shape[0] < 2 * vol_p + nwb or su8.shape[0] < 2 * vol_p \
            or su64.shape[0] < _N_ROWSETS * nr_p:
        stats[_S_STATUS] = 2
        stats[_S_NEED_V] = vol_p
        stats[_S_NEED_T] = nr_p
        return
    ld = sf32
    lv = si32[:vol_p]
    clist = si32[vol_p:2 * vol_p]
    wbr = si32[2 * vol_p:2 * vol_p + nwb]
    lcode = su8[:vol_p]
    lact = su8[vol_p:2 * vol_p]
    s = 0
    for bi in range(blo[0], blo[0] + bd[0]):
        for bj in range(blo[1], blo[1] + bd[1]):
            for bk in range(blo[2], blo[2] + bd[2]):
                wbr[s] = find_brick(keys, vals, bi, bj, bk)
                s += 1

    # ---- plan (read-only) ----------------------------------------------------
    _fw_mark(removed, touched, wlo, w1, su64, nr_p)
    _fw_need(su64, nr_p, w0, w1)
    _fw_gather(density, vmap, wbr, wlo, wd, blo, bd, ld, lv, su64, nr_p)
    _fw_dilate(su64, nr_p, w0, w1)
    nl, tbound, n_vadd, n_vdel = _fw_plan(su64, nr_p, wd, lcode, lact, clist, stats)

    # ---- room? (triangles: bound, ignoring the ones that will be freed) ------
    v_room = cnt[_V_NFREE] + (vijk.shape[0] - cnt[_V_HW]) + n_vdel
    t_room = cnt[_T_NFREE] + (trec.shape[0] - cnt[_T_HW])
    if n_vadd > v_room or tbound > t_room:
        stats[_S_STATUS] = 1
        stats[_S_NEED_V] = max(0, n_vadd - v_room)
        stats[_S_NEED_T] = max(0, tbound - t_room)
        return

    # ---- edit ------------------------------------------------------------------
    na, n_dead = _fw_cells(clist, nl, wd, ld, lv, lcode, lact, su64, nr_p, trec, vrec, tfree,
                           cnt, stats)
    if _fw_unlink_dead(su64, nr_p, wd, lv, trec, vrec) != n_dead:
        stats[_S_ERR] += 1
    _fw_vertices(su64, nr_p, wd, wlo, wbr, blo, bd, lv, origin, spacing, vmap, pos, vijk,
                 valive, vrec, vfree, cnt, stats)
    _fw_add(clist, na, wd, lv, lcode, lact, trec, vrec, tfree, cnt, stats)


# ----------------------------------------------------------------------------
# Python front end
# ----------------------------------------------------------------------------


_NO_VOXELS = np.zeros((0, 3), dtype=np.int32)    # kernels never write their inputs


def _as_ijk(a, name):
    """Validate an (n, 3) array of integer voxel coordinates -> int32 C array.

    int32 (n, 3) arrays take a short path: copied as they are, their range
    is checked by :func:`_update_window` (status 4 / 5)."""
    if a is None:
        return _NO_VOXELS
    if type(a) is np.ndarray and a.dtype == np.int32 and a.ndim == 2 and a.shape[1] == 3:
        return a.copy(order="C")
    arr = np.asarray(a)
    if arr.size == 0:
        return np.zeros((0, 3), dtype=np.int32)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise TypeError(f"{name} must hold integer voxel coordinates, got {arr.dtype}")
    if np.abs(arr).max() >= _COORD_LIMIT:
        raise ValueError(f"{name} has voxel coordinates beyond +-{_COORD_LIMIT}")
    # always a fresh, writable C array: read-only or strided inputs would
    # make numba compile another specialisation of every kernel
    return np.array(arr, dtype=np.int32, order="C", copy=True)


def _as_colors(colors):
    c = np.asarray(colors)
    if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] < 1:
        raise ValueError(f"colors must have shape (n_labels + 1, 3), got {c.shape}")
    if not np.issubdtype(c.dtype, np.integer) or c.min() < 0 or c.max() > 255:
        raise ValueError("colors must be integers in [0, 255]")
    return np.array(c, dtype=np.uint8, order="C", copy=True)


def _initial_capacity(n):
    return int(max(64, n + n // 4))


def _grown(arr, cap, fill):
    out = np.full((cap,) + arr.shape[1:], fill, dtype=arr.dtype)
    out[:arr.shape[0]] = arr
    return out


@dataclass(eq=False)
class CanonicalSurface:
    """Order-independent form of a :class:`Surface`, for equality tests.

    Attributes
    ----------
    ijk : (n, 3) int32
        Vertex voxels, sorted lexicographically.
    pos, nrm : (n, 3) float32
        Position [mm] and unit normal of each vertex, in ``ijk`` order.
    col : (n, 4) uint8
        RGBA colour of each vertex.
    tris : (m, 9) int32
        Oriented triangles as the voxel coordinates of their three corners in
        winding order, rotated so the lexicographically smallest corner comes
        first; rows sorted lexicographically.
    """

    ijk: np.ndarray
    pos: np.ndarray
    nrm: np.ndarray
    col: np.ndarray
    tris: np.ndarray

    def differences(self, other, atol=0.0):
        """Human-readable list of what differs from ``other`` (empty if equal).

        ``atol`` is the tolerance on normals (positions and colours are exact).
        """
        out = []
        if not np.array_equal(self.ijk, other.ijk):
            a = {tuple(r) for r in self.ijk.tolist()}
            b = {tuple(r) for r in other.ijk.tolist()}
            out.append(f"vertices differ: only here {sorted(a - b)[:5]}, "
                       f"only there {sorted(b - a)[:5]}")
            return out
        if not np.array_equal(self.pos, other.pos):
            out.append("positions differ")
        if atol == 0:
            bad = np.flatnonzero((self.nrm != other.nrm).any(axis=1))
        else:
            bad = np.flatnonzero((np.abs(self.nrm - other.nrm) > atol).any(axis=1))
        if bad.size:
            out.append(f"normals differ at {self.ijk[bad[:5]].tolist()}")
        bad = np.flatnonzero((self.col != other.col).any(axis=1))
        if bad.size:
            out.append(f"colours differ at {self.ijk[bad[:5]].tolist()}")
        if not np.array_equal(self.tris, other.tris):
            a = {tuple(r) for r in self.tris.tolist()}
            b = {tuple(r) for r in other.tris.tolist()}
            out.append(f"triangles differ: {len(self.tris)} vs {len(other.tris)}; "
                       f"only here {sorted(a - b)[:3]}, only there {sorted(b - a)[:3]}")
        return out

    def __eq__(self, other):
        if not isinstance(other, CanonicalSurface):
            return NotImplemented
        return not self.differences(other)


class Surface:
    """Triangle surface of a :class:`~bonesim.grid.Grid` with one vertex per
    surface voxel, kept up to date as voxels are removed.

    Build one with :meth:`build`; then call :meth:`update` after each batch
    of removed voxels. See the module docstring for the definitions.

    Vertex and triangle data live in arrays with spare capacity; a slot is
    in use when ``alive[v]`` (vertices) / ``tri_key[t] >= 0`` (triangles);
    free slots hold stale data. Freed slots are reused, and when an update
    needs more room the arrays are replaced by larger copies (amortised
    doubling), so re-read the attributes after :meth:`update` rather than
    keeping references. Use :meth:`arrays` for compact copies. A surface is
    not safe to update from two threads at once, nor to read while updating.

    Attributes
    ----------
    pos : (vcap, 3) float32
        Vertex positions [mm] (voxel centres, case frame).
    nrm : (vcap, 3) float32
        Unit vertex normals (pointing out of the bone).
    col : (vcap, 4) uint8
        Vertex RGBA colours.
    ijk : (vcap, 3) int32
        Voxel of each vertex.
    alive : (vcap,) uint8
        1 for slots holding a vertex.
    tri : (tcap, 3) int32
        Vertex slots of each triangle, counter-clockwise seen from outside
        (a view of the packed triangle records, like ``tri_key``, ``tnext``
        and ``vhead``: not C-contiguous).
    tri_key : (tcap,) int32
        ``2 * triple_id + flip`` for live triangles (``-1`` for free slots);
        with the owner cell (``ijk[tri[t, 0]] - CORNER_OFFSETS[TRIPLE_CORNERS[
        key >> 1, 0]]``) it is the triangle's identity.
    vmap : (n_bricks, 512) int32
        Vertex slot of each grid voxel (same layout as ``grid.density``), -1
        for none.
    vhead : (vcap,) int32, tnext : (tcap, 3) int32
        Vertex -> triangle lists (see module docstring); use
        :meth:`triangles_of`.
    colors : (n_labels + 1, 3) uint8
        The structure colour table given to :meth:`build`.
    shader : bonesim.shading.Shader
        Computes the normals and colours (its ``bone`` mask, ``tint_on`` and
        ``params`` say how).
    """

    def __init__(self, keys, vals, colors, nbr, vmap, pos, nrm, col, ijk, alive, vrec, vfree,
                 trec, tfree, cnt, origin_mm, spacing_mm, shader):
        self._keys = keys
        self._vals = vals
        self.colors = colors
        self._nbr = nbr
        self.vmap = vmap
        self.pos = pos
        self.nrm = nrm
        self.col = col
        self.ijk = ijk
        self.alive = alive
        self._vrec = vrec
        self._vfree = vfree
        self._trec = trec
        self._tfree = tfree
        self._cnt = cnt
        self._origin = np.asarray(origin_mm, dtype=np.float64)
        self._spacing = float(spacing_mm)
        self._record_views()
        self._win_per_input = WINDOW_VOXELS_PER_INPUT   # tests set 0 to force hash sets
        self._stats = np.zeros(_N_STATS, dtype=np.int64)
        self._grow_scratch(4096, 256)
        self.shader = shader

    # ------------------------------------------------------------------ build
    @classmethod
    def build(cls, grid: Grid, colors, *, bone=None,
              shading: ShadingParams | None = None) -> "Surface":
        """Tessellate and shade ``grid`` from scratch.

        Parameters
        ----------
        grid : Grid
            The bone; its ``density``/``label`` arrays are read, not kept.
        colors : (n_labels + 1, 3) uint8 array_like
            Display RGB of each structure index (row 0 for label 0); must
            cover every label present in the grid.
        bone : (n_labels + 1,) bool or 0/1 array_like, optional
            Which labels are bone (:func:`bonesim.shading.bone_labels` of the
            model's structures); thin bone over the other structures takes
            on their colour. None (default): no tint.
        shading : ShadingParams, optional
            Normal smoothing and tint thresholds; default: the shipped
            ``bonesim/data/shading.toml``.

        Returns
        -------
        Surface
        """
        if not isinstance(grid, Grid):
            raise TypeError(f"grid must be a bonesim.grid.Grid, got {type(grid).__name__}")
        colors = _as_colors(colors)
        if grid.label.size and int(grid.label.max()) >= colors.shape[0]:
            raise ValueError(f"colors has {colors.shape[0]} rows but the grid uses "
                             f"label {int(grid.label.max())}")
        n_b = grid.n_bricks
        nbr = _brick_neighbours(grid.keys, grid.vals, grid.bricks)
        shader = Shader(grid, nbr, colors, bone, shading)
        nv = np.zeros(n_b, dtype=np.int64)
        nt = np.zeros(n_b, dtype=np.int64)
        _build_count(grid.density, nbr, nv, nt)
        voff = np.zeros(n_b + 1, dtype=np.int64)
        np.cumsum(nv, out=voff[1:])
        toff = np.zeros(n_b + 1, dtype=np.int64)
        np.cumsum(nt, out=toff[1:])
        n_v = int(voff[-1])
        n_t = int(toff[-1])
        vcap = _initial_capacity(n_v)
        tcap = _initial_capacity(n_t)
        vmap = np.empty((n_b, BRICK_VOXELS), dtype=np.int32)
        pos = np.zeros((vcap, 3), dtype=np.float32)
        nrm = np.zeros((vcap, 3), dtype=np.float32)
        col = np.zeros((vcap, 4), dtype=np.uint8)
        ijk = np.zeros((vcap, 3), dtype=np.int32)
        _build_vertices(grid.density, nbr, grid.bricks, grid.origin_mm, grid.spacing_mm, voff,
                        vmap, pos, ijk)
        trec = np.empty((tcap, _TR_WIDTH), dtype=np.int32)
        trec[:] = _TR_FILL
        err = np.zeros(max(1, (n_b + _CHUNK - 1) // _CHUNK), dtype=np.int64)
        _build_triangles(grid.density, nbr, toff, vmap, trec, err)
        if err.sum():
            raise RuntimeError("surface: a qualifying triangle has a corner without vertex")
        alive = np.zeros(vcap, dtype=np.uint8)
        alive[:n_v] = 1
        vrec = np.full((vcap, 2), -1, dtype=np.int32)
        _link_all(trec, vrec, n_t)
        cnt = np.array([n_v, 0, n_t, 0, n_v, n_t], dtype=np.int64)
        shader.shade_all(grid, vmap, nrm, col)
        return cls(grid.keys, grid.vals, colors, nbr, vmap, pos, nrm, col, ijk, alive, vrec,
                   np.zeros(vcap, dtype=np.int32), trec, np.zeros(tcap, dtype=np.int32), cnt,
                   grid.origin_mm, grid.spacing_mm, shader)

    @classmethod
    def of_model(cls, model, grid: Grid | None = None,
                 shading: ShadingParams | None = None) -> "Surface":
        """:meth:`build` with a model's colours and bone labels (structures of
        kind ``"bone"``), so thin bone shows the structures beneath.

        Parameters
        ----------
        model : bonesim.model.Model
        grid : Grid, optional
            The tissue to tessellate (a state's or a replica); default the
            model's initial grid.
        shading : ShadingParams, optional
            As for :meth:`build`.
        """
        return cls.build(model.grid if grid is None else grid, model.colors,
                         bone=bone_labels(model.structures), shading=shading)

    # ----------------------------------------------------------------- update
    def update(self, grid: Grid, removed, touched=None) -> dict:
        """Re-tessellate after voxels were removed from ``grid``.

        Work is proportional to the number of voxels given, not to the
        surface: cells around removed voxels are re-evaluated, vertices
        created for voxels that became surface and dropped for removed ones,
        and the normals and colours the changes can reach are recomputed
        (:meth:`bonesim.shading.Shader.refresh`).

        Parameters
        ----------
        grid : Grid
            The grid this surface was built from (or a copy sharing its hash
            table), in its new state.
        removed : (n, 3) int array_like
            Voxels ``(i, j, k)`` whose density was set to 0 since the last
            update. Duplicates are harmless.
        touched : (m, 3) int array_like, optional
            Voxels whose density was lowered but stayed > 0.

        Returns
        -------
        dict
            ``vertices_added``, ``vertices_removed``, ``triangles_added``,
            ``triangles_removed``, ``vertices_reshaded``, ``cells_visited``.
        """
        if not isinstance(grid, Grid):
            raise TypeError(f"grid must be a bonesim.grid.Grid, got {type(grid).__name__}")
        if grid.density.shape != self.vmap.shape or not (
                grid.keys is self._keys or np.array_equal(grid.keys, self._keys)):
            raise ValueError("update() needs the grid this surface was built from")
        removed = _as_ijk(removed, "removed")
        touched = _as_ijk(touched, "touched")
        stats = self._stats
        window = True
        while True:
            if window:
                _update_window(grid.keys, grid.vals, grid.density,
                               self._origin, self._spacing, removed, touched,
                               self._win_per_input,
                               self.vmap, self.pos, self.ijk, self.alive,
                               self._vrec, self._vfree, self._trec, self._tfree, self._cnt,
                               stats, self._sf32, self._si32, self._su8, self._su64)
            else:
                _update_kernel(grid.keys, grid.vals, grid.density, self._nbr,
                               self._origin, self._spacing, removed, touched,
                               self._win_per_input,
                               self.vmap, self.pos, self.ijk,
                               self.alive, self.vhead, self._vfree, self.tri, self.tnext,
                               self.tri_key, self._tfree, self._cnt, stats, self._ohead,
                               self._onext)
            st = stats.tolist()
            status = st[_S_STATUS]
            if status == 0:
                break
            if status == 1:
                self._grow(st[_S_NEED_V], st[_S_NEED_T])
            elif status == 2:
                self._grow_scratch(st[_S_NEED_V], st[_S_NEED_T])
            elif status == 3:
                window = False
            else:
                name = "removed" if status == 4 else "touched"
                raise ValueError(f"{name} has voxel coordinates beyond +-{_COORD_LIMIT}")
        if st[_S_ERR]:
            raise RuntimeError(f"surface update found {st[_S_ERR]} inconsistencies")
        n_shaded = self.shader.refresh(grid, self.vmap, self.nrm, self.col, removed, touched)
        return {"vertices_added": st[_S_V_ADD], "vertices_removed": st[_S_V_DEL],
                "triangles_added": st[_S_T_ADD], "triangles_removed": st[_S_T_DEL],
                "vertices_reshaded": n_shaded, "cells_visited": st[_S_CELLS]}

    def _grow_scratch(self, vol, nrows):
        """Scratch of the window path for windows of ``vol`` voxels, ``nrows`` rows."""
        cur = getattr(self, "_sf32", None)
        if cur is None or cur.shape[0] < vol:
            v = vol if cur is None else max(vol, 2 * cur.shape[0])
            self._sf32 = np.zeros(v, dtype=np.float32)
            self._si32 = np.zeros(3 * v, dtype=np.int32)
            self._su8 = np.zeros(2 * v, dtype=np.uint8)
        cur = getattr(self, "_su64", None)
        if cur is None or cur.shape[0] < _N_ROWSETS * nrows:
            n = nrows if cur is None else max(nrows, 2 * cur.shape[0] // _N_ROWSETS)
            self._su64 = np.zeros(_N_ROWSETS * n, dtype=np.uint64)

    def _record_views(self):
        """Public views of the packed vertex / triangle records."""
        self.vhead = self._vrec[:, _VR_HEAD]
        self._ohead = self._vrec[:, _VR_OHEAD]
        self.tri = self._trec[:, 0:3]
        self.tri_key = self._trec[:, _TR_KEY]
        self.tnext = self._trec[:, _TR_NEXT:_TR_NEXT + 3]
        self._onext = self._trec[:, _TR_ONEXT]

    def _grow(self, need_v, need_t):
        if need_v > 0:
            cap = max(2 * self.pos.shape[0], self.pos.shape[0] + need_v)
            self.pos = _grown(self.pos, cap, 0)
            self.nrm = _grown(self.nrm, cap, 0)
            self.col = _grown(self.col, cap, 0)
            self.ijk = _grown(self.ijk, cap, 0)
            self.alive = _grown(self.alive, cap, 0)
            self._vrec = _grown(self._vrec, cap, -1)
            self._vfree = _grown(self._vfree, cap, 0)
        if need_t > 0:
            cap = max(2 * self.tri.shape[0], self.tri.shape[0] + need_t)
            old = self._trec
            self._trec = np.empty((cap, _TR_WIDTH), dtype=np.int32)
            self._trec[:old.shape[0]] = old
            self._trec[old.shape[0]:] = _TR_FILL
            self._tfree = _grown(self._tfree, cap, 0)
        self._record_views()

    # ---------------------------------------------------------------- queries
    @property
    def n_vertices(self) -> int:
        """Number of live vertices (= surface voxels)."""
        return int(self._cnt[_V_ALIVE])

    @property
    def n_triangles(self) -> int:
        """Number of live triangles."""
        return int(self._cnt[_T_ALIVE])

    @property
    def vertex_slots(self) -> np.ndarray:
        """Indices of the live vertex slots, ascending."""
        return np.flatnonzero(self.alive[:self._cnt[_V_HW]])

    @property
    def triangle_slots(self) -> np.ndarray:
        """Indices of the live triangle slots, ascending."""
        return np.flatnonzero(self.tri_key[:self._cnt[_T_HW]] >= 0)

    def vertex_at(self, i: int, j: int, k: int) -> int:
        """Vertex slot of voxel ``(i, j, k)``, or -1 if it is not a surface voxel."""
        b = int(find_brick(self._keys, self._vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                           k >> BRICK_SHIFT))
        return -1 if b < 0 else int(self.vmap[b, voxel_offset(i, j, k)])

    def triangles_of(self, v: int) -> np.ndarray:
        """Triangle slots containing vertex slot ``v`` (int32 array)."""
        if not (0 <= v < self.alive.shape[0]) or not self.alive[v]:
            raise IndexError(f"no live vertex in slot {v}")
        out = np.empty(4 * MAX_PER_CELL * 2, dtype=np.int32)
        n = _triangles_of_vertex(self.vhead, self.tri, self.tnext, v, out)
        if n > out.shape[0]:
            out = np.empty(n, dtype=np.int32)
            _triangles_of_vertex(self.vhead, self.tri, self.tnext, v, out)
        return out[:n].copy()

    def triangle_owner(self, t: int):
        """Identity ``((i, j, k) of the owner cell, triple id, flip)`` of live triangle ``t``."""
        key = int(self.tri_key[t])
        if key < 0:
            raise IndexError(f"no live triangle in slot {t}")
        c0 = TRIPLE_CORNERS[key >> 1, 0]
        cell = self.ijk[self.tri[t, 0]] - CORNER_OFFSETS[c0]
        return tuple(int(x) for x in cell), key >> 1, key & 1

    # ----------------------------------------------------------------- export
    def arrays(self):
        """Compact copies of the mesh.

        Returns
        -------
        pos : (n, 3) float32
            Vertex positions [mm].
        nrm : (n, 3) float32
            Unit vertex normals.
        col : (n, 4) uint8
            RGBA vertex colours.
        tris : (m, 3) int32
            Vertex indices (into the arrays above) of each triangle,
            counter-clockwise seen from outside the bone.
        """
        vs = self.vertex_slots
        remap = np.full(self.alive.shape[0], -1, dtype=np.int32)
        remap[vs] = np.arange(vs.size, dtype=np.int32)
        tris = remap[self.tri[self.triangle_slots]]
        return self.pos[vs].copy(), self.nrm[vs].copy(), self.col[vs].copy(), tris

    def canonical(self) -> CanonicalSurface:
        """Order-independent form (see :class:`CanonicalSurface`); two surfaces
        are the same mesh iff their canonical forms compare equal."""
        vs = self.vertex_slots
        ijk = self.ijk[vs]
        order = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
        rank = np.full(self.alive.shape[0], -1, dtype=np.int64)
        rank[vs[order]] = np.arange(vs.size)
        tr = rank[self.tri[self.triangle_slots]]
        if tr.size:
            first = np.argmin(tr, axis=1)
            rows = np.arange(tr.shape[0])[:, None]
            tr = tr[rows, (first[:, None] + np.arange(3)[None, :]) % 3]
            tr = tr[np.lexsort((tr[:, 2], tr[:, 1], tr[:, 0]))]
        ijk_s = ijk[order]
        tris = ijk_s[tr].reshape(-1, 9).astype(np.int32)
        return CanonicalSurface(ijk_s.copy(), self.pos[vs][order], self.nrm[vs][order],
                                self.col[vs][order], tris)


def warmup() -> None:
    """Compile (or load from the cache) every kernel of this module and of
    :mod:`bonesim.shading` on a tiny grid (bone over another structure)."""
    lab = np.zeros((6, 6, 6), dtype=np.uint8)
    lab[1:5, 1:5, 1:5] = 1
    lab[1:5, 1:5, 1] = 2
    grid = Grid.from_dense(lab)
    surf = Surface.build(grid, np.array([[0, 0, 0], [200, 200, 180], [60, 80, 220]],
                                        dtype=np.uint8), bone=[0, 1, 0])
    b = grid.brick_index(2, 2, 1)
    grid.density[b, voxel_offset(2, 2, 1)] = 0.0
    b = grid.brick_index(2, 2, 2)
    grid.density[b, voxel_offset(2, 2, 2)] = 0.5
    surf.update(grid, np.array([[2, 2, 1]], dtype=np.int32), np.array([[2, 2, 2]]))
    surf._win_per_input = 0                 # the kernel for spread-out inputs
    b = grid.brick_index(3, 2, 1)
    grid.density[b, voxel_offset(3, 2, 1)] = 0.0
    surf.update(grid, np.array([[3, 2, 1]], dtype=np.int32))
    surf.triangles_of(int(surf.vertex_slots[0]))
