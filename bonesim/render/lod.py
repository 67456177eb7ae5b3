"""Level of detail of the bone surface away from the burr and from drilled
bone: vertex clustering (no VTK here; :mod:`bonesim.render.meshbuf` draws
with it, :mod:`bonesim.render.scene` decides when).

Why
---
At the native 0.19 mm voxel a voxel covers about two pixels of the 1024 x
768 window: the phantom's bone surface has some 580,000 triangles, 250,000
facing the camera, most of them about a pixel in size. Software OpenGL
(llvmpipe) pays per triangle (set-up, and a 4x4-pixel block of fragment
shading for each one however small), so most of the frame goes into
detail finer than the screen shows. Away from the burr, where the bone
is as it was, the surface is drawn with one vertex per 2x2x2 block of
voxels instead; drilled surfaces keep their full detail.

Definitions
-----------
*Cluster* of voxel ``(i, j, k)``: the block ``(i, j, k) >> CLUSTER_SHIFT``
(2x2x2 voxels; a cluster never straddles a brick). *Block*: ``(i, j, k) >>
BLOCK_SHIFT`` (8 voxels a side). A block is *drilled* when a voxel removed
or touched since the surface was built (as far as :class:`SurfaceLOD` was
told: :meth:`SurfaceLOD.sync`, :meth:`SurfaceLOD.mark_drilled`) lies within
``NORMAL_RADIUS + 1`` voxels of it along each axis, i.e. the block meets
the box ``c - NORMAL_RADIUS - 1 .. c + NORMAL_RADIUS + 1`` of such a voxel
``c``: every vertex whose position or normal a removal changed (they read
the densities within ``NORMAL_RADIUS``), and every triangle that has one
as a corner (a triangle spans one voxel), lies in drilled blocks. A block
stays drilled for the rest of the run: until another surface is given
(a rebuilt surface, a case reset). A vertex (a surface voxel, see
:mod:`bonesim.engine.surface`) is *far* when its block is not drilled and
lies outside the *near box*, a range of blocks around the burr
(:class:`SurfaceLOD` keeps it; :mod:`bonesim.render.scene` makes it cover
every voxel within ``near_mm`` of the burr's centre along each axis, plus a
block of slack each way, and moves it only when the burr leaves it); every
vertex of an undrilled block is far when there is no burr. The
*representative* ``rep[v]`` of a vertex is the vertex of its cluster at the
smallest voxel in ``(i, j, k)`` order.

Why drilled blocks: a surgeon looks at the cavity's rims. Clustering a
thin drilled rim (where the cavity meets a tube or a plate of bone) after
the burr moved on drew it notched and jagged; only the untouched original
surface away from the burr, smooth on the scale of a cluster, is reduced.

Each live triangle with a far corner is drawn with every far corner ``v``
replaced by ``rep[v]`` (near corners stay) -- dropped when two corners
coincide (it collapsed to an edge or a point) -- and wound, like every
drawn triangle, so that its face normal agrees with the sum of its
corners' normals (:mod:`bonesim.render.meshbuf`). Triangles with only near
corners are drawn as they are. Representatives are real surface vertices,
with their own positions on the smoothed level set, normals and colours:
the coarse surface passes through points of the fine one, about a quarter
as many triangles.

No cracks: the map acts on vertices, so two triangles that shared an edge
share its image. A closed mesh stays closed: every edge of the surface is
used by an even number of triangles, a collapsed triangle uses its
remaining edge twice, so dropping it keeps every edge's count even (a test
checks it on drilled volumes, across the seam between near and far, and
around blocks drilled far from the burr). Both hold whatever set of
vertices is far, so the drilled blocks keep them.

While drilling: the near box follows the burr, and every block a removal
reaches turns drilled in the same :meth:`SurfaceLOD.sync`, so what the burr
opens is drawn at full detail in the same update, and stays so after the
burr moved on. The drilled flags are a dense uint8 array over the blocks
of the grid's bricks (:attr:`SurfaceLOD.drilled`, some 35^3 bytes for the
phantom at 0.19 mm), marked from the removed and touched voxels (work in
the voxels given); the far flags of the vertices of the blocks that turned
drilled outside the near box are cleared in the same call. The level of
detail being off (the camera zoomed out) does not lose them:
:class:`bonesim.render.meshbuf.SurfaceBuffers` keeps marking them. Changes
not given (None) mark nothing. A removal changes which voxels have
vertices only within one voxel of the removed voxel, so
:meth:`SurfaceLOD.sync` recomputes the representatives of every cluster
that meets the 3x3x3 block around each removed or touched voxel (and the
far flags of the vertices there). The far triangles' drawn lists are kept
(:meth:`SurfaceLOD.far_lists`) until something can change them. A far
triangle changes only if a changed voxel lies within ``NORMAL_RADIUS`` of
one of its corners or their representatives (a vertex's position and
normal read the densities within ``NORMAL_RADIUS`` of it), so within
``NORMAL_RADIUS + 1`` voxels of a far corner (a triangle, and a cluster,
span one voxel); the blocks within that reach of a changed voxel are near or drilled after the
call, so the lists are made again only when a block turned drilled outside
the near box, when the near box moves, for another camera for the visible
subset, or for changes not given. Then one pass over the triangle slots
lists them again (~10 ms for the phantom at 0.19 mm).

Second level
------------
Farther still the surface is drawn coarser (render.toml ``[lod]``
``coarse_*``; :mod:`bonesim.render.scene` turns it on while the burr is
shown): a far vertex whose block also lies outside the *mid box* (blocks
within ``coarse_mm`` of the burr, kept like the near box with some slack)
is at *level 2* and is replaced by ``rep2[v]``, the *coarse representative*
of its *coarse cluster* ``(i, j, k) >> COARSE_SHIFT`` (4x4x4 voxels, inside
one block): the vertex of the cluster whose normal is nearest the cluster's
mean normal (the largest dot product with the sum of the cluster's
normals). Only *smooth* clusters get one, those whose every vertex normal
lies within ``acos(coarse_min_cos)`` of the mean normal; the others (thin
plates, crests, corners) keep ``rep2[v] = rep[v]``, the first level. Far
vertices inside the mid box are at *level 1*, drawn with ``rep`` as above;
:attr:`SurfaceLOD.far` holds the level (0 for full detail).

Why the mean normal: the untouched surface of a native-resolution volume
carries the voxel grid's terraces, faint rings a few voxels apart on gently
curved bone. A representative picked by position samples them every four
voxels and draws a cross-hatched moire over a smooth dome; the vertex with
the mean normal shades the cluster as its average, so the distant surface
reads smooth (the rings fade) instead of hatched. Positions are still real
vertices on the level set, so outlines move by at most a coarse cluster.

The level-2 map is a vertex map like the first, so there are no cracks and a
closed mesh stays closed (whatever cracks the full-detail surface itself
has are only mapped, never added; a test checks it). A coarse cluster lies
in one block, and a removal changes vertices and normals only in blocks
it turns drilled, so ``rep2`` is computed once per :meth:`SurfaceLOD.rebuild`
and stays right for every block still drawn at level 2. Moving the mid box
lists the far triangles again, as moving the near box does.

Visible subset: a far triangle as drawn is not a triangle the visible
subset judged, so it is tested itself (a corner's normal or its face toward
the eye, the rule of :mod:`bonesim.render.meshbuf`) against the camera of
the installed subset.

Structures and dust are not touched here: :meth:`bonesim.render.scene.Scene.add_structures`
meshes the structures of a scene with the level of detail on a grid twice
as coarse.
"""
from __future__ import annotations

