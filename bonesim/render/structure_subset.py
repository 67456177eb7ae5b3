"""The drawn subset of a structure mesh: its triangles sealed inside tissue
are left out (no VTK here; :mod:`bonesim.render.scene` draws the subset).

The non-bone structures (sinus, dura, nerves...) are static meshes of the
initial tissue (:meth:`bonesim.render.scene.Scene.add_structures`). Most of
their area lies against bone, inside the solid whose boundary the hybrid
bone surface draws (every occupied voxel, whatever its label, is inside
that closed surface), so most of their triangles can never be seen until
the drill opens the tissue around them. At the native 0.19 mm voxel the
phantom's structures have some 620,000 triangles, more than the bone
surface's visible subset; about half are sealed.

Definition
----------
A triangle's *voxel* is the voxel nearest its centroid. The triangle is
*sealed* when

* in the initial tissue, every voxel within Chebyshev distance
  :data:`SEAL_RADIUS` of its voxel is occupied, and
* the current bone surface has no vertex (surface voxel) within
  Chebyshev distance ``SEAL_RADIUS + 1`` of it, and no voxel within
  :data:`UNSEAL_RADIUS` of it was removed since the surface was given.

Why a sealed triangle is hidden: its corners lie within about a voxel of
its centroid (flying edges makes triangles inside one voxel cell; the
smoothing moves them by a fraction of a voxel), so within about 2 voxels of
its voxel's centre; every surface voxel of
the solid is at least ``SEAL_RADIUS + 2 = 4`` voxels from its voxel (a voxel
whose 26 neighbours are all occupied is not a surface voxel), and a bone
surface vertex lies at most ``max_in_voxels`` (0.4, ``shading.toml``)
inside its voxel's centre: the triangle is inside the closed bone surface,
with more than a voxel to spare. Removing voxels only opens tissue, so a
triangle that stops being sealed never becomes sealed again while the same
surface is updated: :meth:`SealedTriangles.unseal_near` turns triangles
near removed voxels back on (``UNSEAL_RADIUS``: a removed voxel makes its
neighbours surface voxels, 1 + ``SEAL_RADIUS + 1`` from the triangle). The
subset is conservative: it may draw a hidden triangle, never drops one
that could show.

The meshes are closed and drawn with back-face culling, so the triangles
turned away from the camera never show either: :meth:`SealedTriangles.face`
leaves out those clearly turned away (by more than :data:`FACING_MARGIN`)
whenever the camera moves; OpenGL culls the others as before.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from bonesim.engine.grid import BRICK_MASK, BRICK_SHIFT, find_brick

__all__ = ["SEAL_RADIUS", "UNSEAL_RADIUS", "FACING_MARGIN", "SealedTriangles",
           "removed_boxes"]

#: Chebyshev radius [voxels] of the block of the initial tissue that must be
#: all occupied around a sealed triangle's voxel.
SEAL_RADIUS = 2
#: Chebyshev radius [voxels] around a removed voxel within which triangles
#: are no longer sealed.
UNSEAL_RADIUS = SEAL_RADIUS + 2
#: A triangle is left out as turned away when the cosine between its face
#: normal and the direction to the eye is below minus this (OpenGL's culling
#: decides the ones closer to edge-on, as it would without the subset).
FACING_MARGIN = 1e-3


@njit(cache=True, nogil=True, inline="always")
def _occupied(keys, vals, density, i, j, k):
    b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
    if b < 0:
        return False
    return density[b, ((i & BRICK_MASK) << 6) | ((j & BRICK_MASK) << 3) | (k & BRICK_MASK)] > 0


@njit(cache=True, nogil=True, parallel=True)
def _seal(keys, vals, density, vkeys, vvals, vmap, cv, r, sealed):
    """``sealed[t]``: the block of radius ``r`` around ``cv[t]`` all occupied
    and no vertex of ``vmap`` within ``r + 1``."""
    for t in prange(cv.shape[0]):
        ci, cj, ck = cv[t, 0], cv[t, 1], cv[t, 2]
        ok = True
        for i in range(ci - r, ci + r + 1):
            for j in range(cj - r, cj + r + 1):
                for k in range(ck - r, ck + r + 1):
                    if not _occupied(keys, vals, density, i, j, k):
                        ok = False
                        break
                if not ok:
                    break
            if not ok:
                break
        if ok:
            q = r + 1
            for i in range(ci - q, ci + q + 1):
                for j in range(cj - q, cj + q + 1):
                    for k in range(ck - q, ck + q + 1):
                        b = find_brick(vkeys, vvals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                                       k >> BRICK_SHIFT)
                        if b >= 0 and vmap[b, ((i & BRICK_MASK) << 6) | ((j & BRICK_MASK) << 3)
                                           | (k & BRICK_MASK)] >= 0:
                            ok = False
                            break
                    if not ok:
                        break
                if not ok:
                    break
        sealed[t] = 1 if ok else 0


@njit(cache=True, nogil=True)
def _unseal(keys, vals, cv, order, offs, lo, hi, r, sealed, tris, facing, drawn, n_drawn):
    """Clear ``sealed`` of the triangles within ``r`` (Chebyshev) of a box
    ``lo[g]..hi[g]`` (each box within one brick; triangles bucketed by
    brick: ``order[offs[b]:offs[b + 1]]``), appending those facing the
    camera to the ``n_drawn`` triangles of ``drawn``; returns the new
    number drawn."""
    for g in range(lo.shape[0]):
        bi = lo[g, 0] >> BRICK_SHIFT
        bj = lo[g, 1] >> BRICK_SHIFT
        bk = lo[g, 2] >> BRICK_SHIFT
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    b = find_brick(keys, vals, bi + di, bj + dj, bk + dk)
                    if b < 0:
                        continue
                    for s in range(offs[b], offs[b + 1]):
                        t = order[s]
                        if (sealed[t] and lo[g, 0] - r <= cv[t, 0] <= hi[g, 0] + r
                                and lo[g, 1] - r <= cv[t, 1] <= hi[g, 1] + r
                                and lo[g, 2] - r <= cv[t, 2] <= hi[g, 2] + r):
                            sealed[t] = 0
                            if facing[t]:
                                drawn[3 * n_drawn] = tris[t, 0]
                                drawn[3 * n_drawn + 1] = tris[t, 1]
                                drawn[3 * n_drawn + 2] = tris[t, 2]
                                n_drawn += 1
    return n_drawn


@njit(cache=True, nogil=True)
def _boxes(rem, inv, lo, hi):
    for q in range(rem.shape[0]):
        g = inv[q]
        for a in range(3):
            lo[g, a] = min(lo[g, a], rem[q, a])
            hi[g, a] = max(hi[g, a], rem[q, a])


def removed_boxes(removed):
    """The bounding box of the ``removed`` voxels ((k, 3) int) in each brick
    they fall in: ``(lo, hi)``, (g, 3) int32 each."""
    rem = np.ascontiguousarray(removed, dtype=np.int32).reshape(-1, 3)
    if not len(rem):
        return np.zeros((0, 3), np.int32), np.zeros((0, 3), np.int32)
    key = ((rem[:, 0].astype(np.int64) >> BRICK_SHIFT) * 1_000_003
           + (rem[:, 1] >> BRICK_SHIFT)) * 1_000_003 + (rem[:, 2] >> BRICK_SHIFT)
    _, inv = np.unique(key, return_inverse=True)
    n_g = int(inv.max()) + 1
    lo = np.full((n_g, 3), np.iinfo(np.int32).max, dtype=np.int32)
    hi = np.full((n_g, 3), np.iinfo(np.int32).min, dtype=np.int32)
    _boxes(rem, inv.reshape(-1).astype(np.int64), lo, hi)
    return lo, hi


@njit(cache=True, nogil=True)
def _bricks_of(keys, vals, cv, out):
    """Brick index of each voxel ``cv[t]`` (-1 where none is allocated)."""
    for t in range(cv.shape[0]):
        out[t] = find_brick(keys, vals, cv[t, 0] >> BRICK_SHIFT, cv[t, 1] >> BRICK_SHIFT,
                            cv[t, 2] >> BRICK_SHIFT)


@njit(cache=True, nogil=True, parallel=True)
def _facing(pts, tris, eye, dirn, parallel, facing):
    """``facing[t]``: 0 when triangle ``t`` is clearly turned away from the
    camera (its face normal ``(b - a) x (c - a)`` points away from the eye
    by more than a rounding margin), else 1."""
    for t in prange(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ux = np.float64(pts[b, 0]) - pts[a, 0]
        uy = np.float64(pts[b, 1]) - pts[a, 1]
        uz = np.float64(pts[b, 2]) - pts[a, 2]
        wx = np.float64(pts[c, 0]) - pts[a, 0]
        wy = np.float64(pts[c, 1]) - pts[a, 1]
        wz = np.float64(pts[c, 2]) - pts[a, 2]
        fx, fy, fz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
        if parallel:
            ex, ey, ez = -dirn[0], -dirn[1], -dirn[2]
        else:
            ex = eye[0] - pts[a, 0]
            ey = eye[1] - pts[a, 1]
            ez = eye[2] - pts[a, 2]
        d = fx * ex + fy * ey + fz * ez
        scale = np.sqrt((fx * fx + fy * fy + fz * fz) * (ex * ex + ey * ey + ez * ez))
        facing[t] = 0 if d < -FACING_MARGIN * scale else 1


@njit(cache=True, nogil=True)
def _compact(tris, sealed, facing, out):
    """The triangles neither sealed nor turned away, in order, into ``out``
    (flat); returns their number."""
    n = 0
    for t in range(tris.shape[0]):
        if not sealed[t] and facing[t]:
            out[3 * n] = tris[t, 0]
            out[3 * n + 1] = tris[t, 1]
            out[3 * n + 2] = tris[t, 2]
            n += 1
    return n


class SealedTriangles:
    """Which triangles of one structure mesh are sealed inside tissue (module
    docstring), and the index buffer of the others.

    Parameters
    ----------
    grid : bonesim.engine.grid.Grid
        The initial tissue (the one the mesh was made from).
    points : (n, 3) float array
        Mesh vertices [mm], case frame.
    tris : (m, 3) int array
        Vertex indices of the triangles.
    surface : bonesim.engine.surface.Surface
        The bone surface as it is now (its vertices are the surface voxels).
    seal_radius : int
        :data:`SEAL_RADIUS` for meshes of voxel-sized triangles; one more
        per voxel a triangle's corners may lie farther from its centroid
        (a mesh made on a grid twice as coarse: ``SEAL_RADIUS + 1``). The
        unseal radius grows with it.

    Attributes
    ----------
    tris : (m, 3) int32
        The mesh's triangles.
    sealed : (m,) uint8
        1 for sealed triangles.
    facing : (m,) uint8
        0 for triangles clearly turned away from the camera of the last
        :meth:`face` (all 1 before).
    drawn : (3 m,) int32
        Flat index buffer: the first :attr:`n_drawn` triangles are the
        ones neither sealed nor turned away, in mesh order, then those
        unsealed since in the order they were (VTK reads it in place).
    n_drawn : int
    """

    def __init__(self, grid, points, tris, surface, seal_radius: int = SEAL_RADIUS):
        self._r = int(seal_radius)
        self.tris = np.ascontiguousarray(tris, dtype=np.int32).reshape(-1, 3)
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        c = pts[self.tris].mean(axis=1) if len(self.tris) else np.zeros((0, 3))
        self._cv = np.ascontiguousarray(
            np.floor((c - grid.origin_mm) / grid.spacing_mm + 0.5), dtype=np.int32)
        self._keys, self._vals = grid.keys, grid.vals
        self._density = grid.density.copy()          # the initial tissue
        self.sealed = np.zeros(len(self.tris), dtype=np.uint8)
        self.facing = np.ones(len(self.tris), dtype=np.uint8)
        self._pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        self.drawn = np.empty(3 * len(self.tris), dtype=np.int32)
        self.n_drawn = 0
        # triangles bucketed by the brick of their voxel (-1: none allocated)
        b = np.empty(len(self.tris), dtype=np.int64)
        _bricks_of(self._keys, self._vals, self._cv, b)
        ok = b >= 0
        self._order = np.ascontiguousarray(np.flatnonzero(ok)[np.argsort(b[ok], kind="stable")],
                                           dtype=np.int64)
        self._offs = np.zeros(grid.n_bricks + 1, dtype=np.int64)
        np.cumsum(np.bincount(b[ok], minlength=grid.n_bricks), out=self._offs[1:])
        self.reseal(surface)

    def reseal(self, surface) -> int:
        """Recompute every triangle's flag against ``surface`` (a new or
        unknown state of the tissue); returns the number drawn."""
        _seal(self._keys, self._vals, self._density, surface._keys, surface._vals,
              surface.vmap, self._cv, self._r, self.sealed)
        self.n_drawn = _compact(self.tris, self.sealed, self.facing, self.drawn)
        return self.n_drawn

    def unseal_all(self) -> None:
        """Seal nothing (the tissue no longer encloses the mesh)."""
        self.sealed[:] = 0
        self.n_drawn = _compact(self.tris, self.sealed, self.facing, self.drawn)

    def unseal_near(self, removed) -> bool:
        """Unseal the triangles near ``removed`` voxels ((k, 3) int, or the
        boxes of :func:`removed_boxes`); returns whether the drawn buffer
        changed (newly unsealed triangles facing the camera are appended)."""
        lo, hi = removed if isinstance(removed, tuple) else removed_boxes(removed)
        if not len(lo) or not self.sealed.any():
            return False
        n = _unseal(self._keys, self._vals, self._cv, self._order, self._offs, lo, hi,
                    self._r + (UNSEAL_RADIUS - SEAL_RADIUS), self.sealed, self.tris,
                    self.facing, self.drawn,
                    self.n_drawn)
        if n == self.n_drawn:
            return False
        self.n_drawn = n
        return True

    def face(self, eye, direction, parallel: bool = False) -> int:
        """Leave out, besides the sealed ones, the triangles clearly turned
        away from a camera at ``eye`` [mm] looking along ``direction``
        (meshes drawn with back-face culling, closed: such a triangle is
        never seen); returns the number drawn. Call again when the camera
        moves."""
        _facing(self._pts, self.tris, np.asarray(eye, dtype=np.float64),
                np.asarray(direction, dtype=np.float64), bool(parallel), self.facing)
        self.n_drawn = _compact(self.tris, self.sealed, self.facing, self.drawn)
        return self.n_drawn