import weakref

import numpy as np
from numba import njit

from bonesim.engine.brick_hash import unpack_brick_keys
from bonesim.engine.grid import BRICK_MASK, BRICK_SHIFT, EMPTY_KEY, find_brick
from bonesim.engine.normals import NORMAL_RADIUS

__all__ = ["CLUSTER_SHIFT", "COARSE_SHIFT", "BLOCK_SHIFT", "SurfaceLOD", "voxel_px"]

#: A cluster is ``2 ** CLUSTER_SHIFT`` voxels a side.
CLUSTER_SHIFT = 1
#: A coarse cluster (the second level) is ``2 ** COARSE_SHIFT`` voxels a side.
COARSE_SHIFT = 2
#: Near or far is decided per block of ``2 ** BLOCK_SHIFT`` voxels a side.
BLOCK_SHIFT = 3


@njit(cache=True, nogil=True, inline="always")
def _slot_at(keys, vals, vmap, i, j, k):
    """The vertex slot at voxel ``(i, j, k)`` (``vmap``'s entry; -1 where its
    brick is not in the grid)."""
    b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
    if b < 0:
        return -1
    return vmap[b, ((i & BRICK_MASK) << 6) | ((j & BRICK_MASK) << 3) | (k & BRICK_MASK)]


@njit(cache=True, nogil=True, inline="always")
def _cluster_rep(vmap, b, i, j, k):
    """Vertex of the cluster of voxel ``(i, j, k)`` (in brick ``b``: a
    cluster never straddles bricks) at its smallest voxel, -1 if none."""
    ci = (i >> CLUSTER_SHIFT) << CLUSTER_SHIFT
    cj = (j >> CLUSTER_SHIFT) << CLUSTER_SHIFT
    ck = (k >> CLUSTER_SHIFT) << CLUSTER_SHIFT
    n = 1 << CLUSTER_SHIFT
    for a in range(n):
        for e in range(n):
            for c in range(n):
                u = vmap[b, (((ci + a) & BRICK_MASK) << 6) | (((cj + e) & BRICK_MASK) << 3)
                         | ((ck + c) & BRICK_MASK)]
                if u >= 0:
                    return u
    return -1


@njit(cache=True, nogil=True, inline="always")
def _coarse_rep(vmap, nrm, b, i, j, k, min_cos):
    """Coarse representative of the coarse cluster of voxel ``(i, j, k)``
    (in brick ``b``): its vertex whose normal is nearest the cluster's mean
    normal (the largest dot product with the sum of its vertices' normals,
    summed in float64 in ``(i, j, k)`` order; the first in that order among
    equals), or -1 if the cluster has no vertex or is not smooth (a vertex
    whose normal makes a cosine under ``min_cos`` with the mean normal)."""
    n = 1 << COARSE_SHIFT
    ci = (i >> COARSE_SHIFT) << COARSE_SHIFT
    cj = (j >> COARSE_SHIFT) << COARSE_SHIFT
    ck = (k >> COARSE_SHIFT) << COARSE_SHIFT
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for a in range(n):
        for e in range(n):
            for c in range(n):
                u = vmap[b, (((ci + a) & BRICK_MASK) << 6) | (((cj + e) & BRICK_MASK) << 3)
                         | ((ck + c) & BRICK_MASK)]
                if u >= 0:
                    sx += nrm[u, 0]
                    sy += nrm[u, 1]
                    sz += nrm[u, 2]
    norm = np.sqrt(sx * sx + sy * sy + sz * sz)
    if not norm > 0.0:
        return -1
    best = -1
    best_d = -np.inf
    for a in range(n):
        for e in range(n):
            for c in range(n):
                u = vmap[b, (((ci + a) & BRICK_MASK) << 6) | (((cj + e) & BRICK_MASK) << 3)
                         | ((ck + c) & BRICK_MASK)]
                if u >= 0:
                    d = nrm[u, 0] * sx + nrm[u, 1] * sy + nrm[u, 2] * sz
                    if d < min_cos * norm:
                        return -1
                    if d > best_d:
                        best = u
                        best_d = d
    return best


@njit(cache=True, nogil=True)
def _reps_all(keys, vals, vmap, nrm, ijk, alive, min_cos, rep, rep2):
    """Representative of every live vertex slot (dead ones: themselves),
    and coarse representative (``rep`` where its coarse cluster is not
    smooth, and everywhere for ``min_cos`` > 1: no second level)."""
    for v in range(alive.shape[0]):
        rep[v] = v
        rep2[v] = v
        if alive[v]:
            i, j, k = ijk[v, 0], ijk[v, 1], ijk[v, 2]
            b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
            if b >= 0:
                u = _cluster_rep(vmap, b, i, j, k)
                if u >= 0:
                    rep[v] = u
                u2 = _coarse_rep(vmap, nrm, b, i, j, k, min_cos) if min_cos <= 1.0 else -1
                rep2[v] = u2 if u2 >= 0 else rep[v]


@njit(cache=True, nogil=True)
def _reps_near(keys, vals, vmap, changed, rep):
    """Recompute the representatives of every cluster meeting the 3x3x3
    block around each voxel of ``changed``."""
    n = 1 << CLUSTER_SHIFT
    for q in range(changed.shape[0]):
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    i = changed[q, 0] + di
                    j = changed[q, 1] + dj
                    k = changed[q, 2] + dk
                    b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                                   k >> BRICK_SHIFT)
                    if b < 0:
                        continue
                    u0 = _cluster_rep(vmap, b, i, j, k)
                    ci = (i >> CLUSTER_SHIFT) << CLUSTER_SHIFT
                    cj = (j >> CLUSTER_SHIFT) << CLUSTER_SHIFT
                    ck = (k >> CLUSTER_SHIFT) << CLUSTER_SHIFT
                    for a in range(n):
                        for e in range(n):
                            for c in range(n):
                                u = vmap[b, (((ci + a) & BRICK_MASK) << 6)
                                         | (((cj + e) & BRICK_MASK) << 3)
                                         | ((ck + c) & BRICK_MASK)]
                                if 0 <= u < rep.shape[0]:
                                    rep[u] = u0


@njit(cache=True, nogil=True, inline="always")
def _level(bi, bj, bk, box, drilled, dlo):
    """Level of block ``(bi, bj, bk)``: 0 (full detail) inside the near
    box ``box[0]..box[1]`` or drilled (``drilled`` covers the blocks from
    ``dlo``), else 1 inside the mid box ``box[2]..box[3]``, else 2."""
    if (box[0, 0] <= bi <= box[1, 0] and box[0, 1] <= bj <= box[1, 1]
            and box[0, 2] <= bk <= box[1, 2]):
        return 0
    x, y, z = bi - dlo[0], bj - dlo[1], bk - dlo[2]
    if (0 <= x < drilled.shape[0] and 0 <= y < drilled.shape[1]
            and 0 <= z < drilled.shape[2]) and drilled[x, y, z] != 0:
        return 0
    if (box[2, 0] <= bi <= box[3, 0] and box[2, 1] <= bj <= box[3, 1]
            and box[2, 2] <= bk <= box[3, 2]):
        return 1
    return 2


@njit(cache=True, nogil=True)
def _far_flags(ijk, alive, box, drilled, dlo, far):
    """``far[v]``: the level (:func:`_level`) of live vertex ``v``'s block."""
    for v in range(alive.shape[0]):
        if not alive[v]:
            far[v] = 0
            continue
        far[v] = _level(ijk[v, 0] >> BLOCK_SHIFT, ijk[v, 1] >> BLOCK_SHIFT,
                        ijk[v, 2] >> BLOCK_SHIFT, box, drilled, dlo)


@njit(cache=True, nogil=True)
def _flags_near(keys, vals, vmap, ijk, alive, changed, box, drilled, dlo, far):
    """Far flags of the vertices in the 3x3x3 block around each voxel of
    ``changed`` (the only place a removal creates vertices)."""
    for q in range(changed.shape[0]):
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    i = changed[q, 0] + di
                    j = changed[q, 1] + dj
                    k = changed[q, 2] + dk
                    u = _slot_at(keys, vals, vmap, i, j, k)
                    if 0 <= u < far.shape[0]:
                        lev = _level(i >> BLOCK_SHIFT, j >> BLOCK_SHIFT, k >> BLOCK_SHIFT,
                                     box, drilled, dlo)
                        far[u] = lev if alive[u] else 0


@njit(cache=True, nogil=True)
def _mark_drilled(changed, reach, drilled, dlo, new):
    """Mark drilled every block (of those ``drilled`` covers, from ``dlo``)
    that meets the box of ``reach`` voxels around a voxel of ``changed``;
    the blocks marked now (not before) go to ``new`` (block coordinates);
    returns how many."""
    n = 0
    for q in range(changed.shape[0]):
        lo0 = ((changed[q, 0] - reach) >> BLOCK_SHIFT) - dlo[0]
        lo1 = ((changed[q, 1] - reach) >> BLOCK_SHIFT) - dlo[1]
        lo2 = ((changed[q, 2] - reach) >> BLOCK_SHIFT) - dlo[2]
        hi0 = ((changed[q, 0] + reach) >> BLOCK_SHIFT) - dlo[0]
        hi1 = ((changed[q, 1] + reach) >> BLOCK_SHIFT) - dlo[1]
        hi2 = ((changed[q, 2] + reach) >> BLOCK_SHIFT) - dlo[2]
        for x in range(max(lo0, 0), min(hi0, drilled.shape[0] - 1) + 1):
            for y in range(max(lo1, 0), min(hi1, drilled.shape[1] - 1) + 1):
                for z in range(max(lo2, 0), min(hi2, drilled.shape[2] - 1) + 1):
                    if drilled[x, y, z] == 0:
                        drilled[x, y, z] = 1
                        new[n, 0] = x + dlo[0]
                        new[n, 1] = y + dlo[1]
                        new[n, 2] = z + dlo[2]
                        n += 1
    return n


@njit(cache=True, nogil=True)
def _fine_blocks(keys, vals, vmap, blocks, n, far):
    """Clear the far flags of the vertices in the first ``n`` ``blocks``
    (block coordinates)."""
    m = 1 << BLOCK_SHIFT
    for q in range(n):
        i0 = blocks[q, 0] << BLOCK_SHIFT
        j0 = blocks[q, 1] << BLOCK_SHIFT
        k0 = blocks[q, 2] << BLOCK_SHIFT
        for i in range(i0, i0 + m):
            for j in range(j0, j0 + m):
                for k in range(k0, k0 + m):
                    u = _slot_at(keys, vals, vmap, i, j, k)
                    if 0 <= u < far.shape[0]:
                        far[u] = 0


@njit(cache=True, nogil=True, inline="always")
def _faces_eye(pos, nrm, a, b, c, eye, dirn, parallel):
    """Triangle ``(a, b, c)`` (surface winding) is visible in the sense of
    :mod:`bonesim.render.meshbuf`: a corner's normal or its face toward the
    eye (perspective from ``eye``, or parallel along ``dirn``)."""
    for v in (a, b, c):
        if parallel:
            d = -(nrm[v, 0] * dirn[0] + nrm[v, 1] * dirn[1] + nrm[v, 2] * dirn[2])
        else:
            d = (nrm[v, 0] * (eye[0] - pos[v, 0]) + nrm[v, 1] * (eye[1] - pos[v, 1])
                 + nrm[v, 2] * (eye[2] - pos[v, 2]))
        if d > 0.0:
            return True
    ux, uy, uz = pos[b, 0] - pos[a, 0], pos[b, 1] - pos[a, 1], pos[b, 2] - pos[a, 2]
    wx, wy, wz = pos[c, 0] - pos[a, 0], pos[c, 1] - pos[a, 1], pos[c, 2] - pos[a, 2]
    fx, fy, fz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
    if parallel:
        d = -(fx * dirn[0] + fy * dirn[1] + fz * dirn[2])
    else:
        d = fx * (eye[0] - pos[a, 0]) + fy * (eye[1] - pos[a, 1]) + fz * (eye[2] - pos[a, 2])
    return d > 0.0


@njit(cache=True, nogil=True)
def _far_pass(tri, key, pos, nrm, rep, rep2, far, with_vis, eye, dirn, parallel, full, vis):
    """The live triangles with a far corner, as their representatives'
    (``rep`` for a corner at level 1, ``rep2`` at level 2; dropped when two
    coincide), wound by their normals, into ``full`` (flat), and those
    facing the eye into ``vis``; returns both counts."""
    nf = 0
    nv = 0
    for t in range(key.shape[0]):
        if key[t] < 0:
            continue
        a = tri[t, 0]
        b = tri[t, 1]
        c = tri[t, 2]
        if far[a] == 0 and far[b] == 0 and far[c] == 0:
            continue
        a = rep[a] if far[a] == 1 else (rep2[a] if far[a] == 2 else a)
        b = rep[b] if far[b] == 1 else (rep2[b] if far[b] == 2 else b)
        c = rep[c] if far[c] == 1 else (rep2[c] if far[c] == 2 else c)
        if a == b or b == c or a == c:
            continue
        keep = with_vis and _faces_eye(pos, nrm, a, b, c, eye, dirn, parallel)
        ux, uy, uz = pos[b, 0] - pos[a, 0], pos[b, 1] - pos[a, 1], pos[b, 2] - pos[a, 2]
        wx, wy, wz = pos[c, 0] - pos[a, 0], pos[c, 1] - pos[a, 1], pos[c, 2] - pos[a, 2]
        fx, fy, fz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
        sx = nrm[a, 0] + nrm[b, 0] + nrm[c, 0]
        sy = nrm[a, 1] + nrm[b, 1] + nrm[c, 1]
        sz = nrm[a, 2] + nrm[b, 2] + nrm[c, 2]
        if fx * sx + fy * sy + fz * sz < 0.0:
            b, c = c, b
        full[3 * nf] = a
        full[3 * nf + 1] = b
        full[3 * nf + 2] = c
        nf += 1
        if keep:
            vis[3 * nv] = a
            vis[3 * nv + 1] = b
            vis[3 * nv + 2] = c
            nv += 1
    return nf, nv


def voxel_px(spacing_mm: float, distance_mm: float, view_angle_deg: float, height_px: int,
             parallel_scale_mm: float | None = None) -> float:
    """How many pixels a voxel edge covers at ``distance_mm`` from the eye.

    Parameters
    ----------
    spacing_mm : float
        Voxel edge [mm].
    distance_mm : float
        Distance along the view direction [mm] (perspective).
    view_angle_deg : float
        Vertical view angle [deg] (perspective).
    height_px : int
        Height of the 3D view [px].
    parallel_scale_mm : float, optional
        Half the view's height [mm] for a parallel projection (then the
        distance and angle are not used).
    """
    if parallel_scale_mm is not None:
        half = float(parallel_scale_mm)
    else:
        half = float(distance_mm) * np.tan(np.radians(float(view_angle_deg)) / 2.0)
    if not half > 0.0:
        return float("inf")
    return float(spacing_mm) * float(height_px) / (2.0 * half)


class SurfaceLOD:
    """Representatives and far flags of the vertices of one surface, the
    drilled blocks, and the drawn lists of its far triangles (module
    docstring).

    Attributes
    ----------
    rep : (nv,) int32
        Representative of each vertex slot's cluster (itself for dead
        ones), near or far; a triangle maps only its far corners.
    rep2 : (nv,) int32
        Coarse representative of each vertex slot (module docstring,
        "Second level"): valid for the live vertices of the blocks that
        are not drilled (the only ones drawn at level 2).
    far : (nv,) uint8
        Level of each live vertex: 0 full detail, 1 (far: ``rep``), 2 (far
        and outside the mid box: ``rep2``).
    near_box : ((3,) int64, (3,) int64) or None
        Inclusive block range of the near box, None when every vertex is far.
    mid_box : ((3,) int64, (3,) int64) or None
        Inclusive block range of the mid box; None: no level 2.
    coarse_min_cos : float or None
        Smallest cosine between the normals of a coarse cluster's vertices
        and its representative's for the cluster to be drawn at level 2;
        None: no level 2 (``rep2`` is ``rep``).

    Parameters
    ----------
    coarse_min_cos : float, optional
        :attr:`coarse_min_cos`.
    drilled : (nbi, nbj, nbk) uint8
        1 for the drilled blocks (module docstring) of the surface's grid,
        block ``(bi, bj, bk)`` at ``[bi, bj, bk] - drilled_lo``; they cover
        every block that holds a brick of the grid.
    drilled_lo : (3,) int64
        Block coordinates of ``drilled[0, 0, 0]``.
    far_full, far_vis : (3 m,) int32
        The far triangles as drawn (flat), all of them and those facing
        the eye of the last :meth:`far_lists` call with one; valid while
        :attr:`far_valid`.
    """

    def __init__(self, coarse_min_cos=None):
        self.rep = np.zeros(0, dtype=np.int32)
        self.rep2 = np.zeros(0, dtype=np.int32)
        self.far = np.zeros(0, dtype=np.uint8)
        self.near_box = None
        self.mid_box = None
        self.coarse_min_cos = None if coarse_min_cos is None else float(coarse_min_cos)
        self._surface = None
        self.drilled = np.zeros((0, 0, 0), dtype=np.uint8)
        self.drilled_lo = np.zeros(3, dtype=np.int64)
        self._drilled_of = lambda: None  # weakref to the surface the drilled blocks refer to
        self._new_blocks = np.zeros((0, 3), dtype=np.int64)
        self.far_full = np.zeros(0, dtype=np.int32)
        self.far_vis = np.zeros(0, dtype=np.int32)
        self.n_far_full = 0
        self.n_far_vis = 0
        self.far_valid = False
        self._far_tag = None
        self.stats = {"far_passes": 0, "drilled_blocks": 0}

    @staticmethod
    def near_blocks(centre_mm, near_mm, origin_mm, spacing_mm):
        """Block range ``(lo, hi)`` (inclusive, (3,) int64 each) of the near
        box around ``centre_mm`` [mm], or None for no centre."""
        if centre_mm is None:
            return None
        c = (np.asarray(centre_mm, dtype=np.float64) - np.asarray(origin_mm, dtype=np.float64)
             ) / float(spacing_mm)
        r = float(near_mm) / float(spacing_mm)
        lo = np.floor(c - r).astype(np.int64) >> BLOCK_SHIFT
        hi = np.floor(c + r).astype(np.int64) >> BLOCK_SHIFT
        return lo, hi

    def _box(self):
        """(4, 3) int64: the near box's and the mid box's inclusive block
        ranges (:func:`_level`)."""
        box = np.empty((4, 3), np.int64)
        if self.near_box is None:       # an empty box: every vertex is far
            box[0], box[1] = 1, 0
        else:
            box[0], box[1] = self.near_box
        if self.mid_box is None or self.coarse_min_cos is None:    # no level 2
            box[2], box[3] = np.iinfo(np.int64).min, np.iinfo(np.int64).max
        else:
            box[2], box[3] = self.mid_box
        return box

    def _reset_drilled(self, surface) -> None:
        """No block drilled yet; the flag array spans the blocks of every
        brick of ``surface``'s grid (from its brick hash table)."""
        bijk = unpack_brick_keys(surface._keys[surface._keys != EMPTY_KEY])
        if len(bijk):
            lo = (bijk.min(axis=0) << BRICK_SHIFT) >> BLOCK_SHIFT
            hi = (((bijk.max(axis=0) + 1) << BRICK_SHIFT) - 1) >> BLOCK_SHIFT
        else:
            lo, hi = np.zeros(3, np.int64), np.full(3, -1, np.int64)
        self.drilled_lo = lo.astype(np.int64)
        self.drilled = np.zeros(tuple(int(x) for x in hi - lo + 1), dtype=np.uint8)
        self._new_blocks = np.zeros((self.drilled.size, 3), dtype=np.int64)
        self._drilled_of = weakref.ref(surface)
        self.stats["drilled_blocks"] = 0

    def mark_drilled(self, surface, changed) -> np.ndarray:
        """Note removed or touched voxels of ``surface``: every block within
        ``NORMAL_RADIUS + 1`` voxels of one (along each axis) is drilled
        from now on, until another surface is given. Cheap (work in the
        voxels given); call it for every change, with the level of detail
        on or off. Far flags are not touched here (:meth:`sync` does).

        Parameters
        ----------
        surface : Surface
            The surface the voxels were removed from (another one than
            the last: the drilled blocks start again from none).
        changed : (n, 3) int array_like
            Voxels ``(i, j, k)``.

        Returns
        -------
        (m, 3) int64
            The blocks drilled by this call that were not before.
        """
        if surface is not self._drilled_of():
            self._reset_drilled(surface)
        ch = np.ascontiguousarray(changed, dtype=np.int64).reshape(-1, 3)
        if not len(ch) or not self.drilled.size:
            return self._new_blocks[:0]
        n = _mark_drilled(ch, np.int64(NORMAL_RADIUS + 1), self.drilled, self.drilled_lo,
                          self._new_blocks)
        self.stats["drilled_blocks"] += int(n)
        return self._new_blocks[:n]

    def release(self) -> None:
        """Drop everything but the drilled blocks (the level of detail is
        off; :meth:`rebuild` makes the rest again): no reference to the
        surface is kept."""
        self.rep = np.zeros(0, dtype=np.int32)
        self.rep2 = np.zeros(0, dtype=np.int32)
        self.far = np.zeros(0, dtype=np.uint8)
        self._surface = None
        self.far_full = np.zeros(0, dtype=np.int32)
        self.far_vis = np.zeros(0, dtype=np.int32)
        self.n_far_full = self.n_far_vis = 0
        self.far_valid = False
        self._far_tag = None

    def drilled_blocks(self) -> np.ndarray:
        """Block coordinates (m, 3) int64 of the drilled blocks."""
        return np.argwhere(self.drilled) + self.drilled_lo

    def rebuild(self, surface, near_box, mid_box=None) -> None:
        """Recompute everything for ``surface``, ``near_box`` and
        ``mid_box`` (see :meth:`near_blocks`); the drilled blocks are kept
        for the same surface and start again from none for another one."""
        if surface is not self._drilled_of():
            self._reset_drilled(surface)
        self._surface = surface
        nv = surface.pos.shape[0]
        if self.rep.shape[0] != nv:
            self.rep = np.zeros(nv, dtype=np.int32)
            self.rep2 = np.zeros(nv, dtype=np.int32)
            self.far = np.zeros(nv, dtype=np.uint8)
        # no level 2: a cosine no normal pair reaches (rep2 falls back to rep)
        min_cos = 2.0 if self.coarse_min_cos is None else self.coarse_min_cos
        _reps_all(surface._keys, surface._vals, surface.vmap, surface.nrm, surface.ijk,
                  surface.alive, float(min_cos), self.rep, self.rep2)
        self.set_box(near_box, mid_box)

    def set_box(self, near_box, mid_box=None) -> None:
        """Move the near box and the mid box (block ranges, or None)."""
        self.near_box, self.mid_box = (None if b is None else (
            np.asarray(b[0], dtype=np.int64), np.asarray(b[1], dtype=np.int64))
            for b in (near_box, mid_box))
        _far_flags(self._surface.ijk, self._surface.alive, self._box(), self.drilled,
                   self.drilled_lo, self.far)
        self.far_valid = False

    def sync(self, surface, changed) -> None:
        """Follow ``Surface.update``: ``changed`` (n, 3) int are the removed
        and touched voxels given to it since the last call (they are also
        marked drilled, :meth:`mark_drilled`); None when unknown
        (everything is recomputed, and no block is marked drilled)."""
        nv = surface.pos.shape[0]
        if changed is not None:
            ch = np.ascontiguousarray(changed, dtype=np.int32).reshape(-1, 3)
            new = self.mark_drilled(surface, ch)
        if surface is not self._surface or changed is None or self.rep.shape[0] != nv:
            self.rebuild(surface, self.near_box, self.mid_box)
            return
        if not len(ch):
            return
        # rep2 needs no follow-up: a coarse cluster lies in one block, and
        # every cluster whose vertices or normals a change reaches lies in a
        # block now drilled
        _reps_near(surface._keys, surface._vals, surface.vmap, ch, self.rep)
        box = self._box()
        lo, hi = box[0], box[1]
        _flags_near(surface._keys, surface._vals, surface.vmap, surface.ijk, surface.alive,
                    ch, box, self.drilled, self.drilled_lo, self.far)
        # every block within NORMAL_RADIUS + 1 voxels of a changed voxel is
        # now drilled or near, so no far vertex is within reach of the
        # changes: the far triangles change only where blocks turned fine
        # (outside the near box)
        out = np.any((new < lo) | (new > hi), axis=1)
        if np.any(out):
            _fine_blocks(surface._keys, surface._vals, surface.vmap, new[out], int(out.sum()),
                         self.far)
            self.far_valid = False

    def far_lists(self, surface, job_tag, eye, dirn, parallel):
        """The far triangles as drawn, all and (with ``job_tag`` not None)
        those facing a camera at ``eye`` looking along ``dirn``; recomputed
        only when something changed. Returns ``(far_full, n, far_vis, m)``."""
        if not self.far_valid or job_tag is not self._far_tag:
            nt = surface.tri_key.shape[0]
            if self.far_full.shape[0] < 3 * nt:
                self.far_full = np.zeros(3 * nt, dtype=np.int32)
                self.far_vis = np.zeros(3 * nt, dtype=np.int32)
            nf, nv = _far_pass(surface.tri, surface.tri_key, surface.pos, surface.nrm, self.rep,
                               self.rep2, self.far, job_tag is not None,
                               np.asarray(eye, np.float64), np.asarray(dirn, np.float64),
                               bool(parallel), self.far_full, self.far_vis)
            self.n_far_full, self.n_far_vis = int(nf), int(nv)
            self.far_valid = True
            self._far_tag = job_tag
            self.stats["far_passes"] += 1
        return self.far_full, self.n_far_full, self.far_vis, self.n_far_vis
